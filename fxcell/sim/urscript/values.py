"""The values a program computes with and what the interpreter and built-ins share:
poses, the checks that turn a value into a number, the binary operators, a wait."""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass
from typing import Any

from fxcell.sim.motion import MotionToken
from fxcell.sim.urscript.errors import URScriptError


class PoseValue(list[float]):
    """A ``p[...]`` value: a list that remembers it is a pose."""


def format_value(value: object) -> str:
    if isinstance(value, bool):
        return "True" if value else "False"
    if isinstance(value, PoseValue):
        return "p[" + ", ".join(format_value(v) for v in value) + "]"
    if isinstance(value, list):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def as_number(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise URScriptError(f"{what}: expected a number, got {format_value(value)}")
    return float(value)


def as_six(value: object, what: str) -> list[float]:
    if not isinstance(value, list) or len(value) != 6:
        raise URScriptError(f"{what}: expected 6 values, got {format_value(value)}")
    return [as_number(v, what) for v in value]


def binary_op(op: str, a: Any, b: Any) -> Any:
    if op == "and":
        return bool(a) and bool(b)
    if op == "or":
        return bool(a) or bool(b)
    if op == "==":
        return bool(a == b)
    if op == "!=":
        return bool(a != b)
    if isinstance(a, list) and isinstance(b, list) and op in "+-":
        if len(a) != len(b):
            raise URScriptError(f"'{op}' on lists of different lengths")
        out = [binary_op(op, x, y) for x, y in zip(a, b, strict=True)]
        return PoseValue(out) if isinstance(a, PoseValue) or isinstance(b, PoseValue) else out
    if op == "+" and isinstance(a, str) and isinstance(b, str):
        return a + b
    x, y = as_number(a, op), as_number(b, op)
    both_int = isinstance(a, int) and isinstance(b, int)
    if op in ("<", "<=", ">", ">="):
        return {"<": x < y, "<=": x <= y, ">": x > y, ">=": x >= y}[op]
    if op in ("/", "%") and y == 0:
        raise URScriptError("division by zero")
    if both_int:
        ia, ib = int(a), int(b)
        if op == "/":
            q = abs(ia) // abs(ib)  # integer division truncates toward zero
            return q if (ia >= 0) == (ib >= 0) else -q
        if op == "%":
            return int(math.fmod(ia, ib))
        return {"+": ia + ib, "-": ia - ib, "*": ia * ib}[op]
    if op == "%":
        return math.fmod(x, y)
    return {"+": x + y, "-": x - y, "*": x * y, "/": x / y}[op]


def index_of(container: list[Any] | str, index: Any) -> int:
    if isinstance(index, bool) or not isinstance(index, int):
        raise URScriptError(f"index must be an integer, got {format_value(index)}")
    if not 0 <= index < len(container):
        raise URScriptError(f"index {index} out of range (length {len(container)})")
    return index


Wait = MotionToken | float | None  # a motion, a controller time, or the next cycle
Gen = Generator[Wait, None, Any]


@dataclass
class Waiting:
    """A built-in's result that makes the program wait (a motion, a time, the next cycle)."""

    wait: Wait


class HaltSignal(Exception):  # noqa: N818 (control flow, not an error)
    """``halt()``: the program ends here."""
