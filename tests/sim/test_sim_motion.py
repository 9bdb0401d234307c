"""The simulator's motion model and script parsing, in process (no sockets)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.motion.kinematics import Kinematics
from fxcell.sim.motion import (
    JOINT_SPEED_LIMIT,
    Arm,
    JointMove,
    SafetyLimitError,
    ServoTrack,
    Stop,
    TableGuard,
    _profile,
    _trapezoid,
)
from fxcell.sim.script import is_control_script, parse_move_path

START = [0.0, -1.2, 1.2, -1.57, -1.57, 0.0]
DT = 0.002


def arm(q: list[float] = START) -> Arm:
    return Arm(Kinematics.ur3e(), q, make_kinematics=Kinematics.ur3e)


@given(
    distance=st.floats(1e-4, 10.0),
    v=st.floats(0.01, 6.0),
    a=st.floats(0.01, 40.0),
)
def test_trapezoid_is_rest_to_rest_within_its_limits(distance: float, v: float, a: float) -> None:
    ta, tc, vp = _trapezoid(distance, v, a)
    end = 2 * ta + tc
    assert vp <= v * (1 + 1e-12)
    assert _profile(end, ta, tc, vp, a)[0] == pytest.approx(distance, rel=1e-9)
    for t in np.linspace(0, end, 23):
        s, sd, sdd = _profile(float(t), ta, tc, vp, a)
        assert -1e-12 <= s <= distance * (1 + 1e-9)
        assert -1e-12 <= sd <= vp + 1e-12
        assert abs(sdd) <= a + 1e-12


@settings(max_examples=25, deadline=None)
@given(target=st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6))
def test_movej_ends_exactly_on_target_without_exceeding_joint_speeds(target: list[float]) -> None:
    a = arm()
    move = JointMove(a, target, 3.0, 10.0)
    a.run(move)
    for _ in range(int(move.duration / DT) + 2):
        assert a.step(DT) is None
        assert np.all(np.abs(a.qd) <= JOINT_SPEED_LIMIT + 1e-9)
    assert a.q.tolist() == target
    assert move.token.done
    assert move.token.failed is None


def test_servo_tracking_lags_by_the_lookahead_and_settles_exactly() -> None:
    a = arm()
    servo = ServoTrack(a)
    a.run(servo)
    q0 = np.asarray(START)
    speed = 0.5  # rad/s on joint 0
    now = 0.0
    for i in range(1, 501):
        now += DT
        servo.command(a, q0 + np.array([speed * i * DT, 0, 0, 0, 0, 0]), DT, 0.1, 300, now)
        a.step(DT)
    lag = q0[0] + speed * 500 * DT - a.q[0]
    assert lag == pytest.approx(speed * 0.1, rel=0.05)  # lag ≈ lookahead time at 300 gain
    last = servo.setpoint.copy()
    for _ in range(600):  # hold the last setpoint (the motion stopped abruptly) for 1.2 s
        a.step(DT)
    assert a.q.tolist() == last.tolist()
    assert not a.moving


def test_servo_jump_far_beyond_the_speed_limit_is_a_violation() -> None:
    a = arm()
    servo = ServoTrack(a)
    a.run(servo)
    with pytest.raises(SafetyLimitError, match="joint 0 commanded at"):
        servo.command(a, [0.3, *START[1:]], DT, 0.1, 300, 0.0)
    servo.command(a, [0.01, *START[1:]], DT, 0.1, 300, 0.0)  # within 1.5x over 8 ms


def test_a_backlog_of_setpoints_drained_at_once_is_judged_over_the_cycles_it_spans() -> None:
    # 25 setpoints of a 1 rad/s stream that a late receiver hands over in one cycle: the
    # newest is 25 client cycles (50 ms) ahead of the last one taken, 2 ms of wall time later
    a = arm()
    servo = ServoTrack(a)
    a.run(servo)
    ahead = [START[0] + 1.0 * 25 * DT, *START[1:]]
    servo.command(a, START, DT, 0.1, 300, 0.0)
    servo.command(a, ahead, DT, 0.1, 300, DT, packets=25)
    # the same step in one packet is a jump at 6.25 rad/s (over the 8 ms floor)
    b = arm()
    single = ServoTrack(b)
    b.run(single)
    single.command(b, START, DT, 0.1, 300, 0.0)
    with pytest.raises(SafetyLimitError, match=r"joint 0 commanded at 6\.25 rad/s"):
        single.command(b, ahead, DT, 0.1, 300, DT)


def test_the_control_script_credits_every_packet_since_the_setpoint_it_last_took() -> None:
    from fxcell.protocol import SafetyMode
    from fxcell.sim.controller import Controller
    from fxcell.sim.script import _SERVOJ, ControlScript

    def stream(packets_last: int) -> SafetyMode:
        c = Controller(arm())
        script = ControlScript(c, "")
        regs = c.registers
        regs.in_int[0] = _SERVOJ
        regs.in_double[8:11] = [DT, 0.1, 300.0]

        def send(q: list[float], packets: int) -> None:
            regs.in_double[0:6] = q
            c.input_generation += packets
            script.step()

        send(START, 1)
        send([START[0] + 1.0 * 25 * DT, *START[1:]], packets_last)
        return c.safety_mode

    assert stream(25) == SafetyMode.NORMAL  # a backlog of the 500 Hz stream: no violation
    assert stream(1) == SafetyMode.PROTECTIVE_STOP  # one packet jumping as far: a violation


def test_stop_decelerates_every_joint_together() -> None:
    a = arm()
    a.set_state(a.q, np.array([1.0, -0.5, 0.25, 0.0, 0.0, 2.0]), None)
    a.run(Stop(a, 2.0))
    ratios = []
    for _ in range(600):
        a.step(DT)
        if a.moving:
            ratios.append(a.qd[5] / a.qd[0])
    assert not a.moving
    assert ratios == pytest.approx([2.0] * len(ratios))
    assert len(ratios) == pytest.approx(2.0 / 2.0 / DT, abs=2)  # 2 rad/s at 2 rad/s²


def test_table_guard_finds_the_link_in_the_table() -> None:
    kin = Kinematics.ur3e()
    guard = TableGuard((-0.075, -0.065, -0.02), (1.15, 0.73, 0.04))
    hit, clearance = guard.check(kin.joint_frames(START))
    assert hit is None
    assert clearance > 0.05
    hit, _ = guard.check(kin.joint_frames([0.0, 0.6, 0.5, -1.57, -1.57, 0.0]))
    assert hit in ("forearm", "wrist 1", "wrist 2", "wrist 3", "tool")


def test_move_path_and_control_script_are_recognised() -> None:
    text = (
        "def rtde_control():\n    def rtde_cmd():\n        return 0\n    end\n"
        '    def exec_move_path():\n        textmsg("exec_move_path")\n'
        "        # inject move path\n\tsignal_async_progress(0)\n"
        "\tmovej([0.1,-1.2,1.2,-1.57,-1.57,0],a=1.4,v=1.05,r=0)\n"
        "\tsignal_async_progress(1)\n"
        "\tmovel(p[-0.3,-0.2,0.3,2.2,2.2,0],a=1.2,v=0.25,r=0.01)\n    end\nend\n"
    )
    assert is_control_script(text)
    assert not is_control_script("def other():\n  textmsg(1)\nend\n")
    assert parse_move_path(text) == [
        ("movej", [0.1, -1.2, 1.2, -1.57, -1.57, 0.0], 1.4, 1.05),
        ("movel", [-0.3, -0.2, 0.3, 2.2, 2.2, 0.0], 1.2, 0.25),
    ]


def test_joint_limits_are_the_ur3e_maxima() -> None:
    assert JOINT_SPEED_LIMIT.tolist() == [math.pi] * 3 + [2 * math.pi] * 3


def test_the_launcher_agrees_with_the_simulator_on_faults_and_ports() -> None:
    from fxcell.link import embedded
    from fxcell.sim import controller, server

    assert embedded.FAULTS == controller.FAULTS
    assert embedded.CONTROL_PORT == server.CONTROL_PORT
    assert set(embedded.PORTS) == set(server.PORTS)
