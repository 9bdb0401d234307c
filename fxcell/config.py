"""Cell configuration: robot connection, tool, joint limits, scene, recorder, daemon.

One YAML file (``config/cell.yaml``) names the robot and refers to the limits and
scene files beside it. Every model forbids unknown keys, so a typo fails at start
with a :class:`~fxcell.errors.ConfigError` that names the bad key. Units are SI:
metres, radians, seconds.
"""

from __future__ import annotations

import copy
import functools
import math
import os
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from fxcell.errors import ConfigError
from fxcell.layout import LayoutConfig
from fxcell.protocol import URCAP_SCRIPT_PORT
from fxcell.resources import resource_dir
from fxcell.robot_specs import SPECS, UR3E_SPEC, RobotSpec, Vector3, Vector6
from fxcell.signals import parse_signal

CONFIG_DIR = resource_dir("config")

HOME_JOINTS: Vector6 = UR3E_SPEC.home
# The seed's TCP (Robotiq Hand-E fingertip centre) in the flange frame: x, y, z, rx, ry, rz.
SEED_TCP: Vector6 = UR3E_SPEC.tcp
RobotKindName = Literal["ur3e", "ned2"]
"""The robot kinds fxcell ships (:data:`fxcell.robot_specs.SPECS`, :mod:`fxcell.robots`)."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RobotConfig(_Model):
    """Which robot, and how to reach its controller."""

    kind: RobotKindName = "ur3e"
    """The robot kind (:mod:`fxcell.robots`: its link, kinematic model and simulator):
    ``ur3e`` (Universal Robots UR3e) or ``ned2`` (Niryo Ned2). The kind's published limits,
    home and gripper TCP (:mod:`fxcell.robot_specs`) are the defaults of ``limits``,
    ``home`` and ``tool``."""
    host: str | None = None
    """Controller address; ``None`` starts the kind's embedded simulator."""
    external_control: Literal["script", "urcap"] = "script"
    """``script``: ur_rtde uploads its control script; ``urcap``: play ``urcap_program``
    (UR only)."""
    urcap_program: str = "external_control.urp"
    urcap_port: int = Field(URCAP_SCRIPT_PORT, ge=1, le=65535)
    """The cell computer's port the *External Control* URCap fetches its script from (its
    installation's custom port on the pendant; the URCap's default is 50002)."""
    receiver: Literal["stream", "ur_rtde"] = "stream"
    """Source of the 500 Hz state stream: ``stream`` reads every RTDE packet with fxcell's
    reader; ``ur_rtde`` polls ``RTDEReceiveInterface``, which keeps only the newest packet
    (a late poll loses samples)."""
    frequency: float = Field(500.0, gt=0, le=500)
    command_timeout: float = Field(10.0, gt=0)
    """Seconds a general command waits for the robot to confirm its effect."""
    connect_timeout: float = Field(10.0, gt=0)
    reconnect_backoff_max: float = Field(5.0, gt=0)
    realtime_priority: int = Field(80, ge=0, le=99)
    """SCHED_FIFO priority the robot-link process asks for (where the user may: see the
    real-robot guide); 0 keeps it at normal scheduling."""
    heal_attempts: int = Field(5, ge=0, le=20)
    """Times in a row a pick, place or job step goes on by itself after the robot link
    dropped or restarted under it (the arm at rest or braked) without the arm getting any
    further, before it stops for the operator (and four times as many in all)."""
    heal_timeout: float = Field(30.0, gt=0)
    """Seconds such a recovery waits for the link, the arm at rest and external control."""
    heartbeat_timeout: float = Field(0.1, ge=0.02, le=1.0)
    """The link process brakes a running move by itself when it has heard nothing from
    the cell for this long (s): a thread of the cell process beats every 10 ms while a move
    runs and its event loop has run within the last 0.5 s (a frozen process is caught
    within this timeout, a stalled loop within 0.5 s, a late loop never; a process the
    kernel shows running but whose beat waits for the GIL gets up to 0.3 s)."""
    stall_timeout: float = Field(0.08, ge=0.01, le=0.09)
    """... and when no robot state has arrived for this long (s); below the 100 ms after
    which the cell declares the link down."""
    calibration: str | None = "controller"
    """Where the arm's factory calibration comes from: ``controller`` (the default; its
    primary interface's kinematics info, read at every connect, the embedded simulator's
    included), a ``calibration.conf`` file (UR's format), or ``nominal``: UR's published
    model, by explicit choice only (pose moves then miss by millimetres on a real arm).
    Unset (``null``) is the default, ``controller``."""
    accept_nominal_kinematics: bool = False
    """With ``calibration: controller``: when it cannot be read, plan pose moves on the nominal
    model (the TCP may be millimetres off) instead of refusing them (``UncalibratedError``,
    the default: joint moves stay allowed)."""


