"""JSON-compatible copies of fxcell values: command arguments, results, motion records.

One encoding for the Cell's command events and the flight recorder: numpy arrays become
lists, enums their values, dataclasses dicts, poses ``{position, quaternion}``, exceptions
``"Type: message"``; non-finite floats become strings (``"nan"``) so the output stays valid
JSON; anything else its ``repr``.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from pathlib import PurePath
from typing import Any


def to_jsonable(value: Any) -> Any:
    """Turn command arguments, results and motion data into JSON-compatible values.

    numpy arrays become lists, enums their values (names for string enums),
    dataclasses dicts, poses ``{position, quaternion}``; unknown objects their ``repr``.
    Non-finite floats become strings so the output stays valid JSON.
    """
    if value is None or isinstance(value, bool | int | str):
        return value.value if isinstance(value, enum.Enum) else value
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, enum.Enum):
        return to_jsonable(value.value)
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [to_jsonable(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, PurePath):
        return str(value)
    tolist = getattr(value, "tolist", None)  # numpy arrays and scalars
    if callable(tolist):
        return to_jsonable(tolist())
    if hasattr(value, "position") and hasattr(value, "quaternion"):  # fxcell.geometry.Pose
        return {
            "position": to_jsonable(value.position),
            "quaternion": to_jsonable(value.quaternion),
        }
    if isinstance(value, BaseException):
        return f"{type(value).__name__}: {value}"
    return repr(value)
