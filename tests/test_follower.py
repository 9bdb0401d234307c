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
import math

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from fxcell.link.contract import StopReason
from fxcell.link.follower import (
    CELL_SILENT,
    STATE_STALLED,
    Cycle,
    Follower,
    Guard,
    brake_duration,
    path_velocity,
    servo_omega,
)
from fxcell.protocol import CONTROL_PERIOD, RobotMode, RobotState, RuntimeState, SafetyMode

DT = CONTROL_PERIOD
START = (0.1, -1.2, 1.0, -1.4, -1.57, 0.0)
STEP = 0.002  # rad per sample on every joint: 1 rad/s
LOOKAHEAD, GAIN = 0.1, 300.0
OMEGA = servo_omega(LOOKAHEAD, GAIN)
JERK = 10.0  # rad/s³: the shipped limits' jerk (config/ur3e_limits.yaml), which Ruckig keeps


def ramp(n: int, step: float = STEP) -> list[tuple[float, ...]]:
    return [tuple(q + k * step for q in START) for k in range(n)]


def state(t: float, q: tuple[float, ...] = START, **changes: object) -> RobotState:
    base = RobotState(
        timestamp=t,
        robot_mode=RobotMode.RUNNING,
        safety_mode=SafetyMode.NORMAL,
        runtime_state=RuntimeState.PLAYING,
        target_q=q,
        actual_q=q,
        actual_qd=(1.0,) * 6,
    )
    return dataclasses.replace(base, **changes)  # type: ignore[arg-type]


class Run:
    """A follower driven at one state sample per controller cycle, on a clock of its own,
    with servoJ's tracker (as the simulator has it) turning its setpoints into the target
    joint velocities the state reports. It starts tracking the path's first samples in
    steady state (lagging a ramp by 2v/ω)."""

    def __init__(
        self,
        samples: list[tuple[float, ...]],
        guard: Guard | None = None,
        *,
        lookahead: float = LOOKAHEAD,
        gain: float = GAIN,
    ) -> None:
        self.t = 0.0
        self.guard = guard or Guard()
        self.omega = servo_omega(lookahead, gain)
        self.follower = Follower(samples, self.guard, lookahead, gain=gain, now=0.0, clock=0.0)
        self.sent: list[tuple[float, ...]] = []
        self.heard_at = 0.0
        self.state_at = 0.0
        v = [
            (b - a) / DT for a, b in zip(samples[0], samples[min(1, len(samples) - 1)], strict=True)
        ]
        self.q = [a - 2 * x / self.omega for a, x in zip(samples[0], v, strict=True)]
        self.qd = v
        self.accelerations: list[tuple[float, ...]] = []
        """servoJ's acceleration in each cycle that had a fresh setpoint."""
        self.state: RobotState | None = state(0.0, target_q=tuple(self.q), target_qd=tuple(v))

    def cycle(self) -> Cycle:
        out = self.follower.cycle(
            self.t, self.state, heard_at=self.heard_at, state_at=self.state_at
        )
        if out.target is not None:
            self.sent.append(out.target)
        return out

    def track(self, cycles: int) -> None:
        """servoJ's tracker runs ``cycles`` control cycles on the newest setpoint."""
        w = self.omega
        for k in range(cycles):
            a = [
                w * w * (s - x) - 2 * w * v
                for s, x, v in zip(self.sent[-1], self.q, self.qd, strict=True)
            ]
            if k == 0:
                self.accelerations.append(tuple(a))
            self.qd = [v + x * DT for v, x in zip(self.qd, a, strict=True)]
            self.q = [x + v * DT for x, v in zip(self.q, self.qd, strict=True)]

    def advance(self, cycles: int = 1, *, sample: bool = True) -> None:
        if self.sent:
            self.track(cycles)
        self.t += cycles * DT
        if sample:
            self.state_at = self.t
            self.heard_at = self.t
            if self.state is not None:
                self.state = dataclasses.replace(
                    self.state, timestamp=self.t, target_q=tuple(self.q), target_qd=tuple(self.qd)
                )
        self.follower.advance(self.t, self.t if sample else None)

    def run(self, limit: int = 100_000, **advance: object) -> Cycle:
        """Cycles until the follower ends; returns the end."""
        for _ in range(limit):
            out = self.cycle()
            if out.target is None:
                return out
            self.advance(**advance)  # type: ignore[arg-type]
        raise AssertionError("the follower never ended")

    def worst(self) -> float:
        """servoJ's largest acceleration over the braking limit, in the cycles with a
        fresh setpoint."""
        limits = self.guard.brake_acceleration
        return max(
            (abs(a) / m for row in self.accelerations for a, m in zip(row, limits, strict=True)),
            default=0.0,
        )


