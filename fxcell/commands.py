"""The cell's command table: every command, its typed arguments, guard, result and docs, once.

:class:`CellCommands` is the typing ``Protocol`` both :class:`fxcell.cell.Cell` (in
process) and :class:`fxcell.client.RemoteCell` (over the daemon's HTTP API) satisfy.
Each method is one command; its ``@command(...)`` decoration is the table entry:

- ``kind``: ``query`` (reads, never changes the robot: ``GET /api/cell/<name>``),
  ``command`` (changes the robot or the cell, answers when done) or ``move`` (a move:
  runs as an operation, answers at once over HTTP);
- ``args``: the :class:`ArgType` of each parameter (units, lengths, docs);
- ``guard``: the key of the statechart's ``commands`` table (``statecharts/robot.yaml``)
  that admits the command (default: its own name; ``None``: always admitted);
- ``result``: the :class:`ResultType` (how a JSON answer decodes into the Python type
  the method is annotated with).

:data:`COMMANDS` is built from them. The daemon's routes and request models, the
``RemoteCell`` methods (the default bodies below: ``run_command``), the CLI
subcommands, replay's re-execution and the operator page's command list are derived
from it. Adding a command: a decorated method here, its implementation in ``Cell``
(and a guard in the statechart if it needs one). See ``docs/ARCHITECTURE.md``.

This module imports neither numpy nor the motion stack: the light network client
uses it.
"""

from __future__ import annotations

import contextlib
import inspect
import math
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Any, Literal, Protocol, TypeVar

from fxcell.errors import InvalidArgumentError
from fxcell.protocol import ProgramState, RobotMode, SafetyMode
from fxcell.results import GripResult, MoveResult, ProgramStatus

if TYPE_CHECKING:
    from fxcell.geometry import Pose

Kind = Literal["query", "command", "move"]
F = TypeVar("F", bound=Callable[..., Any])


# ----------------------------------------------------------------- argument types


@dataclass(frozen=True)
class ArgType:
    """The type of a command argument: what it means, its unit, its shape.

    ``length`` is ``(min, max)`` for a list of numbers, ``None`` for a scalar;
    ``scalar`` is ``float`` or ``bool``; ``bounds`` is ``(low, high)`` for a float,
    ``low`` exclusive, ``high`` inclusive.
    """

    name: str
    doc: str
    unit: str = ""
    length: tuple[int, int] | None = None
    scalar: Literal["float", "bool", "str", "level"] = "float"
    """``level``: a flag or a number (an IO value: digital true/false, analog 0..1)."""
    bounds: tuple[float, float] | None = None
    closed: bool = False
    """``bounds`` include ``low`` too."""


FACTOR = ArgType("factor", "scale of the joint limits, in (0, 1]", "", bounds=(0.0, 1.0))
JOINTS = ArgType("joints", "joint positions, base to wrist 3", "rad", (6, 6))
POSE = ArgType(
    "pose",
    "[x, y, z, roll, pitch, yaw] or [x, y, z, qx, qy, qz, qw] in the base frame",
    "m, rad",
    (6, 7),
)
VECTOR3 = ArgType("vector3", "displacement along the base axes (x, y, z)", "m", (3, 3))
FLAG = ArgType("flag", "true or false", scalar="bool")
SECONDS = ArgType("seconds", "time limit", "s", bounds=(0.0, 3600.0))

GRIP_WIDTH_RANGE = (0.0, 0.050)
"""The Hand-E's finger opening, closed to fully open (m)."""
GRIP_SPEED_RANGE = (0.020, 0.150)
"""The Hand-E's finger speeds (m/s)."""
GRIP_FORCE_RANGE = (20.0, 185.0)
"""The Hand-E's grip forces (N)."""
GRIP_WIDTH = ArgType(
    "grip_width", "finger opening, 0 (closed) to the stroke (Hand-E 0.050)", "m",
    bounds=GRIP_WIDTH_RANGE,
    closed=True,
)  # fmt: skip
GRIP_SPEED = ArgType(
    "grip_speed",
    "finger speed (Hand-E 0.020 to 0.150)",
    "m/s",
    bounds=GRIP_SPEED_RANGE,
    closed=True,
)
GRIP_FORCE = ArgType(
    "grip_force", "grip force (Hand-E 20 to 185)", "N", bounds=GRIP_FORCE_RANGE, closed=True
)

