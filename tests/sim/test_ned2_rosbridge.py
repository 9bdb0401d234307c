"""Niryo's ROS client, pyniryo2 1.0.1 (roslibpy over the rosbridge WebSocket, port 9090),
unmodified, against the Ned2 simulator: it connects (its action clients wait for their
servers' status), reads joints, pose, hardware status, learning mode and velocity
scaling, calibrates, moves through the arm commander's action, uses the gripper through
the tools commander's action, sets and reads the digital pins through the IO panel's
services and state topic, and stops a running move with ``stop_command``, whether
the move came through the rosbridge or through the TCP server (pyniryo). Protocol errors
are answered as rosbridge answers them."""

from __future__ import annotations

import json
import threading
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from pyniryo import JointsPosition, NiryoRobotException
from pyniryo import NiryoRobot as TcpClient
from websockets.sync.client import connect

from fxcell.motion import ned2
from fxcell.testing import injected_faults
from fxcell.testing.ned2 import Ned2SimulatorHandle, ned2_simulator

with warnings.catch_warnings():
    # pyniryo2 warns at import that Niryo no longer maintains it (since June 2025)
    warnings.filterwarnings("ignore", "This project is officially", DeprecationWarning)
    from pyniryo2 import NiryoRobot

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]


@pytest.fixture(scope="module", autouse=True)
def reactor_awake() -> Iterator[None]:
    """Keep pyniryo2's Twisted reactor waking every 50 ms while this file's tests run.

    roslibpy keeps one reactor per process, running in a thread of its own. A second
    ``NiryoRobot`` starts its connection from the caller's thread (``reactor.connectTCP``),
    which schedules the connect with ``callLater(0)`` but does not wake the reactor. With
    nothing else pending, the reactor stays asleep, and the client gives up after its fixed
    5 s ("Failed to connect to ROS"). Measured with this simulator: a second client 8 s after
    the first failed in 4 tries of 4, and connected in 0.8 s with the reactor kept awake.
    This is a thread-safety gap in the client, not something a rosbridge server can answer.
    """
    from twisted.internet import reactor
    from twisted.internet.task import LoopingCall

    tick = LoopingCall(lambda: None)
    reactor.callFromThread(tick.start, 0.05)  # type: ignore[attr-defined]
    yield
    reactor.callFromThread(tick.stop)  # type: ignore[attr-defined]


MM = 1e-3
FAR = [-1.5, -0.8, 0.8, 1.0, 1.0, 1.0]  # a long move from home


@pytest.fixture
def sim() -> Iterator[Ned2SimulatorHandle]:
    with ned2_simulator() as handle:
        yield handle


@pytest.fixture
def robot(sim: Ned2SimulatorHandle) -> Iterator[Any]:
    r = NiryoRobot(sim.host)
    try:
        yield r
    finally:
        r.end()


@pytest.fixture
def ready(robot: Any) -> Any:
    robot.arm.calibrate_auto()
    robot.arm.set_learning_mode(False)
    return robot


@pytest.fixture
def slowed(ready: Any) -> Any:
    """The robot at 10 % of its velocity: the move to FAR takes ~13.5 s instead of ~2.4, which
    a stop sent once the move is seen running cannot miss on a busy machine (at full speed
    it once arrived after the move had ended, beside a CPU burner on 4 workers)."""
    ready.arm.set_arm_max_velocity(10)
    return ready


def _exchange(host: str, *messages: dict[str, Any], replies: int) -> list[dict[str, Any]]:
    """Send rosbridge messages on a fresh WebSocket; the first ``replies`` answers that
    are not topic messages."""
    answers: list[dict[str, Any]] = []
    with connect(f"ws://{host}:9090", open_timeout=5) as ws:
        for m in messages:
            ws.send(json.dumps(m))
        while len(answers) < replies:
            answer = json.loads(ws.recv(timeout=5))
            if answer["op"] != "publish":
                answers.append(answer)
    return answers


def test_pyniryo2_connects_and_reads_the_robot_as_it_boots(robot: Any) -> None:
    assert robot.client.hardware_version == "ned2"
    assert robot.arm.get_joints() == pytest.approx(ned2.HOME.tolist())
    status = robot.arm.hardware_status()
    assert status.calibration_needed is True
    assert status.hardware_version == "ned2"
    assert len(status.motor_names) == len(status.motors_temperature) == 7
    assert robot.arm.get_learning_mode() is True  # a Ned2 boots compliant
    pose = robot.arm.get_pose().to_list()
    assert pose == pytest.approx(ned2.matrix_to_pose(ned2.forward(ned2.HOME)), abs=1e-9)


def test_calibration_learning_mode_and_velocity_through_the_rosbridge(
    robot: Any, sim: Ned2SimulatorHandle
) -> None:
    robot.arm.calibrate_auto()
    assert robot.arm.need_calibration() is False
    assert sim.state()["calibrated"] is True
    robot.arm.set_learning_mode(False)
    assert robot.arm.get_learning_mode() is False
    assert sim.state()["learning_mode"] is False
    robot.arm.set_arm_max_velocity(40)
    assert robot.arm.get_arm_max_velocity() == 40
    assert sim.state()["velocity_percent"] == 40


