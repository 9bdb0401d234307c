"""``cell.io``: the controller's IO by the names the configuration gives them.

``io.signals`` in the configuration maps names to addresses (``machine_done: DI2``); task
code uses only the names. Outputs are set through the link (``set_output``: the UR's RTDE IO
recipe, ur_rtde's ``RTDEIOInterface`` in the robot-link process; the Ned2's IO panel
service) and confirmed on the state stream; inputs and outputs are read from the newest
state sample. A robot kind that has only some addresses (the Ned2: ``DI1``-``DI5``,
``DO1``-``DO4``) names them (``RobotKind.signals``); a signal configured at another address
is refused, naming the kind, before anything is sent. Every set and wait is the Cell's command of
that name (``io_set``, ``io_wait_for``): recorded, and refused by the command table's guard
before anything is sent; the recorder also logs the IO bits on ``/robot/io`` whenever one
changes.
"""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING

from fxcell.errors import IOTimeoutError, RobotCommandError, UnknownSignalError
from fxcell.signals import Signal, parse_signal

if TYPE_CHECKING:
    from fxcell.cell.context import CellContext

Value = bool | float


class CellIO:
    """The configured IO signals of a :class:`~fxcell.cell.Cell` (``cell.io``)."""

    def __init__(
        self, context: CellContext, addresses: frozenset[str] | None = None, kind: str = ""
    ) -> None:
        self._context = context
        self._addresses = addresses
        self._kind = kind
        self._signals = {
            name: parse_signal(address) for name, address in context.config().io.signals.items()
        }

    @property
    def names(self) -> list[str]:
        """The configured signal names."""
        return sorted(self._signals)

    def signal(self, name: str) -> Signal:
        """The signal called ``name``, or :class:`UnknownSignalError` listing the known ones."""
        try:
            signal = self._signals[name]
        except (KeyError, TypeError):
            known = ", ".join(self.names) or "none (configure io.signals)"
            raise UnknownSignalError(f"no IO signal {name!r} (known: {known})") from None
        if self._addresses is not None and signal.address not in self._addresses:
            raise UnknownSignalError(
                f"{name} is configured at {signal.address}, which a {self._kind} robot does "
                f"not have (its IO: {', '.join(sorted(self._addresses))})"
            )
        return signal

    def get(self, name: str) -> Value:
        """The signal's value in the newest state sample (bool, or V/A for analog)."""
        signal = self.signal(name)
        return signal.read(self._context.sample())

    def snapshot(self) -> dict[str, Value]:
        """Every configured signal's current value (empty while no state arrives)."""
        sample = self._context.latest()
        if sample is None:
            return {}
        return {
            name: s.read(sample)
            for name, s in sorted(self._signals.items())
            if self._addresses is None or s.address in self._addresses
        }

    def check_set(self, name: str, value: object) -> tuple[Signal, bool | float]:
        """The output ``name`` and ``value`` as it takes it, or the error refusing them."""
        signal = self.signal(name)
        return signal, signal.check_value(value)

    def check_wait(self, name: str, value: object) -> Signal:
        """The signal ``name`` if it can be waited for at ``value``, else the error."""
        signal = self.signal(name)
        if not signal.digital and isinstance(value, bool):
            raise UnknownSignalError(f"{name} ({signal.address}) is analog: wait for a number")
        return signal

    async def set(self, name: str, value: Value) -> None:
        """Set output ``name`` (digital: true/false; analog: fraction 0..1 of its range);
        returns once the controller reports a digital output changed."""
        cell = self._context
        async with cell.command("io_set", signal=name, value=value):
            signal, checked = self.check_set(name, value)
            ok = await cell.link().set_output(
                signal.group, signal.index, float(checked), within=cell.timeout()
            )
            if not ok:
                raise RobotCommandError(f"the controller refused to set {name} ({signal.address})")
            if signal.digital:
                await self._until(signal, checked, cell.timeout(), f"{name} to become {checked}")

    async def wait_for(self, name: str, value: Value, timeout: float) -> float:  # noqa: ASYNC109
        """Wait until digital signal ``name`` reads ``value`` (or an analog one reaches at
        least ``value``); returns the seconds waited, raises :class:`IOTimeoutError`."""
        cell = self._context
        async with cell.command("io_wait_for", signal=name, value=value, timeout=timeout) as out:
            signal = self.check_wait(name, value)
            started = time.monotonic()
            await self._until(signal, value, timeout, f"{name} to become {value}")
            out["result"] = waited = time.monotonic() - started
            return waited

    async def _until(self, signal: Signal, value: Value, limit: float, what: str) -> None:
        cell = self._context

        def reached() -> bool:
            sample = cell.latest()
            if sample is None:
                return False
            got = signal.read(sample)
            if signal.digital:
                return got == bool(value)
            return float(got) >= float(value)

        if reached():
            return
        try:
            async with asyncio.timeout(limit):
                with cell.states(8) as states:
                    async for _ in states:
                        if reached():
                            return
        except TimeoutError:
            raise IOTimeoutError(f"waited {limit:g} s for {what}") from None
