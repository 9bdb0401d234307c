"""The simulator's URScript subset: parser properties, the interpreter on an in-process
controller, and programs sent over the script ports of a simulator process."""

from __future__ import annotations

import math
import socket
import struct
import time
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.link.embedded import SimulatorState
from fxcell.motion.kinematics import Kinematics
from fxcell.protocol import RobotMode, RuntimeState
from fxcell.sim.controller import Controller
from fxcell.sim.events import RobotMessage
from fxcell.sim.motion import Arm
from fxcell.sim.primary import encode_robot_message
from fxcell.sim.urscript import (
    BinOp,
    Call,
    Const,
    ExprStmt,
    ListExpr,
    Name,
    Program,
    Unary,
    URScriptError,
    parse,
)
from fxcell.testing import SimulatorHandle, simulator

from .test_sim_primary import Messages
from .test_sim_rtde import nominal_dh_forward as dh_forward
from .test_sim_rtde import rotvec_matrix

START = [0.1, -1.2, 1.2, -1.57, -1.57, 0.3]

# ----------------------------------------------------------------------------- parser


def _render(node: object) -> str:
    """URScript source of an expression tree (fully parenthesised)."""
    if isinstance(node, Const):
        v = node.value
        if isinstance(v, bool):
            return "True" if v else "False"
        if isinstance(v, str):
            return '"' + v + '"'
        return repr(v)
    if isinstance(node, Name):
        return node.id
    if isinstance(node, ListExpr):
        return ("p" if node.pose else "") + "[" + ", ".join(_render(i) for i in node.items) + "]"
    if isinstance(node, BinOp):
        return f"({_render(node.left)} {node.op} {_render(node.right)})"
    if isinstance(node, Unary):
        return (
            f"({node.op} {_render(node.operand)})"
            if node.op == "not"
            else f"({node.op}{_render(node.operand)})"
        )
    if isinstance(node, Call):
        args = [_render(a) for a in node.args] + [f"{k}={_render(v)}" for k, v in node.kwargs]
        return f"{node.func}({', '.join(args)})"
    raise TypeError(node)


names = st.sampled_from(["x", "y", "speed", "q_near", "a1"])
consts = st.one_of(
    st.integers(0, 10**6).map(Const),
    st.floats(0, 1e6, allow_nan=False).map(Const),
    st.booleans().map(Const),
    st.text("abc XYZ_019", max_size=8).map(Const),
)
expressions = st.recursive(
    st.one_of(consts, names.map(Name)),
    lambda inner: st.one_of(
        st.builds(
            BinOp,
            st.sampled_from(["+", "-", "*", "/", "%", "==", "!=", "<", ">=", "and", "or"]),
            inner,
            inner,
        ),
        st.builds(Unary, st.sampled_from(["-", "not"]), inner),
        st.lists(inner, max_size=4).map(lambda items: ListExpr(tuple(items))),
        st.lists(inner, min_size=6, max_size=6).map(
            lambda items: ListExpr(tuple(items), pose=True)
        ),
        st.builds(
            Call,
            st.sampled_from(["movej", "textmsg", "f"]),
            st.lists(inner, max_size=3).map(tuple),
            st.lists(st.tuples(st.sampled_from(["a", "v"]), inner), max_size=1).map(tuple),
        ),
    ),
    max_leaves=12,
)


@settings(deadline=None)  # a busy 2-core machine must not fail on time
@given(expressions)
def test_rendered_expressions_parse_back_to_the_same_tree(expr: object) -> None:
    assert parse(_render(expr) + "\n") == (ExprStmt(expr),)  # type: ignore[arg-type]


arith = st.recursive(
    st.integers(-50, 50).map(Const),
    lambda inner: st.builds(BinOp, st.sampled_from(["+", "-", "*"]), inner, inner),
    max_leaves=10,
)


@settings(deadline=None)
@given(arith)
def test_integer_arithmetic_evaluates_as_python_does(expr: BinOp | Const) -> None:
    source = _render(expr)
    program = Program(make_controller(), f"x = {source}\n")
    assert program.step()
    assert program.error is None
    assert program.globals["x"] == eval(source)  # the same grammar for + - * on integers


@settings(deadline=None)
@given(st.text(max_size=40))
def test_arbitrary_text_parses_or_raises_a_located_error(text: str) -> None:
    try:
        parse(text)
    except URScriptError as exc:
        position = (exc.line, exc.column)
    else:
        return
    assert min(position) >= 1


def test_programs_with_blocks_parse_with_positions() -> None:
    body = parse(
        "def main():\n"
        "  global n = 0\n"
        "  while n < 3:\n"
        "    n = n + 1  # comment\n"
        "  end\n"
        "  if n == 3:\n"
        '    textmsg("three")\n'
        "  elif n > 3:\n"
        "    halt()\n"
        "  else:\n"
        "    movel(p[0.1, 0.2,\n 0.3, 0, 3.14, 0], a=1.2, v=0.25)\n"
        "  end\n"
        "end\n"
    )
    assert len(body) == 1
    with pytest.raises(URScriptError) as info:
        parse("def main():\n  x = (1 + \nend\n")
    assert info.value.line == 3


