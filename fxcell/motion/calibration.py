"""Calibrated UR kinematics: the closed form on the nominal model, refined on the calibrated one.

A calibrated arm's DH parameters differ from the nominal ones by up to millimetres and
milliradians (:class:`fxcell.calibration.Calibration`), which breaks the closed-form inverse
(it needs exactly parallel middle axes). :class:`CalibratedKinematics` keeps the
:class:`~fxcell.motion.kinematics.Kinematics` interface: its forward kinematics is the
calibrated DH chain, and its inverse refines the closed-form branches of the nominal model
onto the calibrated one, nearest the seed first (Newton steps with the analytic Jacobian):
three or four steps bring a millimetre-off start to the rounding floor. Where they do not
converge, next to the wrist singularity, the calibrated solutions lie along the branch's
self-motion (θ4 and θ6 turning together, θ2 and θ3 following), up to a turn of θ6 from the
nominal branch and sometimes close to each other:
:meth:`~fxcell.motion.kinematics.DHChain.valley` searches that
valley with θ6 as its parameter; elsewhere Levenberg-Marquardt. The chain and that loop run
in C (``fxcell/motion/_dhchain.c``, :data:`NATIVE`), else in plain Python floats
(:class:`~fxcell.motion.kinematics.DHChain`). Next to a singularity, where the deltas can
take a branch out of the nominal solutions, and where the nominal closed form has no branch
(at the edge of its workspace, or with θ5 within milliradians of 0 or π, where members of
the wrist-singular continuum are starts too), more starts are refined. No Pinocchio: the
simulator uses this module too.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from fxcell.calibration import Calibration
from fxcell.errors import SingularityError, UnreachableError
from fxcell.geometry import Pose, rotvec_to_matrix
from fxcell.motion.kinematics import (
    _EDGE_C3,
    _LENIENT_C3,
    _LENIENT_H2,
    _LENIENT_WRIST,
    _WRIST_EPS,
    JOINT_NAMES,
    UR3E_DH,
    DHChain,
    FloatArray,
    JointValidity,
    Kinematics,
    _compose,
    _joints,
    _near,
    dh_transform,
)

try:
    from fxcell.motion._dhchain import Chain

    NATIVE = True
    """Whether the calibrated chain runs in C (``fxcell/motion/_dhchain.c``, hatch_build.py)."""
except ImportError:  # not built (no C compiler): the same computations in Python
    Chain = DHChain  # type: ignore[assignment,misc]
    NATIVE = False

if TYPE_CHECKING:
    from fxcell.config import CellConfig, JointLimits


CONVERGED = 1e-12
"""Pose error norm (m and rad together) at which refinement stops."""
ACCEPTED = 1e-9
"""Pose error norm above which a refined branch is dropped (did not converge)."""
_ITERATIONS = 20
_FAST_ITERATIONS = 8
"""Newton steps the hot path gives a start (4 or 5 bring a nominal solution to rounding)."""
_PATIENT_ITERATIONS = 400  # Levenberg-Marquardt's, from far starts (rarely needed)
_SELF_MOTION_TURNS = (0.5 * math.pi, math.pi, 1.5 * math.pi)
"""Radians by which the last resort of the general path turns θ4 and θ6 together (both
ways) from each start: points along the wrist's self-motion at its singularity."""
_SELF_MOTION_ITERATIONS = 3000
"""Levenberg-Marquardt steps the last resort gives each of those starts."""
_EDGE_STEPS = (0.005, 0.02)
"""Metres by which a target at the edge of the nominal workspace is moved to find starts."""
_ROUNDING = 1e-11
"""Pose error norm below which a step that does not improve ends the refinement."""
_SAME_START = 0.05
"""Radians (per joint) within which two starting points count as one."""
_EDGE_TURN = 0.02
"""Radians by which a target near a wrist singularity is turned to find starts."""
_SETTLE_ITERATIONS = 1000
"""Levenberg-Marquardt steps the hot path gives a start that Newton's steps did not bring to a
solution (see :meth:`DHChain.settle`). A start still making progress when they run out is
unrefined and, if it could be nearer, sends the call to the general path (~3 ms): next to the
wrist singularity, steps crawling along the self-motion toward a root took 1000-3000 with
fixed damping factors (the bench's wrist and limits families: 10 of 2000 calls on the general
path with 1000 steps, 7 with 3000). With Nielsen's damping (``adaptive``) the runs that reach
a root take at most a few hundred steps, and those still crawling at 1000 steps (the error
falling like ~1/steps between 1e-7 and 1e-9) still crawl at 3000: bench/ik.py's families,
seed TCP, 1000 poses each, give the same calls to the general path with 1000 steps as with
3000 (wrist 3, limits 4, elbow 1, uniform 1, shoulder 0), 2000 steps sooner, and the same
answers but one (limits: another root 2e-4 rad away, nearer the seed); 500 steps: one more
call each in wrist and limits."""
_STATIONARY = 1e-6
"""``‖Jᵀe‖ / (‖J‖·‖e‖)`` below which a start that did not converge has reached a local minimum
of the error: the branch has no calibrated solution, and is no rival."""
_RIVAL_FACTOR = 3.0
"""How much farther than the farthest refined one an unrefined nominal branch away from the
singularities is assumed to move at most (see :meth:`DHChain.nearest`)."""
_NEAR_SINGULAR = 0.2
"""|sin θ3| or |sin θ5| below which, or the wrist centre's distance from the shoulder
singularity over d4 below which, a nominal branch is always refined: refinement can move it
far."""
_BRANCHES = 8
"""The nominal closed form's branches where none is missing (2 shoulders, 2 wrists, 2 elbows)."""
_START_SLACK = 0.2
"""Radians by which the hot path widens the joint limits for its nominal starts."""
_SINGULAR_MOVE = 0.1
"""Radians (Euclidean): a refinement that moves a nominal start farther is next to a
singularity; where the nominal arm also lacks a branch, the hot path refines the branches of
the seed-corrected target too."""


