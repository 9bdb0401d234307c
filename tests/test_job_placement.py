"""The job looks before the fusion: a misplaced crucible holds the run before the machine
starts, and resuming looks again.

The fake cell renders the machine's positions from its world (``fxcell.testing.vision``):
``next_place_fault`` makes the next crucible it places in the machine stand as described.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from job_fakes import FakeCell, World, expected_world, sample_run

from fxcell.config import JobConfig
from fxcell.job import Job, JobStore
from fxcell.testing.vision import Fault, VisionBench

TIMEOUT = 60.0


@pytest.fixture(scope="module")
def camera() -> VisionBench:
    return VisionBench()


@pytest.fixture
def store(tmp_path: Path) -> Iterator[JobStore]:
    s = JobStore(tmp_path / "job.sqlite3")
    yield s
    s.close()


def starts(cell: FakeCell) -> list[bool]:
    return [v for s, v in cell.io.history if s == "machine_start" and v]


async def test_a_crucible_placed_4_mm_off_holds_the_run_before_the_machine_starts(
    store: JobStore, camera: VisionBench
) -> None:
    run = sample_run(3)
    world = World.for_run(run)
    cell = FakeCell(world)
    cell.camera = camera
    events: list[dict[str, Any]] = []
    job = Job(cell, store, JobConfig(start_timeout=5.0), on_event=events.append)
    # the second crucible slides 4 mm along the deck as the gripper lets go
    original = cell.place

    async def place(station: str, slot: str) -> None:
        if (station, slot) == ("machine", "A2"):
            cell.next_place_fault = Fault.offset(0.004, 0.0)
        await original(station, slot)

    cell.place = place  # type: ignore[method-assign]
    await job.start(run)
    assert await job.wait_state("paused", "fault", "done", timeout=TIMEOUT) == "paused"
    # held before the machine's start pulse: the machine never ran
    assert starts(cell) == []
    assert cell.machine.cycles == 0
    assert "placement check before fusion cycle 1" in job.message
    assert "A2: crucible 4." in job.message
    status = job.status()
    placement = status["placement"]
    assert placement["ok"] is False
    assert placement["positions"]["A2"]["verdict"] == "offset"
    assert placement["positions"]["A2"]["offset_mm"] == pytest.approx(4.0, abs=0.5)
    assert placement["positions"]["A1"]["verdict"] == "seated"
    assert any(e["event"] == "placement" and not e["ok"] for e in events)
    # kept in the database beside the run, with the annotated image
    assert job.run_id is not None
    checks = store.placement_checks(job.run_id)
    assert len(checks) == 1
    assert checks[0].verdict["positions"][1]["verdict"] == "offset"
    assert store.placement_image(checks[0].id)[:2] == b"\xff\xd8"

    # the operator seats it; resuming checks again, then the machine starts
    cell.faults.clear()
    await job.resume()
    assert await job.wait_state("done", "fault", "paused", timeout=TIMEOUT) == "done", job.message
    assert world.places == expected_world(run)
    checks = store.placement_checks(job.run_id)
    assert [c.ok for c in checks] == [False, True]
    assert len(starts(cell)) == 1
    assert len(cell.checks) == 2


async def test_the_check_repeats_while_the_crucible_stays_off(
    store: JobStore, camera: VisionBench
) -> None:
    run = sample_run(1)
    cell = FakeCell(World.for_run(run))
    cell.camera = camera
    cell.next_place_fault = Fault.tilted(0.35, azimuth=1.57)
    job = Job(cell, store, JobConfig(start_timeout=5.0))
    await job.start(run)
    assert await job.wait_state("paused", timeout=TIMEOUT) == "paused"
    assert "A1: crucible not seated flat (tilted)" in job.message
    await job.resume()  # nothing was fixed
    await job.wait_state("running", timeout=TIMEOUT)
    assert await job.wait_state("paused", "done", timeout=TIMEOUT) == "paused"
    assert job.run_id is not None
    assert [c.ok for c in store.placement_checks(job.run_id)] == [False, False]
    assert cell.machine.cycles == 0
    await job.discard()


async def test_without_a_camera_the_machine_starts_unchecked(store: JobStore) -> None:
    run = sample_run(2)
    world = World.for_run(run)
    cell = FakeCell(world)
    job = Job(cell, store, JobConfig(start_timeout=5.0))
    await job.start(run)
    assert await job.wait_state("done", "fault", "paused", timeout=TIMEOUT) == "done"
    assert job.status()["placement"] is None
