"""The Niryo Ned2's model: kinematic chain, limits, forward and inverse kinematics.

Values from Niryo's URDF (ned_ros ``niryo_robot_description/urdf/ned2``, v5.6.x) and its
MoveIt planning limits (the limits and home written once in :mod:`fxcell.robot_specs`,
where the configuration reads them too); see ``/work/shared/reference/niryo-ned2.md`` and
``docs/guides/ned2.md``. The pose is that of ``tool_link`` in ``base_link`` as Niryo's
TCP server reports it (``GET_POSE``: x, y, z in m, roll, pitch, yaw in rad, extrinsic
XYZ = ``Rz(yaw) Ry(pitch) Rx(roll)``).

Geometry: axes 1 and 2 intersect, 2 and 3 are parallel, 4 and 5 intersect, but axis 6
passes 9.25 mm beside the 4/5 intersection: the wrist is not spherical, so there is no
decoupled closed form. :func:`inverse` is a batched damped-least-squares (Levenberg-
Marquardt) solver started from the seed and from a fixed set of branch seeds, that
keeps every converged solution inside the limits and returns the one nearest the seed.

Pure numpy, no runtime state: the simulator (:mod:`fxcell.sim.ned2`) uses the same FK
to report the pose. When the robot seam lands this module moves to
``fxcell/robots/ned2/model.py``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from numpy.typing import ArrayLike

from fxcell.errors import InvalidArgumentError, UnreachableError
from fxcell.geometry import Pose
from fxcell.robot_specs import NED2_SPEC

Array = npt.NDArray[np.float64]
Joints = Sequence[float] | npt.NDArray[np.floating[Any]]  # six joint positions (rad)

__all__ = [
    "ACCELERATION_LIMITS",
    "HOME",
    "JOINT_NAMES",
    "LOWER",
    "NEVER_IN_CONTACT",
    "TOOL_OFFSET",
    "UPPER",
    "VELOCITY_LIMITS",
    "IkResult",
    "Ned2Kinematics",
    "forward",
    "forward_batch",
    "inverse",
    "matrix_to_pose",
    "pose_to_matrix",
    "urdf",
    "within_limits",
]

JOINT_NAMES = ("joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6")
# The published figures live in fxcell.robot_specs (the configuration's defaults too)
LOWER: Array = np.array(NED2_SPEC.position_min)
UPPER: Array = np.array(NED2_SPEC.position_max)
# niryo_moveit_config_standalone joint_limits.yaml (rad/s, rad/s^2)
VELOCITY_LIMITS: Array = np.array(NED2_SPEC.velocity_max)
ACCELERATION_LIMITS: Array = np.array(NED2_SPEC.limits["acceleration"])
HOME: Array = np.array(NED2_SPEC.home)  # Niryo's home ("forearm on shoulder")
TOOL_OFFSET = 0.0285  # hand_link -> tool_link along the hand's z (m)


def _rpy(roll: float, pitch: float, yaw: float) -> Array:
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


def _origin(xyz: Sequence[float], rpy: Sequence[float]) -> Array:
    t = np.eye(4)
    t[:3, :3] = _rpy(*rpy)
    t[:3, 3] = xyz
    return t


_PI = math.pi
# Each joint: the fixed origin in its parent link, then a rotation about its own z.
ORIGINS: tuple[Array, ...] = (
    _origin((0.0, 3.7961e-05, 0.1013), (0.0, 0.0, 0.0)),
    _origin((0.0, 0.0, 0.065), (_PI / 2, -_PI / 2, 0.0)),
    _origin((0.221, -0.012, 0.0), (0.0, 0.0, -_PI / 2)),
    _origin((0.065, 0.0325, 0.0), (0.0, _PI / 2, 0.0)),
    _origin((0.0, 0.0, 0.17), (_PI, -_PI / 2, _PI)),
    _origin((0.0197, 0.00925, 0.0), (0.0, _PI / 2, 0.0)),
)
TOOL: Array = _origin((0.0, 0.0, TOOL_OFFSET), (-_PI / 2, -_PI / 2, 0.0))
_ORIGINS = np.stack(ORIGINS)  # (6, 4, 4)


def pose_to_matrix(pose: Sequence[float]) -> Array:
    """A 4x4 transform from Niryo's ``[x, y, z, roll, pitch, yaw]``."""
    if len(pose) != 6:
        raise InvalidArgumentError(
            f"a pose has 6 values (x, y, z, roll, pitch, yaw), got {len(pose)}"
        )
    t = np.eye(4)
    t[:3, :3] = _rpy(float(pose[3]), float(pose[4]), float(pose[5]))
    t[:3, 3] = [float(v) for v in pose[:3]]
    return t


