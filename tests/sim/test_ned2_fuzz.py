"""Whatever a client sends, the Ned2 simulator answers it as the robot's server would (OK
or KO) or drops the connection, and never logs an unhandled exception: Hypothesis over
the command grammar (real command names with arbitrary parameters) and over raw frames,
and over rosbridge messages (operations, topics, services and goals with arbitrary fields).

The server runs in this process on an event loop of the test's own, so an exception
escaping a handler reaches the loop's exception handler or a log record here.
"""

from __future__ import annotations

import asyncio
import json
import logging
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from websockets.asyncio.client import connect

from fxcell.sim.ned2 import NED2_PORT, ROSBRIDGE_PORT
from fxcell.sim.ned2.protocol import HANDSHAKE_NOTE, Interpreter
from fxcell.sim.ned2.robot import Ned2Robot
from fxcell.sim.ned2.rosbridge import SERVICES
from fxcell.sim.ned2.server import Ned2Server
from fxcell.testing.ned2 import free_ned2_host

pytestmark = pytest.mark.timeout(300)

COMMANDS = [
    "CALIBRATE", "SET_LEARNING_MODE", "GET_LEARNING_MODE", "SET_ARM_MAX_VELOCITY",
    "GET_COLLISION_DETECTED", "CLEAR_COLLISION_DETECTED", "HANDSHAKE", "GET_JOINTS",
    "GET_POSE", "GET_POSE_QUAT", "GET_HOME_POSE", "MOVE_JOINTS", "MOVE_POSE",
    "MOVE_LINEAR_POSE", "MOVE", "SHIFT_POSE", "MOVE_TO_HOME_POSE", "FORWARD_KINEMATICS",
    "INVERSE_KINEMATICS", "UPDATE_TOOL", "GET_CURRENT_TOOL_ID", "GET_CURRENT_TOOL_POSITION",
    "GET_GRIPPER_SPECS", "GRASP_WITH_TOOL", "RELEASE_WITH_TOOL", "OPEN_GRIPPER",
    "CLOSE_GRIPPER", "DIGITAL_WRITE", "DIGITAL_READ", "GET_DIGITAL_IO_STATE", "SET_PIN_MODE",
    "ANALOG_WRITE", "ANALOG_READ", "GET_ANALOG_IO_STATE", "GET_HARDWARE_STATUS", "JOG",
]  # fmt: skip

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**30), 10**30),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(["TRUE", "FALSE", "None", "AUTO", "MANUAL", "HIGH", "LOW", "DO1", "DI1",
                     "AO1", "AI1", "X", "ROLL", "JOINTS", "POSE", "GRIPPER_1", "", "1.2.5"]),
    st.text(max_size=8),
)  # fmt: skip
joint_dicts = st.fixed_dictionaries(
    {f"joint_{i}": st.floats(-3.2, 3.2) for i in range(6)},
    optional={"obj_type": st.sampled_from(["JOINTS", "POSE", "X"]), "metadata": scalars},
)
pose_dicts = st.fixed_dictionaries(
    {k: st.floats(-0.6, 0.6) for k in ("x", "y", "z", "roll", "pitch", "yaw")},
    optional={
        "obj_type": st.sampled_from(["JOINTS", "POSE"]),
        "metadata": st.fixed_dictionaries(
            {"version": st.sampled_from([1, 2, 3]), "frame": st.sampled_from(["", "w", 3]),
             "length_unit": st.sampled_from(["METERS", "MILLIMETERS", 1])}
        ),
    },
)  # fmt: skip
values = st.recursive(
    st.one_of(scalars, joint_dicts, pose_dicts),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner),
    max_leaves=10,
)
requests = st.one_of(
    st.fixed_dictionaries(
        {"command": st.sampled_from(COMMANDS) | st.text(max_size=10) | scalars,
         "param_list": st.lists(values, max_size=8) | values}
    ),
    values,
    st.dictionaries(st.sampled_from(["command", "param_list", "x"]), values),
)  # fmt: skip


@dataclass
class Trouble:
    loop_errors: list[dict[str, Any]] = field(default_factory=list)
    records: list[logging.LogRecord] = field(default_factory=list)


class _Catch(logging.Handler):
    def __init__(self, trouble: Trouble) -> None:
        super().__init__(logging.DEBUG)
        self.trouble = trouble

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info or (record.name == "asyncio" and record.levelno >= logging.ERROR):
            self.trouble.records.append(record)


@pytest.fixture
def trouble() -> Iterator[Trouble]:
    found = Trouble()
    handler = _Catch(found)
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield found
    finally:
        root.removeHandler(handler)


@pytest.fixture
def loop(trouble: Trouble) -> Iterator[asyncio.AbstractEventLoop]:
    lp = asyncio.new_event_loop()
    lp.set_exception_handler(lambda _loop, context: trouble.loop_errors.append(context))
    try:
        yield lp
    finally:
        lp.close()


def _decode(data: bytes) -> dict[str, Any]:
    size = struct.unpack("@H", data[:2])[0]
    assert len(data) == 2 + size
    answer: dict[str, Any] = json.loads(data[2:])
    return answer


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow,
          HealthCheck.function_scoped_fixture])  # fmt: skip