# ----------------------------------------------------------------------------- interpreter


def make_controller(q: list[float] = START) -> Controller:
    kin = Kinematics.ur3e()
    arm = Arm(kin, q, make_kinematics=lambda tcp: Kinematics.ur3e(tcp))
    c = Controller(arm)
    c.robot_mode = RobotMode.RUNNING
    return c


def run(
    c: Controller, text: str, until: Callable[[], bool] | None = None, cycles: int = 5000
) -> None:
    """Start ``text`` on ``c`` and tick until it stops (or ``until``)."""
    assert c.run_script(text)
    c.tick(int(0.4 / 0.002))  # the program start delay
    for _ in range(cycles):
        if (until or (lambda: c.runtime_state == RuntimeState.STOPPED))():
            return
        c.tick()
    raise AssertionError(f"program did not finish; log {c.log_messages}")


def test_movej_reaches_joint_and_pose_targets() -> None:
    c = make_controller()
    target = [0.3, -1.3, 1.25, -1.5, -1.57, 0.2]
    run(c, f"def main():\n  movej({target}, a=3, v=2)\nend\n")
    assert np.allclose(c.arm.q, target, atol=1e-12)
    pose = Kinematics.ur3e().forward(np.array(START)).as_ur()
    run(c, f"movej(p{list(pose)}, a=3, v=2)\n")
    assert np.allclose(c.arm.q, START, atol=1e-6)
    assert c.last_stop_reason == "program finished"


def test_movel_keeps_the_tool_on_the_straight_line() -> None:
    c = make_controller()
    start = Kinematics.ur3e().forward(np.array(START))
    goal = list(start.as_ur())
    goal[0] += 0.08
    goal[2] -= 0.05
    assert c.run_script(f"movel(p{goal}, a=1.0, v=0.2)\n")
    c.tick(200)
    a, b = start.position, np.array(goal[:3])
    worst = 0.0
    for _ in range(3000):
        c.tick()
        p = dh_forward(c.arm.q.tolist())[:3, 3]
        t = float(np.dot(p - a, b - a) / np.dot(b - a, b - a))
        worst = max(worst, float(np.linalg.norm(a + t * (b - a) - p)))
        if c.runtime_state == RuntimeState.STOPPED:
            break
    assert worst < 1e-6
    assert np.allclose(dh_forward(c.arm.q.tolist())[:3, 3], b, atol=1e-9)
    assert np.allclose(dh_forward(c.arm.q.tolist())[:3, :3], rotvec_matrix(goal[3:]), atol=1e-9)


def test_io_tcp_payload_textmsg_variables_and_functions() -> None:
    c = make_controller()
    run(
        c,
        "def main():\n"
        "  def twice(x, k=2):\n"
        "    return x * k\n"
        "  end\n"
        "  global count = 0\n"
        "  poses = [p[0, 0, 0.1, 0, 0, 0], p[0, 0, 0.05, 0, 0, 0]]\n"
        "  while count < twice(2):\n"
        "    count = count + 1\n"
        "  end\n"
        "  set_digital_out(2, True)\n"
        "  set_configurable_digital_out(1, True)\n"
        "  set_tool_digital_out(0, count == 4)\n"
        "  set_tcp(poses[1])\n"
        "  set_payload(1.5, [0, 0, 0.04])\n"
        '  textmsg("count ", count)\n'
        "  sleep(0.1)\n"
        "end\n",
    )
    assert c.io.output_bits == (1 << 2) | (1 << 9) | (1 << 16)
    assert c.tcp == (0.0, 0.0, 0.05, 0.0, 0.0, 0.0)
    assert (c.payload_mass, c.payload_cog) == (1.5, (0.0, 0.0, 0.04))
    assert "textmsg: count 4" in c.log_messages


def test_sleep_takes_controller_time() -> None:
    c = make_controller()
    assert c.run_script("sleep(0.5)\n")
    c.tick(200)
    t0 = c.time
    while c.runtime_state != RuntimeState.STOPPED:
        c.tick()
    assert 0.5 <= c.time - t0 <= 0.51


