"""The trajectory follower, cycle by cycle: no threads, no wall clock.

Each test drives :class:`fxcell.link.follower.Follower` as the link process does (one
``cycle`` and one ``advance`` per controller cycle), with the time and the state samples
as arguments, and checks one rule the link promises: the path's advance and catch-up,
the brakes by itself (client stop, client silence, stalled state stream, the client's
socket closing), the end on a stop in the state, splicing and the end at the target.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging

import pytest

from fxcell.link import wire
from fxcell.link.follower import (
    CELL_SILENT,
    STATE_STALLED,
    Cycle,
    Follower,
    Guard,
    brake_duration,
    path_velocity,
)
from fxcell.protocol import CONTROL_PERIOD, RobotMode, RobotState, RuntimeState, SafetyMode

DT = CONTROL_PERIOD
START = (0.1, -1.2, 1.0, -1.4, -1.57, 0.0)
STEP = 0.002  # rad per sample on every joint: 1 rad/s


def ramp(n: int, step: float = STEP) -> list[tuple[float, ...]]:
    return [tuple(q + k * step for q in START) for k in range(n)]


def state(t: float, q: tuple[float, ...] = START, **changes: object) -> RobotState:
    base = RobotState(
        timestamp=t,
        robot_mode=RobotMode.RUNNING,
        safety_mode=SafetyMode.NORMAL,
        runtime_state=RuntimeState.PLAYING,
        actual_q=q,
        actual_qd=(1.0,) * 6,
    )
    return dataclasses.replace(base, **changes)  # type: ignore[arg-type]


class Run:
    """A follower driven at one state sample per controller cycle, on a clock of its own."""

    def __init__(self, samples: list[tuple[float, ...]], guard: Guard | None = None) -> None:
        self.t = 0.0
        self.guard = guard or Guard()
        self.follower = Follower(samples, self.guard, 0.1, now=0.0, clock=0.0)
        self.sent: list[tuple[float, ...]] = []
        self.heard_at = 0.0
        self.state_at = 0.0
        self.state: RobotState | None = state(0.0)

    def cycle(self) -> Cycle:
        out = self.follower.cycle(
            self.t, self.state, heard_at=self.heard_at, state_at=self.state_at
        )
        if out.target is not None:
            self.sent.append(out.target)
        return out

    def advance(self, cycles: int = 1, *, sample: bool = True) -> None:
        self.t += cycles * DT
        if sample:
            self.state_at = self.t
            self.heard_at = self.t
            if self.state is not None:
                self.state = dataclasses.replace(self.state, timestamp=self.t)
        self.follower.advance(self.t, self.t if sample else None)

    def run(self, limit: int = 100_000, **advance: object) -> Cycle:
        """Cycles until the follower ends; returns the end."""
        for _ in range(limit):
            out = self.cycle()
            if out.target is None:
                return out
            self.advance(**advance)  # type: ignore[arg-type]
        raise AssertionError("the follower never ended")


def joint0(sent: list[tuple[float, ...]]) -> list[float]:
    return [q[0] for q in sent]


# ----------------------------------------------------------------- advance


def test_one_sample_of_path_per_controller_cycle() -> None:
    run = Run(ramp(50))
    for _ in range(20):
        run.cycle()
        run.advance()
    assert run.follower.index == 20
    assert run.sent == ramp(50)[:20]


def test_a_sample_a_few_cycles_late_keeps_the_path_on_the_controller_clock() -> None:
    run = Run(ramp(50))
    run.cycle()
    run.advance(3)  # the controller ran three cycles before this sample
    assert run.follower.u == 3


def test_a_gap_longer_than_the_catch_up_stretches_the_path() -> None:
    run = Run(ramp(50))
    run.cycle()
    run.advance(20)
    assert run.follower.u <= Follower.CATCH_UP


def test_a_burst_of_queued_samples_never_runs_ahead_of_the_followers_clock() -> None:
    run = Run(ramp(200))
    f = run.follower
    for k in range(1, 30):  # 29 samples, all arriving at once (the link was starved)
        f.cycle(0.0, run.state, heard_at=0.0, state_at=0.0)
        f.advance(0.0, k * DT)
    assert f.u <= Follower.CATCH_UP


def test_without_samples_a_timer_paces_the_stream_and_the_next_sample_counts_it() -> None:
    run = Run(ramp(50))
    run.cycle()
    run.advance(sample=False)  # the 3 ms timer: one step
    assert run.follower.u == 1
    run.cycle()
    run.advance(1)  # the sample of the second cycle: the timer already paced one
    assert run.follower.u == 2


# ----------------------------------------------------------------- braking by itself


def _brakes(run: Run, reason: str) -> Cycle:
    end = run.run()
    assert end.status == "stopped"
    assert end.reason == reason
    return end


def _braked_smoothly(run: Run, from_index: int) -> None:
    """The path's rate fell along (1 + cos)/2: speeds decrease, no step beyond the limits."""
    q = joint0(run.sent)[from_index - 1 :]
    speeds = [(b - a) / DT for a, b in itertools.pairwise(q)]
    assert all(b <= a + 1e-9 for a, b in itertools.pairwise(speeds))
    limit = run.guard.brake_acceleration[0]
    assert max(abs(b - a) / DT for a, b in itertools.pairwise(speeds)) <= limit * 1.01
    assert speeds[-1] < 0.05


