"""The link process's trajectory thread keeps servo mode briefly after a move at its target.

Leaving servo mode (servoStop) and entering it again are controller round trips of several
milliseconds each; a next move that starts while the previous one holds its target takes
servo mode over instead. These tests drive :class:`fxcell.link.process._Trajectory` with a
stand-in for the link (its 500 Hz sample clock) and for ur_rtde's control interface, which
records every call: what matters here is the order of servoJ and servoStop. Last, how the
link tells a silent cell from its own beat thread starved of the CPU.
"""

from __future__ import annotations

import dataclasses
import logging
import socket
import threading
import time
import types
from collections.abc import Callable, Iterator
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


class Control:
    """ur_rtde's RTDEControlInterface as far as a trajectory uses it: records calls."""

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.targets: list[tuple[float, ...]] = []
        self.stamps: list[float] = []  # the controller time of each servoJ
        self.walls: list[float] = []  # and its time.monotonic()
        self.stop_walls: list[float] = []  # time.monotonic() of each servoStop
        self.clock: Callable[[], float] = lambda: 0.0
        self.changed = threading.Condition()

    def _record(self, name: str) -> bool:
        with self.changed:
            self.calls.append(name)
            self.changed.notify_all()
        return True

    def servoJ(self, *args: Any) -> bool:  # noqa: N802 (ur_rtde's name)
        self.targets.append(tuple(args[0]))
        self.stamps.append(self.clock())
        self.walls.append(time.monotonic())
        return self._record("servoJ")

    def servoStop(self) -> bool:  # noqa: N802
        self.stop_walls.append(time.monotonic())
        return self._record("servoStop")

    def count(self, name: str) -> int:
        with self.changed:
            return self.calls.count(name)

    def wait_for(self, name: str, n: int, timeout: float = 1.0) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: self.calls.count(name) >= n, timeout)


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


class Link:
    """The attributes of fxcell.link.process.Link a trajectory reads, with a sample clock:
    the controller's time is the wall clock's, in 2 ms cycles, and a sample comes every
    ``cycles`` of them (a controller that skips cycles, or whose samples are lost)."""

    def __init__(self, cycles: int = 1) -> None:
        self.cycles = cycles
        self.control = Control()
        self.control.clock = lambda: self.latest.timestamp if self.latest else 0.0
        self.latest: RobotState | None = RobotState(
            runtime_state=RuntimeState.PLAYING, actual_q=TARGET, target_q=TARGET
        )
        self.last_heard = self.last_state_at = time.monotonic()
        self.sample_walls: list[float] = []  # time.monotonic() of each sample
        self.sent: list[tuple[Any, ...]] = []
        self._samples = 0
        self._tick = threading.Condition()
        self._traj_lock = threading.Lock()
        self._traj: _Trajectory | None = None
        self._running = True
        self._clock = threading.Thread(target=self._run, daemon=True)
        self._clock.start()

    def _run(self) -> None:
        start = time.monotonic()
        cycle = 0
        while self._running:
            # the next sample's cycle; a late wake-up (a busy machine) skips to the present
            due = max(cycle + self.cycles, int((time.monotonic() - start) / CONTROL_PERIOD))
            time.sleep(max(start + due * CONTROL_PERIOD - time.monotonic(), 0.0))
            now = time.monotonic()
            cycle = max(due, int((now - start) / CONTROL_PERIOD))
            self.publish(cycle * CONTROL_PERIOD, now)

    def publish(self, stamp: float, now: float) -> None:
        """A state sample of controller time ``stamp`` arrives at ``now``: servoJ's target
        has tracked the newest setpoint for the cycles since the last sample."""
        self.last_heard = self.last_state_at = now
        self.sample_walls.append(now)
        with self._tick:
            if self.latest is not None:
                q, qd = self.latest.target_q, self.latest.target_qd
                if self.control.targets:
                    last = self.latest.timestamp
                    cycles = max(round((stamp - last) / CONTROL_PERIOD), 1) if last else 1
                    q, qd = _track(q, qd, self.control.targets[-1], cycles)
                self.latest = dataclasses.replace(
                    self.latest, timestamp=stamp, target_q=q, target_qd=qd
                )
            self._samples += 1
            self._tick.notify_all()

    def heard_within(self, timeout: float, now: float) -> bool:
        return now - self.last_heard <= timeout

    def place(self, q: tuple[float, ...]) -> None:
        """The arm rests at ``q`` (where the next trajectory starts)."""
        with self._tick:
            assert self.latest is not None
            self.latest = dataclasses.replace(self.latest, target_q=q, actual_q=q)

    next_sample = process.Link.next_sample

    def send(self, *message: Any) -> None:
        self.sent.append(message)

    def ends(self) -> list[dict[str, Any]]:
        return [m[3] for m in self.sent if m[0] == wire.TRAJ and m[2] == "end"]

    def close(self) -> None:
        self._running = False
        self._clock.join(1.0)