def joint0(sent: list[tuple[float, ...]]) -> list[float]:
    return [q[0] for q in sent]


# ----------------------------------------------------------------- advance


def test_one_sample_of_path_per_controller_cycle() -> None:
    run = Run(ramp(50))
    for _ in range(20):
        run.cycle()
        run.advance()
    assert run.sent == ramp(50)[:20]
    assert run.follower.limited == []


def test_a_sample_a_few_cycles_late_keeps_the_path_on_the_controller_clock() -> None:
    run = Run(ramp(50))
    run.cycle()
    run.advance(3)  # the controller ran three cycles before this sample
    run.cycle()
    assert run.follower.u == 3
    assert run.sent[-1] == ramp(50)[3]


def test_a_gap_longer_than_the_catch_up_stretches_the_path() -> None:
    run = Run(ramp(50))
    run.cycle()
    run.advance(20)
    run.cycle()
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
    run.cycle()
    assert run.follower.u == 1
    run.advance(1)  # the sample of the second cycle: the timer already paced one
    run.cycle()
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
    run.follower.stop(StopReason.STOP_REQUESTED)
    _brakes(run, StopReason.STOP_REQUESTED)
    _braked_smoothly(run, 100)
    duration = brake_duration(path_velocity(ramp(2000), 100), run.guard)
    assert len(run.sent) - 100 == pytest.approx(duration / DT, abs=2)


def test_the_client_socket_closing_brakes_the_same_way() -> None:
    # the link process's reader ends: Link.run() stops the trajectory with this reason
    run = Run(ramp(2000))
    for _ in range(50):
        run.cycle()
        run.advance()
    run.follower.stop(StopReason.LINK_CLOSING)
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
    run.follower.stop(StopReason.SETTLED)
    out = run.cycle()
    assert (out.status, out.reason) == ("stopped", StopReason.SETTLED)
    assert [n for n in run.follower.notices if n.kind == "log"] == []


def test_only_a_stop_away_from_the_target_warns() -> None:
    run = Run(ramp(300))
    run.cycle()
    run.advance()
    run.follower.stop(StopReason.SETTLED)
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
    slower = [tuple(q + k * STEP / 2 for q in path[15]) for k in range(50)]
    run.follower.replace(slower, at_index=15)
    for _ in range(7):
        run.cycle()
        run.advance()
    assert run.sent[10:15] == path[10:15]
    assert run.sent[15:17] == slower[:2]
    assert [n.data for n in run.follower.notices] == [{"ok": True, "late": False}]
    assert run.follower.limited == []


def test_a_late_splice_joins_the_new_samples_where_the_path_is() -> None:
    path = ramp(300)
    run = Run(path)
    for _ in range(20):
        run.cycle()
        run.advance()
    new = path[15:]
    run.follower.replace(new, at_index=15)
    run.cycle()
    assert run.sent[-1] == new[5] == path[20]
    assert [n.data for n in run.follower.notices] == [{"ok": True, "late": True}]
    assert run.follower.limited == []


