"""``fxcell info``: versions of fxcell and its robotics stack, and the configuration in use."""

from __future__ import annotations

import argparse
import importlib.metadata
from typing import Any

from fxcell._version import __version__

STACK = ("ur_rtde", "transitions", "pin", "coal", "ompl", "ruckig", "mcap", "numpy", "pydantic")


def stack_versions() -> dict[str, str]:
    """Installed version of each library fxcell builds on ("missing" if absent)."""
    versions: dict[str, str] = {}
    for dist in STACK:
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            versions[dist] = "missing"
    return versions


def register(sub: Any) -> None:
    p = sub.add_parser("info", help="show versions and the configuration in use")
    p.add_argument("--config", help="cell configuration file (default: config/cell.yaml)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fxcell.config import CellConfig

    print(f"fxcell {__version__}")
    for dist, ver in stack_versions().items():
        print(f"  {dist:<12} {ver}")
    from fxcell.robot_specs import SPECS

    config = CellConfig.load(args.config)
    spec = SPECS[config.robot.kind]
    robot = f"robot: {spec.kind} ({spec.title}), {config.robot.host or 'embedded simulator'}"
    if "external_control" not in spec.robot_options:  # a UR's choice
        robot += f" (external control: {config.robot.external_control})"
    print(robot)
    print(f"arm model: {_arm_model(config)}")
    print(f"tcp: {list(config.tool.tcp)}")
    print(f"scene: {', '.join(o.name for o in config.scene.objects) or 'empty'}")
    stations = [
        f"{name} ({st.rows}x{st.columns} {st.holds})" for name, st in config.layout.stations.items()
    ]
    print(f"stations: {', '.join(stations) or 'none'}")
    print(f"positions: {config.positions_file}")
    if spec.link_process:
        print(f"robot link scheduling: {link_scheduling(config.robot.realtime_priority)}")
    else:
        print("robot link: in the cell process (it hands the robot whole trajectories)")
    print(sila_line(config))
    return 0


def _arm_model(config: Any) -> str:
    """What ``robot.calibration`` makes of the arm (``fxcell status`` shows what was read)."""
    from fxcell.calibration import Calibration
    from fxcell.errors import CalibrationError
    from fxcell.motion.calibration import CONTROLLER, NOMINAL
    from fxcell.robot_specs import SPECS

    source = config.robot.calibration
    if "calibration" in SPECS[config.robot.kind].robot_options:  # a Ned2: no calibration file
        return "nominal (the maker's model; the robot calibrates its own encoders)"
    if source == NOMINAL:
        return "nominal (robot.calibration: nominal; pose moves miss by millimetres on a real arm)"
    if source is None or source == CONTROLLER:
        fallback = (
            "the nominal model" if config.robot.accept_nominal_kinematics else "pose moves refused"
        )
        return f"calibrated, read from the controller at connect (if unreadable: {fallback})"
    try:
        calibration = Calibration.load(source)
    except CalibrationError as exc:
        return f"calibrated from {source}: UNREADABLE ({exc})"
    return f"calibrated from {source}, checksum {calibration.checksum}"


def link_scheduling(priority: int) -> str:
    """Whether a robot-link process started by this user gets real-time scheduling."""
    from fxcell.link.realtime import probe

    scheduling = probe(priority)
    if scheduling.realtime:
        return f"real time ({scheduling.describe()}): permitted for this user"
    return f"normal, not real time: {scheduling.detail} (see docs/guides/real-robot.md)"


def sila_line(config: Any) -> str:
    """The SiLA 2 server's address and its certificate's fingerprint (for pinning by eye)."""
    from fxcell.daemon.sila.identity import CERT_FILE, fingerprint, read_certificate, state_dir

    sila = config.daemon.sila
    where = f"{config.daemon.host}:{sila.port}"
    state = "on" if sila.enabled else "off (fxcell daemon --sila)"
    line = f"sila: {state}, {sila.server_name!r} on {where}"
    if sila.insecure:
        return line + ", without TLS (daemon.sila.insecure)"
    certificate = read_certificate(config)
    if certificate is None:
        return line + f"; no certificate yet ({state_dir(config) / CERT_FILE}: made at first start)"
    try:
        return line + f"; certificate SHA-256 {fingerprint(certificate)}"
    except (ImportError, ValueError) as exc:
        return line + f"; certificate unreadable: {exc}"
