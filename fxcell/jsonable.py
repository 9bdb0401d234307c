"""JSON-compatible copies of fxcell values: command arguments, results, motion records.

One encoding for the Cell's command events, the flight recorder and (with ``api=True``) the
daemon's HTTP answers: numpy arrays become lists, enums their values, dataclasses dicts,
poses ``{position, quaternion}``, exceptions ``"Type: message"``; non-finite floats become
strings (``"nan"``) so the output stays valid JSON; anything else its ``repr``.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Mapping
from pathlib import PurePath
from typing import Any


def to_jsonable(value: Any, *, api: bool = False) -> Any:
    """Turn command arguments, results and motion data into JSON-compatible values.

    numpy arrays become lists, dataclasses and pydantic models dicts, poses
    ``{position, quaternion}``, exceptions ``"Type: message"``; unknown objects their ``repr``.
    Records (``api=False``): enums by value (names for string enums), non-finite floats as
    strings (``"nan"``), so nothing is lost. The daemon's answers (``api=True``): integer
    enums by name, non-finite floats as ``null``, poses also as their UR vector.
    """
    if isinstance(value, enum.Enum):
        if api and not isinstance(value, str):
            return value.name
        return to_jsonable(value.value, api=api)
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        return None if api else repr(value)
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v, api=api) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [to_jsonable(v, api=api) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: to_jsonable(getattr(value, f.name), api=api) for f in dataclasses.fields(value)
        }
    if isinstance(value, PurePath):
        return str(value)
    for method in ("model_dump", "tolist", "as_dict"):  # pydantic models, numpy values, ...
        convert = getattr(value, method, None)
        if callable(convert):
            return to_jsonable(convert(), api=api)
    if hasattr(value, "position") and hasattr(value, "quaternion"):  # fxcell.geometry.Pose
        out = {
            "position": to_jsonable(value.position, api=api),
            "quaternion": to_jsonable(value.quaternion, api=api),
        }
        if api:
            out["ur"] = to_jsonable(value.as_ur(), api=api)
        return out
    if isinstance(value, BaseException):
        return f"{type(value).__name__}: {value}"
    return repr(value) if not api else str(value)