@pytest.fixture
def link() -> Iterator[Link]:
    stand_in = Link()
    yield stand_in
    stand_in.close()


def _run(link: Link, traj_id: int = 1) -> _Trajectory:
    samples = [tuple(v) for v in np.linspace(np.subtract(TARGET, 0.001), TARGET, 10)]
    link.place(samples[0])
    traj = _Trajectory(link, traj_id, samples, 0.03, 2000.0, Guard(cell_timeout=None))  # type: ignore[arg-type]
    link._traj = traj
    traj.thread.start()
    return traj


def _wait_ended(traj: _Trajectory) -> None:
    assert traj.ended.wait(5.0)


def test_a_completed_trajectory_hands_servo_mode_to_the_next_without_servo_stop(
    link: Link,
) -> None:
    traj = _run(link)
    _wait_ended(traj)
    assert link.ends()[0]["status"] == "completed"
    assert traj.hold_started.wait(1.0), "the trajectory never held its target"
    assert traj.release(keep_servo=True)
    traj.thread.join(1.0)
    assert not traj.thread.is_alive()
    assert traj.servo_kept
    assert link.control.count("servoStop") == 0


def test_a_call_after_a_move_ends_the_hold_with_servo_stop(link: Link) -> None:
    traj = _run(link)
    _wait_ended(traj)
    traj.release(keep_servo=False)
    traj.thread.join(1.0)
    assert not traj.thread.is_alive()
    assert not traj.servo_kept
    assert link.control.calls[-1] == "servoStop"


def test_an_unclaimed_hold_leaves_servo_mode_after_its_time(link: Link) -> None:
    traj = _run(link)
    _wait_ended(traj)
    traj.thread.join(5.0)
    assert not traj.thread.is_alive()
    assert link.control.calls[-1] == "servoStop"
    # from the trajectory's last setpoint (its 10th servoJ; the hold follows it) to its
    # servoStop, both stamped by the trajectory's own thread, not by this test's
    held = link.control.stop_walls[-1] - link.control.walls[9]
    assert held >= _Trajectory.HOLD * 0.9
    assert not traj.release(keep_servo=True)  # too late to take it over


def test_a_move_stopped_away_from_its_target_leaves_servo_mode_at_once(link: Link) -> None:
    traj = _run(link)
    traj.stop(StopReason.CELL_SILENT)
    traj.thread.join(5.0)
    assert link.ends()[0]["status"] == "stopped"
    assert link.control.calls[-1] == "servoStop"
    assert not traj.release(keep_servo=True)


def test_a_stop_for_the_settled_robot_keeps_servo_mode_for_the_next_move(link: Link) -> None:
    samples = [TARGET] * 200  # the hold part of a move: the robot is already at the target
    traj = _Trajectory(link, 1, samples, 0.03, 2000.0, Guard(cell_timeout=None))  # type: ignore[arg-type]
    traj.thread.start()
    assert link.control.wait_for("servoJ", 3)  # a few samples streamed
    traj.stop(StopReason.SETTLED)
    _wait_ended(traj)
    assert link.ends()[0]["reason"] == StopReason.SETTLED
    assert traj.hold_started.wait(1.0), "the settled trajectory never held its target"
    assert traj.release(keep_servo=True)
    traj.thread.join(1.0)
    assert traj.servo_kept
    assert link.control.count("servoStop") == 0


