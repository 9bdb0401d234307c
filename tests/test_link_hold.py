"""The link process's trajectory thread keeps servo mode briefly after a move at its target.

Leaving servo mode (servoStop) and entering it again are controller round trips of several
milliseconds each; a next move that starts while the previous one holds its target takes
servo mode over instead. These tests run :class:`fxcell.link.process._Trajectory`'s loop in
the test's own thread against a stand-in for the link: a controller on a stepped clock (no
wall clock, no threads) whose state samples arrive on a schedule the test chooses, and a
stand-in for ur_rtde's control interface that records every call. What the cell does
meanwhile (a stop, the next move's take-over) happens at chosen moments of that clock, so
every run of a test is the same run. Last, how the link tells a silent cell from its own
beat thread starved of the CPU.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import socket
import threading
import time
import types
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np
import pytest

from fxcell.link import process, wire
from fxcell.link.contract import Guard, StopReason
from fxcell.link.follower import servo_omega
from fxcell.link.process import _Trajectory
from fxcell.protocol import CONTROL_PERIOD, RobotState, RuntimeState

pytestmark = pytest.mark.timeout(30)

TARGET = (0.1, -1.2, 1.0, -1.4, -1.57, 0.0)
T = CONTROL_PERIOD
WAKE = 20e-6  # what a wait that a notify ends at once costs on the stepped clock


class Control:
    """ur_rtde's RTDEControlInterface as far as a trajectory uses it: records calls, each
    with the stand-in link's clock and the controller time of its newest sample."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.calls: list[str] = []
        self.targets: list[tuple[float, ...]] = []
        self.stamps: list[float] = []  # the controller time of each servoJ
        self.walls: list[float] = []  # and the link's clock
        self.stop_walls: list[float] = []  # the link's clock at each servoStop

    def servoJ(self, *args: Any) -> bool:  # noqa: N802 (ur_rtde's name)
        self.targets.append(tuple(args[0]))
        latest = self.link.latest
        self.stamps.append(latest.timestamp if latest is not None else 0.0)
        self.walls.append(self.link.now)
        self.calls.append("servoJ")
        return True

    def servoStop(self) -> bool:  # noqa: N802
        self.stop_walls.append(self.link.now)
        self.calls.append("servoStop")
        return True

    def count(self, name: str) -> int:
        return self.calls.count(name)


OMEGA = servo_omega(0.03, 2000.0)


