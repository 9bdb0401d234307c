"""The control-script emulation, driven by the real ur_rtde RTDEControlInterface."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest
from rtde_control import RTDEControlInterface
from rtde_receive import RTDEReceiveInterface
from waiting import wait_until

from fxcell.errors import SimulatorError
from fxcell.link.embedded import SimulatorState
from fxcell.testing import SimulatorHandle, simulator

from .test_sim_primary import Messages
from .test_sim_rtde import dh_forward, rotvec_matrix

START = [0.0, -1.2, 1.2, -1.57, -1.57, 0.0]  # tool down, well inside the workspace


def fresh(r: RTDEReceiveInterface) -> RTDEReceiveInterface:
    """The receive client once it holds a sample from after this call (two cycles later):
    the control client may learn that a command is done a moment before it does."""
    t = r.getTimestamp()
    wait_until(lambda: r.getTimestamp() >= t + 0.004, what="a fresh sample")
    return r


def matrix_rotvec(R: np.ndarray) -> list[float]:
    angle = math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2)))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return (axis / (2 * math.sin(angle)) * angle).tolist()


def pose_matrix(pose: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotvec_matrix(pose[3:])
    T[:3, 3] = pose[:3]
    return T


@dataclass
class Robot:
    sim: SimulatorHandle
    c: RTDEControlInterface
    r: RTDEReceiveInterface

    def ensure_running(self) -> None:
        if not self.c.isProgramRunning():
            self.c.reuploadScript()
            wait_until(self.c.isProgramRunning, what="the control script")


@pytest.fixture(scope="module")
def robot() -> Iterator[Robot]:
    with simulator() as sim:
        sim.set_joints(START)
        sim.bring_up()
        c = RTDEControlInterface(sim.host)
        r = RTDEReceiveInterface(sim.host)
        try:
            yield Robot(sim, c, r)
        finally:
            c.stopScript()
            c.disconnect()
            r.disconnect()


@pytest.fixture
def ready(robot: Robot) -> Robot:
    robot.ensure_running()
    assert robot.c.moveJ(START, 3.0, 20.0)
    return robot


def test_the_control_ports_state_has_the_one_schema(ready: Robot) -> None:
    state = ready.sim.state()
    assert set(state) == SimulatorState.__required_keys__
    assert state["control_script"] is True  # ur_rtde's control script is running
    assert state["robot_mode"] == "RUNNING"


def test_movej_reaches_the_target_on_a_trapezoid(ready: Robot) -> None:
    target = [0.8, -1.0, 1.0, -1.3, -1.57, 0.4]
    t0 = time.monotonic()
    assert ready.c.moveJ(target, 1.0, 2.0)
    elapsed = time.monotonic() - t0
    assert fresh(ready.r).getActualQ() == target
    assert ready.r.getActualQd() == [0.0] * 6
    # leading joint 0.8 rad at v=1, a=2: two 0.5 s ramps (0.5 rad) + 0.3 s cruise
    assert 1.3 <= elapsed < 1.7


def test_movel_moves_the_tool_on_a_straight_line(ready: Robot) -> None:
    start = fresh(ready.r).getActualTCPPose()
    target = [start[0] + 0.08, start[1] - 0.05, start[2] + 0.04, *start[3:]]
    assert ready.c.moveL(target, 0.25, 1.0, True)
    a, b = np.asarray(start[:3]), np.asarray(target[:3])
    direction = (b - a) / np.linalg.norm(b - a)
    samples = 0
    while ready.c.getAsyncOperationProgressEx().isAsyncOperationRunning():
        p = np.asarray(ready.r.getActualTCPPose()[:3]) - a
        assert np.linalg.norm(p - direction * (p @ direction)) < 1e-6
        samples += 1
        time.sleep(0.01)
    assert samples > 20
    final = ready.r.getActualTCPPose()
    assert np.abs(np.asarray(final) - np.asarray(target)).max() < 1e-9


def test_movel_fk_and_movej_ik_reach_their_targets(ready: Robot) -> None:
    q = [0.3, -1.1, 1.3, -1.7, -1.57, 0.2]
    assert ready.c.moveL_FK(q, 0.3, 1.2)
    assert np.abs(np.asarray(fresh(ready.r).getActualQ()) - q).max() < 1e-9
    pose = ready.r.getActualTCPPose()
    assert ready.c.moveJ(START, 2.0, 4.0)
    assert ready.c.moveJ_IK(pose, 2.0, 4.0)
    assert np.abs(np.asarray(fresh(ready.r).getActualQ()) - q).max() < 1e-9
    lower = [pose[0], pose[1], pose[2] - 0.05, *pose[3:]]
    assert ready.c.moveL(lower, 0.2, 1.0)  # synchronous
    assert np.abs(np.asarray(fresh(ready.r).getActualTCPPose()) - lower).max() < 1e-9


def test_async_movej_reports_progress_then_finishes(ready: Robot) -> None:
    target = [0.5, -1.3, 1.1, -1.4, -1.57, 0.0]
    assert ready.c.moveJ(target, 1.0, 2.0, True)
    status = ready.c.getAsyncOperationProgressEx()
    assert status.isAsyncOperationRunning()
    assert ready.c.getAsyncOperationProgress() >= 0
    wait_until(lambda: not ready.c.getAsyncOperationProgressEx().isAsyncOperationRunning())
    assert ready.c.getAsyncOperationProgress() < 0
    assert fresh(ready.r).getActualQ() == target


def test_stopj_decelerates_a_running_move(ready: Robot) -> None:
    target = [1.5, -1.2, 1.2, -1.57, -1.57, 0.0]
    assert ready.c.moveJ(target, 1.0, 4.0, True)
    wait_until(lambda: abs(ready.r.getActualQd()[0]) > 0.99, what="cruise speed")
    t0 = time.monotonic()
    ready.c.stopJ(2.0)  # returns nothing
    elapsed = time.monotonic() - t0
    assert fresh(ready.r).getActualQd() == [0.0] * 6
    q0 = ready.r.getActualQ()[0]
    assert 0.0 < q0 < 1.5
    assert 0.4 <= elapsed < 0.9  # 1 rad/s at 2 rad/s²


def test_stopl_stops_an_async_movel(ready: Robot) -> None:
    p = ready.r.getActualTCPPose()
    target = [p[0] + 0.15, *p[1:]]
    assert ready.c.moveL(target, 0.1, 0.5, True)
    wait_until(lambda: ready.r.getActualTCPPose()[0] > p[0] + 0.02, what="motion")
    ready.c.stopL(1.0)
    assert fresh(ready.r).getActualQd() == [0.0] * 6
    stopped = ready.r.getActualTCPPose()[0]
    assert p[0] + 0.02 < stopped < target[0]
    assert not ready.c.getAsyncOperationProgressEx().isAsyncOperationRunning()


def test_servoj_tracks_with_lookahead_lag_and_settles_exactly(ready: Robot) -> None:
    c, r = ready.c, ready.r
    q0 = np.asarray(r.getActualQ())
    n = 400
    amplitude = 0.3
    lags = []
    for i in range(1, n + 1):
        t_start = c.initPeriod()
        s = 0.5 - 0.5 * math.cos(math.pi * i / n)  # smooth rest-to-rest ramp over 0.8 s
        setpoint = q0 + np.array([amplitude * s, -0.5 * amplitude * s, 0, 0, 0, amplitude * s])
        assert c.servoJ(setpoint.tolist(), 0.5, 0.5, 0.002, 0.1, 300)
        if i == n // 2:
            lags.append(setpoint[0] - r.getActualQ()[0])
        c.waitPeriod(t_start)
    last = setpoint
    assert 0.0 < lags[0] < 0.12  # behind the setpoint, by about the lookahead time
    kin_target = dh_forward(last.tolist())
    wait_until(lambda: r.getActualQd() == [0.0] * 6, timeout=3, what="rest")
    assert c.isSteady()
    reached = pose_matrix(r.getActualTCPPose())
    assert np.linalg.norm(reached[:3, 3] - kin_target[:3, 3]) <= 1e-5
    assert np.abs(np.asarray(r.getActualQ()) - last).max() < 1e-9
    assert c.servoStop(2.0)


def test_speedj_integrates_the_commanded_velocity_and_speedstop_brakes(ready: Robot) -> None:
    c, r = ready.c, ready.r
    start = r.getActualQ()[5]
    for _ in range(150):
        t_start = c.initPeriod()
        assert c.speedJ([0, 0, 0, 0, 0, 0.5], 2.0, 0.002)
        c.waitPeriod(t_start)
    assert r.getActualQd()[5] == pytest.approx(0.5)
    assert c.speedStop(5.0)
    assert fresh(r).getActualQd() == [0.0] * 6
    assert r.getActualQ()[5] - start > 0.1


def test_ik_fk_round_trip_and_tcp_offset(ready: Robot) -> None:
    c, r = ready.c, ready.r
    q = [0.4, -1.0, 1.4, -1.9, -1.4, 0.3]
    tcp = [0.01, -0.02, 0.15, 0.0, 0.0, -1.5708]
    expected = dh_forward(q) @ pose_matrix(tcp)
    fk = c.getForwardKinematics(q, tcp)
    assert np.abs(pose_matrix(fk) - expected).max() < 1e-9
    # getForwardKinematics(q) alone (and, in ur_rtde 1.6.5, with an all-zero TCP) sends no
    # TCP: the script then reads registers 6-11 as they are, like a real controller would.
    T = dh_forward(q)
    flange = [*T[:3, 3], *matrix_rotvec(T[:3, :3])]
    assert np.abs(np.asarray(c.getInverseKinematics(flange, START)) - q).max() < 1e-9
    assert c.getForwardKinematics() == fresh(r).getActualTCPPose()
    assert c.setTcp(tcp)
    wait_until(lambda: abs(r.getActualTCPPose()[2] - r.getTargetTCPPose()[2]) < 1e-12)
    expected_now = dh_forward(r.getActualQ()) @ pose_matrix(tcp)
    wait_until(
        lambda: np.abs(pose_matrix(r.getActualTCPPose()) - expected_now).max() < 1e-9,
        what="TCP pose with the new TCP",
    )
    assert c.poseTrans(flange, tcp) == pytest.approx(fk.copy(), abs=1e-12)
    assert c.setTcp([0.0] * 6)


def test_move_path_visits_each_waypoint_in_turn(ready: Robot) -> None:
    c, r = ready.c, ready.r
    path = [
        [0.2, -1.2, 1.2, -1.57, -1.57, 0.0, 1.5, 3.0, 0.0],
        [0.2, -1.0, 1.0, -1.57, -1.57, 0.0, 1.5, 3.0, 0.0],
        [-0.2, -1.1, 1.3, -1.6, -1.57, 0.1, 1.5, 3.0, 0.0],
    ]
    assert c.moveJ(path, True)
    seen = set()
    while c.getAsyncOperationProgressEx().isAsyncOperationRunning():
        seen.add(c.getAsyncOperationProgress())
        time.sleep(0.005)
    assert {0, 1, 2} <= seen
    assert np.abs(np.asarray(fresh(r).getActualQ()) - path[-1][:6]).max() < 1e-9
    p = r.getActualTCPPose()
    poses = [
        [p[0] + 0.03, *p[1:], 0.25, 1.2, 0.0],
        [p[0] + 0.03, p[1] + 0.03, *p[2:], 0.25, 1.2, 0.0],
    ]
    assert c.moveL(poses)  # a movel path, synchronous
    # ur_rtde writes path waypoints into the script with 6 significant digits
    assert np.abs(np.asarray(fresh(r).getActualTCPPose()) - poses[-1][:6]).max() < 1e-5


def test_payload_and_steady_state_are_reported(ready: Robot) -> None:
    c, r = ready.c, ready.r
    assert c.setPayload(1.2, [0.0, 0.01, 0.05])
    wait_until(lambda: r.getPayload() == 1.2, what="payload")
    assert r.getPayloadCog() == [0.0, 0.01, 0.05]
    assert c.isSteady()
    assert c.moveJ([0.6, -1.2, 1.2, -1.57, -1.57, 0.0], 0.5, 1.0, True)
    wait_until(lambda: any(v != 0 for v in r.getActualQd()), what="motion")
    assert not c.isSteady()
    c.stopJ(4.0)


@pytest.mark.injects_faults("the client starves the RTDE watchdog")
def test_watchdog_stops_the_program_when_the_client_starves_it(ready: Robot) -> None:
    c = ready.c
    # 5 Hz: starved after 200 ms without a kick. At 20 Hz (50 ms) a test process descheduled
    # between two of its kicks on a busy machine starved it while it was still kicking.
    assert c.setWatchdog(5.0)
    end = time.monotonic() + 0.4
    while time.monotonic() < end:
        assert c.kickWatchdog()
        time.sleep(0.02)
    assert c.isProgramRunning()
    wait_until(lambda: not c.isProgramRunning(), timeout=1.0, what="watchdog stop")
    assert "watchdog" in ready.sim.state()["last_stop_reason"]


def test_unsupported_command_stops_the_program_instead_of_hanging(ready: Robot) -> None:
    # circular servoing (command 12) is the one command of the script not modelled; the
    # client sends it as a real-time command and does not wait for it
    pose = fresh(ready.r).getActualTCPPose()
    ready.c.servoC(pose, 0.1, 0.5, 0.0)
    wait_until(lambda: not ready.c.isProgramRunning(), timeout=2.0, what="the program to stop")
    assert "not supported" in ready.sim.state()["last_stop_reason"]
    ready.c.kickWatchdog()  # command 0: a script started next does not find servoC waiting


def test_stop_script_ends_the_program(ready: Robot) -> None:
    ready.c.stopScript()
    assert not ready.c.isProgramRunning()
    assert ready.sim.dashboard("running") == "Program running: false"


def test_reupload_while_running_restarts_the_script(ready: Robot) -> None:
    assert ready.c.isProgramRunning()
    assert ready.c.reuploadScript()  # stopScript, dashboard "stop", upload again
    wait_until(ready.c.isProgramRunning, what="the new script")
    assert ready.c.moveJ([0.1, *START[1:]], 1.0, 2.0)


def test_force_mode_and_contact_moves_are_refused_and_the_script_stays_usable(
    ready: Robot,
) -> None:
    c = ready.c
    t0 = time.monotonic()
    c.forceMode([0.0] * 6, [0, 0, 1, 0, 0, 0], [0.0, 0.0, -10.0, 0.0, 0.0, 0.0], 2, [0.1] * 6)
    c.forceModeStop()
    c.moveUntilContact([0.0, 0.0, -0.02, 0.0, 0.0, 0.0])
    assert time.monotonic() - t0 < 10.0  # answered, never the client's 300 s wait
    assert c.isProgramRunning()
    assert c.moveJ([0.1, *START[1:]], 1.0, 2.0)  # the next command works
    assert np.allclose(fresh(ready.r).getActualQ(), [0.1, *START[1:]], atol=1e-9)
    log = ready.sim.state()["log"]
    for name in ("force_mode", "force_mode_stop", "move_until_contact"):
        assert any(f"{name} (command" in m and "not supported" in m for m in log), log


def tcp_speed_reaches(r: RTDEReceiveInterface, speed: list[float], what: str) -> None:
    wait_until(lambda: np.allclose(r.getActualTCPSpeed(), speed, atol=2e-4), timeout=3.0, what=what)


def test_jog_moves_the_tool_at_the_commanded_speed_in_the_base_tool_and_custom_frames(
    ready: Robot,
) -> None:
    c, r = ready.c, ready.r
    assert c.jogStart([0.03, 0.0, 0.0, 0.0, 0.0, 0.0], c.FEATURE_BASE, 1.0)
    tcp_speed_reaches(r, [0.03, 0, 0, 0, 0, 0], "jogging along base x")
    assert c.jogStart([0.0, -0.02, 0.0, 0.0, 0.0, 0.0], c.FEATURE_BASE, 1.0)  # a new speed
    tcp_speed_reaches(r, [0, -0.02, 0, 0, 0, 0], "jogging along base -y")
    assert c.jogStop()
    assert fresh(r).getActualQd() == [0.0] * 6
    assert c.isProgramRunning()

    tool = rotvec_matrix(fresh(r).getActualTCPPose()[3:])
    assert c.jogStart([0.0, 0.0, 0.02, 0.0, 0.0, 0.0], c.FEATURE_TOOL, 1.0)
    tcp_speed_reaches(r, [*(0.02 * tool[:, 2]), 0, 0, 0], "jogging along the tool's z")
    assert c.jogStop()

    turned = [0.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2]  # a frame turned 90 degrees about z
    assert c.jogStart([0.02, 0.0, 0.0, 0.0, 0.0, 0.0], c.FEATURE_CUSTOM, 1.0, turned)
    tcp_speed_reaches(r, [0, 0.02, 0, 0, 0, 0], "jogging along the custom frame's x")
    assert c.jogStop()
    assert fresh(r).getActualQd() == [0.0] * 6
    assert c.moveJ(START, 1.0, 2.0)  # the script goes on as before


def test_freedrive_mode_lets_a_hand_move_the_arm_along_its_free_axes_only(
    ready: Robot,
) -> None:
    c, r, sim = ready.c, ready.r, ready.sim
    with pytest.raises(SimulatorError, match="not in freedrive"):
        sim.push([0.01, 0.0, 0.0])
    assert c.freedriveMode()
    assert sim.state()["teach_mode"]
    assert c.getFreedriveStatus() == 0  # normal: no singularity nearby
    # as on the controller: the program keeps running and the robot mode stays RUNNING
    assert r.getRobotMode() == 7
    assert r.getRobotStatus() & 0b11 == 0b11
    m = Messages(sim.host, 30002)
    try:  # the primary interface's robot mode data says how: control mode TEACH (1)
        assert m.robot_state()[0][16] == 1
    finally:
        m.close()
    start = np.asarray(fresh(r).getActualTCPPose())
    sim.push([0.01, -0.01, 0.005])
    moved = np.asarray(fresh(r).getActualTCPPose())
    assert np.allclose(moved[:3] - start[:3], [0.01, -0.01, 0.005], atol=1e-9)
    assert c.endFreedriveMode()
    assert not sim.state()["teach_mode"]
    with pytest.raises(SimulatorError, match="not in freedrive"):
        sim.push([0.01, 0.0, 0.0])

    assert c.freedriveMode([0, 0, 1, 0, 0, 0], [0.0] * 6)  # only z is free
    start = np.asarray(fresh(r).getActualTCPPose())
    sim.push([0.01, 0.01, -0.01])
    moved = np.asarray(fresh(r).getActualTCPPose())
    assert np.allclose(moved - start, [0, 0, -0.01, 0, 0, 0], atol=1e-9)
    assert c.endFreedriveMode()
    assert c.moveJ(START, 1.0, 2.0)
