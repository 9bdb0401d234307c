"""Pick and place at the layout's stations against the simulator, checked by where the
simulator says the objects are."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import numpy as np
import pytest

from fxcell import Cell
from fxcell.config import CellConfig
from fxcell.errors import (
    CollisionError,
    HoldingError,
    InterlockError,
    NothingGraspedError,
    SlotError,
    UnknownStationError,
)
from fxcell.geometry import Pose
from fxcell.layout import Layout
from fxcell.testing import SimulatorHandle, brisk, simulator

CONFIG = CellConfig.load()
LAYOUT = Layout(CONFIG.layout)
CRUCIBLE = CONFIG.layout.objects["crucible"]


@pytest.fixture(scope="module")
def sim() -> Iterator[SimulatorHandle]:
    with simulator(time_scale=0.2) as s:
        yield s


@pytest.fixture
def config(tmp_path: Path) -> CellConfig:
    io = CONFIG.io.model_copy(update={"interlocks": {"machine": "machine_start"}})
    return brisk(CONFIG).model_copy(update={"positions_file": tmp_path / "p.yaml", "io": io})


@pytest.fixture
async def cell(sim: SimulatorHandle, config: CellConfig) -> AsyncIterator[Cell]:
    async with Cell(host=sim.host, config=config) as c:
        await c.init()
        await c.gripper_activate()
        await c.io_set("machine_start", False)
        yield c
        if c.held is not None:
            await c.gripper_open()
        await c.go_home()


def put_crucible(sim: SimulatorHandle, name: str, station: str, slot: str) -> None:
    grip = LAYOUT.station(station).grip_pose(slot).position
    sim.add_object(
        name, "crucible", width=CRUCIBLE.width, height=CRUCIBLE.height, mass=CRUCIBLE.mass,
        position=grip.tolist(),
    )  # fmt: skip


def where(sim: SimulatorHandle, name: str) -> np.ndarray:
    return np.array(sim.objects()[name]["pose"][:3])


async def test_a_crucible_picked_from_the_rack_lands_in_the_machine_within_1_mm(
    sim: SimulatorHandle, cell: Cell
) -> None:
    await asyncio.to_thread(put_crucible, sim, "c-B2", "rack", "B2")
    grip = await cell.pick("rack", "B2")
    assert grip.holding
    assert cell.held == "crucible"
    assert sim.state()["payload"] == pytest.approx(CONFIG.tool.payload + CRUCIBLE.mass)
    released = await cell.place("machine", "A1")
    assert not released.holding
    assert cell.held is None
    assert sim.state()["payload"] == pytest.approx(CONFIG.tool.payload)
    target = LAYOUT.station("machine").grip_pose("A1").position
    assert np.linalg.norm(where(sim, "c-B2") - target) < 1e-3
    # and back to the rack
    await cell.pick("machine", "A1")
    await cell.place("rack", "B2")
    assert (
        np.linalg.norm(where(sim, "c-B2") - LAYOUT.station("rack").grip_pose("B2").position) < 1e-3
    )


async def test_an_empty_slot_raises_with_the_slot_named_and_the_arm_above_it(
    cell: Cell,
) -> None:
    with pytest.raises(NothingGraspedError, match="no crucible detected in rack slot C3"):
        await cell.pick("rack", "C3")
    assert cell.held is None
    above = LAYOUT.station("rack").retreat_pose("C3").position
    tcp = np.array((await cell.get_current_pose())[:3])
    assert np.linalg.norm(tcp - above) < 1e-4


async def test_bad_names_and_interlocks_are_refused_before_anything_moves(cell: Cell) -> None:
    before = await cell.get_current_joint_values()
    with pytest.raises(SlotError, match=r"A1\.\.D4"):
        await cell.pick("rack", "E9")
    with pytest.raises(SlotError):
        await cell.pick("rack", "3B")
    with pytest.raises(UnknownStationError, match="known: machine, moulds, rack, tray"):
        await cell.pick("oven", "A1")
    with pytest.raises(HoldingError):
        await cell.place("tray", "A1")
    await cell.io_set("machine_start", True)  # this test's interlock of the machine zone
    with pytest.raises(InterlockError, match="machine zone is interlocked"):
        await cell.pick("machine", "A2")
    await cell.io_set("machine_start", False)
    assert await cell.get_current_joint_values() == pytest.approx(before, abs=1e-6)


async def test_planning_refuses_a_pose_where_the_held_crucible_hits_the_machine(
    sim: SimulatorHandle, cell: Cell
) -> None:
    low = LAYOUT.station("machine").grip_pose("A3") @ Pose([0.0, 0.0, 0.015])
    await asyncio.to_thread(put_crucible, sim, "c-A4", "rack", "A4")
    await cell.pick("rack", "A4")
    with pytest.raises(CollisionError, match="held_crucible"):
        await cell.move_pose(low)
    await cell.place("rack", "A4")
    # The bare gripper may go there.
    await cell.move_pose(LAYOUT.station("machine").approach_pose("A3"))
    await cell.move_pose(low, linear=True)
