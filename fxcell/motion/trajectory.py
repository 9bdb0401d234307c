"""Jerk-limited time parameterisation with Ruckig, sampled at the robot kind's period.

The sample period and the joint count come with the :class:`Limits` (the kind's
:class:`~fxcell.link.capabilities.RobotCapabilities`: a UR3e's 2 ms servo cycle and six
joints); nothing here assumes a robot.

Three kinds of trajectories, all time-optimal within the scaled joint limits for what
they are asked to do:

- :func:`rest_to_rest`: one straight joint-space segment (phase-synchronised, so every
  sample lies on the straight line between start and target);
- :func:`through_waypoints`: a piecewise-linear joint path (e.g. from OMPL). Ruckig
  0.19's community edition has no intermediate waypoints, so each segment is its own
  Ruckig problem and consecutive segments meet with a non-zero velocity chosen from the
  path's geometry (zero only where a joint reverses). Blending leaves the straight
  segments near the corners, so the caller's validator checks the sampled result; a
  segment that fails is retried with rest at its ends, which follows the checked path
  exactly;
- :func:`along_path`: an exact geometric path ``q(s)`` (a Cartesian straight line
  solved by IK) timed with a one-dimensional Ruckig profile on the path parameter,
  with limits derived from the path's joint derivatives.

:func:`braking` is the jerk-limited stop from any state, used by ``stop()`` and
cancellation.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import ruckig
from numpy.typing import ArrayLike, NDArray

from fxcell.config import JointLimits
from fxcell.errors import InvalidFactorError, MoveTooLongError, PlanningError

NEGLIGIBLE_MOVE = 1e-9
"""rad: a move no joint of which travels farther than this is no move (zero duration).

Ruckig would time a 1e-13 rad move as a 0.1 ms profile; a nanoradian is four orders of
magnitude below the joint encoders' resolution, so such a target is already reached."""

Array = NDArray[np.float64]
Validator = Callable[[Array], int | None]
"""Checks sampled joint positions (N, joints); returns the index of the first bad sample or
None."""


def validate_factor(name: str, value: object, minimum: float = 0.0) -> float:
    """``value`` as a float if it is a finite number in (0, 1] and at least ``minimum``;
    else InvalidFactorError."""
    span = f"[{minimum:g}, 1]" if minimum > 0 else "(0, 1]"
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise InvalidFactorError(f"{name} must be a number in {span}, got {type(value).__name__}")
    f = float(value)
    if not (math.isfinite(f) and 0.0 < f <= 1.0 and f >= minimum):
        raise InvalidFactorError(f"{name} must be in {span}, got {value!r}")
    return f


