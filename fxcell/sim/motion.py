"""The simulated UR3e arm: joint state and the motion generators the controller runs.

The arm advances once per 2 ms control cycle. The commanded and the actual joint
state are the same (a perfectly tracking drive); what differs between commands is how
the joint state evolves:

- :class:`JointMove` (movej): a trapezoidal velocity profile along the straight line
  in joint space; ``v``/``a`` bind the leading joint, every joint within its own limit.
- :class:`LinearMove` (movel): the tool moves on a straight line (orientation
  interpolated on the geodesic) with a trapezoidal profile; joints from IK each cycle.
- :class:`ServoTrack` (servoj): a critically damped second-order tracker of the latest
  setpoint. At constant setpoint velocity it lags by about the lookahead time
  (``lag ≈ lookahead_time · (300/gain)^¼``, like the ~34 ms a UR shows for 30 ms); at
  rest it converges to the last setpoint exactly.
- :class:`SpeedTrack` (speedj/speedl): velocity ramps to the target at ``a``.
- :class:`Stop` (stopj/stopl, program stop, safety stop): synchronous deceleration.

A command that would exceed a joint speed limit by far (more than
``VIOLATION_FACTOR`` times the limit) or leave the ±2π range is a safety violation:
:meth:`Arm.step` reports it and the controller makes a protective stop. So does a link
entering the table (see :class:`TableGuard`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from fxcell.geometry import Pose, matrix_to_rotvec, rotvec_to_matrix

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from fxcell.motion.kinematics import Kinematics

    FloatArray = NDArray[np.float64]
else:
    FloatArray = np.ndarray

Joints = Sequence[float] | FloatArray

# UR3e maxima: 180°/s base, shoulder, elbow; 360°/s wrists.
JOINT_SPEED_LIMIT = np.array([math.pi] * 3 + [2 * math.pi] * 3)
JOINT_POSITION_LIMIT = 2 * math.pi
VIOLATION_FACTOR = 1.5
SAFETY_DECELERATION = 20.0  # rad/s², protective and emergency stops
PROGRAM_STOP_DECELERATION = 8.0  # rad/s², program stop / pause
LINK_REACH = 0.8  # m: farther than any point of the arm (and tool) from any joint axis
ZERO6 = np.zeros(6)
ZERO6.flags.writeable = False
SERVO_MIN_INTERVAL = 0.008  # s: the shortest span a servoj step is judged over
SETTLE_POSITION = 1e-8  # rad: servo tracking snaps onto the setpoint below this ...
SETTLE_VELOCITY = 1e-6  # rad/s: ... and this


class MotionError(Exception):
    """A motion cannot continue (IK failure, singularity); the program stops."""


class SafetyLimitError(Exception):
    """A command or a position violates the safety limits: protective stop."""


@dataclass
class MotionToken:
    """What the control script waits on: completion, failure and progress of one command."""

    done: bool = False
    failed: str | None = None
    progress: Callable[[int], None] | None = None
    on_finish: list[Callable[[MotionToken], None]] = field(default_factory=list)

    def finish(self, failed: str | None = None) -> None:
        if self.done:
            return
        self.done = True
        self.failed = failed
        for callback in self.on_finish:
            callback(self)


class Motion:
    """A motion generator: moves the arm each cycle until finished."""

    def __init__(self, token: MotionToken | None = None) -> None:
        self.token = token or MotionToken()

    def step(self, arm: Arm, dt: float) -> bool:
        """Advance one cycle; True when finished."""
        raise NotImplementedError

    def restart(self, arm: Arm) -> Motion | None:
        """A generator continuing this one from the arm's current (resting) state."""
        return None


def _trapezoid(distance: float, v: float, a: float) -> tuple[float, float, float]:
    """(accel time, cruise time, peak speed) of a rest-to-rest trapezoid over ``distance``."""
    if distance <= 0:
        return 0.0, 0.0, 0.0
    ta = v / a
    if a * ta * ta >= distance:  # triangle
        ta = math.sqrt(distance / a)
        return ta, 0.0, a * ta
    return ta, (distance - a * ta * ta) / v, v