def test_a_client_stop_brakes_along_the_path_to_rest() -> None:
    run = Run(ramp(2000))
    for _ in range(100):
        run.cycle()
        run.advance()
    run.follower.stop("stop requested")
    _brakes(run, "stop requested")
    _braked_smoothly(run, 100)
    duration = brake_duration(path_velocity(ramp(2000), 100), run.guard)
    assert len(run.sent) - 100 == pytest.approx(duration / DT, abs=2)


def test_the_client_socket_closing_brakes_the_same_way() -> None:
    # the link process's reader ends: Link.run() stops the trajectory with this reason
    run = Run(ramp(2000))
    for _ in range(50):
        run.cycle()
        run.advance()
    run.follower.stop("link closing")
    _brakes(run, "link closing")
    _braked_smoothly(run, 50)


def test_a_silent_client_brakes_after_the_cell_timeout_not_before() -> None:
    guard = Guard(cell_timeout=0.1)
    run = Run(ramp(2000), guard)
    for _ in range(50):
        run.cycle()
        run.advance()
    heard = run.heard_at
    run.heard_at = heard  # from now on the client says nothing
    for _ in range(int(0.1 / DT)):
        assert run.cycle().target is not None
        assert run.follower.braking is None
        run.advance()
        run.heard_at = heard
    run.cycle()
    run.advance()
    run.heard_at = heard
    assert run.follower.braking is not None
    assert run.follower.braking[0] == CELL_SILENT
    warning = [n.text for n in run.follower.notices if n.kind == "log"]
    assert warning
    assert warning[0].startswith("braking to rest: cell_silent for 0.10")
    end = run.follower
    while (out := end.cycle(run.t, run.state, heard_at=heard, state_at=run.t)).target:
        run.sent.append(out.target)
        run.t += DT
        end.advance(run.t, run.t)
    assert out.status == "stopped"
    assert out.reason == CELL_SILENT


def test_a_client_not_watched_never_brakes_for_silence() -> None:
    run = Run(ramp(300), Guard(cell_timeout=None))
    assert run.run().status == "completed"


def test_a_stalled_state_stream_brakes_after_the_stall_timeout() -> None:
    guard = Guard(stall_timeout=0.08, cell_timeout=None)
    run = Run(ramp(2000), guard)
    for _ in range(20):
        run.cycle()
        run.advance()
    stalled_at = run.t
    while run.follower.braking is None:
        assert run.cycle().target is not None
        run.advance(sample=False)  # the timer paces: no samples come
    assert run.follower.braking[0] == STATE_STALLED
    assert run.follower.braking[1] - stalled_at == pytest.approx(0.08, abs=2 * DT)
    end = run.run(sample=False)
    assert (end.status, end.reason) == ("stopped", STATE_STALLED)


