"""The Ned2's link: :class:`Ned2Link`, an implementation of the robot-neutral contract
(:class:`~fxcell.link.backend.LinkBackend`) over the robot's rosbridge.

- **State**: ``/joint_states`` drives the stream (one :class:`~fxcell.protocol.RobotState`
  per message, stamped with the robot's time); the hardware status, learning mode and
  collision detection are folded in as the modes the robot-mode state machine reads:
  calibration needed or running is ``IDLE`` (``init`` calibrates, as the UR's releases its
  brakes), a calibrated arm is ``RUNNING``, a detected collision is a protective stop, a
  motor error a fault. External control is ready while fxcell holds it (``enable_control``)
  and the arm is calibrated and out of learning mode.
- **IO**: the IO panel's ``/niryo_robot_rpi/digital_io_state`` is folded into every state:
  pin ``DIn`` is bit n of ``digital_input_bits``, ``DOn`` bit n of ``digital_output_bits``
  (so the configuration's ``DI2``/``DO1`` name the Ned2's own pins, :data:`NED2_SIGNALS`);
  an output is set through the panel's ``set_digital_io`` service. Analog IO is not driven.
- **Moves**: a planned trajectory goes to the arm commander's action as a timed
  ``trajectory_msgs/JointTrajectory`` (``EXECUTE_FULL_TRAJ``), a point every
  :data:`POINT_SPACING` s with its velocities; the robot's controller interpolates between
  them. A stop is the commander's ``stop_command``; progress is read from the joint states.
  The TCP server (pyniryo's protocol) has no timed-trajectory command and answers one
  command at a time, so it serves only what the rosbridge lacks here (clearing a detected
  collision; the gripper's tool commands and position, :mod:`fxcell.link.ned2.gripper`).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from fxcell.errors import (
    CalibrationError,
    ConnectionLostError,
    FxcellError,
    RobotCommandError,
    RobotTimeoutError,
    UnsupportedCommandError,
)
from fxcell.geometry import Pose
from fxcell.link.contract import (
    ControllerInfo,
    Guard,
    LinkStatus,
    OutputGroup,
    StopReason,
    TrajectoryProgress,
    TrajectoryResult,
)
from fxcell.link.ned2 import (
    ARM_ACTION,
    EXECUTE_FULL_TRAJ,
    JOINT_NAMES,
    MOVE_ACTION,
    PREEMPTED,
    SUCCEEDED,
)
from fxcell.link.ned2.rosbridge import ActionGoal, RosbridgeClient
from fxcell.link.ned2.tcp import NiryoTcpClient
from fxcell.link.subscription import StateSubscription
from fxcell.protocol import ProgramState, RobotMode, RobotState, RuntimeState, SafetyMode
from fxcell.results import ProgramStatus
from fxcell.settling import REST_TIME, REST_VELOCITY

if TYPE_CHECKING:
    from fxcell.config import RobotConfig

__all__ = ["NED2_SIGNALS", "POINT_SPACING", "Ned2Calibration", "Ned2Link"]

log = logging.getLogger(__name__)

NED2_SIGNALS = frozenset({"DI1", "DI2", "DI3", "DI4", "DI5", "DO1", "DO2", "DO3", "DO4"})
"""The Ned2's digital pins fxcell drives: the IO panel's DI1-DI3, DI5 and DO1-DO3, and the
tool connector's DI4 and DO4 (ned_ros ``niryo_robot_rpi``)."""
IO_STATE_TOPIC = "/niryo_robot_rpi/digital_io_state"
SET_DIGITAL_IO = "/niryo_robot_rpi/set_digital_io"

POINT_SPACING = 0.05
"""Seconds between two points of a trajectory handed to the robot."""
CALIBRATION_TIMEOUT = 60.0
"""Seconds a calibration may take (a Ned2's runs each joint to its end stop)."""
ABORTED_STATUS, STOPPED_STATUS = -3, -4  # niryo_robot_msgs/CommandStatus
STALE_AFTER = 1.0
"""Seconds without a joint state after which the link to a Ned2 counts as down."""
RECONNECT_EVERY = 0.5
"""Seconds between two attempts to reach a Ned2 whose link is down."""
RECONNECT_SILENT = 2.0
"""Seconds a connection that is still open may stay silent before it is opened anew (a
network cut that no end of the connection has noticed yet)."""
ORPHAN_STOP_WITHIN = 5.0
"""Seconds a reconnected link gives the robot to stop a move left over from before."""
WATCH_PERIOD = 0.05
"""Seconds between two looks of the link's watch at the connection and the joint states."""