def _profile(t: float, ta: float, tc: float, vp: float, a: float) -> tuple[float, float, float]:
    """Position, velocity, acceleration of the trapezoid at time ``t``."""
    if t <= 0:
        return 0.0, 0.0, a if ta > 0 else 0.0
    if t < ta:
        return 0.5 * a * t * t, a * t, a
    s1 = 0.5 * a * ta * ta
    if t < ta + tc:
        return s1 + vp * (t - ta), vp, 0.0
    td = t - ta - tc
    if td < ta:
        return s1 + vp * tc + vp * td - 0.5 * a * td * td, vp - a * td, -a
    return 2 * s1 + vp * tc, 0.0, 0.0


class JointMove(Motion):
    """movej: a synchronised trapezoid in joint space from rest to rest."""

    def __init__(
        self,
        arm: Arm,
        target: Joints,
        v: float,
        a: float,
        token: MotionToken | None = None,
    ) -> None:
        super().__init__(token)
        self.start = arm.q.copy()
        self.target = np.asarray(target, dtype=float)
        self.v, self.a = v, a
        self.delta = self.target - self.start
        d = np.abs(self.delta)
        moving = d > 1e-12
        if not moving.any() or v <= 0 or a <= 0:
            self.ta = self.tc = self.vp = self.acc = 0.0
            self.duration = 0.0
        else:
            # Normalised path s in [0, 1]: joint i moves delta_i * s.
            vs = min(float(np.min(np.minimum(v, arm.speed_limit)[moving] / d[moving])), 1e9)
            self.acc = float(a / d[moving].max())
            self.ta, self.tc, self.vp = _trapezoid(1.0, vs, self.acc)
            self.duration = 2 * self.ta + self.tc
        self.t = 0.0

    def step(self, arm: Arm, dt: float) -> bool:
        self.t += dt
        if self.t >= self.duration:
            arm.set_state(self.target, None, None)
            return True
        s, sd, sdd = _profile(self.t, self.ta, self.tc, self.vp, self.acc)
        arm.set_state(self.start + self.delta * s, self.delta * sd, self.delta * sdd)
        return False

    def restart(self, arm: Arm) -> Motion:
        return JointMove(arm, self.target, self.v, self.a, self.token)


class LinearMove(Motion):
    """movel: straight tool path with a trapezoidal profile, joints from IK each cycle."""

    def __init__(
        self,
        arm: Arm,
        target: Pose,
        v: float,
        a: float,
        token: MotionToken | None = None,
        final_q: Joints | None = None,
    ) -> None:
        super().__init__(token)
        kin = arm.kinematics
        self.start_q = arm.q.copy()
        self.start = kin.forward(self.start_q)
        self.target = target
        self.final_q = None if final_q is None else np.asarray(final_q, dtype=float)
        self.v, self.a = v, a
        self.dp = target.position - self.start.position
        self.rel = self.start.rotation.T @ target.rotation
        self.axis_angle = np.asarray(matrix_to_rotvec(self.rel), dtype=float)
        length = max(float(np.linalg.norm(self.dp)), float(np.linalg.norm(self.axis_angle)))
        if length < 1e-12 or v <= 0 or a <= 0:
            self.ta = self.tc = self.vp = self.acc = 0.0
            self.duration = 0.0
        else:
            self.acc = a / length
            self.ta, self.tc, self.vp = _trapezoid(1.0, v / length, self.acc)
            self.duration = 2 * self.ta + self.tc
        self.t = 0.0

    def _pose(self, s: float) -> Pose:
        R = self.start.rotation @ rotvec_to_matrix(self.axis_angle * s)
        return Pose(self.start.position + self.dp * s, R)

    def step(self, arm: Arm, dt: float) -> bool:
        self.t += dt
        finished = self.t >= self.duration
        s = 1.0 if finished else _profile(self.t, self.ta, self.tc, self.vp, self.acc)[0]
        if finished and self.final_q is not None:
            q = self.final_q
        else:
            try:
                q = arm.kinematics.inverse(self._pose(s), arm.q)
            except Exception as exc:  # UnreachableError and numerical failures
                raise MotionError(f"movel: inverse kinematics failed ({exc})") from None
            q = np.asarray(q, dtype=float)
        step = np.abs(q - arm.q)
        if np.any(step > arm.speed_limit * dt * VIOLATION_FACTOR):
            joint = int(np.argmax(step / arm.speed_limit))
            raise SafetyLimitError(
                f"movel: joint {joint} speed limit exceeded (singularity on the path)"
            )
        qd = (q - arm.q) / dt
        arm.set_state(q, None if finished else qd, None if finished else (qd - arm.qd) / dt)
        return finished

    def restart(self, arm: Arm) -> Motion:
        return LinearMove(arm, self.target, self.v, self.a, self.token, self.final_q)


