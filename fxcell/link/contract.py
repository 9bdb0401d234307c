"""The robot-link contract's wire-level parts: requests, stop reasons, value types.

What the asyncio client (:mod:`fxcell.link.client`), the link process
(:mod:`fxcell.link.process`) and the in-process fake (:mod:`fxcell.testing.fake`) agree on:

- **Requests**: one frozen dataclass per operation (:data:`Request`). The client sends the
  dataclass itself; each side answers it through one table keyed by the request's class
  (never by a name built from the message), and a test checks that every table covers
  every request type.
- **Stop reasons**: :class:`StopReason` names why a trajectory ended or braked; the wire
  carries its value (a stable string). :data:`STOP_ERRORS` is the one table from a reason
  to the typed error a move that ended for it raises.
- **Value types** the :class:`~fxcell.link.backend.LinkBackend` protocol speaks:
  :class:`LinkStatus`, :class:`Guard`, :class:`TrajectoryProgress`, :class:`TrajectoryResult`.
- :data:`WIRE_VERSION`, said in the link process's HELLO: the client refuses a process of
  another version with :class:`~fxcell.errors.LinkContractError` (client and process are
  always the same install; this catches a half-updated one).

The link process imports this module: it stays free of numpy and asyncio.
"""

from __future__ import annotations

import enum
import math
import typing
from dataclasses import dataclass
from typing import Literal

from fxcell.errors import (
    ConnectionLostError,
    EmergencyStopError,
    FxcellError,
    InvalidArgumentError,
    LinkBrakeError,
    LinkContractError,
    MoveError,
    MoveStoppedError,
    NotInRemoteControlError,
    ProgramStoppedError,
    ProtectiveStopError,
    RobotCommandError,
    RobotFaultError,
    RobotTimeoutError,
    SafeguardStopError,
)
from fxcell.protocol import SAFETY_STOPS, RuntimeState
from fxcell.signals import Group

OutputGroup = Group
"""An output's group (``standard``, ``configurable``, ``tool``, ``analog``)."""

WIRE_VERSION = 2
"""The version of the messages between the client and the link process (1 was the
untyped ``call(method, kwargs)`` protocol)."""


# ----------------------------------------------------------------- stop reasons


class StopReason(enum.StrEnum):
    """Why a trajectory ended or was braked (the value is what the wire carries)."""

    # asked for: the client, or a link call that needs the arm at rest
    STOP_REQUESTED = "stop requested"
    SETTLED = "settled"
    """The robot is at the target: the stop keeps servo mode for the next move."""
    MOVE_ABORTED = "move aborted"
    SUPERSEDED = "superseded"
    SERVO_STOP = "servo stop"
    TEACH_MODE = "teach mode"
    EXTERNAL_CONTROL_STOPPED = "external control stopped"
    LINK_CLOSING = "link closing"
    # the link process's own guard: it braked by itself
    CELL_SILENT = "cell_silent"
    STATE_STALLED = "state_stalled"
    LINK_DOWN = "link_down"
    # the robot stopped the arm, or refused the stream
    PROTECTIVE_STOP = "protective_stop"
    SAFEGUARD_STOP = "safeguard_stop"
    EMERGENCY_STOP = "emergency_stop"
    FAULT = "fault"
    VIOLATION = "violation"
    PROGRAM_STOPPED = "program_stopped"
    SERVOJ_REFUSED = "servoj_refused"
    NO_EXTERNAL_CONTROL = "no_external_control"
    # the link failed
    LINK_LOST = "link_lost"
    LINK_ERROR = "link_error"
    NONE = ""
    """A trajectory that completed."""


STOP_ERRORS: dict[StopReason, type[FxcellError]] = {
    StopReason.STOP_REQUESTED: MoveStoppedError,
    StopReason.SETTLED: MoveStoppedError,
    StopReason.MOVE_ABORTED: MoveStoppedError,
    StopReason.SUPERSEDED: MoveStoppedError,
    StopReason.SERVO_STOP: MoveStoppedError,
    StopReason.TEACH_MODE: MoveStoppedError,
    StopReason.EXTERNAL_CONTROL_STOPPED: MoveStoppedError,
    StopReason.LINK_CLOSING: MoveStoppedError,
    StopReason.CELL_SILENT: LinkBrakeError,
    StopReason.STATE_STALLED: LinkBrakeError,
    StopReason.LINK_DOWN: LinkBrakeError,
    StopReason.PROTECTIVE_STOP: ProtectiveStopError,
    StopReason.SAFEGUARD_STOP: SafeguardStopError,
    StopReason.EMERGENCY_STOP: EmergencyStopError,
    StopReason.FAULT: RobotFaultError,
    StopReason.VIOLATION: RobotFaultError,
    StopReason.PROGRAM_STOPPED: ProgramStoppedError,
    StopReason.SERVOJ_REFUSED: MoveError,
    StopReason.NO_EXTERNAL_CONTROL: MoveError,
    StopReason.LINK_LOST: ConnectionLostError,
    StopReason.LINK_ERROR: MoveError,
    StopReason.NONE: MoveError,
}
"""The one table from a stop reason to the error of a move that ended for it: the motion
layer raises it for a failed or stopped trajectory, the cell for a move aborted by the
robot's state (a safety stop's state is named as its reason)."""

