"""Niryo's TCP protocol (port 40001) as the robot's ``niryo_robot_user_interface`` serves
it and pyniryo 1.2.5 speaks it.

A frame: a 2-byte native-order length (``struct '@H'``), then that many bytes of JSON.
A request is ``{"command": NAME, "param_list": [...]}``; enums travel by name, booleans
as ``"TRUE"``/``"FALSE"``, None as ``"None"``. The answer is
``{"status": "OK", "command", "list_ret_param", "payload_size"}`` (booleans at the top
level of ``list_ret_param`` as ``"True"``/``"False"``, enums by name) followed by
``payload_size`` raw bytes, or the same with ``"status": "KO"`` and a ``"message"``.

How the robot's server fails, reproduced here:

- bytes that are not JSON (or not UTF-8): it drops the connection without an answer;
- not a JSON object, or keys other than ``command``/``param_list``: KO with an empty
  command name ("Cannot interpret command of incorrect type" / "Incorrect command
  format: ...");
- an unknown command: KO "Unknown command" (pyniryo's handshake tolerates it);
- a wrong number of parameters or a bad parameter: KO naming the command, with the
  interpreter's message;
- a failure on the robot's side: KO "An error occured while executing the last
  command : Error Code : CODE\\nMessage : TEXT" (the robot's spelling).

Until a ``HANDSHAKE`` arrived, every KO message carries the server's note about it.
"""

from __future__ import annotations

import json
import logging
import math
import struct
from collections.abc import Awaitable, Callable
from enum import Enum
from typing import Any

from fxcell.geometry import matrix_to_quaternion
from fxcell.motion import ned2
from fxcell.sim.ned2.robot import (
    ANALOG_INPUTS,
    ANALOG_OUTPUTS,
    DIGITAL_INPUTS,
    DIGITAL_OUTPUTS,
    GRIPPER_STEPS,
    INVALID_PARAMETERS,
    TOOLS,
    Ned2Robot,
    RobotError,
)

log = logging.getLogger(__name__)

