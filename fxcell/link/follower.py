"""The trajectory follower: which setpoint goes out in each controller cycle, and when to stop.

A pure state machine, shared by the link process (:mod:`fxcell.link.process`, which adds
the I/O: ur_rtde's ``servoJ``, the sockets, the clock) and the in-process fake robot
(:mod:`fxcell.testing.fake`). It never reads a clock, sleeps or starts a thread: the time
and the state samples are its arguments, so every rule below is testable cycle by cycle.
Plain Python floats only (the link process imports no numpy; this runs at 500 Hz).

One controller cycle is :meth:`Follower.cycle` (what to send now, or why it ended) and then
:meth:`Follower.advance` (how far the path moves for the next setpoint, once the next state
sample, or its timeout, is known):

- **Advance.** One sample of path per controller cycle, by the state samples' controller
  time. Cycles the controller ran on the previous setpoint (a late link, skipped or lost
  samples; a sample ``k`` cycles after the previous one) are owed, up to ``CATCH_UP``, and
  paid back only as fast as servoJ's response stays gentle: never a jump. The path never
  runs more than ``CATCH_UP`` samples ahead of the follower's own clock either (a burst of
  queued samples after a stall).
- **The limit check.** The follower models servoJ as the critically damped tracker the
  lag compensation assumes (:func:`servo_omega`), run on the setpoints it sends: a
  setpoint that would make servoJ accelerate beyond the braking acceleration (by
  ``LIMIT_TOLERANCE``) or exceed the speed limits is moved to the limit and recorded
  (:attr:`Follower.limited`, a warning for the client's log).
- **Braking.** The trajectory brakes to rest by itself when the client asks (:meth:`stop`,
  also when its socket closes), when the client has been silent for the guard's
  ``cell_timeout`` and when the state stream has been silent for ``stall_timeout``: the
  path's time rate falls from 1 to 0 as ``(1 + cos(πt/T))/2``, ``T`` from the braking
  acceleration and jerk, leaving room for the path's own acceleration
  (:func:`brake_duration`).
- **Stops in the state.** A safety stop or a stopped program in the newest state sample
  ends it at once (``failed``): the controller has stopped the arm.
- **Splicing.** :meth:`replace` swaps the samples not yet sent (optionally from a given
  index) at the next cycle; refused while braking.
- **End and hold.** After the last sample it holds that sample until the robot settles on
  it (or ``SETTLE_MAX`` plus twice the lookahead passed); :meth:`hold_target` then keeps
  servoing it for up to ``HOLD`` s so a next trajectory can take servo mode over.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

from fxcell.link.contract import Guard, StopReason, stop_reason
from fxcell.protocol import CONTROL_PERIOD, RobotState
from fxcell.settling import ARRIVE_TOLERANCE, SETTLE_VELOCITY

Samples = Sequence[tuple[float, ...]]
Status = Literal["completed", "stopped", "failed"]

CELL_SILENT = StopReason.CELL_SILENT
STATE_STALLED = StopReason.STATE_STALLED
SETTLED = StopReason.SETTLED


def brake_duration(velocity: Sequence[float], guard: Guard) -> float:
    """How long the path-preserving stop from ``velocity`` (rad/s per joint) takes.

    The path's time rate falls as ``(1 + cos(π t / T)) / 2``: a joint at speed v then
    decelerates at most at ``π v / (2 T)`` with jerk at most ``π² v / (2 T²)``, on top of
    what the path itself accelerates (at most ``guard.path_acceleration``, slowed by the
    rate's square); ``T`` is the shortest time that keeps every joint within the braking
    limits.
    """
    duration = 2 * CONTROL_PERIOD
    for v, a, own in zip(velocity, guard.brake_acceleration, guard.path_acceleration, strict=False):
        speed = abs(v)
        if speed > 0:
            room = max(a - own, 0.25 * a)
            duration = max(
                duration,
                math.pi * speed / (2 * room),
                math.pi * math.sqrt(speed / (2 * guard.brake_jerk)),
            )
    return duration


def servo_omega(lookahead: float, gain: float) -> float:
    """The natural frequency (1/s) of servoJ's tracker for ``lookahead`` and ``gain``.

    servoJ follows its setpoint like a critically damped second-order system with lag
    ``2/ω = lookahead·(300/gain)^¼`` (URCL issue #86; the motion layer's lag compensation
    and the simulator assume the same): each cycle its target joint velocity changes by
    ``(ω²(s − q) − 2ω q̇)·Δt`` for setpoint ``s``, target position ``q`` and velocity
    ``q̇``. A setpoint one cycle late therefore costs ``ω²·q̇·Δt`` of acceleration.
    """
    lookahead = min(max(lookahead, 0.03), 0.2)
    gain = min(max(gain, 100.0), 2000.0)
    return float(2.0 / (lookahead * (300.0 / gain) ** 0.25))


def path_at(samples: Samples, u: float) -> tuple[float, ...]:
    """The path at fractional sample index ``u`` (linear between samples)."""
    last = len(samples) - 1
    if u >= last:
        return samples[last]
    k = int(u)
    f = u - k
    if f == 0.0:
        return samples[k]
    a, b = samples[k], samples[k + 1]
    return tuple(x + (y - x) * f for x, y in zip(a, b, strict=True))


def path_velocity(samples: Samples, u: float) -> tuple[float, ...]:
    """The planned joint velocity at ``u`` (rad/s), from neighbouring samples."""
    last = len(samples) - 1
    if last < 1:
        return (0.0,) * 6
    k = min(int(u), last - 1)
    return tuple((y - x) / CONTROL_PERIOD for x, y in zip(samples[k], samples[k + 1], strict=True))


def settled(state: RobotState, target: Sequence[float]) -> bool:
    """Whether the robot rests on ``target`` (within the arrival tolerances)."""
    error = max(abs(a - b) for a, b in zip(state.actual_q, target, strict=True))
    return error < ARRIVE_TOLERANCE and max(map(abs, state.actual_qd)) < SETTLE_VELOCITY


@dataclass(frozen=True)
class Notice:
    """Something the follower tells the client (the link sends it; the fake reports it)."""

    kind: Literal["log", "replaced"]
    level: int = logging.INFO
    text: str = ""
    data: dict[str, object] = field(default_factory=dict)


@dataclass
class Cycle:
    """What one controller cycle does: send ``target``, or end with ``status``."""

    target: tuple[float, ...] | None = None
    progress: int | None = None
    """The sample index to report progress for (every ``PROGRESS_EVERY`` samples)."""
    answered: float | None = None
    """The controller time the setpoint answers (the newest sample's, plus paced cycles)."""
    status: Status | None = None
    reason: StopReason = StopReason.NONE


@dataclass
class LimitEvent:
    """A setpoint the limit check changed: it would have stepped beyond the limits."""

    timestamp: float | None
    """Controller time of the state sample the setpoint answered."""
    joint: int
    acceleration: float
    """The acceleration servoJ would have made of the setpoint (rad/s²)."""
    limit: float


class Follower:
    """Follows one (N, 6) joint trajectory at one setpoint per controller cycle."""

    PROGRESS_EVERY = 10  # samples (20 ms)
    CATCH_UP = 4
    """Most controller cycles the path may owe: a state sample ``k`` cycles after the
    previous one (the controller skipped cycles, or their samples were lost) owes up to
    ``min(k, CATCH_UP) - 1`` samples, paid back over the next setpoints so the path keeps
    the controller's time instead of stretching by the missed cycles. Longer gaps stretch
    it. It is also the most the path may run ahead of the follower's own clock (a burst of
    queued samples)."""
    CATCH_UP_SHARE = 0.5
    """The samples beyond one per cycle are caught up only as far as servoJ's response
    stays within this share of the braking acceleration: the controller held the previous
    setpoint for the missed cycles, and a jump by all of them would snap the velocity back
    (a step of ``ω²·q̇·Δt`` per cycle caught up)."""
    CATCH_UP_LEAST = 1 / 16
    """The smallest part of the owed cycles paid back in one cycle (samples)."""
    MAX_HELD = 50
    """Most controller cycles on one setpoint the follower's model of servoJ runs (a longer
    gap in the samples is a stall: it brakes)."""
    LIMIT_TOLERANCE = 1.05
    """The limit check changes a setpoint only beyond this factor of the limits."""
    LIMIT_REPORT_EVERY = 0.5  # s between two warnings about limited setpoints
    HOLD = 0.1  # s a completed trajectory keeps servo mode for a next one
    SETTLE_MAX = 0.3  # s, beyond twice the lookahead time, to settle on the last sample

    def __init__(
        self,
        samples: Samples,
        guard: Guard,
        lookahead: float,
        *,
        gain: float = 300.0,
        now: float,
        clock: float | None = None,
    ) -> None:
        """``now``: the follower's clock at the start; ``clock``: the newest state
        sample's controller time (None: none yet)."""
        self.samples = samples
        self.guard = guard
        self.lookahead = lookahead
        self.u = 0.0  # position along the path, in samples (fractional while braking)
        self.braking: tuple[StopReason, float, float] | None = None  # reason, started, duration
        self.notices: list[Notice] = []
        """Messages for the client since the caller last emptied the list."""
        self.limited: list[LimitEvent] = []
        """Every setpoint the limit check changed (a regression shows here and in the log)."""
        self._stop_reason: StopReason | None = None
        self._replacement: tuple[Samples, int | None] | None = None
        self._settle_until: float | None = None
        self._next_progress = 0
        self._rate = 1.0
        self._want = 0.0  # samples the next cycle advances, by the controller's clock
        self._owed = 0.0  # controller cycles the path is behind (late or skipped cycles)
        self._clock = clock
        self._paced = 0  # setpoints the timer sent since the last sample
        # samples of path the follower's clock allows now (one per cycle, at most CATCH_UP)
        self._budget, self._budget_at = float(self.CATCH_UP), now
        # servoJ's response, per joint: acceleration = w2 * (s - q) - w1 * qd
        omega = servo_omega(lookahead, gain)
        self._w2, self._w1 = omega * omega, 2.0 * omega
        self._accel = tuple(guard.brake_acceleration)
        self._speed = tuple(guard.velocity)
        self._reported_at: float | None = None
        self._unreported = 0
        self._cycle_events = 0
        # servoJ's target as this setpoint stream makes it, one control cycle per setpoint
        # (from servoJ's state at the first cycle): what the arm does when every setpoint
        # is on time. It is not corrected by later samples: a setpoint the controller got
        # a cycle late is the machine's doing, and judging the stream by such a sample
        # (one cycle off by ω²·q̇·Δt) would make the check fight the timing.
        self._model: tuple[list[float], list[float]] | None = None
        self._last_sent: tuple[float, ...] | None = None
        self._held = 0  # cycles the controller ran the last setpoint beyond its first

    # -- requests (between cycles)

    def stop(self, reason: StopReason) -> None:
        """Brake to rest along the path from the next cycle (the first reason stays)."""
        if self._stop_reason is None:
            self._stop_reason = reason

    @property
    def stop_requested(self) -> str | None:
        return self._stop_reason

    def replace(self, samples: Samples, at_index: int | None = None) -> None:
        """Replace the samples not yet sent, at the next cycle; with ``at_index``,
        ``samples[0]`` takes the place of sample ``at_index`` (the ones before it are
        still sent), so a braking profile starts exactly where it was computed from."""
        self._replacement = (samples, at_index)

    # -- one cycle

    def abort_reason(
        self, now: float, heard_at: float | None, state_at: float
    ) -> StopReason | None:
        """Why the trajectory must brake now by itself (``None``: it may go on)."""
        if self._stop_reason is not None:
            return self._stop_reason
        guard = self.guard
        timeout = guard.cell_timeout
        if timeout is not None and heard_at is not None and now - heard_at > timeout:
            return CELL_SILENT
        if now - state_at > guard.stall_timeout:
            return STATE_STALLED
        return None

    def cycle(
        self,
        now: float,
        state: RobotState | None,
        *,
        heard_at: float | None = None,
        state_at: float,
    ) -> Cycle:
        """This cycle's setpoint, or the end: ``now`` is the follower's clock, ``state``
        the newest state sample, ``heard_at`` when the client was last heard (None: not
        watched), ``state_at`` when the newest state sample arrived."""
        if self._model is None and state is not None:
            self._model = (list(state.target_q), list(state.target_qd))
        model = self._model
        if model is not None and self._held and self._last_sent is not None:
            self._hold_model(model, self._last_sent, self._held)
        self._held = 0
        self._move(model)
        if self.braking is None:
            why = self.abort_reason(now, heard_at, state_at)
            if why is not None:
                self._start_braking(why, now, heard_at)
        replacement, self._replacement = self._replacement, None
        if replacement is not None:
            self._splice(*replacement)
        samples, u = self.samples, self.u
        self._rate = 1.0
        if self.braking is not None:
            reason, began, duration = self.braking
            elapsed = now - began
            if elapsed >= duration:
                return Cycle(status="stopped", reason=reason)
            self._rate = 0.5 * (1.0 + math.cos(math.pi * elapsed / duration))
        elif u >= len(samples):
            # hold the last sample until the robot settles on it (servoJ lags by about the
            # lookahead time), then end
            if self._settle_until is None:
                self._settle_until = now + self.SETTLE_MAX + 2 * self.lookahead
            if now > self._settle_until or (state is not None and settled(state, samples[-1])):
                return Cycle(status="completed")
        if state is not None:
            why = stop_reason(state.safety_mode, state.runtime_state)
            if why is not None:
                return Cycle(status="failed", reason=why)
        target = path_at(samples, u)
        if model is not None:
            target = self._check(target, model, now, state)
        self._last_sent = target
        out = Cycle(target=target)
        if u < len(samples):
            i = int(u)
            if self.braking is None and i >= self._next_progress:
                out.progress = i
                out.answered = (
                    None if self._clock is None else self._clock + self._paced * CONTROL_PERIOD
                )
                self._next_progress = (i // self.PROGRESS_EVERY + 1) * self.PROGRESS_EVERY
        return out

    def _start_braking(self, why: StopReason, now: float, heard_at: float | None) -> None:
        samples, u = self.samples, self.u
        velocity = path_velocity(samples, u) if u < len(samples) else (0.0,) * 6
        if max(map(abs, velocity)) > 0:  # not a stop at the target
            duration = brake_duration(velocity, self.guard)
            said = why.value
            if why == CELL_SILENT and heard_at is not None:
                said += f" for {now - heard_at:.3f} s"
            # settled: the cell saw the robot at the target, stopped and past the plan by
            # its clock, a few samples of the slow tail before this stream: a normal end
            level = logging.DEBUG if why == SETTLED else logging.WARNING
            self.notices.append(Notice("log", level, f"braking to rest: {said}"))
        else:  # holding the target: nothing to brake
            duration = 0.0
        self.braking = (why, now, duration)

    def _splice(self, new: Samples, at: int | None) -> None:
        if self.braking is not None:  # already braking by itself: keep that
            self.notices.append(Notice("replaced", data={"ok": False}))
            return
        samples, u = self.samples, self.u
        i = int(u)
        late = at is not None and at < i
        if at is None:
            samples, u = new, 0.0
        elif not late:
            samples, u = list(samples[i:at]) + list(new), 0.0
        else:  # already past it: join the new samples where we are
            samples, u = new, float(min(i - at, len(new) - 1))
        self.samples, self.u = samples, u
        self._settle_until = None
        self.notices.append(Notice("replaced", data={"ok": True, "late": late}))

    def advance(self, now: float, timestamp: float | None, *, poked: bool = False) -> None:
        """Count the controller cycles the next setpoint answers: ``timestamp`` is the
        controller time of a new state sample (None: none came within the timeout, the
        timer paces the stream), ``poked`` that a stop request woke the caller instead
        (brake from here). The path moves at the next :meth:`cycle`, which sees the
        state servoJ is in."""
        if poked and timestamp is None:
            steps = 0
        elif timestamp is None:  # no sample for 3 ms: the timer
            steps = 1
            self._paced += 1
        elif self._clock is not None and timestamp > self._clock:
            # the controller cycles since the last sample, less those the timer paced
            cycles = round((timestamp - self._clock) / CONTROL_PERIOD)
            steps = max(min(cycles, self.CATCH_UP) - self._paced, 0)
            # the controller ran the last setpoint for the cycles beyond the first
            self._held = min(max(cycles - self._paced - 1, 0), self.MAX_HELD)
            self._clock, self._paced = timestamp, 0
        else:  # no earlier time to count from (or the clock went back)
            steps = 1
            self._clock, self._paced = timestamp, 0
        # never faster than the follower's clock (a burst of queued samples): the path may
        # run at most CATCH_UP samples ahead of it, then waits
        self._budget = min(self._budget + (now - self._budget_at) / CONTROL_PERIOD, self.CATCH_UP)
        self._budget_at = now
        if steps > self._budget:
            steps = max(int(self._budget), 0)
        self._budget -= steps
        self._want += steps

    def _move(self, model: tuple[list[float], list[float]] | None) -> None:
        """Move along the path by the cycles counted since the last setpoint: the first at
        the path's rate; the ones the controller ran without a fresh setpoint (a late or
        skipped cycle) are owed, and paid back as fast as servoJ's response stays gentle
        (see ``CATCH_UP_SHARE``): at once after a short gap at low speed, else in parts
        over the next cycles. Never a jump."""
        want, self._want = self._want, 0.0
        end = float(len(self.samples))
        if self.u >= end:
            self._owed = 0.0
            return
        if want <= 0 and self._owed <= 0:
            return
        rate = self._rate
        first = min(want, 1.0)
        self._owed = min(self._owed + want - first, float(self.CATCH_UP))
        extra = 0.0
        if self._owed > 0 and model is not None and self.braking is None:
            # the whole debt if that is gentle, else the largest half, quarter... of it
            part = self._owed
            while part >= self.CATCH_UP_LEAST:
                if self._gentle(path_at(self.samples, min(self.u + first + part, end)), model):
                    extra = part
                    break
                part /= 2
        self._owed -= extra
        self.u = min(self.u + rate * (first + extra), end)

    def _hold_model(
        self, model: tuple[list[float], list[float]], setpoint: tuple[float, ...], cycles: int
    ) -> None:
        """Run the model of servoJ ``cycles`` control cycles on ``setpoint``."""
        w2, w1, dt = self._w2, self._w1, CONTROL_PERIOD
        x, v = model
        for _ in range(cycles):
            for j, s in enumerate(setpoint):
                v[j] += (w2 * (s - x[j]) - w1 * v[j]) * dt
                x[j] += v[j] * dt

    def _gentle(self, target: tuple[float, ...], model: tuple[list[float], list[float]]) -> bool:
        """Whether servoJ's response to ``target`` stays within CATCH_UP_SHARE of the
        braking acceleration, and within the speed limit, on every joint."""
        w2, w1, share, dt = self._w2, self._w1, self.CATCH_UP_SHARE, CONTROL_PERIOD
        for s, q, qd, limit, vmax in zip(
            target, model[0], model[1], self._accel, self._speed, strict=True
        ):
            a = w2 * (s - q) - w1 * qd
            if abs(a) > share * limit or abs(qd + a * dt) > vmax:
                return False
        return True

    def _check(
        self,
        target: tuple[float, ...],
        model: tuple[list[float], list[float]],
        now: float,
        state: RobotState | None,
    ) -> tuple[float, ...]:
        """The limit check on the setpoint stream: the acceleration servoJ makes of
        ``target`` in the next cycle (``model``: its state after the setpoints so far),
        per joint, against the braking acceleration and the speed limit. A setpoint
        beyond them (by LIMIT_TOLERANCE) is moved to the limit and recorded
        (:attr:`limited`, and a warning to the client); ``model`` moves on one cycle."""
        w2, w1, dt = self._w2, self._w1, CONTROL_PERIOD
        tolerance = self.LIMIT_TOLERANCE
        changed: list[float] | None = None
        self._cycle_events = 0
        x, v = model
        for j, (s, q, qd, amax, vmax) in enumerate(
            zip(target, x, v, self._accel, self._speed, strict=True)
        ):
            a = w2 * (s - q) - w1 * qd
            bound: float | None = None
            if a > amax * tolerance:
                bound = amax
            elif a < -amax * tolerance:
                bound = -amax
            speed = qd + (a if bound is None else bound) * dt
            if speed > vmax * tolerance:
                bound = (vmax - qd) / dt
            elif speed < -vmax * tolerance:
                bound = (-vmax - qd) / dt
            if bound is None:
                v[j] = qd = qd + a * dt  # servoJ's cycle on this setpoint
                x[j] = q + qd * dt
                continue
            v[j] = qd + bound * dt
            x[j] = q + v[j] * dt
            if changed is None:
                changed = list(target)
            changed[j] = q + (bound + w1 * qd) / w2
            stamp = state.timestamp if state is not None else None
            self.limited.append(LimitEvent(stamp, j, a, amax))
            self._unreported += 1
            self._cycle_events += 1
        if changed is None:
            return target
        if self._reported_at is None or now - self._reported_at >= self.LIMIT_REPORT_EVERY:
            now_limited = self.limited[-self._cycle_events :]
            event = max(now_limited, key=lambda e: abs(e.acceleration) / e.limit)
            self.notices.append(
                Notice(
                    "log",
                    logging.WARNING,
                    f"setpoint limited ({self._unreported} since the last report): joint "
                    f"{event.joint + 1} would accelerate at {event.acceleration:+.1f} rad/s² "
                    f"(limit {event.limit:g}) at controller time {event.timestamp} s",
                )
            )
            self._reported_at, self._unreported = now, 0
        return tuple(changed)

    # -- after the end

    @property
    def index(self) -> int:
        return int(self.u)

    @property
    def at_target(self) -> bool:
        """Whether the path has been followed to its last sample."""
        return self.u >= len(self.samples)

    def hold_target(self, state: RobotState | None) -> tuple[float, ...] | None:
        """The setpoint of one cycle of the hold after an end at the target (None: the
        hold ends, leave servo mode: a stop was requested or the state shows a stop)."""
        if self._stop_reason is not None:
            return None
        if state is not None and stop_reason(state.safety_mode, state.runtime_state):
            return None
        return self.samples[-1]

    def begin_hold(self) -> None:
        """The hold starts: the settled stop that ended the trajectory does not end it."""
        if self._stop_reason == SETTLED:
            self._stop_reason = None
