"""The simulated Hand-E behind the Robotiq URCap socket (63352), seen by plain and PyPI clients."""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Iterator

import numpy as np
import pytest
from pyrobotiqur import RobotiqGripper
from pyrobotiqur.enums import GripperStatus, ObjectStatus
from waiting import controller_time_passed, wait_until

from fxcell.sim.gripper import ACTIVATION_TIME, STROKE, position_of, width_of
from fxcell.testing import TEST_TIME_SCALE, SimulatorHandle, simulator

PORT = 63352
CRUCIBLE_WIDTH = 0.032
# Three resting arm poses, tool down: where objects are picked, placed, and nothing lies.
PICK = [0.0, -1.2, 1.2, -1.57, -1.57, 0.0]
PLACE = [0.6, -1.1, 1.1, -1.57, -1.57, 0.0]
EMPTY = [-0.6, -1.3, 1.3, -1.57, -1.57, 0.0]


class Raw:
    """A plain-socket URCap client, to check the exact replies."""

    def __init__(self, host: str) -> None:
        self.sock = socket.create_connection((host, PORT), timeout=5)
        self.file = self.sock.makefile("rwb")

    def ask(self, line: str) -> str:
        self.file.write(line.encode() + b"\n")
        self.file.flush()
        return self.file.readline().decode().rstrip("\n")

    def get(self, name: str) -> int:
        reply = self.ask(f"GET {name}")
        key, value = reply.split()
        assert key == name
        return int(value)

    def activate(self) -> None:
        assert self.ask("SET ACT 0") == "ack"
        assert self.ask("SET ACT 1") == "ack"
        wait_until(lambda: self.get("STA") == 3, what="activation")

    def go(self, pos: int, spe: int = 255, force: int = 100) -> None:
        assert self.ask(f"SET POS {pos} SPE {spe} FOR {force} GTO 1") == "ack"

    def wait_stopped(self) -> int:
        wait_until(lambda: self.get("OBJ") != 0, what="the fingers to stop")
        return self.get("OBJ")

    def close(self) -> None:
        self.file.close()
        self.sock.close()


@pytest.fixture(scope="module")
def sim() -> Iterator[SimulatorHandle]:
    with simulator() as s:
        s.bring_up()
        yield s


@pytest.fixture
def raw(sim: SimulatorHandle) -> Iterator[Raw]:
    client = Raw(sim.host)
    yield client
    client.close()


def tcp_position(sim: SimulatorHandle) -> np.ndarray:
    return np.array(sim.gripper()["tcp_pose"][:3])


def test_width_and_position_registers_map_the_50_mm_stroke() -> None:
    assert width_of(0) == STROKE
    assert width_of(255) == 0.0
    for pos in range(256):
        assert position_of(width_of(pos)) == pos


def test_pypi_urcap_client_activates_moves_and_reads_the_gripper(sim: SimulatorHandle) -> None:
    g = RobotiqGripper(sim.host, port=PORT)
    with g:
        g.activate(poll_interval=0.01)
        assert g.get_status() == GripperStatus.ACTIVE
        pos, obj = g.move(128, speed=255, force=50)
        assert (pos, obj) == (128, ObjectStatus.AT_DEST)
        assert g.get_requested_position() == 128
        assert g.get_fault() == 0
        pos, obj = g.open(speed=255)
        assert (pos, obj) == (0, ObjectStatus.AT_DEST)
    assert sim.gripper()["width"] == pytest.approx(STROKE)


def test_replies_are_ack_and_var_value_and_unknown_requests_get_a_question_mark(
    raw: Raw,
) -> None:
    assert raw.ask("SET SPE 12 FOR 34") == "ack"
    assert raw.ask("GET SPE") == "SPE 12"
    assert raw.ask("GET FOR") == "FOR 34"
    assert raw.ask("GET XYZ") == "?"
    assert raw.ask("SET POS") == "?"
    assert raw.ask("HELLO") == "?"


def test_activation_takes_time_and_moves_only_once_active(raw: Raw) -> None:
    assert raw.ask("SET ACT 0") == "ack"
    assert raw.get("STA") == 0
    raw.go(200)  # not active: ignored
    assert raw.ask("SET ACT 1") == "ack"
    assert raw.get("STA") in (1, 3)
    wait_until(lambda: raw.get("STA") == 3, what="activation")
    assert raw.get("PRE") == 200
    raw.go(0)
    assert raw.wait_stopped() == 3