class EndHeld(Link):
    """A link whose sending of a trajectory's end report waits until it is let go: the
    moment between the report and the hold, in which the cell may start the next move."""

    def __init__(self) -> None:
        super().__init__()
        self.end_sent = threading.Event()
        self.let_go = threading.Event()

    def send(self, *message: Any) -> None:
        super().send(*message)
        if message[0] == wire.TRAJ and message[2] == "end":
            self.end_sent.set()
            assert self.let_go.wait(5.0)


@pytest.mark.parametrize("end", ["completed", StopReason.SETTLED])
def test_a_next_move_right_after_the_end_report_takes_servo_mode_over_at_once(end: str) -> None:
    link = EndHeld()
    try:
        if end == "completed":
            traj = _run(link)
        else:
            traj = _Trajectory(link, 1, [TARGET] * 200, 0.03, 2000.0, Guard(cell_timeout=None))  # type: ignore[arg-type]
            traj.thread.start()
            assert link.control.wait_for("servoJ", 3)
            traj.stop(StopReason.SETTLED)
        assert link.end_sent.wait(5.0)
        assert not traj.hold_started.is_set()  # reported, not yet holding
        streamed = len(link.control.calls)
        assert traj.release(keep_servo=True)  # what the next trajectory does
        link.let_go.set()
        traj.thread.join(5.0)
        assert not traj.thread.is_alive()
        # handed over at once, not after holding the target: not one servoJ after the
        # report (a hold servos the target every cycle until its time is up)
        assert link.control.calls[streamed:] == []
        assert traj.servo_kept
        assert link.control.count("servoStop") == 0
    finally:
        link.let_go.set()
        link.close()


def test_a_move_that_ends_away_from_its_target_is_not_taken_over_after_its_report() -> None:
    link = EndHeld()
    try:
        path = [tuple(v) for v in np.linspace(np.subtract(TARGET, 0.1), TARGET, 400)]
        link.place(path[0])
        traj = _Trajectory(link, 1, path, 0.03, 2000.0, Guard(cell_timeout=None))  # type: ignore[arg-type]
        traj.thread.start()
        assert link.control.wait_for("servoJ", 3)
        traj.stop(StopReason.CELL_SILENT)
        assert link.end_sent.wait(5.0)
        assert not traj.release(keep_servo=True)  # it leaves servo mode: the next enters it
        link.let_go.set()
        traj.thread.join(5.0)
        assert not traj.servo_kept
        assert link.control.calls[-1] == "servoStop"
    finally:
        link.let_go.set()
        link.close()


@pytest.mark.parametrize(
    ("reason", "level"),
    [(StopReason.SETTLED, logging.DEBUG), (StopReason.STATE_STALLED, logging.WARNING)],
)
def test_only_a_stop_away_from_the_target_warns_that_the_link_brakes(
    link: Link, reason: StopReason, level: int
) -> None:
    # a slow tail still in motion: the cell may see the robot settled before it streams
    tail = np.linspace(np.subtract(TARGET, 1e-5), TARGET, 400)
    link.place(tuple(tail[0]))
    traj = _Trajectory(link, 1, [tuple(v) for v in tail], 0.03, 2000.0, Guard(cell_timeout=None))  # type: ignore[arg-type]
    traj.thread.start()
    assert link.control.wait_for("servoJ", 3)
    traj.stop(reason)
    _wait_ended(traj)
    said = [(m[1], m[2]) for m in link.sent if m[0] == wire.LOG]
    assert said == [(level, f"braking to rest: {reason}")]


def test_a_stop_during_the_hold_leaves_servo_mode(link: Link) -> None:
    traj = _run(link)
    _wait_ended(traj)
    traj.stop(StopReason.LINK_CLOSING)
    traj.thread.join(1.0)
    assert not traj.thread.is_alive()
    assert link.control.calls[-1] == "servoStop"


RAMP = [tuple(np.add(TARGET, (k * 1e-4,) * 6)) for k in range(-200, 1)]


def _ramp_on(link: Link) -> Link:
    """Stream RAMP on ``link`` to its end (then close the stand-in)."""
    try:
        link.place(RAMP[0])
        traj = _Trajectory(link, 1, RAMP, 0.03, 2000.0, Guard(cell_timeout=None))  # type: ignore[arg-type]
        traj.thread.start()
        _wait_ended(traj)
        traj.stop(StopReason.STOP_REQUESTED)
        traj.thread.join(1.0)
    finally:
        link.close()
    return link


