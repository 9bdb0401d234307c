"""The built-in functions a program may call, registered in :data:`BUILTINS`.

Each takes the running program (for its controller) and the bound arguments; one that
takes time returns a :class:`~fxcell.sim.urscript.values.Waiting`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from fxcell.geometry import Pose
from fxcell.sim.constants import REGISTER_COUNT
from fxcell.sim.motion import JointMove, LinearMove
from fxcell.sim.urscript.errors import URScriptError
from fxcell.sim.urscript.values import (
    HaltSignal,
    PoseValue,
    Waiting,
    as_number,
    as_six,
    format_value,
)

if TYPE_CHECKING:
    from fxcell.sim.urscript.interpreter import Program

Builtin = Callable[["Program", list[Any], dict[str, Any]], Any]


def signature(
    *names: str, **defaults: Any
) -> Callable[[list[Any], dict[str, Any], str], list[Any]]:
    """Bind positional and keyword arguments to ``names`` (defaults from ``defaults``)."""

    def bind(args: list[Any], kwargs: dict[str, Any], func: str) -> list[Any]:
        if len(args) > len(names):
            raise URScriptError(f"{func}: too many arguments")
        values = dict(zip(names, args, strict=False))
        for key, value in kwargs.items():
            if key not in names or key in values:
                raise URScriptError(f"{func}: unexpected argument {key}")
            values[key] = value
        out = []
        for n in names:
            if n in values:
                out.append(values[n])
            elif n in defaults:
                out.append(defaults[n])
            else:
                raise URScriptError(f"{func}: missing argument {n}")
        return out

    return bind


BUILTINS: dict[str, Builtin] = {}
UNSUPPORTED = frozenset(
    {
        "force_mode",
        "end_force_mode",
        "force_mode_set_damping",
        "force_mode_set_gain_scaling",
        "freedrive_mode",
        "end_freedrive_mode",
        "teach_mode",
        "end_teach_mode",
        "movec",
        "servoj",
        "servoc",
        "speedj",
        "speedl",
        "socket_open",
        "socket_send_string",
        "socket_read_ascii_float",
        "run",
        "join",
        "kill",
        "enter_critical",
        "exit_critical",
    }
)


def builtin(name: str, *names: str, **defaults: Any) -> Callable[[Callable[..., Any]], Any]:
    bind = signature(*names, **defaults)

    def register(fn: Callable[..., Any]) -> Callable[..., Any]:
        def call(program: Program, args: list[Any], kwargs: dict[str, Any]) -> Any:
            return fn(program, *bind(args, kwargs, name))

        BUILTINS[name] = call
        return fn

    return register


def _joints_or_ik(program: Program, target: Any, what: str) -> np.ndarray:
    arm = program.c.arm
    values = as_six(target, what)
    if isinstance(target, PoseValue):
        try:
            return np.asarray(arm.kinematics.inverse(Pose.from_ur(values), arm.q), dtype=float)
        except Exception as exc:
            raise URScriptError(f"{what}: no inverse kinematics solution ({exc})") from None
    if any(abs(v) > 2 * math.pi + 1e-9 for v in values):
        raise URScriptError(f"{what}: joint positions {format_value(values)} outside ±2π")
    return np.asarray(values, dtype=float)


def _check_move(program: Program, what: str, a: Any, v: Any) -> tuple[float, float]:
    if program.secondary:
        raise URScriptError(f"{what}: a secondary program cannot move the arm")
    a_, v_ = as_number(a, what), as_number(v, what)
    if not (a_ > 0 and v_ > 0 and math.isfinite(a_) and math.isfinite(v_)):
        raise URScriptError(f"{what}: invalid speed {v_} or acceleration {a_}")
    if not program.c.can_move:
        raise URScriptError(f"{what}: the robot cannot move (not running or stopped)")
    return a_, v_


@builtin("movej", "q", "a", "v", "t", "r", a=1.4, v=1.05, t=0.0, r=0.0)
def _movej(p: Program, q: Any, a: Any, v: Any, t: Any, r: Any) -> Waiting:
    acc, vel = _check_move(p, "movej", a, v)
    target = _joints_or_ik(p, q, "movej")
    arm = p.c.arm
    return Waiting(arm.run(JointMove(arm, target, vel, acc)))


def _linear(p: Program, what: str, pose: Any, a: Any, v: Any) -> Waiting:
    acc, vel = _check_move(p, what, a, v)
    arm = p.c.arm
    final_q = None
    if isinstance(pose, PoseValue):
        target = Pose.from_ur(as_six(pose, what))
    else:
        final_q = _joints_or_ik(p, pose, what)
        target = arm.kinematics.forward(final_q)
    return Waiting(arm.run(LinearMove(arm, target, vel, acc, final_q=final_q)))


@builtin("movel", "pose", "a", "v", "t", "r", a=1.2, v=0.25, t=0.0, r=0.0)
def _movel(p: Program, pose: Any, a: Any, v: Any, t: Any, r: Any) -> Waiting:
    return _linear(p, "movel", pose, a, v)


@builtin("movep", "pose", "a", "v", "r", a=1.2, v=0.25, r=0.0)
def _movep(p: Program, pose: Any, a: Any, v: Any, r: Any) -> Waiting:
    return _linear(p, "movep", pose, a, v)


def _stop(p: Program, what: str, a: Any) -> Waiting:
    if p.secondary:
        raise URScriptError(f"{what}: a secondary program cannot move the arm")
    decel = as_number(a, what)
    if not decel > 0:
        raise URScriptError(f"{what}: deceleration must be > 0")
    return Waiting(p.c.arm.stop_motion(decel))


@builtin("stopj", "a")
def _stopj(p: Program, a: Any) -> Waiting:
    return _stop(p, "stopj", a)


@builtin("stopl", "a", "aRot", aRot=None)
def _stopl(p: Program, a: Any, a_rot: Any) -> Waiting:
    return _stop(p, "stopl", a)


@builtin("sleep", "t")
def _sleep(p: Program, t: Any) -> Waiting:
    seconds = as_number(t, "sleep")
    if seconds < 0:
        raise URScriptError("sleep: negative time")
    return Waiting(p.c.time + seconds)


@builtin("sync")
def _sync(p: Program) -> Waiting:
    return Waiting(None)


@builtin("halt")
def _halt(p: Program) -> None:
    raise HaltSignal()


@builtin("textmsg", "s1", "s2", s2="")
def _textmsg(p: Program, s1: Any, s2: Any) -> None:
    p.c.text_message(format_value(s1) + format_value(s2))


@builtin("popup", "s", "title", "warning", "error", "blocking", title="Popup", warning=False,
         error=False, blocking=False)  # fmt: skip
def _popup(p: Program, s: Any, title: Any, warning: Any, error: Any, blocking: Any) -> None:
    p.c.text_message(f"popup {format_value(title)}: {format_value(s)}")


def _digital(p: Program, what: str, n: Any, b: Any, count: int, shift: int) -> None:
    if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n < count:
        raise URScriptError(f"{what}: output {format_value(n)} out of range 0..{count - 1}")
    p.c.set_digital_output(shift + n, bool(b))


@builtin("set_standard_digital_out", "n", "b")
def _set_standard(p: Program, n: Any, b: Any) -> None:
    _digital(p, "set_standard_digital_out", n, b, 8, 0)


BUILTINS["set_digital_out"] = BUILTINS["set_standard_digital_out"]


@builtin("set_configurable_digital_out", "n", "b")
def _set_configurable(p: Program, n: Any, b: Any) -> None:
    _digital(p, "set_configurable_digital_out", n, b, 8, 8)


@builtin("set_tool_digital_out", "n", "b")
def _set_tool(p: Program, n: Any, b: Any) -> None:
    _digital(p, "set_tool_digital_out", n, b, 2, 16)


def _bit(word: int, n: Any, count: int, what: str) -> bool:
    if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n < count:
        raise URScriptError(f"{what}: {format_value(n)} out of range 0..{count - 1}")
    return bool((word >> n) & 1)


@builtin("get_standard_digital_out", "n")
def _get_standard_out(p: Program, n: Any) -> bool:
    return _bit(p.c.io.output_bits, n, 8, "get_standard_digital_out")


@builtin("get_configurable_digital_out", "n")
def _get_configurable_out(p: Program, n: Any) -> bool:
    return _bit(p.c.io.output_bits >> 8, n, 8, "get_configurable_digital_out")


@builtin("get_standard_digital_in", "n")
def _get_standard_in(p: Program, n: Any) -> bool:
    return _bit(p.c.digital_input_bits, n, 8, "get_standard_digital_in")


BUILTINS["get_digital_in"] = BUILTINS["get_standard_digital_in"]
BUILTINS["get_digital_out"] = BUILTINS["get_standard_digital_out"]


@builtin("set_tcp", "pose")
def _set_tcp(p: Program, pose: Any) -> None:
    tcp = as_six(pose, "set_tcp")
    p.c.arm.set_tcp(tcp)
    p.c.tcp = tuple(tcp)


@builtin("set_payload", "m", "cog", cog=None)
def _set_payload(p: Program, m: Any, cog: Any) -> None:
    mass = as_number(m, "set_payload")
    if mass < 0:
        raise URScriptError("set_payload: negative mass")
    centre = None if cog is None else tuple(as_number(v, "set_payload") for v in cog)
    if centre is not None and len(centre) != 3:
        raise URScriptError("set_payload: cog must have 3 values")
    p.c.set_payload(mass, centre)


@builtin("set_target_payload", "m", "cog", "inertia", inertia=None)
def _set_target_payload(p: Program, m: Any, cog: Any, inertia: Any) -> None:
    _set_payload(p, m, cog)


@builtin("set_payload_mass", "m")
def _set_payload_mass(p: Program, m: Any) -> None:
    _set_payload(p, m, None)


@builtin("set_payload_cog", "CoG")
def _set_payload_cog(p: Program, cog: Any) -> None:
    _set_payload(p, p.c.payload_mass, cog)


@builtin("get_actual_joint_positions")
def _get_q(p: Program) -> list[float]:
    return [float(v) for v in p.c.arm.q]


BUILTINS["get_target_joint_positions"] = BUILTINS["get_actual_joint_positions"]


@builtin("get_actual_joint_speeds")
def _get_qd(p: Program) -> list[float]:
    return [float(v) for v in p.c.arm.qd]


@builtin("get_actual_tcp_pose")
def _get_tcp(p: Program) -> PoseValue:
    return PoseValue(p.c.arm.tcp_pose().as_ur())


BUILTINS["get_target_tcp_pose"] = BUILTINS["get_actual_tcp_pose"]


@builtin("get_forward_kin", "q", "tcp", q=None, tcp=None)
def _fk(p: Program, q: Any, tcp: Any) -> PoseValue:
    arm = p.c.arm
    joints = arm.q if q is None else np.asarray(as_six(q, "get_forward_kin"))
    kin = arm.kinematics
    if tcp is not None and arm.make_kinematics is not None:
        kin = arm.make_kinematics(tuple(as_six(tcp, "get_forward_kin")))
    return PoseValue(kin.forward(joints).as_ur())


@builtin("get_inverse_kin", "x", "qnear", "maxPositionError", "maxOrientationError", "tcp",
         qnear=None, maxPositionError=1e-10, maxOrientationError=1e-10, tcp=None)  # fmt: skip
def _ik(p: Program, x: Any, qnear: Any, _pe: Any, _oe: Any, tcp: Any) -> list[float]:
    arm = p.c.arm
    seed = arm.q if qnear is None else np.asarray(as_six(qnear, "get_inverse_kin"))
    try:
        q = arm.kinematics.inverse(Pose.from_ur(as_six(x, "get_inverse_kin")), seed)
    except Exception as exc:
        raise URScriptError(f"get_inverse_kin: no solution ({exc})") from None
    return [float(v) for v in q]


@builtin("pose_trans", "p_from", "p_from_to")
def _pose_trans(p: Program, a: Any, b: Any) -> PoseValue:
    result = Pose.from_ur(as_six(a, "pose_trans")) @ Pose.from_ur(as_six(b, "pose_trans"))
    return PoseValue(result.as_ur())


@builtin("pose_inv", "p_from")
def _pose_inv(p: Program, a: Any) -> PoseValue:
    return PoseValue(Pose.from_ur(as_six(a, "pose_inv")).inverse().as_ur())


@builtin("is_steady")
def _is_steady(p: Program) -> bool:
    return not p.c.arm.moving


def _register(p: Program, what: str, address: Any) -> int:
    if isinstance(address, bool) or not isinstance(address, int):
        raise URScriptError(f"{what}: address must be an integer")
    if not 0 <= address < REGISTER_COUNT:
        raise URScriptError(f"{what}: address {address} out of range 0..{REGISTER_COUNT - 1}")
    return address


@builtin("write_output_integer_register", "address", "value")
def _write_int(p: Program, address: Any, value: Any) -> None:
    i = _register(p, "write_output_integer_register", address)
    p.c.registers.out_int[i] = int(as_number(value, "write_output_integer_register"))


@builtin("write_output_float_register", "address", "value")
def _write_float(p: Program, address: Any, value: Any) -> None:
    i = _register(p, "write_output_float_register", address)
    p.c.registers.out_double[i] = as_number(value, "write_output_float_register")


@builtin("write_output_boolean_register", "address", "value")
def _write_bool(p: Program, address: Any, value: Any) -> None:
    _bit(0, address, 64, "write_output_boolean_register")  # range check
    n = int(address)
    regs = p.c.registers
    regs.out_bits_high = (regs.out_bits_high & ~(1 << n)) | (int(bool(value)) << n)


@builtin("read_input_integer_register", "address")
def _read_int(p: Program, address: Any) -> int:
    return p.c.registers.in_int[_register(p, "read_input_integer_register", address)]


@builtin("read_input_float_register", "address")
def _read_float(p: Program, address: Any) -> float:
    return p.c.registers.in_double[_register(p, "read_input_float_register", address)]


@builtin("read_input_boolean_register", "address")
def _read_bool(p: Program, address: Any) -> bool:
    return _bit(p.c.registers.in_bits_high, address, 64, "read_input_boolean_register")


@builtin("rtde_set_watchdog", "variable_name", "min_frequency", "action", action="pause")
def _rtde_set_watchdog(p: Program, variable_name: Any, min_frequency: Any, action: Any) -> None:
    what = "rtde_set_watchdog"
    if not isinstance(variable_name, str) or not variable_name.startswith("input_"):
        raise URScriptError(f"{what}: {variable_name!r} is not an RTDE input variable")
    frequency = as_number(min_frequency, what)
    if not (math.isfinite(frequency) and frequency >= 0):
        raise URScriptError(f"{what}: invalid frequency {frequency}")
    kind = str(action).lower()
    if kind not in ("ignore", "pause", "stop"):
        raise URScriptError(f'{what}: action must be "ignore", "pause" or "stop"')
    if frequency == 0 or kind == "ignore":
        p.c.watchdog = None  # a zero frequency turns the watchdog off
        return
    p.c.set_watchdog(variable_name, frequency, action=kind)


@builtin("to_str", "val")
def _to_str(p: Program, val: Any) -> str:
    return format_value(val)


@builtin("str_cat", "op1", "op2")
def _str_cat(p: Program, a: Any, b: Any) -> str:
    return format_value(a) + format_value(b)


@builtin("length", "v")
def _length(p: Program, v: Any) -> int:
    if not isinstance(v, list | str):
        raise URScriptError("length: expected a list or a string")
    return len(v)


def _math(name: str, fn: Callable[..., float], *names: str) -> None:
    @builtin(name, *names)
    def call(p: Program, *args: Any) -> float:
        try:
            return float(fn(*(as_number(a, name) for a in args)))
        except (ValueError, OverflowError):
            raise URScriptError(f"{name}: argument out of domain") from None


for _name, _fn, _args in (
    ("sqrt", math.sqrt, ("f",)),
    ("sin", math.sin, ("f",)),
    ("cos", math.cos, ("f",)),
    ("tan", math.tan, ("f",)),
    ("asin", math.asin, ("f",)),
    ("acos", math.acos, ("f",)),
    ("atan", math.atan, ("f",)),
    ("atan2", math.atan2, ("x", "y")),
    ("pow", math.pow, ("base", "exponent")),
    ("log", lambda b, f: math.log(f, b), ("b", "f")),
    ("d2r", math.radians, ("d",)),
    ("r2d", math.degrees, ("r",)),
    ("fabs", math.fabs, ("f",)),
):
    _math(_name, _fn, *_args)


@builtin("floor", "f")
def _floor(p: Program, f: Any) -> int:
    return math.floor(as_number(f, "floor"))


@builtin("ceil", "f")
def _ceil(p: Program, f: Any) -> int:
    return math.ceil(as_number(f, "ceil"))


@builtin("norm", "a")
def _norm(p: Program, a: Any) -> float:
    if isinstance(a, list):
        return math.sqrt(sum(as_number(v, "norm") ** 2 for v in a))
    return abs(as_number(a, "norm"))
