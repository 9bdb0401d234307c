"""Collision checking of the UR3e, its Robotiq Hand-E gripper and the cell with coal.

A Pinocchio ``GeometryModel`` on top of the robot model (:mod:`fxcell.motion.robot_model`):
every link is a few capsules sized to the real UR3e (no meshes are available; a capsule
along a joint axis stands for the joint's housing), the gripper is a box for its body and
one for its fingers, and the scene's boxes (table, fusion machine, from
``config/scene.yaml``) are fixed obstacles. The robot base stands on the table top
(z = 0). Shapes are written in UR's base frame at the zero configuration and attached
to the joint that carries them, so they do not depend on how the model places its
joint frames.

Checked pairs: every moving link against every scene object and against the fixed base,
and every pair of links two or more joints apart (adjacent links always touch at their
shared joint). Scene pairs get a safety margin (``scene_margin``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from fxcell.config import CellConfig, SceneConfig
from fxcell.errors import CollisionError
from fxcell.geometry import rpy_to_matrix
from fxcell.motion.kinematics import UR3E_DH, Kinematics
from fxcell.motion.robot_model import RobotModel

Array = NDArray[np.float64]

# UR3e geometry (m). DH values from UR; the offsets of the arm tubes along the joint
# axes and the housing radii from UR's published drawings (rounded up).
_D1, _D4, _D5, _D6 = UR3E_DH.d[0], UR3E_DH.d[3], UR3E_DH.d[4], UR3E_DH.d[5]
_A2, _A3 = UR3E_DH.a[1], UR3E_DH.a[2]
SHOULDER_OFFSET = 0.120
"""Upper-arm tube axis from the base axis, along the shoulder joint's axis."""
ELBOW_OFFSET = 0.093
"""The forearm tube sits this much back towards the base axis from the upper arm."""
BASE_HEIGHT = 0.09
"""Height of the fixed base casing above the table top."""

DEFAULT_SCENE_MARGIN = 0.005
"""Clearance (m) demanded between the robot and the scene objects."""
DEFAULT_RESOLUTION = 0.006
"""Largest displacement (m) of any point of the robot between two checked states."""
LEVER_ARMS = np.array([0.65, 0.65, 0.45, 0.30, 0.25, 0.09])
"""Farthest point of the arm and gripper from each joint axis (m), rounded up: a joint
step δ moves no point by more than lever·δ, which sets how densely motions are checked."""


@dataclass(frozen=True)
class Capsule:
    """A capsule between two points (UR base frame, zero configuration) on a body."""

    name: str
    body: int
    """0 = fixed base, 1..6 = moved by that joint."""
    start: tuple[float, float, float]
    end: tuple[float, float, float]
    radius: float


@dataclass(frozen=True)
class FlangeBox:
    """A box in the flange (tool0) frame, carried by joint 6: the gripper."""

    name: str
    size: tuple[float, float, float]
    center: tuple[float, float, float]


_y_fore = -(SHOULDER_OFFSET - ELBOW_OFFSET)
_x_w = _A2 + _A3
_z5 = _D1 - _D5

UR3E_CAPSULES: tuple[Capsule, ...] = (
    Capsule("base", 0, (0, 0, 0.0), (0, 0, BASE_HEIGHT - 0.064), 0.064),
    Capsule("shoulder_column", 1, (0, 0, BASE_HEIGHT), (0, 0, _D1), 0.046),
    Capsule("shoulder_joint", 1, (0, 0, _D1), (0, -SHOULDER_OFFSET, _D1), 0.046),
    Capsule("upper_arm", 2, (0, -SHOULDER_OFFSET, _D1), (_A2, -SHOULDER_OFFSET, _D1), 0.046),
    Capsule("elbow_joint", 2, (_A2, -SHOULDER_OFFSET, _D1), (_A2, _y_fore, _D1), 0.040),
    Capsule("forearm", 3, (_A2, _y_fore, _D1), (_x_w, _y_fore, _D1), 0.038),
    Capsule("wrist_1_joint", 3, (_x_w, _y_fore, _D1), (_x_w, -_D4, _D1), 0.032),
    Capsule("wrist_1_link", 4, (_x_w, -_D4, _D1), (_x_w, -_D4, _D1 - _D5), 0.032),
    Capsule(
        "wrist_2_link", 5, (_x_w, -_D4, _D1 - _D5), (_x_w, -_D4 - _D6 + 0.02, _D1 - _D5), 0.032
    ),
)
"""The arm's links as capsules (the fixed base is a short capsule sitting on the table)."""