class ToolConfig(_Model):
    tcp: Vector6 = SEED_TCP
    """Tool centre point in the flange frame: x, y, z (m) and rotation vector (rad). In a
    :class:`CellConfig` the default is the kind's gripper's (the UR3e's Hand-E fingertips;
    the Ned2's Gripper 1, 75 mm along ``tool_link``'s x)."""
    payload: float = Field(1.0, ge=0, le=3.0)
    """Payload mass in kg (Hand-E with fingers is about 1 kg; the kind's default, at most
    its rated payload); what it holds is added."""
    payload_cog: Vector3 = (0.0, 0.0, 0.055)
    """Centre of gravity of the payload in the flange frame (m)."""


class JointLimits(_Model):
    """Per-joint limits: base, shoulder, elbow, wrist 1, wrist 2, wrist 3."""

    position_min: Vector6 = UR3E_SPEC.limits["position_min"]
    position_max: Vector6 = UR3E_SPEC.limits["position_max"]
    velocity: Vector6 = UR3E_SPEC.limits["velocity"]
    acceleration: Vector6 = UR3E_SPEC.limits["acceleration"]
    """The seed's joint_limits.yaml accelerations (rad/s²). These defaults are the UR3e's;
    in a :class:`CellConfig` those of ``robot.kind`` (:mod:`fxcell.robot_specs`)."""
    jerk: Vector6 = UR3E_SPEC.limits["jerk"]
    braking_acceleration: Vector6 = UR3E_SPEC.limits["braking_acceleration"]
    """Deceleration a stop may use (rad/s²), whatever the move's factors. Higher than the
    planning accelerations so that a stop from full speed takes about a second (a UR3e's
    category-2 stop takes a few tenths), which also keeps the daemon's 3 s shutdown."""
    braking_jerk: Vector6 = UR3E_SPEC.limits["braking_jerk"]
    min_factor: float = Field(0.01, gt=0, le=1)
    """The smallest velocity or acceleration factor a move may use: slower moves are
    refused before planning (a 1e-6 factor would plan hours of samples)."""
    max_move_duration: float = Field(120.0, gt=0, le=3600)
    """A move planned to take longer than this (s) is refused before it is sampled."""

    @field_validator("velocity", "acceleration", "jerk", "braking_acceleration", "braking_jerk")
    @classmethod
    def _positive(cls, v: Vector6) -> Vector6:
        if not all(math.isfinite(x) and x > 0 for x in v):
            raise ValueError("every limit must be a finite number > 0")
        return v


class SceneObject(_Model):
    """A box in the cell, in the robot base frame."""

    name: str
    size: Vector3
    position: Vector3
    """Centre of the box (m)."""
    rpy: Vector3 = (0.0, 0.0, 0.0)


class SceneConfig(_Model):
    objects: tuple[SceneObject, ...] = ()


class RecorderConfig(_Model):
    enabled: bool = False
    directory: Path = Path("logs")
    chunk_duration: float = Field(1.0, gt=0)
    """Seconds per MCAP chunk: bounds what a crash can lose."""
    rotate_size: int = Field(512 * 1024 * 1024, gt=0)
    rotate_duration: float = Field(3600.0, gt=0)
    max_total_size: int | None = Field(20 * 1024**3, gt=0)
    """Bytes all logs in ``directory`` may take; the oldest go first (``null``: no limit)."""
    max_age: float | None = Field(30 * 86400.0, gt=0)
    """Seconds after which a log is removed (``null``: kept for ever)."""