LENGTH = struct.Struct("@H")
SERVER_VERSION = "5.6.1"
MINIMUM_CLIENT_VERSION = "1.2.0"
HANDSHAKE_NOTE = (
    "\nNo handshake has been made between the client and the server. "
    "This error could be the cause of an incompatible versions of the server and the client"
)
BOOLEANS = {"TRUE": True, "FALSE": False}
# pyniryo 1.2.5's Command enum: the names a robot of its generation knows
PYNIRYO_COMMANDS = frozenset(
    [
        "CALIBRATE",
        "SET_LEARNING_MODE",
        "GET_LEARNING_MODE",
        "SET_ARM_MAX_VELOCITY",
        "SET_JOG_CONTROL",
        "GET_COLLISION_DETECTED",
        "CLEAR_COLLISION_DETECTED",
        "HANDSHAKE",
        "GET_JOINTS",
        "GET_POSE",
        "GET_POSE_QUAT",
        "GET_HOME_POSE",
        "SET_HOME_POSE",
        "RESET_HOME_POSE",
        "MOVE_JOINTS",
        "MOVE_POSE",
        "SHIFT_POSE",
        "MOVE_LINEAR_POSE",
        "SHIFT_LINEAR_POSE",
        "JOG_JOINTS",
        "JOG_POSE",
        "FORWARD_KINEMATICS",
        "INVERSE_KINEMATICS",
        "MOVE",
        "JOG",
        "MOVE_TO_HOME_POSE",
        "GET_POSE_SAVED",
        "SAVE_POSE",
        "DELETE_POSE",
        "GET_SAVED_POSE_LIST",
        "PICK_FROM_POSE",
        "PLACE_FROM_POSE",
        "PICK_AND_PLACE",
        "PICK",
        "PLACE",
        "GET_TRAJECTORY_SAVED",
        "GET_SAVED_TRAJECTORY_LIST",
        "EXECUTE_REGISTERED_TRAJECTORY",
        "EXECUTE_TRAJECTORY_FROM_POSES",
        "EXECUTE_TRAJECTORY_FROM_POSES_AND_JOINTS",
        "SAVE_TRAJECTORY",
        "SAVE_LAST_LEARNED_TRAJECTORY",
        "UPDATE_TRAJECTORY_INFOS",
        "DELETE_TRAJECTORY",
        "CLEAN_TRAJECTORY_MEMORY",
        "EXECUTE_TRAJECTORY",
        "GET_SAVED_DYNAMIC_FRAME_LIST",
        "GET_SAVED_DYNAMIC_FRAME",
        "SAVE_DYNAMIC_FRAME_FROM_POSES",
        "SAVE_DYNAMIC_FRAME_FROM_POINTS",
        "EDIT_DYNAMIC_FRAME",
        "DELETE_DYNAMIC_FRAME",
        "MOVE_RELATIVE",
        "MOVE_LINEAR_RELATIVE",
        "UPDATE_TOOL",
        "OPEN_GRIPPER",
        "CLOSE_GRIPPER",
        "PULL_AIR_VACUUM_PUMP",
        "PUSH_AIR_VACUUM_PUMP",
        "SETUP_ELECTROMAGNET",
        "ACTIVATE_ELECTROMAGNET",
        "DEACTIVATE_ELECTROMAGNET",
        "GET_CURRENT_TOOL_ID",
        "GRASP_WITH_TOOL",
        "RELEASE_WITH_TOOL",
        "CONTROL_GRIPPER",
        "GET_CURRENT_TOOL_POSITION",
        "GET_GRIPPER_SPECS",
        "ENABLE_TCP",
        "SET_TCP",
        "RESET_TCP",
        "TOOL_REBOOT",
        "GET_TCP",
        "SET_PIN_MODE",
        "DIGITAL_WRITE",
        "DIGITAL_READ",
        "GET_DIGITAL_IO_STATE",
        "GET_HARDWARE_STATUS",
        "ANALOG_WRITE",
        "ANALOG_READ",
        "GET_ANALOG_IO_STATE",
        "CUSTOM_BUTTON_STATE",
        "SET_CONVEYOR",
        "UNSET_CONVEYOR",
        "CONTROL_CONVEYOR",
        "GET_CONNECTED_CONVEYORS_ID",
        "GET_CONVEYORS_FEEDBACK",
        "GET_IMAGE_COMPRESSED",
        "GET_TARGET_POSE_FROM_REL",
        "GET_TARGET_POSE_FROM_CAM",
        "VISION_PICK",
        "MOVE_TO_OBJECT",
        "DETECT_OBJECT",
        "GET_CAMERA_INTRINSICS",
        "SAVE_WORKSPACE_FROM_POSES",
        "SAVE_WORKSPACE_FROM_POINTS",
        "DELETE_WORKSPACE",
        "GET_WORKSPACE_RATIO",
        "GET_WORKSPACE_LIST",
        "SET_IMAGE_BRIGHTNESS",
        "SET_IMAGE_CONTRAST",
        "SET_IMAGE_SATURATION",
        "GET_IMAGE_PARAMETERS",
        "PLAY_SOUND",
        "SET_VOLUME",
        "STOP_SOUND",
        "DELETE_SOUND",
        "IMPORT_SOUND",
        "GET_SOUNDS",
        "GET_SOUND_DURATION",
        "SAY",
        "LED_RING_SOLID",
        "LED_RING_TURN_OFF",
        "LED_RING_FLASH",
        "LED_RING_ALTERNATE",
        "LED_RING_CHASE",
        "LED_RING_WIPE",
        "LED_RING_RAINBOW",
        "LED_RING_RAINBOW_CYCLE",
        "LED_RING_RAINBOW_CHASE",
        "LED_RING_GO_UP",
        "LED_RING_GO_UP_DOWN",
        "LED_RING_BREATH",
        "LED_RING_SNAKE",
        "LED_RING_CUSTOM",
        "LED_RING_SET_LED",
    ]
)