class Stop(Motion):
    """Decelerate every joint to rest, synchronised so the path direction is kept."""

    def __init__(self, arm: Arm, deceleration: float, token: MotionToken | None = None) -> None:
        super().__init__(token)
        speed = float(np.max(np.abs(arm.qd)))
        deceleration = max(deceleration, 1e-3)
        self.remaining = speed / deceleration
        self.decel = arm.qd / self.remaining if self.remaining > 0 else np.zeros(6)

    def step(self, arm: Arm, dt: float) -> bool:
        if self.remaining <= dt:
            q = arm.q + arm.qd * self.remaining * 0.5
            arm.set_state(q, None, None)
            return True
        self.remaining -= dt
        qd = arm.qd - self.decel * dt
        arm.set_state(arm.q + 0.5 * (arm.qd + qd) * dt, qd, -self.decel)
        return False


class ServoTrack(Motion):
    """servoj: critically damped tracking of the latest setpoint (never finishes by itself)."""

    def __init__(self, arm: Arm) -> None:
        super().__init__()
        self._setpoint: list[float] = arm.q.tolist()
        self.omega = 20.0
        self._omega_of: tuple[float, float] | None = None  # (lookahead, gain) of omega
        self.last_command = -1.0

    @property
    def setpoint(self) -> FloatArray:
        """The latest setpoint (kept as plain floats: an array only when asked for)."""
        return np.array(self._setpoint)

    def command(
        self,
        arm: Arm,
        setpoint: Sequence[float],
        servo_time: float,
        lookahead: float,
        gain: float,
        now: float,
        packets: int = 1,
    ) -> None:
        """Take a new setpoint; a step far beyond the joint speed is a violation.

        ``now`` is wall-clock time: after a late cycle the controller catches up on the
        missed steps at once, but the setpoints still came in over the real interval.
        ``packets``: the client's packets that arrived since the last setpoint taken (the
        cycle reads only the newest). A backlog of packets drained at once (a receiver
        that was late) spans as many of the client's cycles, however short the interval.
        """
        sp = [float(v) for v in setpoint]
        if not all(map(math.isfinite, sp)):
            raise SafetyLimitError("servoj: setpoint is not finite")
        interval = servo_time if self.last_command < 0 else max(now - self.last_command, 0.0)
        # Setpoints from a non-real-time client arrive bunched: judge a step over at least
        # a few cycles, so only a jump far beyond the joint speed is a violation.
        span = max(interval, servo_time * max(packets, 1), SERVO_MIN_INTERVAL)
        allowed = span * VIOLATION_FACTOR
        previous = self._setpoint
        for joint, (new, old, limit) in enumerate(zip(sp, previous, arm.speed_limits, strict=True)):
            if abs(new - old) > limit * allowed:
                speed = abs(new - old) / (allowed / VIOLATION_FACTOR)
                raise SafetyLimitError(
                    f"servoj: joint {joint} commanded at {speed:.2f} rad/s, limit {limit:.2f} rad/s"
                )
            if abs(new) > JOINT_POSITION_LIMIT + 1e-9:
                raise SafetyLimitError(f"servoj: joint {joint} position {new:.3f} out of ±2π")
        self._setpoint = sp
        self.last_command = now
        if (lookahead, gain) != self._omega_of:  # a client keeps them from call to call
            self._omega_of = (lookahead, gain)
            lookahead = min(max(lookahead, 0.03), 0.2)
            gain = min(max(gain, 100.0), 2000.0)
            self.omega = 2.0 / lookahead * (gain / 300.0) ** 0.25

    def step(self, arm: Arm, dt: float) -> bool:
        # plain floats: for 6 joints this is cheaper than numpy's per-call overhead
        q, qd, _ = arm.lists()
        kp = self.omega * self.omega * dt
        kd = 2.0 * self.omega * dt
        settled = True
        new_q, new_qd, new_qdd = [], [], []
        for s, x, v, limit in zip(self._setpoint, q, qd, arm.speed_limits, strict=True):
            e = s - x
            if settled and (abs(e) >= SETTLE_POSITION or abs(v) >= SETTLE_VELOCITY):
                settled = False
            nv = v + kp * e - kd * v
            nv = limit if nv > limit else -limit if nv < -limit else nv
            new_q.append(x + nv * dt)
            new_qd.append(nv)
            new_qdd.append((nv - v) / dt)
        if settled:
            if arm.qd is not ZERO6 or q != self._setpoint:
                arm.set_state(self._setpoint, None, None)  # converged: exactly on the setpoint
            return False
        arm.set_state(  # q: made an array there
            new_q, np.array(new_qd), np.array(new_qdd), lists=(new_q, new_qd, new_qdd)
        )
        return False

    def restart(self, arm: Arm) -> Motion:
        return self


