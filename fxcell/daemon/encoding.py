"""Turning Cell results, events and errors into JSON, and HTTP statuses for errors."""

from __future__ import annotations

from typing import Any

from fxcell import errors
from fxcell.jsonable import to_jsonable

# Most specific first: the first matching class decides the HTTP status.
_STATUS: tuple[tuple[type[BaseException], int], ...] = (
    (errors.NotAuthorizedError, 401),
    (errors.ControlHeldError, 409),
    (errors.RemoteError, 400),
    (errors.InvalidArgumentError, 422),
    (errors.InvalidStateError, 409),
    (errors.UnsupportedCommandError, 409),
    (errors.NotInRemoteControlError, 409),
    (errors.MoveInProgressError, 409),
    (errors.MoveStoppedError, 409),
    (errors.MoveError, 409),  # did not reach its goal (e.g. TrackingError)
    (errors.SafetyStopError, 409),
    (errors.PlanningError, 422),
    # refused for the state of the cell, its gripper or a zone: nothing moved
    (errors.HoldingError, 409),
    (errors.GripperNotPoweredError, 409),
    (errors.GripperNotActivatedError, 409),
    (errors.NothingGraspedError, 409),
    (errors.ObjectLostError, 409),
    (errors.InterlockError, 409),
    (errors.UncalibratedError, 409),
    (errors.GripperError, 502),  # the gripper failed (a fault): the device's doing
    (errors.IOTimeoutError, 504),
    (errors.RobotTimeoutError, 504),
    (errors.ConnectionLostError, 503),
    (errors.RobotCommandError, 502),
    (errors.JobStateError, 409),
    (errors.JobAnswerError, 422),
    (errors.MachineError, 502),
    (errors.JobStoreError, 500),  # the job database is unreadable: the daemon's fault
    (errors.JobError, 409),  # e.g. an unfinished run blocks a new one
    (errors.CameraNotConfiguredError, 409),
    (errors.CameraError, 502),
    (errors.FxcellError, 500),
)
_DETAIL_ATTRS = (
    "command",
    "state",
    "allowed",
    "next_step",
    "remaining",
    "failures",
    "kind",
    "argument",
)


def http_status(exc: BaseException) -> int:
    if isinstance(exc, errors.RemoteError) and exc.status >= 400:
        return exc.status
    for cls, status in _STATUS:
        if isinstance(exc, cls):
            return status
    return 500


def error_info(exc: BaseException) -> dict[str, Any]:
    """``{"type", "message", "status", "detail"}`` for an error; RemoteCell rebuilds it."""
    detail = {a: jsonable(getattr(exc, a)) for a in _DETAIL_ATTRS if hasattr(exc, a)}
    name = type(exc).__name__ if isinstance(exc, errors.FxcellError) else "FxcellError"
    message = str(exc) if isinstance(exc, errors.FxcellError) else f"internal error: {exc!r}"
    return {"type": name, "message": message, "status": http_status(exc), "detail": detail}


def jsonable(value: Any) -> Any:
    """A JSON-compatible copy of ``value`` for an HTTP answer (see :func:`to_jsonable`)."""
    return to_jsonable(value, api=True)