class SilaConfig(_Model):
    """The SiLA 2 server beside the daemon's HTTP API (``fxcell daemon --sila``; guide:
    docs/guides/sila.md)."""

    enabled: bool = False
    """Serve SiLA 2 (``--sila`` turns it on for one start)."""
    port: int = Field(50052, ge=1, le=65535)
    """gRPC port, on the daemon's address (daemon.host)."""
    server_name: str = Field("fxcell cell", min_length=1, max_length=255)
    """The SiLA Server Name schedulers show and discover the cell by (one per cell)."""
    insecure: bool = False
    """Plain (unencrypted) gRPC: development only; SiLA 2 expects TLS."""
    discovery: bool = True
    """Announce the server over zeroconf (mDNS, ``_sila._tcp``) on the daemon's address."""
    state_dir: Path | None = None
    """Where the server UUID, certificate and key are kept; default: beside the token file."""


class DaemonConfig(_Model):
    host: str = "127.0.0.1"
    port: int = Field(8040, ge=0, le=65535)
    """0: a free port the system picks at start; the daemon prints the address it serves
    (clients then need it as ``--url``)."""
    allow_remote: bool = False
    """Binding to a non-loopback address needs this set (and a token)."""
    token_file: Path = Path("~/.config/fxcell/token")
    max_body_size: int = Field(1024 * 1024, ge=1024)
    """Largest request body accepted (bytes); larger ones are refused before they are read."""
    allowed_hosts: tuple[str, ...] = ()
    """Host names (besides localhost, the bind address and any IP address) under which
    the daemon may be reached; other names are refused (DNS-rebinding protection)."""
    header_timeout: float = Field(3.0, gt=0, le=60)
    """Seconds a client has to send a request's headers; a slower connection is closed."""
    body_timeout: float = Field(10.0, gt=0, le=600)
    """Seconds a client has to send a request's body once its headers are in."""
    idle_timeout: int = Field(5, ge=1, le=3600)
    """Seconds a kept-alive connection may stay idle between requests before it is closed."""
    sila: SilaConfig = SilaConfig()
    """The SiLA 2 server (off by default)."""


class IOConfig(_Model):
    """Named IO signals (task code uses the names, never the addresses) and interlocks."""

    signals: dict[str, str] = {}
    """Name → address (``DI2``, ``DO0``, ``CI3``, ``TO1``, ``AI0``, ...; see fxcell.signals)."""
    interlocks: dict[str, str] = {}
    """Zone → signal: no move into a station of that zone while the signal is on."""

    @field_validator("signals")
    @classmethod
    def _addresses(cls, v: dict[str, str]) -> dict[str, str]:
        out = {}
        for name, address in v.items():
            if not name.isidentifier():
                raise ValueError(f"signal name {name!r} must be an identifier (letters, _, digits)")
            out[name] = parse_signal(address).address
        return out

    @model_validator(mode="after")
    def _interlocks_known(self) -> IOConfig:
        for zone, signal in self.interlocks.items():
            if signal not in self.signals:
                raise ValueError(f"interlock of zone {zone!r}: no signal {signal!r}")
        return self


def default_state_dir() -> Path:
    """Where fxcell keeps what the cell is taught and its job database, for the shipped config
    (``$FXCELL_STATE_DIR``, else ``$XDG_STATE_HOME/fxcell`` or ``~/.local/state/fxcell``)."""
    explicit = os.environ.get("FXCELL_STATE_DIR")
    if explicit:
        return Path(explicit).expanduser()
    base = os.environ.get("XDG_STATE_HOME") or "~/.local/state"
    return Path(base).expanduser() / "fxcell"


class JobConfig(_Model):
    """The fusion-machine job (``fxcell.job``): its database and the machine's timing."""

    database: Path = Path("job.sqlite3")
    """The job's SQLite database (runs, sample locations, steps): relative paths are read
    beside the config file (for the shipped config: in :func:`default_state_dir`)."""
    manual: bool = False
    """Ask the operator to start the machine and to confirm it is done, instead of using
    the machine's IO signals."""
    ready_timeout: float = Field(60.0, gt=0)
    """Seconds to wait for ``machine_ready`` before loading a crucible."""
    start_timeout: float = Field(10.0, gt=0)
    """Seconds the machine has to report ``machine_busy`` after the start pulse."""
    done_timeout: float = Field(3600.0, gt=0)
    """Seconds a fusion cycle (fusion, cooling and a margin) may take until ``machine_done``."""
    cycle_estimate: float = Field(900.0, gt=0)
    """Seconds a fusion cycle is expected to take, for the time-left estimate until one has
    been measured."""
    heal_attempts: int = Field(5, ge=0, le=20)
    """Times a step that is safe to repeat (go home, the machine's start pulse) is run again
    after the robot link dropped under it, before the job stops for the operator (pick and
    place go on by themselves within, see ``robot.heal_attempts``)."""


