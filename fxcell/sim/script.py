"""Native emulation of ur_rtde's control script (``def rtde_control():``).

The simulator does not interpret URScript. When the program ur_rtde uploads arrives,
this class runs its main loop natively, once per control cycle, on the same RTDE
registers the real script uses: ``input_int_register_0`` is the command,
``output_int_register_0`` answers ready (1) / done (2), ``output_int_register_2`` is
the async progress word, the double registers carry arguments and results. Register
offsets (ur_rtde's upper range flag) and the injected move path are read from the
uploaded text.
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from fxcell.geometry import Pose
from fxcell.protocol import ControlCommand as C
from fxcell.sim.motion import (
    JointMove,
    LinearMove,
    Motion,
    MotionSequence,
    MotionToken,
    SafetyLimitError,
    ServoTrack,
    SpeedTrack,
)

if TYPE_CHECKING:
    from fxcell.sim.controller import Controller
    from fxcell.sim.motion import Arm

log = logging.getLogger(__name__)

# Commands the script's main loop treats as real-time: processed, then "ready" at once.
REALTIME = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
# The commands a client streams, as plain ints: on Python 3.11 an enum attribute lookup
# costs about as much as the rest of a comparison chain.
_BACKLOG_REPORTED = 10
"""Input packets between two control cycles at which the simulator logs its receiver late."""
_SERVOJ, _SERVOL, _SPEEDJ, _SPEEDL = int(C.SERVOJ), int(C.SERVOL), int(C.SPEEDJ), int(C.SPEEDL)
# Commands that only adjust settings without effect here (dynamics queries).
NO_OPS = frozenset({67, 68, 69, 70, 71})
# jog features (start_jog's input_double_register_6)
JOG_BASE, JOG_TOOL, JOG_CUSTOM = 0, 1, 2
# Commands the simulator cannot model (no force/torque sensing, no contact): refused with a
# logged error, answered so the client does not hang, and the script stays usable.
UNMODELLED = {
    6: "force_mode",
    7: "force_mode_stop",
    8: "zero_ftsensor",
    20: "force_mode_set_damping",
    21: "force_mode_set_gain_scaling",
    25: "tool_contact",
    51: "move_until_contact",
    56: "ft_rtde_input_enable",
    57: "enable_external_ft_sensor",
    62: "start_contact_detection",
    63: "stop_contact_detection",
    64: "read_contact_detection",
    66: "direct_torque",
}
REFUSAL_LOG_INTERVAL = 1.0  # s: a refused command streamed at 500 Hz is logged once a second
# Both the uploaded program and the bare body the ExternalControl URCap receives have it.
SCRIPT_MARKER = "def rtde_cmd():"

_OFFSET_INT = re.compile(r"global\s+reg_offset_int\s*=\s*(\d+)")
_OFFSET_FLOAT = re.compile(r"global\s+reg_offset_float\s*=\s*(\d+)")
_PATH_LINE = re.compile(
    r"^\s*(movej|movel|movep)\((p?)\[([^\]]*)\]\s*,\s*a\s*=\s*([-+0-9.eE]+)\s*,"
    r"\s*v\s*=\s*([-+0-9.eE]+)\s*,\s*r\s*=\s*([-+0-9.eE]+)\s*\)\s*$"
)


def is_control_script(text: str) -> bool:
    return SCRIPT_MARKER in text


def parse_move_path(text: str) -> list[tuple[str, list[float], float, float]]:
    """The ``movej``/``movel`` entries ur_rtde injected into ``exec_move_path``."""
    start = text.find("def exec_move_path():")
    if start < 0:
        return []
    end = text.find("\n    end", start)
    entries = []
    for line in text[start:end].splitlines():
        m = _PATH_LINE.match(line)
        if m:
            kind = "movej" if m.group(1) == "movej" and not m.group(2) else "movel"
            values = [float(x) for x in m.group(3).split(",")]
            entries.append((kind, values, float(m.group(4)), float(m.group(5))))
    return entries


class ScriptError(Exception):
    """A runtime error of the script: the program stops with this reason."""


class ControlScript:
    """ur_rtde's control script main loop, one iteration per control cycle."""

    def __init__(self, controller: Controller, text: str) -> None:
        self.c = controller
        m = _OFFSET_INT.search(text)
        self.oi = int(m.group(1)) if m else 0
        m = _OFFSET_FLOAT.search(text)
        self.of = int(m.group(1)) if m else 0
        self.path = parse_move_path(text)
        self.executing = False
        self.terminated = False
        self.hung = False  # stopped answering (the hang_script fault); the program plays on
        self.wait: MotionToken | None = None
        self.move_token: MotionToken | None = None  # the async move thread
        self.stop_token: MotionToken | None = None  # the async stop thread
        self.servo: ServoTrack | None = None
        self.speed: SpeedTrack | None = None
        self.async_wr_count = 0
        self.async_op_id = 0
        self.target_waypoint: Pose | None = None
        self.jog_frame: np.ndarray | None = None  # rotation of the jog feature while jogging
        self._generation = -1  # input generation last processed by a real-time command
        self._refused_at: dict[int, float] = {}  # command -> controller time last reported
        self._last_realtime = -1
        log.info("RTDE Control Script Loaded (register offsets int %d, float %d)", self.oi, self.of)
        self._async_progress(-1)
        self._signal(1)

    # ------------------------------------------------------------------ registers

    @property
    def arm(self) -> Arm:
        return self.c.arm

    def _int(self, i: int) -> int:
        return self.c.registers.in_int[self.oi + i]

    def _float(self, i: int) -> float:
        return self.c.registers.in_double[self.of + i]

    def _floats(self, i: int, n: int = 6) -> list[float]:
        base = self.of + i
        return self.c.registers.in_double[base : base + n]

    def _write_floats(self, values: object) -> None:
        vals = [float(v) for v in values]  # type: ignore[attr-defined]
        self.c.registers.out_double[self.of : self.of + len(vals)] = vals

    def _write_int(self, i: int, value: int) -> None:
        self.c.registers.out_int[self.oi + i] = int(value)

    def _signal(self, value: int) -> None:
        self._write_int(0, value)

    def _async_progress(self, value: int) -> None:
        self.async_wr_count = self.async_wr_count + 1 if self.async_wr_count < 127 else 0
        if value == 0:
            self.async_op_id = self.async_op_id + 1 if self.async_op_id < 127 else 0
        word = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            word += min(value, 32767) + 32768
        self._write_int(2, word)

    # ------------------------------------------------------------------ main loop

    def terminate(self) -> None:
        self.terminated = True
        self.wait = None
        self.move_token = None
        self.stop_token = None

    def hang(self) -> None:
        """Stop answering commands, as a script blocked in a call does (a read without a
        timeout): the program keeps playing, the registers keep their values, until the
        program is stopped or a new script replaces this one."""
        self.hung = True

    def step(self) -> None:
        if self.terminated or self.hung:
            return
        if self.wait is not None:  # inside a blocking call
            if not self.wait.done:
                return
            failed = self.wait.failed
            self.wait = None
            if failed is not None:
                self._fail(failed)
                return
            self._signal(2)
            self.executing = True
            return
        registers = self.c.registers
        cmd = registers.in_int[self.oi]
        try:
            if cmd in REALTIME:
                # The script re-reads the registers every cycle; only a new packet can
                # change what that does, so unchanged inputs are not processed again.
                generation = self.c.input_generation
                if generation != self._generation or cmd != self._last_realtime:
                    packets = generation - self._generation
                    self._generation = generation
                    self._last_realtime = cmd
                    if cmd == _SERVOJ:  # streamed at 500 Hz: the registers read in place
                        d, of = registers.in_double, self.of
                        self._servo(d[of : of + 6], d[of + 8], d[of + 9], d[of + 10], packets)
                    else:
                        self._process(cmd)
                if not self.terminated:
                    registers.out_int[self.oi] = 1  # ready (_signal(1))
            elif cmd == 0:
                self.executing = False
                self._signal(1)
            elif not self.executing:
                self.executing = True
                self._process(cmd)
                if self.wait is None and not self.terminated and cmd != C.STOP_SCRIPT:
                    self._signal(2)
        except ScriptError as exc:
            self._fail(str(exc))
        except SafetyLimitError as exc:
            self.c.protective_stop(str(exc))

    def _fail(self, reason: str) -> None:
        log.warning("control script stopped: %s", reason)
        self.terminated = True
        self.c.script_finished(reason)

    # ------------------------------------------------------------------ commands

    def _run(self, motion: Motion) -> MotionToken:
        self.servo = None
        self.speed = None
        return self.arm.run(motion)

    def _stop_async_move(self) -> None:
        if self.move_token is not None:
            token, self.move_token = self.move_token, None
            gen = self.arm.generator
            if not token.done and gen is not None and gen.token is token:
                gen.token = MotionToken()  # the thread is killed: its motion no longer reports
            self._async_progress(-1)

    def _move(self, motion: Motion, asynchronous: bool) -> None:
        if asynchronous:
            self._async_progress(0)
            token = motion.token
            self.move_token = token
            token.on_finish.append(self._async_move_finished)
            self._run(motion)
        else:
            self.wait = self._run(motion)

    def _async_move_finished(self, token: MotionToken) -> None:
        if token is not self.move_token or self.terminated:
            return
        self.move_token = None
        self._async_progress(-1)
        if token.failed is not None and token.failed not in ("stopped", "safety stop"):
            self._fail(token.failed)

    def _ik(self, pose: list[float], qnear: list[float] | None = None) -> list[float]:
        seed = self.arm.q if qnear is None else np.asarray(qnear, dtype=float)
        try:
            q = self.arm.kinematics.inverse(Pose.from_ur(pose), seed)
        except Exception as exc:
            raise ScriptError(f"get_inverse_kin: no solution for {pose} ({exc})") from None
        return [float(v) for v in q]

    def _check_move(self, v: float, a: float) -> None:
        if not (math.isfinite(v) and math.isfinite(a)) or v <= 0 or a <= 0:
            raise ScriptError(f"move: invalid speed {v} or acceleration {a}")

    def _joint_target(self, q: list[float], what: str) -> list[float]:
        if not all(math.isfinite(x) for x in q) or any(abs(x) > 2 * math.pi + 1e-9 for x in q):
            raise ScriptError(f"{what}: joint positions {q} outside ±2π")
        return q

    def _servo(
        self, q: list[float], servo_time: float, lookahead: float, gain: float, packets: int = 1
    ) -> None:
        arm = self.arm
        if self.servo is None or arm.generator is not self.servo:
            self.servo = ServoTrack(arm)
            arm.run(self.servo)
            self.speed = None
            packets = 1  # the first setpoint is judged from where the arm stands
        elif packets >= _BACKLOG_REPORTED:
            log.info("servoj: %d packets arrived since the last cycle (a late receiver)", packets)
        self.servo.command(arm, q, servo_time, lookahead, gain, time.monotonic(), packets)

    def _process(self, cmd: int) -> None:
        arm = self.arm
        if cmd in (_SERVOJ, _SERVOL):  # streamed at 500 Hz: tested first
            q = self._floats(0) if cmd == _SERVOJ else self._ik(self._floats(0))
            self._servo(q, self._float(8), self._float(9), self._float(10))
        elif cmd in (_SPEEDJ, _SPEEDL):
            self.jog_frame = None  # a speed command ends jogging (its thread is replaced)
            if self.speed is None or arm.generator is not self.speed:
                self.speed = SpeedTrack(arm)
                arm.run(self.speed)
                self.servo = None
            if cmd == _SPEEDJ:
                self.speed.command_joint(arm, self._floats(0), self._float(6))
            else:
                self.speed.command_tool(arm, self._floats(0), self._float(6))
        elif cmd == C.MOVEJ or cmd == C.MOVEJ_IK:
            v, a, asynchronous = self._float(6), self._float(7), self._int(1) == 1
            self._check_move(v, a)
            q = self._floats(0) if cmd == C.MOVEJ else self._ik(self._floats(0))
            q = self._joint_target(q, "movej")
            self._stop_async_move()
            self.target_waypoint = arm.kinematics.forward(np.asarray(q))
            self._move(JointMove(arm, q, v, a), asynchronous)
        elif cmd == C.MOVEL or cmd == C.MOVEL_FK:
            v, a, asynchronous = self._float(6), self._float(7), self._int(1) == 1
            self._check_move(v, a)
            final_q = None
            if cmd == C.MOVEL:
                target = Pose.from_ur(self._floats(0))
            else:
                final_q = self._joint_target(self._floats(0), "movel")
                target = arm.kinematics.forward(np.asarray(final_q))
            self._stop_async_move()
            self.target_waypoint = target
            self._move(LinearMove(arm, target, v, a, final_q=final_q), asynchronous)
        elif cmd == C.MOVE_PATH:
            asynchronous = self._int(1) == 1
            self._stop_async_move()
            if not self.path:
                raise ScriptError("move_path: no path in the uploaded script")
            self._move(self._path_motion(), asynchronous)
        elif cmd == C.SPEED_STOP or cmd == C.SERVO_STOP:
            decel = self._float(0)
            self.servo = None
            self.speed = None
            self.wait = arm.stop_motion(max(decel, 1e-3))
        elif cmd == C.STOPJ or cmd == C.STOPL:
            decel, asynchronous = self._float(0), self._int(1) == 1
            stop_move = True
            if self.stop_token is not None:
                stop_move = False
                self.stop_token = None
                self._async_progress(-1)
            if stop_move:
                self._stop_async_move()
            self.servo = None
            self.speed = None
            token = arm.stop_motion(max(decel, 1e-3))
            if asynchronous:
                self._async_progress(0)
                self.stop_token = token
                token.on_finish.append(self._async_stop_finished)
            else:
                self.wait = token
        elif cmd == C.SET_PAYLOAD or cmd == 65:  # 65: set_target_payload
            x, y, z = self._floats(1, 3)
            self.c.set_payload(self._float(0), None if x == y == z == 0.0 else (x, y, z))
        elif cmd == C.TEACH_MODE:
            self._stop_async_move()
            self.jog_frame = None
            self.servo = None
            self.speed = None
            self.c.enter_freedrive()
        elif cmd == C.END_TEACH_MODE:
            self.c.end_freedrive()
        elif cmd == C.SET_TCP:
            arm.set_tcp(self._floats(0))
            self.c.tcp = tuple(self._floats(0))
        elif cmd == C.GET_IK_ARGS:
            self._write_floats(self._ik(self._floats(0), self._floats(6)))
        elif cmd == C.GET_IK_DEFAULT:
            self._write_floats(self._ik(self._floats(0)))
        elif cmd in (60, 61):  # inverse kinematics has solution (default / args)
            try:
                self._ik(self._floats(0), self._floats(6) if cmd == 61 else None)
                ok = 1
            except ScriptError:
                ok = 0
            self._write_int(1, ok)
        elif cmd == C.FK_DEFAULT:
            self._write_floats(arm.tcp_pose().as_ur())
        elif cmd == C.FK_ARGS:
            tcp = self._floats(6)
            kin = arm.make_kinematics(tuple(tcp)) if arm.make_kinematics else arm.kinematics
            self._write_floats(kin.forward(np.asarray(self._floats(0))).as_ur())
        elif cmd == C.POSE_TRANS:
            p = Pose.from_ur(self._floats(0)) @ Pose.from_ur(self._floats(6))
            self._write_floats(p.as_ur())
        elif cmd == 40:  # get_tcp_offset
            self._write_floats(self.c.tcp)
        elif cmd == 58:  # get_actual_tool_flange_pose
            self._write_floats(arm.flange_pose().as_ur())
        elif cmd == 28:  # get_target_waypoint
            self._write_floats((self.target_waypoint or arm.tcp_pose()).as_ur())
        elif cmd == 26:  # get_steptime
            self._write_floats([0.002])
        elif cmd == 27:  # get_actual_joint_positions_history: the current position
            self._write_floats(arm.q.tolist())
        elif cmd == 38:  # get_joint_torques (no dynamics model: zero)
            self._write_floats([0.0] * 6)
        elif cmd == C.IS_STEADY:
            steady = not arm.moving and (
                arm.generator is None or arm.generator is self.servo or arm.generator is self.speed
            )
            self._write_int(1, 1 if steady else 0)
        elif cmd == 36:  # is_pose_within_safety_limits
            try:
                self._ik(self._floats(0))
                self._write_int(1, 1)
            except ScriptError:
                self._write_int(1, 0)
        elif cmd == 37:  # is_joints_within_safety_limits
            q = self._floats(0)
            self._write_int(1, 1 if all(abs(x) <= 2 * math.pi for x in q) else 0)
        elif cmd == C.SET_WATCHDOG:
            self.c.set_watchdog(f"input_int_register_{self.oi}", self._float(0))
        elif cmd == C.PROTECTIVE_STOP:
            self.c.protective_stop("protective_stop() called by the program")
        elif cmd == 41:  # start_jog
            self._jog()
        elif cmd == 42:  # stop_jog: the jog thread is killed, then stopl(1.2)
            self.jog_frame = None
            self.servo = None
            self.speed = None
            self.wait = arm.stop_motion(1.2)
        elif cmd == 52:  # freedrive_mode(freeAxes, feature)
            self._stop_async_move()
            self.jog_frame = None
            self.servo = None
            self.speed = None
            axes = tuple(1 if self._int(k) else 0 for k in range(1, 7))
            self.c.enter_freedrive(axes, self._floats(0))
        elif cmd == 53:  # end_freedrive_mode
            self.c.end_freedrive()
        elif cmd == 54:  # get_freedrive_status: 0 = normal (no singularity nearby)
            self._write_int(1, 0)
        elif cmd == 59:  # set_gravity(direction)
            g = self._floats(0, 3)
            if not all(math.isfinite(v) for v in g):
                raise ScriptError(f"set_gravity: direction {g} is not finite")
            self.c.gravity = tuple(g)
        elif cmd == C.STOP_SCRIPT:
            log.info("Received stop script!")
            self.terminated = True
            self.c.script_finished("stopScript")
        elif cmd in UNMODELLED:
            self._refuse(cmd)
        elif cmd in NO_OPS:
            pass
        else:
            name = C(cmd).name if cmd in C._value2member_map_ else str(cmd)
            raise ScriptError(f"command {name} is not supported by the simulator")

    def _jog(self) -> None:
        """start_jog: the jog thread's ``speedl`` of the commanded speed turned from the
        jog feature (base, the TCP as it was when jogging started, or a custom pose) into
        the base frame; a new start_jog while jogging changes only speed and acceleration."""
        arm = self.arm
        speed = self._floats(0)
        acceleration = self._float(7)
        if not all(math.isfinite(v) for v in (*speed, acceleration)):
            raise ScriptError(f"jog: speed {speed} or acceleration {acceleration} not finite")
        if self.jog_frame is None or self.speed is None or arm.generator is not self.speed:
            feature = round(self._float(6))
            if feature == JOG_TOOL:
                self.jog_frame = arm.tcp_pose().rotation
            elif feature == JOG_CUSTOM:
                custom = self._floats(8)
                if not all(math.isfinite(v) for v in custom):
                    raise ScriptError(f"jog: custom feature {custom} is not finite")
                self.jog_frame = Pose.from_ur(custom).rotation
            else:
                self.jog_frame = np.eye(3)
            self.servo = None
            self.speed = SpeedTrack(arm)
            arm.run(self.speed)
        R = self.jog_frame
        xd = np.concatenate([R @ np.asarray(speed[:3]), R @ np.asarray(speed[3:])])
        self.speed.command_tool(arm, xd.tolist(), acceleration)

    def _refuse(self, cmd: int) -> None:
        """An unmodelled command: a zero result, an error in the log, the script goes on."""
        self._write_int(1, 0)
        last = self._refused_at.get(cmd)
        if last is None or self.c.time - last >= REFUSAL_LOG_INTERVAL:
            self._refused_at[cmd] = self.c.time
            self.c.report_error(
                f"{UNMODELLED[cmd]} (command {cmd}) is not supported by the simulator: "
                "ignored, the control script continues"
            )

    def _async_stop_finished(self, token: MotionToken) -> None:
        if token is self.stop_token and not self.terminated:
            self.stop_token = None
            self._async_progress(-1)

    def _path_motion(self) -> Motion:
        factories: list[Callable[[Arm, MotionToken], Motion]] = []
        for kind, values, a, v in self.path:
            if kind == "movej":
                factories.append(_joint_factory(self._joint_target(values, "movej"), v, a))
            else:
                factories.append(_linear_factory(Pose.from_ur(values), v, a))
        return MotionSequence(factories, on_segment=self._async_progress)


def _joint_factory(q: list[float], v: float, a: float) -> Callable[[Arm, MotionToken], Motion]:
    def make(arm: Arm, token: MotionToken) -> Motion:
        return JointMove(arm, q, v, a, token)

    return make


def _linear_factory(pose: Pose, v: float, a: float) -> Callable[[Arm, MotionToken], Motion]:
    def make(arm: Arm, token: MotionToken) -> Motion:
        return LinearMove(arm, pose, v, a, token)

    return make
