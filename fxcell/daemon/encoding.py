"""Turning Cell results, events and errors into JSON, and HTTP statuses for errors."""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from fxcell import errors

# Most specific first: the first matching class decides the HTTP status.
_STATUS: tuple[tuple[type[BaseException], int], ...] = (
    (errors.NotAuthorizedError, 401),
    (errors.ControlHeldError, 409),
    (errors.RemoteError, 400),
    (errors.InvalidArgumentError, 422),
    (errors.InvalidStateError, 409),
    (errors.NotInRemoteControlError, 409),
    (errors.MoveInProgressError, 409),
    (errors.MoveStoppedError, 409),
    (errors.MoveError, 409),  # did not reach its goal (e.g. TrackingError)
    (errors.SafetyStopError, 409),
    (errors.PlanningError, 422),
    (errors.RobotTimeoutError, 504),
    (errors.ConnectionLostError, 503),
    (errors.RobotCommandError, 502),
    (errors.FxcellError, 500),
)
_DETAIL_ATTRS = ("command", "state", "allowed", "next_step", "remaining", "failures")


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
    """A JSON-compatible copy of ``value`` (string enums by value, other enums by name,
    arrays as lists, NaN as null)."""
    if isinstance(value, enum.Enum):
        return str(value.value) if isinstance(value, str) else value.name
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [jsonable(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Path):
        return str(value)
    model_dump = getattr(value, "model_dump", None)  # pydantic models (configuration)
    if callable(model_dump):
        return jsonable(model_dump())
    tolist = getattr(value, "tolist", None)  # numpy arrays and scalars
    if callable(tolist):
        return jsonable(tolist())
    as_dict = getattr(value, "as_dict", None)
    if callable(as_dict):
        return jsonable(as_dict())
    if hasattr(value, "position") and hasattr(value, "quaternion"):  # geometry.Pose
        return {
            "position": jsonable(value.position),
            "quaternion": jsonable(value.quaternion),
            "ur": jsonable(value.as_ur()),
        }
    return str(value)