def matrix_to_pose(t: Array) -> list[float]:
    """Niryo's ``[x, y, z, roll, pitch, yaw]`` of a 4x4 transform (pitch in [-pi/2, pi/2])."""
    r = t[:3, :3]
    pitch = math.atan2(-r[2, 0], math.hypot(r[0, 0], r[1, 0]))
    if abs(math.cos(pitch)) > 1e-9:
        roll = math.atan2(r[2, 1], r[2, 2])
        yaw = math.atan2(r[1, 0], r[0, 0])
    else:  # gimbal lock: put the whole rotation into yaw
        roll = 0.0
        yaw = math.atan2(-r[0, 1], r[1, 1])
    return [float(t[0, 3]), float(t[1, 3]), float(t[2, 3]), roll, pitch, yaw]


def _rz_batch(q: Array) -> Array:
    c, s = np.cos(q), np.sin(q)
    out = np.zeros((*q.shape, 4, 4))
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 2, 2] = 1.0
    out[..., 3, 3] = 1.0
    return out


def _frames(q: Array) -> Array:
    """Joint frames after each joint's rotation, then the tool: (N, 7, 4, 4)."""
    n = q.shape[0]
    rz = _rz_batch(q)  # (N, 6, 4, 4)
    frames = np.empty((n, 7, 4, 4))
    t = np.broadcast_to(np.eye(4), (n, 4, 4))
    for i in range(6):
        t = t @ _ORIGINS[i] @ rz[:, i]
        frames[:, i] = t
    frames[:, 6] = t @ TOOL
    return frames


def forward_batch(q: Array) -> Array:
    """``tool_link`` in ``base_link`` for each row of ``q`` (N, 6): (N, 4, 4)."""
    return _frames(np.asarray(q, dtype=float).reshape(-1, 6))[:, 6]


def forward(q: Joints) -> Array:
    """``tool_link`` in ``base_link`` (4x4) at joint positions ``q`` (rad)."""
    if len(q) != 6:
        raise InvalidArgumentError(f"the Ned2 has 6 joints, got {len(q)} values")
    result: Array = forward_batch(np.asarray(q, dtype=float)[None, :])[0]
    return result


def within_limits(q: Joints, tol: float = 1e-9) -> bool:
    a = np.asarray(q, dtype=float)
    return bool(np.all(a >= LOWER - tol) and np.all(a <= UPPER + tol))