@given(request=requests, handshake=st.booleans())
def test_every_request_is_answered_ok_or_ko_without_an_unhandled_exception(
    loop: asyncio.AbstractEventLoop, trouble: Trouble, request: Any, handshake: bool
) -> None:
    robot = Ned2Robot(time_scale=1e-4, calibrated=True, learning_mode=False)
    interpreter = Interpreter(robot)
    interpreter.handshake_made = handshake
    answer = _decode(loop.run_until_complete(interpreter.interpret(request)))
    assert answer["status"] in ("OK", "KO")
    assert answer["payload_size"] == 0
    if answer["status"] == "KO":
        assert isinstance(answer["message"], str)
        assert answer["message"].endswith(HANDSHAKE_NOTE) is not handshake
    assert not trouble.loop_errors
    assert not trouble.records


frames = st.one_of(
    st.binary(max_size=64),
    st.builds(lambda r: json.dumps(r).encode(), requests),
    st.sampled_from([b"{", b"[]", b"null", b"\xff\xfe", b'{"command": 1}', b""]),
)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow,
          HealthCheck.function_scoped_fixture])  # fmt: skip
@given(data=st.lists(frames, min_size=1, max_size=4))
def test_any_frame_on_the_socket_is_answered_or_the_connection_dropped(
    loop: asyncio.AbstractEventLoop, trouble: Trouble, data: list[bytes]
) -> None:
    async def scenario() -> None:
        server = Ned2Server(free_ned2_host(), time_scale=1e-4, calibrated=True)
        await server.start()
        try:
            reader, writer = await asyncio.open_connection(server.host, NED2_PORT)
            for body in data:
                writer.write(struct.pack("@H", len(body)) + body)
                await writer.drain()
                head = await asyncio.wait_for(reader.read(2), 3.0)
                if not head:  # the robot drops a client whose frame is not JSON
                    break
                size = struct.unpack("@H", head)[0]
                answer = json.loads(await asyncio.wait_for(reader.readexactly(size), 3.0))
                assert answer["status"] in ("OK", "KO")
            writer.close()
            await writer.wait_closed()
        finally:
            await server.close()

    loop.run_until_complete(scenario())
    assert not trouble.loop_errors
    assert not trouble.records


# ---------------------------------------------------------------------- the rosbridge

ARM = "/niryo_robot_arm_commander/robot_action"
TOPICS = [
    "/joint_states", "//joint_states/", "/niryo_robot/robot_state",
    "/niryo_robot_hardware_interface/hardware_status", "/niryo_robot/learning_mode/state",
    f"{ARM}//status", f"{ARM}/goal", f"{ARM}/cancel", f"{ARM}/result",
    "/niryo_robot_tools_commander/action_server/goal", "/ping_pyniryo", "/x", "",
]  # fmt: skip
commands = st.fixed_dictionaries(
    {},
    optional={
        "cmd_type": st.integers(-1, 13) | scalars,
        "joints": st.lists(st.floats(-3.2, 3.2) | scalars, max_size=7),
        "position": st.dictionaries(st.sampled_from(["x", "y", "z"]),
                                    st.floats(-0.6, 0.6) | scalars),
        "rpy": st.dictionaries(st.sampled_from(["roll", "pitch", "yaw"]),
                               st.floats(-3, 3) | scalars),
        "tool_id": st.sampled_from([0, 11, 12]) | scalars,
    },
)  # fmt: skip
goals = st.fixed_dictionaries(
    {"goal_id": st.fixed_dictionaries({"id": st.text(max_size=4) | scalars}) | values,
     "goal": st.fixed_dictionaries({"cmd": commands}) | values}
)  # fmt: skip
OPS = ["subscribe", "unsubscribe", "advertise", "unadvertise", "publish", "call_service", "fly"]


def mostly(choices: list[str], other: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    """One of ``choices`` nine times in ten, else ``other``."""
    return st.integers(0, 9).flatmap(lambda k: other if k == 0 else st.sampled_from(choices))


bridge_messages = st.fixed_dictionaries(
    {"op": mostly(OPS, scalars)},
    optional={
        "id": st.text(max_size=4) | scalars,
        "topic": mostly(TOPICS, values),
        "type": st.sampled_from(["sensor_msgs/JointState", "std_msgs/Bool"]) | scalars,
        "service": mostly(sorted(SERVICES), st.text(max_size=8) | scalars),
        "args": st.fixed_dictionaries({}, optional={"value": scalars, "name": scalars}) | values,
        "msg": goals | values,
        "throttle_rate": scalars,
    },
)  # fmt: skip


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow,
          HealthCheck.function_scoped_fixture])  # fmt: skip
@given(
    messages=st.lists(bridge_messages, min_size=1, max_size=6)
    | st.lists(bridge_messages | st.text(max_size=12), min_size=1, max_size=6)
)
def test_any_rosbridge_message_is_answered_or_ignored_without_an_unhandled_exception(
    loop: asyncio.AbstractEventLoop, trouble: Trouble, messages: list[Any]
) -> None:
    async def scenario() -> None:
        server = Ned2Server(free_ned2_host(), time_scale=1e-4, calibrated=True)
        await server.start()
        try:
            async with connect(f"ws://{server.host}:{ROSBRIDGE_PORT}") as ws:
                for m in messages:
                    await ws.send(m if isinstance(m, str) else json.dumps(m))
                # the bridge reads in order: once this is answered, every message was taken
                await ws.send(json.dumps({"op": "call_service", "id": "end",
                                          "service": "/rosapi/get_param_names"}))  # fmt: skip
                while True:
                    answer = json.loads(await asyncio.wait_for(ws.recv(), 5.0))
                    assert answer["op"] in ("publish", "status", "service_response")
                    if answer.get("id") == "end":
                        assert answer["result"] is True
                        break
        finally:
            await server.close()

    loop.run_until_complete(scenario())
    assert not trouble.loop_errors
    assert not trouble.records
