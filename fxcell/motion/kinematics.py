"""UR3e forward and inverse kinematics in UR's base frame (numpy and math only).

Frames follow UR's published Denavit-Hartenberg parameters (standard DH,
``T_i = Rz(θ_i)·Tz(d_i)·Tx(a_i)·Rx(α_i)``): frame 0 is the controller's base frame (the
teach pendant's, *not* ROS ``base_link``, which is turned 180° about z) and frame 6 is the
flange (``tool0``). A TCP given in the flange frame is appended, so :meth:`Kinematics.forward`
equals RTDE's ``actual_TCP_pose`` for the same TCP.

The inverse is the closed-form solution for the UR geometry (three parallel middle axes):
up to 8 branches (shoulder left/right × wrist flip × elbow up/down), each shifted by 2π per
joint to the equivalent nearest the seed within the joint limits; the nearest (Euclidean
in joint space) wins. At a wrist singularity (θ5 = 0 or π) axes 2, 3, 4 and 6 are parallel
and the solutions form a continuum: the member nearest the seed is returned. Near two
singularities at once, rounding can throw a branch just out of reach; such branches are
polished by Newton steps (to ≤ 1e-10 m/rad; generic poses are exact to ~1e-15).
``inverse`` has a lean hot path for the common case and falls back on the general one.

No Pinocchio here: the simulator imports this module and must start fast
(:mod:`fxcell.motion.robot_model` holds the Pinocchio model and is checked against this one).
``./dev`` and wheel builds compile this module with mypyc (``hatch_build.py``): same source,
same results, ~2.4x faster at the wrist singularity.
"""

from __future__ import annotations

import cmath
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from mypy_extensions import mypyc_attr
from numpy.typing import ArrayLike, NDArray

from fxcell.calibration import UR3E_NOMINAL_A, UR3E_NOMINAL_ALPHA, UR3E_NOMINAL_D
from fxcell.errors import (
    InvalidArgumentError,
    InvalidTargetError,
    SingularityError,
    UnreachableError,
)
from fxcell.geometry import Pose, matrix_to_rotvec

if TYPE_CHECKING:
    from fxcell.config import JointLimits

FloatArray = NDArray[np.float64]
JointValidity = Callable[[FloatArray], bool]

TWO_PI = 2.0 * math.pi
_INV_TWO_PI = 1.0 / TWO_PI

_CUT = 1.0 - 1e-6
"""Fraction of the way to a joint limit a Newton step of :meth:`_singular_arms` goes."""
_TRUST = 0.5
"""Largest Newton step (rad of θ6) in :meth:`_singular_arms`."""
_SPOTS = 3
"""Points where a 2π shift jumps at a limit (or θ2's or θ3's flips) :meth:`_singular_arms`
starts Newton steps from: the best few, if within _MARGIN of the best found."""
_GRID_STEP = 0.35
"""Largest spacing (rad of θ6) of the grid of :meth:`_singular_arms`."""
_MARGIN = 1.0
"""Grid minima at most this much (rad²) above the best found get Newton steps."""
_F_TOL = 1e-13
"""Newton steps stop when the next would lower the distance² by less than this fraction of
it (relative: a member ~1e-8 from the seed is resolved too, not only to √_F_TOL ≈ 3e-7)."""
_Ev = tuple[float, float, float, float, float, float, float, float, float, float, float]
"""f, f', f'', Gauss-Newton f'', θ2, θ3, θ4 (shifted), their derivatives, θ6 (shifted)."""
_WRIST_EPS = 1e-12
"""|sin θ5| below which the wrist counts as exactly singular (θ6 free: see _singular_arms).
Rounding alone leaves ~1e-14 (θ5 = ±2π with the arm stretched: θ1 carries ~3e-14), and a θ6
taken from that noise is valid but arbitrary; treating the wrist as singular up to 1e-12
costs at most ~1e-12 m or rad of pose error."""
_CLIP_EPS = 1e-12
"""Rounding slack on the cosines at the reach boundaries (≈ 1e-13 m of position)."""
_NEAR_WRIST = 1e-6
"""|sin θ5| below which a failed closed form is retried as a wrist singularity."""
_WRIST_SLACK = 1e-14
"""Next to the wrist singularity, a branch this much over ``1/|sin θ5|`` beyond the reach (in
cos θ3) may be a rounding error of θ6 (~1e-16/|sin θ5| rad, moving frame 4 by d5 times that)."""
_NEAR_MISS = 1e-6
"""How far beyond full stretch (in cos θ3) a branch is ever polished rather than dropped; see
:func:`_rounding_slack` for how far it is near which singularity."""
_POLISH_TOL = 1e-10
"""Pose error (m, rad) accepted from a solution polished by Newton steps."""
_EDGE_C3 = 0.1
"""How far beyond full stretch or fold (in cos θ3) :meth:`Kinematics.nearest_within` reports
a missed branch (a calibration's millimetres move cos θ3 by up to ~0.04)."""
_LENIENT_BEND = 0.05
"""rad: how far from straight :meth:`Kinematics.nearest_within` (``lenient``) bends a
stretched or folded arm, or turns θ1 from the shoulder singularity, for starting points."""
_LENIENT_C3 = math.cos(_LENIENT_BEND)
_LENIENT_H2 = math.sin(_LENIENT_BEND) ** 2
"""(h/d4)² below which a ``lenient`` start is taken at the shoulder singularity's edge."""
_LENIENT_WRIST = 0.01
"""|sin θ5| below which ``lenient`` starts are also taken on the wrist-singular continuum
(:meth:`Kinematics._continuum_starts`): a calibration's deltas move a target's θ5 by
milliradians."""
_LIMIT_EPS = 1e-12
"""Rounding slack (rad) at the joint limits: a solution this close beyond is clamped."""
_WRIST_MOVE = 0.1
"""Radians by which refinement next to the wrist singularity may move θ1 and θ5 together (see
:meth:`DHChain.nearest`)."""
_FINAL_STEP = 1e-7
"""Radians: a full Newton step of :meth:`DHChain.newton` this short is its last (the error it
leaves is of the order of its square)."""
_VALLEY_POINTS = 12
"""Points per turn of θ6 at which :meth:`DHChain.valley` samples the wrist's self-motion."""
_VALLEY_PROJECTIONS = 1
"""Gauss-Newton steps on θ1..θ5 (θ6 held) that bring a point back to the valley's floor (the
points are predicted along its tangent: one is enough)."""
_VALLEY_STEPS = 30
"""Steps :meth:`DHChain.valley` takes to close in on a root between two points."""
_VALLEY_HALVINGS = 5
"""Halvings of a bracket after which :meth:`DHChain.valley` drops it: Newton's steps take over
within one or two next to a root; one they keep leaving holds a minimum of the error."""
_VALLEY_NEAR = 0.05
"""|sin θ5| of a start below which :meth:`DHChain.nearest` searches its valley where Newton's
steps fail (farther from the singularity θ6 parametrises the valley poorly:
Levenberg-Marquardt)."""
_VALLEY_FINISH = 1e-5
"""Pose error below which a bracket that did not close is finished by :meth:`DHChain.newton`
(next to a root; a bracket around a minimum of the error stays well above)."""
_VALLEY_FLOOR = 1e-2
"""Pose error (m and rad together) above which a point is off the valley (the arm out of
reach at that θ6): no root is looked for next to it."""
_VALLEY_PREDICT = 0.3
"""Fraction of the points' spacing within which a point's Newton step of θ6 predicts a root
that :meth:`DHChain.valley` looks for even without a sign change (roots closer together than
the points, where the valley passes next to the calibrated wrist singularity)."""
_VALLEY_SAME = 0.25
"""Fraction of the points' spacing within which a predicted root is one already found."""
_VALLEY_TRIES = 6
"""Newton's steps :meth:`DHChain.valley` gives a predicted root (next to one, they converge
in two or three)."""
_VALLEY_ON = 0.1
"""Radians (each of θ1..θ5) within which :meth:`DHChain.nearest` takes a start next to the
wrist singularity for a point of a valley it walked already (a whole turn, uncut): the walk
from it would find the same roots."""
_VALLEY_CUTS = 0.01
_VALLEY_OFF = 2
"""With the start's |sin θ5| below _VALLEY_CUTS, a side of :meth:`DHChain._walk` that was on
the floor stops at its _VALLEY_OFF-th point off it in a row, and the other side goes on past
half a turn to where it stopped: next to the wrist singularity the valley is the arm's
self-motion, cut where the wrist centre's circle leaves the arm's reach (one arc), whose
points (2 chain evaluations each, no bracket across them) the old walk went through to the
half turn on both sides. Farther from the singularity
(|sin θ5| ~0.03, tried) the floor's error passes 1e-2 for a few points and comes back, with a
root after (bench/ik.py's uniform family, --seed 1: one answer farther), and so does it,
rarely, with a single point off (1 stopping it: wrist and limits families, 2 answers farther
each over --seed 1 and 3)."""
_VALLEY_REJECTIONS = 3
"""Rejected steps at which :meth:`DHChain.newton` gives up on a start next to the wrist
singularity (|sin θ5| below _VALLEY_NEAR): its valley is walked next, from the start, so where
Newton's steps stopped is not used. On bench/ik.py's wrist family (seed TCP, 300 poses of
--seed 2) none of the 103 runs that converged had 3 rejected steps, and 628 of the 642 that
did not had 3 or more (mostly alternating with damped steps crawling along the valley), 8
chain evaluations each without the limit; 2 (also tried) lost 6 of the 103 and one answer
of the limits family (--seed 1) to the walk."""
_MAX_WALKED = 16
"""Valleys :meth:`DHChain.nearest` remembers per call (the C code's fixed arrays)."""
_END_PROBES = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7)
"""How far inside an end of a continuum's interval (in u, see :meth:`Kinematics._singular_arms`)
f is probed when Newton's steps stop at the end: a minimum just inside it, f rising toward
the end, is reached from there (a concave step from the end's first cell leapt past one
0.007 of u inside, 4.5e-5 nearer the seed; a seed on the continuum 6e-8 of u inside came
back 1.1e-7 from itself without the last two; Hypothesis)."""
_END_SLACK = 1e-9
"""How far (rad of θ6) beyond an end of a continuum's interval a candidate point (where a
joint's shift flips at a limit) is still tried; see :func:`_within`."""
_SHIFT_SLIP = 1e-9
"""How much farther (rad², Σ over θ2, θ3, θ4, θ6) the closed form's solution at a point of a
continuum may be than f there before f's own joints are taken instead (a 2π shift flipped
by rounding: θ2 came 1.1e-12 beyond its limit at θ3 = 1e-4; Hypothesis)."""
_FLIP_BISECTIONS = 60
"""Bisections of a continuum's parameter for the point where a joint's 2π shift toward the
seed flips at a limit (halving u's step from ≤ 0.25 reaches rounding in ~55)."""
_STALL_STEPS = 8
_QUICK_STALL = 3
"""_STALL_STEPS for a start away from the wrist singularity (|sin θ5| at least ``near``, see
:meth:`DHChain.nearest`): next to the shoulder singularity most starts the nominal closed
form gives (the arm bent by _LENIENT_BEND) have no calibrated solution and settle into a
local minimum, which 4 steps told as well as 8 on the bench's families with fixed damping
factors, and 3 as well as 4 with Nielsen's (``adaptive``: bench/ik.py's families, seed TCP,
400 poses of --seed 1 and 2, the same answers farther from the seed than the reference;
shoulder family chain evaluations per call median 116 -> 108 and 138 -> 133; 2: shoulder
roots missed, with either damping); next to the wrist singularity, a run crawling along the
self-motion toward a root can look stalled over 4."""
_STALL_GAIN = 1e-3
_STALL_FLOOR = 1e-7
"""With ``stationary`` > 0, :meth:`DHChain.settle` reports a local minimum of the error (no
solution near) when _STALL_STEPS steps lowered an error above _STALL_FLOOR by less than the
fraction _STALL_GAIN: next to a singular local minimum (the arm stretched or folded) the
gradient ratio falls to ``stationary`` only after hundreds of steps that leave the error as
it was (to three digits), while a run toward a root lowers it steadily."""
_STALL_DONE = 1e-10
"""With ``stationary`` > 0, an error below this that _STALL_STEPS steps did not halve ends
:meth:`DHChain.settle`'s steps: a root where the Jacobian is singular (the arm exactly at
the shoulder or elbow singularity), which the steps approach ever more slowly (from 1e-10 to
1e-11 took ~600 more in one case), is reached to that."""


@dataclass(frozen=True)
class DH:
    """Standard Denavit-Hartenberg parameters of a 6-axis arm (metres, radians)."""

    d: tuple[float, float, float, float, float, float]
    a: tuple[float, float, float, float, float, float]
    alpha: tuple[float, float, float, float, float, float]


UR3E_DH = DH(d=UR3E_NOMINAL_D, a=UR3E_NOMINAL_A, alpha=UR3E_NOMINAL_ALPHA)
"""UR's published UR3e parameters (the one table is :mod:`fxcell.calibration`'s)."""

# UR's joint and link names (as in UR's URDFs), base to wrist 3. Link k moves with joint k.
JOINT_NAMES = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
LINK_NAMES = (
    "shoulder_link",
    "upper_arm_link",
    "forearm_link",
    "wrist_1_link",
    "wrist_2_link",
    "wrist_3_link",
)


def dh_transform(theta: float, d: float, a: float, alpha: float) -> FloatArray:
    """``Rz(θ)·Tz(d)·Tx(a)·Rx(α)`` as a 4×4 matrix."""
    ct, st = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def _as_tcp(tcp: Sequence[float] | Pose | None) -> Pose:
    if tcp is None:
        return Pose.identity()
    if isinstance(tcp, Pose):
        return tcp
    return Pose.from_ur(tcp)