NAME = ArgType("name", "a name (letters, digits, '_', '-')", scalar="str")
SIGNAL = ArgType("signal", "an IO signal name of the configuration (io.signals)", scalar="str")
LEVEL = ArgType(
    "level", "digital: true or false; analog output: fraction 0..1 of its range", scalar="level"
)
STATION = ArgType("station", "a station of the layout (rack, tray, machine, moulds)", scalar="str")
SLOT = ArgType("slot", "a slot of the station: row letter and column number, e.g. B3", scalar="str")
FRAME_POINT = ArgType("frame_point", "origin, x_point or xy_point", scalar="str")
SLOTS = ArgType(
    "slots",
    "positions that must hold a seated crucible, comma-separated (e.g. A1,A2); '-': none; "
    "empty: each position seated or empty",
    scalar="str",
)
OBJECT_KIND = ArgType("object_kind", "an object kind of the layout (crucible, bead)", scalar="str")

ARG_TYPES: tuple[ArgType, ...] = (
    FACTOR, JOINTS, POSE, VECTOR3, FLAG, SECONDS, GRIP_WIDTH, GRIP_SPEED, GRIP_FORCE,
    NAME, SIGNAL, LEVEL, STATION, SLOT, FRAME_POINT, SLOTS, OBJECT_KIND,
)  # fmt: skip


# ----------------------------------------------------------------- robot features


class Feature(StrEnum):
    """What a command needs of the robot beyond moving its joints. Each entry of the
    table names the features it needs (``requires``); a robot kind lists the features it
    has (:class:`fxcell.link.capabilities.RobotCapabilities`), and the Cell refuses a
    command whose features its kind lacks, before anything is sent."""

    REMOTE_POWER = "remote_power"
    """The arm's power switched on and off over the network."""
    REMOTE_SHUTDOWN = "remote_shutdown"
    """The controller shut down over the network."""
    FREEDRIVE = "freedrive"
    """The arm moved by hand (UR freedrive, the Ned2's learning mode)."""
    GRIPPER = "gripper"
    """A gripper fxcell drives (and so picks and places)."""
    IO = "io"
    """Digital and analog IO by configured names."""


# ----------------------------------------------------------------- result types


@dataclass(frozen=True)
class ResultType:
    """What a command returns: its annotation and how its JSON form decodes to it."""

    annotation: str
    decode: Callable[[Any], Any]


def _floats(value: Any) -> tuple[float, ...]:
    return tuple(float(v) for v in value)


def _move_result(value: Any) -> MoveResult:
    fields: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in value.items()}
    return MoveResult(**fields)


NONE = ResultType("None", lambda value: None)
BOOL = ResultType("bool", bool)
FLOAT = ResultType("float", float)
FLOATS = ResultType("tuple[float, ...]", _floats)
RPY = ResultType("tuple[float, float, float]", _floats)
ROBOT_MODE = ResultType("RobotMode", lambda value: RobotMode[value])
SAFETY_MODE = ResultType("SafetyMode", lambda value: SafetyMode[value])
PROGRAM_STATUS = ResultType(
    "ProgramStatus", lambda value: ProgramStatus(ProgramState(value["state"]), value["program"])
)
MOVE_RESULT = ResultType("MoveResult", _move_result)
MAPPING = ResultType("dict[str, Any]", dict)
GRIP_RESULT = ResultType(
    "GripResult", lambda value: GripResult(float(value["width"]), bool(value["holding"]))
)


# ----------------------------------------------------------------- the table


@dataclass(frozen=True)
class Arg:
    """One parameter of a command."""

    name: str
    type: ArgType
    required: bool
    default: Any
    keyword_only: bool
    doc: str


