"""The arm's dynamic quantities for the RTDE outputs of newer PolyScope versions.

Joint torques (``actual_current_as_torque``), the wrench the arm puts on its base
(``target_base_wrench``) and the TCP's acceleration come from the UR3e's Pinocchio model
(:mod:`fxcell.motion.robot_model`: UR's masses and centres of mass) with the payload on the
flange and the controller's gravity. Built only when a client first asks for one of them
(Pinocchio is not loaded otherwise) and evaluated once per cycle while one is asked for.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from fxcell.motion.robot_model import RobotModel
from fxcell.protocol import CONTROL_PERIOD


class ArmDynamics:
    """Inverse dynamics of the simulated arm (rigid, no friction, no contact)."""

    def __init__(self) -> None:
        robot = RobotModel.ur3e()
        self.model = robot.model
        self.data = self.model.createData()
        self.flange = self.model.frames[robot.flange_frame_id].placement  # in joint 6's frame
        self.joint6 = robot.joint_ids[5]
        self.joint1 = robot.joint_ids[0]
        self.link6 = pin.Inertia(self.model.inertias[self.joint6])
        self.payload: tuple[float, tuple[float, ...]] = (0.0, (0.0, 0.0, 0.0))
        self.gravity: tuple[float, ...] = (0.0, 0.0, 9.82)
        self.model.gravity.linear = -np.array(self.gravity)
        self._speed: tuple[float, ...] | None = None

    def set_payload(self, mass: float, cog: Sequence[float]) -> None:
        """The payload as a point mass at ``cog`` (flange frame), carried by joint 6."""
        key = (float(mass), tuple(float(v) for v in cog))
        if key == self.payload:
            return
        self.payload = key
        inertia = pin.Inertia(max(mass, 0.0), np.array(key[1]), np.zeros((3, 3)))
        self.model.inertias[self.joint6] = self.link6 + self.flange.act(inertia)

    def set_gravity(self, direction: Sequence[float]) -> None:
        """UR's gravity direction: the acceleration opposing gravity, (0, 0, 9.82) upright."""
        g = tuple(float(v) for v in direction)
        if g != self.gravity:
            self.gravity = g
            self.model.gravity.linear = -np.array(g)

    def torques(
        self, q: Sequence[float], qd: Sequence[float], qdd: Sequence[float]
    ) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Joint torques (N·m) and the wrench (N, N·m, base frame) the arm puts on its base."""
        tau = pin.rnea(self.model, self.data, np.array(q), np.array(qd), np.array(qdd))
        # the spatial force joint 1 transmits to the arm, in the base frame: the base
        # carries it, and the arm pushes back on the base with its opposite
        f = self.data.oMi[self.joint1].act(self.data.f[self.joint1])
        wrench = -np.concatenate([f.linear, f.angular])
        return tuple(float(v) for v in tau), tuple(float(v) for v in wrench)

    def tcp_acceleration(self, speed: tuple[float, ...], steps: int) -> tuple[float, ...]:
        """The TCP's acceleration from its speed now and ``steps`` cycles ago."""
        last, self._speed = self._speed, speed
        if last is None or steps <= 0:
            return (0.0,) * 6
        dt = steps * CONTROL_PERIOD
        return tuple((a - b) / dt for a, b in zip(speed, last, strict=True))
