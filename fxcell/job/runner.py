"""The fusion-machine job: runs a :class:`~fxcell.job.spec.Run` on a cell, step by step.

The job's states and commands are data (``statecharts/job.yaml``, drawn in ``job.mmd``):
``idle``, ``running``, ``pausing``, ``paused``, ``waiting_for_machine``, ``fault``, ``done``.
Every step is recorded in the :class:`~fxcell.job.store.JobStore` (its start before the robot
moves; its end with the locations it changed and the job state, in one transaction), so a
new :class:`Job` on the same database finds an interrupted run (:meth:`Job.recover`), asks
the operator where the state is ambiguous (:attr:`Job.questions`) and resumes from there.

Commands: :meth:`Job.start`, :meth:`Job.pause` (the current step finishes first),
:meth:`Job.resume` (with answers to recovery questions), :meth:`Job.abort` (cancels the
current step: the cell brakes; the run stays resumable), :meth:`Job.confirm` (manual
machine mode), :meth:`Job.discard`. Events are plain dicts (``time``, ``run``, ``event``:
``state``, ``step``, ``progress``, ``question`` or ``prompt``, and its fields: the shape of the
recorder's ``/job`` topic), given to ``on_event`` and to every :meth:`Job.events` iterator.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time
from collections.abc import (
    AsyncIterator,
    Awaitable,
    Callable,
    Collection,
    Coroutine,
    Mapping,
    Sequence,
)
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Concatenate, ParamSpec, Protocol, TypeVar

from transitions import Machine

from fxcell.cell.healing import HEAL_LISTENER, Heal, announce, arm_moved, retrying
from fxcell.cell.statemachine import Statechart, machine_states, read_statechart
from fxcell.config import JobConfig
from fxcell.errors import (
    ConnectionLostError,
    FxcellError,
    InvalidStateError,
    IOTimeoutError,
    JobAnswerError,
    JobError,
    JobStateError,
    LinkBrakeError,
    MachineError,
    NothingGraspedError,
)
from fxcell.job.plan import (
    HOME,
    PICK,
    START,
    WAIT,
    Step,
    describe_location,
    initial_locations,
    location,
    make_plan,
)
from fxcell.job.spec import MOULDS, Run, RunSpec, load_run, validate_run
from fxcell.job.store import (
    BEAD,
    CRUCIBLE,
    GRIPPER,
    Change,
    JobStore,
    Key,
    PlacementRecord,
    StepRecord,
)
from fxcell.layout import Layout
from fxcell.resources import resource_dir

if TYPE_CHECKING:
    from fxcell.cell.cell import Cell
    from fxcell.protocol import RobotState
    from fxcell.vision.placement import PlacementReport

log = logging.getLogger(__name__)

CHART = resource_dir("statecharts") / "job.yaml"

# The machine's signals, as named in the cell's IO configuration.
START_SIGNAL = "machine_start"
READY = "machine_ready"
BUSY = "machine_busy"
DONE = "machine_done"
ERROR = "machine_error"

# Manual-mode prompts (what Job.confirm answers).
PROMPT_STARTED = "machine_started"
PROMPT_DONE = "machine_done"

# Time-left estimates per step until one of the kind has been measured (s).
_DEFAULT_ESTIMATE = {HOME: 5.0, START: 2.0, PICK: 8.0}
_MOTION_ESTIMATE = 8.0

T = TypeVar("T")
P = ParamSpec("P")
Event = dict[str, Any]


class JobIO(Protocol):
    """The cell's digital IO as the job uses it (signal names from the configuration).

    Results are ignored (typed ``object``) so that richer implementations fit.
    """

    async def set(self, signal: str, value: bool, /) -> None: ...

    def get(self, signal: str, /) -> object:
        """The signal's value now (truthy when on)."""
        ...

    async def wait_for(self, signal: str, value: bool, timeout: float, /) -> object:  # noqa: ASYNC109
        """Return once ``signal`` is ``value``; :class:`~fxcell.errors.IOTimeoutError` after
        ``timeout`` seconds."""
        ...


class JobGripper(Protocol):
    """The gripper's object detection, as the job asks it."""

    async def get_width(self) -> object:
        """Read the fingers (and refresh :attr:`holding`)."""
        ...

    @property
    def holding(self) -> bool:
        """Whether the last read found an object between the fingers."""
        ...