class SpeedTrack(Motion):
    """speedj / speedl: ramp the joint (or tool) velocity to the target at ``a``."""

    def __init__(self, arm: Arm) -> None:
        super().__init__()
        self.target: FloatArray = np.zeros(6)
        self.acceleration = 1.0
        self.tool: FloatArray | None = None  # tool-space velocity for speedl

    def command_joint(self, arm: Arm, qd: Sequence[float], acceleration: float) -> None:
        target = np.asarray(qd, dtype=float)
        if not np.all(np.isfinite(target)):
            raise SafetyLimitError("speedj: velocity is not finite")
        if np.any(np.abs(target) > arm.speed_limit * VIOLATION_FACTOR):
            joint = int(np.argmax(np.abs(target) / arm.speed_limit))
            raise SafetyLimitError(f"speedj: joint {joint} speed limit exceeded")
        self.target = np.clip(target, -arm.speed_limit, arm.speed_limit)
        self.tool = None
        self.acceleration = max(acceleration, 1e-3)

    def command_tool(self, arm: Arm, xd: Sequence[float], acceleration: float) -> None:
        self.tool = np.asarray(xd, dtype=float)
        self.acceleration = max(acceleration, 1e-3)

    def step(self, arm: Arm, dt: float) -> bool:
        if self.tool is not None:
            J = arm.kinematics.jacobian(arm.q)
            try:
                target = np.asarray(np.linalg.solve(J, self.tool), dtype=np.float64)
            except np.linalg.LinAlgError:
                raise SafetyLimitError("speedl: singular configuration") from None
            if np.any(np.abs(target) > arm.speed_limit * VIOLATION_FACTOR):
                raise SafetyLimitError("speedl: joint speed limit exceeded (near a singularity)")
            self.target = target
        diff = self.target - arm.qd
        step = self.acceleration * dt
        qd = np.where(np.abs(diff) <= step, self.target, arm.qd + np.sign(diff) * step)
        arm.set_state(arm.q + 0.5 * (arm.qd + qd) * dt, qd, (qd - arm.qd) / dt)
        return False

    def restart(self, arm: Arm) -> Motion:
        return self


class MotionSequence(Motion):
    """Run generators made lazily one after another (each starts from the state it finds)."""

    def __init__(
        self,
        factories: list[Callable[[Arm, MotionToken], Motion]],
        token: MotionToken | None = None,
        on_segment: Callable[[int], None] | None = None,
    ) -> None:
        super().__init__(token)
        self.factories = factories
        self.index = -1
        self.current: Motion | None = None
        self.on_segment = on_segment

    def step(self, arm: Arm, dt: float) -> bool:
        while True:
            if self.current is None:
                self.index += 1
                if self.index >= len(self.factories):
                    return True
                if self.on_segment is not None:
                    self.on_segment(self.index)
                self.current = self.factories[self.index](arm, self.token)
            if self.current.step(arm, dt):
                self.current = None
                if self.index + 1 >= len(self.factories):
                    return True
            return False

    def restart(self, arm: Arm) -> Motion:
        rest = self.factories[max(self.index, 0) :]
        return MotionSequence(rest, self.token, self.on_segment)