def test_a_splice_that_jumps_is_limited_and_recorded() -> None:
    # the check on the setpoint stream: a replacement 0.5 rad away would be a step far
    # beyond the braking acceleration; servoJ gets the setpoint at the limit instead
    run = Run(ramp(300))
    for _ in range(20):
        run.cycle()
        run.advance()
    away = [tuple(q + 0.5 for q in START)] * 100
    run.follower.replace(away, at_index=None)
    for _ in range(5):
        run.cycle()
        run.advance()
    assert run.worst() <= 1.0 + 1e-9
    events = run.follower.limited
    assert {e.joint for e in events} == set(range(6))
    assert all(abs(e.acceleration) > e.limit for e in events)
    warnings = [n.text for n in run.follower.notices if n.kind == "log"]
    assert len(warnings) == 1  # one warning per LIMIT_REPORT_EVERY, with a count
    assert warnings[0].startswith("setpoint limited (6 since the last report): joint ")


def test_a_splice_while_braking_by_itself_is_refused() -> None:
    run = Run(ramp(2000))
    for _ in range(20):
        run.cycle()
        run.advance()
    run.follower.stop(StopReason.STOP_REQUESTED)
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
    f.stop(StopReason.SETTLED)
    f.begin_hold()
    assert f.hold_target(state(0.0)) == path[-1]
    assert f.hold_target(state(0.0, safety_mode=SafetyMode.PROTECTIVE_STOP)) is None
    f.stop(StopReason.LINK_CLOSING)
    assert f.hold_target(state(0.0)) is None


# ----------------------------------------------------------------- every cycle within limits


def smooth_path(distances: list[float], lag: float) -> list[tuple[float, ...]]:
    """A rest-to-rest move of ``distances`` (rad per joint) within the move limits
    (0.7 rad/s² and the jerk ``JERK``, ``q = D (t/T - sin(2πt/T)/2π)``), as the motion layer
    streams it: led by servoJ's lag (``q + lag·q̇ + lag²/4·q̈``). Without the jerk bound a
    10 µrad move lasted 10 ms, which no jerk-limited profile makes: its lag lead alone
    asked for more than the braking acceleration."""
    peak = max(map(abs, distances))
    duration = max(
        math.sqrt(2 * math.pi * peak / 0.7), (4 * math.pi**2 * peak / JERK) ** (1 / 3), 4 * DT
    )
    n = round(duration / DT)
    out = []
    for k in range(n + 1):
        t = k * DT / duration
        c, s = math.cos(2 * math.pi * t), math.sin(2 * math.pi * t)
        row = []
        for q0, d in zip(START, distances, strict=True):
            q = q0 + d * (t - s / (2 * math.pi))
            qd = d / duration * (1 - c)
            qdd = 2 * math.pi * d / duration**2 * s
            row.append(q + lag * qd + lag * lag / 4 * qdd)
        out.append(tuple(row))
    return out


distances = st.lists(st.floats(-1.5, 1.5), min_size=6, max_size=6)
# per controller sample, how many cycles the controller ran since the last one
gaps = st.lists(st.sampled_from([1] * 12 + [2, 3, 4, 6]), min_size=1, max_size=64)


@settings(max_examples=40, deadline=None)
@given(distances, gaps, st.one_of(st.none(), st.floats(0.05, 0.95)))
@example([0.0, 0.0, 1e-5, 0.0, 0.0, 0.0], [1], None)  # the shortest moves (10 µrad)
def test_every_cycle_stays_within_the_limits_across_late_samples_and_stops(
    move: list[float], pattern: list[int], stop_at: float | None
) -> None:
    path = smooth_path(move, 2 / OMEGA)
    run = Run(path)
    stop_index = None if stop_at is None else stop_at * len(path)
    for k in range(100_000):
        if stop_index is not None and run.follower.u >= stop_index:
            run.follower.stop(StopReason.STOP_REQUESTED)
        out = run.cycle()
        if out.target is None:
            break
        run.advance(pattern[k % len(pattern)])
    assert out.status == ("completed" if stop_index is None else "stopped")
    assert run.follower.limited == []
    assert run.worst() <= 1.05