@mypyc_attr(allow_interpreted_subclasses=True)  # CalibratedKinematics; see hatch_build.py
class Kinematics:
    """Forward and inverse kinematics of a UR arm with a TCP.

    ``limits`` are the joint position limits ``(lower, upper)`` (6 each); by default those of
    :class:`fxcell.config.JointLimits` (±2π).
    """

    def __init__(
        self,
        dh: DH,
        tcp: Sequence[float] | Pose | None = None,
        limits: tuple[Sequence[float], Sequence[float]] | None = None,
    ) -> None:
        if (
            dh.a[0] != 0.0
            or dh.a[3:] != (0.0, 0.0, 0.0)
            or dh.d[1:3] != (0.0, 0.0)
            or dh.alpha != UR3E_DH.alpha
        ):
            raise InvalidArgumentError("the closed-form inverse needs the UR geometry (UR3E_DH)")
        self.dh = dh
        self.tcp: Pose = _as_tcp(tcp)
        if limits is None:
            limits = _default_limits()
        lo = [float(v) for v in limits[0]]
        hi = [float(v) for v in limits[1]]
        if len(lo) != 6 or len(hi) != 6 or not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise InvalidArgumentError(f"joint limits must be 6 increasing pairs, got {limits!r}")
        self.lower: tuple[float, ...] = tuple(lo)
        self.upper: tuple[float, ...] = tuple(hi)
        self._lo_hi = tuple(zip(lo, hi, strict=True))
        self._geom = (dh.d[0], dh.d[3], dh.d[4], dh.d[5], dh.a[1], dh.a[2])
        Rt, pt = self.tcp.rotation, self.tcp.position
        self._tcp_is_identity = bool(np.array_equal(Rt, np.eye(3)) and not pt.any())
        # flange = target · tcp⁻¹, kept as plain floats for the hot path
        Ri = Rt.T
        self._tcp_inv = (*Ri.ravel().tolist(), *(-(Ri @ pt)).tolist())
        self._tcp = (*Rt.ravel().tolist(), *pt.tolist())
        self._tcp_matrix = self.tcp.matrix

    @classmethod
    def ur3e(
        cls,
        tcp: Sequence[float] | Pose | None = None,
        limits: JointLimits | tuple[Sequence[float], Sequence[float]] | None = None,
    ) -> Kinematics:
        """The UR3e; ``tcp`` in the flange frame (``[x, y, z, rx, ry, rz]`` or a Pose),
        ``None`` = the flange (``tool0``); ``limits`` a JointLimits or ``(lower, upper)``."""
        if limits is not None and not isinstance(limits, tuple):
            limits = (limits.position_min, limits.position_max)
        return cls(UR3E_DH, tcp, limits)

    @property
    def reach(self) -> float:
        """No TCP position farther than this from the base origin is reachable (m): the
        sum of the DH lengths and the TCP offset, plus 1 cm for calibration deltas."""
        lengths = sum(abs(v) for v in (*self.dh.a, *self.dh.d))
        return float(lengths + float(np.linalg.norm(self.tcp.position)) + 0.01)

    def with_tcp(self, tcp: Sequence[float] | Pose | None) -> Kinematics:
        """The same arm and limits with another TCP."""
        return Kinematics(self.dh, tcp, (self.lower, self.upper))

    # ------------------------------------------------------------ forward

    def _flange(self, q: Sequence[float]) -> list[float]:
        """Flange transform as 12 floats: rotation row-major, then position.

        The DH chain written out for the UR geometry (axes 2, 3, 4 parallel), frame axes as
        vectors: about a third of the work of the generic product.
        """
        q1, q2, q3, q4, q5, q6 = q
        d1, d4, d5, d6, a2, a3 = self._geom
        c1, s1 = math.cos(q1), math.sin(q1)
        q23 = q2 + q3
        q234 = q23 + q4
        c2, s2 = math.cos(q2), math.sin(q2)
        c23, s23 = math.cos(q23), math.sin(q23)
        c234, s234 = math.cos(q234), math.sin(q234)
        c5, s5 = math.cos(q5), math.sin(q5)
        c6, s6 = math.cos(q6), math.sin(q6)
        # frame 1: x1 = (c1, s1, 0), y1 = (0, 0, 1), z1 = (s1, -c1, 0); frame 4 turns about z1
        x4x, x4y, x4z = c234 * c1, c234 * s1, s234
        z4x, z4y, z4z = s234 * c1, s234 * s1, -c234
        # frame 5: x5 = c5 x4 + s5 z1, y5 = -z4, z5 = -s5 x4 + c5 z1
        x5x, x5y, x5z = c5 * x4x + s5 * s1, c5 * x4y - s5 * c1, c5 * x4z
        z5x, z5y, z5z = -s5 * x4x + c5 * s1, -s5 * x4y - c5 * c1, -s5 * x4z
        # frame 6 turns about z5
        x6x, x6y, x6z = c6 * x5x - s6 * z4x, c6 * x5y - s6 * z4y, c6 * x5z - s6 * z4z
        y6x, y6y, y6z = -s6 * x5x - c6 * z4x, -s6 * x5y - c6 * z4y, -s6 * x5z - c6 * z4z
        reach = a2 * c2 + a3 * c23  # along x1
        return [
            x6x,
            y6x,
            z5x,
            x6y,
            y6y,
            z5y,
            x6z,
            y6z,
            z5z,
            reach * c1 + d4 * s1 + d5 * z4x + d6 * z5x,
            reach * s1 - d4 * c1 + d5 * z4y + d6 * z5y,
            d1 + a2 * s2 + a3 * s23 + d5 * z4z + d6 * z5z,
        ]

    def forward(self, q: ArrayLike) -> Pose:
        """TCP pose in UR's base frame for joint positions ``q`` (rad)."""
        f = self._flange(_joints(q))
        if not self._tcp_is_identity:
            f = _compose(f, self._tcp)
        return Pose._raw(np.array(f[9:]), np.array((f[0:3], f[3:6], f[6:9])))

    def forward_rows(self, q: ArrayLike) -> list[float]:
        """:meth:`forward` as 12 plain floats, no arrays: the rotation row-major, then the
        position (the same values)."""
        f = self._flange(_joints(q))
        return f if self._tcp_is_identity else _compose(f, self._tcp)

    def forward_flange(self, q: ArrayLike) -> Pose:
        """Flange (``tool0``) pose, whatever the TCP."""
        f = self._flange(_joints(q))
        return Pose._raw(np.array(f[9:]), np.array(f[:9]).reshape(3, 3))

    def joint_frames(self, q: ArrayLike) -> list[FloatArray]:
        """4×4 frames: base, after each of the 6 joints (the last is the flange), then the TCP.

        The DH frames 0..6 of UR's convention (views into one (8, 4, 4) array).
        """
        return list(self._frames(q))

    def _frames(self, q: ArrayLike) -> FloatArray:
        """The :meth:`joint_frames` as one (8, 4, 4) array, written out for the UR geometry
        like :meth:`_flange`."""
        q1, q2, q3, q4, q5, q6 = _joints(q)
        d1, d4, d5, d6, a2, a3 = self._geom
        c1, s1 = math.cos(q1), math.sin(q1)
        c2, s2 = math.cos(q2), math.sin(q2)
        c23, s23 = math.cos(q2 + q3), math.sin(q2 + q3)
        c234, s234 = math.cos(q2 + q3 + q4), math.sin(q2 + q3 + q4)
        c5, s5 = math.cos(q5), math.sin(q5)
        c6, s6 = math.cos(q6), math.sin(q6)
        # x1 = (c1, s1, 0), y1 = (0, 0, 1), z1 = (s1, -c1, 0): joints 2-4 turn in the x1-y1 plane
        z1 = (s1, -c1, 0.0)
        o1 = (0.0, 0.0, d1)
        x2, y2 = (c2 * c1, c2 * s1, s2), (-s2 * c1, -s2 * s1, c2)
        o2 = (a2 * x2[0], a2 * x2[1], d1 + a2 * x2[2])
        x3, y3 = (c23 * c1, c23 * s1, s23), (-s23 * c1, -s23 * s1, c23)
        o3 = (o2[0] + a3 * x3[0], o2[1] + a3 * x3[1], o2[2] + a3 * x3[2])
        x4, z4 = (c234 * c1, c234 * s1, s234), (s234 * c1, s234 * s1, -c234)
        o4 = (o3[0] + d4 * z1[0], o3[1] + d4 * z1[1], o3[2])
        x5 = (c5 * x4[0] + s5 * z1[0], c5 * x4[1] + s5 * z1[1], c5 * x4[2])
        y5 = (-z4[0], -z4[1], -z4[2])
        z5 = (-s5 * x4[0] + c5 * z1[0], -s5 * x4[1] + c5 * z1[1], -s5 * x4[2])
        o5 = (o4[0] + d5 * z4[0], o4[1] + d5 * z4[1], o4[2] + d5 * z4[2])
        x6 = tuple(c6 * a + s6 * b for a, b in zip(x5, y5, strict=True))
        y6 = tuple(-s6 * a + c6 * b for a, b in zip(x5, y5, strict=True))
        o6 = (o5[0] + d6 * z5[0], o5[1] + d6 * z5[1], o5[2] + d6 * z5[2])
        flat: list[float] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        for x, y, z, o in (
            ((c1, s1, 0.0), (0.0, 0.0, 1.0), z1, o1),
            (x2, y2, z1, o2),
            (x3, y3, z1, o3),
            (x4, z1, z4, o4),
            (x5, y5, z5, o5),
            (x6, y6, z5, o6),
        ):
            flat += (x[0], y[0], z[0], o[0], x[1], y[1], z[1], o[1], x[2], y[2], z[2], o[2])
        out = np.empty((8, 4, 4))
        out[:7, :3, :] = np.array(flat).reshape(7, 3, 4)
        out[:7, 3, :] = (0.0, 0.0, 0.0, 1.0)
        out[7] = out[6] @ self._tcp_matrix
        return out

    def jacobian(self, q: ArrayLike) -> FloatArray:
        """Geometric Jacobian (6×6) at the TCP in the base frame: rows vx, vy, vz, wx, wy, wz."""
        F = self._frames(q)
        z = F[:6, :3, 2]  # joint k turns about z of frame k-1
        d = F[7, :3, 3] - F[:6, :3, 3]  # from each joint axis to the TCP
        J = np.empty((6, 6))
        J[0] = z[:, 1] * d[:, 2] - z[:, 2] * d[:, 1]
        J[1] = z[:, 2] * d[:, 0] - z[:, 0] * d[:, 2]
        J[2] = z[:, 0] * d[:, 1] - z[:, 1] * d[:, 0]
        J[3:] = z.T
        return J

    # ------------------------------------------------------------ singularities

    def singularity_margins(self, q: ArrayLike) -> tuple[float, float, float]:
        """Distances from the three UR singularities at ``q``.

        ``(shoulder, elbow, wrist)``: shoulder = distance (m) of the wrist centre (frame 5
        origin) from the plane of axes 1 and 2; elbow = |sin θ3|; wrist = |sin θ5|.
        """
        qq = _joints(q)
        f = self._flange(qq)
        d6 = self.dh.d[5]
        x5, y5 = f[9] - d6 * f[2], f[10] - d6 * f[5]
        shoulder = abs(math.cos(qq[0]) * x5 + math.sin(qq[0]) * y5)
        return shoulder, abs(math.sin(qq[2])), abs(math.sin(qq[4]))

    def singularity(
        self, q: ArrayLike, *, distance: float = 1e-3, sine: float = 1e-3
    ) -> str | None:
        """``"shoulder"``, ``"elbow"`` or ``"wrist"`` if ``q`` is within the margins of that
        singularity (``distance`` in metres for the shoulder, ``sine`` for |sin θ3| and
        |sin θ5|), else None."""
        shoulder, elbow, wrist = self.singularity_margins(q)
        for name, value, tol in (
            ("shoulder", shoulder, distance),
            ("elbow", elbow, sine),
            ("wrist", wrist, sine),
        ):
            if value < tol:
                return name
        return None

    def check_singularity(
        self, q: ArrayLike, *, distance: float = 1e-3, sine: float = 1e-3
    ) -> None:
        """Raise :class:`SingularityError` if ``q`` is within the given margins of one."""
        kind = self.singularity(q, distance=distance, sine=sine)
        if kind is not None:
            raise SingularityError(f"{kind} singularity at q={np.round(_joints(q), 6).tolist()}")

    # ------------------------------------------------------------ inverse

    def _branches(self, pose: Pose, seed: list[float]) -> list[list[float]]:
        """Every closed-form solution (angles not yet shifted) reaching ``pose`` at the TCP.

        At an exact wrist singularity each shoulder/elbow branch is a continuum; the member
        nearest ``seed`` is returned (see :meth:`_singular_arms`).
        """
        f = [*pose.rotation.ravel().tolist(), *pose.position.tolist()]
        if not self._tcp_is_identity:
            f = _compose(f, self._tcp_inv)
        r00, r01, r02, r10, r11, r12, _r20, _r21, r22, px, py, pz = f
        d4, d6 = self.dh.d[3], self.dh.d[5]

        # wrist centre (frame 5 origin): its component along axis 2 (horizontal) must be d4
        p5x, p5y, p5z = px - d6 * r02, py - d6 * r12, pz - d6 * r22
        h2 = p5x * p5x + p5y * p5y - d4 * d4
        if h2 < 0.0:
            if h2 < -_CLIP_EPS * d4 * d4:
                return []
            h2 = 0.0
        h = math.sqrt(h2)
        phi = math.atan2(p5y, p5x)
        out: list[list[float]] = []
        for hs in (h, -h) if h > 0.0 else (h,):
            t1 = phi + math.atan2(d4, hs)
            s1, c1 = math.sin(t1), math.cos(t1)
            # axis 2 (= 3 = 4) expressed in the flange frame is (s5 c6, -s5 s6, c5)
            zx = r00 * s1 - r10 * c1
            zy = r01 * s1 - r11 * c1
            zz = r02 * s1 - r12 * c1
            s5a = math.sqrt(zx * zx + zy * zy)
            if s5a > _WRIST_EPS:
                n = len(out)
                # Near the shoulder or wrist singularity θ1 or θ6 carry amplified rounding
                # error, which can throw a stretched arm just out of reach: such branches
                # come back in ``rough`` (stretch clipped) and are polished by Newton steps.
                rough: list[list[float]] = []
                slack = min(_rounding_slack(s5a, h), _NEAR_MISS)
                t6a, t6b = math.atan2(-zy, zx), math.atan2(zy, -zx)
                self._arm(f, p5x, p5y, p5z, t1, s1, c1, s5a, zz, t6a, out, 0, rough, slack)
                self._arm(f, p5x, p5y, p5z, t1, s1, c1, -s5a, zz, t6b, out, 0, rough, slack)
                for sol in rough:
                    fixed = self._reach_by_wrist(f, p5x, p5y, p5z, s1, c1, sol, pose)
                    out.extend(fixed or [p for p in (self._polish(sol, pose),) if p])
                if len(out) == n and s5a < _NEAR_WRIST:
                    # still nothing: search θ6 as at the singularity, then polish
                    for s5 in (s5a, -s5a):
                        for sol in self._singular_arms(f, p5x, p5y, p5z, t1, s1, c1, s5, zz, seed):
                            if self._reaches(sol, pose):
                                out.append(sol)
                            elif polished := self._polish(sol, pose):
                                out.append(polished)
            else:
                c5 = 1.0 if zz >= 0.0 else -1.0
                out += self._singular_arms(f, p5x, p5y, p5z, t1, s1, c1, 0.0, c5, seed)
        return out

    def _reach_by_wrist(
        self,
        f: list[float],
        p5x: float,
        p5y: float,
        p5z: float,
        s1: float,
        c1: float,
        sol: list[float],
        pose: Pose,
    ) -> list[list[float]]:
        """A stretched (or folded) arm just out of reach next to the wrist singularity,
        brought into reach by θ6; [] if that does not reach ``pose`` within 1e-10.

        There θ6 carries rounding error amplified ~1/|sin θ5|, which moves frame 4's origin
        on its circle around the wrist centre and can leave the arm ~1e-8 short of it. Turning
        θ6 by the few 1e-8 rad that bring cos θ3 back to ±1 costs only ~|sin θ5| times that
        in orientation. Newton's method on the pose error (:meth:`_polish`) converges slowly
        there (at the stretch the arm cannot move radially to first order): this is a
        1-D Newton on cos θ3(θ6) instead, then :meth:`_arm`.
        """
        d1, _, d5, _, a2, a3 = self._geom
        r00, r01, _, r10, r11, _, r20, r21 = f[:8]
        k3, l3 = 1.0 / (2.0 * a2 * a3), a2 * a2 + a3 * a3
        sin, cos = math.sin, math.cos

        def c3_of(t6: float) -> float:
            s6, c6 = sin(t6), cos(t6)
            ox = p5x + d5 * (s6 * r00 + c6 * r01)
            oy = p5y + d5 * (s6 * r10 + c6 * r11)
            X = c1 * ox + s1 * oy
            Y = p5z + d5 * (s6 * r20 + c6 * r21) - d1
            return (X * X + Y * Y - l3) * k3

        t1, t5, t6 = sol[0], sol[4], sol[5]
        c3 = c3_of(t6)
        goal = 1.0 if c3 > 0.0 else -1.0
        for _ in range(4):
            if abs(c3) <= 1.0 + _CLIP_EPS:
                break
            h = 1e-6
            slope = (c3_of(t6 + h) - c3_of(t6 - h)) / (2.0 * h)
            if abs(slope) < 1e-9:  # the circle is tangent to the reach: no first-order fix
                return []
            t6 -= (c3 - goal) / slope
            c3 = c3_of(t6)
        else:
            return []
        found: list[list[float]] = []
        self._arm(f, p5x, p5y, p5z, t1, s1, c1, sin(t5), cos(t5), t6, found, 0)
        return [q for q in found if self._reaches(q, pose)]

    def _reaches(self, q: list[float], pose: Pose) -> bool:
        """Whether ``q`` reaches ``pose`` within 1e-10 (m and rad)."""
        reached = self.forward(q)
        return reached.distance(pose) <= _POLISH_TOL and reached.angle_to(pose) <= _POLISH_TOL

    def _polish(self, sol: list[float], pose: Pose) -> list[float] | None:
        """``sol`` after Newton steps, or None if it still misses ``pose`` by over 1e-10.

        Only near two singularities at once, where the pose pins some joints down to no
        better than ~1e-10 m of pose error (far below the robot's 3e-5 m repeatability).
        """
        out: list[float] = self.refine(np.array(sol), pose, iterations=60).tolist()
        return out if self._reaches(out, pose) else None

    def _arm(
        self,
        f: list[float],
        p5x: float,
        p5y: float,
        p5z: float,
        t1: float,
        s1: float,
        c1: float,
        s5: float,
        c5: float,
        t6: float,
        out: list[list[float]],
        elbow: int,
        rough: list[list[float]] | None = None,
        slack: float = _NEAR_MISS,
        clip: float = _CLIP_EPS,
    ) -> None:
        """Append the solutions for given θ1, θ5 (as sine, cosine) and θ6 to ``out``.

        ``elbow`` 0 appends both elbow branches, +1 / -1 only that sign of sin θ3; ``clip``
        is the rounding slack accepted beyond full stretch or fold. Solutions that miss the
        stretch by less than ``slack`` go to ``rough`` if given.
        """
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = f[:9]
        d1, d5 = self.dh.d[0], self.dh.d[4]
        a2, a3 = self.dh.a[1], self.dh.a[2]
        s6, c6 = math.sin(t6), math.cos(t6)
        # axis 5 (z4) and x4 in the base frame
        z4x = -(s6 * r00 + c6 * r01)
        z4y = -(s6 * r10 + c6 * r11)
        z4z = -(s6 * r20 + c6 * r21)
        u, v, w = c5 * c6, -c5 * s6, -s5
        x4x = r00 * u + r01 * v + r02 * w
        x4y = r10 * u + r11 * v + r12 * w
        x4z = r20 * u + r21 * v + r22 * w
        t234 = math.atan2(x4z, c1 * x4x + s1 * x4y)
        # frame 4 origin in the arm plane (frame 1 coordinates): a planar 2R problem
        o4x, o4y, o4z = p5x - d5 * z4x, p5y - d5 * z4y, p5z - d5 * z4z
        X = c1 * o4x + s1 * o4y
        Y = o4z - d1
        c3 = (X * X + Y * Y - a2 * a2 - a3 * a3) / (2.0 * a2 * a3)
        if c3 > 1.0 or c3 < -1.0:
            if abs(c3) > 1.0 + clip:
                if rough is None or abs(c3) > 1.0 + slack:
                    return
                out = rough
            c3 = 1.0 if c3 > 0.0 else -1.0
        s3a = math.sqrt(1.0 - c3 * c3)
        t5 = math.atan2(s5, c5)
        base = math.atan2(Y, X)
        signs: tuple[int, ...] = (1, -1) if elbow == 0 and s3a > 0.0 else (elbow or 1,)
        for sign in signs:
            s3 = sign * s3a
            t3 = math.atan2(s3, c3)
            t2 = base - math.atan2(a3 * s3, a2 + a3 * c3)
            out.append([t1, t2, t3, t234 - t2 - t3, t5, t6])

    def _continuum_starts(
        self,
        f: list[float],
        p5x: float,
        p5y: float,
        p5z: float,
        t1: float,
        s1: float,
        c1: float,
        c5: float,
        seed: list[float],
    ) -> list[list[float]]:
        """Wrist singular (θ5 = 0 or π): members of the continuum to start the calibrated
        refinement from (``lenient`` :meth:`nearest_within`), both elbows, one per interval
        of θ6 where the arm reaches frame 4's origin (see :meth:`_singular_arms`): its middle,
        where the arm is farthest from stretched and folded, or the seed's θ6 where the arm
        reaches the whole circle. The refinement walks the valley from there
        (:meth:`DHChain.valley`); the member nearest the seed (:meth:`_singular_arms`, ~30
        times the work) is no better a start. Plain square roots where that has hypot, as
        ``fxcell/motion/_dhchain.c`` computes it (libm's hypot rounds otherwise than
        Python's)."""
        r00, r01, r10, r11, r20, r21 = f[0], f[1], f[3], f[4], f[6], f[7]
        d1, _, d5, _, a2, a3 = self._geom
        X5, Y5 = c1 * p5x + s1 * p5y, p5z - d1
        ax, ay = c1 * r00 + s1 * r10, r20
        bx, by = c1 * r01 + s1 * r11, r21
        # z4·w = -(A s6 + B c6) = -k·D cos(θ6 - γ), w the wrist centre from the shoulder
        A = ax * X5 + ay * Y5
        B = bx * X5 + by * Y5
        kD, gamma = math.sqrt(A * A + B * B), math.atan2(A, B)
        # |frame-4 origin - shoulder|² = D² + d5² + 2 d5 k D cos(θ6 - γ) within the 2R reach
        den = 2.0 * d5 * kD
        D2 = X5 * X5 + Y5 * Y5
        mids: list[float] = []
        if den < 1e-15:
            mids.append(seed[5])
        else:
            lo_c = ((a2 - a3) * (a2 - a3) - D2 - d5 * d5) / den
            hi_c = ((a2 + a3) * (a2 + a3) - D2 - d5 * d5) / den
            if lo_c > 1.0 + _CLIP_EPS or hi_c < -1.0 - _CLIP_EPS:
                return []
            near = math.acos(min(max(hi_c, -1.0), 1.0))
            far = math.acos(min(max(lo_c, -1.0), 1.0))
            if hi_c >= 1.0 and lo_c <= -1.0:
                mids.append(seed[5])
            elif hi_c >= 1.0:
                mids.append(gamma)
            elif lo_c <= -1.0:
                mids.append(gamma + math.pi)
            else:
                mids += [gamma + 0.5 * (near + far), gamma - 0.5 * (near + far)]
        out: list[list[float]] = []
        for t6 in mids:
            self._arm(f, p5x, p5y, p5z, t1, s1, c1, 0.0, c5, t6, out, 0)
        return out

    def _singular_arms(
        self,
        f: list[float],
        p5x: float,
        p5y: float,
        p5z: float,
        t1: float,
        s1: float,
        c1: float,
        s5: float,
        c5: float,
        seed: list[float],
        bound: float = math.inf,
        nearest_only: bool = False,
    ) -> list[list[float]]:
        """Wrist singular (θ5 = 0 or π): axes 2, 3, 4 and 6 are parallel and θ6 is free.

        One solution per elbow sign (up, then down), each the member of the continuum nearest
        ``seed`` (after the 2π shifts of :meth:`_nearest`); none if the arm cannot reach, or
        (the search cut short) if no member is nearer than ``bound`` in Σ (θj - seed_j)²
        over j = 2, 3, 4, 6. ``nearest_only``: the elbow that looks nearer first, and the
        other only if it beats that one (so the nearest of the two, possibly alone, last).

        In the arm plane (coordinates c1·x + s1·y and z), θ6 = t turns axis 5 and so moves
        frame 4's origin on a circle of radius d5 around the wrist centre; the arm reaches
        it on one or two intervals of t whose ends stretch or fold the arm, or on the whole
        circle. θ2 + θ3 + θ4 is the angle of x4, ±t plus a constant, and θ2, θ3 come from
        the planar 2R problem, so every joint and its first two derivatives in t are in
        closed form. The distance² to the seed, f(t) = Σ (θj - seed_j)² over j = 2, 3, 4, 6
        (θ1 and θ5 are fixed), has several local minima (the θ4 and θ6 terms alone have two;
        θ2, θ3 swing fast near the ends and where the circle passes near the shoulder) and
        jumps where a joint reaches a limit and its 2π shift flips to the far equivalent.

        So: f for both elbows on a grid in u, t = lo + span·sin²u (smooth in u at the ends,
        where θ3 has an infinite slope in t), at most _GRID_STEP rad of t apart; Newton
        steps in u from the grid's local minima (those within _MARGIN of the best found),
        each step stopping short of a joint limit (and, where a joint's 2π shift flips
        past one anyway, at the last point before the flip, by bisection; u comes within
        1e-9 of the ends, below where rounding resolves θ3); and the points where a joint's 2π shift
        toward the seed jumps at a limit, or else (θ2, θ3) flips half a turn from the seed
        (roots of cos(·) = const in closed form), as candidates and starts. Candidates are
        compared on the solutions :meth:`_arm` gives for them. About 10-30 grid points (one
        loop of plain floats, :func:`_continuum_f`) and 1-5 short Newton runs per shoulder
        (the grid and golden-section search this replaced took ~130 solves). Also used, with
        the tiny |sin θ5| of a pose next to the singularity, for the fallback of
        :meth:`_branches`.
        """
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = f[:9]
        d1, _, d5, _, a2, a3 = self._geom
        # wrist centre from the shoulder, and x6, y6, z6 in the arm plane
        X5, Y5 = c1 * p5x + s1 * p5y, p5z - d1
        ax, ay = c1 * r00 + s1 * r10, r20
        bx, by = c1 * r01 + s1 * r11, r21
        zx, zy = c1 * r02 + s1 * r12, r22
        D = math.hypot(X5, Y5)
        ex, ey = (X5 / D, Y5 / D) if D > 0.0 else (1.0, 0.0)
        # z4·e = -(A s6 + B c6) = -k cos(θ6 - γ)
        A = ax * ex + ay * ey
        B = bx * ex + by * ey
        k, gamma = math.hypot(A, B), math.atan2(A, B)
        # |frame-4 origin - shoulder|² = D² + d5² + 2 d5 D k cos(θ6 - γ) within the 2R reach
        den = 2.0 * d5 * D * k
        # the reachable θ6: [lo, hi] with ends where the arm is stretched or folded, or the
        # whole circle (periodic)
        periodic = False
        if den < 1e-15:
            periodic, intervals = True, [(gamma - math.pi, gamma + math.pi)]
        else:
            lo_c = ((a2 - a3) ** 2 - D * D - d5 * d5) / den
            hi_c = ((a2 + a3) ** 2 - D * D - d5 * d5) / den
            if lo_c > 1.0 + _CLIP_EPS or hi_c < -1.0 - _CLIP_EPS:
                return []
            near = math.acos(min(max(hi_c, -1.0), 1.0))
            far = math.acos(min(max(lo_c, -1.0), 1.0))
            if hi_c >= 1.0 and lo_c <= -1.0:
                periodic, intervals = True, [(gamma - math.pi, gamma + math.pi)]
            elif hi_c >= 1.0:
                intervals = [(gamma - far, gamma + far)]
            elif lo_c <= -1.0:
                intervals = [(gamma + near, gamma + TWO_PI - near)]
            else:
                intervals = [(gamma + near, gamma + far), (gamma - far, gamma - near)]

        _, g2, g3, g4, _, g6 = seed
        lims = self._lo_hi
        (lo2, hi2), (lo3, hi3), (lo4, hi4), (lo6, hi6) = lims[1], lims[2], lims[3], lims[5]
        sigma = ay * bx - ax * by  # dθ234/dθ6: ±1 at the singularity
        sg = 1.0 if sigma >= 0.0 else -1.0
        t234_0 = math.atan2(c5 * ay - s5 * zy, c5 * ax - s5 * zx)
        k3 = 1.0 / (2.0 * a2 * a3)
        l3 = a2 * a2 + a3 * a3
        tau, inv = TWO_PI, _INV_TWO_PI
        sin, cos, atan2, sqrt = math.sin, math.cos, math.atan2, math.sqrt

        def ev(t: float, e: float) -> _Ev | None:
            """f, f', f'' (Newton), 2 Σ θj'² (Gauss-Newton), then θ2, θ3, θ4 shifted
            toward the seed and their derivatives; None where out of reach or limits."""
            s, c = sin(t), cos(t)
            u, v = c * ax - s * bx, c * ay - s * by
            dx, dy = d5 * (s * ax + c * bx), d5 * (s * ay + c * by)
            X, Y = X5 + dx, Y5 + dy
            r2 = X * X + Y * Y
            c3 = (r2 - l3) * k3
            if c3 > 1.0 or c3 < -1.0:
                if abs(c3) > 1.0 + _CLIP_EPS:
                    return None
                c3 = 1.0 if c3 > 0.0 else -1.0
            s3 = e * sqrt(1.0 - c3 * c3)
            t3 = atan2(s3, c3)
            t2 = atan2(Y, X) - atan2(a3 * s3, a2 + a3 * c3)
            t4 = atan2(c5 * v - s5 * zy, c5 * u - s5 * zx) - t2 - t3
            w2 = t2 + tau * (((g2 - t2) * inv + 0.5) // 1.0)
            if not lo2 <= w2 <= hi2:
                w2 = _near(t2, g2, lo2, hi2)
                if w2 != w2:
                    return None
            w3 = t3 + tau * (((g3 - t3) * inv + 0.5) // 1.0)
            if not lo3 <= w3 <= hi3:
                w3 = _near(t3, g3, lo3, hi3)
                if w3 != w3:
                    return None
            w4 = t4 + tau * (((g4 - t4) * inv + 0.5) // 1.0)
            if not lo4 <= w4 <= hi4:
                w4 = _near(t4, g4, lo4, hi4)
                if w4 != w4:
                    return None
            w6 = t + tau * (((g6 - t) * inv + 0.5) // 1.0)
            if not lo6 <= w6 <= hi6:
                w6 = _near(t, g6, lo6, hi6)
                if w6 != w6:
                    return None
            e2, e3, e4, e6 = w2 - g2, w3 - g3, w4 - g4, w6 - g6
            fv = e2 * e2 + e3 * e3 + e4 * e4 + e6 * e6
            if s3 == 0.0:  # at an end of the interval: the derivatives are infinite
                return fv, 0.0, 0.0, 0.0, w2, w3, w4, 0.0, 0.0, 0.0, w6
            # derivatives: X' = d5 u, Y' = d5 v, X'' = -dx, Y'' = -dy
            Xd, Yd = d5 * u, d5 * v
            r2d = 2.0 * (X * Xd + Y * Yd)
            c3d = r2d * k3
            c3dd = 2.0 * k3 * (Xd * Xd + Yd * Yd - X * dx - Y * dy)
            d3 = -c3d / s3
            d3d = -(c3dd + c3 * d3 * d3) / s3
            bd = (X * Yd - Y * Xd) / r2
            bdd = (Y * dx - X * dy) / r2 - bd * r2d / r2
            q = a3 * (a2 * c3 + a3)
            betad = q * d3 / r2
            betadd = (a3 * a2 * c3d * d3 + q * d3d) / r2 - betad * r2d / r2
            d2 = bd - betad
            d2d = bdd - betadd
            d4 = sigma - d2 - d3
            d4d = -d2d - d3d
            hg = 2.0 * (d2 * d2 + d3 * d3 + d4 * d4 + 1.0)
            return (
                fv,
                2.0 * (e2 * d2 + e3 * d3 + e4 * d4 + e6),
                hg + 2.0 * (e2 * d2d + e3 * d3d + e4 * d4d),
                hg,
                w2,
                w3,
                w4,
                d2,
                d3,
                d4,
                w6,
            )

        # On an interval with ends, Newton steps in u, t = lo + span·sin²u (smooth in u at
        # the ends, where θ3 has an infinite slope in t); on the whole circle, in t itself.
        umin, umax = 1e-9, 0.5 * math.pi - 1e-9

        def t_of(u: float, lo: float, span: float) -> float:
            return u if periodic else lo + span * sin(u) ** 2

        def u_of(t: float, lo: float, span: float) -> float:
            if periodic:
                return t
            x = (t - lo) / span if span > 0.0 else 0.0
            return min(max(math.asin(math.sqrt(min(max(x, 0.0), 1.0))), umin), umax)

        def flip_point(
            u: float, beyond: float, cur: _Ev, e: float, lo: float, span: float
        ) -> float:
            """The u nearest ``beyond`` on ``u``'s side of a 2π-shift flip (or of the reach
            or a limit: ``ev`` None) between them, to ~1e-15 rad of u."""
            for _ in range(_FLIP_BISECTIONS):
                mid = 0.5 * (u + beyond)
                if mid in (u, beyond):
                    break
                at = ev(t_of(mid, lo, span), e)
                if at is None or _shift_flipped(cur, at):
                    beyond = mid
                else:
                    u = mid
            return u

        def descend(u: float, cur: _Ev, e: float, lo: float, span: float) -> tuple[float, float]:
            """Newton steps on f from u (:func:`newton_u`); from an end they stop at (f' is 0
            there in u), from the lowest of points _END_PROBES of u inside it too."""
            u, t, cur = newton_u(u, cur, e, lo, span)
            if periodic or umin < u < umax:
                return cur[0], t
            inner: tuple[float, _Ev] | None = None
            for p in _END_PROBES:
                pu = u + p if u <= umin else u - p
                c = ev(t_of(pu, lo, span), e)
                if c is not None and c[0] < cur[0] and (inner is None or c[0] < inner[1][0]):
                    inner = (pu, c)
            if inner is not None:
                _, it, ic = newton_u(inner[0], inner[1], e, lo, span)
                if ic[0] < cur[0]:
                    return ic[0], it
            return cur[0], t

        def newton_u(
            u: float, cur: _Ev, e: float, lo: float, span: float
        ) -> tuple[float, float, _Ev]:
            """Newton steps on f from u; a step stops short of a joint limit."""
            t = t_of(u, lo, span)
            for _ in range(20):
                fv, g, h, hg, w2, w3, w4, d2, d3, d4, w6 = cur
                if periodic:
                    tu, tuu = 1.0, 0.0
                else:
                    tu, tuu = span * sin(2.0 * u), 2.0 * span * cos(2.0 * u)
                hgu = hg * tu * tu
                if hgu <= 0.0:
                    break
                hu = h * tu * tu + g * tuu
                # at most _TRUST rad of θ6 per step (and 0.25 of u, where t(u) is flat)
                lim = min(0.25, _TRUST / abs(tu))
                if hu > 0.0:
                    step = -g * tu / hu
                    if g * tu * step > -_F_TOL * fv:  # converged: f within _F_TOL of itself
                        break
                    if abs(step) > lim:
                        step = math.copysign(lim, step)
                elif g == 0.0:
                    break
                else:  # concave (e.g. an end that is a maximum in u): the longest step, downhill
                    step = -math.copysign(lim, g * tu)
                if not periodic:
                    step = min(max(u + step, umin), umax) - u
                # a joint reaching its limit would jump to its far equivalent: stop short
                for w, d, jl, jh in (
                    (w2, d2 * tu, lo2, hi2),
                    (w3, d3 * tu, lo3, hi3),
                    (w4, d4 * tu, lo4, hi4),
                    (w6, tu, lo6, hi6),
                ):
                    nw = w + d * step
                    if nw > jh >= w:
                        step = _CUT * (jh - w) / d
                    elif nw < jl <= w:
                        step = _CUT * (jl - w) / d
                for _ in range(6):
                    nu = u + step
                    nt = t_of(nu, lo, span)
                    new = ev(nt, e)
                    if new is not None and new[0] <= fv:
                        break
                    if new is None or _shift_flipped(cur, new):
                        # past a point where a joint's 2π shift toward the seed flips at a
                        # limit (f's minimum can be right there, next to a stretched end
                        # where θ2, θ3 swing fast): the last u before it, by bisection
                        nu = flip_point(u, nu, cur, e, lo, span)
                        nt = t_of(nu, lo, span)
                        new = ev(nt, e)
                        if new is not None and new[0] <= fv:
                            break
                    step *= 0.25
                else:
                    break
                moved = abs(nu - u)
                u, t, cur = nu, nt, new
                if moved < 1e-10:
                    break
            return u, t, cur

        # Candidates besides the Newton minima: the interval ends, and the points where a
        # joint reaches a limit (there the 2π shift jumps: f can have its minimum right at
        # such a point). In the plane (complex numbers), o4 = W + d5·N·e^{i·t234} with
        # N = ±i and t234 = t234(0) + σ·t, so each of these points is a root of
        # cos(t234 + const) = const: a joint at value L is
        #   θ6: t = L;  θ3: |o4| fixed;  θ2: |o4 - a2·e^{iL}| = |a3|;
        #   θ4: o3 = o4 - a3·e^{i(t234 - L)} = W + (d5·N - a3·e^{-iL})·e^{i·t234}, |o3| = |a2|.
        Nc = complex(0.0, -sg * (1.0 if c5 >= 0.0 else -1.0))
        Wc = complex(X5, Y5)
        roots: list[tuple[float, float]] = []  # (t234, elbow sign or 0 = both)

        def circle(centre: complex, rot: complex, target: float) -> list[float]:
            """t234 where |centre + rot·e^{i·t234}| = target (rot ≠ 0)."""
            r, m = abs(centre), abs(rot)
            if r * m < 1e-15:
                return []
            kc = (target * target - r * r - m * m) / (2.0 * r * m)
            if not -1.0 <= kc <= 1.0:
                return []
            base_ = cmath.phase(centre) - cmath.phase(rot)
            dlt = math.acos(kc)
            return [base_ + dlt, base_ - dlt]

        def elbow_of(o3: complex, o4: complex) -> float:
            x = (o3.conjugate() * (o4 - o3)).imag
            return 1.0 if x > 0.0 else -1.0

        for levels, kind in (
            (_jumps(g2, lo2, hi2, True), 2),
            (_jumps(g3, lo3, hi3, True), 3),
            (_jumps(g4, lo4, hi4, False), 4),
        ):
            flip = g2 + math.pi if kind == 2 else g3 + math.pi if kind == 3 else math.nan
            for L in levels:
                sides = (-1e-6, 1e-6) if flip == L else (0.0,)
                if kind == 2:
                    o3 = a2 * cmath.exp(1j * L)
                    for r in circle(Wc - o3, d5 * Nc, abs(a3)):
                        ee = elbow_of(o3, Wc + d5 * Nc * cmath.exp(1j * r))
                        roots += [(r + dr, ee) for dr in sides]
                elif kind == 3:
                    sl = math.sin(L)
                    if abs(sl) > 1e-9:
                        reach = math.sqrt(l3 + 2.0 * a2 * a3 * math.cos(L))
                        for r in circle(Wc, d5 * Nc, reach):
                            roots += [(r + dr, 1.0 if sl > 0.0 else -1.0) for dr in sides]
                else:
                    rot = d5 * Nc - a3 * cmath.exp(-1j * L)
                    for r in circle(Wc, rot, abs(a2)):
                        e4 = cmath.exp(1j * r)
                        o4 = Wc + d5 * Nc * e4
                        roots.append((r, elbow_of(o4 - a3 * e4 * cmath.exp(-1j * L), o4)))
        extra = [(sg * (r - t234_0), e) for r, e in roots]
        extra += [(L, 0.0) for L in _jumps(g6, lo6, hi6, False)]

        # f on a grid in u (in t on the whole circle) and at the limit points, both elbows
        # at once (t234 = t234(0) + σ·t: exact at the singularity, off by ~|s5| next to it,
        # where the candidates are only a guide, checked on :meth:`_arm`'s solutions)
        consts = (X5, Y5, d5 * ax, d5 * bx, d5 * ay, d5 * by, l3, k3, a2, a3, t234_0, sg)
        goals = (g2, g3, g4, g6)
        bounds = (lo2, hi2, lo3, hi3, lo4, hi4, lo6, hi6)
        # no start or candidate above the bound + _MARGIN is ever used: the grid skips them
        cap = bound + _MARGIN
        grids = []
        for lo, hi in intervals:
            span = hi - lo
            # about _GRID_STEP rad of θ6 apart at most (u = π/4 ± π/(4n) maps to
            # span·sin(π/(2n)) ≤ span·π/(2n) of t); as dense on the whole circle (spaced
            # by _GRID_STEP it misses minima)
            n = max(4, math.ceil(math.pi * span / (2.0 * _GRID_STEP)))
            if periodic:
                us = tgrid = [lo + i * tau / n for i in range(n)]
            else:
                us = [i * (0.5 * math.pi) / n for i in range(n + 1)]  # the ends exactly
                tgrid = [lo + span * q for q in _sin2(n)]
            grids.append((lo, span, us, *_continuum_f(tgrid, consts, goals, bounds, cap)))
        at = [
            (ee, tt, lo, hi - lo)
            for t, ee in extra
            for lo, hi in intervals
            if (tt := _within(t, lo, hi, periodic)) == tt
        ]
        fat = _continuum_f([a[1] for a in at], consts, goals, bounds, cap)
        ends: set[float] = set()
        if not periodic:
            for lo, hi in intervals:
                ends |= {lo, hi, t_of(0.5 * math.pi, lo, hi - lo)}
        elbows = []
        inf = math.inf
        for ie, e in enumerate((1.0, -1.0)):
            spots = [
                (fs, ts, lo, span)
                for (ee, ts, lo, span), fs in zip(at, fat[ie], strict=True)
                if (ee == 0.0 or ee == e) and fs < inf
            ]
            starts: list[tuple[float, float, float, float]] = []  # f, u, lo, span
            for lo, span, us, *vals2 in grids:
                # Newton from the grid's local minima
                vals = vals2[ie]
                if periodic:
                    left, right = vals[-1:] + vals[:-1], vals[1:] + vals[:1]
                else:
                    left, right = [inf, *vals[:-1]], [*vals[1:], inf]
                minima = [
                    i
                    for i, (fc, fl, fr) in enumerate(zip(vals, left, right, strict=True))
                    if fc <= fl and fc <= fr and fc < inf
                ]
                starts += [(vals[i], us[i], lo, span) for i in minima]
                # a dip between two grid points beside a minimum, the nearer one higher:
                # where f still falls at the neighbour, going on away from the minimum,
                # Newton's steps start there too (a dip 0.07 rad of θ6 past the neighbour of
                # a stretched end, 5e-4 rad nearer the seed, was missed; Hypothesis)
                floor = min(vals) + _MARGIN  # above it no start is descended (see below)
                for i in minima:
                    for j, away in ((i - 1, -1.0), (i + 1, 1.0)):
                        if periodic:
                            j %= len(us)
                        elif not 0 <= j < len(us):
                            continue
                        if not vals[j] <= floor:
                            continue
                        uj = us[j] if periodic else min(max(us[j], umin), umax)
                        c = ev(t_of(uj, lo, span), e)
                        if c is None:
                            continue
                        tu = 1.0 if periodic else span * sin(2.0 * uj)
                        if c[1] * tu * away < 0.0:
                            starts.append((vals[j], uj, lo, span))
                if not periodic:
                    # an end is a critical point of f in u: a minimum in the end's first
                    # cell, past a rise, is reached from the cell's middle, not from the end
                    last = len(us) - 1
                    for i, j in ((0, 1), (last, last - 1)):
                        if vals[i] < inf and vals[i] <= vals[j]:
                            starts.append((vals[i], 0.5 * (us[i] + us[j]), lo, span))
            starts.sort()
            spots.sort()
            lowest = min(starts[0][0] if starts else math.inf, spots[0][0] if spots else math.inf)
            elbows.append((lowest, e, starts, spots))
        if nearest_only:
            elbows.sort()

        def best_at(
            t: float, fv: float, e: float, chosen: tuple[float, list[float]] | None
        ) -> tuple[float, list[float]] | None:
            """The solution at θ6 = ``t`` (elbow ``e``, f ``fv`` there) nearer the seed than
            ``chosen`` (Σ over θ2, θ3, θ4, θ6 first), or None."""
            found: list[list[float]] = []
            self._arm(f, p5x, p5y, p5z, t1, s1, c1, s5, c5, t, found, int(e))
            if found and t in ends and abs(sin(found[0][2])) < 1e-6:
                # at an end rounding leaves the arm ~1e-16 short of the stretch (or fold),
                # which is θ3 ~1e-8 off it: also θ3 on it, θ2 and θ4 turned to match
                q1, q2, q3, q4, q5, q6 = found[0]
                base = q2 + atan2(a3 * sin(q3), a2 + a3 * cos(q3))
                q3s = 0.0 if cos(q3) > 0.0 else math.copysign(math.pi, q3)
                q2s = base - atan2(0.0, a2 + a3 * cos(q3s))
                found.append([q1, q2s, q3s, q4 + q2 + q3 - q2s - q3s, q5, q6])
            better: tuple[float, list[float]] | None = None
            lowest = math.inf

            def rank(sol: list[float]) -> float:
                """``sol`` shifted toward the seed, kept in ``better`` if nearer; its
                distance² less the θ1, θ5 terms (the same for every t), inf if none fits."""
                nonlocal better
                if (shifted := self._nearest(sol, seed)) is None:
                    return math.inf
                g = shifted[1]
                rest = shifted[0] - (g[0] - seed[0]) ** 2 - (g[4] - seed[4]) ** 2
                if (chosen is None or rest < chosen[0]) and (better is None or rest < better[0]):
                    better = (rest, g)
                return rest

            for sol in found:
                lowest = min(lowest, rank(sol))
            if found and lowest > fv + _SHIFT_SLIP and (c := ev(t, e)) is not None:
                # next to a stretch the closed form's rounding (~1e-16/|sin θ3|) can put a
                # joint at a limit (a flip point) beyond it by more than _LIMIT_EPS, where
                # its shift toward the seed flips: the joints f was found on, then
                rank([found[0][0], c[4], c[5], c[6], found[0][4], c[10]])
            return better

        out: list[list[float]] = []
        for _, e, starts, spots in elbows:
            tried: list[tuple[float, float]] = []
            top = bound  # the best found so far
            for fs, u, lo, span in starts:
                tried.append((fs, t_of(u, lo, span)))
                if not periodic:
                    u = min(max(u, umin), umax)
                if fs <= top + _MARGIN and (c := ev(t_of(u, lo, span), e)) is not None:
                    res = descend(u, c, e, lo, span)
                    tried.append(res)
                    top = min(top, res[0])
            # descend from the best end or limit point too
            spots.sort()
            for i, (fs, ts, los, spans) in enumerate(spots):
                tried.append((fs, ts))
                u = u_of(ts, los, spans)
                if (
                    i < _SPOTS
                    and fs <= top + _MARGIN
                    and (c := ev(t_of(u, los, spans), e)) is not None
                ):
                    tried.append(descend(u, c, e, los, spans))
            # the best by f, checked on the solution itself (at an end or a limit the
            # rounding of the closed form can land on the other side of a 2π jump)
            tried.sort()
            chosen: tuple[float, list[float]] | None = None
            ranked: set[float] = set()
            for fv, t in tried:
                if fv > bound or (chosen is not None and fv >= chosen[0] - 1e-12):
                    break
                ranked.add(t)
                better = best_at(t, fv, e, chosen)
                if better is not None:
                    chosen = better
            if not periodic:
                # an end's joints with θ3 on the stretch (or fold) can lie in a sliver of
                # ~1e-15 of θ6 where a shift sits at its limit, nearer than f on the grid
                # around it says (both θ2 and θ3 at 2π there, f 21.2 next to it; Hypothesis)
                for ends_of in intervals:
                    for t in ends_of:
                        if t in ranked:
                            continue  # ranked above already
                        better = best_at(t, math.inf, e, chosen)
                        if better is not None and better[0] <= bound:
                            chosen = better
            if chosen is not None:
                out.append(chosen[1])
                if nearest_only:
                    bound = min(bound, chosen[0])
        return out

    def _nearest(self, sol: list[float], seed: list[float]) -> tuple[float, list[float]] | None:
        """The 2π-equivalent of ``sol`` nearest ``seed`` within the limits, and its distance²."""
        total = 0.0
        out = []
        for v, s, (lo, hi) in zip(sol, seed, self._lo_hi, strict=True):
            w = _near(v, s, lo, hi)
            if w != w:  # NaN: no equivalent within the limits
                return None
            total += (w - s) * (w - s)
            out.append(w)
        return total, out

    def _fast_nearest(self, target: Pose, seed: list[float]) -> list[float] | None:
        """The hot path of :meth:`inverse`: the nearest solution without building every branch
        (see :meth:`nearest_and_runner_up`)."""
        return self.nearest_within(target, seed, 0.0)[0]

    def nearest_within(
        self, target: Pose, seed: list[float], margin: float, lenient: bool = False
    ) -> tuple[list[float] | None, list[tuple[float, list[float]]], float, bool]:
        """The solution nearest ``seed`` (None: see below); with ``margin`` > 0 (rad,
        Euclidean) also every solution whose distance from the seed is within ``margin`` of
        the nearest one's, as (distance², joints) nearest first, and a bound: every other
        solution's distance² is at least the third value; fourth, whether a branch not pruned
        misses full stretch or fold by less than _EDGE_C3 (in cos θ3): slightly other arm
        lengths would reach it. ``margin`` 0 is :meth:`inverse`'s
        hot path. The calibrated inverse (:mod:`fxcell.motion.calibration`) refines the
        solutions within the margin, which the deltas may reorder.

        Same result as ranking :meth:`_branches` with :meth:`_nearest`, with shared terms
        computed once per shoulder and wrist branch, branches pruned as soon as their
        partial distance exceeds the best (plus the margin), and the 2π shift toward the seed
        inlined (``_near`` only when the shifted angle leaves the limits); an exactly wrist-singular
        shoulder goes to :meth:`_singular_arms` last, unless the others' best already beats
        its θ1 and θ5 alone. Returns None, to fall back on the general path, next to the
        singularities that need its special handling (polishing) or when nothing fits.

        ``lenient`` (starting points for the calibrated inverse, not solutions): a target
        a little beyond the nominal reach (within _EDGE_C3·d4² in h² beyond the shoulder
        singularity, within _EDGE_C3 in cos θ3 beyond full stretch or fold), or next to it,
        gets branches with the arm bent by _LENIENT_BEND (θ3 ≈ ±_LENIENT_BEND; the wrist
        centre that far from the shoulder singularity, both sides), so the branches the
        deltas make on either side each have a start; a shoulder branch within
        _LENIENT_WRIST of the wrist singularity also gets members of its continuum
        (:meth:`_continuum_starts`, not the nearest: the refinement walks the valley).
        """
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = target._R.tolist()
        px, py, pz = target._p.tolist()
        if not self._tcp_is_identity:  # flange = target · tcp⁻¹, written out
            b00, b01, b02, b10, b11, b12, b20, b21, b22, bx, by, bz = self._tcp_inv
            px, py, pz = (
                r00 * bx + r01 * by + r02 * bz + px,
                r10 * bx + r11 * by + r12 * bz + py,
                r20 * bx + r21 * by + r22 * bz + pz,
            )
            r00, r01, r02 = (
                r00 * b00 + r01 * b10 + r02 * b20,
                r00 * b01 + r01 * b11 + r02 * b21,
                r00 * b02 + r01 * b12 + r02 * b22,
            )
            r10, r11, r12 = (
                r10 * b00 + r11 * b10 + r12 * b20,
                r10 * b01 + r11 * b11 + r12 * b21,
                r10 * b02 + r11 * b12 + r12 * b22,
            )
            r20, r21, r22 = (
                r20 * b00 + r21 * b10 + r22 * b20,
                r20 * b01 + r21 * b11 + r22 * b21,
                r20 * b02 + r21 * b12 + r22 * b22,
            )
        d1, d4, d5, d6, a2, a3 = self._geom
        s0, s1_, s2, s3, s4, s5 = seed
        (lo0, hi0), (lo1, hi1), (lo2, hi2), (lo3, hi3), (lo4, hi4), (lo5, hi5) = self._lo_hi
        tau, inv = TWO_PI, _INV_TWO_PI
        atan2, sqrt = math.atan2, math.sqrt
        p5x, p5y, p5z = px - d6 * r02, py - d6 * r12, pz - d6 * r22
        rho2 = p5x * p5x + p5y * p5y
        h2 = rho2 - d4 * d4
        clamped = False
        if lenient and h2 < _LENIENT_H2 * d4 * d4:
            if h2 < -_EDGE_C3 * d4 * d4 or rho2 == 0.0:
                return None, [], math.inf, True
            h2 = _LENIENT_H2 * d4 * d4
            clamped = True
        if h2 < 0.0:  # beyond the shoulder singularity by rounding, or out of reach
            if h2 < -_CLIP_EPS * d4 * d4:
                return None, [], math.inf, True
            h2 = 0.0
        h = sqrt(h2)
        # (c1, sn1) has norm √((h² + d4²) / rho2): 1 but for a clipped h2
        norm = rho2 if h2 > 1e-12 and not clamped else sqrt(rho2 * (h2 + d4 * d4))
        k3 = 1.0 / (2.0 * a2 * a3)
        l3 = a2 * a2 + a3 * a3
        best = cut = math.inf
        best_q: list[float] | None = None
        found: list[tuple[float, list[float]]] = []
        near_miss = False
        edge = False
        shoulders = []
        # next to the shoulder singularity θ1 carries rounding error amplified ~1/h, but
        # the pose reached moves only to second order: the two branches nearly coincide
        for hs in (h, -h) if h > 0.0 else (h,):
            c1 = (p5x * hs - p5y * d4) / norm
            sn1 = (p5y * hs + p5x * d4) / norm
            t = atan2(sn1, c1)
            v1 = t + tau * (((s0 - t) * inv + 0.5) // 1.0)
            if not lo0 <= v1 <= hi0:
                v1 = _near(t, s0, lo0, hi0)
                if v1 != v1:
                    continue
            shoulders.append(((v1 - s0) * (v1 - s0), v1, c1, sn1, t))
        if len(shoulders) == 2 and shoulders[1][0] < shoulders[0][0]:
            shoulders.reverse()  # nearest θ1 first: the pruning bites early
        singular = []
        for e1, v1, c1, sn1, t1 in shoulders:
            if e1 >= cut:
                continue
            zx = r00 * sn1 - r10 * c1
            zy = r01 * sn1 - r11 * c1
            zz = r02 * sn1 - r12 * c1
            s5a = sqrt(zx * zx + zy * zy)
            if s5a <= _WRIST_EPS or (lenient and s5a < _LENIENT_WRIST):
                # exactly singular; or, for starting points, close enough that the deltas
                # can put the calibrated solutions anywhere along the continuum
                singular.append((e1, t1, c1, sn1, 1.0 if zz >= 0.0 else -1.0))
                if s5a <= _WRIST_EPS:
                    continue
            # next to the wrist or shoulder singularity θ6 or θ1 carries amplified rounding
            # error: a stretched arm can then miss its reach, which the general path fixes
            slack = _rounding_slack(s5a, h)
            c6, sn6 = zx / s5a, -zy / s5a
            t6 = atan2(-zy, zx)
            t5 = atan2(s5a, zz)
            z4x = -(sn6 * r00 + c6 * r01)
            z4y = -(sn6 * r10 + c6 * r11)
            z4z = -(sn6 * r20 + c6 * r21)
            u, v, w = zz * c6, -zz * sn6, -s5a
            x4x = r00 * u + r01 * v + r02 * w
            x4y = r10 * u + r11 * v + r12 * w
            x4z = r20 * u + r21 * v + r22 * w
            x4p = c1 * x4x + sn1 * x4y
            # the two wrists: (θ5, θ6) and (-θ5, θ6 + π), which turns z4 and x4 over;
            # the one nearer the seed first
            wrists = []
            for sign, t5w, t6w in ((1.0, t5, t6), (-1.0, -t5, t6 + math.pi)):
                v5 = t5w + tau * (((s4 - t5w) * inv + 0.5) // 1.0)
                if not lo4 <= v5 <= hi4:
                    v5 = _near(t5w, s4, lo4, hi4)
                    if v5 != v5:
                        continue
                v6 = t6w + tau * (((s5 - t6w) * inv + 0.5) // 1.0)
                if not lo5 <= v6 <= hi5:
                    v6 = _near(t6w, s5, lo5, hi5)
                    if v6 != v6:
                        continue
                wrists.append((e1 + (v5 - s4) * (v5 - s4) + (v6 - s5) * (v6 - s5), sign, v5, v6))
            if len(wrists) == 2 and wrists[1][0] < wrists[0][0]:
                wrists.reverse()
            for e6, sign, v5, v6 in wrists:
                if e6 >= cut:
                    continue
                t234 = atan2(sign * x4z, sign * x4p)
                sd5 = sign * d5
                ox, oy, oz = p5x - sd5 * z4x, p5y - sd5 * z4y, p5z - sd5 * z4z
                X = c1 * ox + sn1 * oy
                Y = oz - d1
                c3 = (X * X + Y * Y - l3) * k3
                if lenient and abs(c3) > _LENIENT_C3:
                    if abs(c3) >= 1.0 + _EDGE_C3:
                        continue
                    c3 = _LENIENT_C3 if c3 > 0.0 else -_LENIENT_C3
                if c3 > 1.0 or c3 < -1.0:
                    if margin > 0.0 and abs(c3) < 1.0 + _EDGE_C3:
                        edge = True
                    if abs(c3) > 1.0 + _CLIP_EPS:
                        miss = abs(c3) - 1.0
                        near_miss = near_miss or miss <= slack
                        continue
                    c3 = 1.0 if c3 > 0.0 else -1.0
                s3a = sqrt(1.0 - c3 * c3)
                base = atan2(Y, X)
                g = atan2(a3 * s3a, a2 + a3 * c3)
                t3 = atan2(s3a, c3)
                for t2, t3e in ((base - g, t3), (base + g, -t3)):
                    v2 = t2 + tau * (((s1_ - t2) * inv + 0.5) // 1.0)
                    if not lo1 <= v2 <= hi1:
                        v2 = _near(t2, s1_, lo1, hi1)
                        if v2 != v2:
                            continue
                    e = e6 + (v2 - s1_) * (v2 - s1_)
                    if e >= cut:
                        continue
                    v3 = t3e + tau * (((s2 - t3e) * inv + 0.5) // 1.0)
                    if not lo2 <= v3 <= hi2:
                        v3 = _near(t3e, s2, lo2, hi2)
                        if v3 != v3:
                            continue
                    t4 = t234 - t2 - t3e
                    v4 = t4 + tau * (((s3 - t4) * inv + 0.5) // 1.0)
                    if not lo3 <= v4 <= hi3:
                        v4 = _near(t4, s3, lo3, hi3)
                        if v4 != v4:
                            continue
                    e += (v3 - s2) * (v3 - s2) + (v4 - s3) * (v4 - s3)
                    if e < cut:
                        sol = [v1, v2, v3, v4, v5, v6]
                        if margin > 0.0:
                            found.append((e, sol))
                        if e < best:
                            best, best_q = e, sol
                            cut = best if margin == 0.0 else (sqrt(best) + margin) ** 2
        if near_miss and not lenient:
            return None, found, math.inf, True
        # exactly wrist singular (θ5 = 0 or π, θ6 free), last: the others' best prunes it
        for e1, t1, c1, sn1, c5 in singular:
            v5 = _near(0.0 if c5 > 0.0 else math.pi, s4, lo4, hi4)
            if v5 != v5:
                continue
            e5 = e1 + (v5 - s4) * (v5 - s4)
            if e5 >= cut:
                continue
            f = [r00, r01, r02, r10, r11, r12, r20, r21, r22, px, py, pz]
            if lenient:  # starting points: members the refinement walks the valley from
                sols = self._continuum_starts(f, p5x, p5y, p5z, t1, sn1, c1, c5, seed)
            else:
                sols = self._singular_arms(
                    f, p5x, p5y, p5z, t1, sn1, c1, 0.0, c5, seed, cut - e5, nearest_only=True
                )
            for sol in sols:
                ranked = self._nearest(sol, seed)
                if ranked is None or ranked[0] >= cut:
                    continue
                if margin > 0.0:
                    found.append(ranked)
                if ranked[0] < best:
                    best, best_q = ranked
                    cut = best if margin == 0.0 else (sqrt(best) + margin) ** 2
        if margin > 0.0:
            found = sorted(c for c in found if c[0] < cut)
        return best_q, found, cut, edge

    def inverse(
        self,
        pose: Pose | Sequence[float],
        seed: ArrayLike | None = None,
        *,
        valid: JointValidity | None = None,
        singularity_margin: float | None = None,
        refine: bool = False,
    ) -> FloatArray:
        """Joint positions reaching ``pose`` (TCP, base frame), nearest ``seed`` within limits.

        Nearest = smallest Euclidean distance in joint space, over the closed-form branches
        and their 2π shifts. ``valid`` (e.g. a collision check) rejects candidates; the
        nearest accepted one is returned. ``singularity_margin`` rejects candidates that
        close to a singularity (see :meth:`singularity`; the same value is used as metres
        and as sine). ``refine`` adds Newton steps (the closed form is already exact to
        rounding error). ``pose`` may be anything :meth:`Pose.parse` accepts.

        Raises :class:`UnreachableError` when no solution is within reach and the limits or
        accepted by ``valid``, :class:`SingularityError` when the only solutions left are
        singular.
        """
        target = pose if isinstance(pose, Pose) else Pose.parse(pose)
        s = [0.0] * 6 if seed is None else _joints(seed)
        if valid is None and singularity_margin is None and not refine:
            fast = self._fast_nearest(target, s)
            if fast is not None:
                return np.array(fast)
        branches = self._branches(target, s)
        if not branches:
            raise UnreachableError(f"pose out of reach of the arm: {target!r}")
        ranked = sorted(c for c in (self._nearest(b, s) for b in branches) if c)
        if not ranked:
            raise UnreachableError(
                f"no inverse-kinematics solution within the joint limits: {target!r}"
            )
        singular: str | None = None
        rejected = 0
        for _, sol in ranked:
            q = np.array(sol)
            if singularity_margin is not None:
                kind = self.singularity(q, distance=singularity_margin, sine=singularity_margin)
                if kind is not None:
                    singular = singular or kind
                    continue
            if valid is not None and not valid(q):
                rejected += 1
                continue
            return self.refine(q, target) if refine else q
        if rejected == 0 and singular is not None:
            raise SingularityError(
                f"every inverse-kinematics solution for {target!r} is within "
                f"{singularity_margin} of a singularity (the nearest: {singular})"
            )
        raise UnreachableError(
            f"{len(ranked)} inverse-kinematics solutions within the joint limits, "
            f"none accepted by the validity check, for {target!r}"
        )

    def inverse_near(self, pose: Pose, seed: ArrayLike) -> FloatArray:
        """The solution continuous with ``seed`` (a path's next point): the closed form's
        nearest, as :meth:`inverse`."""
        return self.inverse(pose, seed)

    def inverse_all(
        self, pose: Pose | Sequence[float], seed: ArrayLike | None = None
    ) -> list[FloatArray]:
        """One solution per closed-form branch that fits the limits (up to 8; branches that
        coincide at a singularity once), each the 2π-equivalent nearest ``seed`` (default:
        zeros), sorted by distance to it."""
        target = pose if isinstance(pose, Pose) else Pose.parse(pose)
        s = [0.0] * 6 if seed is None else _joints(seed)
        ranked = sorted(c for c in (self._nearest(b, s) for b in self._branches(target, s)) if c)
        out: list[FloatArray] = []
        kept: list[list[float]] = []
        for _, sol in ranked:  # branches coincide at singularities: keep one of each
            # every joint within 1e-9 of a kept one's, on plain floats (a NumPy reduction per
            # pair cost ~60 µs per call, which the calibrated general path makes a dozen times)
            if not any(
                all(abs(v - w) < 1e-9 for v, w in zip(sol, other, strict=True)) for other in kept
            ):
                kept.append(sol)
                out.append(np.array(sol))
        return out

    def refine(self, q: ArrayLike, pose: Pose, *, iterations: int = 8) -> FloatArray:
        """Gauss-Newton steps on the TCP pose error from ``q``, damped Levenberg-Marquardt
        style near singularities; each accepted step lowers the error."""
        qq = np.array(_joints(q))
        err = _pose_error(self.forward(qq), pose)
        norm = float(np.linalg.norm(err))
        lam = 1e-14
        eye = np.eye(6)
        for _ in range(iterations):
            if norm < 1e-15:
                break
            J = self.jacobian(qq)
            JJt = J @ J.T
            while True:
                trial = qq + J.T @ np.linalg.solve(JJt + lam * eye, err)
                trial_err = _pose_error(self.forward(trial), pose)
                trial_norm = float(np.linalg.norm(trial_err))
                if trial_norm < norm:
                    qq, err, norm = trial, trial_err, trial_norm
                    lam = max(lam * 0.1, 1e-14)
                    break
                lam *= 10.0
                if lam > 1.0:
                    return qq
        return qq


class DHChain:
    """A 6R arm's standard DH chain with per-joint θ offsets (a calibrated UR arm) and a TCP:
    forward kinematics, geometric Jacobian and Newton steps, in plain floats.

    ``T_j = Rz(q_j + θ_j)·Tz(d_j)·Tx(a_j)·Rx(α_j)``; ``tcp`` is 12 floats (rotation row-major,
    then position) in the flange frame. The calibrated inverse
    (:class:`fxcell.motion.calibration.CalibratedKinematics`) refines the nominal closed form
    with :meth:`newton`: from a start a few millimetres off, three or four steps reach the
    rounding floor (~1e-15), about a microsecond each compiled.
    """

    def __init__(
        self,
        theta: Sequence[float],
        a: Sequence[float],
        d: Sequence[float],
        alpha: Sequence[float],
        tcp: Sequence[float],
    ) -> None:
        self._theta = [float(v) for v in theta]
        self._a = [float(v) for v in a]
        self._d = [float(v) for v in d]
        self._ca = [math.cos(float(v)) for v in alpha]
        self._sa = [math.sin(float(v)) for v in alpha]
        self._tcp = [float(v) for v in tcp]

    def frame(self, q: Sequence[float]) -> list[float]:
        """The TCP frame at ``q`` as 12 floats (rotation row-major, then position)."""
        return self._evaluate(q, None)

    def frame_and_jacobian(self, q: Sequence[float]) -> tuple[list[float], list[float]]:
        """The TCP frame (as :meth:`frame`) and the geometric Jacobian in the base frame,
        36 floats row-major (rows vx, vy, vz, wx, wy, wz)."""
        jac = [0.0] * 36
        return self._evaluate(q, jac), jac

    def _evaluate(self, q: Sequence[float], jac: list[float] | None) -> list[float]:
        # frame axes X, Y, Z and origin O, as columns; joint j turns about Z of frame j-1
        xx, xy, xz = 1.0, 0.0, 0.0
        yx, yy, yz = 0.0, 1.0, 0.0
        zx, zy, zz = 0.0, 0.0, 1.0
        ox, oy, oz = 0.0, 0.0, 0.0
        axes = [0.0] * 36  # z and origin of frame j-1 per joint (for the Jacobian)
        cos, sin = math.cos, math.sin
        for j in range(6):
            k = 6 * j
            axes[k] = zx
            axes[k + 1] = zy
            axes[k + 2] = zz
            axes[k + 3] = ox
            axes[k + 4] = oy
            axes[k + 5] = oz
            t = q[j] + self._theta[j]
            ct, st = cos(t), sin(t)
            ca, sa, a, d = self._ca[j], self._sa[j], self._a[j], self._d[j]
            ux, uy, uz = ct * xx + st * yx, ct * xy + st * yy, ct * xz + st * yz
            vx, vy, vz = ct * yx - st * xx, ct * yy - st * xy, ct * yz - st * xz
            ox, oy, oz = ox + a * ux + d * zx, oy + a * uy + d * zy, oz + a * uz + d * zz
            xx, xy, xz = ux, uy, uz
            yx, yy, yz, zx, zy, zz = (
                ca * vx + sa * zx,
                ca * vy + sa * zy,
                ca * vz + sa * zz,
                ca * zx - sa * vx,
                ca * zy - sa * vy,
                ca * zz - sa * vz,
            )
        t00, t01, t02, t10, t11, t12, t20, t21, t22, tx, ty, tz = self._tcp
        px = ox + xx * tx + yx * ty + zx * tz
        py = oy + xy * tx + yy * ty + zy * tz
        pz = oz + xz * tx + yz * ty + zz * tz
        out = [
            xx * t00 + yx * t10 + zx * t20,
            xx * t01 + yx * t11 + zx * t21,
            xx * t02 + yx * t12 + zx * t22,
            xy * t00 + yy * t10 + zy * t20,
            xy * t01 + yy * t11 + zy * t21,
            xy * t02 + yy * t12 + zy * t22,
            xz * t00 + yz * t10 + zz * t20,
            xz * t01 + yz * t11 + zz * t21,
            xz * t02 + yz * t12 + zz * t22,
            px,
            py,
            pz,
        ]
        if jac is not None:
            for j in range(6):
                k = 6 * j
                ax, ay, az = axes[k], axes[k + 1], axes[k + 2]
                rx, ry, rz = px - axes[k + 3], py - axes[k + 4], pz - axes[k + 5]
                jac[j] = ay * rz - az * ry
                jac[6 + j] = az * rx - ax * rz
                jac[12 + j] = ax * ry - ay * rx
                jac[18 + j] = ax
                jac[24 + j] = ay
                jac[30 + j] = az
        return out

    def newton(
        self,
        q: Sequence[float],
        target: Sequence[float],
        iterations: int = 20,
        converged: float = 1e-12,
        rounding: float = 1e-11,
        rejections: int = 0,
    ) -> tuple[list[float], float]:
        """Newton steps on the TCP pose error (position, rotation vector) from ``q`` toward
        ``target`` (12 floats as :meth:`frame`): the joints and the error norm left (m and
        rad together). A step that does not lower the error is retried damped
        (Levenberg-Marquardt), as next to a singularity; the steps stop below ``converged``,
        or below ``rounding`` when no step improves, or after a full step shorter than
        _FINAL_STEP, whose length squared is returned as the error (its order); with
        ``rejections`` > 0, at that many rejected steps (see _VALLEY_REJECTIONS)."""
        qq = [float(v) for v in q]
        rejected = 0
        frame, jac = self.frame_and_jacobian(qq)
        err = _twist_to(frame, target)
        norm = _norm6(err)
        lam = 0.0
        for _ in range(iterations):
            if norm < converged:
                break
            step = _solve6(jac, err, lam)
            if step is None:
                lam = max(lam, 1e-9)
                continue
            size = _norm6(step)
            if lam == 0.0 and size < _FINAL_STEP:
                # a full Newton step this short leaves an error of its square's order, far
                # below converged: taken without evaluating the chain again
                qq = [qq[k] + step[k] for k in range(6)]
                return qq, size * size
            trial = [qq[0] + step[0], qq[1] + step[1], qq[2] + step[2]]
            trial += [qq[3] + step[3], qq[4] + step[4], qq[5] + step[5]]
            frame, trial_jac = self.frame_and_jacobian(trial)
            trial_err = _twist_to(frame, target)
            trial_norm = _norm6(trial_err)
            if trial_norm < norm:
                qq, jac, err, norm = trial, trial_jac, trial_err, trial_norm
                lam = lam * 0.1 if lam > 1e-9 else 0.0
            else:
                if norm < rounding:  # at the rounding floor: no better step exists
                    break
                rejected += 1
                if rejected == rejections:
                    break
                lam = 1e-6 if lam == 0.0 else lam * 10.0
                if lam > 1.0:
                    break
        return qq, norm

    def settle(
        self,
        q: Sequence[float],
        target: Sequence[float],
        iterations: int = 60,
        converged: float = 1e-12,
        stationary: float = 1e-6,
        window: int = _STALL_STEPS,
        adaptive: bool = False,
    ) -> tuple[list[float], float, float]:
        """Levenberg-Marquardt (damping scaled by the diagonal of ``JᵀJ``) from ``q`` toward
        ``target``, for starts Newton's steps do not bring to a solution (next to a
        singularity): the joints, the error norm left and how far that point is from
        stationary, ``‖Jᵀe‖ / (‖J‖·‖e‖)``. A last value below ``stationary`` (where the steps
        stop) with an error left is a local minimum of the error: no solution near ``q`` (the
        target beyond this branch's reach, as a stretched arm's). With ``stationary`` > 0 an
        error that stalls far from a root (over ``window`` steps) ends the steps too, reported as
        stationary (0), and so does one that crawls into a root below _STALL_DONE.

        The damping ``lam`` starts at 1e-3; a rejected step multiplies it by 5 and an
        accepted one by 0.2, or, ``adaptive`` (the hot path, :meth:`nearest`), by Nielsen's
        rule (Madsen, Nielsen & Tingleff, *Methods for non-linear least squares problems*,
        2004, §3.2): an accepted step by ``max(1/3, 1 - (2ρ - 1)³)``, ρ the gain ratio
        (:func:`_gain_ratio`), so a step the linear model predicted well lowers the damping
        at once and a poor one raises it; rejected steps in a row by 2, 4, 8... Next to the
        shoulder singularity the fixed factors kept the damping too high where the model was
        good (runs crawling for hundreds of steps): on the bench's families (seed TCP, 400
        poses) chain evaluations per call p99 shoulder 1544 -> 608, wrist 1332 -> 790,
        limits 967 -> 482, no answer farther from the seed (one shoulder and one wrist answer
        nearer). The general path keeps the fixed factors (the bench's reference)."""
        qq = [float(v) for v in q]
        frame, jac = self.frame_and_jacobian(qq)
        err = _twist_to(frame, target)
        norm = _norm6(err)
        gradient = _gradient_ratio(jac, err, norm)
        lam = 1e-3
        grow = 2.0  # adaptive: the factor of lam at the next rejected step
        mark = norm  # the error at the start of the current _STALL_STEPS
        for it in range(iterations):
            if norm < converged or gradient < stationary:
                break
            if stationary > 0.0 and it > 0 and it % window == 0:
                if norm > _STALL_FLOOR and norm > (1.0 - _STALL_GAIN) * mark:
                    gradient = 0.0  # stalled far from a root: a local minimum's basin
                    break
                if norm < _STALL_DONE and norm > 0.5 * mark:
                    break  # crawling into a singular root: close enough
                mark = norm
            step = _solve6(jac, err, lam, True)
            if step is None:
                lam *= 5.0
                if lam > 1e9:
                    break
                continue
            trial = [qq[0] + step[0], qq[1] + step[1], qq[2] + step[2]]
            trial += [qq[3] + step[3], qq[4] + step[4], qq[5] + step[5]]
            frame, trial_jac = self.frame_and_jacobian(trial)
            trial_err = _twist_to(frame, target)
            trial_norm = _norm6(trial_err)
            if trial_norm < norm:
                if adaptive:
                    t = 2.0 * _gain_ratio(jac, err, step, lam, norm, trial_norm) - 1.0
                    lam = max(lam * max(1.0 / 3.0, 1.0 - t * t * t), 1e-9)
                    grow = 2.0
                else:
                    lam = max(lam * 0.2, 1e-9)
                qq, jac, err, norm = trial, trial_jac, trial_err, trial_norm
                gradient = _gradient_ratio(jac, err, norm)
            else:
                if adaptive:
                    lam *= grow
                    grow *= 2.0
                else:
                    lam *= 5.0
                if lam > 1e9:
                    break
        return qq, norm, gradient

    def _project(
        self, q: list[float], target: Sequence[float]
    ) -> tuple[list[float], list[float], list[float], float]:
        """``q`` brought toward the valley's floor by Gauss-Newton steps on θ1..θ5 with θ6
        held: the joints, Jacobian, error and its norm."""
        frame, jac = self.frame_and_jacobian(q)
        err = _twist_to(frame, target)
        norm = _norm6(err)
        for _ in range(_VALLEY_PROJECTIONS):
            held = list(jac)
            for r in range(6):
                held[6 * r + 5] = 0.0
            x = _solve6(held, err, 1e-12)
            if x is None:
                break
            trial = [q[k] + x[k] for k in range(6)]
            frame, trial_jac = self.frame_and_jacobian(trial)
            trial_err = _twist_to(frame, target)
            trial_norm = _norm6(trial_err)
            if not trial_norm < norm:
                break
            q, jac, err, norm = trial, trial_jac, trial_err, trial_norm
        return q, jac, err, norm

    def valley(
        self, q: Sequence[float], target: Sequence[float], converged: float = 1e-12
    ) -> list[tuple[list[float], float]]:
        """The solutions along the wrist's self-motion through ``q`` (see :meth:`_walk`)."""
        return self._walk(q, target, converged)[0]

    def _walk(
        self,
        q: Sequence[float],
        target: Sequence[float],
        converged: float,
        seed: Sequence[float] | None = None,
        bound: float = math.inf,
    ) -> tuple[list[tuple[list[float], float]], list[list[float]] | None]:
        """The solutions along the wrist's self-motion through ``q``: (joints, error norm)
        pairs, the norm below ``converged`` unless a root's search ran out of steps; roots
        that cannot be nearer ``seed`` (default ``q``) than ``bound`` (rad, Euclidean) are
        not looked for.

        Next to the wrist singularity (sin θ5 ≈ 0) the calibrated solutions lie along a
        curved valley of the pose error (θ6 turning, θ2, θ3 and θ4 following), far from the
        nominal branches and, next to the singularity, close to each other: damped steps
        crawl along it and find one. θ6 is the valley's parameter: at _VALLEY_POINTS points
        of a full turn around ``q``'s θ6, each predicted along the valley's tangent from the
        previous one, θ1..θ5 are brought back to the floor with θ6 held (a well-conditioned
        problem); Newton's step of all six joints there says on which side a root is (its
        θ6 part changes sign from + to - across one). The points go half a turn each way
        (the valley may be cut where the arm is out of reach); each bracket is closed by
        Newton's steps, bisected where one would leave it. Where the valley passes next to
        the calibrated arm's own wrist singularity its roots can lie closer together than the
        points (no sign change between them): a point whose Newton step of θ6 predicts a root
        within _VALLEY_PREDICT of the spacing where none was found gets Newton's steps too.

        Known misses (bench/ik.py's wrist family, seed TCP: the hot path's answer farther
        than the reference's for 11 of the first 200 poses, 19 of the next 200): two or three
        roots within ~0.3 rad of θ6 where the pose is (nearly) exactly wrist-singular, the
        valley's error there ~1e-5 against ~1e-3 elsewhere; the points, one projection each,
        are ~5e-4 off the floor there, so the signs of θ6's steps are unreliable (two or three
        projections, tried, missed more); roots next to a cut; and starts with |sin θ5| just
        above _VALLEY_NEAR (0.1 or 0.2 instead, tried: no better). Fewer points (8, 10) missed
        more; probing ±0.1 rad along the valley from each root found none of them, ±0.25 rad
        one of 11 for ~30 % more chain evaluations.

        ``bound`` (:meth:`nearest` gives the distance of the best solution found so far): a
        bracket whose root is surely farther from ``seed`` (:func:`_chord_bound`, less
        _WRIST_MOVE for the valley's bend) is not closed, nor a root predicted farther (the
        point's distance less twice its step of θ6, θ4 turning with it, and _WRIST_MOVE).
        On the bench's wrist family (seed TCP, 400 poses) this saves ~13 % of the chain
        evaluations per call at the median (~7 % on average) and changes no answer (tried
        without the _WRIST_MOVE slack: also none).
        Stopping the walk itself where θ1, θ5 and the rest of θ6's turn are too far
        (tried) saved nothing: the valleys it cut were walked again from other starts.
        Next to the singularity (_VALLEY_CUTS) a side stops where it leaves the floor
        (_VALLEY_OFF points off it in a row) and the other goes on past half a turn to that
        point: a cut valley's points beyond the cut are not walked twice over (C hot path on
        1000 poses of each family, --seed 1, 2 and 3: wrist mean time per call -4 to -10 %,
        limits -7 %, no answer farther from the seed). Taking a start on a cut valley walked
        already for walked (tried) saved ~16 % of the wrist family's chain evaluations but
        lost roots (6 answers farther in 1200 poses): walks from other points of a cut valley
        find roots next to the cut that the first one missed."""
        h = TWO_PI / _VALLEY_POINTS
        near = q if seed is None else seed
        roots: list[tuple[list[float], float]] = []
        origin = self._project([float(v) for v in q], target)
        if origin[3] < converged:
            roots.append((origin[0], origin[3]))
        samples: list[tuple[list[float], float]] = []  # points on the floor, θ6's step
        # the points on the floor by their turn from the origin, -half..half (None: off it)
        half = _VALLEY_POINTS // 2
        floor: list[list[float] | None] = [None] * (2 * half + 1)
        last = half  # the - side's last point: beyond half where the + side left the floor
        cuts = abs(math.sin(q[4])) < _VALLEY_CUTS  # a side stops where it leaves the floor
        for sign in (1.0, -1.0):
            qq, jac, err, norm = origin
            previous = 0.0  # the Newton step of θ6 at the last point on the floor (0: none)
            below = qq
            been_on = False
            off = 0  # points off the floor in a row
            for point in range((half if sign > 0.0 else last) + 1):
                if point:
                    held = list(jac)
                    column = [0.0] * 6
                    for r in range(6):
                        column[r] = -jac[6 * r + 5]
                        held[6 * r + 5] = 0.0
                    tangent = _solve6(held, column, 1e-12) or [0.0] * 6
                    tangent[5] = 1.0
                    qq = [qq[k] + sign * h * tangent[k] for k in range(6)]
                    qq, jac, err, norm = self._project(qq, target)
                    if norm < converged:
                        roots.append((qq, norm))
                        previous = 0.0
                        been_on = True
                        off = 0
                        continue
                step = _solve6(jac, err, 0.0)
                if norm > _VALLEY_FLOOR or step is None:
                    previous = 0.0  # off the floor (out of reach there): no bracket across
                    off += 1
                    if cuts and been_on and off == _VALLEY_OFF:
                        # left the floor: the rest of this side is walked from the other
                        if sign > 0.0:
                            last = _VALLEY_POINTS - point
                        break
                    continue
                been_on = True
                off = 0
                if point or sign > 0.0:
                    samples.append((qq, step[5]))
                    if point <= half:
                        floor[half + (point if sign > 0.0 else -point)] = qq
                if (
                    sign * previous > 0.0
                    and sign * step[5] < 0.0
                    and not _chord_bound(below, qq, near) - _WRIST_MOVE > bound
                ):
                    if sign > 0.0:
                        roots.append(self._close(below, qq, target, converged))
                    else:
                        roots.append(self._close(qq, below, target, converged))
                previous = step[5]
                below = qq
        # roots closer together than the points leave no sign change between them: a point
        # whose Newton step of θ6 predicts a root within _VALLEY_PREDICT of the spacing, where
        # no root found is, gets _VALLEY_TRIES Newton's steps
        for qq, t in samples:
            if not abs(t) < _VALLEY_PREDICT * h:
                continue
            if _wrapped_distance(qq, near) - 2.0 * abs(t) - _WRIST_MOVE > bound:
                continue  # the predicted root cannot be nearer the seed than the best
            aim = qq[5] + t
            if any(
                abs(r[5] - aim - TWO_PI * round((r[5] - aim) * _INV_TWO_PI)) < _VALLEY_SAME * h
                for r, e in roots
                if e < converged
            ):
                continue
            root = self.newton(qq, target, _VALLEY_TRIES, converged, converged)
            if root[1] < converged:
                roots.append(root)
        if any(p is None for p in floor):
            return roots, None  # cut (the arm out of reach): a walk from elsewhere sees its ends
        return roots, [p for p in floor if p is not None]

    def _close(
        self, lower: list[float], upper: list[float], target: Sequence[float], converged: float
    ) -> tuple[list[float], float]:
        """The root of the valley between points ``lower`` and ``upper`` (θ6 increasing)."""
        lo, hi = lower[5], upper[5]
        qq, jac, err, norm = self._project(list(lower), target)
        halved = 0
        for _ in range(_VALLEY_STEPS):
            if norm < converged:
                break
            step = _solve6(jac, err, 0.0)
            if step is None:
                break
            if step[5] > 0.0:
                lo = qq[5]
            else:
                hi = qq[5]
            t = qq[5] + step[5]
            if lo < t < hi:  # Newton's step: near the root it needs no projection
                qq = [qq[k] + step[k] for k in range(6)]
                size = _norm6(step)
                if size < _FINAL_STEP:
                    return qq, size * size  # as in newton: an error of the step's square
                frame, jac = self.frame_and_jacobian(qq)
                err = _twist_to(frame, target)
                norm = _norm6(err)
            else:
                halved += 1
                if halved > _VALLEY_HALVINGS:
                    break  # a minimum of the error between the points, not a root
                qq = [qq[0], qq[1], qq[2], qq[3], qq[4], 0.5 * (lo + hi)]
                qq, jac, err, norm = self._project(qq, target)
        if converged <= norm < _VALLEY_FINISH:
            # off the floor a step's sign can mislead the bracket: Newton's steps of all
            # six joints finish from next to the root
            return self.newton(qq, target, _VALLEY_STEPS, converged, converged)
        return qq, norm

    def nearest(
        self,
        starts: Sequence[tuple[float, Sequence[float]]],
        target: Sequence[float],
        seed: Sequence[float],
        lower: Sequence[float],
        upper: Sequence[float],
        newton_iterations: int,
        settle_iterations: int,
        converged: float,
        rounding: float,
        stationary: float,
        accepted: float,
        factor: float,
        near: float,
    ) -> tuple[list[float] | None, float, float, float, int]:
        """Starts refined toward ``target``, the solution nearest ``seed``.

        ``starts``: (distance², joints) pairs (as :meth:`Kinematics.nearest_within` gives
        them; the distances are not used), taken in the order of their distance from the
        seed with each joint's difference wrapped into ±π. A start farther than the best
        solution found plus ``factor`` × the largest move the refinement of such a start
        made is skipped (it cannot come nearer), unless it is next to a singularity, where
        refinement moves far: |sin θ3| or |sin θ5| below ``near``, or the target next to
        the shoulder singularity (:meth:`_singular_target`); next to the wrist singularity
        alone, a start is skipped when its θ1 and θ5 alone are too far (:func:`_wrist_bound`);
        next to the shoulder singularity alone (|sin θ3| and |sin θ5| at least ``near``), when
        it is farther than the best plus ``factor`` × the largest move any refinement made
        (otherwise every start there is refined: the C hot path on 1000 poses of every
        bench/ik.py family, --seed 1 to 4, gave no answer farther from the seed, shoulder
        family median time per call -1 to -8 %).
        Refined: :meth:`newton`; if that leaves an error above ``accepted``, every solution
        along the start's valley (:meth:`valley`) next to the wrist singularity (|sin θ5|
        below _VALLEY_NEAR, the target away from the shoulder's; a start on a valley walked
        whole already, :func:`_on_walked`, is skipped), else :meth:`settle` from
        where Newton's steps left off; if no
        start gave a solution, those whose valley walk found none are settled too (the walk
        misses roots where the valley is cut, the arm stretched or folded); a solution's
        joints are shifted by 2π toward the seed within [lower, upper] (dropped if none
        fits).
        Returns the best joints (None: none), their distance², the largest move a
        refinement made (rad, Euclidean), the smallest distance of a start that neither
        converged nor reached a local minimum of the error (inf: none) and
        :meth:`_singular_target`'s flags.
        ``fxcell.motion._dhchain.Chain.nearest`` is this in C."""
        n = len(starts)
        qs = [[float(v) for v in start] for _, start in starts]
        distance = [0.0] * n
        for i in range(n):
            d = 0.0
            for k in range(6):
                w = qs[i][k] - seed[k]
                w -= TWO_PI * round(w * _INV_TWO_PI)
                d += w * w
            distance[i] = math.sqrt(d)
        order = sorted(range(n), key=lambda i: distance[i])
        singular_at = self._singular_target(target, near)
        shoulder = singular_at & 1 != 0
        best: list[float] | None = None
        best_d = math.inf
        moved = 0.0
        regular = 0.0  # the largest move of a start away from the singularities
        unrefined = math.inf
        missed: list[int] = []  # starts whose valley walk found no root
        walked: list[list[list[float]]] = []  # the points of the valleys walked whole
        pending, retry = order, False
        while True:
            for i in pending:
                start = qs[i]
                singular = (
                    shoulder or abs(math.sin(start[2])) < near or abs(math.sin(start[4])) < near
                )
                found: list[list[float]] = []
                q = start
                if not retry:
                    if (
                        best is not None
                        and not singular
                        and distance[i] > math.sqrt(best_d) + factor * regular + 1e-9
                    ):
                        continue  # it cannot come nearer
                    if (
                        best is not None
                        and shoulder
                        and not (abs(math.sin(start[2])) < near or abs(math.sin(start[4])) < near)
                        and distance[i] > math.sqrt(best_d) + factor * moved + 1e-9
                    ):
                        continue  # next to the shoulder singularity alone: by the largest move
                    if (
                        best is not None
                        and not shoulder
                        and abs(math.sin(start[4])) < near
                        and _wrist_bound(start, seed) > math.sqrt(best_d) + 1e-9
                    ):
                        continue  # next to the wrist singularity, but θ1 and θ5 alone are too far
                    on_valley = not shoulder and abs(math.sin(start[4])) < _VALLEY_NEAR
                    if on_valley and any(_on_walked(start, w) for w in walked):
                        continue  # on a valley walked already
                    q, err = self.newton(
                        start,
                        target,
                        newton_iterations,
                        converged,
                        rounding,
                        _VALLEY_REJECTIONS if on_valley else 0,
                    )
                    if err <= accepted:
                        found.append(q)
                    elif on_valley:
                        # along the wrist's self-motion: every solution on this branch's valley
                        roots, floor = self._walk(start, target, converged, seed, math.sqrt(best_d))
                        if floor is not None and len(walked) < _MAX_WALKED:
                            walked.append(floor)
                        found += [r for r, e in roots if e <= accepted]
                        if not found:
                            missed.append(i)
                            continue
                if not found:  # damped steps, on from where Newton's left off
                    q, err, gradient = self.settle(
                        q,
                        target,
                        settle_iterations,
                        converged,
                        stationary,
                        _QUICK_STALL if abs(math.sin(start[4])) >= near else _STALL_STEPS,
                        True,
                    )
                    if err > accepted:
                        if not gradient <= stationary and distance[i] < unrefined:
                            unrefined = distance[i]
                        continue
                    found.append(q)
                for q in found:
                    m = 0.0
                    for k in range(6):
                        m += (q[k] - start[k]) * (q[k] - start[k])
                    m = math.sqrt(m)
                    moved = max(moved, m)
                    if not singular:
                        regular = max(regular, m)
                    shifted = [0.0] * 6
                    d = 0.0
                    inside = True
                    for k in range(6):
                        w = _near(q[k], seed[k], lower[k], upper[k])
                        if w != w:
                            inside = False
                            break
                        shifted[k] = w
                        d += (w - seed[k]) * (w - seed[k])
                    if inside and d < best_d:
                        best, best_d = shifted, d
            if retry or best is not None or not missed:
                break
            # nothing found: where the valley is cut (the arm stretched or folded) its walk
            # can miss a root that damped steps reach
            pending, retry = missed, True
        return best, best_d, moved, unrefined, singular_at

    def _singular_target(self, g: Sequence[float], near: float) -> int:
        """Next to which singularities target ``g`` is, whatever the joints: 1 if its wrist
        centre (of its flange, ``g · tcp⁻¹``) is within ``near``·d4 of the shoulder
        singularity (h² below (near·d4)², h its distance from the plane of axes 1 and 2),
        2 if the wrist is (|sin θ5| below ``near``) for either shoulder, 3 both, 0 neither."""
        t = self._tcp
        f = [0.0] * 9
        pf = [0.0] * 3
        for r in range(3):
            g0, g1, g2 = g[3 * r], g[3 * r + 1], g[3 * r + 2]
            f[3 * r] = g0 * t[0] + g1 * t[1] + g2 * t[2]
            f[3 * r + 1] = g0 * t[3] + g1 * t[4] + g2 * t[5]
            f[3 * r + 2] = g0 * t[6] + g1 * t[7] + g2 * t[8]
            pf[r] = g[9 + r] - (f[3 * r] * t[9] + f[3 * r + 1] * t[10] + f[3 * r + 2] * t[11])
        d4 = self._d[3]
        x = pf[0] - self._d[5] * f[2]
        y = pf[1] - self._d[5] * f[5]
        rho2 = x * x + y * y
        h2 = rho2 - d4 * d4
        out = 1 if h2 < near * near * d4 * d4 else 0
        h = math.sqrt(h2) if h2 > 0.0 else 0.0
        if rho2 > 0.0:
            for hs in (h, -h):
                c1 = (x * hs - y * d4) / rho2
                s1 = (y * hs + x * d4) / rho2
                zx = f[0] * s1 - f[3] * c1
                zy = f[1] * s1 - f[4] * c1
                if zx * zx + zy * zy < near * near:
                    out |= 2
        return out


def _wrapped_distance(a: Sequence[float], b: Sequence[float]) -> float:
    """Euclidean distance of joints ``a`` and ``b``, each joint's difference wrapped into
    ±π: a lower bound of the distance of any 2π-equivalents of them."""
    d = 0.0
    for k in range(6):
        w = a[k] - b[k]
        w -= TWO_PI * round(w * _INV_TWO_PI)
        d += w * w
    return math.sqrt(d)


def _chord_bound(a: Sequence[float], b: Sequence[float], seed: Sequence[float]) -> float:
    """A lower bound of the (wrapped) distance from ``seed`` of any point on the segment
    between joints ``a`` and ``b``: ``(|a - s| + |b - s| - |a - b|) / 2`` (triangle
    inequality: a point x on it has |x - a| + |x - b| = |a - b|)."""
    return 0.5 * (_wrapped_distance(a, seed) + _wrapped_distance(b, seed) - _wrapped_distance(a, b))


def _on_walked(q: Sequence[float], floor: list[list[float]]) -> bool:
    """Whether ``q`` lies on the valley whose points ``floor`` are (a whole turn of θ6 on the
    floor, see :meth:`DHChain._walk`): θ1..θ5 within _VALLEY_ON of the line between the two
    points whose θ6 enclose its own (each joint's difference wrapped into ±π)."""
    half = _VALLEY_POINTS // 2
    h = TWO_PI / _VALLEY_POINTS
    origin = floor[half]
    w = q[5] - origin[5]
    w -= TWO_PI * round(w * _INV_TWO_PI)
    u = w / h
    k = math.floor(u)
    if k < -half or k >= half:
        return False
    a = floor[half + k]
    b = floor[half + k + 1]
    f = u - k
    for j in range(5):
        step = b[j] - a[j]
        step -= TWO_PI * round(step * _INV_TWO_PI)
        off = q[j] - (a[j] + f * step)
        off -= TWO_PI * round(off * _INV_TWO_PI)
        if not abs(off) < _VALLEY_ON:
            return False
    return True


def _wrist_bound(start: Sequence[float], seed: Sequence[float]) -> float:
    """Next to the wrist singularity (sin θ5 ≈ 0) refinement can turn θ2, θ3, θ4 and θ6 far
    (the arm's self-motion there), but θ1 and θ5 only by the deltas' order: a lower bound of
    the distance from ``seed`` of any solution it reaches from ``start``, with _WRIST_MOVE
    for those moves."""
    w1 = start[0] - seed[0]
    w5 = start[4] - seed[4]
    w1 -= TWO_PI * round(w1 * _INV_TWO_PI)
    w5 -= TWO_PI * round(w5 * _INV_TWO_PI)
    return math.sqrt(w1 * w1 + w5 * w5) - _WRIST_MOVE


def _gradient_ratio(jac: list[float], err: list[float], norm: float) -> float:
    """``‖Jᵀe‖ / (‖J‖_F·‖e‖)``: 0 where the error ``e`` (norm ``norm``) is stationary."""
    grad = 0.0
    size = 0.0
    for k in range(6):
        acc = 0.0
        for r in range(6):
            v = jac[6 * r + k]
            acc += v * err[r]
            size += v * v
        grad += acc * acc
    scale = math.sqrt(size) * norm
    return math.sqrt(grad) / scale if scale > 0.0 else 0.0


def _gain_ratio(
    jac: list[float],
    err: list[float],
    step: list[float],
    lam: float,
    norm: float,
    trial_norm: float,
) -> float:
    """The gain ratio ρ of Marquardt's ``step`` (damping ``lam``, see :func:`_solve6`) from
    the point of Jacobian ``jac`` and error ``err`` (norm ``norm``) to one of error norm
    ``trial_norm``: the decrease of ``‖e‖²/2`` over the linear model's,
    ``stepᵀ·(Jᵀe + lam·(diag(JᵀJ) + 1e-12)·step) / 2``; -1 where the model predicts none."""
    predicted = 0.0
    for i in range(6):
        g = 0.0
        dd = 0.0
        for r in range(6):
            v = jac[6 * r + i]
            g += v * err[r]
            dd += v * v
        predicted += step[i] * (g + lam * (dd + 1e-12) * step[i])
    predicted *= 0.5
    actual = 0.5 * (norm * norm - trial_norm * trial_norm)
    return actual / predicted if predicted > 0.0 else -1.0


def _twist_to(frame: list[float], target: Sequence[float]) -> list[float]:
    """Position difference and rotation vector (base frame) from ``frame`` to ``target``
    (12 floats each, rotation row-major then position)."""
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = frame[0:9]
    b00, b01, b02, b10, b11, b12, b20, b21, b22 = target[0:9]
    # E = B·Aᵀ: its skew part and trace give the rotation vector
    e01 = b00 * a10 + b01 * a11 + b02 * a12
    e02 = b00 * a20 + b01 * a21 + b02 * a22
    e10 = b10 * a00 + b11 * a01 + b12 * a02
    e12 = b10 * a20 + b11 * a21 + b12 * a22
    e20 = b20 * a00 + b21 * a01 + b22 * a02
    e21 = b20 * a10 + b21 * a11 + b22 * a12
    trace = (
        b00 * a00 + b01 * a01 + b02 * a02
        + b10 * a10 + b11 * a11 + b12 * a12
        + b20 * a20 + b21 * a21 + b22 * a22
    )  # fmt: skip
    wx, wy, wz = 0.5 * (e21 - e12), 0.5 * (e02 - e20), 0.5 * (e10 - e01)
    s = math.sqrt(wx * wx + wy * wy + wz * wz)  # sin of the angle
    scale = math.atan2(s, 0.5 * (trace - 1.0)) / s if s > 1e-300 else 1.0
    return [
        target[9] - frame[9],
        target[10] - frame[10],
        target[11] - frame[11],
        scale * wx,
        scale * wy,
        scale * wz,
    ]


def _norm6(v: list[float]) -> float:
    a, b, c, d, e, f = v
    return math.sqrt(a * a + b * b + c * c + d * d + e * e + f * f)


def _solve6(
    jac: list[float], rhs: list[float], lam: float, scaled: bool = False
) -> list[float] | None:
    """``J·x = rhs`` (``lam`` 0), or the damped least squares ``(JᵀJ + lam·I)·x = Jᵀ·rhs``
    (``scaled``: Marquardt's ``(JᵀJ + lam·(diag(JᵀJ) + 1e-12))·x = Jᵀ·rhs``), by Gaussian
    elimination with partial pivoting on a flat 6×7 array; None if singular to rounding."""
    m = [0.0] * 42
    if lam == 0.0 and not scaled:
        for i in range(6):
            for k in range(6):
                m[7 * i + k] = jac[6 * i + k]
            m[7 * i + 6] = rhs[i]
    else:
        for i in range(6):
            for k in range(i, 6):
                acc = 0.0
                for r in range(6):
                    acc += jac[6 * r + i] * jac[6 * r + k]
                m[7 * i + k] = acc
                m[7 * k + i] = acc
            m[7 * i + i] += lam * (m[7 * i + i] + 1e-12) if scaled else lam
            acc = 0.0
            for r in range(6):
                acc += jac[6 * r + i] * rhs[r]
            m[7 * i + 6] = acc
    for c in range(6):
        p = c
        big = abs(m[7 * c + c])
        for r in range(c + 1, 6):
            v = abs(m[7 * r + c])
            if v > big:
                p, big = r, v
        if big < 1e-300:
            return None
        if p != c:
            for k in range(c, 7):
                m[7 * c + k], m[7 * p + k] = m[7 * p + k], m[7 * c + k]
        inv_p = 1.0 / m[7 * c + c]
        for r in range(c + 1, 6):
            f = m[7 * r + c] * inv_p
            if f != 0.0:
                for k in range(c + 1, 7):
                    m[7 * r + k] -= f * m[7 * c + k]
    x = [0.0] * 6
    for c in range(5, -1, -1):
        acc = m[7 * c + 6]
        for k in range(c + 1, 6):
            acc -= m[7 * c + k] * x[k]
        v = acc / m[7 * c + c]
        if v - v != 0.0:  # NaN or inf
            return None
        x[c] = v
    return x


def _rounding_slack(s5: float, h: float) -> float:
    """How far beyond the reach (in cos θ3) rounding can throw a branch that does reach.

    θ6 carries rounding error ~1e-16/|sin θ5| rad next to the wrist singularity and θ1
    ~4e-17/h next to the shoulder's (h: the wrist centre's distance from it, m); either
    moves the arm's target point and so cos θ3 by about as much again. _WRIST_SLACK leaves
    a factor 100 over that. Elsewhere a branch beyond
    the reach by more than the clip (_CLIP_EPS) is out of reach: polishing it only burns
    time (up to milliseconds of Newton steps that cannot converge).
    """
    if s5 <= 0.0 or h <= 0.0:
        return math.inf
    return _WRIST_SLACK / s5 + _WRIST_SLACK / h


def _near(v: float, s: float, lo: float, hi: float) -> float:
    """The 2π-equivalent of angle ``v`` nearest ``s`` within [lo, hi], or NaN if none."""
    v += TWO_PI * round((s - v) * _INV_TWO_PI)
    # outside the limits (the seed is near or beyond one): the equivalent just inside, if any;
    # a solution exactly at the limit may come out a rounding error beyond it
    if v > hi:
        v = hi if v - hi < _LIMIT_EPS else v - TWO_PI * math.ceil((v - hi) * _INV_TWO_PI)
        if v < lo:
            return math.nan
    elif v < lo:
        v = lo if lo - v < _LIMIT_EPS else v + TWO_PI * math.ceil((lo - v) * _INV_TWO_PI)
        if v > hi:
            return math.nan
    return v


_SIN2_TABLES: dict[int, list[float]] = {}


def _sin2(n: int) -> list[float]:
    """sin²(i·π/(2n)) for i = 0..n (the u grid of :meth:`Kinematics._singular_arms`)."""
    table = _SIN2_TABLES.get(n)
    if table is None:
        table = _SIN2_TABLES[n] = [math.sin(i * (0.5 * math.pi) / n) ** 2 for i in range(n + 1)]
    return table


def _continuum_f(
    ts: list[float],
    consts: tuple[float, ...],
    goals: tuple[float, float, float, float],
    bounds: tuple[float, ...],
    cap: float = math.inf,
) -> tuple[list[float], list[float]]:
    """The distance² f of :meth:`Kinematics._singular_arms` at each θ6 in ``ts``, for the
    elbow up and down (inf out of reach, beyond a limit or, as soon as a partial sum
    shows it, above ``cap``), in one loop of plain floats."""
    X5, Y5, ax, bx, ay, by, l3, k3, a2, a3, t0, sg = consts
    g2, g3, g4, g6 = goals
    lo2, hi2, lo3, hi3, lo4, hi4, lo6, hi6 = bounds
    sin, cos, atan2, sqrt = math.sin, math.cos, math.atan2, math.sqrt
    tau, inv, inf = TWO_PI, _INV_TWO_PI, math.inf
    ups: list[float] = []
    downs: list[float] = []
    for t in ts:
        # the 2π shifts toward the seed written out (_near only beyond a limit)
        w = t + tau * (((g6 - t) * inv + 0.5) // 1.0)
        if not lo6 <= w <= hi6:
            w = _near(t, g6, lo6, hi6)
        f6 = (w - g6) * (w - g6)
        if f6 > cap:
            ups.append(inf)
            downs.append(inf)
            continue
        s, c = sin(t), cos(t)
        X = X5 + s * ax + c * bx
        Y = Y5 + s * ay + c * by
        c3 = (X * X + Y * Y - l3) * k3
        if c3 > 1.0 or c3 < -1.0:
            if abs(c3) > 1.0 + _CLIP_EPS:
                ups.append(inf)
                downs.append(inf)
                continue
            c3 = 1.0 if c3 > 0.0 else -1.0
        s3 = sqrt(1.0 - c3 * c3)
        t3 = atan2(s3, c3)
        bb = atan2(Y, X)
        be = atan2(a3 * s3, a2 + a3 * c3)
        t234 = t0 + sg * t
        for t2, t3e, out in ((bb - be, t3, ups), (bb + be, -t3, downs)):
            w = t2 + tau * (((g2 - t2) * inv + 0.5) // 1.0)
            if not lo2 <= w <= hi2:
                w = _near(t2, g2, lo2, hi2)
            fv = f6 + (w - g2) * (w - g2)
            if fv > cap:
                out.append(inf)
                continue
            t4 = t234 - t2 - t3e
            w = t3e + tau * (((g3 - t3e) * inv + 0.5) // 1.0)
            if not lo3 <= w <= hi3:
                w = _near(t3e, g3, lo3, hi3)
            fv += (w - g3) * (w - g3)
            w = t4 + tau * (((g4 - t4) * inv + 0.5) // 1.0)
            if not lo4 <= w <= hi4:
                w = _near(t4, g4, lo4, hi4)
            fv += (w - g4) * (w - g4)
            out.append(fv if fv == fv else inf)
    return ups, downs


def _within(t: float, lo: float, hi: float, periodic: bool) -> float:
    """The 2π-equivalent of θ6 = ``t`` in [lo, hi], or just beyond an end (within
    _END_SLACK: the ends' own rounding where the circle of frame 4 grazes the reach, an
    interval ~6e-6 long ending 3e-11 short of a limit point that reached the pose; whether it
    does is left to the reach check with its clip), or NaN."""
    tt = lo + (t - lo) % TWO_PI
    if tt <= hi or (not periodic and tt <= hi + _END_SLACK):
        return tt
    if not periodic and tt >= lo + TWO_PI - _END_SLACK:
        return tt - TWO_PI
    return math.nan


def _shift_flipped(a: _Ev, b: _Ev) -> bool:
    """Whether one of θ2, θ3, θ4, θ6 (their 2π shifts toward the seed) differs by over π
    between two points of a continuum: a shift flipped between them at a joint limit."""
    return (
        abs(b[4] - a[4]) > math.pi
        or abs(b[5] - a[5]) > math.pi
        or abs(b[6] - a[6]) > math.pi
        or abs(b[10] - a[10]) > math.pi
    )


def _jumps(g: float, lo: float, hi: float, flip: bool) -> list[float]:
    """Where the equivalent of an angle nearest ``g`` within [lo, hi] changes (mod 2π): the
    limits where it jumps to the far side, if the half-turn window around ``g`` crosses
    them; else, if ``flip``, g + π, where two equivalents are equally near."""
    out = [lo] if lo > g - math.pi else []
    if hi < g + math.pi and not (out and abs(math.remainder(hi - lo, TWO_PI)) < 1e-9):
        out.append(hi)
    return out if out or not flip else [g + math.pi]


def _pose_error(current: Pose, target: Pose) -> FloatArray:
    """Twist (base frame) from ``current`` to ``target``: position difference, rotation vector."""
    dp = target.position - current.position
    dr = matrix_to_rotvec(target.rotation @ current.rotation.T)
    return np.array([*dp.tolist(), *dr])


def _compose(a: list[float], b: Sequence[float]) -> list[float]:
    """Product of two transforms given as 12 floats (rotation row-major, position)."""
    a00, a01, a02, a10, a11, a12, a20, a21, a22, ax, ay, az = a
    b00, b01, b02, b10, b11, b12, b20, b21, b22, bx, by, bz = b
    return [
        a00 * b00 + a01 * b10 + a02 * b20,
        a00 * b01 + a01 * b11 + a02 * b21,
        a00 * b02 + a01 * b12 + a02 * b22,
        a10 * b00 + a11 * b10 + a12 * b20,
        a10 * b01 + a11 * b11 + a12 * b21,
        a10 * b02 + a11 * b12 + a12 * b22,
        a20 * b00 + a21 * b10 + a22 * b20,
        a20 * b01 + a21 * b11 + a22 * b21,
        a20 * b02 + a21 * b12 + a22 * b22,
        a00 * bx + a01 * by + a02 * bz + ax,
        a10 * bx + a11 * by + a12 * bz + ay,
        a20 * bx + a21 * by + a22 * bz + az,
    ]


def _joints(q: ArrayLike) -> list[float]:
    """Six finite joint values as floats (a list of six floats is returned as is, not
    copied: callers must not modify it), or InvalidTargetError."""
    if isinstance(q, list) and len(q) == 6:
        a, b, c, d, e, f = q  # unrolled: this runs for every inverse-kinematics call
        if (
            type(a) is float
            and type(b) is float
            and type(c) is float
            and type(d) is float
            and type(e) is float
            and type(f) is float
        ):
            total = a + b + c + d + e + f
            if total - total != 0.0:  # NaN or inf somewhere (or a sum beyond 1e308)
                raise InvalidTargetError(f"joint positions must be 6 finite numbers, got {q!r}")
            return q
    if type(q) is np.ndarray and q.dtype == np.float64 and q.shape == (6,):
        out: list[float] = q.tolist()
    else:
        arr = np.asarray(q) if not isinstance(q, str | bytes) else np.asarray(None)
        if arr.dtype.kind not in "iuf" or arr.shape != (6,):
            raise InvalidTargetError(f"joint positions must be 6 numbers, got {q!r}")
        out = arr.astype(np.float64).tolist()
    total = out[0] + out[1] + out[2] + out[3] + out[4] + out[5]
    if total - total != 0.0:  # NaN or inf somewhere (or a sum beyond 1e308: not joints either)
        raise InvalidTargetError(f"joint positions must be 6 finite numbers, got {q!r}")
    return out


def _default_limits() -> tuple[Sequence[float], Sequence[float]]:
    from fxcell.config import JointLimits  # lazy: pydantic costs ~0.1 s to import

    lim = JointLimits()
    return lim.position_min, lim.position_max