@dataclass(frozen=True)
class Command:
    """One entry of the command table."""

    name: str
    kind: Kind
    doc: str
    args: tuple[Arg, ...]
    result: ResultType
    guard: str | None
    """Key of the statechart's ``commands`` table; ``None``: admitted in every state."""
    needs_control: bool
    """Over the daemon: needs control of the cell (``stop`` needs only the token)."""
    signature: inspect.Signature
    requires: frozenset[Feature] = frozenset()
    """The robot features the command needs (a kind without one of them refuses it)."""

    @property
    def changes_robot(self) -> bool:
        """Whether the command changes the robot or the cell (needs the daemon's token)."""
        return self.kind != "query"

    @property
    def summary(self) -> str:
        return self.doc.split("\n\n", 1)[0].replace("\n", " ").replace("``", "")

    def check_args(self, args: Mapping[str, Any]) -> None:
        """Raise :class:`InvalidArgumentError` for a name the command does not take."""
        unknown = set(args) - {a.name for a in self.args}
        if unknown:
            raise InvalidArgumentError(
                f"{self.name}() takes no argument {', '.join(sorted(unknown))}"
            )

    def check_values(self, args: Mapping[str, Any]) -> None:
        """Raise :class:`InvalidArgumentError` for a required argument left out or a value
        its :class:`ArgType` refuses: a number that is not finite or outside the type's
        bounds, a list of another length or with an element that is not a finite number,
        a flag that is not a bool, an empty name. (``None`` is the default of an optional
        argument; poses may also be ``Pose`` objects, checked where they are used.)"""
        for arg in self.args:
            value = args.get(arg.name)
            if value is None:
                if arg.required:
                    raise InvalidArgumentError(f"{self.name}() needs {arg.name}")
                continue
            problem = _problem(arg.type, value)
            if problem:
                raise InvalidArgumentError(f"{self.name}(): {arg.name} {problem}")

    def known_args(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """``args`` restricted to the command's parameters (recorded extras dropped)."""
        names = {a.name for a in self.args}
        return {k: v for k, v in args.items() if k in names}


def _finite(value: Any) -> bool:
    """A finite real number (numpy scalars too), not a bool nor a string."""
    return _number(value) and math.isfinite(float(value))


def _problem(kind: ArgType, value: Any) -> str:
    """What is wrong with ``value`` as a ``kind`` ("" if nothing)."""
    if kind.scalar == "bool":
        return "" if isinstance(value, bool) else f"must be true or false, got {value!r}"
    if kind.scalar == "str":
        return "" if isinstance(value, str) and value else f"must be a name, got {value!r}"
    if kind.scalar == "level":
        ok = isinstance(value, bool) or _finite(value)
        return "" if ok else f"must be true, false or a finite number, got {value!r}"
    if kind.length is not None:
        if not isinstance(value, list | tuple):
            return ""  # a Pose or an array: the command checks it
        low, high = kind.length
        if not low <= len(value) <= high:
            count = str(low) if low == high else f"{low} to {high}"
            return f"must be {count} numbers ({kind.unit}), got {len(value)}"
        ok = all(_finite(v) for v in value)
        return "" if ok else f"must be finite numbers, got {list(value)!r}"
    if not _finite(value):
        return f"must be a finite number, got {value!r}"
    if kind.bounds is not None:
        bottom, top = kind.bounds
        above = bottom <= float(value) if kind.closed else bottom < float(value)
        if not (above and float(value) <= top):
            return f"must be in {'[' if kind.closed else '('}{bottom:g}, {top:g}], got {value!r}"
    return ""


def _number(value: Any) -> bool:
    """A real number (numpy scalars too), not a bool."""
    if isinstance(value, bool):
        return False
    try:
        float(value)
    except (TypeError, ValueError, OverflowError):
        return False
    return not isinstance(value, str | bytes)


@dataclass(frozen=True)
class _Spec:
    kind: Kind
    result: ResultType
    args: Mapping[str, ArgType]
    guard: str | Literal[True] | None
    needs_control: bool
    docs: Mapping[str, str]
    requires: frozenset[Feature]


def command(
    kind: Kind,
    result: ResultType,
    *,
    args: Mapping[str, ArgType] | None = None,
    guard: str | Literal[True] | None = True,
    needs_control: bool = True,
    docs: Mapping[str, str] | None = None,
    requires: Sequence[Feature] = (),
) -> Callable[[F], F]:
    """Mark a :class:`CellCommands` method as a command (``guard=True``: its own name;
    ``requires``: the robot features it needs)."""

    def mark(fn: F) -> F:
        fn.__fxcell_command__ = _Spec(  # type: ignore[attr-defined]
            kind,
            result,
            dict(args or {}),
            guard,
            needs_control,
            dict(docs or {}),
            frozenset(requires),
        )
        return fn

    return mark


def _given(frame: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in frame.items() if k != "self"}


# Common parameter docs.
_DOCS = {
    "velocity_factor": "velocity factor of this move (default: the cell's)",
    "acceleration_factor": "acceleration factor of this move (default: the cell's)",
    "queue": "wait for a running move to end instead of failing with MoveInProgressError",
    "timeout": "time limit (default: the cell's command timeout)",
}
_HEAL_DOCS = {"timeout": "time limit (default: robot.heal_timeout)"}
_GRIP_DOCS = {"expect_object": "raise NothingGraspedError if the fingers close on nothing"}
_MOVE = {"velocity_factor": FACTOR, "acceleration_factor": FACTOR, "queue": FLAG}
_AT_SLOT = {
    "station": STATION,
    "slot": SLOT,
    "velocity_factor": FACTOR,
    "acceleration_factor": FACTOR,
}


class CellCommands(Protocol):
    """The cell's commands, satisfied by ``Cell`` and ``RemoteCell``.

    Every method's default body sends it through :meth:`run_command` (how
    ``RemoteCell`` implements them all); ``Cell`` implements each one.
    """

    async def run_command(self, command: str, /, **args: Any) -> Any:
        """Run ``command`` of :data:`COMMANDS` with keyword arguments (positional-only: a
        command may have an argument called ``name``)."""
        ...

    # ------------------------------------------------------------- general

    @command(
        "command", NONE, args={"timeout": SECONDS}, docs=_DOCS, requires=[Feature.REMOTE_POWER]
    )
    async def power_on(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        """Power the arm on; returns when the robot mode is IDLE."""
        return await self.run_command("power_on", **_given(locals()))  # type: ignore[no-any-return]

    @command("command", NONE, args={"timeout": SECONDS}, docs=_DOCS)
    async def brake_release(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        """Release the brakes; returns when the robot mode is RUNNING."""
        return await self.run_command("brake_release", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "command", NONE, args={"timeout": SECONDS}, docs=_DOCS, requires=[Feature.REMOTE_POWER]
    )
    async def power_off(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        """Power the arm off; returns when the robot mode is POWER_OFF."""
        return await self.run_command("power_off", **_given(locals()))  # type: ignore[no-any-return]

    @command("command", NONE, args={"timeout": SECONDS}, docs=_DOCS)
    async def init(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        """Power on, release the brakes and start external control, as far as needed.

        Idempotent: a cell already under external control returns at once.
        """
        return await self.run_command("init", **_given(locals()))  # type: ignore[no-any-return]

    @command("command", NONE, args={"timeout": SECONDS}, docs=_DOCS)
    async def start_external_control(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        """Start the control program (script upload or URCap program, as configured).

        Returns when the program is PLAYING and accepts commands.
        """
        return await self.run_command("start_external_control", **_given(locals()))  # type: ignore[no-any-return]

    @command("command", NONE, args={"timeout": SECONDS}, docs=_DOCS)
    async def stop_external_control(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        """Stop the control program; returns when no program is playing."""
        return await self.run_command("stop_external_control", **_given(locals()))  # type: ignore[no-any-return]

    @command("command", NONE, args={"timeout": SECONDS}, guard=None, docs=_HEAL_DOCS)
    async def restore_control(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        """After the robot link dropped or restarted: wait until it is up and the arm is seen
        at rest, then take external control back (and set the tool again).

        A safety stop raises its error (``ProtectiveStopError``, ...); an arm that is not
        running (powered off, brakes engaged) raises ``InvalidStateError``; nothing within
        ``timeout`` raises ``RobotTimeoutError``. What pick, place and the job do by
        themselves before they go on.
        """
        return await self.run_command("restore_control", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "command",
        NONE,
        args={"wait": FLAG, "timeout": SECONDS},
        docs={"wait": "wait out the controller's 5 s rule instead of failing", **_DOCS},
    )
    async def unlock_protective_stop(
        self,
        wait: bool = False,
        *,
        timeout: float | None = None,  # noqa: ASYNC109
    ) -> None:
        """Unlock a protective stop and re-establish external control if it was on.

        The controller refuses within 5 s of the stop: that raises
        ``ProtectiveStopUnlockTooSoonError``, unless ``wait`` is true, when this waits
        until the controller accepts.
        """
        return await self.run_command("unlock_protective_stop", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "command", NONE, args={"timeout": SECONDS}, docs=_DOCS, requires=[Feature.REMOTE_SHUTDOWN]
    )
    async def shutdown(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        """Shut down the robot and its controller; returns when the controller is gone."""
        return await self.run_command("shutdown", **_given(locals()))  # type: ignore[no-any-return]

    # ------------------------------------------------------------- queries

    @command("query", ROBOT_MODE)
    async def get_robot_mode(self) -> RobotMode:
        """The robot mode (``RobotMode.RUNNING``, ``IDLE``, ``POWER_OFF``, ...)."""
        return await self.run_command("get_robot_mode")  # type: ignore[no-any-return]

    @command("query", SAFETY_MODE)
    async def get_safety_status(self) -> SafetyMode:
        """The safety mode (``SafetyMode.NORMAL``, ``PROTECTIVE_STOP``, ...)."""
        return await self.run_command("get_safety_status")  # type: ignore[no-any-return]

    @command("query", PROGRAM_STATUS)
    async def get_program_state(self) -> ProgramStatus:
        """The controller's program state and loaded program (dashboard ``programState``)."""
        return await self.run_command("get_program_state")  # type: ignore[no-any-return]

    @command("query", BOOL)
    async def is_in_remote_control(self) -> bool:
        """True when the teach pendant is in Remote control."""
        return await self.run_command("is_in_remote_control")  # type: ignore[no-any-return]

    @command("query", FLOATS)
    async def get_current_joint_values(self) -> tuple[float, ...]:
        """The six joint positions, rad."""
        return await self.run_command("get_current_joint_values")  # type: ignore[no-any-return]

    @command("query", FLOATS)
    async def get_current_pose(self) -> tuple[float, ...]:
        """The TCP pose: position (m) and quaternion ``(x, y, z, qx, qy, qz, qw)``."""
        return await self.run_command("get_current_pose")  # type: ignore[no-any-return]

    @command("query", RPY, guard="get_current_pose")
    async def get_current_rpy(self) -> tuple[float, float, float]:
        """The TCP orientation as roll, pitch, yaw (rad), R = Rz(y)·Ry(p)·Rx(r)."""
        return await self.run_command("get_current_rpy")  # type: ignore[no-any-return]

    @command("query", FLOATS, guard="get_current_pose")
    async def get_current_pose_rpy(self) -> tuple[float, ...]:
        """The TCP pose as ``(x, y, z, roll, pitch, yaw)`` (m, rad)."""
        return await self.run_command("get_current_pose_rpy")  # type: ignore[no-any-return]

    @command("query", FLOATS)
    async def get_velocity(self) -> tuple[float, ...]:
        """The six joint velocities, rad/s."""
        return await self.run_command("get_velocity")  # type: ignore[no-any-return]

    @command("query", FLOAT, guard=None)
    async def get_velocity_factor(self) -> float:
        """The default velocity factor of moves."""
        return await self.run_command("get_velocity_factor")  # type: ignore[no-any-return]

    @command("query", FLOAT, guard=None)
    async def get_acceleration_factor(self) -> float:
        """The default acceleration factor of moves."""
        return await self.run_command("get_acceleration_factor")  # type: ignore[no-any-return]

    @command("query", FLOATS, guard=None)
    async def get_max_acceleration(self) -> tuple[float, ...]:
        """The joints' configured maximum accelerations (rad/s², before the factor)."""
        return await self.run_command("get_max_acceleration")  # type: ignore[no-any-return]

    # ------------------------------------------------------------- factors

    @command("command", NONE, args={"value": FACTOR}, guard=None)
    async def set_velocity_factor(self, value: float) -> None:
        """Default velocity factor of moves, in (0, 1]; InvalidFactorError otherwise."""
        return await self.run_command("set_velocity_factor", **_given(locals()))  # type: ignore[no-any-return]

    @command("command", NONE, args={"value": FACTOR}, guard=None)
    async def set_acceleration_factor(self, value: float) -> None:
        """Default acceleration factor of moves, in (0, 1]; InvalidFactorError otherwise."""
        return await self.run_command("set_acceleration_factor", **_given(locals()))  # type: ignore[no-any-return]

    # ------------------------------------------------------------- moves

    @command("move", MOVE_RESULT, args={"target": JOINTS, **_MOVE}, guard="move", docs=_DOCS)
    async def move_joint(
        self,
        target: Sequence[float],
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        queue: bool = False,
    ) -> MoveResult:
        """Move to joint positions (rad) on a jerk-limited, collision-free trajectory.

        Factors in (0, 1] scale the joint velocity / acceleration limits for this move
        (default: the cell's factors, see ``set_velocity_factor``). While another move
        runs, a move raises ``MoveInProgressError``, or with ``queue=True`` waits for it
        to end and then starts (every move takes ``queue``; ``stop()`` also ends the
        moves waiting so).
        """
        return await self.run_command("move_joint", **_given(locals()))  # type: ignore[no-any-return]

    @command("move", MOVE_RESULT, args=_MOVE, guard="move", docs=_DOCS)
    async def go_home(
        self,
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        queue: bool = False,
    ) -> MoveResult:
        """Move to the configured home joints ([0, -π/2, 0, -π/2, 0, 0] by default)."""
        return await self.run_command("go_home", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "move",
        MOVE_RESULT,
        args={"target": POSE, "linear": FLAG, **_MOVE},
        guard="move",
        docs={"linear": "move the TCP on a straight line", **_DOCS},
    )
    async def move_pose(
        self,
        target: Pose | Sequence[float],
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        linear: bool = False,
        queue: bool = False,
    ) -> MoveResult:
        """Move the TCP to a pose: a Pose, [x, y, z, qx, qy, qz, qw] or [x, y, z, r, p, y].

        ``linear=True`` moves the TCP on a straight line (else a joint-space move to the
        IK solution nearest the current joints).
        """
        return await self.run_command("move_pose", **_given(locals()))  # type: ignore[no-any-return]

    @command("move", MOVE_RESULT, args={"distance": VECTOR3, **_MOVE}, guard="move", docs=_DOCS)
    async def move_distance(
        self,
        distance: Sequence[float],
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        queue: bool = False,
    ) -> MoveResult:
        """Move the TCP by [dx, dy, dz] (m, base axes) on a straight line, orientation kept."""
        return await self.run_command("move_distance", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "move",
        MOVE_RESULT,
        args={"start_pose": POSE, "target_pose": POSE, **_MOVE},
        guard="move",
        docs={"start_pose": "the pose to go first", "target_pose": "the pose to go then", **_DOCS},
    )
    async def move_relative(
        self,
        start_pose: Pose | Sequence[float],
        target_pose: Pose | Sequence[float],
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        queue: bool = False,
    ) -> MoveResult:
        """Move the TCP to ``start_pose``, then to ``target_pose`` (two joint-space moves).

        Both legs are planned, and so checked, before the robot moves.
        """
        return await self.run_command("move_relative", **_given(locals()))  # type: ignore[no-any-return]

    # ------------------------------------------------------------- gripper

    @command("command", NONE, guard="gripper", requires=[Feature.GRIPPER])
    async def gripper_activate(self) -> None:
        """Activate the gripper (the Hand-E: needs the arm powered; once after each power-up)."""
        return await self.run_command("gripper_activate")  # type: ignore[no-any-return]

    @command(
        "command",
        GRIP_RESULT,
        args={"speed": GRIP_SPEED},
        guard="gripper",
        requires=[Feature.GRIPPER],
    )
    async def gripper_open(self, *, speed: float | None = None) -> GripResult:
        """Open the gripper fully; returns where the fingers stopped and whether they hold."""
        return await self.run_command("gripper_open", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "command",
        GRIP_RESULT,
        args={"speed": GRIP_SPEED, "grip_force": GRIP_FORCE, "expect_object": FLAG},
        guard="gripper",
        docs=_GRIP_DOCS,
        requires=[Feature.GRIPPER],
    )
    async def gripper_close(
        self,
        *,
        speed: float | None = None,
        grip_force: float | None = None,
        expect_object: bool = False,
    ) -> GripResult:
        """Close the gripper fully or until an object stops the fingers.

        ``expect_object=True`` raises ``NothingGraspedError`` when they close on nothing.
        """
        return await self.run_command("gripper_close", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "command",
        GRIP_RESULT,
        args={
            "width": GRIP_WIDTH,
            "speed": GRIP_SPEED,
            "grip_force": GRIP_FORCE,
            "expect_object": FLAG,
        },
        guard="gripper",
        docs=_GRIP_DOCS,
        requires=[Feature.GRIPPER],
    )
    async def gripper_move(
        self,
        width: float,
        *,
        speed: float | None = None,
        grip_force: float | None = None,
        expect_object: bool = False,
    ) -> GripResult:
        """Move the fingers to an opening (m) at a speed (m/s) with at most a force (N);
        speed and force left out: the gripper's own. A two-position gripper (the Ned2's)
        takes only 0 and its full opening."""
        return await self.run_command("gripper_move", **_given(locals()))  # type: ignore[no-any-return]

    @command("query", FLOAT, guard="gripper", requires=[Feature.GRIPPER])
    async def get_gripper_width(self) -> float:
        """The gripper's finger opening (m)."""
        return await self.run_command("get_gripper_width")  # type: ignore[no-any-return]

    # ------------------------------------------------------------- IO

    @command("query", MAPPING, guard="io", requires=[Feature.IO])
    async def get_io(self) -> dict[str, Any]:
        """Every configured IO signal's value: digital ones true/false, analog ones in V or A."""
        return await self.run_command("get_io")  # type: ignore[no-any-return]

    @command(
        "command", NONE, args={"signal": SIGNAL, "value": LEVEL}, guard="io", requires=[Feature.IO]
    )
    async def io_set(self, signal: str, value: bool | float) -> None:
        """Set an output by its configured name; returns once the controller reports it."""
        return await self.run_command("io_set", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "command",
        FLOAT,
        args={"signal": SIGNAL, "value": LEVEL, "timeout": SECONDS},
        guard="io",
        requires=[Feature.IO],
    )
    async def io_wait_for(
        self,
        signal: str,
        value: bool | float = True,
        timeout: float = 60.0,  # noqa: ASYNC109
    ) -> float:
        """Wait until a signal reads ``value`` (analog: reaches at least it); returns the
        seconds waited, or raises ``IOTimeoutError``."""
        return await self.run_command("io_wait_for", **_given(locals()))  # type: ignore[no-any-return]

    # ------------------------------------------------------------- teach-in

    @command("command", NONE, requires=[Feature.FREEDRIVE])
    async def freedrive_start(self) -> None:
        """Put the arm in freedrive (teach mode): it can be guided by hand until
        ``freedrive_stop``. Moves are refused meanwhile."""
        return await self.run_command("freedrive_start")  # type: ignore[no-any-return]

    @command("command", NONE, requires=[Feature.FREEDRIVE])
    async def freedrive_stop(self) -> None:
        """End freedrive; the arm holds where it was left."""
        return await self.run_command("freedrive_stop")  # type: ignore[no-any-return]

    @contextlib.asynccontextmanager
    async def freedrive(self) -> AsyncIterator[None]:
        """``async with cell.freedrive():`` the arm can be guided by hand inside the block."""
        await self.freedrive_start()
        try:
            yield
        finally:
            await self.freedrive_stop()

    @command("command", MAPPING, args={"name": NAME}, guard="teach")
    async def teach(self, name: str) -> dict[str, Any]:
        """Store the current joints and TCP pose as position ``name`` (re-teaching keeps the
        previous value in the positions file); returns what was stored."""
        return await self.run_command("teach", **_given(locals()))  # type: ignore[no-any-return]

    @command("query", MAPPING, guard=None)
    async def get_positions(self) -> dict[str, Any]:
        """Every taught position: name → joints (rad), TCP pose and when it was taught."""
        return await self.run_command("get_positions")  # type: ignore[no-any-return]

    @command("move", MOVE_RESULT, args={"name": NAME, **_MOVE}, guard="move", docs=_DOCS)
    async def move_to(
        self,
        name: str,
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        queue: bool = False,
    ) -> MoveResult:
        """Move to a taught position (its joints), or to ``home``; an unknown name raises
        ``UnknownPositionError`` listing the known ones."""
        return await self.run_command("move_to", **_given(locals()))  # type: ignore[no-any-return]

    # ------------------------------------------------------------- layout, pick and place

    @command("query", MAPPING, guard=None)
    async def get_layout(self) -> dict[str, Any]:
        """The stations: frame, slots (name → grip pose), object kind, body; for drawing."""
        return await self.run_command("get_layout")  # type: ignore[no-any-return]

    @command("command", MAPPING, args={"station": STATION, "point": FRAME_POINT}, guard="teach")
    async def teach_frame_point(self, station: str, point: str) -> dict[str, Any]:
        """Re-teach one point of a station's frame (``origin``, ``x_point``, ``xy_point``) at
        the TCP's current position. Once all three are re-taught (any order) the frame
        changes, and every slot and the station's obstacle move with it; returns
        ``{"applied", "pending", "frame"}``."""
        return await self.run_command("teach_frame_point", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "move", GRIP_RESULT, args=_AT_SLOT, guard="move", docs=_DOCS, requires=[Feature.GRIPPER]
    )
    async def pick(
        self,
        station: str,
        slot: str,
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
    ) -> GripResult:
        """Pick the object in a slot: approach above it, descend straight, grip (an empty
        slot raises ``NothingGraspedError``, the arm back above it), rise straight.

        Bad station or slot names and unreachable slots raise before anything moves; a
        station in an interlocked zone (the fusion machine while busy) raises
        ``InterlockError``. The held object is then part of collision checking and the
        payload set on the controller.
        """
        return await self.run_command("pick", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "move", GRIP_RESULT, args=_AT_SLOT, guard="move", docs=_DOCS, requires=[Feature.GRIPPER]
    )
    async def place(
        self,
        station: str,
        slot: str,
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
    ) -> GripResult:
        """Place the held object in a slot: approach, descend straight, release, rise."""
        return await self.run_command("place", **_given(locals()))  # type: ignore[no-any-return]

    @command(
        "command",
        MAPPING,
        args={"expected": SLOTS},
        guard=None,
        needs_control=False,
        docs={"expected": SLOTS.doc},
    )
    async def check_placement(self, expected: str = "") -> dict[str, Any]:
        """Look at the fusion machine's crucible positions with the camera: each is
        ``empty``, ``seated``, ``offset``, ``tilted`` or ``foreign``, with a confidence and
        the measured offset (mm); anything on the holder outside them is an obstruction.

        Returns ``{"ok", "reason", "positions", "obstructions", ...}``; the annotated image
        is recorded (MCAP ``/camera/placement``) and served by the daemon
        (``/api/camera/placement.jpg``). Raises ``CameraError`` when no frame comes.
        """
        return await self.run_command("check_placement", **_given(locals()))  # type: ignore[no-any-return]

    @command("command", NONE, args={"kind": OBJECT_KIND}, guard=None)
    async def declare_held(self, kind: str | None = None) -> None:
        """Tell the cell what the gripper holds: an object kind of the layout (``crucible``,
        ``bead``), or nothing when left out (e.g. after a restart, when a job knows it).
        Collision checking and the payload set on the controller follow."""
        return await self.run_command("declare_held", **_given(locals()))  # type: ignore[no-any-return]

    @command("command", BOOL, needs_control=False)
    async def stop(self) -> bool:
        """Stop the running move (it brakes to a stop) and the moves queued after it.

        True if a move was running. Over the daemon it needs the token, not control.
        """
        return await self.run_command("stop")  # type: ignore[no-any-return]


def _build() -> dict[str, Command]:
    table: dict[str, Command] = {}
    for name, fn in vars(CellCommands).items():
        spec: _Spec | None = getattr(fn, "__fxcell_command__", None)
        if spec is None:
            continue
        signature = inspect.signature(fn)
        params = [p for p in signature.parameters.values() if p.name != "self"]
        if {p.name for p in params} != set(spec.args):
            raise TypeError(f"{name}: the argument types do not match the parameters")
        if spec.kind == "query" and params:
            raise TypeError(f"{name}: a query takes no arguments (GET /api/cell/<name>)")
        args = tuple(
            Arg(
                p.name,
                spec.args[p.name],
                p.default is inspect.Parameter.empty,
                None if p.default is inspect.Parameter.empty else p.default,
                p.kind is inspect.Parameter.KEYWORD_ONLY,
                spec.docs.get(p.name, spec.args[p.name].doc),
            )
            for p in params
        )
        guard = name if spec.guard is True else spec.guard
        doc = inspect.cleandoc(fn.__doc__ or "")
        table[name] = Command(
            name,
            spec.kind,
            doc,
            args,
            spec.result,
            guard,
            spec.needs_control,
            signature,
            spec.requires,
        )
    return table


COMMANDS: dict[str, Command] = _build()
"""Every command of the cell, by name, in definition order."""


def get_command(name: str) -> Command:
    """The table entry of ``name``; :class:`InvalidArgumentError` for an unknown one."""
    try:
        return COMMANDS[name]
    except KeyError:
        raise InvalidArgumentError(f"unknown command {name!r}") from None


__all__ = [
    "ARG_TYPES",
    "COMMANDS",
    "Arg",
    "ArgType",
    "CellCommands",
    "Command",
    "ResultType",
    "command",
    "get_command",
]