class CommandError(Exception):
    """The interpreter's own refusal (the robot's ``TcpCommandException``/``TypeError``)."""


class UnhandledError(Exception):
    """What the robot's server catches around the interpreter (a ``KeyError`` on a bad
    boolean, ...): answered as "An error occured while executing the last command"."""


def frame(obj: dict[str, Any], payload: bytes = b"") -> bytes:
    data = json.dumps(obj).encode()
    return LENGTH.pack(len(data)) + data + payload


def _nb_args(name: str, args: tuple[Any, ...], *expected: int) -> None:
    if len(args) not in expected:
        raise CommandError(
            f"{list(expected)} parameters expected but {len(args)} given\nIn function __{name}"
        )


def _expected_type(type_name: str, given: Any) -> CommandError:
    # the robot builds this message by string concatenation: a non-string value fails
    # with Python's own TypeError, which is what the client then reads
    if not isinstance(given, str):
        return CommandError(f'can only concatenate str (not "{type(given).__name__}") to str')
    return CommandError(f"Expected the following type: {type_name}.\nGiven: {given}")


def _floats(values: Any) -> list[float]:
    try:
        return [float(v) for v in values]
    except (ValueError, TypeError, OverflowError):
        raise _expected_type("float", values) from None


def _choice(value: Any, choices: dict[str, Any]) -> Any:
    if not isinstance(value, str) or value not in choices:
        raise CommandError(f"Expected one of the following: {choices.keys()}.\nGiven: {value}")
    return choices[value]


def _boolean_key(value: Any) -> bool:
    """``dict[value]`` on the robot: a KeyError (or TypeError) reaches the server."""
    if not isinstance(value, str) or value not in BOOLEANS:
        raise UnhandledError(repr(value) if isinstance(value, str) else str(value))
    return BOOLEANS[value]


def _int(value: Any) -> int:
    if type(value) is not int:
        raise _expected_type("int", value)
    return value


def _version_tuple(text: str) -> tuple[int, ...]:
    parts = []
    for p in text.split("."):
        digits = "".join(c for c in p if c.isdigit())
        parts.append(int(digits) if digits else 0)
    return tuple(parts)


def _pose_from_dict(d: Any) -> list[float]:
    if not isinstance(d, dict):
        raise UnhandledError(f"'{type(d).__name__}' object is not subscriptable")
    try:
        values = [d["x"], d["y"], d["z"], d["roll"], d["pitch"], d["yaw"]]
    except KeyError as exc:
        raise UnhandledError(repr(exc.args[0])) from None
    pose = _floats(values)
    meta = d.get("metadata")
    if isinstance(meta, dict):
        if meta.get("frame") not in ("", None, "world"):
            raise RobotError(INVALID_PARAMETERS, f"Unknown frame {meta.get('frame')!r}")
        if meta.get("version") == 2 and meta.get("length_unit") == "MILLIMETERS":
            pose[:3] = [v / 1000.0 for v in pose[:3]]
    return pose


def _joints_from_dict(d: Any) -> list[float]:
    if not isinstance(d, dict):
        raise UnhandledError(f"'{type(d).__name__}' object is not subscriptable")
    keys = sorted(
        (k for k in d if isinstance(k, str) and k.startswith("joint_") and k[6:].isdigit()),
        key=lambda k: int(k[6:]),
    )
    return _floats([d[k] for k in keys])


def _pose_dict(pose: list[float]) -> dict[str, Any]:
    x, y, z, roll, pitch, yaw = pose
    meta = {"version": 2, "frame": "", "length_unit": "METERS"}
    return {"x": x, "y": y, "z": z, "roll": roll, "pitch": pitch, "yaw": yaw, "metadata": meta}


Handler = Callable[..., Awaitable[tuple[Any, ...]]]


