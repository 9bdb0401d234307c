"""The seed's fx_* functions: synchronous, booleans and values as the thesis specifies."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator

import pytest

from fxcell import compat
from fxcell.config import CellConfig
from fxcell.testing import SimulatorHandle, simulator

WORK = [0.4, -1.4, 1.6, -1.8, -1.57, 0.0]


@pytest.fixture(scope="module")
def connected() -> Iterator[SimulatorHandle]:
    with simulator() as sim:
        sim.set_joints(WORK)
        assert compat.fx_connect(sim.host) is True
        try:
            yield sim
        finally:
            compat.fx_close()


def test_general_functions_return_the_seed_values(connected: SimulatorHandle) -> None:
    assert compat.fx_get_robot_mode() == "POWER_OFF"
    assert compat.fx_is_in_remote_control() is True
    assert compat.fx_unlock_protective_stop() is False  # not in a protective stop
    assert compat.fx_power_on() is True
    assert compat.fx_get_robot_mode() == "IDLE"
    assert compat.fx_brake_release() is True
    assert compat.fx_get_robot_mode() == "RUNNING"
    assert compat.fx_start_external_control() is True
    assert compat.fx_get_program_state().state == "PLAYING"
    assert compat.fx_stop_external_control() is True
    assert compat.fx_get_program_state().state == "STOPPED"
    assert compat.fx_power_off() is True
    assert compat.fx_get_robot_mode() == "POWER_OFF"
    assert compat.fx_init() is True
    assert compat.fx_init() is True  # idempotent
    assert compat.fx_get_robot_mode() == "RUNNING"
    assert connected.state()["runtime_state"] == "PLAYING"


def test_queries_return_plain_lists(connected: SimulatorHandle) -> None:
    q = compat.fx_get_current_joint_values()
    assert q == pytest.approx(WORK, abs=1e-6)
    pose = compat.fx_get_current_pose()
    assert len(pose) == 7
    assert math.isclose(sum(v * v for v in pose[3:]), 1.0, abs_tol=1e-9)
    rpy = compat.fx_get_current_rpy()
    assert compat.fx_get_current_pose_rpy() == pytest.approx(pose[:3] + rpy)
    assert compat.fx_get_velocity() == [0.0] * 6
    assert compat.fx_get_max_acceleration() == list(CellConfig.load().limits.acceleration)


def test_scaling_factors_accept_only_the_unit_interval(connected: SimulatorHandle) -> None:
    assert compat.fx_set_velocity_factor(0.5) is True
    assert compat.fx_get_velocity_scaling_factor() == 0.5
    for bad in (0, -0.1, 1.5, math.nan, "x"):
        assert compat.fx_set_velocity_factor(bad) is False  # type: ignore[arg-type]
        assert compat.fx_set_acceleration_factor(bad) is False  # type: ignore[arg-type]
    assert compat.fx_get_velocity_scaling_factor() == 0.5
    assert compat.fx_set_acceleration_factor(1.0) is True
    assert compat.fx_get_acceleration_scaling_factor() == 1.0


def test_moves_return_booleans(connected: SimulatorHandle) -> None:
    assert compat.fx_init() is True
    target = [WORK[0] + 0.2, *WORK[1:]]
    assert compat.fx_move_joint(target, 0.5, 0.5) is True
    assert compat.fx_get_current_joint_values() == pytest.approx(target, abs=1e-4)
    assert compat.fx_move_joint([0.0] * 5, 0.5) is False  # malformed: refused, not raised
    assert compat.fx_move_joint(WORK, 2.0) is False  # bad factor
    assert compat.fx_move_distance([0.0, 0.0, 0.02], 0.5, 0.5) is True
    assert compat.fx_move_joint(WORK, 0.5, 0.5) is True


def test_fx_stop_from_another_thread_stops_a_move(connected: SimulatorHandle) -> None:
    assert compat.fx_init() is True
    results: list[bool] = []
    mover = threading.Thread(
        target=lambda: results.append(compat.fx_move_joint([WORK[0] + 1.0, *WORK[1:]], 0.3, 0.5))
    )
    mover.start()
    deadline = time.monotonic() + 10
    while abs(compat.fx_get_velocity()[0]) < 0.05:
        assert time.monotonic() < deadline, "the move did not start"
        time.sleep(0.01)
    assert compat.fx_stop() is True
    mover.join(10)
    assert results == [False]  # the move did not reach its target
    assert max(map(abs, compat.fx_get_velocity())) < 1e-3
    assert compat.fx_move_joint(WORK, 0.5, 0.5) is True


def test_gripper_functions_return_booleans_and_the_width(connected: SimulatorHandle) -> None:
    assert compat.fx_init() is True
    assert compat.fx_gripper_activate() is True
    assert compat.fx_gripper_move(0.03) is True
    assert compat.fx_get_gripper_width() == pytest.approx(0.03, abs=2e-4)
    assert compat.fx_gripper_move(0.08) is False  # beyond the 50 mm stroke: refused, logged
    assert compat.fx_gripper_close() is True
    assert compat.fx_get_gripper_width() == pytest.approx(0.0)
    assert compat.fx_gripper_open() is True
