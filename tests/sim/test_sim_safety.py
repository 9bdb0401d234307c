"""Safety stops and injected faults, as the real ur_rtde clients observe them."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
from dashboard_client import DashboardClient
from rtde_control import RTDEControlInterface
from rtde_receive import RTDEReceiveInterface

from fxcell.testing import SimulatorHandle

from .test_sim_control import START, fresh, wait_until

# every test here makes a safety stop or a fault of the controller and checks how it is seen
pytestmark = pytest.mark.injects_faults("the controller's safety stops and faults under test")

PROTECTIVE_STOP, SAFEGUARD_STOP, ROBOT_EMERGENCY_STOP = 3, 5, 7
POWER_OFF, RUNNING = 3, 7
STOPPED, PLAYING, PAUSED = 1, 2, 4


@dataclass
class Clients:
    sim: SimulatorHandle
    c: RTDEControlInterface
    r: RTDEReceiveInterface

    def restart_program(self) -> None:
        self.c.reuploadScript()
        wait_until(self.c.isProgramRunning, what="the control script")


@pytest.fixture
def clients(sim: SimulatorHandle) -> Iterator[Clients]:
    sim.set_joints(START)
    sim.bring_up()
    c = RTDEControlInterface(sim.host)
    r = RTDEReceiveInterface(sim.host)
    try:
        yield Clients(sim, c, r)
    finally:
        c.disconnect()
        r.disconnect()


def test_protective_stop_unlock_after_5_s_then_reupload_moves_again(clients: Clients) -> None:
    # judged on the controller's own clock (a simulator starved by a busy machine keeps
    # its rule on its own time): the stop came after `before`, and was seen at `seen`
    c, r = clients.c, clients.r

    def controller_time() -> float:
        return float(clients.sim.state()["time"])

    q = r.getActualQ()
    jump = [q[0] + 0.3, *q[1:]]  # 150 rad/s if done in one 2 ms servo step
    before = controller_time()
    c.servoJ(jump, 0.5, 0.5, 0.002, 0.1, 300)
    wait_until(r.isProtectiveStopped, what="protective stop")
    seen = controller_time()
    assert r.getSafetyMode() == PROTECTIVE_STOP
    assert r.getSafetyStatusBits() & 1 << 2
    assert r.getRuntimeState() == STOPPED
    assert not c.moveJ([0.2, *START[1:]], 1.0, 1.0)
    d = DashboardClient(clients.sim.host)
    d.connect()
    try:
        with pytest.raises(RuntimeError, match="Cannot unlock protective stop until 5s"):
            d.unlockProtectiveStop()
        while True:
            asked = controller_time()
            try:
                d.unlockProtectiveStop()
                break
            except RuntimeError:
                # refused, though asked 5 s after the stop or later
                assert asked - seen < 5.0, f"unlock refused {asked - seen:.2f} s after the stop"
                time.sleep(0.1)
        # released no earlier than 5 s after the stop
        assert controller_time() - before >= 5.0
    finally:
        d.disconnect()
    wait_until(lambda: r.getSafetyMode() == 1, what="NORMAL")
    clients.restart_program()
    assert c.moveJ([0.2, *START[1:]], 1.0, 1.0)
    assert fresh(r).getActualQ()[0] == pytest.approx(0.2, abs=1e-12)


def test_a_link_entering_the_table_is_a_protective_stop(clients: Clients) -> None:
    c, r = clients.c, clients.r
    into_table = [0.0, 0.6, 0.5, -1.57, -1.57, 0.0]  # upper arm and forearm point down
    assert not c.moveJ(into_table, 1.0, 2.0)
    wait_until(lambda: r.getSafetyMode() == PROTECTIVE_STOP, what="protective stop")
    assert "entered the table" in clients.sim.state()["last_stop_reason"]
    wait_until(lambda: r.getActualQd() == [0.0] * 6, what="rest after the stop")
    assert r.getActualQ()[1] < 0.6


def test_injected_protective_stop_is_seen_by_every_client(clients: Clients) -> None:
    sim, c, r = clients.sim, clients.c, clients.r
    assert c.moveJ([0.6, *START[1:]], 0.5, 1.0, True)
    sim.inject("protective_stop")
    wait_until(r.isProtectiveStopped, what="protective stop")
    assert r.getSafetyStatusBits() == 1 << 2 | 1 << 10
    assert sim.dashboard("safetystatus") == "Safetystatus: PROTECTIVE_STOP"
    assert sim.dashboard("robotmode") == "Robotmode: RUNNING"
    wait_until(lambda: r.getActualQd() == [0.0] * 6, what="rest")
    assert 0.0 < r.getActualQ()[0] < 0.6
    # the control interface reads the state in a thread of its own: its view may lag r's
    wait_until(lambda: not c.isProgramRunning(), what="the control interface sees no program")
    assert not c.moveJ(START, 1.0, 1.0)
    assert sim.dashboard("unlock protective stop").startswith("Cannot unlock protective stop")


def test_the_program_can_trigger_a_protective_stop(clients: Clients) -> None:
    assert not clients.c.triggerProtectiveStop()  # the command never completes
    wait_until(clients.r.isProtectiveStopped, what="protective stop")
    assert "called by the program" in clients.sim.state()["last_stop_reason"]


def test_speedj_far_beyond_the_joint_limit_is_a_protective_stop(clients: Clients) -> None:
    clients.c.speedJ([0, 0, 0, 0, 0, 20.0], 1.0, 0.002)
    wait_until(clients.r.isProtectiveStopped, what="protective stop")
    assert "speed limit" in clients.sim.state()["last_stop_reason"]


def test_safeguard_stop_pauses_and_release_plus_play_resumes(clients: Clients) -> None:
    sim, c, r = clients.sim, clients.c, clients.r
    sim.inject("safeguard_stop")
    wait_until(lambda: r.getSafetyMode() == SAFEGUARD_STOP)
    assert r.getRuntimeState() == PAUSED
    # the control interface reads the state in a thread of its own: its view may lag r's
    wait_until(lambda: not c.isProgramRunning(), what="the control interface sees it paused")
    assert not c.moveJ([0.2, *START[1:]], 1.0, 1.0)
    assert sim.dashboard("play") == "Failed to execute: play"
    sim.inject("safeguard_stop_release")
    wait_until(lambda: r.getSafetyMode() == 1)
    assert sim.dashboard("play") == "Starting program"
    wait_until(c.isProgramRunning)
    assert c.moveJ([0.2, *START[1:]], 1.0, 1.0)


def test_stop_program_and_power_loss_stop_the_script(clients: Clients) -> None:
    sim, c, r = clients.sim, clients.c, clients.r
    sim.inject("stop_program")
    wait_until(lambda: r.getRuntimeState() == STOPPED)
    # the control client's own receive thread may see that sample a moment after r's
    wait_until(lambda: not c.isProgramRunning())
    assert not c.moveJ([0.2, *START[1:]], 1.0, 1.0)
    clients.restart_program()
    assert c.moveJ([0.2, *START[1:]], 1.0, 1.0, True)
    sim.inject("power_loss")
    wait_until(lambda: r.getRobotMode() == POWER_OFF)
    assert r.getRuntimeState() == STOPPED
    assert r.getActualQd() == [0.0] * 6
    assert r.getRobotStatus() & 1 == 0
    assert sim.dashboard("robotmode") == "Robotmode: POWER_OFF"


def test_emergency_stop_powers_off_until_released(clients: Clients) -> None:
    sim, c, r = clients.sim, clients.c, clients.r
    sim.inject("emergency_stop")
    wait_until(lambda: r.getSafetyMode() == ROBOT_EMERGENCY_STOP)
    assert r.isEmergencyStopped()
    assert r.getRobotMode() == POWER_OFF
    assert r.getRuntimeState() == STOPPED
    sim.dashboard("power on")
    assert sim.dashboard("robotmode") == "Robotmode: POWER_OFF"
    sim.inject("emergency_stop_release")
    wait_until(lambda: r.getSafetyMode() == 1)
    sim.bring_up()
    clients.restart_program()
    assert c.moveJ([0.2, *START[1:]], 1.0, 1.0)


def test_local_control_refuses_the_control_interface_and_scripts(clients: Clients) -> None:
    sim, c = clients.sim, clients.c
    c.stopScript()
    sim.inject("local_control")
    with pytest.raises(RuntimeError, match="enable remote control"):
        RTDEControlInterface(sim.host)
    c.reuploadScript()  # the controller ignores scripts from the network in Local control
    with pytest.raises(AssertionError):
        wait_until(c.isProgramRunning, timeout=0.5)
    d = DashboardClient(sim.host)
    d.connect()
    try:
        assert not d.isInRemoteControl()
    finally:
        d.disconnect()
    sim.inject("remote_control")
    clients.restart_program()


RECEIVER = """
import sys, time
from rtde_receive import RTDEReceiveInterface
r = RTDEReceiveInterface(sys.argv[1])
print("connected", flush=True)
sys.stdin.readline()
t0 = time.monotonic()
while r.isConnected() and time.monotonic() - t0 < 10:
    time.sleep(0.01)