@dataclass(frozen=True)
class Limits:
    """Per-joint kinematic limits a trajectory must respect (already scaled), and the
    period it is sampled at; the joint count is the vectors' length."""

    velocity: Array
    acceleration: Array
    jerk: Array
    position_min: Array
    position_max: Array
    period: float
    """Seconds between two samples: the robot kind's trajectory sample period."""
    max_duration: float = math.inf
    """A trajectory longer than this (s) is refused before it is sampled (bounds memory)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"the sample period must be > 0 s, got {self.period!r}")

    @property
    def joints(self) -> int:
        return len(self.velocity)

    @classmethod
    def from_config(
        cls,
        limits: JointLimits,
        velocity_factor: float = 1.0,
        acceleration_factor: float = 1.0,
        *,
        period: float,
    ) -> Limits:
        """Scale the configured limits: velocity by ``velocity_factor``, acceleration and
        jerk by ``acceleration_factor`` (both validated to be in (0, 1]); samples every
        ``period`` s."""
        vf = validate_factor("velocity_factor", velocity_factor)
        af = validate_factor("acceleration_factor", acceleration_factor)
        return cls(
            velocity=np.asarray(limits.velocity, float) * vf,
            acceleration=np.asarray(limits.acceleration, float) * af,
            jerk=np.asarray(limits.jerk, float) * af,
            position_min=np.asarray(limits.position_min, float),
            position_max=np.asarray(limits.position_max, float),
            period=period,
            max_duration=limits.max_move_duration,
        )

    @classmethod
    def for_braking(cls, limits: JointLimits, *, period: float) -> Limits:
        """The limits a stop brakes with: the configured braking deceleration and jerk."""
        return cls(
            velocity=np.asarray(limits.velocity, float),
            acceleration=np.asarray(limits.braking_acceleration, float),
            jerk=np.asarray(limits.braking_jerk, float),
            position_min=np.asarray(limits.position_min, float),
            position_max=np.asarray(limits.position_max, float),
            period=period,
        )

    def with_velocity(self, velocity: ArrayLike) -> Limits:
        return Limits(
            np.asarray(velocity, float),
            self.acceleration,
            self.jerk,
            self.position_min,
            self.position_max,
            self.period,
            self.max_duration,
        )


@dataclass(frozen=True)
class Trajectory:
    """Joint positions, velocities and accelerations sampled every ``period`` seconds.

    Sample ``k`` is the state at ``t = k·period``; the last sample is the exact end state
    (at ``duration``, which need not be a multiple of the period).
    """

    positions: Array
    velocities: Array
    accelerations: Array
    duration: float
    period: float
    """Seconds between two samples (the robot kind's trajectory sample period)."""
    segments: int = 1
    """Ruckig segments it was built from (1 for a direct move)."""
    stops: int = 0
    """Interior waypoints where the trajectory comes to rest."""

    @property
    def times(self) -> Array:
        t = np.arange(len(self.positions), dtype=float) * self.period
        t[-1] = self.duration
        return t

    def __len__(self) -> int:
        return len(self.positions)

    def state(self, index: int) -> tuple[Array, Array, Array]:
        """Position, velocity, acceleration of sample ``index`` (clamped to the end)."""
        i = min(max(index, 0), len(self.positions) - 1)
        return self.positions[i], self.velocities[i], self.accelerations[i]


# ----------------------------------------------------------------- Ruckig plumbing


def _input(limits: Limits) -> ruckig.InputParameter:
    inp = ruckig.InputParameter(limits.joints)
    inp.max_velocity = limits.velocity.tolist()
    inp.max_acceleration = limits.acceleration.tolist()
    inp.max_jerk = limits.jerk.tolist()
    return inp


def _solve(inp: ruckig.InputParameter) -> ruckig.Trajectory:
    dof = inp.degrees_of_freedom
    traj = ruckig.Trajectory(dof)
    try:
        result = ruckig.Ruckig(dof).calculate(inp, traj)
    except ruckig.RuckigError as exc:  # input it refuses (its message names the value)
        raise PlanningError(f"Ruckig could not time the motion: {str(exc).strip()}") from None
    if result not in (ruckig.Result.Working, ruckig.Result.Finished):
        raise PlanningError(f"Ruckig could not time the motion: {result}")
    return traj


def _segment(
    start: Array,
    target: Array,
    v0: Array,
    v1: Array,
    limits: Limits,
    *,
    phase: bool,
) -> ruckig.Trajectory:
    inp = _input(limits)
    inp.current_position = start.tolist()
    inp.current_velocity = v0.tolist()
    inp.current_acceleration = [0.0] * limits.joints
    inp.target_position = target.tolist()
    inp.target_velocity = v1.tolist()
    inp.target_acceleration = [0.0] * limits.joints
    inp.min_position = limits.position_min.tolist()
    inp.max_position = limits.position_max.tolist()
    inp.synchronization = ruckig.Synchronization.Phase if phase else ruckig.Synchronization.Time
    return _solve(inp)


def _evaluate(traj: ruckig.Trajectory, times: Array) -> tuple[Array, Array, Array]:
    """Positions, velocities, accelerations (len(times), dof) of a Ruckig trajectory.

    Vectorised over the seven constant-jerk phases of each joint's profile; falls back
    to ``at_time`` for profiles with a braking or acceleration pre-phase.
    """
    dof = traj.degrees_of_freedom
    n = len(times)
    pos, vel, acc = np.empty((n, dof)), np.empty((n, dof)), np.empty((n, dof))
    profiles = traj.profiles[0]
    for d, prof in enumerate(profiles):
        t = np.asarray(prof.t, float)
        if prof.brake.duration > 0 or prof.accel.duration > 0:
            break
        starts = np.concatenate(([0.0], np.cumsum(t)))
        k = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, 6)
        tau = np.clip(times - starts[k], 0.0, None)
        tau = np.minimum(tau, t[k])  # past the end: hold the final state
        j = np.asarray(prof.j, float)[k]
        a0 = np.asarray(prof.a, float)[k]
        v0 = np.asarray(prof.v, float)[k]
        p0 = np.asarray(prof.p, float)[k]
        pos[:, d] = p0 + tau * (v0 + tau * (a0 / 2 + tau * j / 6))
        vel[:, d] = v0 + tau * (a0 + tau * j / 2)
        acc[:, d] = a0 + tau * j
    else:
        return pos, vel, acc
    for i, tk in enumerate(times):
        pos[i], vel[i], acc[i] = traj.at_time(float(tk))
    return pos, vel, acc


