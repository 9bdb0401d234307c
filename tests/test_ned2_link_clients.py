"""The Ned2 driver's two clients against the Ned2 simulator: the TCP client (pyniryo's
protocol) runs commands and raises the robot's refusals as typed errors with their status
code; the rosbridge client streams joint states while a move holds the TCP connection and
stops that move with ``stop_command``; a lost robot fails both with ConnectionLostError."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator

import pytest

from fxcell.errors import (
    ConnectionLostError,
    InvalidArgumentError,
    RobotCommandError,
    RobotCommandStatusError,
)
from fxcell.link.ned2.rosbridge import RosbridgeClient
from fxcell.link.ned2.tcp import NiryoTcpClient, joints, robot_bool
from fxcell.motion import ned2
from fxcell.testing.ned2 import Ned2SimulatorHandle, ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(60)]

FAR = [-1.5, -0.8, 0.8, 1.0, 1.0, 1.0]
CALIBRATION_NOT_DONE, STOPPED = -113, -4


@pytest.fixture
def sim() -> Iterator[Ned2SimulatorHandle]:
    with ned2_simulator() as handle:
        yield handle


@pytest.fixture
async def tcp(sim: Ned2SimulatorHandle) -> AsyncIterator[NiryoTcpClient]:
    client = NiryoTcpClient(sim.host)
    await client.connect()
    try:
        yield client
    finally:
        await client.close()


@pytest.fixture
async def bridge(sim: Ned2SimulatorHandle) -> AsyncIterator[RosbridgeClient]:
    client = RosbridgeClient(sim.host)
    await client.connect()
    try:
        yield client
    finally:
        await client.close()


async def test_commands_run_and_answer_their_values(
    tcp: NiryoTcpClient, sim: Ned2SimulatorHandle
) -> None:
    status = (await tcp.command("GET_HARDWARE_STATUS")).values
    assert robot_bool(status[4]) is True  # calibration needed, as the robot boots
    await tcp.command("CALIBRATE", "AUTO", within=30)
    await tcp.command("SET_LEARNING_MODE", False)
    await tcp.command("MOVE_JOINTS", 0.2, 0.1, -0.3, 0.0, 0.5, 0.0, within=30)
    q = joints((await tcp.command("GET_JOINTS")).values)
    assert q == pytest.approx([0.2, 0.1, -0.3, 0.0, 0.5, 0.0])
    assert sim.state()["joints"] == pytest.approx(q)


async def test_a_refusal_is_a_typed_error_with_the_robots_status_code(
    tcp: NiryoTcpClient, sim: Ned2SimulatorHandle
) -> None:
    with pytest.raises(RobotCommandStatusError) as refused:
        await tcp.command("MOVE_JOINTS", *FAR)
    assert refused.value.code == CALIBRATION_NOT_DONE
    assert "calibrate" in refused.value.detail
    assert sim.state()["joints"] == pytest.approx(ned2.HOME.tolist())
    with pytest.raises(RobotCommandError, match="parameters expected"):
        await tcp.command("GET_JOINTS", 1)  # a protocol error: no status code
    with pytest.raises(InvalidArgumentError, match="65535"):
        await tcp.command("MOVE_JOINTS", "x" * 70_000)  # refused before anything is sent
    assert joints((await tcp.command("GET_JOINTS")).values) == pytest.approx(ned2.HOME.tolist())


async def test_joint_states_stream_while_a_move_holds_the_tcp_connection_and_a_stop_ends_it(
    tcp: NiryoTcpClient, bridge: RosbridgeClient, sim: Ned2SimulatorHandle
) -> None:
    await bridge.call("/niryo_robot/joints_interface/calibrate_motors", {"value": 1}, within=30)
    await bridge.call("/niryo_robot/learning_mode/activate", {"value": False})
    updates: asyncio.Queue[list[float]] = asyncio.Queue()
    sub = await bridge.subscribe(
        "/joint_states", "sensor_msgs/JointState", lambda msg: updates.put_nowait(msg["position"])
    )
    at_rest = await updates.get()
    move = asyncio.create_task(tcp.command("MOVE_JOINTS", *FAR, within=60))
    async with asyncio.timeout(10):  # the stream shows the arm moving
        while await updates.get() == at_rest:
            pass
    assert not move.done()  # the TCP answer waits for the end of the move
    answer = await bridge.call("/niryo_robot_arm_commander/stop_command")
    assert answer["status"] == 1
    with pytest.raises(RobotCommandStatusError) as stopped:
        await move
    assert stopped.value.code == STOPPED
    state = sim.state()
    assert state["moving"] is False
    assert state["joints"] != pytest.approx(FAR)
    async with asyncio.timeout(10):  # and then where it stopped
        while await updates.get() != pytest.approx(state["joints"], abs=1e-12):
            pass
    await bridge.unsubscribe(sub)


async def test_a_service_that_refuses_raises_and_an_unknown_one_too(
    bridge: RosbridgeClient, sim: Ned2SimulatorHandle
) -> None:
    with pytest.raises(RobotCommandStatusError) as refused:
        await bridge.call(
            "/niryo_robot_arm_commander/set_max_velocity_scaling_factor", {"value": 500}
        )
    assert refused.value.code < 0
    assert sim.state()["velocity_percent"] == 100
    with pytest.raises(RobotCommandError, match="does not exist"):
        await bridge.call("/fly")


async def test_a_robot_that_goes_dark_fails_both_clients_with_connection_lost(
    tcp: NiryoTcpClient, bridge: RosbridgeClient, sim: Ned2SimulatorHandle
) -> None:
    sim.inject("power_loss")
    with pytest.raises(ConnectionLostError):
        await tcp.command("GET_JOINTS")
    with pytest.raises(ConnectionLostError):
        await bridge.call("/niryo_robot_arm_commander/is_active")
    assert not bridge.connected
    fresh = NiryoTcpClient(sim.host)
    with pytest.raises(ConnectionLostError, match="cannot reach"):
        await fresh.connect()