BRANCH_TOLERANCE = 0.05
"""rad: how far the calibrated solution may lie from the nominal one it was refined from."""


class CalibratedKinematics(Kinematics):
    """A UR3e with a factory calibration (and a TCP): FK and IK on the calibrated model.

    ``forward``, ``joint_frames`` and ``jacobian`` are the calibrated chain's; ``inverse`` and
    ``inverse_all`` refine the nominal closed-form branches onto it. With all-zero deltas it
    equals :class:`Kinematics` to rounding error.
    """

    def __init__(
        self,
        calibration: Calibration,
        tcp: Sequence[float] | Pose | None = None,
        limits: tuple[Sequence[float], Sequence[float]] | None = None,
    ) -> None:
        super().__init__(UR3E_DH, tcp, limits)
        self.calibration = calibration
        self.nominal = Kinematics(UR3E_DH, self.tcp, (self.lower, self.upper))
        # the hot path's starts: the nominal model with the limits widened by _START_SLACK,
        # so that a branch whose calibrated solution is just inside a limit its nominal one
        # is just beyond still has its start, at its distance from the seed
        self._starts = Kinematics(
            UR3E_DH,
            self.tcp,
            (
                [v - _START_SLACK for v in self.lower],
                [v + _START_SLACK for v in self.upper],
            ),
        )
        theta, a, d, alpha = calibration.dh()
        # Rz(q + θ)·Tz(d)·Tx(a)·Rx(α) = Rz(q)·C with C fixed per joint
        self._links = [dh_transform(theta[j], d[j], a[j], alpha[j]) for j in range(6)]
        self._chain = Chain(theta, a, d, alpha, self._tcp)
        if NATIVE:  # the hot path in one call (Chain.fast): the starts' closed form too
            s = self._starts
            self._chain.hot_path(
                s._geom, s._tcp, s._tcp_inv, s._tcp_is_identity, s.lower, s.upper,
                self.lower, self.upper, _FAST_ITERATIONS, _SETTLE_ITERATIONS, CONVERGED,
                _ROUNDING, _STATIONARY, ACCEPTED, _RIVAL_FACTOR, _NEAR_SINGULAR,
                _SINGULAR_MOVE, _LENIENT_H2, _LENIENT_C3, _EDGE_C3, _LENIENT_WRIST,
                _WRIST_EPS, _BRANCHES,
            )  # fmt: skip
        self.fallbacks = 0
        """Calls of :meth:`inverse` (without ``valid`` or a margin) that the hot path left to
        the general one (the benchmark reports it)."""

    @classmethod
    def ur3e_calibrated(
        cls,
        calibration: Calibration,
        tcp: Sequence[float] | Pose | None = None,
        limits: JointLimits | tuple[Sequence[float], Sequence[float]] | None = None,
    ) -> CalibratedKinematics:
        """The calibrated UR3e; ``limits`` a JointLimits or ``(lower, upper)``."""
        if limits is not None and not isinstance(limits, tuple):
            limits = (limits.position_min, limits.position_max)
        return cls(calibration, tcp, limits)

    def with_tcp(self, tcp: Sequence[float] | Pose | None) -> CalibratedKinematics:
        return CalibratedKinematics(self.calibration, tcp, (self.lower, self.upper))

    # ------------------------------------------------------------ forward

    def _frames(self, q: ArrayLike) -> FloatArray:
        qq = _joints(q)
        out = np.empty((8, 4, 4))
        out[0] = np.eye(4)
        for j in range(6):
            C = self._links[j]
            c, s = math.cos(qq[j]), math.sin(qq[j])
            A = C.copy()
            A[0] = c * C[0] - s * C[1]
            A[1] = s * C[0] + c * C[1]
            out[j + 1] = out[j] @ A
        out[7] = out[6] @ self._tcp_matrix
        return out

    def forward(self, q: ArrayLike) -> Pose:
        f = self._chain.frame(_joints(q))
        return Pose._raw(np.array(f[9:]), np.array((f[0:3], f[3:6], f[6:9])))

    def forward_rows(self, q: ArrayLike) -> list[float]:
        return self._chain.frame(_joints(q))

    def forward_flange(self, q: ArrayLike) -> Pose:
        F = self._frames(q)[6]
        return Pose._raw(F[:3, 3].copy(), F[:3, :3].copy())

    def _flange(self, q: Sequence[float]) -> list[float]:
        F = self._frames(q)[6]
        out: list[float] = [*F[:3, :3].ravel().tolist(), *F[:3, 3].tolist()]
        return out

    def jacobian(self, q: ArrayLike) -> FloatArray:
        return np.array(self._chain.frame_and_jacobian(_joints(q))[1]).reshape(6, 6)

    # ------------------------------------------------------------ inverse

    def solve(
        self,
        q_nominal: ArrayLike,
        target: Pose,
        *,
        patient: bool = False,
        seed: Sequence[float] | None = None,
    ) -> FloatArray | None:
        """Refine a nominal solution onto the calibrated model; None if it does not converge
        or has no 2π-equivalent within the joint limits. Each joint is the equivalent nearest
        ``seed`` (default: the start). ``patient``: Levenberg-Marquardt for many iterations
        instead of a few Newton steps (for starts far from a solution)."""
        start = _joints(q_nominal)
        if patient:
            qq, err, _ = self._chain.settle(
                start, _rows(target), _PATIENT_ITERATIONS, CONVERGED, 0.0
            )
        else:
            qq, err = self._chain.newton(start, _rows(target), _ITERATIONS, CONVERGED, _ROUNDING)
        if err > ACCEPTED:
            return None
        shifted = self._shifted(qq, start if seed is None else seed)
        return None if shifted is None else np.array(shifted)

    def _shifted(self, q: list[float], seed: Sequence[float]) -> list[float] | None:
        """Each joint's 2π-equivalent nearest ``seed`` within the limits (None: none)."""
        out = []
        for v, s, lo, hi in zip(q, seed, self.lower, self.upper, strict=True):
            w = _near(v, s, lo, hi)
            if w != w:
                return None
            out.append(w)
        return out

    def nominal_target(self, target: Pose, q: ArrayLike) -> Pose:
        """``target`` moved by the nominal model's offset from the calibrated one at ``q``:
        the pose whose nominal inverse lands near the calibrated solution when ``q`` is near it
        (the offset changes slowly with ``q``). Keeps the closed form in reach of poses at the
        edge of the nominal workspace."""
        F = self.forward(q).matrix
        R, p = F[:3, :3], F[:3, 3]
        F_inv = np.eye(4)
        F_inv[:3, :3] = R.T
        F_inv[:3, 3] = -(R.T @ p)
        M = self.nominal.forward(q).matrix @ F_inv @ target.matrix
        return Pose._raw(M[:3, 3].copy(), M[:3, :3].copy())

    def _corrected(self, target: Pose, q: FloatArray) -> FloatArray:
        """The nominal solution for ``target`` corrected by the offset at ``q`` (a nominal
        solution of a branch): on the same branch and ~1e-6 m from the calibrated solution;
        ``q`` itself if the corrected target has no solution."""
        try:
            return self.nominal.inverse(self.nominal_target(target, q), q)
        except UnreachableError:
            return q

    def _solutions(
        self, target: Pose, seed: FloatArray, *, thorough: bool = True
    ) -> Iterator[FloatArray]:
        """Calibrated solutions, distinct, lazily: each start (see :meth:`_start_groups`)
        refined directly and, if that fails, re-solved for the target corrected by the offset
        on its own branch, then refined; each joint shifted by 2π toward ``seed``. Not
        ``thorough``: the starts at the edge of the workspace only if the first group (the
        target's and the seed-corrected target's nominal branches) finds nothing.

        A start within _SAME_START of one tried already (per joint) is skipped: one array
        operation against all of them (the edge group brings up to ~80 starts; a NumPy
        call per pair took ~1.5 ms of a call next to the wrist singularity)."""
        tried: list[FloatArray] = []
        found: list[FloatArray] = []
        s = seed.tolist()
        for group in self._start_groups(target, seed):
            if found and not thorough:
                return
            for start in group:
                if tried and bool(
                    (np.abs(np.array(tried) - start).max(axis=1) < _SAME_START).any()
                ):
                    continue
                tried.append(start)
                q = self.solve(start, target, seed=s)
                if q is None:
                    q = self.solve(self._corrected(target, start), target, seed=s)
                if q is not None and not any(np.max(np.abs(q - f)) < 1e-9 for f in found):
                    found.append(q)
                    yield q
        if found:
            return
        # Near a wrist singularity at the edge of the workspace (e.g. the elbow folded) the
        # nominal branches can be a tenth of a radian from the calibrated solution, where
        # Newton's steps overshoot; damped steps get there (about 1 pose in 10^4).
        for start in tried:
            q = self.solve(start, target, patient=True, seed=s)
            if q is not None and not any(np.max(np.abs(q - f)) < 1e-9 for f in found):
                found.append(q)
                yield q
        if found:
            return
        # Exactly wrist-singular with the arm nearly stretched: the nominal closed form has
        # no branch, and damped steps from one point of the wrist's self-motion (θ4 and θ6
        # turning together) can stall; from points a quarter turn apart along it, with more
        # steps, one gets there (a few poses in 10^3 of the bench's wrist family).
        goal = _rows(target)
        for start in tried:
            for turn in _SELF_MOTION_TURNS:
                for sign in (1.0, -1.0):
                    moved = start.tolist()
                    moved[3] += turn
                    moved[5] -= sign * turn
                    qq, err, _ = self._chain.settle(
                        moved, goal, _SELF_MOTION_ITERATIONS, CONVERGED, 0.0
                    )
                    if err > ACCEPTED:
                        continue
                    shifted = self._shifted(qq, s)
                    if shifted is None:
                        continue
                    q = np.array(shifted)
                    if not any(np.max(np.abs(q - f)) < 1e-9 for f in found):
                        found.append(q)
                        yield q
            if found:
                return

    def _start_groups(self, target: Pose, seed: FloatArray) -> Iterator[list[FloatArray]]:
        """Nominal solutions to start from, nearest ``seed`` first within each group: for the
        target and the seed-corrected target; then, since a branch at the edge of the nominal
        workspace (arm stretched, wrist centre near axis 1, wrist singular) may have none, for
        targets moved a little inwards (towards the shoulder), outwards (away from axis 1)
        and turned about the tool's axes; last the seed itself."""

        s = seed.tolist()

        def distance2(q: FloatArray) -> float:
            # np.sum((q - seed) ** 2) in plain floats, in its order (the same value): ~4x
            # faster on the ~80 starts of the edge group
            d = 0.0
            for v, w in zip(q.tolist(), s, strict=True):
                d += (v - w) * (v - w)
            return d

        def nearest_first(poses: list[Pose]) -> list[FloatArray]:
            out = [q for pose in poses for q in self.nominal.inverse_all(pose, seed)]
            out.sort(key=distance2)
            return out

        yield nearest_first([target, self.nominal_target(target, seed)])
        p, R = target.position, target.rotation
        inwards = np.array([0.0, 0.0, UR3E_DH.d[0]]) - p
        inwards /= max(float(np.linalg.norm(inwards)), 1e-9)
        outwards = np.array([p[0], p[1], 0.0])
        outwards /= max(float(np.linalg.norm(outwards)), 1e-9)
        edge = [Pose._raw(p + step * d, R) for step in _EDGE_STEPS for d in (inwards, outwards)]
        edge += [
            Pose._raw(p, R @ rotvec_to_matrix(sign * _EDGE_TURN * axis))
            for axis in np.eye(3)
            for sign in (1.0, -1.0)
        ]
        yield nearest_first(edge)
        yield [seed]

    def _nearest_fast(self, target: Pose, seed: list[float]) -> FloatArray | None:
        """The hot path of :meth:`inverse`: the nominal branches refined (in C when
        :data:`NATIVE`, see :meth:`DHChain.nearest`), the result nearest the seed; None to
        leave the decision to the general path.

        The deltas move a solution by millimetres over the UR3e's ~0.1 m lever arms (a few
        hundredths of a radian), more next to a singularity, and may so reorder branches
        that the nominal solutions put about equally far from the seed: a branch is refined
        unless it is farther than the best found plus _RIVAL_FACTOR × the largest move a
        refinement made, and always next to a singularity (_NEAR_SINGULAR). When a
        refinement moved by over _SINGULAR_MOVE or the target is next to a singularity, and
        the nominal arm lacks a branch there, or at the edge of its workspace, the branches
        of the target corrected by the offset at the seed are refined too: the deltas can
        take the seed's own branch out of the nominal solutions of the target (a wrist near
        θ5 = 0 turns by tenths of a radian per millimetre).

        Where a nominal branch is within _LENIENT_WRIST of the wrist singularity, members
        of its continuum are starts too (:meth:`Kinematics._continuum_starts`), from which
        the refinement walks the valley.

        With the C extension (:data:`NATIVE`) all of this is one call, ``Chain.fast`` (the
        nominal closed form written out in C as well), which computes
        :meth:`_nearest_python` bit for bit (tests/test_native.py)."""
        goal = _rows(target)
        if NATIVE:
            best = self._chain.fast(goal, seed)
            return None if best is None else np.array(best)
        return self._nearest_python(target, goal, seed)

    def _nearest_python(
        self, target: Pose, goal: list[float], seed: list[float]
    ) -> FloatArray | None:
        """:meth:`_nearest_fast` with the nominal closed form of :class:`Kinematics`
        (``goal``: ``target`` as 12 floats)."""
        starts = self._starts
        nearest, candidates, _, edge = starts.nearest_within(target, seed, math.inf, lenient=True)
        if nearest is None:
            return None
        best, best_d, moved, unrefined, singular = self._refine(candidates, goal, seed)
        if best is None or unrefined <= math.sqrt(best_d) + _RIVAL_FACTOR * moved:
            return None
        if edge or (len(candidates) < _BRANCHES and (singular or moved > _SINGULAR_MOVE)):
            corrected = _compose(
                _compose(starts.forward_rows(seed), _inverse_rows(self._chain.frame(seed))),
                goal,
            )
            own, candidates, _, _ = starts.nearest_within(
                _pose(corrected), seed, math.inf, lenient=True
            )
            if own is not None:
                q, d, _, _, _ = self._refine(candidates, goal, seed)
                if q is not None and d < best_d:
                    best = q
        return np.array(best)

    def _refine(
        self, starts: list[tuple[float, list[float]]], goal: list[float], seed: list[float]
    ) -> tuple[list[float] | None, float, float, float, int]:
        """:meth:`DHChain.nearest` with the hot path's settings."""
        return self._chain.nearest(
            starts,
            goal,
            seed,
            self.lower,
            self.upper,
            _FAST_ITERATIONS,
            _SETTLE_ITERATIONS,
            CONVERGED,
            _ROUNDING,
            _STATIONARY,
            ACCEPTED,
            _RIVAL_FACTOR,
            _NEAR_SINGULAR,
        )

    def inverse(
        self,
        pose: Pose | Sequence[float],
        seed: ArrayLike | None = None,
        *,
        valid: JointValidity | None = None,
        singularity_margin: float | None = None,
        refine: bool = False,
    ) -> FloatArray:
        """As :meth:`Kinematics.inverse`, on the calibrated model (``refine`` is implied)."""
        target = pose if isinstance(pose, Pose) else Pose.parse(pose)
        s_list = [0.0] * 6 if seed is None else list(_joints(seed))
        if valid is None and singularity_margin is None:
            fast = self._nearest_fast(target, s_list)
            if fast is not None:
                return fast
            self.fallbacks += 1
        s = np.array(s_list)
        singular: str | None = None
        rejected = 0
        everything = self._solutions(target, s, thorough=valid is not None)
        candidates = sorted(everything, key=lambda q: float(np.sum((q - s) ** 2)))
        for q in candidates:
            if singularity_margin is not None:
                kind = self.singularity(q, distance=singularity_margin, sine=singularity_margin)
                if kind is not None:
                    singular = singular or kind
                    continue
            if valid is not None and not valid(q):
                rejected += 1
                continue
            return q
        if rejected == 0 and singular is not None:
            raise SingularityError(
                f"every inverse-kinematics solution for {target!r} is within "
                f"{singularity_margin} of a singularity (the nearest: {singular})"
            )
        if rejected == 0:
            raise UnreachableError(
                f"no inverse-kinematics solution of the calibrated arm within the limits: "
                f"{target!r}"
            )
        raise UnreachableError(
            f"{rejected} inverse-kinematics solutions within the joint limits, "
            f"none accepted by the validity check, for {target!r}"
        )

    def inverse_near(self, pose: Pose, seed: ArrayLike) -> FloatArray:
        """The solution continuous with ``seed`` (a path's next point): the closed form's
        nearest, as :meth:`inverse`."""
        return self.inverse(pose, seed)

    def inverse_all(
        self, pose: Pose | Sequence[float], seed: ArrayLike | None = None
    ) -> list[FloatArray]:
        """Each nominal branch refined onto the calibrated model, nearest ``seed`` first."""
        target = pose if isinstance(pose, Pose) else Pose.parse(pose)
        s = np.zeros(6) if seed is None else np.array(_joints(seed))
        out = list(self._solutions(target, s))
        out.sort(key=lambda q: float(np.sum((q - s) ** 2)))
        return out