class _Line:
    """A rest-to-rest straight joint segment, timed as a scalar profile (stays on the line)."""

    def __init__(self, start: Array, target: Array, limits: Limits) -> None:
        self.start = start
        self.delta = target - start
        self._traj = _scalar(*_line_limits(self.delta, limits))
        self.duration = float(self._traj.duration)

    def evaluate(self, times: Array) -> tuple[Array, Array, Array]:
        s, sd, sdd = _evaluate(self._traj, times)
        return self.start + s * self.delta, sd * self.delta, sdd * self.delta


class _Ruckig:
    def __init__(self, traj: ruckig.Trajectory) -> None:
        self._traj = traj
        self.duration = float(traj.duration)

    def evaluate(self, times: Array) -> tuple[Array, Array, Array]:
        return _evaluate(self._traj, times)


class Piece(Protocol):
    """A timed piece of a trajectory."""

    @property
    def duration(self) -> float: ...

    def evaluate(self, times: Array) -> tuple[Array, Array, Array]: ...


def _grid(total: float, period: float, max_duration: float = math.inf) -> Array:
    """Sample times every ``period`` from 0, the last one at ``total`` exactly."""
    if not total <= max_duration:
        raise MoveTooLongError(
            f"the move would take {total:.1f} s, longer than the {max_duration:g} s allowed "
            "(limits.max_move_duration): raise the speed factors or split the move"
        )
    n = max(round(math.ceil(total / period - 1e-9)), 1) + 1
    t = np.arange(n, dtype=float) * period
    t[-1] = total
    return t


def _sample(pieces: Sequence[Piece], limits: Limits, max_duration: float = math.inf) -> Trajectory:
    """Sample consecutive pieces on one grid, every ``limits.period`` from their start."""
    ends = np.cumsum([p.duration for p in pieces])
    total = float(ends[-1])
    t = _grid(total, limits.period, max_duration)
    n, dof = len(t), limits.joints
    pos, vel, acc = np.empty((n, dof)), np.empty((n, dof)), np.empty((n, dof))
    which = np.minimum(np.searchsorted(ends, t, side="left"), len(pieces) - 1)
    starts = np.concatenate(([0.0], ends[:-1]))
    for j, piece in enumerate(pieces):
        mask = which == j
        if mask.any():
            local = np.clip(t[mask] - starts[j], 0.0, piece.duration)
            pos[mask], vel[mask], acc[mask] = piece.evaluate(local)
    return Trajectory(pos, vel, acc, total, limits.period, segments=len(pieces))


def _scalar(v: float, a: float, j: float) -> ruckig.Trajectory:
    """The time-optimal rest-to-rest profile of a scalar from 0 to 1."""
    inp = ruckig.InputParameter(1)
    inp.current_position = [0.0]
    inp.target_position = [1.0]
    inp.max_velocity = [v]
    inp.max_acceleration = [a]
    inp.max_jerk = [j]
    return _solve(inp)


# ----------------------------------------------------------------- public builders


def _profile(
    v: float, a: float, j: float, period: float, max_duration: float = math.inf
) -> tuple[Array, Array, Array, Array]:
    """Sample the time-optimal rest-to-rest profile of a scalar s from 0 to 1.

    Returns times, s, ds/dt and d²s/dt² every ``period`` (last sample at the end time).
    """
    traj = _scalar(v, a, j)
    t = _grid(float(traj.duration), period, max_duration)
    s, sd, sdd = (x[:, 0] for x in _evaluate(traj, t))
    s[-1], sd[-1], sdd[-1] = 1.0, 0.0, 0.0
    return t, np.clip(s, 0.0, 1.0), sd, sdd


def _line_limits(delta: Array, limits: Limits) -> tuple[float, float, float]:
    """Limits of s on the line q0 + s·delta: the tightest joint, scaled by its share."""
    ad = np.abs(delta)
    moving = ad > 1e-15
    return (
        float(np.min(limits.velocity[moving] / ad[moving])),
        float(np.min(limits.acceleration[moving] / ad[moving])),
        float(np.min(limits.jerk[moving] / ad[moving])),
    )


def minimum_duration(start: ArrayLike, target: ArrayLike, limits: Limits) -> float:
    """Time-optimal rest-to-rest duration of a joint move under ``limits`` (the bound
    Ruckig computes with every joint free to move independently)."""
    zero = np.zeros(limits.joints)
    return float(
        _segment(
            np.asarray(start, float), np.asarray(target, float), zero, zero, limits, phase=False
        ).duration
    )