def test_moves_through_the_arm_commanders_action_arrive(
    ready: Any, sim: Ned2SimulatorHandle
) -> None:
    goal = [0.5, -0.3, 0.2, 0.3, -0.5, 0.4]
    ready.arm.move_joints(goal)
    assert sim.state()["joints"] == pytest.approx(goal, abs=1e-9)
    target = [0.25, -0.06, 0.18, 0.0, 1.2, 0.1]
    ready.arm.move_pose(target)
    pose = sim.state()["pose"]
    assert np.linalg.norm(np.array(pose[:3]) - target[:3]) < 1 * MM
    ready.arm.move_linear_pose([0.25, 0.06, 0.18, 0.0, 1.2, 0.1])
    assert sim.state()["pose"][1] == pytest.approx(0.06, abs=1 * MM)


def test_the_gripper_closes_and_opens_through_the_tools_commanders_action(
    ready: Any, sim: Ned2SimulatorHandle
) -> None:
    ready.tool.close_gripper()
    assert sim.state()["gripper_open"] is False
    ready.tool.open_gripper()
    assert sim.state()["gripper_open"] is True


def test_stop_command_stops_a_move_that_the_tcp_server_is_running(
    slowed: Any, sim: Ned2SimulatorHandle
) -> None:
    tcp = TcpClient(sim.host, verbose=False)
    errors: list[Exception] = []

    def move() -> None:
        try:
            tcp.move(JointsPosition(*FAR))
        except NiryoRobotException as exc:
            errors.append(exc)

    mover = threading.Thread(target=move)
    mover.start()
    try:
        sim.wait_for("moving", True)
        slowed.arm.stop_move()
        mover.join(30)
    finally:
        tcp.close_connection()
    assert len(errors) == 1
    assert "Error Code : -4" in str(errors[0])  # STOPPED
    state = sim.state()
    assert state["moving"] is False
    assert state["joints"] != pytest.approx(FAR)


def test_stop_command_preempts_a_move_of_the_arm_action(
    slowed: Any, sim: Ned2SimulatorHandle
) -> None:
    results: list[dict[str, Any]] = []
    done = threading.Event()

    def finished(result: dict[str, Any]) -> None:
        results.append(result)
        done.set()

    slowed.arm.move_joints(FAR, callback=finished)
    sim.wait_for("moving", True)
    slowed.arm.stop_move()
    assert done.wait(30)
    assert results[0]["status"] == -4
    assert sim.state()["joints"] != pytest.approx(FAR)


def test_a_service_nobody_offers_is_answered_as_rosbridge_answers(
    sim: Ned2SimulatorHandle,
) -> None:
    status, response = _exchange(
        sim.host,
        {"op": "call_service", "id": "c1", "service": "/fly", "args": {}},
        replies=2,
    )
    assert status == {
        "op": "status",
        "level": "error",
        "msg": "call_service InvalidServiceException: Service /fly does not exist",
        "id": "c1",
    }
    assert response["op"] == "service_response"
    assert response["result"] is False
    assert response["id"] == "c1"


def test_arguments_of_the_wrong_type_are_refused_and_change_nothing(
    sim: Ned2SimulatorHandle,
) -> None:
    _, response = _exchange(
        sim.host,
        {
            "op": "call_service",
            "id": "c2",
            "service": "/niryo_robot/learning_mode/activate",
            "args": {"value": "no"},
        },
        replies=2,
    )
    assert response["result"] is False
    assert "value" in response["values"]
    assert sim.state()["learning_mode"] is True


def test_topic_names_are_resolved_as_ros_resolves_them(sim: Ned2SimulatorHandle) -> None:
    with connect(f"ws://{sim.host}:9090", open_timeout=5) as ws:
        ws.send(json.dumps({"op": "subscribe", "id": "s1", "topic": "//joint_states/"}))
        message = json.loads(ws.recv(timeout=5))
    assert message["topic"] == "//joint_states/"  # under the name the client used
    assert message["msg"]["position"] == pytest.approx(ned2.HOME.tolist())


def test_a_power_loss_closes_the_rosbridge_and_the_restore_opens_it(
    sim: Ned2SimulatorHandle,
) -> None:
    with injected_faults("the robot goes dark"):
        sim.inject("power_loss")
    with pytest.raises(ConnectionRefusedError):  # nobody listens on 9090
        connect(f"ws://{sim.host}:9090", open_timeout=5).close()
    sim.inject("power_restore")
    robot = NiryoRobot(sim.host)
    try:
        assert robot.arm.need_calibration() is True
    finally:
        robot.end()


def test_pyniryo2_sets_and_reads_the_digital_pins_through_the_io_panel(
    robot: Any, sim: Ned2SimulatorHandle
) -> None:
    from pyniryo2.exceptions import RobotCommandException
    from pyniryo2.io.enums import PinID, PinState

    shown = threading.Event()

    def on_state(pins: list[Any]) -> None:
        if any(p.name == "DO1" and p.value for p in pins):
            shown.set()

    robot.io.get_digital_io_states.subscribe(on_state)
    try:
        robot.io.digital_write(PinID.DO1, PinState.HIGH)
        assert sim.state()["digital_out"]["DO1"] is True
        assert robot.io.digital_read(PinID.DO1) is True
        assert shown.wait(5.0)  # the IO panel's state topic shows it
    finally:
        robot.io.get_digital_io_states.unsubscribe()
    sim.set_input("DI2", 1)
    assert robot.io.digital_read(PinID.DI2) is True
    with pytest.raises(RobotCommandException, match="-114"):  # DIGITAL_IO_PANEL_ERROR
        robot.io.digital_write(PinID.DI2, PinState.HIGH)  # an input cannot be set
    assert sim.state()["digital_in"]["DI2"] is True