def _inverse_rows(f: list[float]) -> list[float]:
    """The inverse of a rigid transform given as 12 floats (rotation row-major, position)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22, x, y, z = f
    return [
        r00, r10, r20, r01, r11, r21, r02, r12, r22,
        -(r00 * x + r10 * y + r20 * z),
        -(r01 * x + r11 * y + r21 * z),
        -(r02 * x + r12 * y + r22 * z),
    ]  # fmt: skip


def _pose(f: list[float]) -> Pose:
    """A pose from 12 floats (rotation row-major, then position)."""
    return Pose._raw(np.array(f[9:]), np.array(f[:9]).reshape(3, 3))


def _rows(pose: Pose) -> list[float]:
    """A pose as 12 floats: rotation row-major, then position."""
    out: list[float] = [*pose.rotation.ravel().tolist(), *pose.position.tolist()]
    return out


def calibrated_model(calibration: Calibration, tcp: Pose | None = None) -> Any:
    """Pinocchio model of the calibrated UR3e in UR's base frame: revolute-z joints named as
    UR's (``shoulder_pan_joint`` ...), frames ``tool0`` (flange) and ``tcp``."""
    import pinocchio as pin

    theta, a, d, alpha = calibration.dh()
    model = pin.Model()
    model.name = "ur3e_calibrated"
    parent = 0
    placement = pin.SE3.Identity()
    for j in range(6):
        parent = model.addJoint(parent, pin.JointModelRZ(), placement, JOINT_NAMES[j])
        placement = pin.SE3(dh_transform(theta[j], d[j], a[j], alpha[j]))
    flange = model.addFrame(pin.Frame("tool0", parent, placement, pin.FrameType.OP_FRAME))
    tool = placement * pin.SE3((tcp or Pose.identity()).matrix)
    model.addFrame(pin.Frame("tcp", parent, flange, tool, pin.FrameType.OP_FRAME))
    return model


CONTROLLER = "controller"
"""``robot.calibration`` value (the default): read the calibration from the controller at
connect."""
NOMINAL = "nominal"
"""``robot.calibration`` value: UR's nominal model, by explicit choice."""


def kinematics_for(config: CellConfig) -> Kinematics:
    """The arm of a configuration: calibrated when ``robot.calibration`` names a file (read
    here; CalibrationError if it is unreadable), else the nominal UR3e (``nominal``, or until
    the Cell has read the controller's calibration); with the tool's TCP and the limits."""
    source = config.robot.calibration
    if source is None or source in (CONTROLLER, NOMINAL):
        return Kinematics.ur3e(config.tool.tcp, config.limits)
    return calibrated_kinematics(config, Calibration.load(source))


def calibrated_kinematics(config: CellConfig, calibration: Calibration) -> Kinematics:
    """The configuration's arm (TCP, limits) with ``calibration``; nominal if all-zero."""
    tcp, limits = config.tool.tcp, config.limits
    if calibration.is_nominal:
        return Kinematics.ur3e(tcp, limits)
    return CalibratedKinematics.ur3e_calibrated(calibration, tcp, limits)
