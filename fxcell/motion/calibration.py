"""Calibrated UR kinematics: the closed form on the nominal model, refined on the calibrated one.

A calibrated arm's DH parameters differ from the nominal ones by up to millimetres and
milliradians (:class:`fxcell.calibration.Calibration`), which breaks the closed-form inverse
(it needs exactly parallel middle axes). :class:`CalibratedKinematics` keeps the
:class:`~fxcell.motion.kinematics.Kinematics` interface: its forward kinematics is the
calibrated DH chain, and its inverse takes each closed-form branch of the nominal model as the
start of Gauss-Newton steps on the calibrated one (by default with Pinocchio, on the model of
:func:`calibrated_model`; ``backend="numpy"`` for the simulator, which must not load
Pinocchio). Two or three steps bring a millimetre-off start to ~1e-13 m.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from fxcell.calibration import Calibration
from fxcell.errors import SingularityError, UnreachableError
from fxcell.geometry import Pose, matrix_to_rotvec, rotvec_to_matrix
from fxcell.motion.kinematics import (
    JOINT_NAMES,
    TWO_PI,
    UR3E_DH,
    FloatArray,
    JointValidity,
    Kinematics,
    _joints,
    dh_transform,
)

if TYPE_CHECKING:
    from fxcell.config import CellConfig, JointLimits

Backend = Literal["pinocchio", "numpy"]

CONVERGED = 1e-12
"""Pose error norm (m and rad together) at which refinement stops."""
ACCEPTED = 1e-9
"""Pose error norm above which a refined branch is dropped (did not converge)."""
_ITERATIONS = 20
_PATIENT_ITERATIONS = 400  # Levenberg-Marquardt's, from far starts (rarely needed)
_EDGE_STEPS = (0.005, 0.02)
"""Metres by which a target at the edge of the nominal workspace is moved to find starts."""
_ROUNDING = 1e-11
"""Pose error norm below which a step that does not improve ends the refinement."""
_SAME_START = 0.05
"""Radians (per joint) within which two starting points count as one."""
_EDGE_TURN = 0.02
"""Radians by which a target near a wrist singularity is turned to find starts."""


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
        *,
        backend: Backend = "pinocchio",
    ) -> None:
        super().__init__(UR3E_DH, tcp, limits)
        self.calibration = calibration
        self.backend: Backend = backend
        self.nominal = Kinematics(UR3E_DH, self.tcp, (self.lower, self.upper))
        theta, a, d, alpha = calibration.dh()
        # Rz(q + θ)·Tz(d)·Tx(a)·Rx(α) = Rz(q)·C with C fixed per joint
        self._links = [dh_transform(theta[j], d[j], a[j], alpha[j]) for j in range(6)]
        self._pin: Any = None

    @classmethod
    def ur3e_calibrated(
        cls,
        calibration: Calibration,
        tcp: Sequence[float] | Pose | None = None,
        limits: JointLimits | tuple[Sequence[float], Sequence[float]] | None = None,
        *,
        backend: Backend = "pinocchio",
    ) -> CalibratedKinematics:
        """The calibrated UR3e; ``limits`` a JointLimits or ``(lower, upper)``."""
        if limits is not None and not isinstance(limits, tuple):
            limits = (limits.position_min, limits.position_max)
        return cls(calibration, tcp, limits, backend=backend)

    def with_tcp(self, tcp: Sequence[float] | Pose | None) -> CalibratedKinematics:
        return CalibratedKinematics(
            self.calibration, tcp, (self.lower, self.upper), backend=self.backend
        )

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

    def _tcp_frame(self, q: FloatArray) -> FloatArray:
        """4×4 TCP frame (Pinocchio when that is the backend: faster)."""
        if self.backend == "pinocchio":
            pin, model, data, fid = self._pinocchio()
            pin.framesForwardKinematics(model, data, q)
            out: FloatArray = data.oMf[fid].homogeneous
            return out
        frame: FloatArray = self._frames(q)[7]
        return frame

    def forward(self, q: ArrayLike) -> Pose:
        F = self._frames(q)[7]
        return Pose._raw(F[:3, 3].copy(), F[:3, :3].copy())

    def forward_rows(self, q: ArrayLike) -> list[float]:
        F = self._frames(q)[7]
        out: list[float] = [*F[:3, :3].ravel().tolist(), *F[:3, 3].tolist()]
        return out

    def forward_flange(self, q: ArrayLike) -> Pose:
        F = self._frames(q)[6]
        return Pose._raw(F[:3, 3].copy(), F[:3, :3].copy())

    def _flange(self, q: Sequence[float]) -> list[float]:
        F = self._frames(q)[6]
        out: list[float] = [*F[:3, :3].ravel().tolist(), *F[:3, 3].tolist()]
        return out

    # ------------------------------------------------------------ inverse

    def solve(
        self, q_nominal: ArrayLike, target: Pose, *, patient: bool = False
    ) -> FloatArray | None:
        """Refine a nominal solution onto the calibrated model; None if it does not converge
        or leaves the joint limits (also after shifts by 2π). ``patient``: Levenberg-Marquardt
        for many iterations instead of a few Newton steps (for starts far from a solution)."""
        start = np.array(_joints(q_nominal))
        q, err = self._marquardt(start, target) if patient else self._newton(start, target)
        if err > ACCEPTED:
            return None
        for j in range(6):
            v = float(q[j])
            if v < self.lower[j]:
                v += TWO_PI * math.ceil((self.lower[j] - v) / TWO_PI)
            elif v > self.upper[j]:
                v -= TWO_PI * math.ceil((v - self.upper[j]) / TWO_PI)
            if not self.lower[j] <= v <= self.upper[j]:
                return None
            q[j] = v
        return q

    def nominal_target(self, target: Pose, q: ArrayLike) -> Pose:
        """``target`` moved by the nominal model's offset from the calibrated one at ``q``:
        the pose whose nominal inverse lands near the calibrated solution when ``q`` is near it
        (the offset changes slowly with ``q``). Keeps the closed form in reach of poses at the
        edge of the nominal workspace."""
        F = self._tcp_frame(np.array(_joints(q)))
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

    def _solutions(self, target: Pose, seed: FloatArray) -> Iterator[FloatArray]:
        """Calibrated solutions, distinct, lazily: each start (see :meth:`_start_groups`)
        re-solved for the target corrected by the offset on its own branch, then refined."""
        tried: list[FloatArray] = []
        found: list[FloatArray] = []
        for group in self._start_groups(target, seed):
            for start in group:
                if any(np.max(np.abs(start - t)) < _SAME_START for t in tried):
                    continue
                tried.append(start)
                q = self.solve(self._corrected(target, start), target)
                if q is not None and not any(np.max(np.abs(q - f)) < 1e-9 for f in found):
                    found.append(q)
                    yield q
        if found:
            return
        # Near a wrist singularity at the edge of the workspace (e.g. the elbow folded) the
        # nominal branches can be a tenth of a radian from the calibrated solution, where
        # Newton's steps overshoot; damped steps get there (about 1 pose in 10^4).
        for start in tried:
            q = self.solve(start, target, patient=True)
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
        s = np.zeros(6) if seed is None else np.array(_joints(seed))
        if valid is None and singularity_margin is None:
            try:
                start = self.nominal.inverse(target, s)
                q = self.solve(self._corrected(target, start), target)
                # At the edge of the workspace the seed's branch can be missing from the
                # nominal solutions of the target (the deltas move the wrist out of nominal
                # reach); the target corrected at the seed still has it. Only when both
                # agree is the nearest nominal branch the nearest calibrated one.
                seed_branch = self.nominal.inverse(self.nominal_target(target, s), s)
            except UnreachableError:
                q = None
            # the refinement must stay on the nominal branch nearest the seed (the deltas
            # are millimetres); Newton that wandered to another branch is not an answer
            if (
                q is not None
                and float(np.max(np.abs(q - start))) < BRANCH_TOLERANCE
                and float(np.max(np.abs(seed_branch - start))) < BRANCH_TOLERANCE
            ):
                return q
        singular: str | None = None
        rejected = 0
        candidates = sorted(self._solutions(target, s), key=lambda q: float(np.sum((q - s) ** 2)))
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

    # ------------------------------------------------------------ Pinocchio

    def _pinocchio(self) -> tuple[Any, Any, Any, int]:
        if self._pin is None:
            import pinocchio as pin

            model = calibrated_model(self.calibration, self.tcp)
            self._pin = (pin, model, model.createData(), model.getFrameId("tcp"))
        out: tuple[Any, Any, Any, int] = self._pin
        return out

    def _tcp_and_jacobian(self, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """TCP frame (4×4) and geometric Jacobian (rows v, ω; base frame) at ``q``."""
        if self.backend == "pinocchio":
            pin, model, data, fid = self._pinocchio()
            J = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL_WORLD_ALIGNED)
            F: FloatArray = data.oMf[fid].homogeneous  # computeFrameJacobian placed the frames
            return F, J
        frames = self._frames(q)
        z = frames[:6, :3, 2]
        d = frames[7, :3, 3] - frames[:6, :3, 3]
        return frames[7], np.vstack((np.cross(z, d).T, z.T))

    def _newton(self, q: FloatArray, target: Pose) -> tuple[FloatArray, float]:
        """Newton steps on the TCP pose error; a step that does not lower the error is
        retried damped (Levenberg-Marquardt), as near a singularity."""
        Rt, pt = target.rotation, target.position

        def error(F: FloatArray) -> FloatArray:
            return np.concatenate((pt - F[:3, 3], matrix_to_rotvec(Rt @ F[:3, :3].T)))

        F, J = self._tcp_and_jacobian(q)
        err = error(F)
        norm = float(np.linalg.norm(err))
        lam = 0.0
        for _ in range(_ITERATIONS):
            if norm < CONVERGED:
                break
            try:
                if lam == 0.0:
                    step = np.linalg.solve(J, err)
                else:
                    step = J.T @ np.linalg.solve(J @ J.T + lam * np.eye(6), err)
            except np.linalg.LinAlgError:
                lam = max(lam, 1e-9)
                continue
            trial = q + step
            F, J_trial = self._tcp_and_jacobian(trial)
            trial_err = error(F)
            trial_norm = float(np.linalg.norm(trial_err))
            if trial_norm < norm:
                q, J, err, norm = trial, J_trial, trial_err, trial_norm
                lam *= 0.1 if lam > 1e-9 else 0.0
            else:
                if norm < _ROUNDING:  # at the rounding floor: no better step exists
                    break
                lam = 1e-6 if lam == 0.0 else lam * 10.0
                if lam > 1.0:
                    break
                if self.backend == "pinocchio":
                    self._tcp_and_jacobian(q)  # keep Pinocchio's data at q
        return q, norm

    def _marquardt(self, q: FloatArray, target: Pose) -> tuple[FloatArray, float]:
        """Levenberg-Marquardt (diagonal scaling) on the TCP pose error, for far starts."""
        Rt, pt = target.rotation, target.position

        def error(F: FloatArray) -> FloatArray:
            return np.concatenate((pt - F[:3, 3], matrix_to_rotvec(Rt @ F[:3, :3].T)))

        F, J = self._tcp_and_jacobian(q)
        err = error(F)
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
            F, J_trial = self._tcp_and_jacobian(trial)
            trial_err = error(F)
            trial_norm = float(np.linalg.norm(trial_err))
            if trial_norm < norm:
                q, J, err, norm = trial, J_trial, trial_err, trial_norm
                lam = max(lam / 3.0, 1e-12)
            else:
                lam *= 4.0
                if lam > 1e8:
                    break
                if self.backend == "pinocchio":
                    self._tcp_and_jacobian(q)  # keep Pinocchio's data at q
        return q, norm


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
"""``robot.calibration`` value: read the calibration from the controller at connect."""


def kinematics_for(config: CellConfig, *, backend: Backend = "pinocchio") -> Kinematics:
    """The arm of a configuration: calibrated when ``robot.calibration`` names a file (read
    here; CalibrationError if it is unreadable), else the nominal UR3e (until the Cell has
    read the controller's calibration); with the tool's TCP and the joint limits."""
    source = config.robot.calibration
    if source is None or source == CONTROLLER:
        return Kinematics.ur3e(config.tool.tcp, config.limits)
    return calibrated_kinematics(config, Calibration.load(source), backend=backend)


def calibrated_kinematics(
    config: CellConfig, calibration: Calibration, *, backend: Backend = "pinocchio"
) -> Kinematics:
    """The configuration's arm (TCP, limits) with ``calibration``; nominal if all-zero."""
    tcp, limits = config.tool.tcp, config.limits
    if calibration.is_nominal:
        return Kinematics.ur3e(tcp, limits)
    return CalibratedKinematics.ur3e_calibrated(calibration, tcp, limits, backend=backend)