class Ned2Calibration:
    """A Ned2's kinematic calibration: the arm as Niryo publishes it (the robot corrects
    its own encoders when it calibrates; fxcell plans on the nominal model)."""

    checksum = hashlib.sha256(b"niryo ned2 nominal").hexdigest()[:8]
    is_nominal = True

    def summary(self) -> dict[str, object]:
        return {"kind": "ned2", "model": "nominal", "checksum": self.checksum}

    @classmethod
    def nominal(cls) -> Ned2Calibration:
        return cls()

    @classmethod
    def load(cls, path: str) -> Ned2Calibration:
        raise CalibrationError(
            f"robot.calibration: {path}: a Ned2 has no calibration file (it calibrates its "
            "encoders itself); use 'controller' or 'nominal'"
        )


def trajectory_message(samples: np.ndarray, period: float) -> dict[str, Any]:
    """A ``trajectory_msgs/JointTrajectory`` through ``samples`` (one every ``period``
    s): a point every :data:`POINT_SPACING` s and the last, velocities by central
    differences of the samples."""
    n = len(samples)
    step = max(1, round(POINT_SPACING / period))
    indices = [*range(0, n - 1, step), n - 1]
    velocities = np.gradient(samples, period, axis=0) if n > 1 else np.zeros_like(samples)
    velocities[0] = 0.0
    velocities[-1] = 0.0
    points = []
    for i in indices:
        t = i * period
        secs = math.floor(t)
        points.append(
            {
                "positions": [float(v) for v in samples[i]],
                "velocities": [float(v) for v in velocities[i]],
                "time_from_start": {"secs": secs, "nsecs": round((t - secs) * 1e9)},
            }
        )
    return {"joint_names": list(JOINT_NAMES), "points": points}


