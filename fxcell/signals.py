"""The controller's IO by short addresses: ``DI2`` (standard digital input 2), ``CO1``, ``AO1``.

===== ============================== ===== ====================================
name  what                            range bit in ``actual_digital_*_bits``
===== ============================== ===== ====================================
DIn   standard digital input          0..7  n
DOn   standard digital output         0..7  n
CIn   configurable digital input      0..7  8 + n
COn   configurable digital output     0..7  8 + n
TIn   tool digital input              0..1  16 + n
TOn   tool digital output             0..1  16 + n
AIn   standard analog input (V or A)  0..1  -
AOn   standard analog output          0..1  -
===== ============================== ===== ====================================

Task code never uses these directly: the configuration names each signal
(``io.signals: {machine_done: DI2}``) and ``cell.io`` takes those names.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal

from fxcell.errors import InvalidArgumentError
from fxcell.protocol import RobotState

Group = Literal["standard", "configurable", "tool", "analog"]

_PATTERN = re.compile(r"^(D|C|T|A)(I|O)([0-9])$")
_GROUPS: dict[str, tuple[Group, int, int]] = {
    # letter: group, bit offset, count
    "D": ("standard", 0, 8),
    "C": ("configurable", 8, 8),
    "T": ("tool", 16, 2),
    "A": ("analog", 0, 2),
}


@dataclass(frozen=True)
class Signal:
    """One IO point of the controller."""

    address: str
    """``DI2``, ``CO1``, ... (canonical, upper case)."""
    group: Group
    output: bool
    index: int

    @property
    def digital(self) -> bool:
        return self.group != "analog"

    @property
    def bit(self) -> int:
        """Its bit in ``actual_digital_input_bits``/``actual_digital_output_bits``."""
        return _GROUPS[self.address[0]][1] + self.index

    def read(self, state: RobotState) -> bool | float:
        """The signal's value in a state sample (bool for digital, V or A for analog)."""
        if self.digital:
            bits = state.digital_output_bits if self.output else state.digital_input_bits
            return bool((bits >> self.bit) & 1)
        prefix = "standard_analog_output" if self.output else "standard_analog_input"
        return float(getattr(state, f"{prefix}{self.index}"))

    def check_value(self, value: object) -> bool | float:
        """``value`` as this output takes it, or :class:`InvalidArgumentError`."""
        if not self.output:
            raise InvalidArgumentError(f"{self.address} is an input: it cannot be set")
        if self.digital:
            if isinstance(value, bool) or value in (0, 1):
                return bool(value)
            raise InvalidArgumentError(
                f"{self.address} is digital: give true or false, not {value!r}"
            )
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise InvalidArgumentError(f"{self.address} is analog: give a number, not {value!r}")
        if not 0.0 <= float(value) <= 1.0:
            raise InvalidArgumentError(
                f"{self.address}: {value!r} is outside [0, 1] (fraction of the output's range)"
            )
        return float(value)


def parse_signal(address: str) -> Signal:
    """``"DI2"`` → :class:`Signal`; :class:`InvalidArgumentError` for anything else."""
    m = _PATTERN.match(address.strip().upper()) if isinstance(address, str) else None
    if m is None:
        raise InvalidArgumentError(
            f"not an IO address: {address!r} "
            "(DI0-7, DO0-7, CI0-7, CO0-7, TI0-1, TO0-1, AI0-1, AO0-1)"
        )
    letter, direction, digit = m.groups()
    group, _, count = _GROUPS[letter]
    index = int(digit)
    if index >= count:
        raise InvalidArgumentError(f"{address!r}: {group} IO has points 0..{count - 1}")
    return Signal(f"{letter}{direction}{index}", group, direction == "O", index)
