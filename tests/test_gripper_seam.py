"""``cell.gripper`` over the gripper seam, driven by a context made here and a scripted
driver: every argument is checked against the driver's spec before anything is sent
(UnsupportedGripError naming the kind for what the tool cannot do), the state machine
follows the driver's reports, a fault mid-move and a cancelled move end as the seam says,
and a kind without a gripper refuses its commands naming the kind."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest

from fxcell.cell.context import CellContext
from fxcell.cell.gripper import Gripper
from fxcell.config import CellConfig
from fxcell.errors import (
    ConnectionLostError,
    GripperFaultError,
    GripperNotPoweredError,
    InvalidArgumentError,
    NothingGraspedError,
    UnsupportedCommandError,
    UnsupportedGripError,
)
from fxcell.events import EventBus
from fxcell.layout import Layout
from fxcell.link.gripper import HAND_E, GripperReading, GripperSpec
from fxcell.protocol import RobotMode, RobotState
from fxcell.results import GripResult

pytestmark = pytest.mark.timeout(20)

TWO_POSITIONS = GripperSpec(
    name="Test Gripper",
    stroke=0.03,
    speed_range=None,
    force_range=None,
    default_speed=None,
    default_force=None,
    continuous=False,
)


class ScriptedGripper:
    """A driver that records what it is sent; ``holds`` decides a close's outcome."""

    def __init__(self, spec: GripperSpec) -> None:
        self._spec = spec
        self.sent: list[tuple[str, Any]] = []
        self.holds = False
        self.fault = 0
        self.halted = False
        self.block: asyncio.Event | None = None
        self.moving = asyncio.Event()

    @property
    def spec(self) -> GripperSpec:
        return self._spec

    async def read(self) -> GripperReading:
        return GripperReading(True, self.fault, 0.0, self.holds)

    async def activate(self, within: float, guard: Callable[[], None]) -> None:
        self.sent.append(("activate", within))

    async def move(
        self,
        width: float,
        speed: float | None,
        force: float | None,
        *,
        within: float,
        guard: Callable[[], None],
    ) -> GripResult:
        self.sent.append(("move", (width, speed, force)))
        self.moving.set()
        if self.block is not None:
            await self.block.wait()
        if self.fault:
            raise GripperFaultError(self.fault)
        holding = self.holds and width == 0.0
        return GripResult(0.02 if holding else width, holding)

    async def halt(self) -> None:
        self.halted = True

    async def close(self) -> None:
        pass


def _context(mode: RobotMode = RobotMode.RUNNING) -> CellContext:
    @contextlib.asynccontextmanager
    async def record(name: str, /, **args: Any) -> AsyncIterator[dict[str, Any]]:
        yield {}

    def unused(*args: Any) -> Any:
        raise AssertionError("the gripper does not use this")

    config = CellConfig()
    return CellContext(
        bus=EventBus(),
        command=record,
        record=record,
        link=unused,
        sample=lambda: RobotState(robot_mode=mode),
        latest=lambda: RobotState(robot_mode=mode),
        states=unused,
        hold=unused,
        config=lambda: config,
        layout=lambda: Layout(config.layout),
        host=lambda: "127.0.0.1",
        timeout=lambda: 5.0,
    )


def _gripper(
    spec: GripperSpec, mode: RobotMode = RobotMode.RUNNING
) -> tuple[Gripper, ScriptedGripper]:
    driver = ScriptedGripper(spec)
    return Gripper(_context(mode), lambda host: driver, "testkind"), driver


async def test_what_a_two_position_gripper_cannot_do_is_refused_naming_the_kind() -> None:
    gripper, driver = _gripper(TWO_POSITIONS)
    for call in (
        lambda: gripper.move(0.01),
        lambda: gripper.close(speed=0.05),
        lambda: gripper.close(force=40.0),
        lambda: gripper.open(speed=0.1),
    ):
        with pytest.raises(UnsupportedGripError, match="testkind") as refused:
            await call()
        assert refused.value.kind == "testkind"
    with pytest.raises(InvalidArgumentError, match="outside"):
        await gripper.move(0.031)
    assert driver.sent == []  # nothing reached the tool
    assert (await gripper.open()).width == pytest.approx(0.03)
    assert driver.sent == [("move", (0.03, None, None))]
    assert gripper.opening(0.022) == pytest.approx(0.03)  # it opens fully


async def test_a_continuous_gripper_takes_widths_and_checks_its_ranges() -> None:
    gripper, driver = _gripper(HAND_E)
    await gripper.move(0.021, speed=0.05, force=50.0)
    assert driver.sent == [("move", (0.021, 0.05, 50.0))]
    with pytest.raises(InvalidArgumentError):
        await gripper.move(0.02, speed=0.5)
    assert gripper.opening(0.032) == pytest.approx(0.032)
    assert gripper.opening(0.07) == pytest.approx(HAND_E.stroke)


async def test_the_state_follows_what_the_driver_reports() -> None:
    gripper, driver = _gripper(TWO_POSITIONS)
    await gripper.activate()
    assert gripper.state == "empty"
    driver.holds = True
    assert (await gripper.close(expect_object=True)).holding
    assert gripper.state == "holding"
    assert gripper.holding
    driver.holds = False
    await gripper.open()
    with pytest.raises(NothingGraspedError):
        await gripper.close(expect_object=True)
    assert gripper.state == "empty"


async def test_a_fault_mid_move_is_typed_and_a_cancelled_move_halts_the_fingers() -> None:
    gripper, driver = _gripper(TWO_POSITIONS)
    driver.block = asyncio.Event()
    closing = asyncio.create_task(gripper.close())
    await driver.moving.wait()
    closing.cancel()
    with pytest.raises(asyncio.CancelledError):
        await closing
    assert driver.halted
    driver.block = None
    driver.fault = 0x0E
    driver.sent.clear()
    with pytest.raises(GripperFaultError):
        await gripper.close()  # the read before the move sees the fault
    assert gripper.state == "fault"
    assert driver.sent == []


async def test_an_unpowered_arm_and_a_kind_without_a_gripper_are_refused() -> None:
    gripper, driver = _gripper(TWO_POSITIONS, RobotMode.POWER_OFF)
    with pytest.raises(GripperNotPoweredError):
        await gripper.close()
    assert driver.sent == []
    none = Gripper(_context(), None, "toy")
    with pytest.raises(UnsupportedCommandError, match="toy"):
        await none.open()
    closed_cell = Gripper(
        dataclasses.replace(_context(), host=lambda: None), lambda host: driver, "testkind"
    )
    with pytest.raises(ConnectionLostError):
        await closed_cell.close()