def test_finger_motion_takes_the_time_of_its_speed(raw: Raw) -> None:
    raw.activate()
    raw.go(0)
    raw.wait_stopped()
    start = time.monotonic()
    raw.go(255, spe=0)  # 20 mm/s over 50 mm: 2.5 s before time scaling
    assert raw.wait_stopped() == 3
    elapsed = time.monotonic() - start
    assert elapsed >= 0.9 * 2.5 * TEST_TIME_SCALE
    assert raw.get("POS") == 255


def test_closing_on_nothing_closes_fully_with_obj_3(sim: SimulatorHandle, raw: Raw) -> None:
    sim.set_joints(EMPTY)
    raw.activate()
    raw.go(255)
    assert raw.wait_stopped() == 3
    assert raw.get("POS") == 255
    assert sim.gripper()["held"] is None


def test_picked_object_moves_with_the_tcp_and_stays_where_released(
    sim: SimulatorHandle, raw: Raw
) -> None:
    sim.set_joints(PICK)
    raw.activate()
    raw.go(0)
    raw.wait_stopped()
    start = tcp_position(sim)
    sim.add_object(
        "crucible_a", "crucible", width=CRUCIBLE_WIDTH, height=0.04, mass=0.05, position=start
    )
    raw.go(255)
    assert raw.wait_stopped() == 2  # stopped on an object while closing
    assert raw.get("POS") == position_of(CRUCIBLE_WIDTH)
    assert sim.gripper()["held"] == "crucible_a"

    sim.set_joints(PLACE)
    target = tcp_position(sim)
    assert np.linalg.norm(target - start) > 0.1
    wait_until(
        lambda: np.linalg.norm(np.array(sim.objects()["crucible_a"]["pose"][:3]) - target) < 1e-3,
        what="the held crucible to follow the TCP",
    )
    raw.go(0)
    assert raw.wait_stopped() == 3
    assert sim.gripper()["held"] is None
    sim.set_joints(EMPTY)
    controller_time_passed(sim, 0.05)  # 25 cycles in which a held crucible would follow
    placed = sim.objects()["crucible_a"]
    assert not placed["held"]
    assert np.linalg.norm(np.array(placed["pose"][:3]) - target) < 1e-3


def test_injected_fault_stops_the_fingers_until_reactivated(sim: SimulatorHandle, raw: Raw) -> None:
    sim.set_joints(EMPTY)
    raw.activate()
    raw.go(0)
    raw.wait_stopped()
    raw.go(255, spe=0)  # a full stroke takes 2.5 s (scaled)
    wait_until(lambda: raw.get("POS") > 0, what="the fingers to start closing")
    sim.inject("gripper_fault", "0x0E")
    assert raw.get("FLT") == 0x0E
    stopped = raw.get("POS")
    controller_time_passed(sim, 2.5 * TEST_TIME_SCALE)  # the rest of the stroke, and more
    assert raw.get("POS") == stopped < 255
    assert raw.get("OBJ") == 0
    raw.activate()
    assert raw.get("FLT") == 0


def test_dropped_object_stays_and_the_fingers_close_on(sim: SimulatorHandle, raw: Raw) -> None:
    sim.set_joints(PICK)
    raw.activate()
    raw.go(0)
    raw.wait_stopped()
    where = tcp_position(sim) + np.array([0.0, 0.0, 1e-3])  # within the grasp tolerance
    sim.add_object("bead_a", "glass_bead", width=0.02, height=0.02, mass=0.01, position=where)
    raw.go(255)
    assert raw.wait_stopped() == 2
    assert sim.inject("gripper_drop") == "bead_a dropped"
    assert raw.wait_stopped() == 3
    assert raw.get("POS") == 255
    sim.set_joints(EMPTY)
    controller_time_passed(sim, 0.05)  # 25 cycles in which a held bead would follow
    bead = sim.objects()["bead_a"]
    assert not bead["held"]
    assert math.dist(bead["pose"][:3], where) < 1e-6
    raw.go(0)
    raw.wait_stopped()
    sim.add_object("bead_a", "glass_bead", width=0.02, height=0.02, mass=0.01, position=[0, 0, 5])


def test_without_tool_power_the_gripper_loses_and_cannot_regain_activation(
    sim: SimulatorHandle, raw: Raw
) -> None:
    raw.activate()
    sim.dashboard("power off")
    sim.wait_for("robot_mode", "POWER_OFF")
    wait_until(lambda: raw.get("STA") == 0, what="the activation to be lost")
    assert raw.ask("SET ACT 1") == "ack"
    controller_time_passed(sim, 3 * ACTIVATION_TIME * TEST_TIME_SCALE)  # 3 activations' time
    assert raw.get("STA") != 3
    sim.bring_up()
    raw.activate()
