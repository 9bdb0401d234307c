"""The lab's fusion job, unchanged, on the shipped Ned2 cell (``config/ned2-cell.yaml``): the
Cell starts the embedded Ned2 simulator with the fusion machine on the Ned2's pins and four
crucibles in the rack; ``Job(cell, store)`` loads the machine, starts it by its start pin,
waits for it, takes the beads to the tray and the crucibles back, with no operator. The same
run through the daemon (``fxcell daemon`` on a Ned2 cell, ``fxcell job start``). Where
everything ends is read from the simulator's own objects."""

from __future__ import annotations

import asyncio
import json
import os
import random
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from fxcell import Cell
from fxcell.client import RemoteCell
from fxcell.config import CONFIG_DIR, CellConfig
from fxcell.daemon.process import DaemonProcess
from fxcell.job import Job, JobStore, final_locations
from fxcell.job.plan import location
from fxcell.layout import Layout
from fxcell.link.ned2.embedded import request
from fxcell.testing import injected_faults
from fxcell.testing.ned2 import ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.slow, pytest.mark.timeout(900)]

CONFIG = CellConfig.load(CONFIG_DIR / "ned2-cell.yaml")
LAYOUT = Layout(CONFIG.layout)
# the guide's example run (docs/guides/ned2.md): its crucibles' rack slots
RUN = Path(__file__).parent.parent / "docs" / "examples" / "ned2-run-4-samples.yaml"
RACK = ["A1", "A2", "A3", "B1"]
# the machine's cycle shortened to 4 s of fusion and 2 s of cooling (the Vitriox: 600 + 300)
MACHINE = ["--machine", "--fusion-time", "4", "--cooling-time", "2"]
TIMEOUT = 600.0
TOKEN = "ned2-job-token-0123456789abcdef"


def objects(host: str) -> dict[str, Any]:
    result: dict[str, Any] = json.loads(request(host, "objects"))
    return result


def place_of(obj: dict[str, Any]) -> str | None:
    """Where an object of the simulated world is, as the job names places (within 1 mm)."""
    if obj["held"]:
        return "gripper"
    position = np.array(obj["pose"][:3])
    for station in LAYOUT:
        if station.config.holds != obj["kind"]:
            continue
        for slot in station.slots:
            if np.linalg.norm(station.grip_pose(slot).position - position) < 1e-3:
                return location(station.name, slot)
    return None


@pytest.fixture
async def cell(tmp_path: Path) -> AsyncIterator[Cell]:
    config = CONFIG.model_copy(
        update={
            "positions_file": tmp_path / "positions.yaml",
            "job": CONFIG.job.model_copy(update={"database": tmp_path / "job.sqlite3"}),
        }
    )
    crucibles = ["--crucibles", ",".join(RACK)]
    # the robot at its own speed (time scale 1: the arm moves as the cell planned it); the
    # machine's durations are given short instead
    options = {"time_scale": 1.0, "extra_args": [*MACHINE, *crucibles]}
    async with Cell(config=config, record=None, simulator_options=options) as c:
        yield c


@pytest.mark.long  # four samples on the Ned2's speeds: minutes of robot time (./dev test -m long)
async def test_four_samples_run_unattended_on_the_ned2_cell(cell: Cell, tmp_path: Path) -> None:
    host = cell.host
    assert host is not None
    before = await asyncio.to_thread(objects, host)
    assert {place_of(o) for o in before.values()} == {location("rack", s) for s in RACK}
    machine = json.loads(await asyncio.to_thread(request, host, "machine"))
    assert machine["state"] == "idle"
    assert machine["io"]["start"]["signal"] == CONFIG.io.signals["machine_start"]

    started = time.monotonic()
    await cell.init()  # the simulated Ned2 boots uncalibrated, as a real one
    await cell.gripper_activate()
    store = JobStore(tmp_path / "job.sqlite3")
    job = Job(cell, store)
    await job.start(RUN)
    state = await job.wait_state("done", "fault", "paused", timeout=TIMEOUT)
    wall = time.monotonic() - started
    assert state == "done", job.message
    print(f"4 samples on the Ned2 simulator: {wall:.1f} s from init to done")

    after = await asyncio.to_thread(objects, host)
    assert job.run is not None
    for sample in job.run.samples:
        crucible = f"crucible-{sample.rack}"
        # every crucible back in its rack slot, empty: the machine fused its sample
        assert place_of(after[crucible]) == location("rack", sample.rack)
        assert after[crucible]["contents"] is None
        # and its bead, carrying the sample, on the sample's tray slot
        bead = after[f"{crucible}.bead"]
        assert place_of(bead) == location("tray", sample.tray)
        assert bead["contents"] == "sample"
    assert len(after) == 2 * len(RACK)  # nothing else appeared
    assert store.locations(1) == final_locations(job.run)
    assert cell.held is None
    machine = json.loads(await asyncio.to_thread(request, host, "machine"))
    assert machine["state"] == "idle"  # the moulds emptied, no fault
    assert machine["fault"] is None
    store.close()


