"""The simulated Ned2's rosbridge: the WebSocket (port 9090) on which Niryo's ROS clients
(pyniryo2 through roslibpy) reach the robot's topics, services and actions.

It speaks the rosbridge v2 protocol (JSON objects with an ``op``):

- **topics** the robot publishes (joint states, the tool pose, hardware status, learning
  mode, collision detection, velocity scaling, whether a move is active, the tool's id,
  the digital IO's levels at the IO panel's 10 Hz):
  a subscription gets the latest message at once, then one every period (or every
  ``throttle_rate`` ms if slower);
- **services** (stop, learning mode, calibration, velocity scaling, the tool, the IO
  panel's digital pins, rosapi's parameters), each call served concurrently so that
  ``stop_command`` reaches a move that another connection (the TCP server or an action)
  is running; a service nobody offers or arguments of the wrong type are answered
  ``result: false`` with a status message;
- **actions** over topics as ROS 1's actionlib does it (``goal``, ``cancel``, ``status``,
  ``result``): the arm commander's ``robot_action`` (moves by joints, pose and linear
  pose, and a timed ``trajectory_msgs/JointTrajectory``: ``EXECUTE_FULL_TRAJ``) and the
  tools commander's ``action_server`` (Gripper 1 open and close).

Names are canonical as ROS makes them (``/a//b/`` is ``/a/b``). Advertising and
publishing are accepted (pyniryo2 publishes a heartbeat on ``/ping_pyniryo``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import re
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from fxcell.geometry import matrix_to_quaternion
from fxcell.link.ned2 import (
    ABORTED,
    ACTIVE,
    ARM_ACTION,
    EXECUTE_FULL_TRAJ,
    JOINT_NAMES,
    PENDING,
    PREEMPTED,
    REJECTED,
    SUCCEEDED,
)
from fxcell.motion import ned2
from fxcell.sim.ned2 import ROSBRIDGE_PORT
from fxcell.sim.ned2.robot import (
    INVALID_PARAMETERS,
    MOTOR_NAMES,
    STOPPED,
    TOOLS,
    Ned2Robot,
    RobotError,
)

log = logging.getLogger(__name__)

SUCCESS = 1  # niryo_robot_msgs/CommandStatus.SUCCESS
DIGITAL_IO_PANEL_ERROR = -114
PARAMETERS: dict[str, Any] = {
    "/niryo_robot/hardware_version": "ned2",
    "/niryo_robot/simulation_mode": True,
}
TOOL_ACTION = "/niryo_robot_tools_commander/action_server"
STATUS_PERIOD = 0.2  # s: actionlib servers publish their goals' status at 5 Hz

# niryo_robot_arm_commander ArmMoveCommand.cmd_type, niryo_robot_tools_commander ToolCommand
MOVE_JOINTS, MOVE_POSE, MOVE_LINEAR_POSE = 0, 1, 5
OPEN_GRIPPER, CLOSE_GRIPPER = 1, 2


def canonical(name: str) -> str:
    """A ROS graph name as ROS resolves it: no repeated or trailing slashes."""
    name = re.sub("/+", "/", name)
    return name[:-1] if len(name) > 1 and name.endswith("/") else name


def _header(seq: int) -> dict[str, Any]:
    now = time.time()
    secs = math.floor(now)
    return {"seq": seq, "stamp": {"secs": secs, "nsecs": int((now - secs) * 1e9)}, "frame_id": ""}


class FieldError(Exception):
    """Arguments or a goal that do not fit the message type (rosbridge's
    FieldTypeMismatchException)."""


def _field(args: dict[str, Any], name: str, kind: type, where: str) -> Any:
    value = args.get(name)
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
        raise FieldError(f"{where}: expected a {kind.__name__} for field {name!r}, got {value!r}")
    return value


# ------------------------------------------------------------------------ topics


@dataclass
class _Stream:
    """One client's subscription to one topic: its ids and the task publishing it."""

    ids: set[str | None] = field(default_factory=set)
    task: asyncio.Task[None] | None = None
    previous: tuple[float, np.ndarray] | None = None  # joint states: time and joints


@dataclass(frozen=True)
class Topic:
    """A topic the robot publishes: its message type, period (s) and message."""

    type: str
    period: float
    message: Callable[[_Stream, int], dict[str, Any]]


