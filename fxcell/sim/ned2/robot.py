"""The simulated Ned2: joints moving at the model's limits, calibration, learning mode,
collision detection, the tool (Gripper 1) with objects, IO and the hardware status.

Objects are the simulators' common :class:`~fxcell.sim.gripper.SimObject` (grip point, kind,
size, contents), so that a simulated device such as the fusion machine
(:mod:`fxcell.sim.fusion`) sees the same world on either robot; the robot is the machine's
:class:`~fxcell.sim.fusion.MachineIO` (its digital pins, the inputs a device owns refused
to anyone else).

Errors the robot's ROS side reports are :class:`RobotError` (a ``CommandStatus`` code
and a message); the TCP server wraps them as Niryo's server does.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fxcell.errors import InvalidArgumentError
from fxcell.geometry import Pose
from fxcell.motion import ned2
from fxcell.sim.gripper import SimObject
from fxcell.sim.signals import Signal

# niryo_robot_msgs/CommandStatus values the simulator reports
ABORTED = -3
STOPPED = -4
INVALID_PARAMETERS = -52
HARDWARE_NOT_OK = -111
LEARNING_MODE_ON = -112
CALIBRATION_NOT_DONE = -113
CALIBRATION_IN_PROGRESS = -125
GOAL_STILL_ACTIVE = -221
INVERT_KINEMATICS_FAILURE = -232
TOOL_FAILURE = -251
TOOL_NOT_CONNECTED = -253

CALIBRATION_TIME = 8.0  # s: the arm runs to its end stops and back (x time scale)
GRIPPER_TIME = 0.5  # s: fingers open or close
GRIPPER_1_STROKE = 0.027  # m between open and closed fingers
GRIPPER_TCP = 0.075  # m along tool_link's x: where the fingers close (Gripper 1)
GRASP_TOLERANCE = 0.01  # m: an object's grip point this close to the fingers is caught
# Gripper 1 position in motor steps (closed, open): Niryo's tools_definition.yaml (ned2)
GRIPPER_STEPS = (900, 2200)
TOOLS = {"NONE": 0, "GRIPPER_1": 11}
DIGITAL_INPUTS = ("DI1", "DI2", "DI3", "DI4", "DI5")
DIGITAL_OUTPUTS = ("DO1", "DO2", "DO3", "DO4")
ANALOG_INPUTS = ("AI1", "AI2")
ANALOG_OUTPUTS = ("AO1", "AO2")
MACHINE_SIGNALS: dict[str, str] = {
    "start": "DO1",
    "ready": "DI1",
    "busy": "DI2",
    "done": "DI3",
    "error": "DI5",
}
"""The fusion machine's signals by default (``--machine-io``): pins of the Ned2's IO panel
(DI4 and DO4 are on the tool connector)."""
MOTOR_NAMES = ["joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6", "tool"]
MOTOR_TYPES = ["NIRYO_STEPPER"] * 3 + ["DXL_XL430"] * 2 + ["DXL_XL330"] * 2
CYCLE = 0.01  # s of robot time per motion step
TRAJECTORY_START_TOLERANCE = 0.01  # rad: a trajectory must start this close to the arm


class RobotError(Exception):
    """What the robot's ROS side answers: a CommandStatus code and its message."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(f"Error Code : {code}\nMessage : {message}")
        self.code = code
        self.message = message


def new_object(
    name: str,
    position: np.ndarray | list[float],
    width: float = 0.02,
    *,
    kind: str = "object",
    height: float = 0.04,
    mass: float = 0.02,
    contents: str | None = None,
) -> SimObject:
    """An upright object whose grip point is at ``position`` (base_link, m)."""
    return SimObject(name, kind, width, height, mass, Pose(position), contents=contents)