def _track(
    q: tuple[float, ...], qd: tuple[float, ...], setpoint: tuple[float, ...], cycles: int
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """servoJ's target after ``cycles`` control cycles towards ``setpoint`` (the
    critically damped tracker the follower and the simulator assume)."""
    x, v = list(q), list(qd)
    for _ in range(cycles):
        for j, s in enumerate(setpoint):
            v[j] += (OMEGA * OMEGA * (s - x[j]) - 2 * OMEGA * v[j]) * CONTROL_PERIOD
            x[j] += v[j] * CONTROL_PERIOD
    return tuple(x), tuple(v)


def every(cycles: int = 1) -> Iterator[tuple[float, float]]:
    """A controller whose samples (arrival on the link's clock, controller time) come
    every ``cycles`` control cycles: one that skips cycles, or whose samples are lost."""
    for k in itertools.count(1):
        yield k * cycles * T, k * cycles * T


class Link:
    """The attributes of fxcell.link.process.Link a trajectory reads, on a stepped clock.

    ``now`` only moves when the trajectory waits for a sample (``next_sample``): to the
    next sample's arrival if that comes within the wait, else by the whole wait. Actions
    registered with :meth:`when` run at the first wait at which their condition holds, as
    the cell's calls would arrive from another thread.
    """

    stream = None  # no socket: a stall's explanation reads no unread bytes

    def __init__(self, arrivals: Iterable[tuple[float, float]] | None = None) -> None:
        self.now = 0.0
        self.control = Control(self)
        self.latest: RobotState | None = RobotState(
            runtime_state=RuntimeState.PLAYING, actual_q=TARGET, target_q=TARGET
        )
        self.last_heard = self.last_state_at = 0.0
        self.sample_walls: list[float] = []  # the clock at each sample's arrival
        self.sent: list[tuple[Any, ...]] = []
        self.sent_at: list[float] = []  # the clock at each message
        self._arrivals = iter(arrivals if arrivals is not None else every())
        self._next = next(self._arrivals)
        self._actions: list[tuple[Callable[[], bool], Callable[[], object]]] = []
        self._samples = 0
        self._tick = threading.Condition()
        self._traj_lock = threading.Lock()
        self._traj: _Trajectory | None = None

    def when(self, condition: Callable[[], bool], action: Callable[[], object]) -> None:
        self._actions.append((condition, action))

    def _act(self) -> None:
        for entry in list(self._actions):
            if entry[0]():
                self._actions.remove(entry)
                entry[1]()

    def next_sample(
        self, seen: int, timeout: float, woken: Callable[[], bool] | None = None
    ) -> tuple[int, RobotState | None]:
        self._act()
        if self._samples != seen:
            return self._samples, self.latest
        if woken is not None and woken():
            self.now += WAKE  # woken at once; a loop that kept waking would still end
            return self._samples, self.latest
        arrival, stamp = self._next
        if arrival <= self.now + timeout:
            self.now = max(self.now, arrival)
            self.publish(stamp)
            self._next = next(self._arrivals)
        else:
            self.now += timeout
        return self._samples, self.latest

    def publish(self, stamp: float) -> None:
        """A state sample of controller time ``stamp`` arrives now: servoJ's target has
        tracked the newest setpoint for the cycles since the last sample."""
        self.last_heard = self.last_state_at = self.now
        self.sample_walls.append(self.now)
        assert self.latest is not None
        q, qd = self.latest.target_q, self.latest.target_qd
        if self.control.targets:
            last = self.latest.timestamp
            cycles = max(round((stamp - last) / T), 1) if last else 1
            q, qd = _track(q, qd, self.control.targets[-1], cycles)
        self.latest = dataclasses.replace(self.latest, timestamp=stamp, target_q=q, target_qd=qd)
        self._samples += 1

    def heard_within(self, timeout: float, now: float) -> bool:
        return now - self.last_heard <= timeout

    def place(self, q: tuple[float, ...]) -> None:
        """The arm rests at ``q`` (where the next trajectory starts)."""
        assert self.latest is not None
        self.latest = dataclasses.replace(self.latest, target_q=q, actual_q=q)

    def send(self, *message: Any) -> None:
        self.sent.append(message)
        self.sent_at.append(self.now)

    def ended_at(self) -> float:
        """The clock at the trajectory's end report."""
        return next(t for t, m in zip(self.sent_at, self.sent, strict=True) if m[2:3] == ("end",))

    def ends(self) -> list[dict[str, Any]]:
        return [m[3] for m in self.sent if m[0] == wire.TRAJ and m[2] == "end"]

    def trajectory(self, samples: list[tuple[float, ...]]) -> _Trajectory:
        """A trajectory of ``samples`` on this link, the arm resting at the first."""
        self.place(samples[0])
        traj = _Trajectory(
            self,  # type: ignore[arg-type]
            1,
            samples,
            0.03,
            2000.0,
            Guard(cell_timeout=None),
            clock=lambda: self.now,
        )
        self._traj = traj
        return traj

    def run(self, traj: _Trajectory) -> None:
        """The trajectory's loop, to its end (the hold's included), in this thread."""
        traj._run()
        assert not self._actions, "an action's moment never came"


class EndHeld(Link):
    """A link that runs ``on_end`` as it sends a trajectory's end report: the moment
    between the report and the hold, in which the cell may start the next move."""

    def __init__(self, on_end: Callable[[], object]) -> None:
        super().__init__()
        self.on_end = on_end

    def send(self, *message: Any) -> None:
        super().send(*message)
        if message[0] == wire.TRAJ and message[2] == "end":
            self.on_end()


SHORT = [tuple(v) for v in np.linspace(np.subtract(TARGET, 0.001), TARGET, 10)]


def _servo_js(link: Link, n: int) -> Callable[[], bool]:
    return lambda: link.control.count("servoJ") >= n


def test_a_completed_trajectory_hands_servo_mode_to_the_next_without_servo_stop() -> None:
    link = Link()
    traj = link.trajectory(SHORT)
    released: list[bool] = []
    link.when(traj.hold_started.is_set, lambda: released.append(traj.release(keep_servo=True)))
    link.run(traj)
    assert link.ends()[0]["status"] == "completed"
    assert released == [True]
    assert traj.servo_kept
    assert link.control.count("servoStop") == 0


def test_a_call_after_a_move_ends_the_hold_with_servo_stop() -> None:
    link = Link()
    traj = link.trajectory(SHORT)
    link.when(traj.hold_started.is_set, lambda: traj.release(keep_servo=False))
    link.run(traj)
    assert not traj.servo_kept
    assert link.control.calls[-1] == "servoStop"
    # at once, not after holding the target for its time
    assert link.control.stop_walls[-1] - link.ended_at() <= 2 * T


def test_an_unclaimed_hold_leaves_servo_mode_after_its_time() -> None:
    link = Link()
    traj = link.trajectory(SHORT)
    link.run(traj)
    assert link.control.calls[-1] == "servoStop"
    # from the end report (the hold follows it) to the servoStop: the hold's time, to
    # the cycle
    held = link.control.stop_walls[-1] - link.ended_at()
    assert _Trajectory.HOLD - 1e-9 <= held <= _Trajectory.HOLD + 2 * T
    assert not traj.release(keep_servo=True)  # too late to take it over


def test_a_move_stopped_away_from_its_target_leaves_servo_mode_at_once() -> None:
    link = Link()
    traj = link.trajectory(SHORT)
    link.when(_servo_js(link, 1), lambda: traj.stop(StopReason.CELL_SILENT))
    link.run(traj)
    assert link.ends()[0]["status"] == "stopped"
    assert link.control.calls[-1] == "servoStop"
    assert not traj.hold_started.is_set()
    assert not traj.release(keep_servo=True)


def test_a_stop_for_the_settled_robot_keeps_servo_mode_for_the_next_move() -> None:
    link = Link()
    traj = link.trajectory([TARGET] * 200)  # a move's hold part: the robot is at the target
    link.when(_servo_js(link, 3), lambda: traj.stop(StopReason.SETTLED))
    released: list[bool] = []
    link.when(traj.hold_started.is_set, lambda: released.append(traj.release(keep_servo=True)))
    link.run(traj)
    assert link.ends()[0]["reason"] == StopReason.SETTLED
    assert link.control.count("servoJ") < 200  # it ended there, not at the last sample
    assert released == [True]
    assert traj.servo_kept
    assert link.control.count("servoStop") == 0


@pytest.mark.parametrize("end", ["completed", StopReason.SETTLED])
def test_a_next_move_right_after_the_end_report_takes_servo_mode_over_at_once(end: str) -> None:
    took_over: list[bool] = []
    streamed: list[int] = []

    def next_move() -> None:
        assert not traj.hold_started.is_set()  # reported, not yet holding
        streamed.append(len(link.control.calls))
        took_over.append(traj.release(keep_servo=True))  # what the next trajectory does

    link = EndHeld(next_move)
    if end == "completed":
        traj = link.trajectory(SHORT)
    else:
        traj = link.trajectory([TARGET] * 200)
        link.when(_servo_js(link, 3), lambda: traj.stop(StopReason.SETTLED))
    link.run(traj)
    assert took_over == [True]
    # handed over at once, not after holding the target: not one servoJ after the report
    # (a hold servos the target every cycle until its time is up)
    assert link.control.calls[streamed[0] :] == []
    assert traj.servo_kept
    assert link.control.count("servoStop") == 0


def test_a_move_that_ends_away_from_its_target_is_not_taken_over_after_its_report() -> None:
    took_over: list[bool] = []
    link = EndHeld(lambda: took_over.append(traj.release(keep_servo=True)))
    traj = link.trajectory([tuple(v) for v in np.linspace(np.subtract(TARGET, 0.1), TARGET, 400)])
    link.when(_servo_js(link, 3), lambda: traj.stop(StopReason.CELL_SILENT))
    link.run(traj)
    assert took_over == [False]  # it leaves servo mode: the next move enters it
    assert not traj.servo_kept
    assert link.control.calls[-1] == "servoStop"


@pytest.mark.parametrize(
    ("reason", "level"),
    [(StopReason.SETTLED, logging.DEBUG), (StopReason.STATE_STALLED, logging.WARNING)],
)
def test_only_a_stop_away_from_the_target_warns_that_the_link_brakes(
    reason: StopReason, level: int
) -> None:
    # a slow tail still in motion: the cell may see the robot settled before it streams
    link = Link()
    tail = np.linspace(np.subtract(TARGET, 1e-5), TARGET, 400)
    traj = link.trajectory([tuple(v) for v in tail])
    link.when(_servo_js(link, 3), lambda: traj.stop(reason))
    link.run(traj)
    said = [(m[1], m[2]) for m in link.sent if m[0] == wire.LOG]
    assert said == [(level, f"braking to rest: {reason}")]


def test_a_stop_during_the_hold_leaves_servo_mode() -> None:
    link = Link()
    traj = link.trajectory(SHORT)
    link.when(traj.hold_started.is_set, lambda: traj.stop(StopReason.LINK_CLOSING))
    link.run(traj)
    assert link.control.calls[-1] == "servoStop"
    held = link.control.stop_walls[-1] - link.ended_at()
    assert held <= 2 * T  # not the hold's whole time
    assert not traj.servo_kept


RAMP = [tuple(np.add(TARGET, (k * 1e-4,) * 6)) for k in range(-200, 1)]


def _ramp_on(link: Link) -> Control:
    """Stream RAMP on ``link`` to its end and through its hold."""
    link.run(link.trajectory(RAMP))
    assert link.ends()[0]["status"] == "completed"
    return link.control


def _advance(c: Control) -> np.ndarray:
    """Each setpoint's place on RAMP, in samples from its start."""
    return np.round((np.array(c.targets)[:, 0] - RAMP[0][0]) / 1e-4)


@pytest.mark.parametrize("cycles", [1, 2, 3])
def test_a_controller_skipping_cycles_keeps_the_path_on_its_clock(cycles: int) -> None:
    # A busy simulator (or lost samples) shows cycles without a sample of their own: each
    # setpoint advances the path by the cycles since the last, so the move keeps its time.
    c = _ramp_on(Link(every(cycles)))
    end = c.targets.index(RAMP[-1])
    advance = _advance(c)[: end + 1]
    assert np.diff(advance).max() <= _Trajectory.CATCH_UP
    # never ahead of the controller's clock
    elapsed = (np.array(c.stamps[: end + 1]) - c.stamps[0]) / T
    assert np.all(advance <= elapsed + cycles)
    # and it keeps the controller's time: it does not lose the skipped cycles (a path that
    # ignored them would take `cycles` times, or with the 3 ms timer 1.5 times, as long)
    took = (c.stamps[end] - c.stamps[0]) / T
    assert took <= len(RAMP) - 1 + cycles, f"{took:.0f} cycles for {len(RAMP) - 1} samples"


def test_a_long_controller_gap_stretches_the_path_rather_than_jumping() -> None:
    c = _ramp_on(Link(every(20)))  # 40 ms of controller time per sample
    advance = _advance(c)[: c.targets.index(RAMP[-1]) + 1]
    assert np.diff(advance).max() <= _Trajectory.CATCH_UP
    # the path lost what the catch-up could not make good: it took longer than planned
    took = (c.stamps[c.targets.index(RAMP[-1])] - c.stamps[0]) / T
    assert took > len(RAMP) - 1


def backlogged(stall: float) -> Iterator[tuple[float, float]]:
    """A link process starved for ``stall`` s after 39 cycles of samples: the samples the
    controller sent meanwhile queued up, and then arrive at once (each as soon as the
    trajectory waits for the next), and one per cycle again after them."""
    for k in range(1, 40):
        yield k * T, k * T
    woke = 39 * T + stall
    backlog = round(stall / T)
    for k in range(40, 40 + backlog):
        yield woke, k * T
    for j, k in enumerate(itertools.count(40 + backlog), start=1):
        yield woke + j * T, k * T


def test_a_burst_of_queued_samples_after_a_stall_does_not_jump_the_setpoint() -> None:
    # The controller reads the newest setpoint once per cycle: the setpoints sent within
    # one cycle must not add up to a jump (the controller refuses one with a protective
    # stop). The path waits out the backlog instead.
    link = Link(backlogged(0.05))
    c = _ramp_on(link)
    burst = [i for i, w in enumerate(c.walls) if w == 39 * T + 0.05]
    assert len(burst) >= round(0.05 / T) - 1  # the queued samples did arrive at once
    advance = _advance(c)
    walls = np.array(c.walls)
    for i in range(len(walls)):
        within = walls[i:] - walls[i] <= T
        jump = advance[i:][within].max() - advance[i]
        assert jump <= _Trajectory.CATCH_UP + 1, f"{jump:.0f} samples within one cycle"


def test_beats_waiting_in_the_channel_keep_a_starved_link_from_calling_the_cell_silent() -> None:
    # The link's beat thread may not have run (CPU, GIL) while the cell beat on: the beats
    # waiting in the channel show it alive. Once they are read, silence counts again.
    mine, theirs = socket.socketpair()
    with mine, theirs:
        link = types.SimpleNamespace(last_heard=time.monotonic() - 1.0, beats=mine)
        now = time.monotonic()
        assert not process.Link.heard_within(link, 0.1, now)  # type: ignore[arg-type]
        theirs.send(b"bbb")
        assert process.Link.heard_within(link, 0.1, now)  # type: ignore[arg-type]
        assert link.last_heard == now
        later = now + 0.2
        assert not process.Link.heard_within(link, 0.1, later)  # type: ignore[arg-type]
        theirs.close()
        assert not process.Link.heard_within(link, 0.1, later)  # type: ignore[arg-type]
