"""Poses and rotations in UR's base frame.

A :class:`Pose` is a position (metres) and a rotation matrix. It converts to and from
every form fxcell meets: the teach pendant's and RTDE's ``[x, y, z, rx, ry, rz]`` (rotation
vector), quaternions ``(x, y, z, w)``, roll-pitch-yaw with ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``
(the UR/ROS convention) and 4×4 homogeneous matrices. The conversions are exact and stable
near the awkward angles (rotation vectors near 0 and π, pitch near ±π/2).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from numbers import Real
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fxcell.errors import InvalidTargetError
from fxcell.robot_specs import Vector6

FloatArray = NDArray[np.float64]

_ORTHO_TOL = 1e-6
"""How far from orthonormal (max abs of RᵀR − I) a matrix may be to count as a rotation."""


# ----------------------------------------------------------------- rotation conversions


def quaternion_to_matrix(q: ArrayLike) -> FloatArray:
    """Rotation matrix of a quaternion ``(x, y, z, w)``; it is normalised first."""
    x, y, z, w = _quaternion_floats(q)
    return _quat_matrix(x, y, z, w)


def _quaternion_floats(q: ArrayLike) -> tuple[float, float, float, float]:
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (4,) or not np.all(np.isfinite(arr)):
        raise InvalidTargetError(f"a quaternion is 4 finite numbers (x, y, z, w), got {q!r}")
    n = math.hypot(*(float(v) for v in arr))  # no overflow for huge components
    if n < 1e-6:
        raise InvalidTargetError(f"quaternion {q!r} has (almost) zero norm: not a rotation")
    x, y, z, w = (float(v) / n for v in arr)
    return x, y, z, w


def _quat_matrix(x: float, y: float, z: float, w: float) -> FloatArray:
    """Matrix of a unit quaternion (no checks)."""
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return np.array(
        [
            [1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)],
            [2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)],
            [2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)],
        ]
    )


def matrix_to_quaternion(R: ArrayLike) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)`` of a rotation matrix, with ``w >= 0``.

    Shepperd's method: the largest of the four candidate components is computed from the
    diagonal, the others from off-diagonal sums, so no branch loses precision.
    """
    m = np.asarray(R, dtype=np.float64)
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = m.tolist()
    return _rows_quaternion(r00, r01, r02, r10, r11, r12, r20, r21, r22)