def test_stopj_brakes_the_moving_arm() -> None:
    c = make_controller()
    assert c.run_script("movej([1.5, -1.2, 1.2, -1.57, -1.57, 0.3], a=1, v=1)\n")
    for _ in range(400):
        c.tick()
    assert c.arm.moving
    c.program = None  # the move's program is gone; a new program brakes the arm with stopj
    c.runtime_state = RuntimeState.STOPPED
    run(c, "stopj(4.0)\n")
    assert not c.arm.moving
    assert c.arm.q[0] < 1.5


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            'def main():\n  textmsg("a")\n  not_a_function(1)\nend\n',
            "compile_error_name_not_found:not_a_function:",
        ),
        (
            "def main():\n  force_mode(p[0,0,0,0,0,0], [0,0,1,0,0,0], [0,0,9,0,0,0], 2, f)\nend\n",
            "force_mode is not supported",
        ),
    ],
)
def test_an_unknown_function_stops_the_program_as_a_compile_error(text: str, message: str) -> None:
    c = make_controller()
    sent: list[RobotMessage] = []
    c.on_robot_message = sent.append
    assert not c.run_script(text)
    assert c.runtime_state == RuntimeState.STOPPED
    assert any(message in m for m in c.log_messages)
    assert "textmsg: a" not in c.log_messages  # nothing ran
    _, kind, _, _, message_type, line, _ = struct.unpack_from(
        ">iBQbbii", encode_robot_message(sent[-1])
    )
    assert (message_type, kind) == (10, 20)  # runtime exception message
    assert line in (2, 3)


def test_a_runtime_error_stops_the_program_where_it_happens() -> None:
    c = make_controller()
    run(c, 'def main():\n  x = [1, 2]\n  textmsg("before")\n  y = x[5]\n  textmsg("after")\nend\n')
    assert "textmsg: before" in c.log_messages
    assert "textmsg: after" not in c.log_messages
    assert "out of range" in c.last_stop_reason
    assert any("(line 4" in m for m in c.log_messages)


def test_a_secondary_program_runs_beside_the_main_program() -> None:
    c = make_controller()
    assert c.run_script("def main():\n  sleep(10)\nend\n")
    c.tick(300)
    assert c.runtime_state == RuntimeState.PLAYING
    assert c.run_script('sec io():\n  set_digital_out(5, True)\n  textmsg("sec ran")\nend\n')
    c.tick()
    assert c.runtime_state == RuntimeState.PLAYING
    assert c.program is not None
    assert c.io.output_bits == 1 << 5
    assert "textmsg: sec ran" in c.log_messages
    assert not c.run_secondary("sec bad():\n  sleep(1)\nend\n")
    assert c.runtime_state == RuntimeState.PLAYING  # a failing secondary does not stop main


def test_speed_slider_scales_programmed_moves() -> None:
    durations = []
    for fraction in (1.0, 0.5):
        c = make_controller()
        c.io.speed_slider = fraction
        assert c.run_script("movej([0.6, -1.2, 1.2, -1.57, -1.57, 0.3], a=2, v=1)\n")
        c.tick(200)
        t0 = c.time
        peak = 0.0
        while c.runtime_state != RuntimeState.STOPPED:
            c.tick()
            peak = max(peak, float(np.abs(c.arm.qd).max()))
        durations.append((c.time - t0, peak))
    (t_full, v_full), (t_half, v_half) = durations
    assert math.isclose(t_half, 2 * t_full, rel_tol=0.02)
    assert math.isclose(v_half, v_full / 2, rel_tol=0.02)


# ----------------------------------------------------------------------------- over TCP


def test_programs_sent_to_the_script_ports_run_on_the_simulator() -> None:
    with simulator() as sim:
        sim.set_joints(START)
        sim.bring_up()
        target = [0.2, -1.25, 1.2, -1.57, -1.57, 0.3]
        with socket.create_connection((sim.host, 30002), timeout=5) as s:
            s.sendall(
                f'def fxtest():\n  textmsg("moving")\n  movej({target}, a=3, v=2)\n'
                "  set_digital_out(1, True)\n  sleep(5)\nend\n".encode()
            )
            wait(sim, lambda st: "textmsg: moving" in st["log"] and np.allclose(st["q"], target))
            s.sendall(b"sec side():\n  set_digital_out(3, True)\nend\n")
            deadline = time.monotonic() + 10
            while True:  # the masterboard's digital outputs on the primary interface
                m = Messages(sim.host, 30001)
                try:
                    board = struct.unpack_from(">ii", m.robot_state()[3])
                finally:
                    m.close()
                if board[1] == (1 << 1) | (1 << 3):
                    break
                assert time.monotonic() < deadline, f"outputs {board[1]:#x}"
            assert sim.state()["runtime_state"] == "PLAYING"  # the main program still sleeps
        with socket.create_connection((sim.host, 30001), timeout=5) as s:
            s.sendall(b"no_such_thing()\n")
            state = wait(sim, lambda st: st["runtime_state"] == "STOPPED")
            assert any("compile_error_name_not_found:no_such_thing:" in m for m in state["log"])
        assert (
            sim.dashboard("load nothing_here.urp") == "File not found: /programs/nothing_here.urp"
        )


def wait(
    sim: SimulatorHandle, predicate: Callable[[SimulatorState], bool], timeout: float = 10.0
) -> SimulatorState:
    deadline = time.monotonic() + timeout
    while True:
        state = sim.state()
        if predicate(state):
            return state
        assert time.monotonic() < deadline, f"timed out; state {state}"
        time.sleep(0.01)