class TableGuard:
    """Points along the links (from :meth:`Kinematics.joint_frames`) against the table box.

    The base stands on the table top (z = 0), so only points from the upper arm on are
    checked; the test box is the table grown by ``margin`` upward.
    """

    def __init__(
        self,
        centre: Sequence[float],
        size: Sequence[float],
        margin: float = 0.0,
        samples: int = 4,
    ) -> None:
        c = np.asarray(centre, dtype=float)
        h = np.asarray(size, dtype=float) / 2
        self.low = c - h
        self.high = c + h
        self.high[2] += margin
        self.samples = samples

    def check(self, frames: Sequence[FloatArray]) -> tuple[str | None, float]:
        """(link in the table or None, a lower bound of the clearance to the table box)."""
        # frames: base, after joint 1..6, tcp; the base column (base to shoulder) is skipped.
        origins = np.array([f[:3, 3] for f in frames[1:]])
        lowest = float(origins[:, 2].min())
        if lowest > self.high[2]:
            return None, lowest - self.high[2]  # every link point is above the table top
        a, b = origins[:-1], origins[1:]
        t = np.linspace(0.0, 1.0, self.samples + 1)[:, None, None]
        points = a + (b - a) * t  # (samples + 1, links, 3)
        inside = np.all((points >= self.low) & (points <= self.high), axis=2).any(axis=0)
        if not inside.any():
            return None, 0.0
        return LINK_NAMES[int(np.argmax(inside))], 0.0


# Programmed moves follow the speed slider as on the real robot (servo/speed tracking and
# stops run in real time).
_SCALED = (JointMove, LinearMove, MotionSequence)

LINK_NAMES = ("upper arm", "forearm", "wrist 1", "wrist 2", "wrist 3", "tool")