def _joint_states(robot: Ned2Robot, stream: _Stream, seq: int) -> dict[str, Any]:
    now = time.monotonic()
    q = robot.joints.copy()
    velocity = [0.0] * 6
    if stream.previous is not None and robot.moving:
        t0, q0 = stream.previous
        dt = (now - t0) / robot.time_scale  # robot seconds
        if dt > 0:
            velocity = [float(v) for v in (q - q0) / dt]
    stream.previous = (now, q)
    return {
        "header": _header(seq),
        "name": list(JOINT_NAMES),
        "position": [float(v) for v in q],
        "velocity": velocity,
        "effort": [0.0] * 6,
    }


def _robot_state(robot: Ned2Robot) -> dict[str, Any]:
    t = ned2.forward(robot.joints)
    x, y, z, roll, pitch, yaw = ned2.matrix_to_pose(t)
    qx, qy, qz, qw = matrix_to_quaternion(t[:3, :3])
    zero = {"x": 0.0, "y": 0.0, "z": 0.0}
    return {
        "position": {"x": x, "y": y, "z": z},
        "rpy": {"roll": roll, "pitch": pitch, "yaw": yaw},
        "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
        "twist": {"linear": zero, "angular": zero},
        "tcp_speed": 0.0,
    }


def _hardware_status(robot: Ned2Robot, seq: int) -> dict[str, Any]:
    row = robot.hardware_status()
    errors = [int(v) for v in row[10]]
    return {
        "header": _header(seq),
        "rpi_temperature": row[0],
        "hardware_version": row[1],
        "connection_up": row[2],
        "error_message": row[3].strip("'"),
        "calibration_needed": row[4],
        "calibration_in_progress": row[5],
        "motor_names": list(MOTOR_NAMES),
        "motor_types": row[7],
        "temperatures": row[8],
        "voltages": row[9],
        "hardware_errors": errors,
        "hardware_errors_message": [
            f"overload on {name}" if code else ""
            for name, code in zip(MOTOR_NAMES, errors, strict=True)
        ],
    }


def _digital_io_state(robot: Ned2Robot) -> dict[str, Any]:
    """``niryo_robot_rpi/DigitalIOState``: each pin's name and level, inputs and outputs."""
    return {
        "digital_inputs": [{"name": n, "value": v} for n, v in sorted(robot.digital_in.items())],
        "digital_outputs": [{"name": n, "value": v} for n, v in sorted(robot.digital_out.items())],
    }


# ------------------------------------------------------------------------ services

Service = Callable[[Ned2Robot, dict[str, Any]], Awaitable[dict[str, Any]]]


