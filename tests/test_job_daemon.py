"""The fusion-machine job end to end: the daemon on a simulator (cell, Hand-E, fusion machine)
running a run through RemoteCell, killed with SIGKILL at several points and restarted; the
simulator's object poses say where every crucible and bead ended up.

The simulator runs in its own process (the lab's robot and machine outlive the daemon), so a
killed daemon leaves the world as it was: objects where the arm left them.
"""

from __future__ import annotations

import asyncio
import random
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from fxcell.client import RemoteCell
from fxcell.config import CellConfig
from fxcell.daemon.process import DaemonProcess
from fxcell.job.plan import location
from fxcell.layout import Layout
from fxcell.testing import SimulatorHandle, brisk_limits, simulator

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

TOKEN = "job-test-token-0123456789abcdef"
LAYOUT = Layout(CellConfig.load().layout)
RUN = {
    "name": "two samples",
    "samples": [
        {"id": "S01", "rack": "A1", "machine": "A1", "tray": "A1"},
        {"id": "S02", "rack": "A2", "machine": "A2", "tray": "A2"},
    ],
}


@pytest.fixture(scope="module")
def sim() -> Iterator[SimulatorHandle]:
    args = ["--fusion-time", "20", "--cooling-time", "10", "--crucibles", "A1,A2"]
    with simulator(time_scale=0.05, extra_args=args) as s:  # fusion 1 s, cooling 0.5 s
        yield s


def write_config(tmp: Path, host: str) -> Path:
    config = {
        "robot": {"host": host},
        "daemon": {"token_file": str(tmp / "token")},
        "limits": brisk_limits(),
        "job": {"database": str(tmp / "job.sqlite3"), "ready_timeout": 30.0},
        "positions_file": str(tmp / "positions.yaml"),
    }
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def place_of(obj: dict[str, Any]) -> str | None:
    """Where an object of the simulated world is, as the job names places."""
    if obj["held"]:
        return "gripper"
    position = np.array(obj["pose"][:3])
    for station in LAYOUT:
        for slot in station.slots:
            if np.linalg.norm(station.grip_pose(slot).position - position) < 1e-3:
                return location(station.name, slot)
    return None


async def job_state(cell: RemoteCell, *states: str, within: float = 120.0) -> dict[str, Any]:
    deadline = time.monotonic() + within
    while True:
        status = await cell.job_status()
        if status["state"] in states:
            return status
        assert time.monotonic() < deadline, f"job stayed {status['state']}: {status}"
        await asyncio.sleep(0.05)


def start_daemon(config: Path) -> DaemonProcess:
    daemon = DaemonProcess.start(config, token=TOKEN)
    daemon.wait_connected()
    return daemon


async def resume_as_the_operator(daemon: DaemonProcess, sim: SimulatorHandle) -> dict[str, Any]:
    """After a restart: init the robot, answer the questions from what is really there."""
    async with RemoteCell(daemon.url, TOKEN, name="operator") as cell:
        status = await job_state(cell, "paused", "fault", "running", "waiting_for_machine")
        if status["state"] in ("running", "waiting_for_machine"):
            return status
        return await answer_and_resume(cell, sim, status)


async def answer_and_resume(
    cell: RemoteCell, sim: SimulatorHandle, status: dict[str, Any]
) -> dict[str, Any]:
    """What the operator does: init, activate the gripper, look where each questioned
    object is (the simulator's truth), answer, resume."""
    await cell.init()
    await cell.gripper_activate()
    world = await asyncio.to_thread(sim.objects)
    answers = {}
    for q in status["questions"]:
        name = f"crucible-{_rack_slot(q['sample'])}"
        if q["object"] == "bead":
            name += ".bead"
        truth = place_of(world[name])
        assert truth in q["choices"], (q, truth)
        answers[q["id"]] = truth
    return await cell.job_resume(answers)


def _rack_slot(sample: str) -> str:
    return next(s["rack"] for s in RUN["samples"] + SIXTEEN["samples"] if s["id"] == sample)


async def kill_during(daemon: DaemonProcess, step_prefix: str, nth: int = 0) -> str:
    """SIGKILL the daemon a random moment into the ``nth`` step whose text starts so."""
    async with RemoteCell(daemon.url, TOKEN, name="watcher") as cell:
        seen: list[str] = []
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            status = await cell.job_status()
            step = status.get("step") or ""
            working = status["state"] in ("running", "waiting_for_machine")
            if working and step.startswith(step_prefix) and (not seen or seen[-1] != step):
                seen.append(step)
            if len(seen) > nth:
                break
            await asyncio.sleep(0.02)
        else:
            tail = "\n".join(daemon.output[-20:])
            raise AssertionError(f"no step {step_prefix!r} (#{nth}) came: {status}\n{tail}")
    await asyncio.sleep(random.uniform(0.1, 0.8))  # the kill moment, not a wait
    daemon.stop(signal.SIGKILL)
    return seen[-1]