class Ned2Link:
    """The Cell's link to a Ned2 (see the module's docstring)."""

    def __init__(
        self,
        host: str | None,
        robot: RobotConfig,
        *,
        on_state: Callable[[RobotState], None],
        on_status: Callable[[LinkStatus, str], None],
        on_control: Callable[[bool, str], None],
        sample_period: float = 0.01,
        forward: Callable[[np.ndarray], Pose] | None = None,
    ) -> None:
        if host is None:
            raise ConnectionLostError("a Ned2 link needs the robot's address")
        self.host = host
        self.robot = robot
        self.sample_period = sample_period
        self._on_state, self._on_status, self._on_control = on_state, on_status, on_control
        self._forward = forward
        self._tcp = Pose.identity()  # the configured TCP in tool_link's frame (set_tool)
        self._bridge = RosbridgeClient(host)
        self._latest: RobotState | None = None
        self._subscriptions: set[StateSubscription] = set()
        self._messages = 0
        self._hardware: dict[str, Any] = {}
        self._learning = True
        self._collision = False
        self._io_bits = (0, 0)  # digital inputs, outputs: bit n is pin n
        self._control_wanted = False
        self._control = False
        self._up = False
        self._first = asyncio.Event()
        self._run: _Run | None = None
        self._heard = 0.0  # time.monotonic() of the newest joint state
        self._connected_at = 0.0  # ... and of the newest connection to the rosbridge
        self._resuming = False  # reconnected, a command left over not stopped yet
        self._quiet: tuple[float, float] | None = None  # robot time at rest: (since, newest)
        self._watcher: asyncio.Task[None] | None = None

    # ---------------------------------------------------------------- the contract's state

    @property
    def latest(self) -> RobotState | None:
        return self._latest if self._up else None

    @property
    def control_ready(self) -> bool:
        return self._control

    @property
    def up(self) -> bool:
        return self._up

    @property
    def messages_sent(self) -> int:
        return self._messages

    def subscribe(self, maxsize: int = 1024) -> StateSubscription:
        return StateSubscription(self._subscriptions, maxsize)

    async def start(self, wait: bool = True) -> None:
        self._on_status(LinkStatus.STARTING, f"connecting to the Ned2 at {self.host}")
        await self._connect(self._bridge)
        self._watcher = asyncio.create_task(self._watch(), name=f"Ned2 link {self.host}")
        if wait:
            try:
                async with asyncio.timeout(5.0):
                    await self._first.wait()
            except TimeoutError:
                await self.close()
                raise RobotTimeoutError(f"the Ned2 at {self.host} sent no joint state") from None

    async def _connect(self, bridge: RosbridgeClient) -> None:
        """Connect ``bridge`` and subscribe to the topics the state is made of."""
        await bridge.connect()
        self._connected_at = time.monotonic()
        await bridge.subscribe(
            "/niryo_robot_hardware_interface/hardware_status",
            "niryo_robot_msgs/HardwareStatus",
            self._on_hardware,
        )
        await bridge.subscribe(
            "/niryo_robot/learning_mode/state", "std_msgs/Bool", self._on_learning
        )
        await bridge.subscribe(
            "/niryo_robot_arm_commander/collision_detected", "std_msgs/Bool", self._on_collision
        )
        await bridge.subscribe(IO_STATE_TOPIC, "niryo_robot_rpi/DigitalIOState", self._on_io)
        await bridge.subscribe("/joint_states", "sensor_msgs/JointState", self._on_joints)
        self._messages += 5

    async def _watch(self) -> None:
        """Mark the link down when the rosbridge connection ends or the joint states stop
        (a robot switched off, a cable pulled, a stalled robot computer), and reach the
        robot again every :data:`RECONNECT_EVERY` s while it is down."""
        retry_at = 0.0
        ran = time.monotonic()
        while True:
            await asyncio.sleep(WATCH_PERIOD)
            now = time.monotonic()
            late, ran = now - ran > 4 * WATCH_PERIOD, now
            if late:
                # the loop was held up: the joint states that came meanwhile are read
                # before this task looks again, so its own lateness is not the robot's
                continue
            if self._up:
                if not self._bridge.connected:
                    self._lost(self._bridge.closed_because or "the rosbridge connection ended")
                elif now - self._heard > STALE_AFTER:
                    self._lost(f"no joint state for {1e3 * (now - self._heard):.0f} ms")
                retry_at = now + RECONNECT_EVERY
                continue
            if now < retry_at:
                continue
            retry_at = now + RECONNECT_EVERY
            silent = now - max(self._heard, self._connected_at)
            if self._bridge.connected and silent < RECONNECT_SILENT:
                continue  # connected: a robot that paused may publish again
            with contextlib.suppress(FxcellError):
                await self._reconnect()

    def _lost(self, reason: str) -> None:
        """The link is down: no state until the robot is reached again, and what the state
        was made of is forgotten (a robot back from a power loss needs calibrating)."""
        self._up = False
        self._first.clear()
        self._hardware, self._learning, self._collision = {}, True, False
        log.warning("robot link to %s down: %s", self.host, reason)
        self._update_control(reason)
        self._on_status(LinkStatus.DOWN, reason)

    async def _reconnect(self) -> None:
        old, self._bridge = self._bridge, RosbridgeClient(self.host)
        await old.close()
        self._resuming = True  # not up before a command left over from before is stopped
        self._quiet = None
        try:
            await self._connect(self._bridge)
            await self._stop_orphan()
        finally:
            self._resuming = False  # the next joint state brings the link up

    async def _stop_orphan(self) -> None:
        """Stop a move the robot still runs from before the link went down. The Ned2 holds
        a whole trajectory and finishes it without its client; the link that sent it has
        lost track of it, so it is stopped (no motion without the cell watching it), and
        the link is up again once the arm commander is idle and the joint states have shown
        the arm at rest for REST_TIME of the robot's time."""
        active = "/niryo_robot_arm_commander/is_active"
        answer = await self._bridge.call(active, within=ORPHAN_STOP_WITHIN)
        if not answer.get("value"):
            return
        log.warning(
            "the Ned2 at %s still runs a command sent before the link went down: stopping it",
            self.host,
        )
        self._messages += 1
        stop = "/niryo_robot_arm_commander/stop_command"
        await self._bridge.call(stop, within=ORPHAN_STOP_WITHIN)
        for _ in range(round(ORPHAN_STOP_WITHIN / WATCH_PERIOD)):  # a poll with a deadline
            quiet = self._quiet
            if (
                quiet is not None
                and quiet[1] - quiet[0] >= REST_TIME - 1e-9
                and not (await self._bridge.call(active, within=ORPHAN_STOP_WITHIN)).get("value")
            ):
                return
            await asyncio.sleep(WATCH_PERIOD)
        raise RobotTimeoutError(
            f"the Ned2 at {self.host} did not stop within {ORPHAN_STOP_WITHIN:g} s"
        )

    async def close(self) -> None:
        watcher, self._watcher = self._watcher, None
        if watcher is not None:
            watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await watcher
        await self._bridge.close()
        if self._up:
            self._up = False
            self._on_status(LinkStatus.CLOSED, "closed")

    # ---------------------------------------------------------------- the robot's topics

    def _on_hardware(self, msg: dict[str, Any]) -> None:
        self._hardware = msg

    def _on_learning(self, msg: dict[str, Any]) -> None:
        self._learning = bool(msg.get("data"))
        self._update_control("learning mode " + ("on" if self._learning else "off"))

    def _on_io(self, msg: dict[str, Any]) -> None:
        self._io_bits = (
            _pin_bits(msg.get("digital_inputs"), "DI"),
            _pin_bits(msg.get("digital_outputs"), "DO"),
        )

    def _on_collision(self, msg: dict[str, Any]) -> None:
        self._collision = bool(msg.get("data"))

    def _calibrated(self) -> bool:
        hw = self._hardware
        return (
            bool(hw) and not hw.get("calibration_needed") and not hw.get("calibration_in_progress")
        )

    def _update_control(self, why: str) -> None:
        ready = self._control_wanted and self._calibrated() and not self._learning
        if ready != self._control:
            self._control = ready
            self._on_control(ready, why)

    def _on_joints(self, msg: dict[str, Any]) -> None:
        names = msg.get("name")
        position = msg.get("position")
        if not isinstance(names, list) or not isinstance(position, list):
            return
        order = [names.index(j) for j in JOINT_NAMES if j in names]
        if len(order) != 6:
            return
        q = tuple(float(position[i]) for i in order)
        velocity = msg.get("velocity") or [0.0] * len(names)
        qd = tuple(float(velocity[i]) for i in order)
        stamp = (msg.get("header") or {}).get("stamp") or {}
        timestamp = float(stamp.get("secs", 0)) + float(stamp.get("nsecs", 0)) * 1e-9
        if self._resuming:  # reconnected, a leftover command not stopped yet: not up
            self._heard = time.monotonic()
            still = max(map(abs, qd)) < REST_VELOCITY
            since = self._quiet[0] if self._quiet is not None else timestamp
            self._quiet = (since, timestamp) if still else None
            return
        hw = self._hardware
        if not hw or hw.get("calibration_needed") or hw.get("calibration_in_progress"):
            mode = RobotMode.IDLE
        else:
            mode = RobotMode.RUNNING
        if self._collision:
            safety = SafetyMode.PROTECTIVE_STOP
        elif any(hw.get("hardware_errors") or []):
            safety = SafetyMode.FAULT
        else:
            safety = SafetyMode.NORMAL
        self._update_control("state")
        tcp = (
            (self._forward(np.asarray(q)) @ self._tcp).as_ur()
            if self._forward is not None
            else (0.0,) * 6
        )
        state = RobotState(
            timestamp=timestamp,
            robot_mode=mode,
            safety_mode=safety,
            runtime_state=RuntimeState.PLAYING if self._control else RuntimeState.STOPPED,
            target_q=q,
            actual_q=q,
            actual_qd=qd,
            target_tcp_pose=tuple(tcp),
            actual_tcp_pose=tuple(tcp),
            digital_input_bits=self._io_bits[0],
            digital_output_bits=self._io_bits[1],
            received_at=time.monotonic(),
        )
        self._latest = state
        self._heard = time.monotonic()
        for sub in list(self._subscriptions):
            sub.offer(state)
        if not self._up:
            self._up = True
            self._first.set()
            self._on_status(LinkStatus.UP, "joint states arrive")
        self._on_state(state)

    # ---------------------------------------------------------------- operations

    async def power(self, on: bool, within: float = 5.0) -> None:
        raise UnsupportedCommandError("power_on" if on else "power_off", "ned2")

    async def release_brakes(self, within: float = 5.0) -> None:
        """Calibrate the motors (a Ned2 boots needing it; nothing to do once calibrated)."""
        self._messages += 1
        await self._bridge.call(
            "/niryo_robot/joints_interface/calibrate_motors",
            {"value": 1},
            within=max(within, CALIBRATION_TIMEOUT),
        )

    async def remote_control(self, within: float = 5.0) -> bool:
        return True  # a Ned2 has no pendant switch: it always takes network commands

    async def unlock_protective_stop(self, within: float = 5.0) -> bool:
        """Clear the detected collision (on the TCP server: the rosbridge has no service
        for it)."""
        tcp = NiryoTcpClient(self.host)
        await tcp.connect(within)
        try:
            self._messages += 1
            await tcp.command("CLEAR_COLLISION_DETECTED", within=within)
        finally:
            await tcp.close()
        return True

    async def program_status(self, within: float = 5.0) -> ProgramStatus:
        state = ProgramState.PLAYING if self._control else ProgramState.STOPPED
        return ProgramStatus(state, "")

    async def shutdown(self, within: float = 5.0) -> None:
        raise UnsupportedCommandError("shutdown", "ned2")

    async def controller_info(self, within: float = 5.0) -> ControllerInfo:
        version = self._hardware.get("hardware_version")
        return ControllerInfo(robot_model=str(version) if version else "ned2")

    async def read_calibration(self) -> Ned2Calibration:
        return Ned2Calibration()

    async def enable_control(self, within: float) -> None:
        """Hold the arm (leave learning mode) and take commands."""
        self._control_wanted = True
        self._messages += 1
        await self._bridge.call(
            "/niryo_robot/learning_mode/activate", {"value": False}, within=within
        )
        try:
            async with asyncio.timeout(within):
                while not self._control:
                    await self._next_state()
        except TimeoutError:
            raise RobotTimeoutError(
                f"the Ned2 did not leave learning mode within {within:g} s"
            ) from None

    async def disable_control(self, within: float = 5.0) -> None:
        await self.servo_stop(within)
        self._control_wanted = False
        self._update_control("external control stopped")

    async def servo_stop(self, within: float = 5.0) -> bool:
        run = self._run
        if run is not None and not run.done:
            await run.stop(StopReason.SERVO_STOP)
        return True

    async def set_output(
        self, group: OutputGroup, index: int, value: float, within: float = 5.0
    ) -> bool:
        """Set digital output ``DO{index}`` through the IO panel's service (False for an
        output the Ned2 does not have; a refusal raises RobotCommandStatusError)."""
        name = f"DO{index}"
        if group != "standard" or name not in NED2_SIGNALS:
            return False
        self._messages += 1
        await self._bridge.call(
            SET_DIGITAL_IO, {"name": name, "value": value >= 0.5}, within=within
        )
        return True

    async def set_tool(
        self,
        tcp: tuple[float, ...],
        mass: float,
        cog: tuple[float, float, float],
        within: float = 5.0,
    ) -> bool:
        """The TCP the state's ``actual_tcp_pose`` reports (the Ned2 plans nothing itself and
        fxcell's own model carries the TCP; the robot's TCP setting is left alone, so its
        pendant and pyniryo's ``get_pose`` keep showing ``tool_link``). No payload setting:
        the Ned2 has none."""
        self._tcp = Pose.from_ur(tcp)
        return True

    async def teach_mode(self, on: bool, within: float = 5.0) -> bool:
        """Learning mode: the arm moved by hand."""
        self._messages += 1
        await self._bridge.call("/niryo_robot/learning_mode/activate", {"value": on}, within=within)
        return True

    async def execute_trajectory(
        self,
        samples: ArrayLike,
        *,
        lookahead_time: float = 0.1,
        gain: float = 300.0,
        guard: Guard | None = None,
    ) -> _Run:
        points = np.asarray(samples, dtype=float)
        if points.ndim != 2 or points.shape[1] != 6 or len(points) == 0:
            raise RobotCommandError(
                f"a Ned2 trajectory is (N, 6) joint positions, not {points.shape}"
            )
        goal = await self._bridge.send_goal(
            ARM_ACTION,
            MOVE_ACTION,
            {
                "cmd": {
                    "cmd_type": EXECUTE_FULL_TRAJ,
                    "trajectory": trajectory_message(points, self.sample_period),
                }
            },
        )
        self._messages += 1
        run = _Run(self, goal, len(points))
        self._run = run
        return run

    async def _next_state(self) -> RobotState:
        with self.subscribe(4) as states:
            return await states.next_within(1.0)