class Interpreter:
    """One client's command interpreter (the handshake is per connection)."""

    def __init__(self, robot: Ned2Robot) -> None:
        self.robot = robot
        self.handshake_made = False
        self.handlers: dict[str, Handler] = {
            name[3:].upper(): getattr(self, name) for name in dir(self) if name.startswith("_c_")
        }

    # ---------------------------------------------------------------- dispatch

    def failure(self, command: str, message: str) -> dict[str, Any]:
        if not self.handshake_made:
            message += HANDSHAKE_NOTE
        return {
            "command": command,
            "status": "KO",
            "message": message,
            "list_ret_param": [],
            "payload_size": 0,
        }

    async def interpret(self, request: Any) -> bytes:
        if not isinstance(request, dict):
            return frame(
                self.failure("", f"Cannot interpret command of incorrect type: {type(request)}")
            )
        if set(request.keys()) != {"command", "param_list"}:
            return frame(self.failure("", "Incorrect command format: " + str(request)))
        raw = request["command"]
        if not isinstance(raw, str):
            name = f"'{type(raw).__name__}' object has no attribute 'upper'"
            return frame(self.failure(raw if _jsonable_scalar(raw) else "", _server_error(name)))
        command = raw.upper()
        handler = self.handlers.get(command)
        if handler is None and command in PYNIRYO_COMMANDS:
            # a command of the robot's this simulator does not model
            return frame(self.failure(command, "Not implemented in the fxcell Ned2 simulator"))
        if handler is None:
            return frame(self.failure("", "Unknown command"))
        params = request["param_list"]
        if not isinstance(params, list):
            params = list(params) if isinstance(params, (str, dict)) else None
            if params is None:
                return frame(
                    self.failure(
                        raw, _server_error("argument after * must be an iterable, not a number")
                    )
                )
        try:
            result = await handler(*params)
        except CommandError as exc:
            return frame(self.failure(command, str(exc)))
        except RobotError as exc:
            return frame(self.failure(raw, _server_error(str(exc))))
        except UnhandledError as exc:
            return frame(self.failure(raw, _server_error(str(exc))))
        answer = [
            v.name if isinstance(v, Enum) else str(v) if isinstance(v, bool) else v for v in result
        ]
        return frame(
            {"status": "OK", "command": command, "list_ret_param": answer, "payload_size": 0}
        )

    # ---------------------------------------------------------------- main purpose

    async def _c_handshake(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("handshake", a, 1)
        response: dict[str, str] = {}
        version = a[0]
        if not isinstance(version, str):
            raise CommandError(
                f"'<' not supported between instances of '{type(version).__name__}' and 'str'"
            )
        if _version_tuple(version) < _version_tuple(MINIMUM_CLIENT_VERSION):
            response["message"] = (
                f"Your PyNiryo client ({version}) is older than {MINIMUM_CLIENT_VERSION}: "
                "upgrade it to use every feature of this robot"
            )
        self.handshake_made = True
        return (response,)

    async def _c_calibrate(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("calibrate", a, 1)
        _choice(a[0], {"MANUAL": 1, "AUTO": 0})
        await self.robot.calibrate()  # the Ned2 calibrates itself in either mode
        return ()

    async def _c_get_learning_mode(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_learning_mode", a, 0)
        return (self.robot.learning_mode,)

    async def _c_set_learning_mode(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("set_learning_mode", a, 1)
        on = _choice(a[0], BOOLEANS)
        self.robot.set_learning_mode(on)
        return (True,)

    async def _c_set_arm_max_velocity(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("set_arm_max_velocity", a, 1)
        v = a[0]
        if type(v) not in (int, float) or not 0 < v <= 100:
            raise _expected_type("float/integer [1 -100]", v)
        self.robot.velocity_percent = float(v)
        return ()

    async def _c_get_collision_detected(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_collision_detected", a, 0)
        return (self.robot.collision_detected,)

    async def _c_clear_collision_detected(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("clear_collision_detected", a, 0)
        self.robot.collision_detected = False
        return ()

    # ---------------------------------------------------------------- joints and pose

    async def _c_get_joints(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_joints", a, 0)
        return tuple(float(v) for v in self.robot.joints)

    async def _c_get_pose(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_pose", a, 0)
        return tuple(self.robot.pose())

    async def _c_get_pose_quat(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_pose_quat", a, 0)
        t = ned2.forward(self.robot.joints)
        return (*[float(v) for v in t[:3, 3]], *matrix_to_quaternion(t[:3, :3]))

    async def _c_get_home_pose(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_home_pose", a, 0)
        return tuple(float(v) for v in ned2.HOME)

    async def _c_move_joints(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("move_joints", a, 6)
        goal = self.robot.check_joints(_floats(a))
        await self.robot.move_joints(goal)
        return ()

    async def _c_move_pose(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("move_pose", a, 7)
        await self._move_pose(_floats(a[:-1]), a[-1], linear=False)
        return ()

    async def _c_move_linear_pose(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("move_linear_pose", a, 7)
        await self._move_pose(_floats(a[:-1]), a[-1], linear=True)
        return ()

    async def _move_pose(self, pose: list[float], frame_name: Any, *, linear: bool) -> None:
        if frame_name not in ("", None, "world"):
            raise RobotError(INVALID_PARAMETERS, f"Unknown frame {frame_name!r}")
        if linear:
            self.robot.solve(pose)  # refuse an unreachable goal before moving
            await self.robot.move_linear(pose)
        else:
            await self.robot.move_joints(self.robot.solve(pose))

    async def _c_move(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("move", a, 2)
        position, linear_text = a
        linear = _boolean_key(linear_text)
        if not isinstance(position, dict) or "obj_type" not in position:
            raise UnhandledError("'obj_type'")
        kind = position["obj_type"]
        if kind == "JOINTS":
            if linear:
                raise CommandError(
                    "The robot can only do a linear move with a pose, not with joints"
                )
            joints = _joints_from_dict(position)
            await self.robot.move_joints(self.robot.check_joints(joints))
        else:
            await self._move_pose(_pose_from_dict(position), "", linear=linear)
        return ()

    async def _c_shift_pose(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("shift_pose", a, 2, 3)
        axes = {"X": 0, "Y": 1, "Z": 2, "ROLL": 3, "PITCH": 4, "YAW": 5}
        axis = _choice(a[0], axes)
        try:
            value = float(a[1])
        except (TypeError, ValueError, OverflowError):
            raise _expected_type("float", a[1]) from None
        linear = _boolean_key(a[2]) if len(a) == 3 else False
        pose = self.robot.pose()
        pose[axis] += value
        await self._move_pose(pose, "", linear=linear)
        return ()

    async def _c_move_to_home_pose(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("move_to_home_pose", a, 0)
        await self.robot.move_joints(ned2.HOME.copy())
        return ()

    async def _c_forward_kinematics(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("forward_kinematics", a, 1)
        q = _joints_from_dict(a[0])
        if len(q) != 6 or not all(math.isfinite(v) for v in q):
            raise RobotError(INVALID_PARAMETERS, "Joints must be 6 finite numbers")
        return (_pose_dict(ned2.matrix_to_pose(ned2.forward(q))),)

    async def _c_inverse_kinematics(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("inverse_kinematics", a, 1)
        q = self.robot.solve(_pose_from_dict(a[0]))
        d: dict[str, Any] = {f"joint_{i}": float(v) for i, v in enumerate(q)}
        d["metadata"] = {"version": 1}
        return (d,)

    # ---------------------------------------------------------------- tool

    async def _c_update_tool(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("update_tool", a, 0)
        return ()

    async def _c_get_current_tool_id(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_current_tool_id", a, 0)
        return (self.robot.tool,)

    async def _c_get_current_tool_position(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_current_tool_position", a, 0)
        return (self.robot.tool_position(),)

    async def _c_get_gripper_specs(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_gripper_specs", a, 1)
        _choice(a[0], {**TOOLS, "GRIPPER_2": 12, "GRIPPER_3": 13, "GRIPPER_4": 14})
        return (list(GRIPPER_STEPS), [-1000, 1000])

    async def _c_grasp_with_tool(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("grasp_with_tool", a, 0)
        await self.robot.close_gripper()
        return ()

    async def _c_release_with_tool(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("release_with_tool", a, 0)
        await self.robot.open_gripper()
        return ()

    async def _c_open_gripper(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("open_gripper", a, 3)
        for v in a:
            _int(v)
        await self.robot.open_gripper()
        return ()

    async def _c_close_gripper(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("close_gripper", a, 3)
        for v in a:
            _int(v)
        await self.robot.close_gripper()
        return ()

    # ---------------------------------------------------------------- IO and hardware

    async def _c_digital_write(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("digital_write", a, 2)
        state = _choice(a[1], {"HIGH": True, "LOW": False})
        if a[0] not in DIGITAL_OUTPUTS:
            raise RobotError(INVALID_PARAMETERS, f"Digital output {a[0]} does not exist")
        self.robot.digital_out[a[0]] = state
        return ()

    async def _c_digital_read(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("digital_read", a, 1)
        pin = a[0]
        if pin in DIGITAL_INPUTS:
            value = self.robot.digital_in[pin]
        elif pin in DIGITAL_OUTPUTS:
            value = self.robot.digital_out[pin]
        else:
            raise RobotError(INVALID_PARAMETERS, f"Digital IO {pin} does not exist")
        return ("HIGH" if value else "LOW",)

    async def _c_get_digital_io_state(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_digital_io_state", a, 0)
        rows = [[n, 1, int(v)] for n, v in self.robot.digital_in.items()]
        rows += [[n, 0, int(v)] for n, v in self.robot.digital_out.items()]
        rows.sort(key=lambda r: str(r[0]))
        return tuple(rows)

    async def _c_set_pin_mode(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("set_pin_mode", a, 2)
        _choice(a[1], {"OUTPUT": 0, "INPUT": 1})
        raise RobotError(INVALID_PARAMETERS, "The Ned2's IO have a fixed mode")

    async def _c_analog_write(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("analog_write", a, 2)
        if a[0] not in ANALOG_OUTPUTS:
            raise RobotError(INVALID_PARAMETERS, f"Analog output {a[0]} does not exist")
        v = _floats([a[1]])[0]
        if not 0.0 <= v <= 5.0:
            raise RobotError(INVALID_PARAMETERS, "An analog output takes 0 to 5 V")
        self.robot.analog_out[a[0]] = v
        return ()

    async def _c_analog_read(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("analog_read", a, 1)
        if a[0] in ANALOG_INPUTS:
            return (self.robot.analog_in[a[0]],)
        if a[0] in ANALOG_OUTPUTS:
            return (self.robot.analog_out[a[0]],)
        raise RobotError(INVALID_PARAMETERS, f"Analog IO {a[0]} does not exist")

    async def _c_get_analog_io_state(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_analog_io_state", a, 0)
        rows = [[n, 1, v] for n, v in self.robot.analog_in.items()]
        rows += [[n, 0, v] for n, v in self.robot.analog_out.items()]
        rows.sort(key=lambda r: str(r[0]))
        return tuple(rows)

    async def _c_get_hardware_status(self, *a: Any) -> tuple[Any, ...]:
        _nb_args("get_hardware_status", a, 0)
        return tuple(self.robot.hardware_status())


def _server_error(text: str) -> str:
    return f"An error occured while executing the last command : {text}"


def _jsonable_scalar(v: Any) -> bool:
    return v is None or isinstance(v, (int, float, bool))
