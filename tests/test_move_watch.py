"""How a running move follows the state stream: the bounded wait for each sample, the
deadline that catches a stream that stops, and the end of the move at the plan's end.

Against a stub link (no simulator, no link process): the stream is fed by the test, one
sample at a time, so each test knows which sample the move acted on.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import numpy as np
import pytest

from fxcell.config import CellConfig
from fxcell.errors import ConnectionLostError
from fxcell.link.capabilities import UR3E, RobotCapabilities
from fxcell.link.client import StateSubscription, TrajectoryProgress, TrajectoryResult
from fxcell.link.contract import StopReason
from fxcell.motion.moves import MotionPlanner, MoveExecution, MovePlan
from fxcell.protocol import RobotState

CONFIG = CellConfig.load()
DT = UR3E.sample_period  # the UR3e's trajectories: one sample per 2 ms servo cycle
HOME = np.array(CONFIG.home)
TARGET = HOME + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.005])
PROGRESS_EVERY = 10  # samples between two progress reports, as the link process sends them


@pytest.fixture(scope="module")
def planner() -> MotionPlanner:
    return MotionPlanner(CONFIG)


@pytest.fixture(scope="module")
def plan(planner: MotionPlanner) -> MovePlan:
    return planner.plan_joint(HOME, TARGET, search=False)


def _state(k: int, q: np.ndarray, t0: float = 100.0) -> RobotState:
    """Sample ``k`` of the stream: controller time ``t0 + k`` cycles, the arm still at ``q``."""
    return RobotState(timestamp=t0 + k * DT, actual_q=tuple(q.tolist()), received_at=float(k))


class StubRun:
    """A trajectory that runs until it is stopped (a TrajectoryRun)."""

    def __init__(self, total: int) -> None:
        self.total = total
        self.progress: TrajectoryProgress | None = None
        self.stops: list[str] = []
        self._done: asyncio.Future[TrajectoryResult] = asyncio.get_running_loop().create_future()

    @property
    def done(self) -> bool:
        return self._done.done()

    async def replace_remaining(self, samples: Any, at_index: int | None = None) -> bool:
        return False

    async def stop(self, reason: StopReason = StopReason.STOP_REQUESTED) -> TrajectoryResult:
        self.stops.append(reason)
        if not self._done.done():
            self._done.set_result(TrajectoryResult("stopped", reason, 0, self.total, None, 0.0))
        return await self.wait()

    async def wait(self) -> TrajectoryResult:
        return await asyncio.shield(self._done)

    async def next_progress(self) -> TrajectoryProgress | None:
        return None if self.done else self.progress


class WatchedSubscription(StateSubscription):
    """A subscription that tells when its reader waits for the next sample (so it is done
    with the previous one)."""

    def __init__(self, subscriptions: set[StateSubscription], maxsize: int) -> None:
        super().__init__(subscriptions, maxsize)
        self.waiting = asyncio.Event()
        self.since = 0.0  # when the reader began to wait (for the latest sample)

    async def next_within(self, timeout: float) -> RobotState:  # noqa: ASYNC109
        self.since = time.monotonic()
        self.waiting.set()
        return await super().next_within(timeout)


class StubLink:
    """The parts of a LinkBackend a MoveExecution uses; the test feeds the samples."""

    def __init__(self, first: RobotState) -> None:
        self.latest: RobotState | None = first
        self.subscriptions: set[StateSubscription] = set()
        self.watched: list[WatchedSubscription] = []
        self.run: StubRun | None = None
        self.started = asyncio.Event()

    def subscribe(self, maxsize: int = 1024) -> StateSubscription:
        sub = WatchedSubscription(self.subscriptions, maxsize)
        self.watched.append(sub)
        return sub

    async def execute_trajectory(self, samples: Any, **_: Any) -> StubRun:
        self.run = StubRun(len(samples))
        self.started.set()
        return self.run

    def feed(self, state: RobotState) -> None:
        self.latest = state
        for sub in self.watched:
            sub.waiting.clear()
        for sub in tuple(self.subscriptions):
            sub.offer(state)

    async def handled(self, move: asyncio.Task[Any]) -> None:
        """Until the move has handled what was fed: it waits for the next sample, or ended."""
        waiting = asyncio.ensure_future(self.watched[0].waiting.wait())
        try:
            await asyncio.wait({waiting, move}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            waiting.cancel()


# ----------------------------------------------------------------- StateSubscription


async def test_a_bounded_wait_returns_a_waiting_sample_at_once() -> None:
    sub = StateSubscription(set(), 8)
    sub.offer(_state(0, HOME))
    assert (await sub.next_within(0.0)).timestamp == _state(0, HOME).timestamp


async def test_a_bounded_wait_times_out_at_its_deadline() -> None:
    with StateSubscription(set(), 8) as sub:
        t0 = time.monotonic()
        with pytest.raises(TimeoutError):
            await sub.next_within(0.1)
        waited = time.monotonic() - t0
    assert 0.1 - 0.002 <= waited < 0.1 + 0.1


async def test_one_timer_serves_a_reader_that_gets_every_sample_in_time() -> None:
    # samples every 20 ms for 0.3 s, each awaited with a 0.1 s bound: none times out, the
    # timer armed by the first wait is re-armed when it fires (every ~0.1 s), never per
    # sample; then the stream stops, and the last wait times out 0.1 s after it began
    loop = asyncio.get_running_loop()
    subscriptions: set[StateSubscription] = set()
    with StateSubscription(subscriptions, 8) as sub:
        timers = set()
        for k in range(15):
            loop.call_later(0.02, sub.offer, _state(k, HOME))
            state = await sub.next_within(0.1)
            assert state.received_at == k
            timers.add(id(sub._timer))
        assert len(timers) <= 6  # 15 waits, a timer per 0.1 s at most (and at times none)
        t0 = time.monotonic()
        with pytest.raises(TimeoutError):
            await sub.next_within(0.1)
        waited = time.monotonic() - t0
        assert 0.1 - 0.002 <= waited < 0.1 + 0.1
    assert sub._timer is None
    assert not subscriptions


async def test_an_unbounded_reader_never_times_out_on_the_timer_of_a_bounded_one() -> None:
    loop = asyncio.get_running_loop()
    with StateSubscription(set(), 8) as sub:
        with pytest.raises(TimeoutError):
            await sub.next_within(0.01)
        loop.call_later(0.05, sub.offer, _state(1, HOME))
        assert (await sub.__anext__()).received_at == 1


async def test_a_bounded_wait_keeps_its_deadline_when_the_subscription_closes() -> None:
    loop = asyncio.get_running_loop()
    sub = StateSubscription(set(), 8)
    loop.call_later(0.02, sub.close)
    t0 = time.monotonic()
    with pytest.raises(TimeoutError):
        await sub.next_within(0.1)
    assert time.monotonic() - t0 >= 0.1 - 0.002
    assert sub._timer is None


async def test_a_full_buffer_drops_the_oldest_sample() -> None:
    sub = StateSubscription(set(), 2)
    for k in range(3):
        sub.offer(_state(k, HOME))
    assert sub.dropped == 1
    assert [(await sub.__anext__()).received_at for _ in range(2)] == [1, 2]


# ----------------------------------------------------------------- the move's watch


@pytest.mark.parametrize(
    "capabilities",
    [UR3E, RobotCapabilities("slow-stream", 6, DT, state_patience=0.6)],
    ids=lambda c: c.kind,
)
async def test_a_move_whose_state_stream_stops_is_braked_and_fails_at_its_kinds_patience(
    capabilities: RobotCapabilities, plan: MovePlan
) -> None:
    planner = MotionPlanner(CONFIG, capabilities=capabilities)
    patience = capabilities.state_patience
    link = StubLink(_state(0, HOME))
    execution = MoveExecution(plan, link, planner)  # type: ignore[arg-type]
    move = asyncio.create_task(execution.run())
    await link.started.wait()
    # a stream for twice the patience (the bounded wait's timer is re-armed on the way),
    # then nothing: the link is not reported down, only the samples stop
    for k in range(1, round(2 * patience / DT)):
        link.feed(_state(k, HOME))
        await asyncio.sleep(DT)  # the stream's pace
    await link.handled(move)
    with pytest.raises(ConnectionLostError, match=f"no robot state for {patience:g} s"):
        await move
    waited = time.monotonic() - link.watched[0].since  # from the wait after the last sample
    assert patience - 0.002 <= waited < patience + 0.25
    # the trajectory was ended before the error went through: a robot whose controller
    # holds the whole trajectory (the Ned2) would run on, and refuse the next one
    assert link.run is not None
    assert link.run.done
    assert link.run.stops == [StopReason.MOVE_ABORTED]


async def test_a_move_ends_at_the_sample_where_the_link_sends_the_last_planned_one(
    planner: MotionPlanner, plan: MovePlan
) -> None:
    # The arm is at the target, still, from the first sample on (as when the servo's lead
    # brings it there early): the move ends as soon as the link has sent the plan's last
    # sample by the controller's clock (its progress reports name the sample they answer),
    # neither before nor a sample later, however late the reports reach the loop.
    link = StubLink(_state(0, TARGET))
    execution = MoveExecution(plan, link, planner)  # type: ignore[arg-type]
    move = asyncio.create_task(execution.run())
    await link.started.wait()
    run = link.run
    assert run is not None
    last = len(plan.trajectory) - 1
    ended_at = None
    for k in range(1, last + 50):
        state = _state(k, TARGET)
        link.feed(state)
        if k % PROGRESS_EVERY == 0:  # the link sent sample k for the state of time t(k)
            run.progress = TrajectoryProgress(k, run.total, None, 0.0, 0.0, state.timestamp)
        await link.handled(move)
        if run.stops:
            ended_at = k
            break
    assert ended_at == last
    assert run.stops == [StopReason.SETTLED]
    result = await move
    assert not result.stopped
    assert result.joint_error < 1e-9
