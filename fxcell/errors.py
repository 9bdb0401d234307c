"""The one exception hierarchy of fxcell.

Every error the public API raises derives from :class:`FxcellError`. Errors that
reject bad input also derive from :class:`ValueError` so that generic callers can
catch them the usual way. Nothing from ur_rtde (``RuntimeError``) and no bare
``asyncio.CancelledError`` leaks out of the public API: they are translated here.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping


class FxcellError(Exception):
    """Root of every error fxcell raises."""


# ----------------------------------------------------------------- configuration


class ConfigError(FxcellError, ValueError):
    """A configuration file or value is invalid; the message names the bad key."""


class CalibrationError(FxcellError, ValueError):
    """A calibration (UR's ``calibration.conf`` or the controller's kinematics info) is
    unreadable or malformed."""


class UncalibratedError(FxcellError):
    """A pose move was refused: the arm's calibration could not be read from the controller
    and the configuration does not accept the nominal model
    (``robot.accept_nominal_kinematics``); nothing was sent."""


# ----------------------------------------------------------------- bad input


class InvalidArgumentError(FxcellError, ValueError):
    """An argument is malformed or out of range; nothing was sent to the robot."""


class InvalidFactorError(InvalidArgumentError):
    """A velocity or acceleration factor is not a finite number in (0, 1]."""


class MoveTooLongError(InvalidArgumentError):
    """The move would take longer than ``limits.max_move_duration``; nothing was sent."""


class InvalidTargetError(InvalidArgumentError):
    """A joint or pose target is malformed, non-finite or outside the joint limits."""


class UnreachableError(InvalidTargetError):
    """No inverse-kinematics solution exists for a pose (within the joint limits)."""


class SingularityError(InvalidTargetError):
    """The target or the path to it passes through a kinematic singularity."""


class CollisionError(InvalidTargetError):
    """The target, or every path to it, is in collision with the cell or the robot."""


class PlanningError(FxcellError):
    """The planner found no collision-free path in its time budget."""


# ----------------------------------------------------------------- state and robot


class InvalidStateError(FxcellError):
    """A command is not allowed in the cell's current state; nothing was sent.

    ``next_step`` says what the operator does to get on from ``state``.
    """

    def __init__(
        self, command: str, state: str, allowed: Iterable[str], next_step: str = ""
    ) -> None:
        self.command = command
        self.state = state
        self.allowed = tuple(allowed)
        self.next_step = next_step
        needs = ", ".join(self.allowed) or "no state"
        hint = f": {next_step}" if next_step else ""
        super().__init__(
            f"{command}() is refused: the robot is {state}{hint} ({command} needs {needs})"
        )


class UnsupportedCommandError(FxcellError):
    """The cell's robot kind cannot do this command (its capabilities,
    :mod:`fxcell.link.capabilities`); nothing was sent."""

    def __init__(self, command: str, kind: str) -> None:
        self.command = command
        self.kind = kind
        super().__init__(f"{command}() is not supported by a {kind} robot")


class NotInRemoteControlError(FxcellError):
    """The teach pendant is in Local control: network commands are refused."""


class RobotCommandError(FxcellError):
    """The controller refused or failed a command (reply quoted in the message)."""


class RobotCommandStatusError(RobotCommandError):
    """The controller failed a command with a status code (a Ned2's ``CommandStatus``:
    -3 aborted, -4 stopped, -113 calibration not done, ...)."""

    def __init__(self, code: int, detail: str) -> None:
        self.code = code
        self.detail = detail
        super().__init__(f"{detail} (status {code})")

    def __reduce__(self) -> tuple[type[RobotCommandStatusError], tuple[int, str]]:
        return (type(self), (self.code, self.detail))


class SafetyStopError(FxcellError):
    """A safety stop is active or happened during the command."""


class ProtectiveStopError(SafetyStopError):
    """The robot is (or went) in protective stop."""


class ProtectiveStopUnlockTooSoonError(ProtectiveStopError):
    """The controller refuses to unlock a protective stop within 5 s of it."""

    def __init__(self, remaining: float) -> None:
        self.remaining = remaining
        super().__init__(
            f"cannot unlock the protective stop for another {remaining:.2f} s "
            "(the controller requires 5 s after the stop; pass wait=True to wait)"
        )


class SafeguardStopError(SafetyStopError):
    """A safeguard stop (external safety input) is active."""


class EmergencyStopError(SafetyStopError):
    """An emergency stop is active."""


class RobotFaultError(SafetyStopError):
    """The safety system reports a fault or a violation."""


class RobotTimeoutError(FxcellError, TimeoutError):
    """The robot did not confirm a command's effect within its timeout."""


class ConnectionLostError(FxcellError, ConnectionError):
    """The link to the robot controller is down (or dropped during the command)."""


class RobotLinkError(ConnectionLostError):
    """The robot-link process failed; the message collects what failed per client."""

    def __init__(self, message: str, failures: Mapping[str, str] | None = None) -> None:
        self.failures = dict(failures or {})
        detail = "; ".join(f"{part}: {why}" for part, why in self.failures.items())
        super().__init__(f"{message}: {detail}" if detail else message)


class LinkContractError(RobotLinkError):
    """The robot-link process and its client do not speak the same contract: a different
    wire version (a half-updated install) or a message neither side knows. Nothing was
    sent to the robot."""


# ----------------------------------------------------------------- motion


class MoveError(FxcellError):
    """A move failed while executing."""


class MoveStoppedError(MoveError):
    """The move was stopped (``stop()``, cancellation, or a safety event) before the target.

    ``result`` holds the move's :class:`~fxcell.motion.moves.MoveResult` (where it came to rest)
    when the move braked under fxcell's control.
    """

    def __init__(self, message: str, result: object | None = None) -> None:
        self.result = result
        super().__init__(message)