def _pin_bits(pins: object, prefix: str) -> int:
    """The levels of ``DigitalIO`` entries (``{name, value}``) named ``<prefix><n>`` as bits."""
    bits = 0
    for pin in pins if isinstance(pins, list) else []:
        name = pin.get("name") if isinstance(pin, dict) else None
        if isinstance(name, str) and name.startswith(prefix) and name[len(prefix) :].isdigit():
            n = int(name[len(prefix) :])
            if n < 16 and pin.get("value"):
                bits |= 1 << n
    return bits


class _Run:
    """A trajectory the Ned2's arm commander runs (a :class:`TrajectoryRun`)."""

    def __init__(self, link: Ned2Link, goal: ActionGoal, total: int) -> None:
        self.link = link
        self.goal = goal
        self.total = total
        self.started = time.monotonic()
        latest = link.latest  # progress counts from the robot's time when the goal went out
        self.start_stamp: float | None = latest.timestamp if latest is not None else None
        self._result: TrajectoryResult | None = None
        self._stop_reason: StopReason | None = None
        self._waiter = asyncio.ensure_future(self._wait())

    @property
    def done(self) -> bool:
        return self._result is not None

    @property
    def progress(self) -> TrajectoryProgress | None:
        state = self.link.latest
        if state is None:
            return None
        if self.start_stamp is None:
            self.start_stamp = state.timestamp
        index = round((state.timestamp - self.start_stamp) / self.link.sample_period)
        index = min(max(index, 0), self.total - 1)
        return TrajectoryProgress(
            index, self.total, state.actual_q, 0.0, time.time(), state.timestamp
        )

    async def replace_remaining(self, samples: ArrayLike, at_index: int | None = None) -> bool:
        """The robot's controller holds the whole trajectory, so nothing can be spliced:
        a braking profile asked for becomes the controller's own stop (its deceleration,
        not fxcell's profile); False once the trajectory has ended."""
        if self._result is not None:
            return False
        self._stop_reason = self._stop_reason or StopReason.STOP_REQUESTED
        await self.link._bridge.call("/niryo_robot_arm_commander/stop_command")
        return True

    async def stop(self, reason: StopReason = StopReason.STOP_REQUESTED) -> TrajectoryResult:
        if self._result is None:
            self._stop_reason = reason
            await self.link._bridge.call("/niryo_robot_arm_commander/stop_command")
        return await self.wait()

    async def wait(self) -> TrajectoryResult:
        return await asyncio.shield(self._waiter)

    async def next_progress(self) -> TrajectoryProgress | None:
        if self._result is not None:
            return None
        await self.link._next_state()
        return None if self._result is not None else self.progress

    async def _wait(self) -> TrajectoryResult:
        duration_from = time.monotonic()
        try:
            status, result = await self.link._bridge.goal_result(self.goal)
        except ConnectionLostError as exc:
            return self._end("failed", StopReason.LINK_LOST, str(exc), duration_from)
        code = result.get("status")
        message = str(result.get("message", ""))
        if status == SUCCEEDED:
            return self._end("completed", StopReason.NONE, "", duration_from)
        if status == PREEMPTED or code == STOPPED_STATUS:
            reason = self._stop_reason or StopReason.STOP_REQUESTED
            return self._end("stopped", reason, message, duration_from)
        if code == ABORTED_STATUS:
            return self._end("failed", StopReason.PROTECTIVE_STOP, message, duration_from)
        return self._end(
            "failed", StopReason.LINK_ERROR, f"{message} (status {code})", duration_from
        )

    def _end(self, status: Any, reason: StopReason, detail: str, since: float) -> TrajectoryResult:
        state = self.link.latest
        progress = self.progress
        self._result = TrajectoryResult(
            status,
            reason,
            progress.index if progress is not None else 0,
            self.total,
            state.actual_q if state is not None else None,
            time.monotonic() - since,
            detail,
        )
        return self._result
