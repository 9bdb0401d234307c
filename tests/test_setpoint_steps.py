"""The per-cycle judge of recorded state streams (fxcell.testing.setpoint_steps)."""

from __future__ import annotations

from fxcell.link.follower import servo_omega
from fxcell.protocol import CONTROL_PERIOD, RobotMode, RobotState, RuntimeState, SafetyMode
from fxcell.testing.setpoint_steps import check_states

DT = CONTROL_PERIOD
ACCEL = (4.0, 4.0, 4.0, 8.0, 8.0, 8.0)
SPEED = (3.14, 3.14, 3.14, 6.28, 6.28, 6.28)
OMEGA = servo_omega(0.1, 300.0)


def stream(setpoints: list[float], stamps: list[int] | None = None) -> list[RobotState]:
    """servoJ's target, as the controller reports it, tracking ``setpoints`` on joint 1
    (one per control cycle); ``stamps`` picks the cycles that were sampled."""
    q = v = 0.0
    states = []
    for k, s in enumerate(setpoints):
        v += (OMEGA * OMEGA * (s - q) - 2 * OMEGA * v) * DT
        q += v * DT
        states.append(
            RobotState(
                timestamp=(k + 1) * DT,
                robot_mode=RobotMode.RUNNING,
                safety_mode=SafetyMode.NORMAL,
                runtime_state=RuntimeState.PLAYING,
                target_q=(q, 0, 0, 0, 0, 0),
                target_qd=(v, 0, 0, 0, 0, 0),
            )
        )
    if stamps is not None:
        states = [states[k] for k in stamps]
    return states


def ramp(n: int, speed: float) -> list[float]:
    return [speed * DT * k for k in range(n)]


def test_a_smooth_stream_is_within_the_limits() -> None:
    report = check_states(stream(ramp(50, 0.0) + [0.0] * 10), ACCEL, SPEED)
    assert report.cycles > 50
    assert report.over == []


def test_a_setpoint_jump_is_a_step_beyond_the_limits() -> None:
    path = ramp(100, 0.5)
    path[60:] = [p + 0.01 for p in path[60:]]  # a jump by five samples
    report = check_states(stream(path), ACCEL, SPEED)
    assert report.over
    assert report.over[0].joint == 0
    assert report.worst_ratio > 1.4  # ω²·0.01 rad ≈ 4 rad/s² on top of the ramp


def test_cycles_on_a_held_setpoint_are_counted_apart() -> None:
    path = ramp(100, 1.0)
    held = path[:50] + [path[49]] * 10 + path[60:]  # the link sent nothing for 20 ms
    report = check_states(stream(held), ACCEL, SPEED)
    assert report.held >= 9
    assert report.worst_held_ratio > 1.05


def test_cycles_across_a_gap_in_the_controller_clock_are_left_out() -> None:
    stamps = [k for k in range(100) if not 40 < k < 45]  # the controller skipped four
    report = check_states(stream(ramp(100, 1.0), stamps), ACCEL, SPEED)
    assert report.gaps == 1
    assert report.cycles == len(stamps) - 2
