"""A job heals what needs no human: its robot link killed again and again, it goes on by itself.

The library's ``Job`` on a ``Cell`` in this process, the simulator (arm, Hand-E with the
crucibles, fusion machine) in its own: the robot-link process is SIGKILLed at random
moments of a 4-sample run (mid-move, mid-grasp, while the machine fuses, ...). The run
must end ``done`` without the operator, with every crucible back in its rack slot and every
bead on its tray slot by the simulator's own object poses, and the store must say so too.

The kill moments are random but seedable: ``FXCELL_KILL_SEED=N`` repeats a run, and a
failure names its seed.
"""

from __future__ import annotations

import asyncio
import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fxcell.cell import Cell
from fxcell.config import CellConfig
from fxcell.job import Job, JobStore
from fxcell.job.plan import location
from fxcell.layout import Layout
from fxcell.testing import SimulatorHandle, brisk, injected_faults, simulator

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

KILLS = 10
RUN = {
    "name": "four samples",
    "samples": [
        {"id": f"S0{i}", "rack": f"A{i}", "machine": f"A{i}", "tray": f"A{i}"} for i in range(1, 5)
    ],
}


def config_for(tmp: Path) -> CellConfig:
    base = CellConfig.load()
    job = {"database": tmp / "job.sqlite3", "ready_timeout": 30.0}
    return base.model_copy(
        update={
            "limits": brisk(base).limits,
            "job": base.job.model_copy(update=job),
            "positions_file": tmp / "positions.yaml",
        }
    )


def place_of(layout: Layout, obj: dict[str, Any]) -> str | None:
    """Where an object of the simulated world is, as the job names places."""
    if obj["held"]:
        return "gripper"
    position = np.array(obj["pose"][:3])
    for station in layout:
        for slot in station.slots:
            if np.linalg.norm(station.grip_pose(slot).position - position) < 1e-3:
                return location(station.name, slot)
    return None


async def kill_the_link_at_random(cell: Cell, job: Job, rng: random.Random) -> list[str]:
    """SIGKILL the link process ``KILLS`` times while the job works; what each one hit."""
    hit: list[str] = []
    link = cell.link
    assert link is not None
    while len(hit) < KILLS and job.state in ("running", "waiting_for_machine"):
        # a random moment: the kill itself, not a wait for a condition
        await asyncio.sleep(rng.uniform(1.0, 5.0))
        if job.state not in ("running", "waiting_for_machine"):
            break
        if not link.up:  # still coming back from the previous kill: that one counts once
            continue
        hit.append(job.status()["step"] or job.state)
        link.kill_process()
    return hit


@pytest.mark.long  # a 4-sample run with ten restarts: minutes of robot time (./dev test -m long)
async def test_a_run_whose_link_is_killed_ten_times_ends_in_place_without_the_operator(
    tmp_path: Path,
) -> None:
    seed = int(os.environ.get("FXCELL_KILL_SEED") or random.randrange(2**32))
    rng = random.Random(seed)
    config = config_for(tmp_path)
    args = ["--fusion-time", "20", "--cooling-time", "10", "--crucibles", "A1,A2,A3,A4"]
    with simulator(time_scale=0.05, extra_args=args) as sim:
        async with Cell(sim.host, config=config) as cell:
            await cell.init()
            await cell.gripper_activate()
            store = JobStore(config.job.database)
            try:
                job = Job(cell, store, config.job)
                await job.recover()
                with injected_faults("link process SIGKILL", link_losses=KILLS):
                    await job.start(RUN)
                    hit = await kill_the_link_at_random(cell, job, rng)
                    state = await job.wait_state("done", "fault", "paused", timeout=600)
                why = f"seed {seed} (FXCELL_KILL_SEED={seed} repeats it); kills hit {hit}"
                assert state == "done", f"{why}: {job.status()['message']}"
                assert len(hit) == KILLS, f"{why}: the run ended before {KILLS} kills"
                assert cell.link_losses == KILLS, why
                status = job.status()
                assert status["heals"]["count"] >= 1, why
                assert all(h["phase"] != "failed" for h in job.heals), (why, job.heals)
                for sample in status["samples"]:  # the record
                    assert sample["crucible"] == location("rack", sample["rack"]), why
                    assert sample["bead"] == location("tray", sample["tray"]), why
                await job.close()
            finally:
                store.close()
        await assert_in_place(sim, cell.layout, why)


async def assert_in_place(sim: SimulatorHandle, layout: Layout, why: str) -> None:
    """Every crucible in its rack slot, every bead on its tray slot (the simulator's poses)."""
    world = await asyncio.to_thread(sim.objects)
    for sample in RUN["samples"]:
        crucible = world[f"crucible-{sample['rack']}"]
        bead = world[f"crucible-{sample['rack']}.bead"]
        assert place_of(layout, crucible) == location("rack", sample["rack"]), why
        assert place_of(layout, bead) == location("tray", sample["tray"]), why
