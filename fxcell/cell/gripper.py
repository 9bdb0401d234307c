"""``cell.gripper``: the robot kind's gripper in SI units, through its driver.

The kind names its driver (:class:`~fxcell.link.gripper.GripperDriver`: the UR3e's Robotiq
Hand-E through the URCap's socket, the Ned2's Gripper 1 through its TCP server) and the
driver's :class:`~fxcell.link.gripper.GripperSpec` says what it can do: widths are finger
openings in m (0 closed .. the stroke), speeds in m/s, forces in N (the Hand-E: 0..0.050,
0.020..0.150, 20..185; the tool's registers or steps are the driver's business). An
opening, speed or force the kind's gripper cannot do is refused with
:class:`~fxcell.errors.UnsupportedGripError` naming the kind, out-of-range values with
:class:`~fxcell.errors.InvalidArgumentError`, before anything is sent. Every command is
recorded like an arm command (``gripper_activate``, ``gripper_move``, ...) and is refused
before anything is sent while the arm is off (the tool flange has no power).
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
from fxcell.errors import (
    ConnectionLostError,
    GripperFaultError,
    GripperNotActivatedError,
    GripperNotPoweredError,
    InvalidArgumentError,
    NothingGraspedError,
    ObjectLostError,
    UnsupportedCommandError,
    UnsupportedGripError,
)
from fxcell.events import DeviceEvent
from fxcell.protocol import RobotMode
from fxcell.results import GripResult

if TYPE_CHECKING:
    from fxcell.cell.context import CellContext
    from fxcell.link.gripper import GripperDriver, GripperFactory, GripperSpec

ACTIVATION_TIMEOUT = 10.0  # s
_POWERED = (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
_TOLERANCE = 1e-12

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
    """The cell's gripper (``cell.gripper``), driven by its robot kind's driver."""

    def __init__(self, context: CellContext, factory: GripperFactory | None, kind: str) -> None:
        self._context = context
        self._factory = factory
        self._kind = kind
        self._driver: GripperDriver | None = None
        self._host: str | None = None
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

    @property
    def spec(self) -> GripperSpec:
        """What the kind's gripper can do (stroke, speeds, forces, object detection)."""
        return self._io().spec

    def opening(self, width: float) -> float:
        """The opening to use when at least ``width`` (m) is needed (pick and place: an
        object's width and a clearance): see :meth:`GripperSpec.opening`."""
        return self.spec.opening(width)

    def check_fits(self, width: float, what: str) -> None:
        """Refuse (:class:`UnsupportedGripError`, naming the kind) an object ``width`` m
        across that the fingers cannot open around (``what``: the object, for the
        message). Without a controller address there is no gripper to ask: its own
        commands refuse then."""
        try:
            spec = self.spec
        except ConnectionLostError:
            return
        if width >= spec.stroke:
            raise UnsupportedGripError(
                self._kind,
                "width",
                f"a {what} is {width * 1e3:.1f} mm across: the {self._kind}'s {spec.name} "
                f"opens only {spec.stroke * 1e3:.1f} mm",
            )

    def _state_changed(self, source: str, dest: str, trigger: str) -> None:
        self.last["state"] = dest
        data = {"event": "state", "source": source, "state": dest, "trigger": trigger}
        self._context.bus.publish(DeviceEvent(time.time(), "gripper", data))

    def _report(self, event: str, width: float | None = None) -> None:
        """Remember and publish (recorder topic ``/gripper``, the daemon's stream) the state."""
        self.last.update(event=event, holding=self._holding)
        if width is not None:
            self.last["width"] = width
        self._context.bus.publish(DeviceEvent(time.time(), "gripper", dict(self.last)))

    def _io(self) -> GripperDriver:
        if self._factory is None:
            raise UnsupportedCommandError("gripper", self._kind)
        host = self._context.host()
        if host is None:
            raise ConnectionLostError("the cell is not open (use `async with Cell(...)`)")
        if self._driver is None or self._host != host:
            self._driver = self._factory(host)
            self._host = host
        return self._driver

    def _check_power(self, command: str) -> None:
        sample = self._context.latest()
        mode = sample.robot_mode if sample is not None else RobotMode.DISCONNECTED
        if mode not in _POWERED:
            self.machine.fire("unpowered")
            raise GripperNotPoweredError(
                f"{command}() is refused: the robot is {mode.name} and the tool flange has no "
                "power (power the arm on first)"
            )

    async def _check_ready(self, io: GripperDriver) -> None:
        reading = await io.read()
        if reading.fault:
            self.machine.fire("fault")
            raise GripperFaultError(reading.fault)
        if not reading.active:
            self.machine.fire("inactive")
            raise GripperNotActivatedError("the gripper is not activated: call activate() first")

    async def activate(self, *, timeout: float = ACTIVATION_TIMEOUT) -> None:  # noqa: ASYNC109
        """Activate (the Hand-E: reset, then ``ACT 1``) unless already active without a
        fault."""
        async with self._context.record("gripper_activate"), self._lock:
            self._check_power("gripper_activate")
            io = self._io()
            reading = await io.read()
            if reading.active and not reading.fault:
                self.machine.fire("activated")
                return
            self.machine.fire("activate")
            await io.activate(timeout, lambda: self._check_power("gripper_activate"))
            self._holding = False
            self.machine.fire("activated")
            self._report("activated", (await io.read()).width)

    async def open(self, *, speed: float | None = None) -> GripResult:
        """Open fully; returns where the fingers stopped (``speed``: m/s, None: the
        gripper's own)."""
        try:
            stroke: float | None = self._io().spec.stroke
        except (ConnectionLostError, UnsupportedCommandError):
            stroke = None  # refused inside the recorded command
        return await self._run("gripper_open", stroke, speed, None, expect_object=False)

    async def close(
        self,
        *,
        speed: float | None = None,
        force: float | None = None,
        expect_object: bool = False,
    ) -> GripResult:
        """Close fully or until an object stops the fingers (``expect_object``: or raise)."""
        return await self._run("gripper_close", 0.0, speed, force, expect_object=expect_object)

    async def move(
        self,
        width: float,
        *,
        speed: float | None = None,
        force: float | None = None,
        expect_object: bool = False,
    ) -> GripResult:
        """Move the fingers to ``width`` (m) at ``speed`` (m/s) with at most ``force`` (N);
        None: the gripper's own speed and force."""
        return await self._run("gripper_move", width, speed, force, expect_object=expect_object)

    async def get_width(self) -> float:
        """The finger opening in m (also refreshes :attr:`holding`)."""
        reading = await self._io().read()
        self._holding = reading.holding
        if reading.active and not reading.fault:
            self.machine.fire("stopped_holding" if self._holding else "stopped_empty")
        self._report("read", reading.width)
        return reading.width

    async def check_holding(self) -> None:
        """Raise :class:`ObjectLostError` if the object held before has left the fingers."""
        if not self._holding:
            return
        reading = await self._io().read()
        if not reading.holding:
            self._holding = False
            self.machine.fire("lost")
            self._report("object lost")
            raise ObjectLostError("the gripper no longer holds its object")

    def _check_args(
        self, spec: GripperSpec, width: float, speed: float | None, force: float | None
    ) -> None:
        """Refuse what the kind's gripper cannot do (nothing sent)."""
        kind, tool = self._kind, spec.name
        if not (math.isfinite(width) and -_TOLERANCE <= width <= spec.stroke + _TOLERANCE):
            raise InvalidArgumentError(
                f"gripper width {width!r} is outside [0, {spec.stroke:g}] (m) of the {kind}'s "
                f"{tool}"
            )
        ends = abs(width) <= _TOLERANCE or abs(width - spec.stroke) <= _TOLERANCE
        if not spec.continuous and not ends:
            raise UnsupportedGripError(
                kind,
                "width",
                f"the {kind}'s {tool} only closes (0) or opens fully ({spec.stroke:g} m), "
                f"not to {width!r} m",
            )
        for label, value, span, unit in (
            ("speed", speed, spec.speed_range, "m/s"),
            ("force", force, spec.force_range, "N"),
        ):
            if value is None:
                continue
            if span is None:
                raise UnsupportedGripError(
                    kind, label, f"the {kind}'s {tool} has no {label} setting (give none)"
                )
            lo, hi = span
            if not (math.isfinite(value) and lo - _TOLERANCE <= value <= hi + _TOLERANCE):
                raise InvalidArgumentError(
                    f"gripper {label} {value!r} is outside [{lo:g}, {hi:g}] ({unit}) of the "
                    f"{kind}'s {tool}"
                )

    async def _run(
        self,
        name: str,
        width: float | None,
        speed: float | None,
        force: float | None,
        *,
        expect_object: bool,
    ) -> GripResult:
        """Run a finger move (``width`` None: fully open) as the recorded command ``name``."""
        args = {"width": width, "speed": speed, "force": force, "expect_object": expect_object}
        async with self._context.record(name, **args) as outcome, self._lock:
            io = self._io()
            if width is None:
                width = io.spec.stroke
            self._check_args(io.spec, width, speed, force)
            self._check_power(name)
            await self._check_ready(io)
            self.machine.fire("move")
            try:
                result = await io.move(
                    width,
                    speed,
                    force,
                    within=self._context.timeout(),
                    guard=lambda: self._check_power(name),
                )
            except asyncio.CancelledError:
                with contextlib.suppress(Exception):
                    await asyncio.shield(io.halt())  # stop the fingers where they are
                raise
            except GripperFaultError as exc:
                self._holding = False
                self.machine.fire("fault")
                self._report(f"fault 0x{exc.code:02X}")
                raise
            self._holding = result.holding
            self.machine.fire("stopped_holding" if result.holding else "stopped_empty")
            self._report(name, result.width)
            if expect_object and not result.holding:
                raise NothingGraspedError(
                    f"the fingers closed to {result.width * 1e3:.1f} mm on nothing"
                )
            outcome["result"] = result
            return result

    async def close_connection(self) -> None:
        if self._driver is not None:
            await self._driver.close()
            self._driver = None
