"""Calibrated UR kinematics: the closed form on the nominal model, refined on the calibrated one.

A calibrated arm's DH parameters differ from the nominal ones by up to millimetres and
milliradians (:class:`fxcell.calibration.Calibration`), which breaks the closed-form inverse
(it needs exactly parallel middle axes). :class:`CalibratedKinematics` keeps the
:class:`~fxcell.motion.kinematics.Kinematics` interface: its forward kinematics is the
calibrated DH chain, and its inverse takes the closed-form branch of the nominal model nearest
the seed as the start of Newton steps on the calibrated one, with the analytic Jacobian, in
plain floats (:class:`~fxcell.motion.kinematics.DHChain`, compiled with the rest of that
module): three or four steps bring a millimetre-off start to the rounding floor. Only when
another branch could come nearer the seed once moved by the deltas, or the nominal closed form
has no branch there (at the edge of its workspace, next to a singularity), are more starts
refined. No Pinocchio: the simulator uses this module too.
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
    JOINT_NAMES,
    UR3E_DH,
    DHChain,
    FloatArray,
    JointValidity,
    Kinematics,
    _compose,
    _joints,
    _near,
    _twist_to,
    dh_transform,
)

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
_EDGE_STEPS = (0.005, 0.02)
"""Metres by which a target at the edge of the nominal workspace is moved to find starts."""
_ROUNDING = 1e-11
"""Pose error norm below which a step that does not improve ends the refinement."""
_SAME_START = 0.05
"""Radians (per joint) within which two starting points count as one."""
_EDGE_TURN = 0.02
"""Radians by which a target near a wrist singularity is turned to find starts."""
_CORRECTIONS = 3
"""Offset corrections of a start Newton's steps did not bring to a solution (each followed by
Newton steps again): see :meth:`CalibratedKinematics._corrected_newton`."""
_SETTLE_ITERATIONS = 60
"""Levenberg-Marquardt steps the hot path gives a start that Newton's steps and the offset
corrections did not bring to a solution (see :meth:`DHChain.settle`)."""
_STATIONARY = 1e-6
"""``‖Jᵀe‖ / (‖J‖·‖e‖)`` below which a start that did not converge has reached a local minimum
of the error: the branch has no calibrated solution, and is no rival."""
_RIVAL_MARGIN = 1.0
"""Radians (Euclidean in joint space) beyond the nearest nominal branch's distance from the
seed within which the hot path of :meth:`CalibratedKinematics.inverse` looks for a rival."""
_RIVAL_FACTOR = 3.0
"""How much farther than the refined branch moved a rival branch is assumed to move."""
_NEAR_SEED = 0.2
"""Radians (Euclidean) from the seed within which the hot path trusts the nominal branches of
the target alone (beyond, it also refines the branch of the seed-corrected target)."""


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
        theta, a, d, alpha = calibration.dh()
        # Rz(q + θ)·Tz(d)·Tx(a)·Rx(α) = Rz(q)·C with C fixed per joint
        self._links = [dh_transform(theta[j], d[j], a[j], alpha[j]) for j in range(6)]
        self._chain = DHChain(theta, a, d, alpha, self._tcp)
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
            q, err = self._marquardt(np.array(start), target)
            qq: list[float] = q.tolist()
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
        target's and the seed-corrected target's nominal branches) finds nothing."""
        tried: list[FloatArray] = []
        found: list[FloatArray] = []
        s = seed.tolist()
        for group in self._start_groups(target, seed):
            if found and not thorough:
                return
            for start in group:
                if any(np.max(np.abs(start - t)) < _SAME_START for t in tried):
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

    def _start_groups(self, target: Pose, seed: FloatArray) -> Iterator[list[FloatArray]]:
        """Nominal solutions to start from, nearest ``seed`` first within each group: for the
        target and the seed-corrected target; then, since a branch at the edge of the nominal
        workspace (arm stretched, wrist centre near axis 1, wrist singular) may have none, for
        targets moved a little inwards (towards the shoulder), outwards (away from axis 1)
        and turned about the tool's axes; last the seed itself."""

        def nearest_first(poses: list[Pose]) -> list[FloatArray]:
            out = [q for pose in poses for q in self.nominal.inverse_all(pose, seed)]
            out.sort(key=lambda q: float(np.sum((q - seed) ** 2)))
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
        """The hot path of :meth:`inverse`: the nominal solutions nearest ``seed`` (within
        _RIVAL_MARGIN of the nearest) refined by Newton steps, the nearest result if no
        other branch could come nearer once refined; else None (the general path decides).

        The deltas move a solution by up to a few tenths of a radian (millimetres over the
        UR3e's ~0.1 m lever arms; more next to a singularity), and may so reorder branches
        that the nominal solution puts about equally far from the seed. Any branch outside
        the margin is assumed to move at most _RIVAL_FACTOR times as far as the farthest
        refined. At the edge of the nominal workspace (arm nearly stretched or folded) the
        deltas can add a branch the nominal arm lacks: the general path looks for it."""
        goal = _rows(target)
        # within _RIVAL_MARGIN of the nearest nominal branch first; if none converges or a
        # branch beyond could still come nearer once refined, every branch (still far cheaper
        # than the general path)
        refined: dict[tuple[float, ...], tuple[list[float], float, bool]] = {}
        for margin in (_RIVAL_MARGIN, math.inf):
            nearest, candidates, bound, _ = self.nominal.nearest_within(
                target, seed, margin, lenient=True
            )
            if nearest is None:
                return None
            best: list[float] | None = None
            best_d = math.inf
            moved = 0.0
            unrefined = math.inf  # the nearest nominal solution that did not converge
            for d_nominal, start in candidates:
                if best is not None and math.sqrt(d_nominal) > (
                    math.sqrt(best_d) + _RIVAL_FACTOR * math.sqrt(moved) + 1e-9
                ):
                    break  # this one and the rest (farther) cannot come nearer
                key = tuple(start)
                if key not in refined:  # the second margin's round refines each start once
                    refined[key] = self._refine_start(start, goal)
                q, err, absent = refined[key]
                if err > ACCEPTED:
                    if not absent:
                        unrefined = min(unrefined, d_nominal)
                    continue
                m = sum((a - b) * (a - b) for a, b in zip(q, start, strict=True))
                moved = max(moved, m)
                shifted = self._shifted(q, seed)
                if shifted is None:
                    continue
                d = sum((a - b) * (a - b) for a, b in zip(shifted, seed, strict=True))
                if d < best_d:
                    best, best_d = shifted, d
            if best is None:
                continue  # none within the margin converged: every branch
            # every branch not refined, moved as far, stays farther than the best found
            reach = math.sqrt(best_d) + _RIVAL_FACTOR * math.sqrt(moved) + 1e-9
            if math.sqrt(unrefined) <= reach:
                return None
            if math.sqrt(bound) > reach:
                break
        else:
            return None
        if best_d > _NEAR_SEED * _NEAR_SEED:
            # Next to a singularity the deltas can take the seed's own branch out of the
            # nominal solutions of the target (a wrist near θ5 = 0 turns by tenths of a
            # radian per millimetre); the target corrected by the offset at the seed has it.
            corrected = _compose(
                _compose(self.nominal.forward_rows(seed), _inverse_rows(self._chain.frame(seed))),
                goal,
            )
            own = self.nominal.nearest_within(_pose(corrected), seed, 0.0, lenient=True)[0]
            if own is None or max(abs(a - b) for a, b in zip(own, best, strict=True)) < (
                BRANCH_TOLERANCE
            ):
                return np.array(best)  # no such branch, or the one found
            q, err = self._chain.newton(own, goal, _FAST_ITERATIONS, CONVERGED, _ROUNDING)
            if err > ACCEPTED:
                q, err = self._corrected_newton(own, goal)
            shifted = self._shifted(q, seed) if err <= ACCEPTED else None
            if shifted is not None:
                d = sum((a - b) * (a - b) for a, b in zip(shifted, seed, strict=True))
                if d < best_d - 1e-12:
                    return np.array(shifted)
        return np.array(best)

    def _refine_start(
        self, start: list[float], goal: list[float]
    ) -> tuple[list[float], float, bool]:
        """A nominal start refined by the hot path: Newton's steps, then the offset
        corrections, then Levenberg-Marquardt; the joints, the error norm left and, when it
        did not converge, whether it ended at a local minimum of the error (the branch has no
        calibrated solution: the target is beyond its reach)."""
        q, err = self._chain.newton(start, goal, _FAST_ITERATIONS, CONVERGED, _ROUNDING)
        if err > ACCEPTED:
            q, err = self._corrected_newton(start, goal)
        if err <= ACCEPTED:
            return q, err, False
        q, err, gradient = self._chain.settle(
            start, goal, _SETTLE_ITERATIONS, CONVERGED, _STATIONARY
        )
        return q, err, err > ACCEPTED and gradient <= _STATIONARY

    def _corrected_newton(self, start: list[float], goal: list[float]) -> tuple[list[float], float]:
        """Newton steps from ``start`` once it is corrected by the calibration's offset:
        up to _CORRECTIONS times the nominal solution (lenient, nearest the last) for the goal
        moved by the calibrated arm's error at the last, ``goal · F_cal(q)⁻¹ · F_nom(q)``;
        for starts next to a singularity, where the nominal branch is too far for Newton's
        steps (returns the last joints and the error norm left)."""
        q, err = start, math.inf
        for _ in range(_CORRECTIONS):
            moved = _compose(
                _compose(goal, _inverse_rows(self._chain.frame(q))), self.nominal.forward_rows(q)
            )
            nxt = self.nominal.nearest_within(_pose(moved), q, 0.0, lenient=True)[0]
            if nxt is None:
                break
            q = nxt
            q, err = self._chain.newton(q, goal, _FAST_ITERATIONS, CONVERGED, _ROUNDING)
            if err <= ACCEPTED:
                break
        return q, err

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

    def inverse_all(
        self, pose: Pose | Sequence[float], seed: ArrayLike | None = None
    ) -> list[FloatArray]:
        """Each nominal branch refined onto the calibrated model, nearest ``seed`` first."""
        target = pose if isinstance(pose, Pose) else Pose.parse(pose)
        s = np.zeros(6) if seed is None else np.array(_joints(seed))
        out = list(self._solutions(target, s))
        out.sort(key=lambda q: float(np.sum((q - s) ** 2)))
        return out

    def _marquardt(self, q: FloatArray, target: Pose) -> tuple[FloatArray, float]:
        """Levenberg-Marquardt (diagonal scaling) on the TCP pose error, for far starts."""
        goal = _rows(target)

        def evaluate(q: FloatArray) -> tuple[FloatArray, FloatArray]:
            frame, jac = self._chain.frame_and_jacobian(q.tolist())
            return np.array(_twist_to(frame, goal)), np.array(jac).reshape(6, 6)

        err, J = evaluate(q)
        norm = float(np.linalg.norm(err))
        lam = 1e-4
        for _ in range(_PATIENT_ITERATIONS):
            if norm < CONVERGED:
                break
            A = J.T @ J
            try:
                step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), J.T @ err)
            except np.linalg.LinAlgError:
                break
            trial = q + step
            trial_err, J_trial = evaluate(trial)
            trial_norm = float(np.linalg.norm(trial_err))
            if trial_norm < norm:
                q, J, err, norm = trial, J_trial, trial_err, trial_norm
                lam = max(lam / 3.0, 1e-12)
            else:
                lam *= 4.0
                if lam > 1e8:
                    break
        return q, norm


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