def assert_in_place(world: dict[str, Any], samples: list[dict[str, Any]]) -> None:
    """Every crucible empty in its rack slot, its bead (with the sample) on its tray slot."""
    for sample in samples:
        crucible = f"crucible-{sample['rack']}"
        assert place_of(world[crucible]) == location("rack", sample["rack"])
        assert world[crucible]["contents"] is None
        bead = world[f"{crucible}.bead"]
        assert place_of(bead) == location("tray", sample["tray"])
        assert bead["contents"] == "sample"
    assert len(world) == 2 * len(samples)


def fxcell_cli(url: str, *args: str) -> str:
    """One ``fxcell`` client command against the daemon, as an operator types it."""
    done = subprocess.run(
        [sys.executable, "-m", "fxcell", *args, "--url", url, "--token", TOKEN],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, f"fxcell {' '.join(args)}: {done.stdout}{done.stderr}"
    return done.stdout


@pytest.mark.long  # minutes of robot time again: the long tier (./dev test -m long)
async def test_the_same_run_through_the_daemon_and_the_cli(tmp_path: Path) -> None:
    samples = yaml.safe_load(RUN.read_text())["samples"]
    machine = [*MACHINE, "--crucibles", ",".join(RACK)]
    with ned2_simulator(time_scale=1.0, extra_args=machine) as world:
        config = tmp_path / "cell.yaml"
        config.write_text(
            yaml.safe_dump(
                {  # a user's Ned2 cell: the rest from the shipped config/ned2-cell.yaml
                    "robot": {"kind": "ned2", "host": world.host},
                    "daemon": {"token_file": str(tmp_path / "token")},
                    "job": {"database": str(tmp_path / "job.sqlite3")},
                    "positions_file": str(tmp_path / "positions.yaml"),
                }
            )
        )
        with DaemonProcess.start(config, token=TOKEN) as daemon:
            await asyncio.to_thread(daemon.wait_connected)
            started = time.monotonic()
            for command in (["init"], ["gripper-activate"], ["job", "start", str(RUN)]):
                await asyncio.to_thread(fxcell_cli, daemon.url, *command)
            async with RemoteCell(daemon.url, TOKEN, name="watcher") as cell:
                deadline = time.monotonic() + TIMEOUT
                while (status := await cell.job_status())["state"] not in ("done", "fault"):
                    assert status["state"] != "paused", status
                    assert time.monotonic() < deadline, status
                    await asyncio.sleep(0.2)
            assert status["state"] == "done", status
            print(f"4 samples through the daemon: {time.monotonic() - started:.1f} s")
        assert_in_place(await asyncio.to_thread(world.objects), samples)


DROPS = 4


@pytest.mark.long  # one sample, its network dropped: about a minute (./dev test -m long)
async def test_a_ned2_run_whose_network_drops_again_and_again_ends_in_place_by_itself(
    cell: Cell, tmp_path: Path
) -> None:
    # The Ned2's network cut at random moments (seedable: FXCELL_KILL_SEED=N) of a
    # one-sample run: the link comes back, a move the robot still ran is stopped, and the
    # job heals each loss without the operator.
    seed = int(os.environ.get("FXCELL_KILL_SEED", random.randrange(1 << 30)))
    rng = random.Random(seed)
    host = cell.host
    assert host is not None
    await cell.init()
    await cell.gripper_activate()
    store = JobStore(tmp_path / "job.sqlite3")
    job = Job(cell, store)
    sample = {"id": "S01", "rack": "A1", "tray": "A1"}
    hit: list[str] = []
    with injected_faults("the Ned2's network dropped at random moments", link_losses=DROPS):
        await job.start({"name": "one sample", "samples": [sample]})
        while len(hit) < DROPS and job.state in ("running", "waiting_for_machine"):
            await asyncio.sleep(rng.uniform(2.0, 8.0))  # a random moment, not a condition
            link = cell.link
            if job.state not in ("running", "waiting_for_machine") or link is None:
                break
            if not link.up:  # still coming back from the previous drop: that one counts once
                continue
            hit.append(job.status()["step"] or job.state)
            await asyncio.to_thread(request, host, "inject drop_connection")
        state = await job.wait_state("done", "fault", "paused", timeout=TIMEOUT)
    assert state == "done", f"seed {seed}, drops during {hit}: {job.message}"
    assert len(hit) == DROPS, f"seed {seed}: the run ended after {len(hit)} drops"
    assert cell.link_losses == DROPS, f"seed {seed}, drops during {hit}"
    world = await asyncio.to_thread(objects, host)
    assert place_of(world["crucible-A1"]) == location("rack", "A1")
    assert world["crucible-A1"]["contents"] is None
    assert place_of(world["crucible-A1.bead"]) == location("tray", "A1")
    assert world["crucible-A1.bead"]["contents"] == "sample"
    assert job.run is not None
    assert store.locations(1) == final_locations(job.run)
    store.close()
