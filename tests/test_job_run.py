"""The job on a fake cell and machine: whole runs, a missing crucible, pause, abort, faults."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from job_fakes import FakeCell, World, expected_world, sample_run

from fxcell.cell.statemachine import diagram_path, read_statechart, to_mermaid
from fxcell.config import JobConfig
from fxcell.errors import (
    ConnectionLostError,
    JobAnswerError,
    JobError,
    JobSpecError,
    JobStateError,
    JobStoreError,
    ProtectiveStopError,
)
from fxcell.job import Job, JobStore, Run, final_locations, make_plan
from fxcell.job.runner import CHART
from fxcell.protocol import RobotState

TIMEOUT = 30.0  # generous: a busy 2-core machine


@pytest.fixture
def store(tmp_path: Path) -> Iterator[JobStore]:
    s = JobStore(tmp_path / "job.sqlite3")
    yield s
    s.close()


class Bench:
    """A run, its world, the fake cell and the job, with the events it emitted."""

    def __init__(
        self, store: JobStore, n: int, config: JobConfig | None = None, fusion_time: float = 0.0
    ) -> None:
        self.run: Run = sample_run(n)
        self.world = World.for_run(self.run)
        self.cell = FakeCell(self.world, fusion_time=fusion_time)
        self.events: list[dict[str, Any]] = []
        self.store = store
        self.job = Job(self.cell, store, config, on_event=self.events.append)

    async def until(self, *states: str) -> str:
        return await self.job.wait_state(*states, timeout=TIMEOUT)

    def assert_finished(self) -> None:
        assert self.job.state == "done"
        assert self.world.places == expected_world(self.run)
        assert self.job.run_id is not None
        assert self.store.locations(self.job.run_id) == final_locations(self.run)
        assert self.store.unfinished_run() is None


@pytest_asyncio.fixture
async def bench(store: JobStore) -> AsyncIterator[Bench]:
    b = Bench(store, 4)
    yield b
    await b.job.close()
    b.cell.machine.close()


async def test_sixteen_samples_end_with_every_bead_on_its_tray_slot_and_every_crucible_home(
    store: JobStore,
) -> None:
    b = Bench(store, 16, fusion_time=0.01)
    await b.job.recover()
    run_id = await b.job.start(b.run)
    assert await b.until("done", "paused", "fault") == "done", b.job.message
    b.assert_finished()
    assert b.cell.machine.cycles == 4
    steps = store.steps(run_id)
    assert [s.seq for s in steps] == list(range(len(make_plan(b.run))))
    assert all(s.outcome == "done" and s.ended is not None and s.ended >= s.started for s in steps)
    assert b.job.progress() == {"done": len(steps), "total": len(steps), "eta": 0}
    assert store.run(run_id).state == "done"
    status = b.job.status()
    assert status["samples"][0] == {
        "id": "S1",
        "rack": "A1",
        "machine": "A1",
        "tray": "D4",
        "cycle": 1,
        "crucible": "rack:A1",
        "bead": "tray:D4",
    }
    # per cycle: load four crucibles, then unload four beads, then return four crucibles
    first = b.cell.moves[:24]
    assert [(a, st) for a, st, _ in first[:8]] == [("pick", "rack"), ("place", "machine")] * 4
    assert [(a, st) for a, st, _ in first[8:16]] == [("pick", "moulds"), ("place", "tray")] * 4
    assert [(a, st) for a, st, _ in first[16:24]] == [("pick", "machine"), ("place", "rack")] * 4


async def test_every_step_and_location_change_is_an_event(bench: Bench) -> None:
    stream = bench.job.events()
    first = asyncio.ensure_future(anext(stream))
    await asyncio.sleep(0)
    await bench.job.start(bench.run)
    assert (await first)["event"] == "state"
    await stream.aclose()
    await bench.until("done")
    kinds = [e["event"] for e in bench.events]
    assert kinds[0] == "state"
    assert kinds.count("progress") == len(bench.job.plan)
    ends = [e for e in bench.events if e["event"] == "step" and e["phase"] == "end"]
    assert len(ends) == len(bench.job.plan)
    moved = [m for e in ends for m in e["moved"]]
    assert moved[0] == {"sample": "S1", "object": "crucible", "from": "rack:A1", "to": "gripper"}
    beads = [m for m in moved if m["object"] == "bead" and m["from"] is None]
    assert [m["to"] for m in beads] == ["mould:A1", "mould:A2", "mould:A3", "mould:A4"]
    states = [(e["from"], e["to"]) for e in bench.events if e["event"] == "state"]
    assert states == [
        ("idle", "running"),
        ("running", "waiting_for_machine"),
        ("waiting_for_machine", "running"),
        ("running", "done"),
    ]
    assert all(e["run"] == bench.job.run_id and e["time"] > 0 for e in bench.events)


async def test_a_missing_crucible_pauses_the_run_with_a_clear_message(bench: Bench) -> None:
    crucible = bench.world.places.pop("rack:A3")
    await bench.job.start(bench.run)
    assert await bench.until("paused", "done", "fault") == "paused"
    assert bench.job.message.startswith("no crucible detected in rack slot A3")
    assert bench.job.questions == {}
    run_id = bench.job.run_id
    assert run_id is not None
    last = bench.store.steps(run_id)[-1]
    assert (last.kind, last.outcome, last.detail) == (
        "pick:rack",
        "failed",
        "no crucible detected in rack slot A3",
    )
    assert bench.store.locations(run_id)[(2, "crucible")] == "rack:A3"
    assert bench.store.run(run_id).state == "paused"
    bench.world.places["rack:A3"] = crucible  # the operator puts it back
    await bench.job.resume()
    assert await bench.until("done", "paused", "fault") == "done"
    bench.assert_finished()


async def test_pause_finishes_the_current_step_then_resume_goes_on(bench: Bench) -> None:
    bench.cell.gate = asyncio.Event()
    await bench.job.start(bench.run)
    await asyncio.wait_for(bench.cell.in_step.wait(), TIMEOUT)
    await bench.job.pause()
    assert bench.job.state == "pausing"
    with pytest.raises(JobStateError, match="job pause\\(\\) is refused: the job is pausing"):
        await bench.job.pause()
    bench.cell.gate.set()
    assert await bench.until("paused") == "paused"
    assert bench.world.places.get("gripper") == "crucible:S1"  # the pick finished, no more
    assert bench.job.progress()["done"] == 1
    moves = len(bench.cell.moves)
    await bench.job.resume()
    assert await bench.until("done", "fault") == "done"
    assert bench.cell.moves[moves] == ("place", "machine", "A1")
    bench.assert_finished()


async def test_pause_while_the_machine_fuses_waits_no_longer(store: JobStore) -> None:
    b = Bench(store, 1, fusion_time=0.3)
    await b.job.start(b.run)
    await b.until("waiting_for_machine")
    await b.job.pause()
    assert await b.until("paused") == "paused"
    await b.job.resume()
    assert await b.until("done", "fault") == "done"
    b.assert_finished()
    b.cell.machine.close()


async def test_abort_mid_pick_brakes_and_asks_where_the_crucible_is(bench: Bench) -> None:
    bench.cell.gate = asyncio.Event()
    await bench.job.start(bench.run)
    await asyncio.wait_for(bench.cell.in_step.wait(), TIMEOUT)
    await bench.job.abort()
    assert bench.job.state == "paused"
    (question,) = bench.job.questions.values()
    assert question.id == "S1/crucible"
    assert question.choices == ("rack:A1", "gripper")
    assert "rack slot A1" in question.text
    assert question.text.startswith("The crucible of sample S1 was being picked from rack slot A1")
    assert any(e["event"] == "question" for e in bench.events)
    bench.cell.gate = None
    with pytest.raises(JobAnswerError, match="answer first"):
        await bench.job.resume()
    with pytest.raises(JobAnswerError, match="'tray:A1' is not one of rack:A1, gripper"):
        await bench.job.resume({"S1/crucible": "tray:A1"})
    with pytest.raises(JobAnswerError, match="no such question"):
        await bench.job.resume({"S1/crucible": "rack:A1", "S9/bead": "gripper"})
    assert bench.job.state == "paused"
    homes = bench.cell.homes
    await bench.job.resume({"S1/crucible": "rack:A1"})
    assert await bench.until("done", "fault", "paused") == "done"
    assert bench.cell.homes == homes + 3  # first home after the abort, then the plan's two
    bench.assert_finished()
    assert bench.job.run_id is not None
    outcomes = [s.outcome for s in bench.store.steps(bench.job.run_id) if s.seq == 0]
    assert outcomes == ["aborted", "done"]


async def test_a_failed_home_after_an_answer_asks_again_with_the_fault(
    bench: Bench, monkeypatch: pytest.MonkeyPatch
) -> None:
    bench.cell.gate = asyncio.Event()
    await bench.job.start(bench.run)
    await asyncio.wait_for(bench.cell.in_step.wait(), TIMEOUT)
    await bench.job.abort()
    bench.cell.gate = None
    home = bench.cell.go_home

    async def stopped() -> None:
        monkeypatch.setattr(bench.cell, "go_home", home)
        raise ProtectiveStopError("protective stop")

    monkeypatch.setattr(bench.cell, "go_home", stopped)
    await bench.job.resume({"S1/crucible": "rack:A1"})
    assert await bench.until("fault", "done") == "fault"
    assert bench.job.message.startswith("going home after the interruption failed")
    # the step is still unsettled: the fault shows the question that resume will ask
    (question,) = bench.job.status()["questions"]
    assert question["id"] == "S1/crucible"
    await bench.job.resume({"S1/crucible": "rack:A1"})
    assert await bench.until("done", "fault", "paused") == "done"
    bench.assert_finished()


async def test_a_machine_error_while_fusing_faults_and_resume_waits_again(store: JobStore) -> None:
    b = Bench(store, 2, fusion_time=0.3)
    await b.job.start(b.run)
    await b.until("waiting_for_machine")
    b.cell.machine.fail()
    assert await b.until("fault") == "fault"
    assert b.job.message == "the fusion machine reports an error"
    b.cell.io.write("machine_error", False)  # the operator clears it; the cycle goes on
    await b.job.resume()
    assert await b.until("done", "fault", "paused") == "done"
    b.assert_finished()
    b.cell.machine.close()


async def test_a_machine_error_before_a_step_faults_at_once(bench: Bench) -> None:
    bench.cell.machine.fail()
    await bench.job.start(bench.run)
    assert await bench.until("fault", "done") == "fault"
    assert bench.cell.moves == []
    assert bench.job.message == "the fusion machine reports an error"


async def test_a_machine_that_never_starts_faults_after_the_start_timeout(store: JobStore) -> None:
    b = Bench(store, 1, JobConfig(start_timeout=0.05))
    b.cell.io.on_set.clear()  # the machine ignores the start pulse
    await b.job.start(b.run)
    assert await b.until("fault", "done") == "fault"
    assert b.job.message == "the fusion machine did not report busy within 0.05 s"
    assert b.cell.io.get("machine_start") is False


async def test_manual_mode_asks_the_operator_to_start_and_to_confirm_done(store: JobStore) -> None:
    b = Bench(store, 2, JobConfig(manual=True))
    await b.job.start(b.run)
    with pytest.raises(JobStateError, match="confirm"):
        await b.job.confirm()
    await b.until("waiting_for_machine")
    assert b.job.prompt is not None
    assert b.job.prompt["id"] == "machine_started"
    with pytest.raises(JobAnswerError, match="asks 'machine_started', not 'machine_done'"):
        await b.job.confirm("machine_done")
    await b.cell.io.set("machine_start", True)  # the operator presses start on the machine
    await b.job.confirm("machine_started")
    async with asyncio.timeout(TIMEOUT):  # the job goes on to its wait step
        while b.job.prompt is None or b.job.prompt["id"] != "machine_done":
            assert b.job.state in ("running", "waiting_for_machine"), b.job.message
            await asyncio.sleep(0.001)
    assert b.cell.machine.state == "done"
    await b.job.confirm()
    assert await b.until("done", "fault", "paused") == "done"
    b.assert_finished()
    assert [e["id"] for e in b.events if e["event"] == "prompt"] == [
        "machine_started",
        "machine_done",
    ]


async def test_commands_outside_their_states_are_refused(bench: Bench) -> None:
    with pytest.raises(JobStateError, match="the job is idle \\(pause needs running"):
        await bench.job.pause()
    with pytest.raises(JobStateError):
        await bench.job.resume()
    with pytest.raises(JobSpecError):
        await bench.job.start({"samples": [{"id": "x", "rack": "Q1", "tray": "A1"}]})
    assert bench.job.state == "idle"
    assert bench.store.unfinished_run() is None
    bench.cell.gate = asyncio.Event()
    await bench.job.start(bench.run)
    with pytest.raises(JobStateError, match="start"):
        await bench.job.start(bench.run)
    await bench.job.abort()


async def test_an_unfinished_run_blocks_a_new_one_until_discarded(bench: Bench) -> None:
    bench.cell.gate = asyncio.Event()
    first = await bench.job.start(bench.run)
    await bench.job.abort()
    other = Job(bench.cell, bench.store)
    with pytest.raises(JobError, match=f"run {first} .* is unfinished"):
        await other.start(bench.run)
    await other.recover()
    assert other.state == "paused"
    await other.discard()
    assert other.state == "idle"
    assert bench.store.unfinished_run() is None
    assert bench.store.run(first).state == "discarded"


async def test_time_left_comes_from_measured_step_durations(store: JobStore) -> None:
    b = Bench(store, 2)
    b.cell.delay = 0.001
    await b.job.start(b.run)
    await b.until("done")
    means = store.mean_durations()
    second = Bench(store, 2)
    await second.job.start(second.run)
    eta = second.job.progress()["eta"]  # before the task has run a step
    assert eta == pytest.approx(sum(means[s.kind] for s in second.job.plan), abs=0.1)
    assert eta < 60  # not the unmeasured fusion estimate (900 s)
    await second.until("done")
    b.cell.machine.close()
    second.cell.machine.close()


def test_the_job_statechart_drawing_is_current() -> None:
    chart = read_statechart(CHART)
    assert diagram_path(CHART).read_text() == to_mermaid(chart), "run `fxcell statechart`"
    states = set(chart.leaf_states())
    assert states == {
        "idle",
        "running",
        "pausing",
        "paused",
        "waiting_for_machine",
        "fault",
        "done",
    }
    for command, allowed in chart.commands.items():
        assert set(allowed) <= states, command
    assert all(s.get("next") for s in chart.states)


async def test_a_cell_fault_mid_place_faults_and_resume_asks_where_the_crucible_is(
    bench: Bench,
) -> None:
    place = bench.cell.place

    async def protective_stop(station: str, slot: str) -> None:
        bench.cell.place = place  # type: ignore[method-assign]
        raise ProtectiveStopError("protective stop")

    bench.cell.place = protective_stop  # type: ignore[method-assign]
    await bench.job.start(bench.run)
    assert await bench.until("fault", "done") == "fault"
    assert bench.job.message == (
        "place the crucible of sample S1 in machine position A1 failed: protective stop"
    )
    # the fault itself asks (the operator's page shows it before anyone tries to resume)
    (question,) = bench.job.status()["questions"]
    assert question["id"] == "S1/crucible"
    assert any(e["event"] == "question" for e in bench.events)
    with pytest.raises(JobAnswerError, match="answer first: The crucible of sample S1"):
        await bench.job.resume()
    await bench.job.resume({"S1/crucible": "gripper"})
    assert await bench.until("done", "fault", "paused") == "done"
    bench.assert_finished()


async def test_a_database_that_fails_faults_the_job_and_the_step_stays_open(
    bench: Bench, monkeypatch: pytest.MonkeyPatch
) -> None:
    def disk_full(*args: Any, **kwargs: Any) -> None:
        raise JobStoreError("job database: disk full")

    monkeypatch.setattr(bench.store, "end_step", disk_full)
    await bench.job.start(bench.run)
    assert await bench.until("fault", "done") == "fault"
    assert bench.job.message == "the job stopped on an unexpected error: job database: disk full"
    monkeypatch.undo()
    again = Job(bench.cell, bench.store)
    with pytest.raises(JobError, match="unfinished"):
        await again.start(bench.run)
    assert bench.job.run_id is not None
    (step,) = bench.store.steps(bench.job.run_id)
    assert step.ended is None  # the pick happened, its end is not recorded: resume will ask
    await bench.job.resume({"S1/crucible": "gripper"})
    assert await bench.until("done", "fault", "paused") == "done"
    bench.assert_finished()


async def test_two_starts_at_once_make_one_run(bench: Bench) -> None:
    bench.cell.gate = asyncio.Event()
    results = await asyncio.gather(
        bench.job.start(bench.run), bench.job.start(bench.run), return_exceptions=True
    )
    assert sorted(type(r).__name__ for r in results) == ["JobStateError", "int"]
    assert bench.store.unfinished_run() == bench.job.run_id
    await bench.job.abort()


class FlakyLinkCell(FakeCell):
    """A cell whose robot link drops under the first ``drops`` go-home moves."""

    def __init__(self, world: World, drops: int) -> None:
        super().__init__(world)
        self.drops = drops

    async def go_home(self) -> None:
        if self.drops:
            self.drops -= 1
            raise ConnectionLostError("move aborted: robot went to disconnected")
        await super().go_home()


async def test_a_step_the_lost_link_interrupted_goes_on_by_itself_and_is_shown(
    store: JobStore,
) -> None:
    run = sample_run(1)
    world = World.for_run(run)
    cell = FlakyLinkCell(world, drops=2)
    events: list[dict[str, Any]] = []
    job = Job(cell, store, on_event=events.append)
    await job.start(run)
    assert await job.wait_state("done", "paused", "fault", timeout=TIMEOUT) == "done"
    assert world.places == expected_world(run)
    assert cell.restores == 2  # control restored before each new attempt
    heals = [e for e in events if e["event"] == "heal"]
    assert [(h["phase"], h["attempt"]) for h in heals] == [("start", 1), ("start", 2), ("done", 2)]
    assert heals[0]["what"] == "go home"
    assert heals[0]["step"] == "go home"
    assert job.status()["heals"]["count"] == 2
    assert job.run_id is not None
    home = next(r for r in store.steps(job.run_id) if r.kind == "home")
    assert home.detail == "went on by itself after 2 lost robot link(s)"  # recorded
    cell.machine.close()


async def test_a_link_that_keeps_dropping_stops_the_job_for_the_operator(store: JobStore) -> None:
    run = sample_run(1)
    world = World.for_run(run)
    cell = FlakyLinkCell(world, drops=100)
    job = Job(cell, store, JobConfig(heal_attempts=2))
    await job.start(run)
    assert await job.wait_state("done", "paused", "fault", timeout=TIMEOUT) == "fault"
    assert "disconnected" in job.message
    assert cell.restores == 2
    assert [h["phase"] for h in job.heals] == ["start", "start", "failed"]
    cell.machine.close()


class DriftingFlakyLinkCell(FlakyLinkCell):
    """Each go-home move the lost link interrupts got the arm 0.01 rad further."""

    async def go_home(self) -> None:
        q = self.robot_state.actual_q[0] if self.robot_state else 0.0
        self.robot_state = RobotState(actual_q=(q + 0.01, 0.0, 0.0, 0.0, 0.0, 0.0))
        await super().go_home()


@pytest.mark.parametrize(
    ("drops", "state", "restores", "last"),
    [
        (5, "done", 5, "done"),  # interrupted more often than the budget: goes on
        (100, "fault", 8, "failed"),  # never arrives: stops after four budgets in all
    ],
)
async def test_a_move_that_gets_further_each_time_is_healed_within_four_budgets(
    store: JobStore, drops: int, state: str, restores: int, last: str
) -> None:
    run = sample_run(1)
    world = World.for_run(run)
    cell = DriftingFlakyLinkCell(world, drops=drops)
    job = Job(cell, store, JobConfig(heal_attempts=2))
    await job.start(run)
    assert await job.wait_state("done", "paused", "fault", timeout=TIMEOUT) == state
    assert cell.restores == restores
    assert [h["phase"] for h in job.heals][-1] == last
    cell.machine.close()