class CameraConfig(_Model):
    """A camera of the cell: where its frames come from, its intrinsics and where it is.

    The camera frame is OpenCV's: z along the optical axis, x to the image's right, y down.
    """

    source: str | int | None = "simulator"
    """Where frames come from: ``null`` (no camera: the placement check is unavailable), a
    V4L2/USB index (``0``), a stream URL OpenCV opens (``rtsp://...``, ``http://.../mjpg``),
    ``snapshot:http://...`` (one JPEG per HTTP GET, as network cameras offer), or
    ``simulator``: the camera the simulator renders (the controller's address, port
    :data:`SIMULATOR_CAMERA_PORT`)."""
    width: int = Field(1280, ge=16, le=8192)
    height: int = Field(960, ge=16, le=8192)
    fx: float = Field(1100.0, gt=0)
    """Focal length in pixels (from a calibration: docs/guides/vision.md)."""
    fy: float = Field(1100.0, gt=0)
    cx: float = 639.5
    cy: float = 479.5
    distortion: tuple[float, ...] = ()
    """OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]); empty: none."""
    mount: Literal["base", "flange"] = "base"
    """What :attr:`pose` is relative to: the robot base, or the flange (a wrist camera)."""
    pose: Vector6 = (0.0, 0.33, 0.60, 3.0414, 0.0, 0.0)
    """The camera frame in the base (or flange) frame: x, y, z (m), rotation vector (rad)."""
    timeout: float = Field(5.0, gt=0)
    """Seconds a frame may take to arrive."""

    @field_validator("distortion")
    @classmethod
    def _distortion_length(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if len(v) not in (0, 4, 5, 8, 12, 14):
            raise ValueError("OpenCV takes 4, 5, 8, 12 or 14 distortion coefficients")
        return v


SIMULATOR_CAMERA_PORT = 8089
"""The simulator serves its rendered camera on this port of its address (``GET /snapshot.jpg``)."""


class FiducialConfig(_Model):
    """One ArUco marker on the crucible holder: its id and centre in the station frame (m)."""

    id: int = Field(ge=0)
    position: tuple[float, float]


class PlacementThresholds(_Model):
    """Where the placement check draws its lines (chosen from measured data: bench/placement.py)."""

    offset: float = Field(0.0012, gt=0)
    """A crucible whose rim centre is farther than this (m) from its position is ``offset``."""
    tilt_ratio: float = Field(0.972, gt=0, le=1)
    """A rim whose minor/major axis ratio is below this is ``tilted`` (cos 13.6° ≈ 0.972)."""
    diameter: float = Field(0.0012, gt=0)
    """A top disc whose minor axis differs from the crucible's width by more than this (m) is
    not a crucible (``foreign``)."""
    rectangularity: float = Field(0.88, gt=0, le=1)
    """A top whose area fills more of its bounding rectangle than this is boxy: ``foreign``."""
    saturation: float = Field(60.0, gt=0, le=255)
    """A top whose mean colour saturation (0-255) exceeds this is not platinum: ``foreign``."""
    presence: float = Field(0.12, gt=0, le=1)
    """A position whose foreground covers less than this fraction of a crucible's disc is
    ``empty``."""
    obstruction: float = Field(2.0e-5, gt=0)
    """Foreground of more than this area (m²) on the holder outside the positions is an
    obstruction (something left in the gripper's path)."""


class VisionConfig(_Model):
    """The camera and the placement check of the fusion machine's crucible positions."""

    camera: CameraConfig = CameraConfig()
    station: str = "machine"
    """The layout station whose positions the check judges (its slots, its object kind)."""
    dictionary: str = "DICT_4X4_50"
    """The ArUco dictionary of the holder's markers (``cv2.aruco`` name)."""
    marker_size: float = Field(0.028, gt=0)
    """Side of each marker's black square (m)."""
    markers: tuple[FiducialConfig, ...] = (
        FiducialConfig(id=0, position=(-0.045, -0.042)),
        FiducialConfig(id=1, position=(0.225, -0.042)),
        FiducialConfig(id=2, position=(0.225, 0.042)),
        FiducialConfig(id=3, position=(-0.045, 0.042)),
    )
    """The holder's markers, on the seat plane (z = 0 of the station frame)."""
    holder: tuple[float, float, float, float] = (-0.078, -0.068, 0.258, 0.068)
    """The holder's top plate in the station frame: x min, y min, x max, y max (m)."""
    thresholds: PlacementThresholds = PlacementThresholds()
    check_before_start: bool = True
    """The job checks the positions before it starts the machine (when a camera is set)."""

    @field_validator("markers")
    @classmethod
    def _enough_markers(cls, v: tuple[FiducialConfig, ...]) -> tuple[FiducialConfig, ...]:
        if len(v) < 2 or len({m.id for m in v}) != len(v):
            raise ValueError("give at least two markers with distinct ids")
        return v


class CellConfig(_Model):
    """Everything a :class:`~fxcell.cell.cell.Cell` and the daemon need."""

    robot: RobotConfig = RobotConfig()
    tool: ToolConfig = ToolConfig()
    """The tool; what it leaves out is the kind's (:mod:`fxcell.robot_specs`)."""
    home: Vector6 = HOME_JOINTS
    """Home joints (rad); default: the kind's."""
    limits: JointLimits = JointLimits()
    """Joint limits; what they leave out are the kind's, and all must fit its range."""
    scene: SceneConfig = SceneConfig()
    """Fixed obstacles that are not stations (the table); stations add their bodies."""
    layout: LayoutConfig = LayoutConfig()
    io: IOConfig = IOConfig()
    positions_file: Path = Path("positions.yaml")
    """Taught positions and station frames (written by ``cell.teach``): relative paths are
    read beside the config file (for the shipped config: in :func:`default_state_dir`)."""
    recorder: RecorderConfig = RecorderConfig()
    daemon: DaemonConfig = DaemonConfig()
    job: JobConfig = JobConfig()
    vision: VisionConfig = VisionConfig()

    @model_validator(mode="before")
    @classmethod
    def _kind_defaults(cls, data: Any) -> Any:
        """What ``home``, ``tool`` and ``limits`` leave out is the kind's (the defaults of
        the models above are the UR3e's)."""
        if not isinstance(data, dict):
            return data
        spec = SPECS.get(str(_kind_of(data.get("robot"))))
        if spec is None:
            return data  # the kind's own validation names the problem
        out = dict(data)
        out.setdefault("home", spec.home)
        tool = out.get("tool")
        if tool is None:
            out["tool"] = {"tcp": spec.tcp, "payload": spec.payload}
        elif isinstance(tool, dict):
            out["tool"] = {"tcp": spec.tcp, "payload": spec.payload, **tool}
        limits = out.get("limits")
        if limits is None:
            out["limits"] = dict(spec.limits)
        elif isinstance(limits, dict):
            out["limits"] = {**spec.limits, **limits}
        return out

    @model_validator(mode="after")
    def _fits_kind(self) -> CellConfig:
        spec = SPECS.get(self.robot.kind)
        if spec is not None:
            _check_kind(self, spec)
        return self

    @classmethod
    def load(cls, path: str | Path | None = None) -> CellConfig:
        """Load ``cell.yaml``; ``limits_file``/``scene_file``/``layout_file`` are read beside it.

        A user's file overrides the shipped configuration of its ``robot.kind``
        (``config/cell.yaml`` for a UR3e, ``config/ned2-cell.yaml`` for a Ned2): what it
        leaves out (limits, scene, layout, IO signals, ...) comes from the shipped files,
        mappings merged key by key, so no cell ever plans without the cell's scene.
        """
        path = Path(path) if path is not None else CONFIG_DIR / UR3E_SPEC.shipped_config
        data = _with_sections(_read_yaml(path), path)
        spec = SPECS.get(str(_kind_of(data.get("robot")) or UR3E_SPEC.kind))
        if spec is None:  # from_dict names the unknown kind
            spec = UR3E_SPEC
        shipped = CONFIG_DIR / spec.shipped_config
        own = any(
            path.resolve() == (CONFIG_DIR / s.shipped_config).resolve() for s in SPECS.values()
        )
        if not own:
            data = _merged(_with_sections(_read_yaml(shipped), shipped), data)
        base = default_state_dir() if own else path.parent
        positions = Path(str(data.get("positions_file", "positions.yaml"))).expanduser()
        data["positions_file"] = positions if positions.is_absolute() else base / positions
        job = data.get("job") or {}
        if isinstance(job, dict):  # else from_dict names the error
            database = Path(str(job.get("database", "job.sqlite3"))).expanduser()
            data["job"] = {
                **job,
                "database": database if database.is_absolute() else base / database,
            }
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "<dict>") -> CellConfig:
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            problems = "; ".join(
                f"{'.'.join(str(p) for p in err['loc'])}: {err['msg']}"
                if err["loc"]
                else str(err["msg"]).removeprefix("Value error, ")
                for err in exc.errors()
            )
            raise ConfigError(f"{source}: {problems}") from None