STATE_STOPS = frozenset(
    {StopReason.PROTECTIVE_STOP, StopReason.SAFEGUARD_STOP, StopReason.EMERGENCY_STOP}
    | {StopReason.FAULT, StopReason.VIOLATION, StopReason.PROGRAM_STOPPED}
)
"""The reasons a state sample shows (the robot stopped the arm or the program)."""
LINK_BRAKES = frozenset(r for r, error in STOP_ERRORS.items() if error is LinkBrakeError)
"""Why the link process brakes a trajectory by itself (its :class:`Guard`)."""


def stop_reason(safety_mode: int, runtime_state: int) -> StopReason | None:
    """Why a trajectory cannot continue, from one state sample (``None``: it can)."""
    stop = SAFETY_STOPS.get(safety_mode)
    if stop is not None:
        return StopReason(stop)
    if runtime_state != RuntimeState.PLAYING:
        return StopReason.PROGRAM_STOPPED
    return None


# ----------------------------------------------------------------- requests


ControlMode = Literal["script", "urcap"]


@dataclass(frozen=True, slots=True)
class Dashboard:
    """One Dashboard request line; answered with the reply line (``str``)."""

    command: str


@dataclass(frozen=True, slots=True)
class Ping:
    """Is the link process's worker alive; answered ``"pong"``."""


@dataclass(frozen=True, slots=True)
class LeaveServo:
    """Leave servo mode (a held target after the last move); answered ``True``."""


@dataclass(frozen=True, slots=True)
class StartControl:
    """Start external control: the ``script`` upload or the ``urcap`` program; ``timeout``
    (s) for it to play. Answered ``True`` once it accepts commands."""

    mode: ControlMode
    program: str
    timeout: float


@dataclass(frozen=True, slots=True)
class StopControl:
    """Stop external control (braking a running trajectory first); answered ``True``."""

    mode: ControlMode


@dataclass(frozen=True, slots=True)
class ServoStop:
    """Stop any streamed trajectory and leave servo mode; answered whether it did."""


@dataclass(frozen=True, slots=True)
class SetOutput:
    """Set a digital (0/1) or analog (fraction of its range) output; answered whether the
    controller took it."""

    group: OutputGroup
    index: int
    value: float


@dataclass(frozen=True, slots=True)
class SetTool:
    """Set the TCP (flange frame, UR pose) and the payload (kg, centre of gravity m)."""

    tcp: tuple[float, ...]
    mass: float
    cog: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class TeachMode:
    """Enter (``on``) or leave teach mode (freedrive); answered whether it did."""

    on: bool


Request = (
    Dashboard | Ping | LeaveServo | StartControl | StopControl | ServoStop | SetOutput | SetTool
) | TeachMode
REQUESTS: tuple[type[Request], ...] = typing.get_args(Request)
"""Every request type: each side's handler table must cover all of them."""

REMOTE_QUERY = "is in remote control"
"""The Dashboard's Local/Remote query: a cell asks it every few hundred milliseconds in the
background (the pendant's switch is in no state stream)."""


def counts_as_sent(request: Request) -> bool:
    """Whether ``request`` counts in a link's ``messages_sent``: every request but
    :data:`REMOTE_QUERY`, which changes nothing and which the cell's background poll sends
    at moments of its own (a count of what a command sent must not depend on them)."""
    return not (isinstance(request, Dashboard) and request.command == REMOTE_QUERY)


# ----------------------------------------------------------------- trajectory messages
# (sent as (wire.TRAJ_START | TRAJ_REPLACE | TRAJ_STOP, message): not answered by a reply,
# the link process reports on the trajectory with wire.TRAJ messages)


@dataclass(frozen=True, slots=True)
class StartTrajectory:
    """Stream ``samples`` (``wire.pack_samples``: N joint vectors 2 ms apart) with servoJ."""

    id: int
    samples: tuple[int, bytes]
    lookahead_time: float
    gain: float
    guard: Guard