HAND_E: tuple[FlangeBox, ...] = (
    # Coupling and gripper body: about 0.1 m long from the flange.
    FlangeBox("gripper_body", (0.100, 0.075, 0.100), (0.0, 0.0, 0.050)),
    # Both fingers at any opening (50 mm stroke), to just past the fingertip centre.
    FlangeBox("gripper_fingers", (0.075, 0.075, 0.053), (0.0, 0.0, 0.1265)),
)
"""Robotiq Hand-E collision boxes in the flange frame (square in x/y, so the finger
direction does not matter)."""


def _segment_placement(p: Array, q: Array) -> pin.SE3:
    """The frame of a z-aligned shape centred between ``p`` and ``q``."""
    axis = q - p
    length = float(np.linalg.norm(axis))
    z = axis / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    return pin.SE3(R, 0.5 * (p + q))


class CollisionChecker:
    """Answers whether joint configurations and motions are free of collision.

    ``model`` is the Pinocchio model of the arm (joints 1..6 at UR's joint angles);
    ``flange_in_joint6`` the flange (tool0) placement in joint 6's frame.
    """

    def __init__(
        self,
        model: pin.Model,
        scene: SceneConfig,
        *,
        flange_in_joint6: pin.SE3 | None = None,
        gripper: bool = True,
        scene_margin: float = DEFAULT_SCENE_MARGIN,
        resolution: float = DEFAULT_RESOLUTION,
    ) -> None:
        if model.nq != 6:
            raise ValueError(f"expected a 6-joint arm model, got nq={model.nq}")
        self.model = model
        self.data = model.createData()
        self.resolution = float(resolution)
        self.scene_margin = float(scene_margin)
        zero = np.zeros(6)
        pin.forwardKinematics(model, self.data, zero)
        oMi = [self.data.oMi[i].copy() for i in range(7)]
        if flange_in_joint6 is None:
            flange_world = Kinematics.ur3e().forward_flange(zero).matrix
            flange_in_joint6 = oMi[6].inverse() * pin.SE3(flange_world[:3, :3], flange_world[:3, 3])

        gm = pin.GeometryModel()
        self._body: list[int] = []
        self._scene: set[int] = set()
        for c in UR3E_CAPSULES:
            p, q = np.asarray(c.start, float), np.asarray(c.end, float)
            world = _segment_placement(p, q)
            shape = coal.Capsule(c.radius, float(np.linalg.norm(q - p)))
            self._add(gm, c.name, c.body, oMi[c.body].inverse() * world, shape)
        if gripper:
            for box in HAND_E:
                placement = flange_in_joint6 * pin.SE3(np.eye(3), np.asarray(box.center, float))
                self._add(gm, box.name, 6, placement, coal.Box(*box.size))
        for obj in scene.objects:
            placement = pin.SE3(rpy_to_matrix(obj.rpy), np.asarray(obj.position, float))
            gid = self._add(gm, obj.name, 0, placement, coal.Box(*obj.size))
            self._scene.add(gid)

        for a in range(gm.ngeoms):
            for b in range(a + 1, gm.ngeoms):
                if self._checked(a, b):
                    gm.addCollisionPair(pin.CollisionPair(a, b))
        self.geometry_model = gm
        self.geometry_data = pin.GeometryData(gm)
        for k, pair in enumerate(gm.collisionPairs):
            if pair.first in self._scene or pair.second in self._scene:
                self.geometry_data.collisionRequests[k].security_margin = self.scene_margin
        self.names = [g.name for g in gm.geometryObjects]

    def _add(self, gm: pin.GeometryModel, name: str, body: int, M: pin.SE3, shape: object) -> int:
        gid = int(gm.addGeometryObject(pin.GeometryObject(name, body, M, shape)))
        self._body.append(body)
        return gid

    def _checked(self, a: int, b: int) -> bool:
        ba, bb = self._body[a], self._body[b]
        if ba == 0 and bb == 0:  # fixed against fixed (base, table, machine)
            return False
        return abs(ba - bb) >= 2 or a in self._scene or b in self._scene

    @classmethod
    def for_config(cls, config: CellConfig, **options: float | bool) -> CollisionChecker:
        """The checker for a cell: the UR3e model, the gripper and the configured scene."""
        robot = RobotModel.ur3e(limits=config.limits)
        return cls(
            robot.model,
            config.scene,
            flange_in_joint6=robot.flange_in_joint6,
            **options,  # type: ignore[arg-type]
        )

    # ------------------------------------------------------------ queries

    def in_collision(self, q: ArrayLike) -> bool:
        """True if configuration ``q`` collides (stops at the first colliding pair)."""
        return bool(
            pin.computeCollisions(
                self.model, self.data, self.geometry_model, self.geometry_data,
                np.asarray(q, float), True,
            )
        )  # fmt: skip

    def colliding_pairs(self, q: ArrayLike) -> list[tuple[str, str]]:
        """Names of every colliding pair at ``q``."""
        pin.computeCollisions(
            self.model, self.data, self.geometry_model, self.geometry_data,
            np.asarray(q, float), False,
        )  # fmt: skip
        out = []
        for k, pair in enumerate(self.geometry_model.collisionPairs):
            if self.geometry_data.collisionResults[k].isCollision():
                out.append((self.names[pair.first], self.names[pair.second]))
        return out

    def check(self, q: ArrayLike, what: str = "target") -> None:
        """Raise :class:`CollisionError` naming the colliding parts if ``q`` collides."""
        if self.in_collision(q):
            pairs = ", ".join(f"{a}–{b}" for a, b in self.colliding_pairs(q))
            raise CollisionError(f"the {what} is in collision: {pairs}")

    def first_collision(self, samples: ArrayLike) -> int | None:
        """Index of the first colliding state among consecutive ``samples`` (N, 6), or None.

        States are checked at most ``resolution`` (metres of motion) apart, plus
        the last; a hit is reported at the checked sample.
        """
        s = np.asarray(samples, float)
        for i in self._checkpoints(s):
            if self.in_collision(s[i]):
                return int(i)
        return None

    def motion_free(
        self, start: ArrayLike, end: ArrayLike, resolution: float | None = None
    ) -> bool:
        """True if the straight joint-space motion from ``start`` to ``end`` is free
        (checked every ``resolution`` metres of motion, default :attr:`resolution`)."""
        a, b = np.asarray(start, float), np.asarray(end, float)
        step = self.resolution if resolution is None else float(resolution)
        n = max(math.ceil(float(np.max(np.abs(b - a) * LEVER_ARMS)) / step), 1)
        # Check the end first (cheap rejection of a bad target), then bisect the middle.
        order = [n, *_bisection_order(n)]
        return not any(self.in_collision(a + (b - a) * (k / n)) for k in order)

    def _checkpoints(self, s: Array) -> Iterable[int]:
        if len(s) == 0:
            return []
        moved = np.abs(np.diff(s, axis=0)) * LEVER_ARMS
        steps = np.max(moved, axis=1) if len(s) > 1 else np.zeros(0)
        travelled = np.concatenate(([0.0], np.cumsum(steps)))
        idx = np.searchsorted(travelled, np.arange(0.0, travelled[-1], self.resolution))
        return sorted({*idx.tolist(), len(s) - 1})


def _bisection_order(n: int) -> Sequence[int]:
    """Indices 0..n-1 ordered coarse to fine (midpoint first), for early rejection."""
    seen: list[int] = []
    mark = [False] * (n + 1)
    mark[n] = True
    step = n
    while step >= 1:
        for k in range(0, n, step):
            if not mark[k]:
                mark[k] = True
                seen.append(k)
        step //= 2
    for k in range(n):
        if not mark[k]:
            seen.append(k)
    return seen