def _kind_of(robot: Any) -> object:
    """``robot.kind`` of a configuration's raw ``robot`` section (the UR3e when it names
    none; whatever it gives, for the validation to judge)."""
    if isinstance(robot, RobotConfig):
        return robot.kind
    if isinstance(robot, dict):
        return robot.get("kind", UR3E_SPEC.kind)
    return UR3E_SPEC.kind


def _check_kind(config: CellConfig, spec: RobotSpec) -> None:
    """ValueError naming the kind for what it cannot take."""
    kind = spec.kind
    for option, allowed in spec.robot_options.items():
        value = getattr(config.robot, option)
        if value not in allowed:
            shown = ", ".join("null" if a is None else str(a) for a in allowed)
            raise ValueError(
                f"robot.{option}: a {kind} ({spec.title}) takes {shown}, not {value!r}"
            )
    limits = config.limits
    checks = (
        ("home", config.home, spec.position_min, spec.position_max),
        ("limits.position_min", limits.position_min, spec.position_min, spec.position_max),
        ("limits.position_max", limits.position_max, spec.position_min, spec.position_max),
    )
    for name, values, low, high in checks:
        if len(values) != len(low):
            raise ValueError(f"{name}: a {kind} has {len(low)} joints, not {len(values)}")
        for joint, (v, lo, hi) in enumerate(zip(values, low, high, strict=True), start=1):
            if not lo - 1e-9 <= v <= hi + 1e-9:
                raise ValueError(
                    f"{name}: joint {joint} at {v:g} rad is outside the {kind}'s range "
                    f"[{lo:.4f}, {hi:.4f}] rad"
                )
    for joint, (lo, hi) in enumerate(
        zip(limits.position_min, limits.position_max, strict=True), start=1
    ):
        if lo >= hi:
            raise ValueError(f"limits: joint {joint}'s position_min is not below its position_max")
    for joint, (v, top) in enumerate(zip(limits.velocity, spec.velocity_max, strict=True), 1):
        if v > top + 1e-9:
            raise ValueError(
                f"limits.velocity: joint {joint} at {v:g} rad/s is above the {kind}'s {top:g} rad/s"
            )
    if config.tool.payload > spec.payload_max:
        raise ValueError(
            f"tool.payload: {config.tool.payload} kg is above the {kind}'s rated "
            f"{spec.payload_max} kg"
        )