async def finish(cell: RemoteCell, daemon: DaemonProcess, within: float) -> dict[str, Any]:
    """Wait for ``done``: a fault or a pause on the way (the cell stopping a step by itself)
    fails the run; no operator resumes past it."""
    final = await job_state(cell, "done", "fault", "paused", within=within)
    assert final["state"] == "done", (final["message"], daemon.output[-15:])
    return final


async def assert_in_place(sim: SimulatorHandle, run: dict[str, Any], why: object) -> None:
    """Every crucible in its rack slot, every bead on its tray slot (the simulator's poses)."""
    world = await asyncio.to_thread(sim.objects)
    for sample in run["samples"]:
        crucible = world[f"crucible-{sample['rack']}"]
        bead = world[f"crucible-{sample['rack']}.bead"]
        assert place_of(crucible) == location("rack", sample["rack"]), why
        assert place_of(bead) == location("tray", sample["tray"]), why


@pytest.mark.long  # a 4-sample run with five restarts: minutes of robot time (./dev test -m long)
@pytest.mark.injects_faults("the daemon SIGKILLed five times, mid-move")
async def test_a_run_killed_five_times_ends_with_every_sample_in_place(
    sim: SimulatorHandle, tmp_path: Path
) -> None:
    config = write_config(tmp_path, sim.host)
    daemon = await asyncio.to_thread(start_daemon, config)
    try:
        async with RemoteCell(daemon.url, TOKEN, name="operator") as cell:
            await cell.init()
            await cell.gripper_activate()
            started = await cell.job_start(RUN)
            assert started["state"] in ("running", "waiting_for_machine")
        kills = [
            ("pick the crucible", 0),  # mid-grasp in the rack
            ("place the crucible", 1),  # the second crucible on its way into the machine
            ("wait for fusion", 0),  # during the fusion
            ("pick the bead", 0),  # a bead out of its mould
            ("place the crucible", 0),  # a crucible on its way back to the rack
        ]
        interrupted = []
        for prefix, nth in kills:
            interrupted.append(await kill_during(daemon, prefix, nth))
            daemon = await asyncio.to_thread(start_daemon, config)
            await resume_as_the_operator(daemon, sim)
        async with RemoteCell(daemon.url, TOKEN, name="operator") as cell:
            done = await finish(cell, daemon, within=240)
        assert all(s["crucible"].startswith("rack:") for s in done["samples"]), done
        await assert_in_place(sim, RUN, interrupted)
    finally:
        daemon.stop()


async def test_a_missing_crucible_pauses_the_run_naming_the_slot(
    sim: SimulatorHandle, tmp_path: Path
) -> None:
    config = write_config(tmp_path, sim.host)
    daemon = await asyncio.to_thread(start_daemon, config)
    try:
        async with RemoteCell(daemon.url, TOKEN, name="operator") as cell:
            await cell.init()
            await cell.gripper_activate()
            run = {"samples": [{"id": "S09", "rack": "C3", "machine": "A3", "tray": "C3"}]}
            await cell.job_start(run)  # the simulator's rack has crucibles in A1 and A2 only
            paused = await job_state(cell, "paused", "fault")
            assert paused["state"] == "paused", paused["message"]
            assert "no crucible detected in rack slot C3" in paused["message"]
            assert paused["samples"][0]["crucible"] == "rack:C3"  # the record did not move it
            await cell.job_discard()
    finally:
        daemon.stop()


SIXTEEN = {
    "name": "sixteen samples",
    "samples": [
        {"id": f"S{i + 1:02d}", "rack": slot, "machine": f"A{i % 4 + 1}", "tray": slot}
        for i, slot in enumerate(f"{row}{col}" for row in "ABCD" for col in range(1, 5))
    ],
}


@pytest.mark.long
@pytest.mark.timeout(1800)
async def test_a_sixteen_sample_run_ends_with_every_bead_on_the_tray(tmp_path: Path) -> None:
    # Four fusion cycles: 10-15 min of robot time, hence `long` (./dev test -m long).
    args = ["--fusion-time", "20", "--cooling-time", "10", "--crucibles", "16"]
    with simulator(time_scale=0.05, extra_args=args) as world:
        config = write_config(tmp_path, world.host)
        daemon = await asyncio.to_thread(start_daemon, config)
        try:
            async with RemoteCell(daemon.url, TOKEN, name="operator") as cell:
                await cell.init()
                await cell.gripper_activate()
                await cell.job_start(SIXTEEN)
                done = await finish(cell, daemon, within=1500)
            print(f"recoveries from lost links: {done['heals']['count']}")
            await assert_in_place(world, SIXTEEN, "sixteen samples")
        finally:
            daemon.stop()
