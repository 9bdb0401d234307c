"""The Ned2 driver's two clients against the Ned2 simulator: the TCP client (pyniryo's
protocol) runs commands and raises the robot's refusals as typed errors with their status
code; the rosbridge client streams joint states while a move holds the TCP connection and
stops that move with ``stop_command``; a lost robot fails both with ConnectionLostError."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator
from typing import Any

import numpy as np
import pytest

from fxcell.errors import (
    ConnectionLostError,
    InvalidArgumentError,
    RobotCommandError,
    RobotCommandStatusError,
)
from fxcell.link.ned2 import (
    ABORTED,
    ARM_ACTION,
    EXECUTE_FULL_TRAJ,
    JOINT_NAMES,
    MOVE_ACTION,
    PREEMPTED,
    SUCCEEDED,
)
from fxcell.link.ned2.rosbridge import RosbridgeClient
from fxcell.link.ned2.tcp import NiryoTcpClient, joints, robot_bool
from fxcell.motion import ned2
from fxcell.testing import injected_faults
from fxcell.testing.ned2 import Ned2SimulatorHandle, ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(60)]

FAR = [-1.5, -0.8, 0.8, 1.0, 1.0, 1.0]
CALIBRATION_NOT_DONE, STOPPED, INVALID_PARAMETERS = -113, -4, -52


def quintic_trajectory(
    q0: np.ndarray, q1: np.ndarray, duration: float, step: float
) -> dict[str, Any]:
    """A ``trajectory_msgs/JointTrajectory`` from ``q0`` to ``q1`` along the straight joint
    line (a quintic time law), a point every ``step`` s."""
    points = []
    for t in np.arange(0.0, duration + step / 2, step):
        tau = min(t / duration, 1.0)
        s = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
        ds = (30 * tau**2 - 60 * tau**3 + 30 * tau**4) / duration
        secs = int(t)
        points.append(
            {
                "positions": (q0 + s * (q1 - q0)).tolist(),
                "velocities": (ds * (q1 - q0)).tolist(),
                "time_from_start": {"secs": secs, "nsecs": round((t - secs) * 1e9)},
            }
        )
    return {"joint_names": list(JOINT_NAMES), "points": points}


def trajectory_goal(trajectory: dict[str, Any]) -> dict[str, Any]:
    return {"cmd": {"cmd_type": EXECUTE_FULL_TRAJ, "trajectory": trajectory}}


async def ready_arm(bridge: RosbridgeClient) -> None:
    await bridge.call("/niryo_robot/joints_interface/calibrate_motors", {"value": 1}, within=30)
    await bridge.call("/niryo_robot/learning_mode/activate", {"value": False})


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
    await ready_arm(bridge)
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
    with injected_faults("the robot goes dark"):
        sim.inject("power_loss")
    with pytest.raises(ConnectionLostError):
        await tcp.command("GET_JOINTS")
    with pytest.raises(ConnectionLostError):
        await bridge.call("/niryo_robot_arm_commander/is_active")
    assert not bridge.connected
    fresh = NiryoTcpClient(sim.host)
    with pytest.raises(ConnectionLostError, match="cannot reach"):
        await fresh.connect()


async def test_a_timed_trajectory_runs_through_the_arm_action_and_ends_on_its_last_point(
    bridge: RosbridgeClient, sim: Ned2SimulatorHandle
) -> None:
    await ready_arm(bridge)
    q0, q1 = ned2.HOME.copy(), np.array([0.4, -0.2, 0.1, 0.3, -0.4, 0.2])
    seen: list[list[float]] = []
    await bridge.subscribe(
        "/joint_states", "sensor_msgs/JointState", lambda m: seen.append(m["position"])
    )
    goal = await bridge.send_goal(
        ARM_ACTION,
        MOVE_ACTION,
        {
            "cmd": {
                "cmd_type": EXECUTE_FULL_TRAJ,
                "trajectory": quintic_trajectory(q0, q1, 2.0, 0.1),
            }
        },
    )
    status, result = await bridge.goal_result(goal, within=30)
    assert (status, result["status"]) == (SUCCEEDED, 1)
    assert sim.state()["joints"] == pytest.approx(q1.tolist(), abs=1e-12)
    # every streamed position is on the trajectory's straight joint line
    direction = (q1 - q0) / np.linalg.norm(q1 - q0)
    for q in seen:
        offset = np.asarray(q) - q0
        assert np.linalg.norm(offset - (offset @ direction) * direction) < 1e-9
    assert len({round(float((np.asarray(q) - q0) @ direction), 6) for q in seen}) > 3


async def test_a_trajectory_that_does_not_start_at_the_arm_is_refused_and_nothing_moves(
    bridge: RosbridgeClient, sim: Ned2SimulatorHandle
) -> None:
    await ready_arm(bridge)
    elsewhere = ned2.HOME + 0.1
    goal = await bridge.send_goal(
        ARM_ACTION,
        MOVE_ACTION,
        trajectory_goal(quintic_trajectory(elsewhere, elsewhere + 0.2, 1.0, 0.1)),
    )
    status, result = await bridge.goal_result(goal, within=30)
    assert (status, result["status"]) == (ABORTED, INVALID_PARAMETERS)
    assert "start" in result["message"]
    assert sim.state()["joints"] == pytest.approx(ned2.HOME.tolist())


async def test_a_stop_preempts_a_running_trajectory(
    bridge: RosbridgeClient, sim: Ned2SimulatorHandle
) -> None:
    await ready_arm(bridge)
    q0, q1 = ned2.HOME.copy(), np.array([0.4, -0.2, 0.1, 0.3, -0.4, 0.2])
    goal = await bridge.send_goal(
        ARM_ACTION,
        MOVE_ACTION,
        {
            "cmd": {
                "cmd_type": EXECUTE_FULL_TRAJ,
                "trajectory": quintic_trajectory(q0, q1, 20.0, 0.5),
            }
        },
    )
    sim.wait_for("moving", True)
    await bridge.call("/niryo_robot_arm_commander/stop_command")
    status, result = await bridge.goal_result(goal, within=30)
    assert (status, result["status"]) == (PREEMPTED, STOPPED)
    state = sim.state()
    assert state["moving"] is False
    assert state["joints"] != pytest.approx(q1.tolist())
