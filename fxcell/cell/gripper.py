"""``cell.gripper``: the Robotiq Hand-E in SI units, through the Robotiq URCap's socket.

Widths are finger openings in m (0 closed .. 0.050 open), speeds in m/s (0.020..0.150),
forces in N (20..185); the URCap's 0..255 registers are an implementation detail. Every
command is recorded like an arm command (``gripper_activate``, ``gripper_move``, ...) and is
refused before anything is sent while the arm is off (the tool flange has no power).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from transitions import Machine

from fxcell.cell.statemachine import STATECHART_DIR, machine_states, read_statechart
from fxcell.commands import GRIP_FORCE_RANGE, GRIP_SPEED_RANGE, GRIP_WIDTH_RANGE
from fxcell.errors import (
    ConnectionLostError,
    GripperFaultError,
    GripperNotActivatedError,
    GripperNotPoweredError,
    InvalidArgumentError,
    NothingGraspedError,
    ObjectLostError,
    RobotTimeoutError,
)
from fxcell.events import DeviceEvent
from fxcell.link.gripper import URCapGripperClient
from fxcell.protocol import RobotMode
from fxcell.results import GripResult

if TYPE_CHECKING:
    from fxcell.cell.cell import Cell

STROKE = GRIP_WIDTH_RANGE[1]  # m, Hand-E fully open (0.050)
SPEED_RANGE = GRIP_SPEED_RANGE  # m/s
FORCE_RANGE = GRIP_FORCE_RANGE  # N
POLL = 0.01  # s between two status reads while the fingers move
ACTIVATION_TIMEOUT = 10.0  # s
_POWERED = (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)


def _register(value: float, lo: float, hi: float) -> int:
    return max(0, min(255, round(255.0 * (value - lo) / (hi - lo))))


def _width(position: int) -> float:
    return STROKE * (1.0 - max(0, min(255, position)) / 255.0)


GRIPPER_CHART = STATECHART_DIR / "gripper.yaml"


class _Model:
    state: str


class GripperState:
    """The gripper's companion state machine (``statecharts/gripper.yaml``), as fxcell knows
    it from the commands and reads it sent; ``on_change(source, dest, trigger)``."""

    def __init__(self, on_change: Callable[[str, str, str], None]) -> None:
        chart = read_statechart(GRIPPER_CHART)
        self._model = _Model()
        self._machine = Machine(
            model=self._model,
            states=machine_states(chart.states),
            transitions=chart.transitions,
            initial=chart.initial,
            auto_transitions=False,
            ignore_invalid_triggers=True,
        )
        self._on_change = on_change

    @property
    def state(self) -> str:
        return self._model.state

    def fire(self, trigger: str) -> None:
        source = self.state
        self._model.trigger(trigger)  # type: ignore[attr-defined]
        if self.state != source:
            self._on_change(source, self.state, trigger)


class Gripper:
    """The cell's Hand-E (``cell.gripper``); needs the Robotiq URCap on the controller."""

    def __init__(self, cell: Cell) -> None:
        self._cell = cell
        self._client: URCapGripperClient | None = None
        self._holding = False
        self._lock = asyncio.Lock()
        self.last: dict[str, object] = {"state": "unknown"}
        """The newest known state: ``state`` (of statecharts/gripper.yaml), ``width`` (m),
        ``holding``, ``event`` (what read it)."""
        self.machine = GripperState(self._state_changed)

    @property
    def holding(self) -> bool:
        """Whether the last command or read left an object between the fingers."""
        return self._holding

    @property
    def state(self) -> str:
        """The gripper's state in ``statecharts/gripper.yaml`` (``empty``, ``holding``, ...)."""
        return self.machine.state

    def _state_changed(self, source: str, dest: str, trigger: str) -> None:
        self.last["state"] = dest
        data = {"event": "state", "source": source, "state": dest, "trigger": trigger}
        self._cell.bus.publish(DeviceEvent(time.time(), "gripper", data))

    def _report(self, event: str, width: float | None = None) -> None:
        """Remember and publish (recorder topic ``/gripper``, the daemon's stream) the state."""
        self.last.update(event=event, holding=self._holding)
        if width is not None:
            self.last["width"] = width
        self._cell.bus.publish(DeviceEvent(time.time(), "gripper", dict(self.last)))

    def _io(self) -> URCapGripperClient:
        host = self._cell.host
        if host is None:
            raise ConnectionLostError("the cell is not open (use `async with Cell(...)`)")
        if self._client is None or self._client.host != host:
            self._client = URCapGripperClient(host)
        return self._client

    def _check_power(self, command: str) -> None:
        sample = self._cell.robot_state
        mode = sample.robot_mode if sample is not None else RobotMode.DISCONNECTED
        if mode not in _POWERED:
            self.machine.fire("unpowered")
            raise GripperNotPoweredError(
                f"{command}() is refused: the robot is {mode.name} and the tool flange has no "
                "power (power the arm on first)"
            )

    async def _check_ready(self, io: URCapGripperClient) -> None:
        fault = await io.get("FLT")
        if fault:
            self.machine.fire("fault")
            raise GripperFaultError(fault)
        if await io.get("STA") != 3:
            self.machine.fire("inactive")
            raise GripperNotActivatedError("the gripper is not activated: call activate() first")

    async def activate(self, *, timeout: float = ACTIVATION_TIMEOUT) -> None:  # noqa: ASYNC109
        """Activate (reset, then ``ACT 1``) unless already active without a fault."""
        async with self._cell._command("gripper_activate"), self._lock:
            self._check_power("gripper_activate")
            io = self._io()
            if await io.get("STA") == 3 and await io.get("FLT") == 0:
                self.machine.fire("activated")
                return
            self.machine.fire("activate")
            await io.set(ACT=0)
            await io.set(ACT=1)
            deadline = time.monotonic() + timeout
            while await io.get("STA") != 3:
                if time.monotonic() > deadline:
                    raise RobotTimeoutError(f"the gripper did not activate within {timeout:g} s")
                self._check_power("gripper_activate")
                await asyncio.sleep(POLL)
            self._holding = False
            self.machine.fire("activated")
            self._report("activated", _width(await io.get("POS")))

    async def open(
        self, *, speed: float = SPEED_RANGE[1], force: float = FORCE_RANGE[0]
    ) -> GripResult:
        """Open fully; returns where the fingers stopped."""
        return await self._run("gripper_open", STROKE, speed, force, expect_object=False)

    async def close(
        self,
        *,
        speed: float = SPEED_RANGE[1],
        force: float = FORCE_RANGE[1],
        expect_object: bool = False,
    ) -> GripResult:
        """Close fully or until an object stops the fingers (``expect_object``: or raise)."""
        return await self._run("gripper_close", 0.0, speed, force, expect_object=expect_object)

    async def move(
        self,
        width: float,
        *,
        speed: float = SPEED_RANGE[1],
        force: float = FORCE_RANGE[1],
        expect_object: bool = False,
    ) -> GripResult:
        """Move the fingers to ``width`` (m) at ``speed`` (m/s) with at most ``force`` (N)."""
        return await self._run("gripper_move", width, speed, force, expect_object=expect_object)

    async def get_width(self) -> float:
        """The finger opening in m (also refreshes :attr:`holding`)."""
        io = self._io()
        width = _width(await io.get("POS"))
        obj = await io.get("OBJ")
        self._holding = obj in (1, 2)
        if await io.get("STA") == 3:
            self.machine.fire("stopped_holding" if self._holding else "stopped_empty")
        self._report("read", width)
        return width

    async def check_holding(self) -> None:
        """Raise :class:`ObjectLostError` if the object held before has left the fingers."""
        if not self._holding:
            return
        obj = await self._io().get("OBJ")
        if obj not in (1, 2):
            self._holding = False
            self.machine.fire("lost")
            self._report("object lost")
            raise ObjectLostError("the gripper no longer holds its object")

    async def _run(
        self, name: str, width: float, speed: float, force: float, *, expect_object: bool
    ) -> GripResult:
        args = {"width": width, "speed": speed, "force": force, "expect_object": expect_object}
        async with self._cell._command(name, **args) as outcome, self._lock:
            for label, value, (lo, hi) in (
                ("width", width, (0.0, STROKE)),
                ("speed", speed, SPEED_RANGE),
                ("force", force, FORCE_RANGE),
            ):
                if not (math.isfinite(value) and lo - 1e-12 <= value <= hi + 1e-12):
                    raise InvalidArgumentError(
                        f"gripper {label} {value!r} is outside [{lo:g}, {hi:g}] "
                        f"({'m' if label == 'width' else 'm/s' if label == 'speed' else 'N'})"
                    )
            self._check_power(name)
            io = self._io()
            await self._check_ready(io)
            position = round(255.0 * (1.0 - width / STROKE))
            self.machine.fire("move")
            try:
                result = await self._go(io, name, position, speed, force)
            except asyncio.CancelledError:
                with contextlib.suppress(Exception):
                    await asyncio.shield(io.set(GTO=0))  # stop the fingers where they are
                raise
            self.machine.fire("stopped_holding" if result.holding else "stopped_empty")
            self._report(name, result.width)
            if expect_object and not result.holding:
                raise NothingGraspedError(
                    f"the fingers closed to {result.width * 1e3:.1f} mm on nothing"
                )
            outcome["result"] = result
            return result

    async def _go(
        self, io: URCapGripperClient, name: str, position: int, speed: float, force: float
    ) -> GripResult:
        await io.set(
            POS=position,
            SPE=_register(speed, *SPEED_RANGE),
            FOR=_register(force, *FORCE_RANGE),
            GTO=1,
        )
        deadline = time.monotonic() + self._cell.command_timeout
        while True:
            fault = await io.get("FLT")
            if fault:
                self._holding = False
                self.machine.fire("fault")
                self._report(f"fault 0x{fault:02X}")
                raise GripperFaultError(fault, f"the gripper faulted (0x{fault:02X}) mid-motion")
            if await io.get("PRE") == position:
                obj = await io.get("OBJ")
                if obj != 0:
                    break
            if time.monotonic() > deadline:
                raise RobotTimeoutError(
                    f"{name}: the fingers did not stop within {self._cell.command_timeout:g} s"
                )
            self._check_power(name)
            await asyncio.sleep(POLL)
        self._holding = obj in (1, 2)
        return GripResult(_width(await io.get("POS")), self._holding)

    async def close_connection(self) -> None:
        if self._client is not None:
            await self._client.close()
            self._client = None