def rest_to_rest(start: ArrayLike, target: ArrayLike, limits: Limits) -> Trajectory:
    """The time-optimal jerk-limited move along the straight joint-space line.

    On a straight line every joint moves in proportion, so the optimum is a scalar
    profile under the tightest joint's limits; every sample lies on the line.
    """
    q0 = np.asarray(start, float)
    q1 = np.asarray(target, float)
    delta = q1 - q0
    if not np.any(np.abs(delta) > NEGLIGIBLE_MOVE):
        z = np.zeros((1, limits.joints))
        return Trajectory(q1[None, :].copy(), z, z.copy(), 0.0, limits.period)
    t, s, sd, sdd = _profile(*_line_limits(delta, limits), limits.period, limits.max_duration)
    pos = q0 + s[:, None] * delta
    pos[-1] = q1
    return Trajectory(pos, sd[:, None] * delta, sdd[:, None] * delta, float(t[-1]), limits.period)


def waypoint_velocities(waypoints: Array, limits: Limits) -> Array:
    """Velocities at the waypoints for passing through without stopping.

    In each segment the cruise velocity is the straight-line velocity the segment could
    reach (bounded by the joint velocities and by what the acceleration limits reach
    over the segment). At an interior waypoint each joint keeps the smaller of the
    adjacent segments' cruise speeds, and stops where it reverses direction. Each is
    clipped to its joint's limit: ``d * (limit / |d|)`` can round past it, and Ruckig
    refuses a target velocity beyond its limit by a single ulp.
    """
    m = len(waypoints)
    v = np.zeros((m, limits.joints))
    if m < 3:
        return v
    deltas = np.diff(waypoints, axis=0)
    cruise = np.zeros_like(deltas)
    for k, d in enumerate(deltas):
        ad = np.abs(d)
        moving = ad > 1e-9
        if not moving.any():
            continue
        scale = min(
            float(np.min(limits.velocity[moving] / ad[moving])),
            float(np.min(np.sqrt(limits.acceleration[moving] / ad[moving]))),
        )
        cruise[k] = d * scale
    for k in range(1, m - 1):
        a, b = cruise[k - 1], cruise[k]
        same = a * b > 0
        v[k] = np.where(same, np.sign(a) * np.minimum(np.abs(a), np.abs(b)), 0.0)
    return np.clip(v, -limits.velocity, limits.velocity)


def through_waypoints(
    waypoints: Sequence[Sequence[float]] | Array,
    limits: Limits,
    *,
    validate: Validator | None = None,
    blend: bool = True,
) -> Trajectory:
    """Time a piecewise-linear joint path, passing interior waypoints without stopping.

    ``validate`` checks the sampled positions; where a blended segment fails it, that
    segment is redone from rest to rest (exactly on the checked straight segment).
    """
    given = np.asarray(waypoints, float)
    # Drop repeated waypoints: a zero-length segment has nothing to time.
    keep = [0] + [
        k for k in range(1, len(given)) if np.max(np.abs(given[k] - given[k - 1])) > NEGLIGIBLE_MOVE
    ]
    wp = given[keep]
    wp[-1] = given[-1]  # end exactly at the target
    if len(wp) == 1:
        return rest_to_rest(wp[0], wp[0], limits)
    if len(wp) == 2:
        return rest_to_rest(wp[0], wp[1], limits)
    vel = waypoint_velocities(wp, limits) if blend else np.zeros_like(wp)
    for _ in range(len(wp) + 1):
        pieces: list[Piece] = []
        for k in range(len(wp) - 1):
            rest = not vel[k].any() and not vel[k + 1].any()
            try:
                pieces.append(
                    _Line(wp[k], wp[k + 1], limits)
                    if rest
                    else _Ruckig(
                        _segment(wp[k], wp[k + 1], vel[k], vel[k + 1], limits, phase=False)
                    )
                )
            except PlanningError:
                if rest:
                    raise
                vel[k] = vel[k + 1] = 0.0
                break
        else:
            traj = _sample(pieces, limits, limits.max_duration)
            traj.positions[-1] = wp[-1]
            traj.velocities[-1] = 0.0
            traj.accelerations[-1] = 0.0
            bad = validate(traj.positions) if validate is not None else None
            if bad is None:
                stops = sum(1 for k in range(1, len(wp) - 1) if not vel[k].any())
                return Trajectory(
                    traj.positions,
                    traj.velocities,
                    traj.accelerations,
                    traj.duration,
                    limits.period,
                    segments=len(pieces),
                    stops=stops,
                )
            ends = np.cumsum([p.duration for p in pieces])
            seg = min(int(np.searchsorted(ends, bad * limits.period)), len(pieces) - 1)
            if not vel[seg].any() and not vel[seg + 1].any():
                raise PlanningError("the timed path left the collision-free corridor")
            vel[seg] = vel[seg + 1] = 0.0
    raise PlanningError("could not time the path")  # pragma: no cover - loop always returns


