"""cell.gripper against the simulated Hand-E: SI units, typed errors, pick and place."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator

import numpy as np
import pytest
from waiting import controller_time_passes, until

from fxcell import Cell
from fxcell.cell.gripper import GripResult
from fxcell.cell.statemachine import CellState
from fxcell.config import CellConfig
from fxcell.errors import (
    GripperFaultError,
    GripperNotActivatedError,
    GripperNotPoweredError,
    InvalidArgumentError,
    NothingGraspedError,
    ObjectLostError,
)
from fxcell.events import DeviceEvent
from fxcell.testing import SimulatorHandle, brisk, injected_faults, simulator

PICK = [0.0, -1.2, 1.2, -1.57, -1.57, 0.0]
PLACE = [0.4, -1.1, 1.1, -1.57, -1.57, 0.0]
EMPTY = [-0.4, -1.3, 1.3, -1.57, -1.57, 0.0]
CRUCIBLE = 0.032
# Finger times scale with the simulator: at 0.2 a slow full close takes 0.5 s, long enough to
# fault or cancel it midway on a busy machine.
TIME_SCALE = 0.2


@pytest.fixture(scope="module")
def sim() -> Iterator[SimulatorHandle]:
    with simulator(time_scale=TIME_SCALE) as s:
        yield s


@pytest.fixture
async def cell(sim: SimulatorHandle) -> AsyncIterator[Cell]:
    async with Cell(host=sim.host, config=brisk(CellConfig.load())) as c:
        await c.init()
        yield c


async def _closing(sim: SimulatorHandle) -> bool:
    """Whether the simulated fingers have left the fully open width."""
    return float((await asyncio.to_thread(sim.gripper))["width"]) < 0.049


def tcp(sim: SimulatorHandle) -> np.ndarray:
    return np.array(sim.gripper()["tcp_pose"][:3])


async def test_commands_are_refused_without_tool_power(sim: SimulatorHandle) -> None:
    await asyncio.to_thread(sim.dashboard, "power off")
    await asyncio.to_thread(sim.wait_for, "robot_mode", "POWER_OFF")
    async with Cell(host=sim.host) as c:
        with pytest.raises(GripperNotPoweredError):
            await c.gripper.activate()
        with pytest.raises(GripperNotPoweredError):
            await c.gripper.close()
        assert c.gripper.state == "unpowered"


async def test_moving_before_activation_is_refused(sim: SimulatorHandle, cell: Cell) -> None:
    await asyncio.to_thread(sim.dashboard, "power off")  # the gripper loses its activation
    await asyncio.to_thread(sim.wait_for, "robot_mode", "POWER_OFF")
    await cell.wait_for_state(CellState.POWER_OFF)  # the Cell has seen it too: init acts
    await cell.init()
    with pytest.raises(GripperNotActivatedError):
        await cell.gripper.open()


async def test_out_of_range_arguments_are_refused(cell: Cell) -> None:
    await cell.gripper.activate()
    for kwargs in ({"width": 0.06}, {"width": 0.01, "speed": 0.5}, {"width": 0.01, "force": 5}):
        with pytest.raises(InvalidArgumentError):
            await cell.gripper.move(**kwargs)  # type: ignore[arg-type]


async def test_pick_and_place_moves_the_object_within_1_mm(
    sim: SimulatorHandle, cell: Cell
) -> None:
    await cell.gripper.activate()
    await cell.move_joint(PICK)
    assert await cell.gripper.open() == GripResult(pytest.approx(0.05), False)  # type: ignore[arg-type]
    where = tcp(sim)
    await asyncio.to_thread(
        sim.add_object, "crucible_1", "crucible", width=CRUCIBLE, height=0.04, mass=0.05,
        position=where,
    )  # fmt: skip
    states: list[str] = []
    cell.bus.subscribe(
        lambda e: (
            states.append(e.data["state"])
            if isinstance(e, DeviceEvent) and e.data.get("event") == "state"
            else None
        )
    )
    result = await cell.gripper.close(expect_object=True)
    assert result.holding
    assert cell.gripper.holding
    assert cell.gripper.state == "holding"
    assert result.width == pytest.approx(CRUCIBLE, abs=0.2e-3)
    await cell.move_joint(PLACE)
    target = tcp(sim)
    released = await cell.gripper.open()
    assert not released.holding
    # The companion statechart (statecharts/gripper.yaml), published on the bus (/gripper).
    assert states == ["moving", "holding", "moving", "empty"]
    await cell.move_joint(EMPTY)
    placed = sim.objects()["crucible_1"]
    assert not placed["held"]
    assert np.linalg.norm(np.array(placed["pose"][:3]) - target) < 1e-3
    assert np.linalg.norm(target - where) > 0.05


async def test_closing_on_nothing_raises_when_an_object_was_expected(cell: Cell) -> None:
    await cell.gripper.activate()
    await cell.move_joint(EMPTY)
    await cell.gripper.open()
    with pytest.raises(NothingGraspedError):
        await cell.gripper.close(expect_object=True)
    assert await cell.gripper.get_width() == pytest.approx(0.0)
    assert not cell.gripper.holding


async def test_a_fault_mid_grasp_is_a_typed_error(sim: SimulatorHandle, cell: Cell) -> None:
    await cell.gripper.activate()
    await cell.move_joint(EMPTY)
    await cell.gripper.open()
    grasp = asyncio.create_task(cell.gripper.close(speed=0.02))
    await until(lambda: _closing(sim), "the fingers to start closing")
    with injected_faults("a gripper fault"):
        await asyncio.to_thread(sim.inject, "gripper_fault", "0x0E")
    with pytest.raises(GripperFaultError) as info:
        await grasp
    assert info.value.code == 0x0E
    assert cell.gripper.state == "fault"
    with pytest.raises(GripperFaultError):
        await cell.gripper.open()
    await cell.gripper.activate()  # clears the fault
    assert cell.gripper.state == "empty"
    assert (await cell.gripper.open()).width == pytest.approx(0.05)


async def test_a_slipped_object_is_reported_lost(sim: SimulatorHandle, cell: Cell) -> None:
    await cell.gripper.activate()
    await cell.move_joint(PICK)
    await cell.gripper.open()
    await asyncio.to_thread(
        sim.add_object, "bead_1", "glass_bead", width=0.02, height=0.02, mass=0.01,
        position=tcp(sim),
    )  # fmt: skip
    await cell.gripper.close(expect_object=True)
    with injected_faults("the held object slips out"):
        await asyncio.to_thread(sim.inject, "gripper_drop")
    with pytest.raises(ObjectLostError):
        await cell.gripper.check_holding()
    await cell.gripper.open()
    await asyncio.to_thread(
        sim.add_object, "bead_1", "glass_bead", width=0.02, height=0.02, mass=0.01,
        position=[0, 0, 5],
    )  # fmt: skip


async def test_cancelling_a_grasp_stops_the_fingers(sim: SimulatorHandle, cell: Cell) -> None:
    await cell.gripper.activate()
    await cell.move_joint(EMPTY)
    await cell.gripper.open()
    grasp = asyncio.create_task(cell.gripper.close(speed=0.02))
    await until(lambda: _closing(sim), "the fingers to start closing")
    grasp.cancel()
    with pytest.raises(asyncio.CancelledError):
        await grasp
    first = await cell.gripper.get_width()
    # Closing on, the fingers would cover 10 mm in 0.1 s of the simulator's time (0.5 s a stroke).
    await controller_time_passes(sim, 0.1)
    assert await cell.gripper.get_width() == first > 0.0