def _lost_to_gaps(walls: list[float]) -> float:
    """Controller cycles a path may lose to the gaps in ``walls`` (the catch-up stops at
    CATCH_UP cycles: a longer gap, a busy machine's, stretches the path)."""
    gaps = np.diff(walls) / CONTROL_PERIOD
    return float(np.sum(np.maximum(gaps - _Trajectory.CATCH_UP, 0.0)))


@pytest.mark.parametrize("cycles", [1, 2, 3])
def test_a_controller_skipping_cycles_keeps_the_path_on_its_clock(cycles: int) -> None:
    # A busy simulator (or lost samples) shows cycles without a sample of their own: each
    # setpoint advances the path by the cycles since the last, so the move keeps its time.
    link = _ramp_on(Link(cycles))
    assert link.ends()[0]["status"] == "completed"
    c = link.control
    end = c.targets.index(RAMP[-1])
    advance = np.round((np.array(c.targets[: end + 1])[:, 0] - RAMP[0][0]) / 1e-4)
    assert np.diff(advance).max() <= _Trajectory.CATCH_UP
    # never ahead of the controller's clock (which is the wall clock) by more than CATCH_UP
    elapsed = (np.array(c.walls[: end + 1]) - c.walls[0]) / CONTROL_PERIOD
    assert np.all(advance <= elapsed + _Trajectory.CATCH_UP + 1)
    # and it keeps the controller's time: it does not lose the skipped cycles (a path that
    # ignored them would take `cycles` times, or with the 3 ms timer 1.5 times, as long),
    # but for what gaps longer than the catch-up (a busy machine) cost
    took = (c.stamps[end] - c.stamps[0]) / CONTROL_PERIOD
    slack = _lost_to_gaps(c.walls[: end + 1]) + _lost_to_gaps(link.sample_walls) + cycles + 3
    assert took <= len(RAMP) - 1 + slack, f"{took:.0f} cycles for {len(RAMP) - 1} samples"


def test_a_long_controller_gap_stretches_the_path_rather_than_jumping() -> None:
    link = _ramp_on(Link(cycles=20))  # 40 ms of controller time per sample
    path = np.array(link.control.targets[: link.control.targets.index(RAMP[-1]) + 1])
    assert np.abs(np.diff(path[:, 0])).max() <= _Trajectory.CATCH_UP * 1e-4 + 1e-12


class Backlogged(Link):
    """A link process starved for ``stall`` s: the samples the controller sent meanwhile
    queued up, and then arrive at once, each as soon as the trajectory answered the last."""

    def __init__(self, stall: float) -> None:
        self.stall = stall
        super().__init__()

    def _run(self) -> None:
        start = time.monotonic()
        for k in range(1, 40):  # moving at one sample per cycle first
            time.sleep(max(start + k * CONTROL_PERIOD - time.monotonic(), 0.0))
            self.publish(k * CONTROL_PERIOD, time.monotonic())
        time.sleep(self.stall)
        backlog = round(self.stall / CONTROL_PERIOD)
        for k in range(40, 40 + backlog):
            answered = self.control.count("servoJ")
            self.publish(k * CONTROL_PERIOD, time.monotonic())
            self.control.wait_for("servoJ", answered + 1, 0.05)
        cycle = 40 + backlog
        while self._running:
            cycle += 1
            time.sleep(CONTROL_PERIOD)
            self.publish(cycle * CONTROL_PERIOD, time.monotonic())


def test_a_burst_of_queued_samples_after_a_stall_does_not_jump_the_setpoint() -> None:
    # The controller reads the newest setpoint once per cycle: the setpoints sent within
    # one cycle must not add up to a jump (the controller refuses one with a protective
    # stop). The path waits out the backlog instead.
    link = _ramp_on(Backlogged(stall=0.05))
    c = link.control
    assert link.ends()[0]["status"] == "completed"
    advance = np.round((np.array(c.targets)[:, 0] - RAMP[0][0]) / 1e-4)
    walls = np.array(c.walls)
    for i in range(len(walls)):
        within = walls[i:] - walls[i] <= CONTROL_PERIOD
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