async def _stop_command(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    robot.abort(STOPPED, "Command has been stopped")
    robot.log.append("stop command")
    return {"status": SUCCESS, "message": "Command stopped"}


async def _is_active(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    return {"value": robot.moving}


async def _learning_mode(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    on = _field(args, "value", bool, "learning_mode/activate")
    robot.set_learning_mode(on)
    return {"status": SUCCESS, "message": f"Learning mode {'activated' if on else 'deactivated'}"}


async def _calibrate(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    mode = _field(args, "value", int, "calibrate_motors")
    if mode not in (1, 2):  # AUTO, MANUAL
        return {"status": INVALID_PARAMETERS, "message": f"Unknown calibration mode {mode}"}
    try:
        await robot.calibrate()  # the Ned2 calibrates itself in either mode
    except RobotError as exc:
        return {"status": exc.code, "message": exc.message}
    return {"status": SUCCESS, "message": "Calibration done"}


async def _request_new_calibration(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    if robot.moving or robot.calibrating:
        return {"status": STOPPED, "message": "The robot is busy: no new calibration now"}
    robot.calibrated = False
    robot.log.append("new calibration requested")
    return {"status": SUCCESS, "message": "New calibration requested"}


async def _velocity_scaling(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    value = _field(args, "value", int, "set_max_velocity_scaling_factor")
    if not 1 <= value <= 100:
        return {"status": INVALID_PARAMETERS, "message": "The value must be between 1 and 100"}
    robot.velocity_percent = float(value)
    return {"status": SUCCESS, "message": f"Max velocity scaling factor set to {value} %"}


async def _update_tool(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    if robot.tool == "NONE":
        return {"status": -253, "message": "No tool connected"}
    return {"status": SUCCESS, "message": f"Tool {robot.tool} ({TOOLS[robot.tool]}) found"}


async def _set_digital_io(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    """``niryo_robot_rpi/SetDigitalIO`` as the robot's IO panel answers it: only a digital
    output can be set."""
    name = _field(args, "name", str, "set_digital_io")
    value = _field(args, "value", bool, "set_digital_io")
    if name in robot.digital_out:
        robot.digital_out[name] = value
        return {"status": SUCCESS, "message": f"Successfully set value for {name}"}
    if name in robot.digital_in or name in robot.analog_in or name in robot.analog_out:
        return {"status": DIGITAL_IO_PANEL_ERROR, "message": f"{name} is not a digital output."}
    return {"status": DIGITAL_IO_PANEL_ERROR, "message": f"No IO found for {name}"}


async def _get_digital_io(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    name = _field(args, "name", str, "get_digital_io")
    levels = {**robot.digital_in, **robot.digital_out}
    if name not in levels:
        return {"status": DIGITAL_IO_PANEL_ERROR, "message": f"No GPIO found for {name}"}
    return {"status": SUCCESS, "message": "OK", "value": levels[name]}


async def _get_param(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    # rosapi: the value as JSON, else the request's default (JSON) or null
    name = canonical(_field(args, "name", str, "rosapi/get_param"))
    if name in PARAMETERS:
        return {"value": json.dumps(PARAMETERS[name])}
    default = args.get("default", "")
    if isinstance(default, str) and default:
        try:
            return {"value": json.dumps(json.loads(default))}
        except ValueError:
            return {"value": json.dumps(default)}
    return {"value": json.dumps(None)}


async def _get_param_names(robot: Ned2Robot, args: dict[str, Any]) -> dict[str, Any]:
    return {"names": sorted(PARAMETERS)}


SERVICES: dict[str, Service] = {
    "/niryo_robot_arm_commander/stop_command": _stop_command,
    "/niryo_robot_arm_commander/is_active": _is_active,
    "/niryo_robot/learning_mode/activate": _learning_mode,
    "/niryo_robot/joints_interface/calibrate_motors": _calibrate,
    "/niryo_robot/joints_interface/request_new_calibration": _request_new_calibration,
    "/niryo_robot_arm_commander/set_max_velocity_scaling_factor": _velocity_scaling,
    "/niryo_robot_tools_commander/update_tool": _update_tool,
    "/niryo_robot_rpi/set_digital_io": _set_digital_io,
    "/niryo_robot_rpi/get_digital_io": _get_digital_io,
    "/rosapi/get_param": _get_param,
    "/rosapi/get_param_names": _get_param_names,
}
"""The services the simulated robot offers on its rosbridge."""


# ------------------------------------------------------------------------ actions


async def _arm_goal(robot: Ned2Robot, cmd: dict[str, Any]) -> None:
    kind = _field(cmd, "cmd_type", int, "robot_action")
    if kind == MOVE_JOINTS:
        joints = cmd.get("joints")
        if not isinstance(joints, list) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in joints
        ):
            raise FieldError(f"robot_action: expected a list of numbers for 'joints', got {joints}")
        await robot.move_joints(robot.check_joints([float(v) for v in joints]))
        return
    if kind in (MOVE_POSE, MOVE_LINEAR_POSE):
        position = cmd.get("position")
        rpy = cmd.get("rpy")
        if not isinstance(position, dict) or not isinstance(rpy, dict):
            raise FieldError("robot_action: a pose needs 'position' and 'rpy'")
        pose = [_field(position, k, float, "robot_action") for k in ("x", "y", "z")]
        pose += [_field(rpy, k, float, "robot_action") for k in ("roll", "pitch", "yaw")]
        if kind == MOVE_LINEAR_POSE:
            robot.solve(pose)  # refuse an unreachable goal before moving
            await robot.move_linear(pose)
        else:
            await robot.move_joints(robot.solve(pose))
        return
    if kind == EXECUTE_FULL_TRAJ:
        times, positions, velocities = _joint_trajectory(cmd.get("trajectory"))
        await robot.follow_trajectory(times, positions, velocities)
        return
    raise RobotError(INVALID_PARAMETERS, f"Command type {kind} is not modelled by the simulator")


def _numbers(value: Any, n: int, where: str) -> list[float]:
    if not isinstance(value, list) or len(value) != n:
        raise FieldError(f"{where}: expected {n} numbers, got {value!r:.80}")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise FieldError(f"{where}: expected {n} numbers, got {value!r:.80}")
    return [float(v) for v in value]


def _joint_trajectory(message: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times, positions and velocities (points x joints in the arm's order) of a
    ``trajectory_msgs/JointTrajectory``; its points without velocities get zeros."""
    if not isinstance(message, dict) or not isinstance(message.get("points"), list):
        raise FieldError("robot_action: EXECUTE_FULL_TRAJ needs a trajectory with points")
    names = message.get("joint_names")
    if not isinstance(names, list) or sorted(map(str, names)) != sorted(JOINT_NAMES):
        raise FieldError(f"robot_action: the trajectory's joint_names must be {list(JOINT_NAMES)}")
    order = [names.index(j) for j in JOINT_NAMES]
    times, positions, velocities = [], [], []
    for point in message["points"]:
        if not isinstance(point, dict):
            raise FieldError("robot_action: a trajectory point must be an object")
        q = _numbers(point.get("positions"), 6, "positions")
        v = _numbers(point.get("velocities") or [0.0] * 6, 6, "velocities")
        stamp = point.get("time_from_start")
        if not isinstance(stamp, dict):
            raise FieldError("robot_action: a point needs time_from_start {secs, nsecs}")
        secs = _field(stamp, "secs", int, "time_from_start")
        nsecs = _field(stamp, "nsecs", int, "time_from_start")
        times.append(secs + nsecs * 1e-9)
        positions.append([q[i] for i in order])
        velocities.append([v[i] for i in order])
    return (
        np.array(times, dtype=float),
        np.array(positions, dtype=float).reshape(-1, 6),
        np.array(velocities, dtype=float).reshape(-1, 6),
    )


async def _tool_goal(robot: Ned2Robot, cmd: dict[str, Any]) -> None:
    kind = _field(cmd, "cmd_type", int, "tool action")
    tool_id = _field(cmd, "tool_id", int, "tool action")
    if tool_id != TOOLS.get(robot.tool):
        raise RobotError(-251, f"Tool {tool_id} is not the connected tool")
    if kind == OPEN_GRIPPER:
        await robot.open_gripper()
    elif kind == CLOSE_GRIPPER:
        await robot.close_gripper()
    else:
        raise RobotError(INVALID_PARAMETERS, f"Tool command {kind} is not modelled")


@dataclass
class _Goal:
    id: str
    stamp: dict[str, Any]
    status: int = PENDING
    text: str = ""
    task: asyncio.Task[None] | None = None

    def message(self) -> dict[str, Any]:
        return {
            "goal_id": {"stamp": self.stamp, "id": self.id},
            "status": self.status,
            "text": self.text,
        }


@dataclass
class ActionServer:
    """An actionlib server: goals run one at a time, their status published at 5 Hz."""

    name: str
    action_type: str  # e.g. niryo_robot_arm_commander/RobotMove
    execute: Callable[[Ned2Robot, dict[str, Any]], Awaitable[None]]
    goals: dict[str, _Goal] = field(default_factory=dict)

    def status_array(self, seq: int) -> dict[str, Any]:
        return {"header": _header(seq), "status_list": [g.message() for g in self.goals.values()]}


# ------------------------------------------------------------------------ the bridge


@dataclass(eq=False)
class _Client:
    ws: ServerConnection
    streams: dict[str, _Stream] = field(default_factory=dict)
    advertised: set[str] = field(default_factory=set)
    tasks: set[asyncio.Task[None]] = field(default_factory=set)


class Rosbridge:
    """The rosbridge WebSocket of one simulated robot (any number of clients)."""

    def __init__(self, robot: Ned2Robot) -> None:
        self.robot = robot
        self._server: Server | None = None
        self._clients: set[_Client] = set()
        self._tasks: set[asyncio.Task[Any]] = set()
        self.stalled_until = 0.0
        """The event loop's time until which the topics publish nothing (a stalled robot)."""
        self.actions = {
            ARM_ACTION: ActionServer(ARM_ACTION, "niryo_robot_arm_commander/RobotMove", _arm_goal),
            TOOL_ACTION: ActionServer(TOOL_ACTION, "niryo_robot_tools_commander/Tool", _tool_goal),
        }
        r = robot
        self.topics: dict[str, Topic] = {
            "/joint_states": Topic(
                "sensor_msgs/JointState", 0.02, lambda s, n: _joint_states(r, s, n)
            ),
            "/niryo_robot/robot_state": Topic(
                "niryo_robot_msgs/RobotState", 0.05, lambda s, n: _robot_state(r)
            ),
            "/niryo_robot_hardware_interface/hardware_status": Topic(
                "niryo_robot_msgs/HardwareStatus", 0.1, lambda s, n: _hardware_status(r, n)
            ),
            "/niryo_robot/learning_mode/state": Topic(
                "std_msgs/Bool", 0.1, lambda s, n: {"data": r.learning_mode}
            ),
            "/niryo_robot_arm_commander/collision_detected": Topic(
                "std_msgs/Bool", 0.1, lambda s, n: {"data": r.collision_detected}
            ),
            "/niryo_robot_arm_commander/is_active": Topic(
                "std_msgs/Bool", 0.1, lambda s, n: {"data": r.moving}
            ),
            "/niryo_robot/max_velocity_scaling_factor": Topic(
                "std_msgs/Int32", 0.1, lambda s, n: {"data": round(r.velocity_percent)}
            ),
            "/niryo_robot_rpi/digital_io_state": Topic(
                "niryo_robot_rpi/DigitalIOState", 0.1, lambda s, n: _digital_io_state(r)
            ),
            "/niryo_robot_tools_commander/current_id": Topic(
                "std_msgs/Int32", 0.1, lambda s, n: {"data": TOOLS[r.tool]}
            ),
        }
        for server in self.actions.values():
            self.topics[server.name + "/status"] = Topic(
                "actionlib_msgs/GoalStatusArray", STATUS_PERIOD, self._status_of(server)
            )

    @staticmethod
    def _status_of(server: ActionServer) -> Callable[[_Stream, int], dict[str, Any]]:
        return lambda stream, seq: server.status_array(seq)

    async def start(self, host: str, port: int = ROSBRIDGE_PORT) -> None:
        self._server = await serve(self._serve, host, port, compression=None)

    async def close(self) -> None:
        """Stop listening, end every goal and close every client (the robot went dark or
        the simulator stops)."""
        server, self._server = self._server, None
        if server is not None:
            server.close()
            await server.wait_closed()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    def cut(self) -> None:
        """The robot's network drops: every client's connection fails (no closing
        handshake); the server goes on listening."""
        for client in list(self._clients):
            client.ws.transport.abort()

    async def drop(self) -> None:
        """The robot went dark: stop listening and cut every connection, with no closing
        handshake (the clients see their connection fail)."""
        server, self._server = self._server, None
        if server is not None:
            server.close(close_connections=False)
        for client in list(self._clients):
            client.ws.transport.abort()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if server is not None:
            await server.wait_closed()

    def _spawn(self, coro: Awaitable[None], client: _Client | None = None) -> asyncio.Task[None]:
        task: asyncio.Task[None] = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        if client is not None:
            client.tasks.add(task)
            task.add_done_callback(client.tasks.discard)
        return task

    # ---------------------------------------------------------------- one client

    async def _serve(self, ws: ServerConnection) -> None:
        client = _Client(ws)
        self._clients.add(client)
        try:
            async for raw in ws:
                await self._receive(client, raw)
        except ConnectionClosed:
            pass
        finally:
            self._clients.discard(client)
            for task in list(client.tasks):
                task.cancel()
            await asyncio.gather(*client.tasks, return_exceptions=True)

    async def _receive(self, client: _Client, raw: str | bytes) -> None:
        try:
            message = json.loads(raw)
        except ValueError:
            await self._status(client, f"Unable to load the message {raw!r:.80}")
            return
        if not isinstance(message, dict) or not isinstance(message.get("op"), str):
            await self._status(client, "Received a message without an op")
            return
        op = message["op"]
        cid = message.get("id")
        topic = message.get("topic")
        name = canonical(topic) if isinstance(topic, str) else None
        if op == "subscribe":
            await self._subscribe(client, topic if isinstance(topic, str) else None, message)
        elif op == "unsubscribe":
            self._unsubscribe(client, topic if isinstance(topic, str) else None, cid)
        elif op == "advertise" and name is not None:
            client.advertised.add(name)
        elif op == "unadvertise" and name is not None:
            client.advertised.discard(name)
        elif op == "publish":
            if name is None or (name not in client.advertised and "type" not in message):
                await self._status(
                    client,
                    f"publish: Cannot infer topic type for topic {topic} as it is not yet "
                    "advertised",
                    cid,
                )
                return
            await self._published(client, name, message.get("msg"))
        elif op == "call_service":
            # served concurrently: a stop must not wait behind a calibration
            self._spawn(self._call(client, message), client)
        elif op not in ("advertise", "unadvertise"):
            await self._status(client, f"Unknown operation: {op}", cid)

    @staticmethod
    async def _send(client: _Client, message: dict[str, Any]) -> None:
        with contextlib.suppress(ConnectionClosed):
            await client.ws.send(json.dumps(message))

    async def _status(self, client: _Client, msg: str, cid: object = None) -> None:
        status: dict[str, Any] = {"op": "status", "level": "error", "msg": msg}
        if cid is not None:
            status["id"] = cid
        await self._send(client, status)

    # ---------------------------------------------------------------- topics

    async def _subscribe(self, client: _Client, given: str | None, message: dict[str, Any]) -> None:
        """Subscribe ``client`` to the topic it named ``given``: messages go out under that
        name, as rosbridge sends them (the client matches them by it)."""
        cid = message.get("id")
        if given is None:
            await self._status(client, "subscribe: the message has no topic", cid)
            return
        name = canonical(given)
        wanted = message.get("type")
        topic = self.topics.get(name)
        if topic is None:
            if name.rsplit("/", 1)[-1] in ("result", "feedback") and name.rsplit("/", 1)[0] in (
                self.actions
            ):
                # an action's result and feedback: sent to the goal's client when it ends
                client.streams.setdefault(given, _Stream()).ids.add(
                    cid if isinstance(cid, str) else None
                )
            elif not isinstance(wanted, str):
                await self._status(
                    client,
                    f"subscribe: Cannot infer topic type for topic {name} as it is not yet "
                    "advertised",
                    cid,
                )
            return  # a typed subscription to a topic nobody publishes: nothing comes
        if isinstance(wanted, str) and wanted != topic.type:
            await self._status(
                client, f"subscribe: {name} is of type {topic.type}, not {wanted}", cid
            )
            return
        throttle = message.get("throttle_rate", 0)
        period = topic.period
        if isinstance(throttle, int) and not isinstance(throttle, bool) and throttle > 0:
            period = max(period, throttle / 1000.0)
        stream = client.streams.setdefault(given, _Stream())
        stream.ids.add(cid if isinstance(cid, str) else None)
        if stream.task is None:
            stream.task = self._spawn(self._publish(client, given, topic, stream, period), client)

    @staticmethod
    def _unsubscribe(client: _Client, name: str | None, cid: object) -> None:
        stream = client.streams.get(name) if name is not None else None
        if stream is None or name is None:
            return
        if isinstance(cid, str) and cid in stream.ids:
            stream.ids.discard(cid)
        else:
            stream.ids.clear()
        if not stream.ids:
            del client.streams[name]
            if stream.task is not None:
                stream.task.cancel()

    async def _publish(
        self, client: _Client, name: str, topic: Topic, stream: _Stream, period: float
    ) -> None:
        seq = 0
        loop = asyncio.get_running_loop()
        while True:
            if loop.time() < self.stalled_until:
                await asyncio.sleep(self.stalled_until - loop.time())
            message = topic.message(stream, seq)
            try:
                await client.ws.send(json.dumps({"op": "publish", "topic": name, "msg": message}))
            except ConnectionClosed:
                return
            seq += 1
            await asyncio.sleep(period)

    async def _published(self, client: _Client, name: str, msg: Any) -> None:
        """A client's message on a topic: goals and cancellations reach their action."""
        base, _, leaf = name.rpartition("/")
        server = self.actions.get(base)
        if server is None or not isinstance(msg, dict):
            return  # nobody in the simulated robot listens to it
        if leaf == "goal":
            await self._goal(client, server, msg)
        elif leaf == "cancel":
            wanted = msg.get("id", "")  # empty: every goal
            for goal in server.goals.values():
                if wanted not in ("", goal.id):
                    continue
                if goal.status == ACTIVE:
                    self.robot.abort(STOPPED, "Command has been stopped")
                elif goal.status == PENDING and goal.task is not None:
                    goal.task.cancel()

    # ---------------------------------------------------------------- actions

    async def _goal(self, client: _Client, server: ActionServer, msg: dict[str, Any]) -> None:
        goal_id = msg.get("goal_id")
        body = msg.get("goal")
        if not isinstance(goal_id, dict) or not isinstance(goal_id.get("id"), str):
            await self._status(client, f"{server.name}/goal: the goal has no goal_id.id")
            return
        goal = _Goal(goal_id["id"], goal_id.get("stamp") or {"secs": 0, "nsecs": 0})
        server.goals[goal.id] = goal
        finished = [g.id for g in server.goals.values() if g.status not in (PENDING, ACTIVE)]
        for old in finished[: max(0, len(server.goals) - 10)]:  # actionlib forgets old goals
            del server.goals[old]
        goal.task = self._spawn(self._run(client, server, goal, body))

    async def _run(self, client: _Client, server: ActionServer, goal: _Goal, body: Any) -> None:
        result = {"status": SUCCESS, "message": "Command has been successfully processed"}
        try:
            if not isinstance(body, dict) or not isinstance(body.get("cmd"), dict):
                raise FieldError(f"{server.name}: the goal needs a 'cmd'")
            if any(g.status == ACTIVE for g in server.goals.values()):
                goal.status, goal.text = REJECTED, "A goal is still active"
                result = {"status": -221, "message": goal.text}
            else:
                goal.status = ACTIVE
                await server.execute(self.robot, body["cmd"])
                goal.status = SUCCEEDED
        except FieldError as exc:
            goal.status, goal.text = REJECTED, str(exc)
            result = {"status": INVALID_PARAMETERS, "message": str(exc)}
        except RobotError as exc:
            goal.status = PREEMPTED if exc.code == STOPPED else ABORTED
            goal.text = exc.message
            result = {"status": exc.code, "message": exc.message}
        except asyncio.CancelledError:
            goal.status, goal.text = PREEMPTED, "Command has been stopped"
            result = {"status": STOPPED, "message": goal.text}
        leaf = server.name + "/result"
        for given in [t for t in client.streams if canonical(t) == leaf]:
            await self._send(
                client,
                {
                    "op": "publish",
                    "topic": given,
                    "msg": {"header": _header(0), "status": goal.message(), "result": result},
                },
            )

    # ---------------------------------------------------------------- services

    async def _call(self, client: _Client, message: dict[str, Any]) -> None:
        raw = message.get("service")
        name = canonical(raw) if isinstance(raw, str) else raw
        cid = message.get("id")
        args = message.get("args", {})
        if args is None or args == []:
            args = {}
        handler = SERVICES.get(name) if isinstance(name, str) else None
        answer: dict[str, Any] = {"op": "service_response", "service": raw}
        if cid is not None:
            answer["id"] = cid
        if handler is None:
            error = f"Service {raw} does not exist"
            await self._status(client, f"call_service InvalidServiceException: {error}", cid)
            await self._send(client, {**answer, "values": error, "result": False})
            return
        try:
            if not isinstance(args, dict):
                raise FieldError(f"{raw}: the arguments must be an object, got {args!r}")
            values = await handler(self.robot, args)
        except FieldError as exc:
            await self._status(client, f"call_service FieldTypeMismatchException: {exc}", cid)
            await self._send(client, {**answer, "values": str(exc), "result": False})
            return
        await self._send(client, {**answer, "values": values, "result": True})
