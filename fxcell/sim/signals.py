"""Names of the controller's IO signals, as the simulator's CLI and control port take them.

``DI5`` standard digital input 5 (a bare ``5`` means the same), ``CI2`` configurable input 2,
``TI0`` tool input 0, ``AI0`` standard analog input 0, ``TAI1`` tool analog input 1; the
outputs ``DO``, ``CO``, ``TO`` likewise. Bits in RTDE's ``actual_digital_input_bits`` and
``actual_digital_output_bits``: standard 0-7, configurable 8-15, tool 16-17.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from fxcell.errors import InvalidArgumentError

# kind -> (count, first bit in the 64-bit digital word; None for analog)
KINDS: dict[str, tuple[int, int | None]] = {
    "DI": (8, 0),
    "CI": (8, 8),
    "TI": (2, 16),
    "AI": (2, None),
    "TAI": (2, None),
    "DO": (8, 0),
    "CO": (8, 8),
    "TO": (2, 16),
}
INPUT_KINDS = frozenset({"DI", "CI", "TI", "AI", "TAI"})
_NAME = re.compile(r"^([A-Za-z]*)([0-9]+)$")
_TRUE = frozenset({"1", "true", "on", "high"})
_FALSE = frozenset({"0", "false", "off", "low"})


@dataclass(frozen=True)
class Signal:
    """One IO signal: its kind (``DI``, ``AI``, ``DO``, ...) and index."""

    kind: str
    index: int

    def __str__(self) -> str:
        return f"{self.kind}{self.index}"

    @property
    def is_input(self) -> bool:
        return self.kind in INPUT_KINDS

    @property
    def is_digital(self) -> bool:
        return KINDS[self.kind][1] is not None

    @property
    def bit(self) -> int:
        """Its bit in RTDE's digital input/output word (digital signals only)."""
        first = KINDS[self.kind][1]
        if first is None:
            raise InvalidArgumentError(f"{self} is analog: it has no bit")
        return first + self.index


def parse_signal(text: str) -> Signal:
    """``"DI5"``, ``"5"``, ``"ci2"``, ``"AI0"``, ``"DO0"`` → :class:`Signal`."""
    m = _NAME.match(text.strip())
    if m is None:
        raise InvalidArgumentError(
            f"not a signal name: {text!r} (e.g. DI5 or 5, CI2, TI0, AI0, TAI1, DO0, CO1, TO0)"
        )
    kind = m.group(1).upper() or "DI"
    if kind not in KINDS:
        raise InvalidArgumentError(
            f"unknown signal kind {m.group(1)!r} in {text!r} (known: {', '.join(KINDS)})"
        )
    index = int(m.group(2))
    count = KINDS[kind][0]
    if index >= count:
        raise InvalidArgumentError(f"{kind} has signals 0..{count - 1}; {text!r} is not one")
    return Signal(kind, index)


def parse_value(signal: Signal, text: str) -> float:
    """A signal value: 0/1 (also true/false, on/off) for digital, a finite float for analog."""
    word = text.strip().lower()
    if signal.is_digital:
        if word in _TRUE:
            return 1.0
        if word in _FALSE:
            return 0.0
        raise InvalidArgumentError(f"{signal} is digital: its value is 0 or 1, not {text!r}")
    try:
        value = float(word)
    except ValueError:
        raise InvalidArgumentError(f"{signal} is analog: not a number: {text!r}") from None
    if not math.isfinite(value):
        raise InvalidArgumentError(f"{signal}: the value must be finite, not {text!r}")
    return value