class JobCell(Protocol):
    """What the job needs of a cell; :class:`fxcell.cell.cell.Cell` satisfies it."""

    @property
    def layout(self) -> Layout:
        """The stations as taught now (re-teaching a frame changes them)."""
        ...

    @property
    def io(self) -> JobIO: ...

    @property
    def gripper(self) -> JobGripper: ...

    @property
    def held(self) -> str | None:
        """The kind of object the cell knows the gripper holds (None: nothing known)."""
        ...

    @property
    def robot_state(self) -> RobotState | None:
        """The arm's latest sample (None while disconnected): a recovery that got the arm
        further does not count against ``heal_attempts``."""
        ...

    async def declare_held(self, kind: str | None = None, /) -> object:
        """The gripper holds an object of ``kind`` (after a restart, when the job knows)."""
        ...

    async def restore_control(self) -> object:
        """Wait for the robot link, the arm at rest and external control (after a lost link);
        a safety stop raises its error."""
        ...

    async def pick(self, station: str, slot: str, /) -> object:
        """Approach, descend, close, verify, retreat; :class:`NothingGraspedError` when the
        gripper closes on nothing (the arm is back above the slot, gripper open)."""
        ...

    async def place(self, station: str, slot: str, /) -> object: ...

    async def go_home(self) -> object: ...

    async def inspect_placement(self, expected: Collection[str], /) -> PlacementReport | None:
        """Look at the machine's positions: ``expected`` must hold seated crucibles, the
        others be empty. ``None``: no camera (the job starts the machine unchecked);
        :class:`~fxcell.errors.CameraError` when the camera gives no frame."""
        ...


if TYPE_CHECKING:  # mypy proves that the real Cell is a JobCell

    def _cell_is_a_job_cell(cell: Cell) -> JobCell:
        return cell


@dataclass(frozen=True)
class Question:
    """Where is an object whose step was interrupted? ``choices`` are stored locations."""

    id: str
    text: str
    choices: tuple[str, ...]
    sample: str
    object: str


class _Model:
    state: str


def _link_lost(error: FxcellError) -> bool:
    """A failure a lost (or just restored) robot link explains: nothing for the operator."""
    if isinstance(error, ConnectionLostError | LinkBrakeError):
        return True
    return isinstance(error, InvalidStateError) and error.state in _LINK_STATES


_LINK_STATES = frozenset({"disconnected", "running.program_stopped", "running.stopping"})


def _one_at_a_time(
    fn: Callable[Concatenate[Job, P], Awaitable[T]],
) -> Callable[Concatenate[Job, P], Coroutine[Any, Any, T]]:
    """A job command that waits for any other such command to finish first."""

    @functools.wraps(fn)
    async def command(job: Job, /, *args: P.args, **kwargs: P.kwargs) -> T:
        async with job._commands:
            return await fn(job, *args, **kwargs)

    return command