class LinkBrakeError(MoveStoppedError):
    """The robot-link process braked the move by itself along its path: the state stream
    stalled, the cell went silent or the link went down. The arm is at rest where it braked;
    nothing else happened, so the move can simply be made again (pick, place and the job do
    that by themselves)."""


class MoveInProgressError(MoveError):
    """Another move is already running and the caller did not ask to queue."""


class TrackingError(MoveError):
    """The robot did not follow the planned trajectory within tolerance."""


# ----------------------------------------------------------------- recorder, daemon


class RecorderError(FxcellError):
    """The MCAP recorder cannot write or read a log."""


class RemoteError(FxcellError):
    """The daemon refused a request; ``status`` is the HTTP status code."""

    def __init__(self, message: str, status: int = 0) -> None:
        self.status = status
        super().__init__(message)


class NotAuthorizedError(RemoteError):
    """The request lacks a valid bearer token."""


class ControlHeldError(RemoteError):
    """Another client holds control of the cell."""


# ----------------------------------------------------------------- embedded simulator


class SimulatorError(FxcellError):
    """The embedded controller simulator did not start, stopped, or refused a request."""


# ----------------------------------------------------------------- cell


class ProgramStoppedError(MoveStoppedError):
    """The control program stopped during a move (teach-pendant stop, or it ended)."""


# ----------------------------------------------------------------- gripper


class GripperError(FxcellError):
    """The robot kind's gripper (the UR3e's Robotiq Hand-E through the URCap's socket, the
    Ned2's Gripper 1 through its TCP server) failed a command."""


class GripperNotPoweredError(GripperError):
    """The arm is off, so the tool flange (and the gripper) has no power; nothing was sent."""


class GripperNotActivatedError(GripperError):
    """The gripper is not activated (the Hand-E: ``STA`` is not 3; the Ned2: no Gripper 1
    on its tool port): call ``activate()`` first."""


class GripperFaultError(GripperError):
    """The gripper reports a fault (``FLT``); it stays faulted until re-activated."""

    def __init__(self, code: int, message: str = "") -> None:
        self.code = code
        super().__init__(message or f"the gripper reports fault 0x{code:02X}; re-activate it")


class NothingGraspedError(GripperError):
    """An object was expected between the fingers, but they closed on nothing."""


class UnsupportedGripError(InvalidArgumentError):
    """The robot kind's gripper cannot do this opening, speed or force (its
    :class:`~fxcell.link.gripper.GripperSpec`); nothing was sent."""

    def __init__(self, kind: str, argument: str, message: str) -> None:
        self.kind = kind
        self.argument = argument
        super().__init__(message)


class HoldingError(GripperError):
    """Refused for what the gripper holds: a pick while it holds something, a place while it
    holds nothing or an object the station does not take; nothing moved."""


class ObjectLostError(GripperError):
    """The object the gripper held is no longer between its fingers."""


# ----------------------------------------------------------------- layout, IO, teach


class LayoutError(InvalidArgumentError):
    """A station, slot or taught frame of the cell layout is unknown or malformed."""


class UnknownStationError(LayoutError):
    """A station name the layout does not have; the message lists the known ones."""


class SlotError(LayoutError):
    """A slot name that is malformed or outside its station's grid; nothing moved."""


class UnknownSignalError(InvalidArgumentError):
    """An IO signal name the configuration does not have (``io.signals``), or a value the
    signal cannot take; the message lists the known names."""


class IOTimeoutError(FxcellError, TimeoutError):
    """An IO signal did not reach the awaited value in time."""


class UnknownPositionError(InvalidArgumentError):
    """A taught position name that does not exist; the message lists the known ones."""


class InterlockError(FxcellError):
    """A move into a zone was refused (or stopped) because the zone's interlock signal is on,
    e.g. the fusion machine reports busy; nothing moved into the zone."""


# ----------------------------------------------------------------- job


class JobError(FxcellError):
    """The fusion-machine job failed or refused a request."""


class JobSpecError(JobError, InvalidArgumentError):
    """A run file or run dict is invalid; nothing moved.

    ``sample`` names the sample (its id, or ``#n`` counting from 1 when it has none) and
    ``field`` the offending field, when the problem is in one sample.
    """

    def __init__(self, message: str, sample: str | None = None, field: str | None = None) -> None:
        self.sample = sample
        self.field = field
        where = ""
        if sample is not None:
            where = f"sample {sample}" + (f", field {field!r}" if field else "") + ": "
        super().__init__(where + message)


class JobStateError(JobError):
    """A job command is not allowed in the job's current state; nothing changed."""

    def __init__(self, command: str, state: str, allowed: Iterable[str]) -> None:
        self.command = command
        self.state = state
        self.allowed = tuple(allowed)
        super().__init__(
            f"job {command}() is refused: the job is {state} "
            f"({command} needs {', '.join(self.allowed) or 'no state'})"
        )


class JobAnswerError(JobError, ValueError):
    """A recovery answer is missing, or names a place that is not one of the question's choices."""


class JobStoreError(JobError):
    """The job database is unreadable, or its records contradict each other."""


class MachineError(JobError):
    """The fusion machine reports an error, or did not answer as its protocol requires."""


# ----------------------------------------------------------------- camera


class CameraError(FxcellError):
    """The camera gave no frame: not configured, cannot be opened, or too slow (the
    message says which and where it was looked for)."""


class CameraNotConfiguredError(CameraError):
    """No camera is configured (``vision.camera.source`` is null)."""