@pytest.mark.parametrize(
    ("changes", "reason"),
    [
        ({"safety_mode": SafetyMode.PROTECTIVE_STOP}, "protective_stop"),
        ({"safety_mode": SafetyMode.ROBOT_EMERGENCY_STOP}, "emergency_stop"),
        ({"safety_mode": SafetyMode.SAFEGUARD_STOP}, "safeguard_stop"),
        ({"safety_mode": SafetyMode.FAULT}, "fault"),
        ({"runtime_state": RuntimeState.STOPPED}, "program_stopped"),
    ],
)
def test_a_stop_in_the_state_ends_the_trajectory_at_once(
    changes: dict[str, object], reason: str
) -> None:
    run = Run(ramp(2000))
    for _ in range(30):
        run.cycle()
        run.advance()
    assert run.state is not None
    run.state = dataclasses.replace(run.state, **changes)  # type: ignore[arg-type]
    out = run.cycle()
    assert (out.target, out.status, out.reason) == (None, "failed", reason)


def test_a_stop_at_the_target_needs_no_braking() -> None:
    run = Run([START] * 50)
    run.cycle()
    run.advance()
    run.follower.stop(wire.SETTLED)
    out = run.cycle()
    assert (out.status, out.reason) == ("stopped", wire.SETTLED)
    assert [n for n in run.follower.notices if n.kind == "log"] == []


def test_only_a_stop_away_from_the_target_warns() -> None:
    run = Run(ramp(300))
    run.cycle()
    run.advance()
    run.follower.stop(wire.SETTLED)
    run.cycle()
    assert [(n.level, n.text) for n in run.follower.notices] == [
        (logging.DEBUG, "braking to rest: settled")
    ]


# ----------------------------------------------------------------- splicing


def test_a_splice_at_an_index_still_sends_the_samples_before_it() -> None:
    path = ramp(300)
    run = Run(path)
    for _ in range(10):
        run.cycle()
        run.advance()
    new = [tuple(q + 1.0 for q in START)] * 5
    run.follower.replace(new, at_index=15)
    for _ in range(7):
        run.cycle()
        run.advance()
    assert run.sent[10:15] == path[10:15]
    assert run.sent[15:17] == new[:2]
    assert [n.data for n in run.follower.notices] == [{"ok": True, "late": False}]


def test_a_late_splice_joins_the_new_samples_where_the_path_is() -> None:
    run = Run(ramp(300))
    for _ in range(20):
        run.cycle()
        run.advance()
    new = ramp(100, step=0.001)
    run.follower.replace(new, at_index=15)
    run.cycle()
    assert run.sent[-1] == new[5]
    assert [n.data for n in run.follower.notices] == [{"ok": True, "late": True}]


def test_a_splice_while_braking_by_itself_is_refused() -> None:
    run = Run(ramp(2000))
    for _ in range(20):
        run.cycle()
        run.advance()
    run.follower.stop("stop requested")
    run.cycle()
    run.follower.notices.clear()
    run.follower.replace(ramp(10), at_index=None)
    run.advance()
    run.cycle()
    assert [n.data for n in run.follower.notices] == [{"ok": False}]


# ----------------------------------------------------------------- the end


def test_the_end_holds_the_last_sample_until_the_robot_settles() -> None:
    path = ramp(20)
    run = Run(path)
    for _ in range(20):
        run.cycle()
        run.advance()
    for _ in range(5):  # past the path, not settled: the last sample again
        out = run.cycle()
        assert out.target == path[-1]
        run.advance()
    run.state = state(run.t, q=path[-1], actual_qd=(0.0,) * 6)
    assert run.cycle().status == "completed"
    assert run.follower.at_target


def test_the_end_comes_after_the_settle_time_even_if_the_robot_never_settles() -> None:
    run = Run(ramp(20))
    end = run.run()
    assert end.status == "completed"
    settle = Follower.SETTLE_MAX + 2 * 0.1
    assert len(run.sent) * DT == pytest.approx(20 * DT + settle, abs=2 * DT)


def test_the_hold_after_the_end_ends_on_a_stop_but_not_on_the_settled_stop() -> None:
    path = ramp(20)
    f = Follower(path, Guard(), 0.1, now=0.0, clock=0.0)
    f.stop(wire.SETTLED)
    f.begin_hold()
    assert f.hold_target(state(0.0)) == path[-1]
    assert f.hold_target(state(0.0, safety_mode=SafetyMode.PROTECTIVE_STOP)) is None
    f.stop("link closing")
    assert f.hold_target(state(0.0)) is None
