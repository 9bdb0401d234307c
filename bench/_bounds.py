"""Time-optimal bounds in closed form, independent of fxcell's (Ruckig-based) timing.

A single joint moving a distance ``d`` from rest to rest under velocity ``v``,
acceleration ``a`` and jerk ``j`` limits takes the least time with a symmetric S-curve:
it accelerates to a peak velocity ``vp``, cruises at it if ``vp = v``, and brakes
mirror-wise. Reaching ``vp`` from rest takes ``T(vp) = vp/a + a/j`` when the acceleration
limit is reached (``vp >= a²/j``), else ``T(vp) = 2·sqrt(vp/j)``; meanwhile the joint
covers ``vp·T(vp)/2`` (the profile is point-symmetric about its middle). So:

- ``d >= v·T(v)``: ``t = 2·T(v) + (d - v·T(v)) / v`` (cruise);
- else, with the acceleration limit reached (``d >= 2a³/j²``):
  ``vp = (a/2)·(sqrt(a²/j² + 4d/a) - a/j)`` and ``t = 2·(vp/a + a/j)``;
- else (jerk only): ``t = 4·(d/2j)^(1/3)``.

Bounds for several joints: joints free to move independently cannot beat the slowest
one (``free_bound``); on the straight joint line each joint moves in proportion, so the
line parameter ``s`` (0 → 1) gets the tightest of the scaled limits (``line_bound``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence


def rest_to_rest(d: float, v: float, a: float, j: float) -> float:
    """The minimum time (s) to move ``|d|`` from rest to rest under v, a, j limits."""
    d = abs(d)
    if d == 0.0:
        return 0.0
    if not (v > 0 and a > 0 and j > 0):
        raise ValueError("limits must be positive")

    def ramp(vp: float) -> float:  # time from rest to vp
        return vp / a + a / j if vp >= a * a / j else 2.0 * math.sqrt(vp / j)

    if d >= v * ramp(v):
        return 2.0 * ramp(v) + (d - v * ramp(v)) / v
    if d >= 2.0 * a**3 / j**2:
        vp = 0.5 * a * (math.sqrt((a / j) ** 2 + 4.0 * d / a) - a / j)
        return 2.0 * (vp / a + a / j)
    return 4.0 * (d / (2.0 * j)) ** (1.0 / 3.0)


def free_bound(
    delta: Sequence[float], v: Sequence[float], a: Sequence[float], j: Sequence[float]
) -> float:
    """Every joint on its own time-optimal profile: the slowest joint's time."""
    return max(
        (rest_to_rest(d, vi, ai, ji) for d, vi, ai, ji in zip(delta, v, a, j, strict=True)),
        default=0.0,
    )


def line_bound(
    delta: Sequence[float], v: Sequence[float], a: Sequence[float], j: Sequence[float]
) -> float:
    """The straight joint line from rest to rest (every joint in proportion)."""
    moving = [(abs(d), vi, ai, ji) for d, vi, ai, ji in zip(delta, v, a, j, strict=True) if d]
    if not moving:
        return 0.0
    return rest_to_rest(
        1.0,
        min(vi / d for d, vi, _, _ in moving),
        min(ai / d for d, _, ai, _ in moving),
        min(ji / d for d, _, _, ji in moving),
    )


def jerk_tail(tolerance: float, jerk: float) -> float:
    """How long before its end a jerk-limited rest-to-rest profile is already within
    ``tolerance`` of its target (its last phase: ``j·τ³/6``): the part of the bound a
    measurement with that tolerance cannot see."""
    return (6.0 * tolerance / jerk) ** (1.0 / 3.0)


def line_jerk(delta: Sequence[float], j: Sequence[float]) -> float:
    """The jerk of the leading joint on the straight joint line (for :func:`jerk_tail`)."""
    moving = [(abs(d), ji) for d, ji in zip(delta, j, strict=True) if d]
    return min(ji / d for d, ji in moving) * max(d for d, _ in moving)


def braking(v0: float, a0: float, amax: float, jmax: float) -> float:
    """The minimum time (s) to bring one joint from velocity ``v0`` and acceleration
    ``a0`` to rest (zero velocity and acceleration) under ``amax``/``jmax``.

    Normalised so that ``v0 >= 0``: first the acceleration is driven down at full jerk
    (to ``-amax`` at most), held, then released at full jerk to reach zero velocity and
    zero acceleration together. When ``a0 > 0`` the velocity still rises before it falls.
    """
    if v0 < 0 or (v0 == 0 and a0 < 0):
        v0, a0 = -v0, -a0
    if v0 == 0 and a0 == 0:
        return 0.0
    if v0 + a0 * abs(a0) / (2.0 * jmax) < 0:
        # Already braking so hard that releasing the brake alone would reverse the joint:
        # raise the acceleration to q > 0 at full jerk, then bring it back to zero;
        # velocity change (2q² - a0²)/(2j) = -v0.
        q = math.sqrt((a0 * a0 - 2.0 * jmax * v0) / 2.0)
        return (q - a0) / jmax + q / jmax
    # Release from acceleration -p (p > 0) to 0 at jerk jmax reduces v by p²/(2j).
    # Going from a0 to -p at jerk -jmax takes (a0 + p)/j and changes v by
    # (a0² - p²)/(2j). Total velocity change without a hold: (a0² - p²)/(2j) - p²/(2j).
    # Peak p solves v0 + (a0² - 2p²)/(2j) = 0  ->  p = sqrt((2j·v0 + a0²)/2).
    p = math.sqrt(max(0.0, (2.0 * jmax * v0 + a0 * a0) / 2.0))
    if p <= amax:
        return (a0 + p) / jmax + p / jmax
    # With a hold at -amax: ramp down, hold for the remaining velocity, ramp up.
    ramps_dv = (a0 * a0 - amax * amax) / (2.0 * jmax) - amax * amax / (2.0 * jmax)
    hold = (v0 + ramps_dv) / amax
    return (a0 + amax) / jmax + hold + amax / jmax


def braking_bound(
    velocity: Sequence[float], acceleration: Sequence[float], amax: Sequence[float],
    jmax: Sequence[float],
) -> float:  # fmt: skip
    """Every joint braking on its own: the slowest joint's time to rest."""
    return max(
        (
            braking(v, a0, am, jm)
            for v, a0, am, jm in zip(velocity, acceleration, amax, jmax, strict=True)
        ),
        default=0.0,
    )