def along_path(
    path: Callable[[float], Array],
    knots: Array,
    limits: Limits,
) -> Trajectory:
    """Time an exact geometric path ``q = path(s)``, ``s`` in [0, 1], without leaving it.

    ``knots`` are ``path`` evaluated at evenly spaced ``s`` (at least 3), used to bound
    the joint derivatives dq/ds and d²q/ds². The path parameter gets a one-dimensional
    time-optimal Ruckig profile under the tightest joint limits, the samples are
    ``path(s(t))``, and the result is checked against the joint limits and slowed if the
    path's curvature makes a joint exceed them.
    """
    knots = np.asarray(knots, float)
    m = len(knots)
    if m < 3:
        raise ValueError("along_path needs at least 3 knots")
    ds = 1.0 / (m - 1)
    d1 = np.max(np.abs(np.diff(knots, axis=0)), axis=0) / ds
    d2 = np.max(np.abs(np.diff(knots, n=2, axis=0)), axis=0) / ds**2
    if not np.any(d1 > 1e-12):
        return rest_to_rest(knots[0], knots[-1], limits)
    d1 = np.maximum(d1, 1e-12)
    safety = 1.0
    for _ in range(8):
        v_s = safety * float(np.min(limits.velocity / d1))
        # Keep most of the acceleration budget for the tangential term: lower v_s
        # until the centripetal term d²q/ds²·ṡ² takes at most a quarter of it.
        v_cap = float(np.min(np.sqrt(0.25 * limits.acceleration / np.maximum(d2, 1e-12))))
        v_s = min(v_s, v_cap)
        a_s = safety * float(np.min((limits.acceleration - d2 * v_s**2) / d1))
        j_s = safety * float(np.min(limits.jerk / d1))
        t, s, _, _ = _profile(v_s, a_s, j_s, limits.period, limits.max_duration)
        total = float(t[-1])
        n = len(t)
        pos = np.array([path(float(sk)) for sk in s])
        vel = np.gradient(pos, t, axis=0)
        acc = np.gradient(vel, t, axis=0)
        vel[0] = vel[-1] = 0.0
        acc[0] = acc[-1] = 0.0
        v_ratio = float(np.max(np.abs(vel) / limits.velocity))
        a_ratio = float(np.max(np.abs(acc[1:-1]) / limits.acceleration)) if n > 2 else 0.0
        if v_ratio <= 1.0 + 1e-3 and a_ratio <= 1.05:
            return Trajectory(pos, vel, acc, total, limits.period)
        safety *= 0.8 / max(v_ratio, math.sqrt(a_ratio), 1.0)
    raise PlanningError("could not time the path within the joint limits")


def braking(
    position: ArrayLike,
    velocity: ArrayLike,
    acceleration: ArrayLike,
    limits: Limits,
) -> Trajectory:
    """The jerk-limited time-optimal stop from a moving state (sample 0 = that state).

    All joints reach rest together at the slowest joint's minimum braking time.
    """
    inp = _input(limits)
    inp.control_interface = ruckig.ControlInterface.Velocity
    inp.synchronization = ruckig.Synchronization.Time
    inp.current_position = np.asarray(position, float).tolist()
    inp.current_velocity = np.asarray(velocity, float).tolist()
    inp.current_acceleration = np.asarray(acceleration, float).tolist()
    inp.target_velocity = [0.0] * limits.joints
    inp.target_acceleration = [0.0] * limits.joints
    traj = _sample([_Ruckig(_solve(inp))], limits)
    traj.velocities[-1] = 0.0
    traj.accelerations[-1] = 0.0
    return traj


def braking_duration(velocity: ArrayLike, acceleration: ArrayLike, limits: Limits) -> float:
    """The minimum time to rest from ``velocity``/``acceleration`` (the stop bound)."""
    inp = _input(limits)
    inp.control_interface = ruckig.ControlInterface.Velocity
    inp.synchronization = ruckig.Synchronization.No
    inp.current_position = [0.0] * limits.joints
    inp.current_velocity = np.asarray(velocity, float).tolist()
    inp.current_acceleration = np.asarray(acceleration, float).tolist()
    inp.target_velocity = [0.0] * limits.joints
    inp.target_acceleration = [0.0] * limits.joints
    return float(_solve(inp).duration)