def _rows_quaternion(
    r00: float,
    r01: float,
    r02: float,
    r10: float,
    r11: float,
    r12: float,
    r20: float,
    r21: float,
    r22: float,
) -> tuple[float, float, float, float]:
    """:func:`matrix_to_quaternion` of a rotation given as nine floats, row-major."""
    tr = r00 + r11 + r22
    if tr >= r00 and tr >= r11 and tr >= r22:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        w, x, y, z = 0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s
    elif r00 >= r11 and r00 >= r22:
        s = 2.0 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        w, x, y, z = (r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s
    elif r11 >= r22:
        s = 2.0 * math.sqrt(max(1.0 + r11 - r00 - r22, 0.0))
        w, x, y, z = (r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 + r22 - r00 - r11, 0.0))
        w, x, y, z = (r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    n = math.sqrt(x * x + y * y + z * z + w * w)
    return x / n, y / n, z / n, w / n


def rotvec_to_matrix(v: ArrayLike) -> FloatArray:
    """Rotation matrix of a rotation vector (axis × angle, as on the teach pendant)."""
    rx, ry, rz = (float(c) for c in np.asarray(v, dtype=np.float64).reshape(3))
    x, y, z, w = _rotvec_quaternion(rx, ry, rz)
    return _quat_matrix(x, y, z, w)


def _rotvec_quaternion(rx: float, ry: float, rz: float) -> tuple[float, float, float, float]:
    theta = math.hypot(rx, ry, rz)
    half = 0.5 * theta
    # sin(θ/2)/θ, by its Taylor series where the division would lose digits (or divide by 0)
    k = math.sin(half) / theta if theta > 1e-4 else 0.5 - theta * theta / 48.0
    return rx * k, ry * k, rz * k, math.cos(half)


def matrix_to_rotvec(R: ArrayLike) -> tuple[float, float, float]:
    """Rotation vector of a rotation matrix; its angle is in [0, π].

    Through the quaternion, so it is exact near 0 (no 0/0) and near π (the axis comes from the
    dominant diagonal element, not from a vanishing sin θ).
    """
    return _quaternion_rotvec(*matrix_to_quaternion(R))


def rows_to_rotvec(rows: Iterable[float]) -> tuple[float, float, float]:
    """:func:`matrix_to_rotvec` of a rotation given as nine floats, row-major (no array)."""
    return _quaternion_rotvec(*_rows_quaternion(*rows))


def _quaternion_rotvec(x: float, y: float, z: float, w: float) -> tuple[float, float, float]:
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    n = math.hypot(x, y, z)
    # angle / n = 2·atan2(n, w) / n, by its Taylor series when n is tiny (then w ≈ 1)
    k = 2.0 * math.atan2(n, w) / n if n > 1e-6 else 2.0 / w * (1.0 - n * n / (3.0 * w * w))
    return x * k, y * k, z * k


def rpy_to_matrix(rpy: ArrayLike) -> FloatArray:
    """``Rz(yaw)·Ry(pitch)·Rx(roll)`` for ``(roll, pitch, yaw)``."""
    roll, pitch, yaw = (float(c) for c in np.asarray(rpy, dtype=np.float64).reshape(3))
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def matrix_to_rpy(R: ArrayLike) -> tuple[float, float, float]:
    """``(roll, pitch, yaw)`` with ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``, pitch in [-π/2, π/2].

    At gimbal lock (pitch = ±π/2) yaw is 0 and roll carries the whole rotation about x/z.
    Roll is computed after removing yaw, so the result reproduces R to rounding error even
    arbitrarily close to the lock.
    """
    m = np.asarray(R, dtype=np.float64)
    (r00, r01, r02), (r10, r11, r12), (r20, _r21, _r22) = m.tolist()
    h = math.hypot(r00, r10)
    yaw = math.atan2(r10, r00) if h > 0.0 else 0.0
    cy, sy = math.cos(yaw), math.sin(yaw)
    pitch = math.atan2(-r20, h)
    roll = math.atan2(sy * r02 - cy * r12, cy * r11 - sy * r01)
    return roll, pitch, yaw


def rotation_angle(R: ArrayLike) -> float:
    """Angle (rad, in [0, π]) of the rotation R."""
    x, y, z, w = matrix_to_quaternion(R)
    return 2.0 * math.atan2(math.hypot(x, y, z), abs(w))


def _is_real(v: Any) -> bool:
    return isinstance(v, Real) and not isinstance(v, bool)


# ----------------------------------------------------------------- pose


class Pose:
    """A rigid transform: ``position`` (3,) in metres and ``rotation`` (3, 3).

    Immutable: the arrays are read-only copies. ``a @ b`` composes (b expressed in a's
    frame), ``a @ point`` maps a point. Build one with :meth:`from_ur`,
    :meth:`from_quaternion`, :meth:`from_rpy`, :meth:`from_matrix` or :meth:`parse`.
    """

    __slots__ = ("_R", "_p")

    _p: FloatArray
    _R: FloatArray

    def __init__(self, position: ArrayLike = (0.0, 0.0, 0.0), rotation: ArrayLike | None = None):
        p = _finite_array(position, (3,), "position")
        if rotation is None:
            R = np.eye(3)
        else:
            R = _finite_array(rotation, (3, 3), "rotation")
            err = float(np.max(np.abs(R.T @ R - np.eye(3))))
            if err > _ORTHO_TOL or np.linalg.det(R) < 0.0:
                raise InvalidTargetError(f"not a rotation matrix (orthonormality error {err:.2g})")
            R = _orthonormalize(R) if err > 1e-14 else R.copy()
        self._set(p, R)

    def _set(self, p: FloatArray, R: FloatArray) -> None:
        p.flags.writeable = False
        R.flags.writeable = False
        object.__setattr__(self, "_p", p)
        object.__setattr__(self, "_R", R)

    @classmethod
    def _raw(cls, p: FloatArray, R: FloatArray) -> Pose:
        """A pose from arrays known to be valid; they are taken over, not copied."""
        pose = object.__new__(cls)
        pose._set(p, R)
        return pose

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError("Pose is immutable")

    # -------------------------------------------------- constructors

    @classmethod
    def identity(cls) -> Pose:
        return cls._raw(np.zeros(3), np.eye(3))

    @classmethod
    def from_ur(cls, pose: ArrayLike) -> Pose:
        """From ``[x, y, z, rx, ry, rz]`` with a rotation vector (teach pendant, RTDE)."""
        v = _finite_array(pose, (6,), "UR pose [x, y, z, rx, ry, rz]")
        x, y, z, w = _rotvec_quaternion(float(v[3]), float(v[4]), float(v[5]))
        return cls._raw(v[:3].copy(), _quat_matrix(x, y, z, w))

    @classmethod
    def from_quaternion(cls, position: ArrayLike, quaternion: ArrayLike) -> Pose:
        """From a position and a quaternion ``(x, y, z, w)`` (normalised here)."""
        p = _finite_array(position, (3,), "position")
        return cls._raw(p, quaternion_to_matrix(quaternion))

    @classmethod
    def from_rpy(cls, position: ArrayLike, rpy: ArrayLike) -> Pose:
        """From a position and ``(roll, pitch, yaw)``, ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``."""
        p = _finite_array(position, (3,), "position")
        return cls._raw(p, rpy_to_matrix(_finite_array(rpy, (3,), "roll, pitch, yaw")))

    @classmethod
    def from_rotvec(cls, position: ArrayLike, rotvec: ArrayLike) -> Pose:
        """From a position and a rotation vector."""
        p = _finite_array(position, (3,), "position")
        return cls._raw(p, rotvec_to_matrix(_finite_array(rotvec, (3,), "rotation vector")))

    @classmethod
    def from_matrix(cls, T: ArrayLike) -> Pose:
        """From a 4×4 homogeneous matrix (its last row must be ``0 0 0 1``)."""
        m = _finite_array(T, (4, 4), "4×4 transform")
        if np.max(np.abs(m[3] - (0.0, 0.0, 0.0, 1.0))) > 1e-9:
            raise InvalidTargetError("the last row of a 4×4 transform must be [0, 0, 0, 1]")
        return cls(m[:3, 3], m[:3, :3])

    @classmethod
    def parse(cls, obj: object) -> Pose:
        """A pose from what the move APIs accept (as in the seed).

        - a :class:`Pose` (returned as is);
        - 7 numbers ``[x, y, z, qx, qy, qz, qw]`` (quaternion, normalised);
        - 6 numbers ``[x, y, z, roll, pitch, yaw]`` (RPY, *not* a rotation vector: use
          :meth:`from_ur` for teach-pendant poses).

        Anything else, non-finite numbers or a zero quaternion raise
        :class:`~fxcell.errors.InvalidTargetError`.
        """
        if isinstance(obj, Pose):
            return obj
        if isinstance(obj, str | bytes) or not isinstance(obj, Iterable | np.ndarray):
            raise InvalidTargetError(
                f"a pose is a Pose, [x, y, z, qx, qy, qz, qw] or [x, y, z, roll, pitch, yaw]; "
                f"got {type(obj).__name__}"
            )
        items = list(np.asarray(obj).tolist()) if isinstance(obj, np.ndarray) else list(obj)
        if not all(_is_real(v) for v in items):
            raise InvalidTargetError(f"a pose is a list of numbers, got {obj!r}")
        v = np.array(items, dtype=np.float64)
        if not np.all(np.isfinite(v)):
            raise InvalidTargetError(f"pose has a non-finite value: {items!r}")
        if v.size == 7:
            return cls.from_quaternion(v[:3], v[3:])
        if v.size == 6:
            return cls.from_rpy(v[:3], v[3:])
        raise InvalidTargetError(
            f"a pose list has 7 (quaternion) or 6 (roll, pitch, yaw) numbers, got {v.size}"
        )

    # -------------------------------------------------- accessors

    @property
    def position(self) -> FloatArray:
        return self._p

    @property
    def rotation(self) -> FloatArray:
        return self._R

    @property
    def matrix(self) -> FloatArray:
        """4×4 homogeneous matrix (a new, writable array)."""
        T = np.eye(4)
        T[:3, :3] = self._R
        T[:3, 3] = self._p
        return T

    @property
    def quaternion(self) -> tuple[float, float, float, float]:
        """``(x, y, z, w)`` with ``w >= 0``."""
        return matrix_to_quaternion(self._R)

    @property
    def rpy(self) -> tuple[float, float, float]:
        """``(roll, pitch, yaw)`` with ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``."""
        return matrix_to_rpy(self._R)

    @property
    def rotvec(self) -> tuple[float, float, float]:
        """Rotation vector, angle in [0, π]."""
        return matrix_to_rotvec(self._R)

    def as_ur(self) -> Vector6:
        """``(x, y, z, rx, ry, rz)`` as on the teach pendant and in RTDE ``actual_TCP_pose``."""
        x, y, z = self._p.tolist()
        rx, ry, rz = matrix_to_rotvec(self._R)
        return (x, y, z, rx, ry, rz)

    def as_quaternion_list(self) -> list[float]:
        """``[x, y, z, qx, qy, qz, qw]`` (the seed's 7-list form)."""
        return [*self._p.tolist(), *self.quaternion]

    def as_rpy_list(self) -> list[float]:
        """``[x, y, z, roll, pitch, yaw]`` (the seed's 6-list form)."""
        return [*self._p.tolist(), *self.rpy]

    # -------------------------------------------------- algebra

    def __matmul__(self, other: Pose) -> Pose:
        if isinstance(other, Pose):
            return Pose._raw(self._R @ other._p + self._p, self._R @ other._R)
        return NotImplemented

    def transform_point(self, point: ArrayLike) -> FloatArray:
        """Map a point (or an (N, 3) array of points) given in this pose's frame."""
        pts = np.asarray(point, dtype=np.float64)
        return pts @ self._R.T + self._p

    def inverse(self) -> Pose:
        Rt = self._R.T.copy()
        return Pose._raw(-(Rt @ self._p), Rt)

    def distance(self, other: Pose) -> float:
        """Distance (m) between the two positions."""
        return float(np.linalg.norm(self._p - other._p))

    def angle_to(self, other: Pose) -> float:
        """Angle (rad, [0, π]) of the rotation taking this orientation to the other."""
        return rotation_angle(self._R.T @ other._R)

    def isclose(self, other: Pose, *, position_tol: float = 1e-9, angle_tol: float = 1e-9) -> bool:
        return self.distance(other) <= position_tol and self.angle_to(other) <= angle_tol

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Pose):
            return NotImplemented
        return bool(np.array_equal(self._p, other._p) and np.array_equal(self._R, other._R))

    def __hash__(self) -> int:
        return hash((self._p.tobytes(), self._R.tobytes()))

    def __repr__(self) -> str:
        vals = ", ".join(f"{v:.6g}" for v in self.as_ur())
        return f"Pose.from_ur([{vals}])"

    def __reduce__(self) -> tuple[Any, ...]:
        return (Pose, (self._p.copy(), self._R.copy()))


def _finite_array(value: ArrayLike, shape: tuple[int, ...], what: str) -> FloatArray:
    if isinstance(value, str | bytes):
        raise InvalidTargetError(f"{what}: expected numbers, got a string")
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError):
        raise InvalidTargetError(f"{what}: expected numbers, got {value!r}") from None
    if raw.dtype.kind not in "iuf":
        raise InvalidTargetError(f"{what}: expected numbers, got {value!r}")
    arr = np.array(raw, dtype=np.float64)
    if arr.shape != shape:
        raise InvalidTargetError(f"{what}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidTargetError(f"{what}: non-finite value in {arr.tolist()!r}")
    return arr


def _orthonormalize(R: FloatArray) -> FloatArray:
    """The rotation nearest to R (polar decomposition through the SVD)."""
    U, _, Vt = np.linalg.svd(R)
    out: FloatArray = U @ Vt
    return out
