"""The arm's dynamic quantities for the RTDE outputs of newer PolyScope versions.

Joint torques (``actual_current_as_torque``), the wrench the arm puts on its base
(``target_base_wrench``) and the TCP's acceleration come from the UR3e's Pinocchio model
(:mod:`fxcell.motion.robot_model`: UR's masses and centres of mass) with the payload on the
flange and the controller's gravity. Built in a thread while the simulator boots (importing
Pinocchio takes a few hundred ms the cycle must not wait for; a setup asking for these
outputs before it is ready is answered once it is) and evaluated once per cycle while some
recipe holds one of them, only when the joint state, payload or gravity changed (~3 µs).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from fxcell.motion.robot_model import RobotModel
from fxcell.protocol import CONTROL_PERIOD

FloatArray = NDArray[np.float64]


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

    def torques(self, q: FloatArray, qd: FloatArray, qdd: FloatArray) -> tuple[float, ...]:
        """Joint torques (N·m) moving the arm at ``q, qd, qdd`` (inverse dynamics)."""
        tau: FloatArray = pin.rnea(self.model, self.data, q, qd, qdd)
        return tuple(tau.tolist())

    def base_wrench(self) -> tuple[float, ...]:
        """The wrench (N, N·m, base frame) the arm puts on its base, from the last
        :meth:`torques`: the opposite of the force the base transmits through joint 1."""
        f = self.data.oMi[self.joint1].act(self.data.f[self.joint1])
        return tuple((-np.concatenate([f.linear, f.angular])).tolist())

    def tcp_acceleration(self, speed: tuple[float, ...], steps: int) -> tuple[float, ...]:
        """The TCP's acceleration from its speed now and ``steps`` cycles ago."""
        last, self._speed = self._speed, speed
        if last is None or steps <= 0:
            return (0.0,) * 6
        dt = steps * CONTROL_PERIOD
        return tuple((a - b) / dt for a, b in zip(speed, last, strict=True))
