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
  time: a sample ``k`` cycles after the previous one advances the path by up to
  ``CATCH_UP`` samples, and never more than the follower's own clock allows (a burst of
  queued samples after a stall is not a jump).
- **Braking.** The trajectory brakes to rest by itself when the client asks (:meth:`stop`,
  also when its socket closes), when the client has been silent for the guard's
  ``cell_timeout`` and when the state stream has been silent for ``stall_timeout``: the
  path's time rate falls from 1 to 0 as ``(1 + cos(πt/T))/2``, ``T`` from the braking
  acceleration and jerk (:func:`brake_duration`).
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

from fxcell.link.wire import SETTLED
from fxcell.protocol import CONTROL_PERIOD, SAFETY_STOPS, RobotState, RuntimeState
from fxcell.settling import ARRIVE_TOLERANCE, SETTLE_VELOCITY

Samples = Sequence[tuple[float, ...]]
Status = Literal["completed", "stopped", "failed"]

CELL_SILENT = "cell_silent"
STATE_STALLED = "state_stalled"


@dataclass(frozen=True)
class Guard:
    """When and how a trajectory brakes by itself (sent with each trajectory)."""

    brake_acceleration: tuple[float, ...] = (4.0, 4.0, 4.0, 8.0, 8.0, 8.0)
    """Per-joint deceleration limit of a self-initiated stop (rad/s²)."""
    brake_jerk: float = 40.0
    """Jerk limit of a self-initiated stop (rad/s³)."""
    cell_timeout: float | None = 0.1
    """Brake when the client has sent nothing for this long (s; None: never)."""
    stall_timeout: float = 0.08
    """Brake when no state sample has arrived for this long (s)."""


def stop_reason(safety_mode: int, runtime_state: int) -> str | None:
    """Why a trajectory cannot continue, from one state sample (``None``: it can)."""
    stop = SAFETY_STOPS.get(safety_mode)
    if stop is not None:
        return stop
    if runtime_state != RuntimeState.PLAYING:
        return "program_stopped"
    return None


def brake_duration(velocity: Sequence[float], guard: Guard) -> float:
    """How long the path-preserving stop from ``velocity`` (rad/s per joint) takes.

    The path's time rate falls as ``(1 + cos(π t / T)) / 2``: a joint at speed v then
    decelerates at most at ``π v / (2 T)`` with jerk at most ``π² v / (2 T²)``; ``T`` is
    the shortest time that keeps every joint within the braking limits.
    """
    duration = 2 * CONTROL_PERIOD
    for v, a in zip(velocity, guard.brake_acceleration, strict=False):
        speed = abs(v)
        if speed > 0:
            duration = max(
                duration,
                math.pi * speed / (2 * a),
                math.pi * math.sqrt(speed / (2 * guard.brake_jerk)),
            )
    return duration


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
    reason: str = ""


class Follower:
    """Follows one (N, 6) joint trajectory at one setpoint per controller cycle."""

    PROGRESS_EVERY = 10  # samples (20 ms)
    CATCH_UP = 4
    """Most samples one setpoint advances: a state sample ``k`` controller cycles after the
    previous one (the controller skipped cycles, or their samples were lost) advances the
    path by ``min(k, CATCH_UP)`` samples, so the path keeps the controller's time instead
    of stretching by the missed cycles. Longer gaps stretch it. It is also the most the
    path may run ahead of the follower's own clock (a burst of queued samples)."""
    HOLD = 0.1  # s a completed trajectory keeps servo mode for a next one
    SETTLE_MAX = 0.3  # s, beyond twice the lookahead time, to settle on the last sample

    def __init__(
        self,
        samples: Samples,
        guard: Guard,
        lookahead: float,
        *,
        now: float,
        clock: float | None = None,
    ) -> None:
        """``now``: the follower's clock at the start; ``clock``: the newest state
        sample's controller time (None: none yet)."""
        self.samples = samples
        self.guard = guard
        self.lookahead = lookahead
        self.u = 0.0  # position along the path, in samples (fractional while braking)
        self.braking: tuple[str, float, float] | None = None  # reason, started, duration
        self.notices: list[Notice] = []
        """Messages for the client since the caller last emptied the list."""
        self._stop_reason: str | None = None
        self._replacement: tuple[Samples, int | None] | None = None
        self._settle_until: float | None = None
        self._next_progress = 0
        self._rate = 1.0
        self._clock = clock
        self._paced = 0  # setpoints the timer sent since the last sample
        # samples of path the follower's clock allows now (one per cycle, at most CATCH_UP)
        self._budget, self._budget_at = float(self.CATCH_UP), now

    # -- requests (between cycles)

    def stop(self, reason: str) -> None:
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

    def abort_reason(self, now: float, heard_at: float | None, state_at: float) -> str | None:
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
        samples = self.samples
        if self.braking is None:
            why = self.abort_reason(now, heard_at, state_at)
            if why is not None:
                self._start_braking(why, now, heard_at)
        replacement, self._replacement = self._replacement, None
        if replacement is not None:
            self._splice(*replacement)
            samples = self.samples
        u = self.u
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
        out = Cycle(target=path_at(samples, u))
        if u < len(samples):
            i = int(u)
            if self.braking is None and i >= self._next_progress:
                out.progress = i
                out.answered = (
                    None if self._clock is None else self._clock + self._paced * CONTROL_PERIOD
                )
                self._next_progress = (i // self.PROGRESS_EVERY + 1) * self.PROGRESS_EVERY
        return out

    def _start_braking(self, why: str, now: float, heard_at: float | None) -> None:
        samples, u = self.samples, self.u
        velocity = path_velocity(samples, u) if u < len(samples) else (0.0,) * 6
        if max(map(abs, velocity)) > 0:  # not a stop at the target
            duration = brake_duration(velocity, self.guard)
            said = why
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
        """Move along the path for the next setpoint: ``timestamp`` is the controller time
        of a new state sample (None: none came within the timeout, the timer paces the
        stream), ``poked`` that a stop request woke the caller instead (brake from here)."""
        if poked and timestamp is None:
            steps = 0
        elif timestamp is None:  # no sample for 3 ms: the timer
            steps = 1
            self._paced += 1
        elif self._clock is not None and timestamp > self._clock:
            # the controller cycles since the last sample, less those the timer paced
            cycles = round((timestamp - self._clock) / CONTROL_PERIOD)
            steps = max(min(cycles, self.CATCH_UP) - self._paced, 0)
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
        if self.u < len(self.samples):
            self.u = min(self.u + self._rate * steps, float(len(self.samples)))

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