@dataclass(frozen=True, slots=True)
class ReplaceTrajectory:
    """Replace the samples not yet sent (from ``at_index`` of the trajectory; ``None``:
    from the next one)."""

    id: int
    samples: tuple[int, bytes]
    at_index: int | None


@dataclass(frozen=True, slots=True)
class StopTrajectory:
    """Brake the trajectory to rest along its path; ``reason``: a :class:`StopReason`'s
    value (the wire carries the string)."""

    id: int
    reason: str


# ----------------------------------------------------------------- replies

ErrorKind = Literal["robot", "timeout", "connection", "remote", "argument", "contract"]
ERROR_KINDS: dict[str, type[FxcellError]] = {
    "robot": RobotCommandError,
    "timeout": RobotTimeoutError,
    "connection": ConnectionLostError,
    "remote": NotInRemoteControlError,
    "argument": InvalidArgumentError,
    "contract": LinkContractError,
}
"""A failed request's error kind (what the link process replies) and the client's error."""


def reply_error(kind: str, message: str) -> FxcellError:
    """The typed error of a failed reply (an unknown kind: the robot refused it)."""
    return ERROR_KINDS.get(kind, RobotCommandError)(message)


# ----------------------------------------------------------------- value types


class LinkStatus(enum.StrEnum):
    STARTING = "starting"
    UP = "up"
    DOWN = "down"
    CLOSED = "closed"


@dataclass(frozen=True)
class Guard:
    """When and how a trajectory brakes by itself (sent with each trajectory)."""

    brake_acceleration: tuple[float, ...] = (4.0, 4.0, 4.0, 8.0, 8.0, 8.0)
    """Per-joint deceleration limit of a self-initiated stop (rad/s²)."""
    brake_jerk: float = 40.0
    """Jerk limit of a self-initiated stop (rad/s³)."""
    cell_timeout: float | None = 0.1
    """Brake when the client has sent nothing for this long (s; None: never)."""
    stall_timeout: float = 0.08
    """Brake when no state sample has arrived for this long (s)."""
    velocity: tuple[float, ...] = (math.pi,) * 3 + (2 * math.pi,) * 3
    """Per-joint speed limit of every setpoint (rad/s)."""
    path_acceleration: tuple[float, ...] = (0.7, 0.7, 0.7, 1.4, 1.4, 1.4)
    """The most the path itself accelerates (the moves' limits, rad/s²): a stop along the
    path leaves room for it under ``brake_acceleration``."""


@dataclass(frozen=True, slots=True)
class TrajectoryProgress:
    """Where a streamed trajectory is: sample index reached, actual joints, tracking error."""

    index: int
    total: int
    actual_q: tuple[float, ...] | None
    tracking_error: float
    time: float
    """Wall-clock time the report arrived."""
    timestamp: float | None = None
    """Controller time of the state sample for which the link sent sample ``index`` (None:
    not known); at a later sample it sends ``index`` plus the controller cycles between."""


TrajectoryStatus = Literal["completed", "stopped", "failed"]


@dataclass(frozen=True, slots=True)
class TrajectoryResult:
    """How a streamed trajectory ended.

    ``status``: ``completed`` (every sample sent), ``stopped`` (a stop was requested or
    the link's guard braked it) or ``failed``; ``reason`` says why (``NONE`` for a
    completed one), ``detail`` adds what the link knows (a ``LINK_ERROR``'s exception).
    """

    status: TrajectoryStatus
    reason: StopReason
    index: int
    total: int
    actual_q: tuple[float, ...] | None
    duration: float
    detail: str = ""

    @property
    def why(self) -> str:
        """The reason as the logs and errors show it (with the detail)."""
        return f"{self.reason.value}: {self.detail}" if self.detail else self.reason.value

    def error(self) -> type[FxcellError]:
        """The typed error of a move that ended so (see :data:`STOP_ERRORS`)."""
        return STOP_ERRORS[self.reason]


@dataclass(frozen=True, slots=True)
class ControllerInfo:
    """What the controller says about itself (``None``: it could not be read)."""

    controller_version: str | None = None
    serial: str | None = None
    robot_model: str | None = None

    def as_dict(self) -> dict[str, str]:
        """The fields that were read, by name (the Cell's ``controller_info``)."""
        fields = {
            "controller_version": self.controller_version,
            "serial": self.serial,
            "robot_model": self.robot_model,
        }
        return {key: value for key, value in fields.items() if value is not None}