class Job:
    """The fusion-machine job on ``cell``, recording in ``store``.

    Create it, call :meth:`recover` once (it finds a run a previous process left unfinished),
    then :meth:`start` runs. One job per store.
    """

    def __init__(
        self,
        cell: JobCell,
        store: JobStore,
        config: JobConfig | None = None,
        *,
        on_event: Callable[[Event], None] | None = None,
        chart: Statechart | None = None,
    ) -> None:
        self.cell = cell
        self.store = store
        self.config = config or JobConfig()
        self.chart = chart or read_statechart(CHART)
        self._on_event = on_event
        self._model = _Model()
        self._machine = Machine(
            model=self._model,
            states=machine_states(self.chart.states),
            transitions=self.chart.transitions,
            initial=self.chart.initial,
            auto_transitions=False,
        )
        self._subscribers: set[asyncio.Queue[Event]] = set()
        self._commands = asyncio.Lock()
        self._changed = asyncio.Event()
        self.run_id: int | None = None
        self.run: Run | None = None
        self.plan: list[Step] = []
        self.message = ""
        self.questions: dict[str, Question] = {}
        self.prompt: dict[str, str] | None = None
        self._next = 0
        self._current: Step | None = None
        self._home_first = False
        self._task: asyncio.Task[None] | None = None
        self._pause_requested = asyncio.Event()
        self._confirmed: asyncio.Future[None] | None = None
        self._durations: dict[str, tuple[float, int]] = {}
        self.locations: dict[Key, str] = {}
        """Where each object of the run is, as recorded: (sample index, object) -> place."""
        self.placement: dict[str, Any] | None = None
        """The run's last placement check: ``check`` (its id in the store), ``time``, ``ok``,
        ``reason``, ``cycle``, ``positions`` (slot → verdict, offset)."""
        self.heals: list[Event] = []
        """The run's recoveries from a lost robot link (this process), each an event."""
        self._step_heals = 0

    # ------------------------------------------------------------- state

    @property
    def state(self) -> str:
        return self._model.state

    def _check(self, command: str) -> None:
        allowed = self.chart.commands[command]
        if self.state not in allowed:
            raise JobStateError(command, self.state, allowed)

    def _dest(self, trigger: str) -> str:
        """Where ``trigger`` leads from the current state (the chart must declare it)."""
        found = self._machine.get_transitions(trigger, source=self.state)
        if not found:
            raise JobError(f"the job chart has no {trigger!r} from {self.state!r}")
        return str(found[0].dest)

    def _fire(self, trigger: str, message: str = "") -> None:
        """Take a declared transition (already recorded in the store) and announce it."""
        source = self.state
        self._model.trigger(trigger)  # type: ignore[attr-defined]
        self.message = message
        self._changed.set()
        self._changed = asyncio.Event()
        self._emit(
            {
                "event": "state",
                "from": source,
                "to": self.state,
                "trigger": trigger,
                "message": message,
            }
        )

    async def wait_state(self, *states: str, timeout: float | None = None) -> str:  # noqa: ASYNC109
        """Return the state once it is one of ``states`` (``TimeoutError`` after ``timeout``)."""
        async with asyncio.timeout(timeout):
            while self.state not in states:
                await self._changed.wait()
        return self.state

    # ------------------------------------------------------------- events

    def _emit(self, event: Event) -> None:
        event = {"time": time.time(), "run": self.run_id, **event}
        if self._on_event is not None:
            try:
                self._on_event(event)
            except Exception:  # a broken listener must not stop the robot
                log.exception("job event listener failed")
        for queue in self._subscribers:
            queue.put_nowait(event)

    async def events(self) -> AsyncIterator[Event]:
        """Every job event from now on (state, step, progress, question, prompt)."""
        queue: asyncio.Queue[Event] = asyncio.Queue()
        self._subscribers.add(queue)
        try:
            while True:
                yield await queue.get()
        finally:
            self._subscribers.discard(queue)

    # ------------------------------------------------------------- status

    def _estimate(self, step: Step) -> float:
        measured = self._durations.get(step.kind)
        if measured is not None:
            return measured[0] / measured[1]
        if step.action == WAIT:
            return self.config.cycle_estimate
        return _DEFAULT_ESTIMATE.get(step.action, _MOTION_ESTIMATE)

    def _measured(self, kind: str, duration: float) -> None:
        total, n = self._durations.get(kind, (0.0, 0))
        self._durations[kind] = (total + duration, n + 1)

    def progress(self) -> dict[str, Any]:
        """Steps done, steps in all, and the estimated time left (s, from measured steps)."""
        left = self.plan[self._next :]
        return {
            "done": self._next,
            "total": len(self.plan),
            "eta": round(sum(self._estimate(s) for s in left), 1),
        }

    def status(self) -> dict[str, Any]:
        """Everything a page shows: state, progress, questions, each sample's locations."""
        samples: list[dict[str, Any]] = []
        if self.run is not None:
            locations = self.locations
            samples = [
                {
                    "id": s.id,
                    "rack": s.rack,
                    "machine": s.machine,
                    "tray": s.tray,
                    "cycle": s.cycle + 1,
                    "crucible": locations.get((s.index, CRUCIBLE)),
                    "bead": locations.get((s.index, BEAD)),
                }
                for s in self.run.samples
            ]
        current = self._current or (self.plan[self._next] if self._next < len(self.plan) else None)
        return {
            "state": self.state,
            "run": self.run_id,
            "name": self.run.name if self.run else None,
            "message": self.message,
            "step": current.describe(self.run) if current and self.run else None,
            "progress": self.progress() if self.run else None,
            "questions": [asdict(q) for q in self.questions.values()],
            "prompt": self.prompt,
            "heals": {
                "count": sum(1 for h in self.heals if h["phase"] == "start"),
                "recent": self.heals[-5:],
            },
            "samples": samples,
            "placement": self.placement,
        }

    # ------------------------------------------------------------- database

    async def _db(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run a store call in a worker thread; a cancellation waits for the write to finish."""
        fut = asyncio.ensure_future(asyncio.to_thread(fn, *args, **kwargs))
        try:
            return await asyncio.shield(fut)
        except asyncio.CancelledError:
            with contextlib.suppress(Exception):
                await fut
            raise

    # ------------------------------------------------------------- commands

    @_one_at_a_time
    async def recover(self) -> dict[str, Any]:
        """Load the run a previous process left unfinished, if any, and pause on it.

        The job is then ``paused`` at the first step not done; :attr:`questions` holds what
        the operator must answer first (where a step that moves an object was interrupted).
        """
        self._check("start")
        run_id = await self._db(self.store.unfinished_run)
        if run_id is None:
            return self.status()
        await self._load(run_id)
        interrupted = self._analyse(await self._db(self.store.steps, run_id))
        await self._settle_by_gripper()
        what = f"step {self._next + 1}/{len(self.plan)}"
        if self._next < len(self.plan) and self.run is not None:
            what += f" ({self.plan[self._next].describe(self.run)})"
        message = f"run {run_id} recovered: next is {what}"
        if interrupted:
            message += "; it was interrupted"
        if self.questions:
            message += ": answer where the objects are, then resume"
        await self._db(self.store.set_state, run_id, self._dest("recover"), message)
        self._fire("recover", message)
        self._announce_questions()
        return self.status()

    async def _load(self, run_id: int) -> None:
        record = await self._db(self.store.run, run_id)
        self.run_id = run_id
        self.run = record.run
        self.plan = make_plan(record.run)
        self.locations = await self._db(self.store.locations, run_id)
        checks = await self._db(self.store.placement_checks, run_id)
        self.placement = _placement_summary(checks[-1]) if checks else None
        self.heals = []
        self._durations = {
            kind: (mean, 1) for kind, mean in (await self._db(self.store.mean_durations)).items()
        }

    def _analyse(self, records: Sequence[StepRecord]) -> bool:
        """Find the next step and the questions its interruption raises; True if interrupted."""
        done = {r.seq for r in records if r.outcome == "done"}
        self._next = next((s.seq for s in self.plan if s.seq not in done), len(self.plan))
        self.questions = {}
        if self._next >= len(self.plan):
            return False
        step = self.plan[self._next]
        last = next((r for r in reversed(records) if r.seq == step.seq), None)
        interrupted = last is not None and last.outcome in (None, "interrupted", "aborted")
        if interrupted and step.moves_object:
            assert self.run is not None
            assert step.idx is not None
            assert step.obj is not None
            sample = self.run.samples[step.idx]
            src, dst = step.source, step.dest
            verb = "picked from" if step.action == PICK else "placed in"
            where = describe_location(step.dest if step.action != PICK else step.source)
            text = (
                f"The {step.obj} of sample {sample.id} was being {verb} {where} when the job "
                f"stopped. Is it in {describe_location(src)} ({src}) or in "
                f"{describe_location(dst)} ({dst})? If it is elsewhere, put it in one of them "
                f"first; open the gripper unless it holds the {step.obj}."
            )
            qid = f"{sample.id}/{step.obj}"
            self.questions[qid] = Question(qid, text, (src, dst), sample.id, step.obj)
        self._home_first = interrupted
        return interrupted

    async def _record_answers(self, answers: Mapping[str, str], who: str) -> None:
        """Record where each questioned object is (answers checked against the choices)."""
        if not self.questions:
            return
        assert self.run_id is not None
        step = self.plan[self._next]
        for qid, question in self.questions.items():
            assert step.idx is not None
            assert step.obj is not None
            answer = answers[qid].strip()
            changes = []
            if answer != step.source:
                changes = [Change((step.idx, step.obj), step.source, answer)]
            await self._db(
                self.store.record_answer,
                self.run_id,
                step.seq,
                step.kind,
                step.idx,
                changes,
                f"{who}: {question.object} of sample {question.sample} is at {answer}",
            )
        self._analyse(await self._db(self.store.steps, self.run_id))
        self.locations = await self._db(self.store.locations, self.run_id)
        self._home_first = True

    async def _settle_by_gripper(self) -> None:
        """Answer the questions the gripper's object detection settles: an object of an
        interrupted pick or place is in the gripper exactly when the fingers hold one, else
        in the slot (the other choice). Unanswered when the gripper cannot be read."""
        if not self.questions:
            return
        try:
            await self.cell.gripper.get_width()
        except FxcellError as exc:
            log.info("job: the gripper cannot settle the questions: %s", exc)
            return
        holding = self.cell.gripper.holding
        answers = {
            qid: GRIPPER if holding else next(c for c in q.choices if c != GRIPPER)
            for qid, q in self.questions.items()
            if GRIPPER in q.choices
        }
        if len(answers) != len(self.questions):
            return
        log.info("job: the gripper settles where the objects are: %s", answers)
        await self._record_answers(answers, "the gripper's object detection")
        self.questions = {}

    def _announce_questions(self) -> None:
        if self.questions:
            self._emit(
                {"event": "question", "questions": [asdict(q) for q in self.questions.values()]}
            )

    @_one_at_a_time
    async def start(self, run: Run | RunSpec | Mapping[str, Any] | str | Path) -> int:
        """Validate ``run`` (a :class:`Run`, a dict, or a run file) and start it; its id.

        Nothing moves if the run is invalid (:class:`~fxcell.errors.JobSpecError`), or if the
        database holds an unfinished run (recover, then resume or discard it).
        """
        self._check("start")
        if isinstance(run, str | Path):
            run = load_run(run, self.cell.layout)
        elif not isinstance(run, Run):
            run = validate_run(run, self.cell.layout)
        unfinished = await self._db(self.store.unfinished_run)
        if unfinished is not None:
            raise JobError(
                f"run {unfinished} in {self.store.path} is unfinished: "
                "recover() it, then resume or discard it"
            )
        dest = self._dest("start")
        run_id = await self._db(self.store.create_run, run, dest, initial_locations(run))
        await self._load(run_id)
        self._next = 0
        self.questions = {}
        self._home_first = False
        self._fire("start", f"run {run_id} started: {len(run.samples)} samples")
        self._spawn()
        return run_id

    async def pause(self) -> None:
        """Ask the job to stop at the next safe point (after the current step; at once while
        it waits for the machine). Returns at once; the job goes ``pausing``, then ``paused``."""
        self._check("pause")
        # In memory only: "pausing" is recorded with the step's end or the safe point.
        self._fire("pause", "pause asked: finishing the current step")
        self._pause_requested.set()

    def _set_state_now(self, state: str, message: str) -> None:
        assert self.run_id is not None
        self.store.set_state(self.run_id, state, message)

    @_one_at_a_time
    async def resume(self, answers: Mapping[str, str] | None = None) -> None:
        """Go on from ``paused`` or ``fault``; ``answers`` maps each question id to one of its
        choices (:class:`~fxcell.errors.JobAnswerError` if one is missing or not a choice)."""
        self._check("resume")
        if self._task is not None and not self._task.done():
            await self._task  # it has reached its safe point and is returning
        assert self.run_id is not None
        assert self.run is not None
        records = await self._db(self.store.steps, self.run_id)
        self._analyse(records)
        answers = dict(answers or {})
        if not answers:
            await self._settle_by_gripper()
        unknown = set(answers) - set(self.questions)
        if unknown:
            raise JobAnswerError(f"no such question: {', '.join(sorted(unknown))}")
        missing = [q for q in self.questions if q not in answers]
        if missing:
            raise JobAnswerError(
                f"answer first: {'; '.join(self.questions[q].text for q in missing)}"
            )
        for qid, question in self.questions.items():
            answer = answers[qid].strip()
            if answer not in question.choices:
                raise JobAnswerError(
                    f"{qid}: {answer!r} is not one of {', '.join(question.choices)}"
                )
        await self._record_answers(answers, "operator")
        self.questions = {}
        self._pause_requested.clear()
        await self._db(self._set_state_now, self._dest("resume"), "resumed")
        self._fire("resume", "resumed")
        self._spawn()

    @_one_at_a_time
    async def abort(self) -> None:
        """Cancel the current step (the cell brakes); the run stays resumable. Returns once
        the job is ``paused``; where an object was being moved, resuming asks where it is."""
        self._check("abort")
        task = self._task
        if task is not None and not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        assert self.run_id is not None
        if self.state not in ("paused", "fault", "done"):
            message = "aborted"
            await self._db(self._close_open, "aborted", self._dest("abort"), message)
            self._current = None
            self.prompt = None
            self._fire("abort", message)
        self._analyse(await self._db(self.store.steps, self.run_id))
        self._announce_questions()

    def _close_open(self, outcome: str, state: str, message: str) -> None:
        assert self.run_id is not None
        self.store.close_open_steps(self.run_id, outcome, message)
        self.store.set_state(self.run_id, state, message)

    async def confirm(self, prompt: str | None = None) -> None:
        """Manual mode: the operator confirms the current prompt (the machine was started,
        or it is done). ``prompt``, when given, must name the current one."""
        self._check("confirm")
        if self.prompt is None or self._confirmed is None or self._confirmed.done():
            raise JobStateError("confirm", f"{self.state} with nothing to confirm", ())
        if prompt is not None and prompt != self.prompt["id"]:
            raise JobAnswerError(f"the job asks {self.prompt['id']!r}, not {prompt!r}")
        self._confirmed.set_result(None)

    @_one_at_a_time
    async def discard(self) -> None:
        """Give up the paused or faulted run: it is closed in the database (every object's
        last location stays recorded) and the job is ``idle``."""
        self._check("discard")
        assert self.run_id is not None
        run_id = self.run_id
        await self._db(self.store.set_state, run_id, "discarded", "discarded by the operator", True)
        self._fire("discard", f"run {run_id} discarded")
        self.run_id = None
        self.run = None
        self.plan = []
        self.questions = {}
        self.locations = {}
        self.placement = None

    async def close(self) -> None:
        """Stop the job's task (as :meth:`abort` when it runs); the store stays open."""
        if self._task is not None and not self._task.done():
            await self.abort()

    # ------------------------------------------------------------- the work

    def _spawn(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._guarded(), name="fxcell-job")

    async def _guarded(self) -> None:
        HEAL_LISTENER.set(self._on_heal)  # this task's context: the cell's steps report here
        try:
            await self._work()
        except Exception as exc:  # a bug or a dead database: stop, and say so
            log.exception("the job stopped on an unexpected error")
            if self._machine.get_transitions("fail", source=self.state):
                message = f"the job stopped on an unexpected error: {exc}"
                with contextlib.suppress(Exception):
                    await self._db(self._set_state_now, self._dest("fail"), message)
                self._current = None
                self._fire("fail", message)

    async def _work(self) -> None:
        assert self.run_id is not None
        assert self.run is not None
        if self._home_first:
            try:
                await self._healing("go home", self.cell.go_home)
            except FxcellError as exc:
                await self._fault_now(f"going home after the interruption failed: {exc}")
                return
            self._home_first = False
        while self._next < len(self.plan):
            if self._pause_requested.is_set():
                await self._db(self._set_state_now, self._dest("safe_point"), "paused")
                self._fire("safe_point", "paused")
                return
            step = self.plan[self._next]
            if not await self._step(step):
                return
            self._next += 1
            self._emit({"event": "progress", **self.progress()})
        self._current = None
        assert self.run_id is not None
        await self._db(self.store.set_state, self.run_id, self._dest("finish"), "done", True)
        self._fire("finish", f"run {self.run_id} done")

    async def _fault_now(self, message: str) -> None:
        await self._db(self._set_state_now, self._dest("fail"), message)
        # what resume will ask (an earlier interruption not settled yet), shown with the fault
        assert self.run_id is not None
        self._analyse(await self._db(self.store.steps, self.run_id))
        self._fire("fail", message)
        self._announce_questions()

    async def _signal(self, signal: str) -> bool:
        """A machine signal now (read again once a lost robot link is back)."""

        async def read() -> bool:
            return bool(self.cell.io.get(signal))

        return await self._healing(f"read {signal}", read)

    async def _step(self, step: Step) -> bool:
        if not self.config.manual:
            try:
                error = await self._signal(ERROR)
            except FxcellError as exc:
                await self._fault_now(f"the machine's signals cannot be read: {exc}")
                return False
            if error:
                await self._fault_now("the fusion machine reports an error")
                return False
        if step.action == HOME:
            return await self._home(step)
        if step.action == START:
            return await self._start_machine(step)
        if step.action == WAIT:
            return await self._wait_machine(step)
        return await self._move(step)

    async def _begin(self, step: Step, state: tuple[str, str] | None = None) -> int:
        assert self.run_id is not None
        assert self.run is not None
        step_id = await self._db(
            self.store.begin_step, self.run_id, step.seq, step.kind, step.idx, state
        )
        self._current = step
        self._step_heals = 0
        event: Event = {"event": "step", "phase": "start", "seq": step.seq, "kind": step.kind}
        event["text"] = step.describe(self.run)
        if step.moves_object:
            assert step.idx is not None
            event.update(
                sample=self.run.samples[step.idx].id,
                object=step.obj,
                **{"from": step.source, "to": step.dest},
            )
        self._emit(event)
        return step_id

    async def _end(
        self,
        step_id: int,
        step: Step,
        outcome: str,
        changes: Sequence[Change] = (),
        *,
        started: float | None = None,
        detail: str = "",
        trigger: str | None = None,
        message: str = "",
        fire: bool = True,
    ) -> None:
        """Record the step's end with its changes and the state ``trigger`` leads to (in one
        transaction); ``fire=False`` leaves firing ``trigger`` in memory to the caller."""
        assert self.run is not None
        duration = None if started is None else time.monotonic() - started
        state = None if trigger is None else (self._dest(trigger), message)
        if self._step_heals and not detail:  # the store keeps it with the step
            detail = f"went on by itself after {self._step_heals} lost robot link(s)"
        await self._db(
            self.store.end_step,
            step_id,
            outcome,
            changes,
            detail=detail,
            duration=duration,
            state=state,
        )
        if duration is not None and outcome == "done":
            self._measured(step.kind, duration)
        for ch in changes:
            self.locations[ch.key] = ch.new
        self._current = None
        moved = [
            {
                "sample": self.run.samples[ch.key[0]].id,
                "object": ch.key[1],
                "from": ch.old,
                "to": ch.new,
            }
            for ch in changes
        ]
        self._emit(
            {
                "event": "step",
                "phase": "end",
                "seq": step.seq,
                "kind": step.kind,
                "outcome": outcome,
                "duration": duration,
                "detail": detail,
                "moved": moved,
            }
        )
        if trigger is not None and fire:
            self._fire(trigger, message)

    async def _move(self, step: Step) -> bool:
        assert step.station is not None
        assert step.slot is not None
        assert step.idx is not None
        assert step.obj is not None
        if step.station == "machine" and step.action != PICK and not self.config.manual:
            try:
                await self._wait_any([(READY, True)], self.config.ready_timeout)
            except IOTimeoutError:
                await self._fault_now(
                    f"the fusion machine is not ready after {self.config.ready_timeout:g} s"
                )
                return False
        step_id = await self._begin(step)
        started = time.monotonic()
        try:
            if step.action == PICK:
                await self.cell.pick(step.station, step.slot)
            else:
                await self._healing("the gripper's object", lambda: self._know_held(step))
                await self.cell.place(step.station, step.slot)
        except NothingGraspedError:
            msg = f"no {step.obj} detected in {describe_location(step.source)}"
            await self._end(
                step_id,
                step,
                "failed",
                detail=msg,
                trigger="hold",
                message=f"{msg}: put it there, then resume",
            )
            return False
        except Exception as exc:
            if not isinstance(exc, FxcellError):
                log.exception("job step %s failed", step.kind)
            message = f"{step.describe(self.run) if self.run else step.kind} failed: {exc}"
            await self._end(
                step_id,
                step,
                "interrupted",
                detail=str(exc),
                trigger="fail",
                message=message,
                fire=False,
            )
            # where is the object now? asked before the fault shows, so that it carries
            # the question (the operator sees it before trying to resume)
            assert self.run_id is not None
            self._analyse(await self._db(self.store.steps, self.run_id))
            self._fire("fail", message)
            self._announce_questions()
            return False
        change = Change((step.idx, step.obj), step.source, step.dest)
        await self._end(step_id, step, "done", [change], started=started)
        return True

    def _on_heal(self, heal: Heal) -> None:
        """A step went on by itself after a lost robot link: record and show it."""
        step = self._current
        event: Event = {
            "event": "heal",
            "seq": step.seq if step else None,
            "step": step.describe(self.run) if step and self.run else None,
            "what": heal.what,
            "attempt": heal.attempt,
            "phase": heal.phase,
            "reason": heal.reason,
        }
        if heal.phase == "start":
            self._step_heals += 1
        self.heals.append({"time": time.time(), **event})
        self._emit(event)

    async def _healing(self, what: str, call: Callable[[], Awaitable[T]]) -> T:
        """Run a step that is safe to repeat; after a lost robot link, wait for the cell to
        restore control and run it again (``job.heal_attempts``)."""
        return await retrying(
            what,
            call,
            attempts=self.config.heal_attempts,
            healable=_link_lost,
            restore=self.cell.restore_control,
            announce=self._announce_heal,
            moved=arm_moved(self.cell),
        )

    def _announce_heal(self, heal: Heal) -> None:
        announce(heal)  # logged as the cell's own are, and told to the listener (_on_heal)

    async def _know_held(self, step: Step) -> None:
        """Before a place: if the cell does not know it holds the object (a new process after
        a restart), the gripper's object detection confirms what the job recorded."""
        cell = self.cell
        if cell.held is not None or step.station is None:
            return
        try:
            await cell.gripper.get_width()
        except FxcellError as exc:  # the place itself then says what stops it
            log.info("job: the gripper cannot confirm what it holds: %s", exc)
            return
        if cell.gripper.holding:
            await cell.declare_held(cell.layout.station(step.station).config.holds)

    async def _home(self, step: Step) -> bool:
        step_id = await self._begin(step)
        started = time.monotonic()
        try:
            await self._healing("go home", self.cell.go_home)
        except FxcellError as exc:
            await self._end(
                step_id, step, "failed", detail=str(exc), trigger="fail", message=f"go home: {exc}"
            )
            return False
        await self._end(step_id, step, "done", started=started)
        return True

    async def _wait_any(
        self,
        conditions: Sequence[tuple[str, bool]],
        timeout: float,  # noqa: ASYNC109
        *,
        pause: bool = False,
    ) -> str | None:
        """The first signal of ``conditions`` to reach its value; ``None`` if a pause came
        first (with ``pause``); :class:`IOTimeoutError` when none did within ``timeout``."""
        io = self.cell.io
        tasks: dict[asyncio.Task[Any], str | None] = {
            asyncio.ensure_future(io.wait_for(sig, value, timeout)): sig
            for sig, value in conditions
        }
        if pause:
            tasks[asyncio.ensure_future(self._pause_requested.wait())] = None
        try:
            pending = set(tasks)
            timeouts = 0
            while True:
                done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
                for task in done:
                    exc = task.exception()
                    if exc is None:
                        return tasks[task]
                    if not isinstance(exc, IOTimeoutError):
                        raise exc
                    timeouts += 1
                    if timeouts == len(conditions):
                        raise exc
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _ask(self, prompt: str, text: str) -> bool:
        """Manual mode: show a prompt and wait for :meth:`confirm`; False if paused first."""
        self._confirmed = asyncio.get_running_loop().create_future()
        self.prompt = {"id": prompt, "text": text}
        self._emit({"event": "prompt", **self.prompt})
        pause = asyncio.ensure_future(self._pause_requested.wait())
        try:
            waits: set[asyncio.Future[Any]] = {self._confirmed, pause}
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            return self._confirmed.done()
        finally:
            pause.cancel()
            self.prompt = None
            self._confirmed = None

    async def _begin_waiting(self, step: Step, text: str) -> int:
        """Begin a machine step and enter ``waiting_for_machine`` (unless a pause came)."""
        if self.state != "running":  # pausing: the wait ends at once at the safe point
            return await self._begin(step)
        step_id = await self._begin(step, (self._dest("wait_machine"), text))
        if self.state == "running":
            self._fire("wait_machine", text)
        return step_id

    def _if_waiting(self) -> str | None:
        """``machine_done`` while waiting; none while pausing (the loop then pauses)."""
        return "machine_done" if self.state == "waiting_for_machine" else None

    async def _placement_checked(self, step: Step) -> bool:
        """Before the machine starts: are the cycle's crucibles seated, the other positions
        empty, nothing on the holder? If not, hold (paused) with the reason; resuming runs
        this step, and so the check, again. True when the machine may start."""
        assert self.run is not None
        assert self.run_id is not None
        io = self.cell.io
        if not self.config.manual and (io.get(BUSY) or io.get(DONE)):
            return True  # after a restart: the machine started already, too late to look
        expected = {s.machine for s in self.run.samples if s.cycle == step.cycle}
        try:
            report = await self.cell.inspect_placement(expected)
        except FxcellError as exc:
            await self._fault_now(f"placement check before fusion cycle {step.cycle + 1}: {exc}")
            return False
        if report is None:
            return True
        verdict = report.as_dict()
        check_id = await self._db(
            self.store.add_placement_check, self.run_id, step.seq, verdict, report.image
        )
        self.placement = {
            "check": check_id,
            "cycle": step.cycle + 1,
            "time": report.time,
            "ok": report.ok,
            "reason": report.reason,
            "positions": {
                p.slot: {"verdict": p.verdict, "ok": p.ok, "offset_mm": p.offset_mm}
                for p in report.positions
            },
        }
        self._emit({"event": "placement", **self.placement})
        if report.ok:
            return True
        message = (
            f"placement check before fusion cycle {step.cycle + 1}: {report.reason}. "
            "Seat the crucibles in their positions and clear the holder, then resume "
            "(the check runs again)"
        )
        await self._db(self._set_state_now, self._dest("hold"), message)
        self._fire("hold", message)
        return False

    async def _start_machine(self, step: Step) -> bool:
        io = self.cell.io
        if not await self._placement_checked(step):
            return False
        if self.config.manual:
            step_id = await self._begin_waiting(step, "start the fusion machine, then confirm")
            ok = await self._ask(PROMPT_STARTED, "Start the fusion machine, then confirm.")
            if not ok:
                await self._end(step_id, step, "paused", trigger="safe_point", message="paused")
                return False
            await self._end(
                step_id, step, "done", trigger=self._if_waiting(), message="machine started"
            )
            return True
        step_id = await self._begin(step)
        started = time.monotonic()
        try:
            # After a restart the machine may have started already: then only end the pulse.
            if not (await self._signal(BUSY) or await self._signal(DONE)):
                await self._healing("start pulse", lambda: io.set(START_SIGNAL, True))
                fired = await self._wait_any(
                    [(BUSY, True), (DONE, True), (ERROR, True)], self.config.start_timeout
                )
                if fired == ERROR:
                    raise MachineError("the fusion machine reports an error after the start pulse")
            await self._healing("end the start pulse", lambda: io.set(START_SIGNAL, False))
        except FxcellError as exc:
            with contextlib.suppress(FxcellError):  # never leave the start signal on
                await io.set(START_SIGNAL, False)
            msg = str(exc)
            if isinstance(exc, IOTimeoutError):
                msg = (
                    f"the fusion machine did not report busy within {self.config.start_timeout:g} s"
                )
            await self._end(step_id, step, "failed", detail=msg, trigger="fail", message=msg)
            return False
        await self._end(step_id, step, "done", started=started)
        return True

    async def _wait_machine(self, step: Step) -> bool:
        assert self.run is not None
        samples = [s for s in self.run.samples if s.cycle == step.cycle]
        beads = [Change((s.index, BEAD), None, location(MOULDS, s.mould)) for s in samples]
        text = f"fusion cycle {step.cycle + 1} running"
        step_id = await self._begin_waiting(step, text)
        started = time.monotonic()
        if self.config.manual:
            if not await self._ask(PROMPT_DONE, "Confirm when the machine has finished."):
                await self._end(step_id, step, "paused", trigger="safe_point", message="paused")
                return False
            fired: str | None = DONE
        else:
            try:
                fired = await self._wait_any(
                    [(DONE, True), (ERROR, True)], self.config.done_timeout, pause=True
                )
            except IOTimeoutError:
                msg = f"the fusion machine was not done within {self.config.done_timeout:g} s"
                await self._end(step_id, step, "failed", detail=msg, trigger="fail", message=msg)
                return False
            except FxcellError as exc:
                await self._end(
                    step_id, step, "failed", detail=str(exc), trigger="fail", message=str(exc)
                )
                return False
        if fired is None:
            await self._end(step_id, step, "paused", trigger="safe_point", message="paused")
            return False
        if fired == ERROR:
            msg = "the fusion machine reports an error"
            await self._end(step_id, step, "failed", detail=msg, trigger="fail", message=msg)
            return False
        await self._end(
            step_id,
            step,
            "done",
            beads,
            started=started,
            trigger=self._if_waiting(),
            message=f"fusion cycle {step.cycle + 1} done",
        )
        return True


def _placement_summary(record: PlacementRecord) -> dict[str, Any]:
    """The status form of a stored check."""
    return {
        "check": record.id,
        "cycle": None,
        "time": record.time,
        "ok": record.ok,
        "reason": record.reason,
        "positions": {
            p["slot"]: {"verdict": p["verdict"], "ok": p["ok"], "offset_mm": p.get("offset_mm")}
            for p in record.verdict.get("positions", ())
        },
    }
