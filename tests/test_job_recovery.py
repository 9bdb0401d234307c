"""Crash anywhere, recover from the database, resume: the same end state, nothing unaccounted for.

A crash is a :class:`SimulatedCrash` (a ``BaseException``: no handler of the job runs) raised
by the fake cell at one of its awaits (mid-step: before or after the object moved) or by the
store just before or just after a commit (the step boundaries). A new :class:`Job` on a new
connection to the same database then recovers. The last test kills real processes (SIGKILL).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from job_fakes import (
    GRIPPER,
    FakeCell,
    SimulatedCrash,
    World,
    answers_from,
    expected_world,
    sample_run,
)

from fxcell.errors import JobAnswerError
from fxcell.job import Job, JobStore, Run, final_locations
from fxcell.job.runner import CHART  # noqa: F401 - the chart ships beside the runner

TIMEOUT = 30.0
SAMPLES = 5  # two fusion cycles (4 + 1)


class CrashingStore(JobStore):
    """A store whose ``crash_at``-th write dies just before (or just after) it commits."""

    WRITES = ("create_run", "begin_step", "end_step", "set_state", "close_open_steps")

    def __init__(
        self, path: Path, cell: FakeCell, crash_at: int | None = None, after: bool = False
    ) -> None:
        super().__init__(path)
        self.cell = cell
        self.crash_at = crash_at
        self.after = after
        self.writes = 0

    def __getattribute__(self, name: str) -> Any:
        attr = super().__getattribute__(name)
        if name not in CrashingStore.WRITES:
            return attr

        def write(*args: Any, **kwargs: Any) -> Any:
            self.writes += 1
            if self.cell.crashed:  # the process is dead (the cell crashed it)
                raise SimulatedCrash("after the crash")
            hit = self.writes == self.crash_at
            if hit:
                self.cell.crashed = True
            if hit and not self.after:
                raise SimulatedCrash(f"crash before write {self.writes} ({name})")
            result = attr(*args, **kwargs)
            if hit:
                raise SimulatedCrash(f"crash after write {self.writes} ({name})")
            return result

        return write


def where_recorded(store: JobStore, run_id: int, run: Run) -> dict[str, str]:
    """The recorded location of every object: ``crucible:S1`` -> ``rack:A1``."""
    ids = {s.index: s.id for s in run.samples}
    return {f"{obj}:{ids[idx]}": loc for (idx, obj), loc in store.locations(run_id).items()}


def assert_accounted_for(job: Job, store: JobStore, world: World, run: Run) -> None:
    """Every object is where the database says, or where a question offers as a choice.

    A bead the database does not know yet (the machine finished while the job was down) is
    in the mould of the machine position where its crucible is recorded.
    """
    assert job.run_id is not None
    recorded = where_recorded(store, job.run_id, run)
    actual = {obj: place for place, obj in world.places.items()}
    assert set(recorded) <= set(actual), "an object is lost"
    for obj in set(actual) - set(recorded):
        assert obj.startswith("bead:"), f"{obj} is not recorded"
        crucible = recorded["crucible:" + obj.split(":")[1]]
        assert crucible.startswith("machine:")
        assert actual[obj] == "mould:" + crucible.split(":")[1]
        del actual[obj]
    asked = {f"{q.object}:{q.sample}": q.choices for q in job.questions.values()}
    for obj, place in actual.items():
        if obj in asked:
            assert place in asked[obj]
            assert recorded[obj] in asked[obj]
        else:
            assert recorded[obj] == place, f"{obj} is at {place}, recorded at {recorded[obj]}"


async def crash_and_recover(
    tmp_path: Path, *, tick: int | None = None, write: int | None = None, after: bool = False
) -> tuple[bool, FakeCell]:
    """Run until the crash, recover with a new job, resume to the end; whether it crashed."""
    db = tmp_path / f"job-{tick}-{write}-{after}.sqlite3"
    run = sample_run(SAMPLES)
    world = World.for_run(run)
    cell = FakeCell(world)
    cell.crash_at = tick
    first = CrashingStore(db, cell, write, after)
    job = Job(cell, first)
    with contextlib.suppress(SimulatedCrash):
        await job.start(run)
        assert job._task is not None
        await asyncio.wait_for(job._task, TIMEOUT)
    crashed = cell.crashed
    first.close()
    cell.crash_at = None
    cell.crashed = False
    store = JobStore(db)
    try:
        recovered = Job(cell, store)
        await recovered.recover()
        if not crashed:
            assert recovered.state == "idle"
            assert world.places == expected_world(run)
            return False, cell
        if recovered.state == "idle" and store.steps(1):  # it died after recording "done"
            assert store.run(1).state == "done"
        elif recovered.state == "idle":  # it died before the run was recorded: nothing moved
            assert world.places == World.for_run(run).places
            await recovered.start(run)
        else:
            assert recovered.state == "paused"
            assert_accounted_for(recovered, store, world, run)
            await recovered.resume(answers_from(world, recovered))
        if recovered.run_id is not None:
            state = await recovered.wait_state("done", "paused", "fault", timeout=TIMEOUT)
            assert state == "done", recovered.message
        assert world.places == expected_world(run)
        assert store.locations(1) == final_locations(run)
        assert store.unfinished_run() is None
        return True, cell
    finally:
        store.close()
        cell.machine.close()


@pytest.mark.slow
@pytest.mark.timeout(600)
async def test_a_crash_at_any_await_of_the_cell_resumes_to_the_same_end(tmp_path: Path) -> None:
    tick = 1
    while (await crash_and_recover(tmp_path, tick=tick))[0]:
        tick += 1
    assert tick > 100  # every await of a two-cycle run was a crash point


@pytest.mark.slow
@pytest.mark.timeout(600)
@pytest.mark.parametrize("after", [False, True], ids=["before-commit", "after-commit"])
async def test_a_crash_at_any_write_resumes_to_the_same_end(tmp_path: Path, after: bool) -> None:
    write = 1
    while (await crash_and_recover(tmp_path, write=write, after=after))[0]:
        write += 1
    assert write > 70  # every step's start and end of a two-cycle run


async def crashed_mid_step(
    tmp_path: Path, action: str, moved: bool, *, gripper: bool = False
) -> tuple[Job, FakeCell, Run]:
    """Crash in the first ``action`` (pick/place), before or after its object moved;
    ``gripper``: the restarted job can read the gripper's object detection (a new process:
    the cell does not know what it holds)."""
    run = sample_run(1)
    world = World.for_run(run)
    cell = FakeCell(world)
    ticks = {("pick", False): 2, ("pick", True): 3, ("place", False): 5, ("place", True): 6}
    cell.crash_at = ticks[(action, moved)]
    first = JobStore(tmp_path / "job.sqlite3")
    job = Job(cell, first)
    await job.start(run)
    assert job._task is not None
    with pytest.raises(SimulatedCrash):
        await asyncio.wait_for(job._task, TIMEOUT)
    first.close()
    cell.crash_at = None
    cell.crashed = False
    if gripper:
        cell.gripper.readable = True
        cell.held = None
    recovered = Job(cell, JobStore(tmp_path / "job.sqlite3"))
    await recovered.recover()
    return recovered, cell, run


async def test_killed_mid_pick_holding_the_crucible_asks_and_goes_on_to_place(
    tmp_path: Path,
) -> None:
    job, cell, run = await crashed_mid_step(tmp_path, "pick", moved=True)
    assert cell.world.places == {GRIPPER: "crucible:S1"}
    assert job.state == "paused"
    assert "interrupted" in job.message
    (q,) = job.questions.values()
    assert (q.id, q.choices) == ("S1/crucible", ("rack:A1", "gripper"))
    moves = len(cell.moves)
    with pytest.raises(JobAnswerError):
        await job.resume()
    assert len(cell.moves) == moves  # nothing moved without the answer
    homes = cell.homes
    await job.resume({"S1/crucible": "gripper"})
    assert await job.wait_state("done", "paused", "fault", timeout=TIMEOUT) == "done"
    assert cell.homes == homes + 3  # home first: the arm stopped somewhere mid-step
    assert cell.moves[moves] == ("place", "machine", "A1")  # no second pick
    assert cell.world.places == expected_world(run)
    assert job.run_id is not None
    resolved = [s for s in job.store.steps(job.run_id) if s.seq == 0]
    assert [(s.outcome, s.detail) for s in resolved] == [
        ("interrupted", ""),
        ("done", "operator: crucible of sample S1 is at gripper"),
    ]
    job.store.close()
    cell.machine.close()


async def test_killed_mid_place_before_letting_go_asks_and_places_again(tmp_path: Path) -> None:
    job, cell, run = await crashed_mid_step(tmp_path, "place", moved=False)
    (q,) = job.questions.values()
    assert q.choices == ("gripper", "machine:A1")
    assert q.text.startswith("The crucible of sample S1 was being placed in machine position A1")
    moves = len(cell.moves)
    await job.resume({q.id: "gripper"})
    assert await job.wait_state("done", "paused", "fault", timeout=TIMEOUT) == "done"
    assert cell.moves[moves] == ("place", "machine", "A1")
    assert cell.world.places == expected_world(run)
    job.store.close()
    cell.machine.close()


async def test_killed_between_steps_resumes_without_questions(tmp_path: Path) -> None:
    run = sample_run(2)
    world = World.for_run(run)
    cell = FakeCell(world)
    first = CrashingStore(tmp_path / "job.sqlite3", cell, crash_at=3, after=True)  # 1st step's end
    job = Job(cell, first)
    await job.start(run)
    assert job._task is not None
    with pytest.raises(SimulatedCrash, match="end_step"):
        await asyncio.wait_for(job._task, TIMEOUT)
    first.close()
    cell.crashed = False
    store = JobStore(tmp_path / "job.sqlite3")
    recovered = Job(cell, store)
    status = await recovered.recover()
    assert status["state"] == "paused"
    assert status["questions"] == []
    assert status["progress"]["done"] == 1
    assert "interrupted" not in recovered.message
    homes = cell.homes
    await recovered.resume()
    assert await recovered.wait_state("done", timeout=TIMEOUT) == "done"
    assert cell.homes == homes + 2  # only the plan's
    assert world.places == expected_world(run)
    store.close()
    cell.machine.close()


# ----------------------------------------------------------------- real processes, SIGKILL

FAKES = Path(__file__).with_name("job_fakes.py")


def _steps_ended(db: Path) -> int:
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as con:
            return int(
                con.execute("SELECT COUNT(*) FROM steps WHERE ended IS NOT NULL").fetchone()[0]
            )
    except sqlite3.Error:  # not created yet
        return 0


def _start(db: Path, world: Path, run_file: Path) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(FAKES.parent)}
    return subprocess.Popen(
        [sys.executable, str(FAKES), str(db), str(world), str(run_file)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_sigkill_at_random_points_then_restart_ends_with_every_sample_home(tmp_path: Path) -> None:
    run = sample_run(6)
    run_file = tmp_path / "run.yaml"
    run_file.write_text(yaml.safe_dump(run.to_dict()))
    world_file = tmp_path / "world.json"
    World.for_run(run, world_file)
    db = tmp_path / "job.sqlite3"
    rng = random.Random(15)
    total = 2 * 6 * 3 + 3 * 2 + 1  # steps of a two-cycle, six-sample run
    kill_points = sorted(rng.sample(range(1, total - 2), 6))
    for point in kill_points:
        proc = _start(db, world_file, run_file)
        deadline = time.monotonic() + 120
        while _steps_ended(db) < point and proc.poll() is None:
            assert time.monotonic() < deadline, "the job did not get on"
            time.sleep(0.001)
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
        assert proc.returncode == -signal.SIGKILL, "the job ended before its kill point"
    proc = _start(db, world_file, run_file)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, out + err
    assert out.splitlines()[-1] == "done run 1 done"
    world = World.load(world_file)
    assert world.places == expected_world(run)
    store = JobStore(db)
    assert store.unfinished_run() is None
    assert store.locations(1) == final_locations(run)
    store.close()


@pytest.mark.parametrize(("action", "moved"), [("pick", True), ("pick", False), ("place", False)])
async def test_the_grippers_object_detection_answers_where_the_object_is(
    tmp_path: Path, action: str, moved: bool
) -> None:
    job, cell, run = await crashed_mid_step(tmp_path, action, moved, gripper=True)
    assert job.questions == {}  # nothing to ask: the gripper said it
    assert job.locations[(0, "crucible")] == cell.world.where("crucible:S1")
    assert "answer where" not in job.message
    await job.resume()
    assert await job.wait_state("done", "paused", "fault", timeout=TIMEOUT) == "done"
    assert cell.world.places == expected_world(run)
    job.store.close()
    cell.machine.close()