print("lost", round(time.monotonic() - t0, 2), flush=True)
print("reconnected", r.reconnect() and r.isConnected(), flush=True)
r.disconnect()
"""


@pytest.mark.parametrize(
    ("fault", "args", "lost_after"), [("drop_rtde", (), 0), ("stall_rtde", (3,), 2.5)]
)
def test_rtde_drop_and_stall_disconnect_the_receive_client(
    sim: SimulatorHandle, fault: str, args: tuple[object, ...], lost_after: float
) -> None:
    # a separate process: ur_rtde's reaction to a lost connection is not ours to risk
    proc = subprocess.Popen(
        [sys.executable, "-c", RECEIVER, sim.host],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdin is not None
        assert proc.stdout.readline().strip() == "connected"
        sim.inject(fault, *args)
        proc.stdin.write("go\n")
        proc.stdin.flush()
        lost = proc.stdout.readline().split()
        assert lost[0] == "lost"
        assert lost_after - 0.5 <= float(lost[1]) < lost_after + 1.5
        assert proc.stdout.readline().strip() == "reconnected True"
        assert proc.wait(10) == 0
    finally:
        proc.kill()
        proc.wait()
        for f in (proc.stdin, proc.stdout):
            if f is not None:
                f.close()


@pytest.mark.parametrize("delay", [5.0, 0.5])
def test_a_protective_stop_unlocks_after_its_delay_of_controller_time(delay: float) -> None:
    from fxcell.motion.kinematics import Kinematics
    from fxcell.protocol import CONTROL_PERIOD, SafetyMode
    from fxcell.sim.constants import UNLOCK_DELAY
    from fxcell.sim.controller import Controller
    from fxcell.sim.motion import Arm

    assert UNLOCK_DELAY == 5.0  # the real controller's rule, the simulator's default
    arm = Arm(Kinematics.ur3e(), START, make_kinematics=Kinematics.ur3e)
    c = Controller(arm) if delay == UNLOCK_DELAY else Controller(arm, unlock_delay=delay)
    c.protective_stop("a test")
    cycles = round(delay / CONTROL_PERIOD)
    c.tick(cycles - 1)
    assert c.unlock_protective_stop() is not None  # one cycle short of the delay: refused
    assert c.safety_mode == SafetyMode.PROTECTIVE_STOP
    c.tick()
    assert c.unlock_protective_stop() is None
    assert c.safety_mode == SafetyMode.NORMAL
