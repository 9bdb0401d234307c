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
from fxcell.geometry import Pose, rpy_to_matrix
from fxcell.layout import Layout
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
WALL_STEP = 0.02
"""Spacing (rad) of the joint values tried as walls (see :meth:`CollisionChecker.walls`)."""
WALL_SLACK = 0.003
"""Penetration (m) a wall's pair must show at every sample: covers the motion between
samples, so a wall holds for the joint values between them too."""


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


def _lever_arms(model: pin.Model, gm: pin.GeometryModel, bodies: list[int]) -> Array:
    """For each joint, the farthest any point of a body it moves can be from its origin,
    whatever the joints (so a joint step δ moves no point more than lever·δ): the bound
    :data:`LEVER_ARMS` gives the UR3e by hand, here from the chain and the shapes'
    bounding boxes (the distances between successive joint origins, then the farthest
    corner of the body's box from its joint), rounded up to the centimetre."""
    data = model.createData()
    pin.forwardKinematics(model, data, np.zeros(model.nq))
    origins = [np.asarray(data.oMi[k].translation) for k in range(model.njoints)]
    links = [float(np.linalg.norm(origins[k + 1] - origins[k])) for k in range(model.nq)]
    reach = np.zeros(model.nq)
    for g, body in zip(gm.geometryObjects, bodies, strict=True):
        if body == 0:
            continue
        g.geometry.computeLocalAABB()
        box = g.geometry.aabb_local
        lo, hi = np.asarray(box.min_), np.asarray(box.max_)
        corners = [g.placement.act(np.where([i & 1, i & 2, i & 4], hi, lo)) for i in range(8)]
        far = max(float(np.linalg.norm(c)) for c in corners)  # from the body's joint
        for joint in range(1, body + 1):
            chain = sum(links[joint:body])  # joint's origin to the body's joint origin
            reach[joint - 1] = max(reach[joint - 1], chain + far)
    return np.asarray(np.ceil(reach * 100) / 100, dtype=np.float64)


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
        layout: Layout | None = None,
        tcp: pin.SE3 | None = None,
        flange_in_joint6: pin.SE3 | None = None,
        gripper: bool = True,
        scene_margin: float = DEFAULT_SCENE_MARGIN,
        resolution: float = DEFAULT_RESOLUTION,
        arm: Sequence[pin.GeometryObject] | None = None,
        never: Iterable[tuple[str, str]] = (),
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
        self._names: list[str] = []
        self._scene: set[int] = set()
        self._never = {frozenset(pair) for pair in never}
        if arm is not None:  # the arm's (and its gripper's) own bodies, e.g. from a URDF
            for g in arm:
                self._add(gm, g.name, int(g.parentJoint), g.placement, g.geometry)
        else:  # the UR3e's capsules and the Hand-E
            for c in UR3E_CAPSULES:
                p, q = np.asarray(c.start, float), np.asarray(c.end, float)
                world = _segment_placement(p, q)
                shape = coal.Capsule(c.radius, float(np.linalg.norm(q - p)))
                self._add(gm, c.name, c.body, oMi[c.body].inverse() * world, shape)
            if gripper:
                for box in HAND_E:
                    centre = np.asarray(box.center, float)
                    placement = flange_in_joint6 * pin.SE3(np.eye(3), centre)
                    self._add(gm, box.name, 6, placement, coal.Box(*box.size))
        for obj in scene.objects:
            placement = pin.SE3(rpy_to_matrix(obj.rpy), np.asarray(obj.position, float))
            gid = self._add(gm, obj.name, 0, placement, coal.Box(*obj.size))
            self._scene.add(gid)
        # Objects the gripper may hold (one geometry per kind, hanging from the TCP); their
        # pairs stay inactive until attach().
        self._held_geoms: dict[str, int] = {}
        if layout is not None and gripper:
            tcp_in_joint6 = flange_in_joint6 * (tcp if tcp is not None else pin.SE3.Identity())
            for kind_name, kind in layout.config.objects.items():
                # The grip point is at the TCP; the object hangs along the TCP's z axis
                # (out of the flange): its bottom grip_height further, its top above.
                centre = np.array([0.0, 0.0, kind.grip_height - kind.height / 2])
                placement = tcp_in_joint6 * pin.SE3(np.eye(3), centre)
                shape = coal.Cylinder(kind.width / 2, kind.height)
                self._held_geoms[kind_name] = self._add(
                    gm, f"held_{kind_name}", 6, placement, shape
                )
        for station in layout or ():
            body = station.body_pose()
            if body is not None:
                pose, size = body
                placement = pin.SE3(pose.rotation, pose.position)
                self._scene.add(self._add(gm, station.name, 0, placement, coal.Box(*size)))

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
        self.lever_arms = LEVER_ARMS if arm is None else _lever_arms(model, gm, self._body)
        """Farthest point of the arm, gripper and held objects from each joint (m)."""
        self._walls: tuple[tuple[int, float], ...] | None = None
        self._held_pairs: dict[str, list[int]] = {kind: [] for kind in self._held_geoms}
        for k, pair in enumerate(gm.collisionPairs):
            for held, gid in self._held_geoms.items():
                if gid in (pair.first, pair.second):
                    self._held_pairs[held].append(k)
                    self.geometry_data.deactivateCollisionPair(k)
        self.held: str | None = None
        """The object kind attached to the TCP (checked against the scene), or None."""

    def attach(self, kind: str) -> None:
        """Check an object of ``kind`` (a layout object kind) held at the TCP from now on."""
        if kind not in self._held_pairs:
            known = ", ".join(sorted(self._held_pairs)) or "none"
            raise ValueError(f"no held-object geometry for kind {kind!r} (known: {known})")
        self.detach()
        for k in self._held_pairs[kind]:
            self.geometry_data.activateCollisionPair(k)
        self.held = kind

    def detach(self) -> None:
        """The gripper holds nothing (from now on)."""
        if self.held is not None:
            for k in self._held_pairs[self.held]:
                self.geometry_data.deactivateCollisionPair(k)
        self.held = None

    def _add(self, gm: pin.GeometryModel, name: str, body: int, M: pin.SE3, shape: object) -> int:
        gid = int(gm.addGeometryObject(pin.GeometryObject(name, body, M, shape)))
        self._body.append(body)
        self._names.append(name)
        return gid

    def _checked(self, a: int, b: int) -> bool:
        ba, bb = self._body[a], self._body[b]
        if ba == 0 and bb == 0:  # fixed against fixed (base, table, machine)
            return False
        if frozenset((self._names[a], self._names[b])) in self._never:
            return False  # the arm's maker: the joint limits keep these apart
        return abs(ba - bb) >= 2 or a in self._scene or b in self._scene

    @classmethod
    def for_config(cls, config: CellConfig, **options: float | bool) -> CollisionChecker:
        """The checker for a cell: the UR3e model, the gripper and the configured scene."""
        robot = RobotModel.ur3e(limits=config.limits)
        tcp = Pose.from_ur(config.tool.tcp)
        return cls(
            robot.model,
            config.scene,
            layout=Layout(config.layout),
            tcp=pin.SE3(tcp.rotation, tcp.position),
            flange_in_joint6=robot.flange_in_joint6,
            **options,  # type: ignore[arg-type]
        )

    @classmethod
    def from_urdf(
        cls,
        urdf: str,
        scene: SceneConfig,
        *,
        tool_frame: str,
        never: Iterable[tuple[str, str]] = (),
        layout: Layout | None = None,
        tcp: pin.SE3 | None = None,
        **options: float,
    ) -> CollisionChecker:
        """The checker for an arm described by a URDF with collision shapes (no meshes):
        its links' and gripper's bodies (named by their links), the scene, and the
        layout's objects held at ``tcp`` in ``tool_frame`` (the flange or tool link).
        ``never``: pairs of links its maker never checks (the joint limits keep them
        apart)."""
        model = pin.buildModelFromXML(urdf)
        geometry = pin.buildGeomFromUrdfString(model, urdf, pin.COLLISION)
        arm = []
        for g in geometry.geometryObjects:
            g.name = model.frames[g.parentFrame].name  # the link's name, not "<link>_0"
            arm.append(g)
        flange = model.frames[model.getFrameId(tool_frame)].placement
        return cls(
            model,
            scene,
            layout=layout,
            tcp=tcp,
            flange_in_joint6=flange,
            arm=arm,
            never=never,
            **options,  # type: ignore[arg-type]
        )

    # ------------------------------------------------------------ walls

    def walls(self) -> tuple[tuple[int, float], ...]:
        """Joint values no path can cross: ``(joint index, value)`` such that every
        configuration with that joint at that value collides, whatever the other joints.

        Found where a collision pair's relative placement depends on that joint and at
        most one other: the upper arm hanging into the table (any base angle), a link
        folded onto another. Each candidate value (every ``WALL_STEP`` within the limits)
        is kept if the pair collides, ``WALL_SLACK`` deep, at every sample of the other
        joint (spaced so that no point moves more than twice the slack between samples).
        One value per blocked interval. Computed once, on first use (~0.1 s).
        """
        if self._walls is None:
            self._walls = self._find_walls()
        return self._walls

    def separating_wall(self, start: ArrayLike, end: ArrayLike) -> tuple[int, float] | None:
        """A wall strictly between ``start`` and ``end`` (then no path joins them), or None."""
        a, b = np.asarray(start, float), np.asarray(end, float)
        for joint, value in self.walls():
            if min(a[joint], b[joint]) < value < max(a[joint], b[joint]):
                return joint, value
        return None

    def _find_walls(self) -> tuple[tuple[int, float], ...]:
        gm = self.geometry_model
        gd = pin.GeometryData(gm)
        for k, pair in enumerate(gm.collisionPairs):
            margin = (
                self.scene_margin
                if pair.first in self._scene or pair.second in self._scene
                else 0.0
            )
            gd.collisionRequests[k].security_margin = margin - WALL_SLACK
        data = self.model.createData()
        lo, hi = self.model.lowerPositionLimit, self.model.upperPositionLimit
        found: list[tuple[int, float]] = []
        # Walls of the bare gripper: a held object only adds collisions, so they stay walls
        # whatever the gripper holds.
        held = {k for pairs in self._held_pairs.values() for k in pairs}
        for joint in range(6):
            moved = joint + 1  # the body joint ``joint`` carries
            by_free: dict[int | None, list[int]] = {}
            for k, pair in enumerate(gm.collisionPairs):
                if k in held:
                    continue
                bodies = sorted((self._body[pair.first], self._body[pair.second]))
                if bodies[1] != moved:
                    continue
                # joints the pair's relative placement depends on besides ``joint``
                free = list(range(bodies[0], joint)) if bodies[0] > 0 else list(range(joint))
                if len(free) <= 1:
                    by_free.setdefault(free[0] if free else None, []).append(k)
            for free_joint, pairs in by_free.items():
                found += self._walls_of(joint, free_joint, pairs, data, gd, lo, hi)
        return tuple(sorted(found))

    def _walls_of(
        self,
        joint: int,
        free: int | None,
        pairs: list[int],
        data: pin.Data,
        gd: pin.GeometryData,
        lo: Array,
        hi: Array,
    ) -> list[tuple[int, float]]:
        gm = self.geometry_model

        def blocked(value: float, samples: Array) -> bool:
            q = np.zeros(6)
            q[joint] = value
            for v in samples:
                if free is not None:
                    q[free] = v
                pin.forwardKinematics(self.model, data, q)
                pin.updateGeometryPlacements(self.model, data, gm, gd)
                if not any(pin.computeCollision(gm, gd, k) for k in pairs):
                    return False
            return True

        if free is None:
            coarse = fine = np.zeros(1)
        else:
            coarse = np.linspace(lo[free], hi[free], 37)
            step = 2 * WALL_SLACK / self.lever_arms[free]
            fine = np.linspace(lo[free], hi[free], math.ceil((hi[free] - lo[free]) / step) + 1)
        values = np.arange(lo[joint] + WALL_STEP, hi[joint], WALL_STEP)
        hits = [blocked(float(v), coarse) for v in values]
        out: list[tuple[int, float]] = []
        k = 0
        while k < len(values):
            if not hits[k]:
                k += 1
                continue
            end = k
            while end + 1 < len(values) and hits[end + 1]:
                end += 1
            middle = float(values[(k + end) // 2])
            if blocked(middle, fine):
                out.append((joint, middle))
            k = end + 1
        return out

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
        n = max(math.ceil(float(np.max(np.abs(b - a) * self.lever_arms)) / step), 1)
        # Check the end first (cheap rejection of a bad target), then bisect the middle.
        order = [n, *_bisection_order(n)]
        return not any(self.in_collision(a + (b - a) * (k / n)) for k in order)

    def _checkpoints(self, s: Array) -> Iterable[int]:
        if len(s) == 0:
            return []
        moved = np.abs(np.diff(s, axis=0)) * self.lever_arms
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