def _error(frames: Array, target: Array) -> Array:
    """Position and orientation error (N, 6) in the base frame, target minus current."""
    tool = frames[:, 6]
    ep = target[:3, 3] - tool[:, :3, 3]
    r = tool[:, :3, :3]
    rd = target[:3, :3]
    # rotation vector of rd @ r.T: exact, so a seed far off still gets a useful direction
    re = np.einsum("ij,nkj->nik", rd, r)
    tr = np.clip((np.trace(re, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(tr)
    skew = np.stack(
        [re[:, 2, 1] - re[:, 1, 2], re[:, 0, 2] - re[:, 2, 0], re[:, 1, 0] - re[:, 0, 1]], axis=1
    )
    s = np.sin(angle)
    scale = np.where(s > 1e-6, angle / np.maximum(2.0 * s, 1e-12), 0.5)
    er = skew * scale[:, None]
    return np.concatenate([ep, er], axis=1)


def _jacobian(frames: Array) -> Array:
    """Geometric Jacobian (N, 6, 6) of ``tool_link`` in the base frame."""
    z = frames[:, :6, :3, 2]  # joint axes
    p = frames[:, :6, :3, 3]
    pe = frames[:, 6, :3, 3][:, None, :]
    jv = np.cross(z, pe - p)
    return np.concatenate([jv, z], axis=2).transpose(0, 2, 1)


_W = np.array([1.0, 1.0, 1.0, 0.1, 0.1, 0.1])  # 1 rad of orientation weighs as 0.1 m


@dataclass(frozen=True)
class IkResult:
    """Every distinct solution found (nearest the seed first) and the one chosen."""

    q: Array | None
    solutions: tuple[Array, ...]


def _branch_seeds() -> Array:
    """A fixed spread of starting points over the joint ranges: shoulder back/up/forward,
    elbow down/level/up/at its upper limit, wrist rolled either way or not, wrist bent
    either way (72 per base yaw, 144 in all; the base joint is set per target). 48 starts
    left 1 % of random reachable poses unsolved. Without the elbow at 1.5 (0.07 from its
    limit), a solution with θ3 near the limit was missed: on 300 random poses, a fifth of
    them with θ3 at 0.98 of a limit, 3 answers farther than the dense reference's and 15
    poses with fewer solutions found, against 0 and 2 with it (median 17.1 -> 21.5 ms)."""
    rows = []
    for q2 in (-1.2, -0.4, 0.3):
        for q3 in (-1.0, 0.0, 1.2, 1.5):
            for q4 in (-1.6, 0.0, 1.6):
                for q5 in (-1.2, 1.2):
                    rows.append([0.0, q2, q3, q4, q5, 0.0])
    return np.array(rows)


_BRANCHES = _branch_seeds()
_AXIS6_IN_TOOL: Array = TOOL[2, :3].copy()
"""Joint 6's axis in ``tool_link``'s frame."""
_WRIST_BACK = TOOL_OFFSET + float((ORIGINS[5][:3, :3].T @ ORIGINS[5][:3, 3])[2])
"""How far back from ``tool_link`` along joint 6's axis the wrist centre (axes 4 and 5
meeting) lies, up to the 9.25 mm that turn with joint 6 (48.2 mm). Starting the branches'
base joint from there rather than from the TCP: on 604 random poses (a third with θ5 = 0, a
quarter θ2 = 0, a fifth θ3 at 0.96 of a limit), answers farther than the dense reference's
4 -> 1, at the same cost."""
_DENSE = np.random.default_rng(2029).uniform(LOWER, UPPER, size=(400, 6))


def _solve(
    target: Array, seeds: Array, iterations: int, tol_pos: float, tol_rot: float
) -> tuple[Array, Array]:
    """Batched damped least squares from each seed; returns (q, converged). Rows that
    have converged or stalled leave the batch."""
    q = np.clip(seeds.copy(), LOWER, UPPER)
    n = q.shape[0]
    ok = np.zeros(n, dtype=bool)
    active = np.arange(n)
    qa = q
    lam = np.full(n, 1e-3)
    frames = _frames(qa)
    err = _error(frames, target)
    cost = np.sum((err * _W) ** 2, axis=1)
    eye = np.eye(6)
    for _ in range(iterations):
        done = (np.linalg.norm(err[:, :3], axis=1) < tol_pos) & (
            np.linalg.norm(err[:, 3:], axis=1) < tol_rot
        )
        stalled = lam >= 1e6
        if bool(np.any(done | stalled)):
            q[active[done]] = qa[done]
            ok[active[done]] = True
            keep = ~(done | stalled)
            active, qa, lam = active[keep], qa[keep], lam[keep]
            frames, err, cost = frames[keep], err[keep], cost[keep]
            if active.size == 0:
                break
        j = _jacobian(frames) * _W[None, :, None]
        e = err * _W
        jt = j.transpose(0, 2, 1)
        a = jt @ j + lam[:, None, None] * eye
        g = np.einsum("nij,nj->ni", jt, e)
        dq = np.linalg.solve(a, g[..., None])[..., 0]
        # a joint at a limit that the step pushes outwards leaves the step (projected LM):
        # clipping alone makes the others crawl along the limit
        blocked = ((qa >= UPPER - 1e-12) & (dq > 0)) | ((qa <= LOWER + 1e-12) & (dq < 0))
        if bool(np.any(blocked)):
            free = (~blocked)[:, None, :]
            jm = j * free
            jmt = jm.transpose(0, 2, 1)
            am = jmt @ jm + lam[:, None, None] * eye
            gm = np.einsum("nij,nj->ni", jmt, e)
            dq = np.where(blocked, 0.0, np.linalg.solve(am, gm[..., None])[..., 0])
        q_new = np.clip(qa + np.clip(dq, -0.5, 0.5), LOWER, UPPER)
        f_new = _frames(q_new)
        e_new = _error(f_new, target)
        c_new = np.sum((e_new * _W) ** 2, axis=1)
        better = c_new < cost
        qa = np.where(better[:, None], q_new, qa)
        frames = np.where(better[:, None, None, None], f_new, frames)
        err = np.where(better[:, None], e_new, err)
        cost = np.where(better, c_new, cost)
        lam = np.where(better, np.maximum(lam * 0.3, 1e-15), lam * 10.0)
    else:
        done = (np.linalg.norm(err[:, :3], axis=1) < tol_pos) & (
            np.linalg.norm(err[:, 3:], axis=1) < tol_rot
        )
        q[active[done]] = qa[done]
        ok[active[done]] = True
    return q, ok


def inverse(
    target: Array | Sequence[float],
    seed: Joints,
    *,
    extra_seeds: Array | None = None,
    branches: bool = True,
    iterations: int = 60,
    tol_pos: float = 1e-10,
    tol_rot: float = 1e-10,
) -> IkResult:
    """Joint positions within the limits that put ``tool_link`` at ``target`` (a 4x4
    transform or Niryo's 6-value pose), the one nearest ``seed`` (Euclidean in joint
    space); ``q`` is None when no start converged (the pose is out of reach).

    ``branches=False`` starts from the seed (and ``extra_seeds``) only: a local solve for
    a path whose previous point is the seed (a linear move), ~20x faster."""
    t = np.asarray(target, dtype=float)
    if t.shape == (6,):
        t = pose_to_matrix(list(t))
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise InvalidArgumentError("target must be a 4x4 transform or 6 finite pose values")
    s = np.asarray(seed, dtype=float)
    if s.shape != (6,) or not np.all(np.isfinite(s)):
        raise InvalidArgumentError("seed must be 6 finite joint positions")
    # the branches' base joint from the wrist centre, not the TCP: a TCP next to the base axis
    # (the hand folded back over the shoulder) says nothing of it
    wrist = t[:3, 3] - _WRIST_BACK * (t[:3, :3] @ _AXIS6_IN_TOOL)
    base_yaw = math.atan2(wrist[1], wrist[0])
    first = _BRANCHES.copy()
    first[:, 0] = base_yaw
    flipped = _BRANCHES.copy()
    flipped[:, 0] = base_yaw + (math.pi if base_yaw < 0 else -math.pi)
    starts = [s[None, :], first, flipped] if branches else [s[None, :]]
    if extra_seeds is not None:
        starts.append(np.asarray(extra_seeds, dtype=float).reshape(-1, 6))
    q, ok = _solve(t, np.concatenate(starts), iterations, tol_pos, tol_rot)
    if branches and not bool(np.any(ok)):
        # none converged: a pose reachable only near joint limits, where the branch starts
        # settle on a limit; a dense spread of starts finds it (~0.25 s, rare)
        q, ok = _solve(t, _DENSE, iterations, tol_pos, tol_rot)
    found = q[ok]
    distinct: list[Array] = []
    for row in found:
        if not any(np.max(np.abs(row - d)) < 1e-4 for d in distinct):
            distinct.append(row)
    distinct.sort(key=lambda row: float(np.linalg.norm(row - s)))
    return IkResult(distinct[0] if distinct else None, tuple(distinct))


class Ned2Kinematics:
    """The Ned2 as the motion planner plans on it (a
    :class:`~fxcell.robots.registry.KinematicModel`): poses of a TCP given in
    ``tool_link``'s frame, in ``base_link``, as :class:`~fxcell.geometry.Pose`; joint
    solutions within ``lower``..``upper`` (default Niryo's limits), nearest the seed."""

    def __init__(
        self,
        tcp: Pose | None = None,
        lower: Joints | None = None,
        upper: Joints | None = None,
    ) -> None:
        self.tcp = tcp if tcp is not None else Pose.identity()
        self._tcp = self.tcp.matrix
        self._tcp_inverse = np.linalg.inv(self._tcp)
        self.lower = np.maximum(LOWER, np.asarray(LOWER if lower is None else lower, float))
        self.upper = np.minimum(UPPER, np.asarray(UPPER if upper is None else upper, float))
        if self.lower.shape != (6,) or np.any(self.lower > self.upper):
            raise InvalidArgumentError("the Ned2's joint limits: six lower <= upper values")

    @property
    def reach(self) -> float:
        """No TCP position is farther than this from the base origin (m): the chain's
        lengths from the shoulder on, the tool link and the TCP added up."""
        lengths = [float(np.linalg.norm(o[:3, 3])) for o in ORIGINS[2:]]
        shoulder = float(np.linalg.norm((ORIGINS[0] @ ORIGINS[1])[:3, 3]))
        tool = float(np.linalg.norm(TOOL[:3, 3])) + float(np.linalg.norm(self._tcp[:3, 3]))
        return shoulder + sum(lengths) + tool

    def forward(self, q: ArrayLike) -> Pose:
        return Pose.from_matrix(forward(np.asarray(q, dtype=float)) @ self._tcp)

    def inverse_all(self, pose: Pose, seed: ArrayLike | None = None) -> list[Array]:
        start = np.clip(
            np.asarray(HOME if seed is None else seed, dtype=float), self.lower, self.upper
        )
        result = inverse(pose.matrix @ self._tcp_inverse, start)
        return [q for q in result.solutions if np.all(q >= self.lower) and np.all(q <= self.upper)]

    def inverse_near(self, pose: Pose, seed: ArrayLike) -> Array:
        """The solution continuous with ``seed`` (a path's next point): a local solve from
        the seed alone, ~20x faster than the search over every branch, which it falls back
        on when the local solve does not converge within the limits."""
        start = np.clip(np.asarray(seed, dtype=float), self.lower, self.upper)
        q = inverse(pose.matrix @ self._tcp_inverse, start, branches=False).q
        if q is None or np.any(q < self.lower) or np.any(q > self.upper):
            return self.inverse(pose, seed)
        return q

    def inverse(self, pose: Pose, seed: ArrayLike | None = None) -> Array:
        solutions = self.inverse_all(pose, seed)
        if not solutions:
            raise UnreachableError(f"the Ned2 cannot reach {pose} within its joint limits")
        return solutions[0]


_LINKS = (
    "base_link",
    "shoulder_link",
    "arm_link",
    "elbow_link",
    "forearm_link",
    "wrist_link",
    "hand_link",
)
# Simple collision bodies per link in the link's own frame: (shape, size, xyz, rpy);
# cylinders (radius, length) along the local z, boxes (x, y, z). Conservative envelopes of
# Niryo's meshes for planning, not the meshes themselves.
_COLLISION: dict[str, tuple[str, tuple[float, ...], tuple[float, ...], tuple[float, ...]]] = {
    "base_link": ("cylinder", (0.075, 0.10), (0.0, 0.0, 0.05), (0.0, 0.0, 0.0)),
    "shoulder_link": ("cylinder", (0.05, 0.08), (0.0, 0.0, 0.03), (0.0, 0.0, 0.0)),
    "arm_link": ("box", (0.27, 0.055, 0.075), (0.11, -0.006, 0.0), (0.0, 0.0, 0.0)),
    "elbow_link": ("box", (0.10, 0.065, 0.065), (0.035, 0.016, 0.0), (0.0, 0.0, 0.0)),
    "forearm_link": ("cylinder", (0.032, 0.15), (0.0, 0.0, 0.08), (0.0, 0.0, 0.0)),
    "wrist_link": ("box", (0.045, 0.04, 0.04), (0.01, 0.0, 0.0), (0.0, 0.0, 0.0)),
    "hand_link": ("cylinder", (0.022, 0.025), (0.0, 0.0, 0.01), (0.0, 0.0, 0.0)),
    # Niryo's Gripper 1 (custom gripper fingers), approach along tool_link's x
    "gripper_link": ("box", (0.075, 0.06, 0.03), (0.0375, 0.0, 0.0), (0.0, 0.0, 0.0)),
}


NEVER_IN_CONTACT: tuple[tuple[str, str], ...] = (
    ("arm_link", "base_link"),
    ("arm_link", "forearm_link"),
    ("base_link", "elbow_link"),
    ("elbow_link", "hand_link"),
    ("elbow_link", "shoulder_link"),
    ("elbow_link", "wrist_link"),
    ("forearm_link", "hand_link"),
    ("forearm_link", "shoulder_link"),
    ("gripper_link", "elbow_link"),
    ("gripper_link", "forearm_link"),
    ("gripper_link", "wrist_link"),
)
"""Pairs of links two or more joints apart that Niryo's MoveIt configuration never
checks (``niryo_moveit_config_w_gripper1``'s SRDF, reasons "Never" and "User": the joint
limits keep them apart); ``gripper_link`` stands for its ``base_gripper_1``."""


def _geometry(shape: str, size: tuple[float, ...]) -> str:
    if shape == "cylinder":
        return f'<cylinder radius="{size[0]}" length="{size[1]}"/>'
    return f'<box size="{size[0]} {size[1]} {size[2]}"/>'


def _fmt(values: Sequence[float]) -> str:
    return " ".join(repr(float(v)) for v in values)


def _origin_xml(t: Array) -> str:
    rpy = matrix_to_pose(t)[3:]
    return f'<origin xyz="{_fmt(list(t[:3, 3]))}" rpy="{_fmt(rpy)}"/>'


def urdf() -> str:
    """The Ned2 as URDF (the chain above, simple collision bodies, a gripper link), for
    Pinocchio/coal collision checking and the recorder's robot description."""
    parts = ['<?xml version="1.0"?>', '<robot name="niryo_ned2">']
    for link in (*_LINKS, "tool_link", "gripper_link"):
        body = ""
        if link in _COLLISION:
            shape, size, xyz, rpy = _COLLISION[link]
            geom = _geometry(shape, size)
            origin = f'<origin xyz="{_fmt(xyz)}" rpy="{_fmt(rpy)}"/>'
            body = (
                f"<visual>{origin}<geometry>{geom}</geometry></visual>"
                f"<collision>{origin}<geometry>{geom}</geometry></collision>"
            )
        parts.append(f'  <link name="{link}">{body}</link>')
    for i, name in enumerate(JOINT_NAMES):
        parts.append(
            f'  <joint name="{name}" type="revolute"><parent link="{_LINKS[i]}"/>'
            f'<child link="{_LINKS[i + 1]}"/>{_origin_xml(ORIGINS[i])}<axis xyz="0 0 1"/>'
            f'<limit lower="{float(LOWER[i])!r}" upper="{float(UPPER[i])!r}" effort="10.0" '
            f'velocity="{float(VELOCITY_LIMITS[i])!r}"/></joint>'
        )
    parts.append(
        '  <joint name="hand_tool_joint" type="fixed"><parent link="hand_link"/>'
        f'<child link="tool_link"/>{_origin_xml(TOOL)}</joint>'
    )
    parts.append(
        '  <joint name="tool_gripper_joint" type="fixed"><parent link="tool_link"/>'
        '<child link="gripper_link"/><origin xyz="0 0 0" rpy="0 0 0"/></joint>'
    )
    parts.append("</robot>")
    return "\n".join(parts) + "\n"