def _with_sections(data: dict[str, Any], path: Path) -> dict[str, Any]:
    """``data`` with its ``*_file`` references read (relative to ``path``'s directory)."""
    for key, section in (
        ("limits_file", "limits"),
        ("scene_file", "scene"),
        ("layout_file", "layout"),
    ):
        ref = data.pop(key, None)
        if ref is not None:
            if section in data:
                raise ConfigError(f"{path}: give either {key!r} or {section!r}, not both")
            data[section] = _read_yaml(path.parent / str(ref))
    return data


def _merged(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``override`` on top of ``base``: mappings merged key by key, anything else replaced."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merged(out[key], value)
        else:
            out[key] = value
    return out


_YAML_LOADER: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def parse_yaml(text: str) -> Any:
    """YAML's safe subset, parsed by libyaml where PyYAML was built with it (the same result
    as ``yaml.safe_load``, about 12 times faster: every Cell and Job reads its YAML).

    A text parsed before is not parsed again: its result is copied (a tenth of the parse;
    a Cell reads the same configuration and statechart files each time it is made), so
    every caller gets objects of its own to change."""
    return copy.deepcopy(_parsed(text))


@functools.lru_cache(maxsize=64)
def _parsed(text: str) -> Any:
    """The parse of ``text``, shared: never handed out, only copies of it."""
    return yaml.load(text, Loader=_YAML_LOADER)


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}") from None
    try:
        data = parse_yaml(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return data