class Arm:
    """Joint state of the UR3e and the motion generator moving it."""

    def __init__(
        self,
        kinematics: Kinematics,
        q: Sequence[float] = (0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0),
        *,
        table: TableGuard | None = None,
        make_kinematics: Callable[[Any], Kinematics] | None = None,
    ) -> None:
        self.kinematics = kinematics
        self.make_kinematics = make_kinematics
        self.q = np.asarray(q, dtype=float).copy()
        self.qd: FloatArray = ZERO6
        self.qdd: FloatArray = ZERO6
        self.speed_limit = JOINT_SPEED_LIMIT.copy()
        self.speed_limits = tuple(self.speed_limit.tolist())
        self.generator: Motion | None = None
        self.suspended: Motion | None = None
        self.table = table
        self.version = 0  # bumped whenever q changes: lets the state cache FK
        self.speed_fraction = 1.0  # the speed slider: scales time along programmed moves
        self._guard_budget = 0.0  # m a link point may still travel before the next table check
        self._lists: tuple[Any, ...] = ()  # (q, qd, qdd, and the three as lists): see lists()

    @property
    def active(self) -> bool:
        """A motion generator runs or the joints still move."""
        return self.generator is not None or self.qd is not ZERO6

    @property
    def moving(self) -> bool:
        return self.qd is not ZERO6 and bool(self.qd.any())

    def set_state(
        self,
        q: FloatArray | Sequence[float],
        qd: FloatArray | None,
        qdd: FloatArray | None,
        *,
        lists: tuple[list[float], list[float], list[float]] | None = None,
    ) -> None:
        """Set the joint state (``None`` velocities: at rest). ``q`` must not be mutated later;
        ``lists``: the same three as plain floats (kept for :meth:`lists`, not to be mutated)."""
        if q is not self.q:
            self.q = np.array(q, dtype=float)
            self.version += 1
        self.qd = ZERO6 if qd is None else qd
        self.qdd = ZERO6 if qdd is None else qdd
        if lists is not None:
            self._lists = (self.q, self.qd, self.qdd, *lists)

    def lists(self) -> tuple[list[float], list[float], list[float]]:
        """``q``, ``qd`` and ``qdd`` as plain floats, not to be mutated: kept while the arrays
        stay the same objects (the per-cycle readers then need no ``tolist``)."""
        c = self._lists
        if c and c[0] is self.q and c[1] is self.qd and c[2] is self.qdd:
            return c[3], c[4], c[5]
        out = (self.q.tolist(), self.qd.tolist(), self.qdd.tolist())
        self._lists = (self.q, self.qd, self.qdd, *out)
        return out

    def check_position(self, q: FloatArray, what: str, values: list[float] | None = None) -> None:
        """A SafetyLimitError if ``q`` leaves ±2π (``values``: ``q`` as floats, if known)."""
        if values is None:
            values = q.tolist()
        total = sum(values)
        if total - total == 0.0:  # all finite (the common case): plain floats, no numpy
            if max(map(abs, values)) <= JOINT_POSITION_LIMIT + 1e-9:
                return
        elif not np.abs(q).max() > JOINT_POSITION_LIMIT + 1e-9:  # not finite: numpy's verdict
            return
        joint = int(np.argmax(np.abs(q)))
        raise SafetyLimitError(f"{what}: joint {joint} position {q[joint]:.3f} out of ±2π")

    # ------------------------------------------------------------------ generators

    def run(self, motion: Motion) -> MotionToken:
        """Replace the current generator (its token is aborted) and start ``motion``."""
        self._abort_current("replaced by a new motion")
        self.suspended = None
        if self.moving and not isinstance(motion, ServoTrack | SpeedTrack | Stop):
            first = Stop(self, SAFETY_DECELERATION / 2)
            later = motion
            motion = MotionSequence(
                [lambda arm, tok: first, lambda arm, tok: later.restart(arm) or later], later.token
            )
        self.generator = motion
        return motion.token

    def _abort_current(self, why: str) -> None:
        if self.generator is not None:
            self.generator.token.finish(failed=why)
            self.generator = None

    def stop_motion(
        self, deceleration: float = PROGRAM_STOP_DECELERATION, *, hold: bool = False
    ) -> MotionToken:
        """Decelerate to rest; with ``hold`` the interrupted motion can be resumed."""
        if hold and self.generator is not None:
            self.suspended = self.generator
            self.generator = None
        else:
            self._abort_current("stopped")
            self.suspended = None
        stop = Stop(self, deceleration)
        self.generator = stop
        return stop.token

    def resume(self) -> None:
        if self.suspended is not None:
            again = self.suspended.restart(self)
            self.suspended = None
            if isinstance(self.generator, Stop):  # the pause's braking, cut short
                self.generator.token.finish()
                self.generator = None
            if again is not None:
                self.generator = again

    def safety_stop(self) -> None:
        self._abort_current("safety stop")
        self.suspended = None
        self.generator = Stop(self, SAFETY_DECELERATION)

    def halt(self) -> None:
        """Brakes engaged at once (power off)."""
        self._abort_current("halted")
        self.suspended = None
        self.set_state(self.q, None, None)

    # ------------------------------------------------------------------ the cycle

    def step(self, dt: float, *, enabled: bool = True) -> str | None:
        """Advance one cycle; returns a safety violation (protective stop reason) or None."""
        gen = self.generator
        if gen is None:
            if self.qd is not ZERO6:
                self.set_state(self.q, None, None)
            return None
        if not enabled:
            self._abort_current("robot not running")
            self.set_state(self.q, None, None)
            return None
        scale = self.speed_fraction if isinstance(gen, _SCALED) else 1.0
        if scale <= 0.0:  # slider at zero: the programmed move holds where it is
            if self.qd is not ZERO6:
                self.set_state(self.q, None, None)
            return None
        try:
            finished = gen.step(self, dt * scale)
            if scale != 1.0 and self.qd is not ZERO6:
                self.qd = self.qd * scale  # path time runs slower than the clock
                self.qdd = self.qdd * (scale * scale)
            self.check_position(self.q, "motion", self.lists()[0])
        except SafetyLimitError as exc:
            gen.token.finish(failed=str(exc))
            self.generator = None
            return str(exc)
        except MotionError as exc:
            self.generator = None
            self.set_state(self.q, None, None)
            gen.token.finish(failed=str(exc))
            return None
        if finished:
            if self.generator is gen:
                self.generator = None
            gen.token.finish()
        qd = self.qd
        if self.table is not None and qd is not ZERO6:
            speeds = self.lists()[1]
            if not any(speeds):  # at rest (``moving`` without numpy)
                return None
            # No point of the arm moves faster than REACH·Σ|q̇|: check the table only once
            # the arm may have covered its last clearance (and at least every 4 cycles
            # near the table, i.e. < 8 mm of travel between checks).
            travel = LINK_REACH * sum(map(abs, speeds)) * dt  # summed in numpy's order
            self._guard_budget -= travel
            if self._guard_budget <= 0.0:
                hit, clearance = self.table.check(self.kinematics.joint_frames(self.q))
                if hit is not None:
                    self._abort_current("collision")
                    return f"{hit} entered the table"
                self._guard_budget = max(clearance, 3.5 * travel)
        return None

    def set_tcp(self, tcp: Sequence[float]) -> None:
        if self.make_kinematics is not None:
            self.kinematics = self.make_kinematics(tuple(tcp))
            self.version += 1

    def tcp_pose(self) -> Pose:
        return self.kinematics.forward(self.q)

    def flange_pose(self) -> Pose:
        assert self.make_kinematics is not None
        return self.make_kinematics(None).forward(self.q)