@settings(max_examples=20, deadline=None)
@given(distances, distances)
def test_a_next_move_taking_over_at_the_target_stays_within_the_limits(
    first: list[float], second: list[float]
) -> None:
    path = smooth_path(first, 2 / OMEGA)
    run = Run(path)
    assert run.run().status == "completed"
    # the hand-over: a next trajectory from where the first ended, servoJ's state as is
    start = path[-1]
    follow = [
        tuple(a + b - c for a, b, c in zip(start, q, START, strict=True))
        for q in smooth_path(second, 2 / OMEGA)
    ]
    run.follower = Follower(follow, run.guard, LOOKAHEAD, gain=GAIN, now=run.t, clock=run.t)
    assert run.run().status == "completed"
    assert run.follower.limited == []
    assert run.worst() <= 1.05


def test_a_link_brake_from_a_path_still_accelerating_stays_within_the_braking_limit() -> None:
    # the stop starts where the path accelerates hardest: the time rate's fall adds to it
    path = smooth_path([1.5] * 6, 2 / OMEGA)
    run = Run(path, Guard(cell_timeout=None))
    for _ in range(len(path) // 8):
        run.cycle()
        run.advance()
    run.follower.stop(StopReason.STOP_REQUESTED)
    assert run.run().status == "stopped"
    assert run.follower.limited == []
    assert run.worst() <= 1.0 + 1e-6


@pytest.mark.parametrize(("gap", "limited"), [(2, False), (3, True)])
def test_a_stiff_servo_after_missed_cycles_recovers_within_the_limits(
    gap: int, limited: bool
) -> None:
    # lookahead 0.03 s, gain 2000 (ω ≈ 107/s): each cycle the controller runs on the
    # previous setpoint costs ω²·q̇·Δt ≈ 23 rad/s² at 1 rad/s, and a catch-up jump would
    # snap it back as hard. The follower pays the owed cycles back in gentle parts; after
    # two missed cycles even that is not enough, and the check holds servoJ's recovery
    # at the limit and records it (a stiff servo on a busy machine shows in the log)
    run = Run(ramp(400), lookahead=0.03, gain=2000.0)
    for _ in range(50):
        run.cycle()
        run.advance()
    run.cycle()
    run.advance(gap)  # the controller ran gap - 1 cycles on the previous setpoint
    for _ in range(50):
        run.cycle()
        run.advance()
    assert bool(run.follower.limited) is limited
    assert run.worst() <= (Follower.LIMIT_TOLERANCE if limited else Follower.CATCH_UP_SHARE)
    assert run.follower.u <= 100 + gap  # never ahead of the controller's clock
    assert all(abs(b[0] - a[0]) < 2 * STEP for a, b in itertools.pairwise(run.sent))


def test_the_check_holds_a_stiff_servo_within_the_limits_after_a_jump() -> None:
    # a replacement 0.05 rad off at a stiff setting: the check moves the setpoints so that
    # servoJ accelerates at the limit towards the new samples, and converges on them
    run = Run(ramp(400), lookahead=0.03, gain=2000.0)
    for _ in range(50):
        run.cycle()
        run.advance()
    off = [tuple(q + 0.05 for q in p) for p in ramp(800)[50:]]
    run.follower.replace(off)
    for _ in range(500):
        run.cycle()
        run.advance()
    assert run.follower.limited
    assert run.worst() <= Follower.LIMIT_TOLERANCE
    assert run.sent[-1] == off[run.follower.index]  # back on the path


@pytest.mark.parametrize("gap", [2, 3, 4])
def test_a_late_sample_at_full_speed_is_caught_up_gently(gap: int) -> None:
    # at 3 rad/s: servoJ held the previous setpoint for the missed cycles; the follower
    # catches up only as far as servoJ's response stays within CATCH_UP_SHARE
    run = Run(ramp(3000, step=0.006))
    for _ in range(50):
        run.cycle()
        run.advance()
    run.cycle()
    run.advance(gap)
    for _ in range(50):
        run.cycle()
        run.advance()
    assert run.follower.limited == []
    assert run.worst() <= Follower.CATCH_UP_SHARE + 1e-9
    # the path lost at most the missed cycles (it stretched rather than jumped)
    elapsed = round(run.t / DT)
    assert elapsed - gap < run.follower.u <= elapsed
