"""Pinocchio model of the UR3e, built in code from UR's DH parameters.

Frames are UR's, not ROS's: the model's world is the controller's base frame (ROS
``base_link`` is turned 180° about z from it) and each joint turns about the z axis of the
previous DH frame, so ``q`` are UR's joint angles and the ``tool0`` frame is the flange
exactly as :mod:`fxcell.motion.kinematics` computes it (checked to 1e-12 by the tests).

Layout for users of the model (e.g. :mod:`fxcell.motion.collision`, which adds a GeometryModel):

- joints 1..6 (``JOINT_NAMES``), revolute about their local z; joint ``k``'s frame is DH
  frame ``k-1`` turned by ``q[k-1]``;
- body frames ``LINK_NAMES[k-1]`` on joint ``k`` = DH frame ``k`` (UR's link frames, where
  UR gives the centres of mass); ``base`` on the universe; ``tool0`` = DH frame 6 (the
  flange) and ``tcp`` = ``tool0`` · TCP, both on joint 6.

Masses and centres of mass are UR's published UR3e values; the rotational inertias are
approximations (uniform cylinders and spheres), good enough for gravity and rough dynamics.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from fxcell.geometry import Pose
from fxcell.motion.kinematics import DH, JOINT_NAMES, LINK_NAMES, UR3E_DH, _as_tcp, _joints

if TYPE_CHECKING:
    from fxcell.config import JointLimits

FloatArray = NDArray[np.float64]

BASE_FRAME = "base"
FLANGE_FRAME = "tool0"
TCP_FRAME = "tcp"

# UR3e dynamics as published by UR (link k in DH frame k): mass (kg), centre of mass (m).
UR3E_MASSES = (1.98, 3.4445, 1.437, 0.871, 0.805, 0.261)
UR3E_COMS = (
    (0.0, -0.02, 0.0),
    (0.13, 0.0, 0.1157),
    (0.05, 0.0, 0.0238),
    (0.0, 0.0, 0.01),
    (0.0, 0.0, 0.01),
    (0.0, 0.0, -0.02),
)
UR3E_MAX_TORQUES = (56.0, 56.0, 28.0, 12.0, 12.0, 12.0)
"""Rated joint torques (N·m): size-3 base and shoulder, size-2 elbow, size-1 wrists."""


def _dh_fixed(d: float, a: float, alpha: float) -> pin.SE3:
    """The constant part ``Tz(d)·Tx(a)·Rx(α)`` of a DH transform."""
    ca, sa = math.cos(alpha), math.sin(alpha)
    R = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    return pin.SE3(R, np.array([a, 0.0, d]))


def _link_inertia(k: int, dh: DH) -> pin.Inertia:
    """Approximate spatial inertia of link ``k`` (0-based) in its DH frame."""
    m = UR3E_MASSES[k]
    com = np.array(UR3E_COMS[k])
    length = abs(dh.a[k])
    if length > 0.0:  # upper arm and forearm: cylinders r = 4 cm along the DH x axis
        r = 0.04
        ixx = 0.5 * m * r * r
        iyy = izz = m * (3 * r * r + length * length) / 12.0
        inertia = np.diag([ixx, iyy, izz])
    else:  # joint housings: spheres r = 5 cm
        inertia = np.eye(3) * 0.4 * m * 0.05**2
    return pin.Inertia(m, com, inertia)


@dataclass(frozen=True, eq=False)
class RobotModel:
    """The Pinocchio ``model`` with the ids of its joints and frames and its TCP."""

    model: pin.Model
    tcp: Pose
    dh: DH
    joint_ids: tuple[int, ...]
    link_frame_ids: tuple[int, ...]
    base_frame_id: int
    flange_frame_id: int
    tcp_frame_id: int

    @classmethod
    def ur3e(
        cls,
        tcp: Sequence[float] | Pose | None = None,
        limits: JointLimits | None = None,
        dh: DH = UR3E_DH,
    ) -> RobotModel:
        """Build the UR3e; ``tcp`` in the flange frame (``None`` = flange), ``limits``
        default to :class:`fxcell.config.JointLimits` (positions and velocities)."""
        if limits is None:
            from fxcell.config import JointLimits

            limits = JointLimits()
        tcp_pose = _as_tcp(tcp)
        model = pin.Model()
        model.name = "ur3e"
        base_id = model.addFrame(pin.Frame(BASE_FRAME, 0, 0, pin.SE3.Identity(), pin.FIXED_JOINT))
        parent = 0
        placement = pin.SE3.Identity()
        joint_ids: list[int] = []
        link_ids: list[int] = []
        previous_frame = base_id
        for k in range(6):
            jid = model.addJoint(
                parent,
                pin.JointModelRZ(),
                placement,
                JOINT_NAMES[k],
                np.array([UR3E_MAX_TORQUES[k]]),
                np.array([limits.velocity[k]]),
                np.array([limits.position_min[k]]),
                np.array([limits.position_max[k]]),
            )
            joint_frame = model.addFrame(
                pin.Frame(JOINT_NAMES[k], jid, previous_frame, pin.SE3.Identity(), pin.JOINT)
            )
            fixed = _dh_fixed(dh.d[k], dh.a[k], dh.alpha[k])  # joint frame -> DH frame k
            model.appendBodyToJoint(jid, fixed.act(_link_inertia(k, dh)), pin.SE3.Identity())
            link_ids.append(
                model.addFrame(pin.Frame(LINK_NAMES[k], jid, joint_frame, fixed, pin.BODY), False)
            )
            joint_ids.append(jid)
            previous_frame = link_ids[-1]
            parent, placement = jid, fixed
        last = joint_ids[-1]
        flange = placement  # DH frame 6 in joint 6's frame
        flange_id = model.addFrame(
            pin.Frame(FLANGE_FRAME, last, previous_frame, flange, pin.OP_FRAME), False
        )
        tcp_se3 = pin.SE3(np.array(tcp_pose.rotation), np.array(tcp_pose.position))
        tcp_id = model.addFrame(
            pin.Frame(TCP_FRAME, last, flange_id, flange * tcp_se3, pin.OP_FRAME), False
        )
        return cls(
            model=model,
            tcp=tcp_pose,
            dh=dh,
            joint_ids=tuple(joint_ids),
            link_frame_ids=tuple(link_ids),
            base_frame_id=base_id,
            flange_frame_id=flange_id,
            tcp_frame_id=tcp_id,
        )

    # -------------------------------------------------------------- helpers

    def create_data(self) -> pin.Data:
        return self.model.createData()

    @property
    def flange_in_joint6(self) -> pin.SE3:
        """Placement of the flange (``tool0``) in joint 6's frame."""
        return self.model.frames[self.flange_frame_id].placement

    def frame_pose(self, q: ArrayLike, frame_id: int, data: pin.Data | None = None) -> Pose:
        """Placement of a frame in the base frame at ``q``."""
        data = data if data is not None else self.create_data()
        pin.framesForwardKinematics(self.model, data, np.array(_joints(q)))
        M = data.oMf[frame_id]
        return Pose._raw(np.array(M.translation), np.array(M.rotation))

    def tcp_pose(self, q: ArrayLike, data: pin.Data | None = None) -> Pose:
        """TCP pose in the base frame (equals :meth:`Kinematics.forward`)."""
        return self.frame_pose(q, self.tcp_frame_id, data)

    def jacobian(
        self, q: ArrayLike, frame_id: int | None = None, data: pin.Data | None = None
    ) -> FloatArray:
        """6×6 Jacobian of a frame (default the TCP) at ``q``: linear velocity of the frame
        origin and angular velocity, both in base-frame axes (LOCAL_WORLD_ALIGNED)."""
        data = data if data is not None else self.create_data()
        frame = self.tcp_frame_id if frame_id is None else frame_id
        J: FloatArray = pin.computeFrameJacobian(
            self.model, data, np.array(_joints(q)), frame, pin.LOCAL_WORLD_ALIGNED
        )
        return J

    def gravity_torques(self, q: ArrayLike, data: pin.Data | None = None) -> FloatArray:
        """Joint torques (N·m) holding the arm (without payload) against gravity at ``q``."""
        data = data if data is not None else self.create_data()
        tau: FloatArray = pin.computeGeneralizedGravity(self.model, data, np.array(_joints(q)))
        return tau


def ur3e_model(tcp: Sequence[float] | Pose | None = None) -> pin.Model:
    """The UR3e Pinocchio model alone (see :class:`RobotModel` for its frame ids)."""
    return RobotModel.ur3e(tcp).model
