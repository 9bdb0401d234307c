"""The job on the real Cell against the simulator (manual machine mode: the test is the operator
and pours the bead), checked by where the simulator says the objects are."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import numpy as np
import pytest

from fxcell import Cell
from fxcell.config import CellConfig, JobConfig
from fxcell.job import Job, JobStore, final_locations
from fxcell.layout import Layout
from fxcell.testing import SimulatorHandle, brisk, simulator

CONFIG = CellConfig.load()
LAYOUT = Layout(CONFIG.layout)
TIMEOUT = 240.0


@pytest.fixture(scope="module")
def sim() -> Iterator[SimulatorHandle]:
    with simulator(time_scale=0.2) as s:
        yield s


@pytest.fixture
async def cell(sim: SimulatorHandle, tmp_path: Path) -> AsyncIterator[Cell]:
    config = brisk(CONFIG).model_copy(update={"positions_file": tmp_path / "p.yaml"})
    async with Cell(host=sim.host, config=config) as c:
        await c.init()
        await c.gripper_activate()
        yield c


def put(sim: SimulatorHandle, name: str, station: str, slot: str) -> None:
    st = LAYOUT.station(station)
    kind = st.kind
    sim.add_object(
        name, st.config.holds, width=kind.width, height=kind.height, mass=kind.mass,
        position=st.grip_pose(slot).position.tolist(),
    )  # fmt: skip


def distance(sim: SimulatorHandle, name: str, station: str, slot: str) -> float:
    at = np.array(sim.objects()[name]["pose"][:3])
    return float(np.linalg.norm(at - LAYOUT.station(station).grip_pose(slot).position))


@pytest.mark.slow
@pytest.mark.timeout(600)
async def test_one_sample_on_the_simulated_cell_ends_with_bead_on_tray_and_crucible_home(
    sim: SimulatorHandle, cell: Cell, tmp_path: Path
) -> None:
    await asyncio.to_thread(put, sim, "crucible-S1", "rack", "B2")
    store = JobStore(tmp_path / "job.sqlite3")
    job = Job(cell, store, JobConfig(manual=True))
    run = {"samples": [{"id": "S1", "rack": "B2", "tray": "C3", "machine": "A2"}]}
    await job.start(run)
    await job.wait_state("waiting_for_machine", "fault", "paused", timeout=TIMEOUT)
    assert job.state == "waiting_for_machine", job.message
    assert distance(sim, "crucible-S1", "machine", "A2") < 1e-3
    await job.confirm("machine_started")
    async with asyncio.timeout(TIMEOUT):  # the job goes on to its wait step
        while job.prompt is None or job.prompt["id"] != "machine_done":
            assert job.state in ("running", "waiting_for_machine"), job.message
            await asyncio.sleep(0.01)
    await asyncio.to_thread(put, sim, "bead-S1", "moulds", "A2")  # the machine pours the bead
    await job.confirm("machine_done")
    state = await job.wait_state("done", "fault", "paused", timeout=TIMEOUT)
    assert state == "done", job.message
    assert distance(sim, "bead-S1", "tray", "C3") < 1e-3
    assert distance(sim, "crucible-S1", "rack", "B2") < 1e-3
    assert job.run is not None
    assert store.locations(1) == final_locations(job.run)
    assert cell.held is None
    store.close()