@dataclass
class Ned2Robot:
    """The robot's state; moves and calibration are coroutines that take robot time
    (``time_scale`` x real seconds)."""

    time_scale: float = 1.0
    joints: np.ndarray = field(default_factory=lambda: ned2.HOME.copy())
    calibrated: bool = False
    calibrating: bool = False
    learning_mode: bool = True  # a Ned2 boots compliant
    collision_detected: bool = False
    velocity_percent: float = 100.0
    motor_error: int = 0  # joint number with a hardware error, 0: none
    tool: str = "GRIPPER_1"
    gripper_open: bool = True
    held: str | None = None
    objects: dict[str, SimObject] = field(default_factory=dict)
    digital_out: dict[str, bool] = field(
        default_factory=lambda: dict.fromkeys(DIGITAL_OUTPUTS, False)
    )
    digital_in: dict[str, bool] = field(
        default_factory=lambda: dict.fromkeys(DIGITAL_INPUTS, False)
    )
    analog_out: dict[str, float] = field(default_factory=lambda: dict.fromkeys(ANALOG_OUTPUTS, 0.0))
    analog_in: dict[str, float] = field(default_factory=lambda: dict.fromkeys(ANALOG_INPUTS, 0.0))
    moving: bool = False
    log: list[str] = field(default_factory=list)
    faults: list[str] = field(default_factory=list)
    """Every fault since the start: detected collisions and injected faults."""
    input_owners: dict[str, str] = field(default_factory=dict)  # "DI1" -> the device driving it
    _abort: tuple[int, str] | None = None

    # ------------------------------------------------------------------ state

    def pose(self) -> list[float]:
        return ned2.matrix_to_pose(ned2.forward(self.joints))

    def fingers(self) -> np.ndarray:
        t = ned2.forward(self.joints)
        return np.asarray(t[:3, 3] + GRIPPER_TCP * t[:3, 0])

    def state(self) -> dict[str, Any]:
        return {
            "joints": [float(v) for v in self.joints],
            "pose": self.pose(),
            "calibrated": self.calibrated,
            "calibrating": self.calibrating,
            "learning_mode": self.learning_mode,
            "collision_detected": self.collision_detected,
            "moving": self.moving,
            "velocity_percent": self.velocity_percent,
            "motor_error": self.motor_error,
            "tool": self.tool,
            "gripper_open": self.gripper_open,
            "held": self.held,
            "objects": {n: o.pose.position.tolist() for n, o in self.objects.items()},
            "digital_out": dict(self.digital_out),
            "digital_in": dict(self.digital_in),
            "log": self.log[-20:],
            "faults": list(self.faults),
        }

    def hardware_status(self) -> list[Any]:
        error = f"joint_{self.motor_error}: overload" if self.motor_error else ""
        errors = [0] * 7
        if self.motor_error:
            errors[self.motor_error - 1] = 32
        return [
            52.0,
            "ned2",
            True,
            f"'{error}'",
            not self.calibrated,
            self.calibrating,
            list(MOTOR_NAMES),
            list(MOTOR_TYPES),
            [34.0, 35.0, 35.0, 38.0, 37.0, 36.0, 33.0],
            [12.1, 12.1, 12.1, 11.9, 11.9, 11.9, 11.9],
            errors,
        ]

    # ------------------------------------------------------------------ IO (MachineIO)

    def output(self, signal: Signal) -> bool:
        """The level of digital output ``signal`` (DO1-DO4)."""
        return self.digital_out[str(signal)]

    def input(self, signal: Signal) -> float:
        """The value of input ``signal`` (1.0/0.0 for DI1-DI5, volts for AI1-AI2)."""
        name = str(signal)
        if name in self.analog_in:
            return self.analog_in[name]
        return 1.0 if self.digital_in[name] else 0.0

    def set_input(self, signal: Signal | str, value: float, owner: str | None = None) -> None:
        """Set an input from outside the robot (a device wired to it, the control port);
        an input a device drives only by that device (InvalidArgumentError)."""
        name = str(signal)
        if name not in self.digital_in and name not in self.analog_in:
            raise InvalidArgumentError(f"the Ned2 has no input {name}")
        holder = self.input_owners.get(name)
        if holder is not None and holder != owner:
            raise InvalidArgumentError(f"{name} is driven by {holder}")
        if name in self.digital_in:
            self.digital_in[name] = bool(value)
        else:
            self.analog_in[name] = float(value)

    # ------------------------------------------------------------------ faults

    def abort(self, code: int, message: str) -> None:
        """Stop a running move (it fails with ``code``/``message``)."""
        if self.moving:
            self._abort = (code, message)

    def collide(self) -> None:
        self.collision_detected = True
        self.abort(
            ABORTED,
            "Command has been aborted due to a collision or a motor not able to follow the "
            "given trajectory",
        )
        self.log.append("collision detected")
        self.faults.append("collision detected")

    def power_loss(self) -> None:
        self.abort(ABORTED, "Command has been aborted: the robot lost power")
        self.calibrated = False
        self.calibrating = False
        self.learning_mode = True
        self.log.append("power lost")

    def drop_held(self) -> None:
        if self.held is not None:
            obj = self.objects[self.held]
            position = obj.pose.position.copy()
            position[2] = max(0.0, position[2] - 0.05)  # it falls below the fingers
            obj.pose = Pose(position)
            obj.held_from = None
            self.log.append(f"{self.held} slipped out of the gripper")
            self.held = None

    # ------------------------------------------------------------------ commands

    def _check_can_move(self) -> None:
        if self.calibrating:
            raise RobotError(CALIBRATION_IN_PROGRESS, "Calibration in progress")
        if not self.calibrated:
            raise RobotError(CALIBRATION_NOT_DONE, "Robot not calibrated: calibrate it first")
        if self.motor_error:
            raise RobotError(
                HARDWARE_NOT_OK, f"Hardware error on joint_{self.motor_error}: reboot the motor"
            )
        if self.moving:
            raise RobotError(GOAL_STILL_ACTIVE, "A goal is still active")
        # the arm commander leaves learning mode (torque on) before it moves
        self.learning_mode = False

    async def _sleep(self, robot_seconds: float) -> None:
        await asyncio.sleep(max(0.0, robot_seconds * self.time_scale))

    async def calibrate(self) -> None:
        if self.calibrated:
            return  # "auto calibration does nothing if the motors are calibrated"
        if self.calibrating:
            raise RobotError(CALIBRATION_IN_PROGRESS, "Calibration in progress")
        self.calibrating = True
        self.log.append("calibration started")
        try:
            await self._sleep(CALIBRATION_TIME)
        finally:
            self.calibrating = False
        self.calibrated = True
        self.joints = ned2.HOME.copy()
        self._carry()
        self.log.append("calibration done")

    def set_learning_mode(self, on: bool) -> None:
        if on and self.moving:
            self.abort(STOPPED, "Command has been stopped: learning mode activated")
        self.learning_mode = on

    def check_joints(self, q: list[float]) -> np.ndarray:
        a = np.asarray(q, dtype=float)
        if a.shape != (6,) or not np.all(np.isfinite(a)):
            raise RobotError(INVALID_PARAMETERS, "Joints must be 6 finite numbers")
        for i, (v, lo, hi) in enumerate(zip(a, ned2.LOWER, ned2.UPPER, strict=True)):
            if not lo <= v <= hi:
                raise RobotError(
                    INVALID_PARAMETERS,
                    f"joint_{i + 1} target {v:.4f} rad is out of its limits [{lo:.4f}, {hi:.4f}]",
                )
        return a

    def solve(self, pose: list[float]) -> np.ndarray:
        p = np.asarray(pose, dtype=float)
        if p.shape != (6,) or not np.all(np.isfinite(p)) or np.max(np.abs(p[:3])) > 10.0:
            raise RobotError(INVALID_PARAMETERS, "A pose must be 6 finite numbers")
        result = ned2.inverse(p, self.joints)
        if result.q is None:
            raise RobotError(
                INVERT_KINEMATICS_FAILURE, "Failed to get inverse kinematics for this pose"
            )
        return result.q

    def _profile(self, start: np.ndarray, goal: np.ndarray) -> tuple[float, float, float]:
        """The path parameter's limits (1/s, 1/s^2) from the joints' (x velocity %) and
        the segment's duration: every joint follows s(t) at or under its limits."""
        v = ned2.VELOCITY_LIMITS * (self.velocity_percent / 100.0)
        a = ned2.ACCELERATION_LIMITS
        d = np.maximum(np.abs(goal - start), 1e-12)
        vs = float(np.min(v / d))
        as_ = float(np.min(a / d))
        if vs * vs / as_ >= 1.0:  # triangular: never reaches vs
            vs = math.sqrt(as_)
            return vs, as_, 2.0 * vs / as_
        return vs, as_, 1.0 / vs + vs / as_

    async def move_joints(self, goal: np.ndarray) -> None:
        self._check_can_move()
        await self._follow([self.joints.copy(), goal])

    async def move_linear(self, pose: list[float]) -> None:
        self._check_can_move()
        start = ned2.forward(self.joints)
        end = ned2.pose_to_matrix(pose)
        distance = float(np.linalg.norm(end[:3, 3] - start[:3, 3]))
        steps = max(2, math.ceil(distance / 0.005) + 1)
        path = [self.joints.copy()]
        r0 = start[:3, :3]
        rel = r0.T @ end[:3, :3]
        angle = math.acos(max(-1.0, min(1.0, (np.trace(rel) - 1.0) / 2.0)))
        axis = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
        n = np.linalg.norm(axis)
        axis = axis / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])
        for k in range(1, steps):
            s = k / (steps - 1)
            t = np.eye(4)
            t[:3, 3] = start[:3, 3] + s * (end[:3, 3] - start[:3, 3])
            t[:3, :3] = r0 @ _axis_angle(axis, s * angle)
            result = ned2.inverse(t, path[-1], branches=False)
            if result.q is None:  # the local solve lost the branch: look for all of them
                result = ned2.inverse(t, path[-1])
            if result.q is None or np.max(np.abs(result.q - path[-1])) > 0.3:
                raise RobotError(
                    INVERT_KINEMATICS_FAILURE,
                    "Failed to plan a linear trajectory: a point of the line is out of reach",
                )
            path.append(result.q)
        await self._follow(path)

    async def _follow(self, waypoints: list[np.ndarray]) -> None:
        """Run through joint waypoints, each segment timed at the limits."""
        self.moving = True
        self._abort = None
        try:
            for a, b in itertools.pairwise(waypoints):
                vs, as_, duration = self._profile(a, b)
                clock = time.monotonic()
                while True:
                    abort = self._pending_abort()
                    if abort is not None:
                        raise RobotError(*abort)
                    elapsed = (time.monotonic() - clock) / self.time_scale
                    if elapsed >= duration:
                        self.joints = b.copy()
                        self._carry()
                        break
                    self.joints = a + (b - a) * _trapezoid(elapsed, vs, as_, duration)
                    self._carry()
                    await self._sleep(CYCLE)
        finally:
            self.moving = False
            self._abort = None

    async def follow_trajectory(
        self, times: np.ndarray, positions: np.ndarray, velocities: np.ndarray
    ) -> None:
        """Run a timed joint trajectory as the arm's trajectory controller does: points at
        ``times`` (s from the start, robot time), interpolated by cubic Hermite segments
        through their positions and velocities. Refused (nothing moves) unless it starts
        where the arm is, stays within the joint limits and the velocity limits (x the
        velocity scaling), and its times increase."""
        self._check_can_move()
        n = len(times)
        if n == 0 or positions.shape != (n, 6) or velocities.shape != (n, 6):
            raise RobotError(INVALID_PARAMETERS, "A trajectory needs points of 6 joints")
        finite = np.isfinite(times).all() and np.isfinite(positions).all()
        if not finite or not np.isfinite(velocities).all():
            raise RobotError(INVALID_PARAMETERS, "A trajectory's values must be finite")
        if times[0] < 0 or np.any(np.diff(times) <= 0):
            raise RobotError(INVALID_PARAMETERS, "A trajectory's times must increase")
        if np.max(np.abs(positions[0] - self.joints)) > TRAJECTORY_START_TOLERANCE:
            raise RobotError(INVALID_PARAMETERS, "The trajectory does not start where the arm is")
        if not all(ned2.within_limits(q) for q in positions):
            raise RobotError(INVALID_PARAMETERS, "A trajectory point is out of the joint limits")
        limit = ned2.VELOCITY_LIMITS * (self.velocity_percent / 100.0) * 1.001
        if np.any(np.abs(velocities) > limit):
            raise RobotError(INVALID_PARAMETERS, "A trajectory point exceeds the velocity limits")
        self.moving = True
        self._abort = None
        clock = time.monotonic()
        try:
            while True:
                abort = self._pending_abort()
                if abort is not None:
                    raise RobotError(*abort)
                t = (time.monotonic() - clock) / self.time_scale
                if t >= times[-1]:
                    self.joints = positions[-1].copy()
                    self._carry()
                    return
                k = max(int(np.searchsorted(times, t, side="right")) - 1, 0)
                if t < times[0]:  # before the first point: hold where the arm starts
                    self.joints = positions[0].copy()
                else:
                    self.joints = _hermite(
                        t - times[k],
                        times[k + 1] - times[k],
                        positions[k],
                        velocities[k],
                        positions[k + 1],
                        velocities[k + 1],
                    )
                self._carry()
                await self._sleep(CYCLE)
        finally:
            self.moving = False
            self._abort = None

    def _pending_abort(self) -> tuple[int, str] | None:
        return self._abort

    def _carry(self) -> None:
        if self.held is not None:
            self.objects[self.held].pose = Pose(self.fingers())

    # ------------------------------------------------------------------ tool

    def _check_tool(self) -> None:
        if self.tool == "NONE":
            raise RobotError(TOOL_NOT_CONNECTED, "No tool connected")

    async def close_gripper(self) -> None:
        self._check_tool()
        await self._sleep(GRIPPER_TIME)
        self.gripper_open = False
        if self.held is None:
            fingers = self.fingers()
            for obj in self.objects.values():
                if np.linalg.norm(obj.pose.position - fingers) <= GRASP_TOLERANCE:
                    self.held = obj.name
                    obj.pose = Pose(fingers)
                    obj.held_from = Pose()  # its grip point between the fingers
                    self.log.append(f"gripped {obj.name}")
                    break

    async def open_gripper(self) -> None:
        self._check_tool()
        await self._sleep(GRIPPER_TIME)
        self.gripper_open = True
        if self.held is not None:
            self.objects[self.held].held_from = None
            self.log.append(f"released {self.held}")
            self.held = None

    def tool_position(self) -> int:
        closed, opened = GRIPPER_STEPS
        if self.gripper_open:
            return opened
        if self.held is not None:  # the fingers stop on the object
            width = self.objects[self.held].width
            return round(closed + (opened - closed) * min(1.0, width / GRIPPER_1_STROKE))
        return closed


def _trapezoid(t: float, vs: float, as_: float, duration: float) -> float:
    """Progress 0..1 at time ``t`` of a trapezoidal profile (peak ``vs``, accel ``as_``)."""
    ta = vs / as_
    if t <= ta:
        return 0.5 * as_ * t * t
    if t >= duration - ta:
        r = max(0.0, duration - t)
        return 1.0 - 0.5 * as_ * r * r
    return 0.5 * as_ * ta * ta + vs * (t - ta)


def _hermite(
    t: float, h: float, p0: np.ndarray, v0: np.ndarray, p1: np.ndarray, v1: np.ndarray
) -> np.ndarray:
    """The cubic through ``p0`` (velocity ``v0``) at 0 and ``p1`` (``v1``) at ``h``, at ``t``."""
    s = t / h
    h00 = 2 * s**3 - 3 * s**2 + 1
    h10 = s**3 - 2 * s**2 + s
    h01 = -2 * s**3 + 3 * s**2
    h11 = s**3 - s**2
    return np.asarray(h00 * p0 + h10 * h * v0 + h01 * p1 + h11 * h * v1)


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.asarray(np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k))
