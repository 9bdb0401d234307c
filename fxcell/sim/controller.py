"""The simulated controller: robot and safety modes, programs, registers, faults.

One :class:`Controller` is the whole robot as the network sees it. The server calls
:meth:`Controller.tick` once per 2 ms control cycle; the Dashboard, RTDE and script
servers call its methods. Everything runs on one event loop, so there is no locking.

Controller delays (power on, brake release, program start, safety restart) are
multiplied by ``time_scale``; the control cycle and motion always run in real time,
and so does the protective-stop unlock rule: refused until ``unlock_delay`` s of controller
time after the stop (5 s as on the real controller; a test that is not about the rule may
shorten it, ``--unlock-delay``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from fxcell.errors import InvalidArgumentError
from fxcell.link.embedded import FAULTS, SimulatorState  # FAULTS: shared with the launcher
from fxcell.protocol import (
    CONTROL_PERIOD,
    RobotMode,
    RobotStatusBits,
    RuntimeState,
    SafetyMode,
    SafetyStatusBits,
)
from fxcell.sim.constants import DELAYS, REGISTER_COUNT, UNLOCK_DELAY
from fxcell.sim.events import RobotMessage, RuntimeException, TextMessage
from fxcell.sim.program_store import URCAP_PROGRAM, ProgramStore
from fxcell.sim.script import ControlScript, is_control_script
from fxcell.sim.signals import Signal
from fxcell.sim.urscript import Program, URScriptError

# injections that undo a fault or change no behaviour: not counted as faults
_NOT_FAULTS = frozenset(
    {"emergency_stop_release", "safeguard_stop_release", "remote_control", "machine_reset"}
    | {"door_close", "hide_kinematics_info", "show_kinematics_info"}
)

if TYPE_CHECKING:
    from fxcell.sim.motion import Arm

log = logging.getLogger(__name__)


# joint_mode values reported per robot mode
JOINT_MODE = {
    RobotMode.POWER_OFF: 239,
    RobotMode.POWER_ON: 247,  # booting
    RobotMode.BOOTING: 247,
    RobotMode.IDLE: 255,
    RobotMode.RUNNING: 254,
}


_POWERED = frozenset({RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING})
# for the per-cycle paths: on Python 3.11 an enum attribute lookup costs ~0.25 µs
_PLAYING = RuntimeState.PLAYING
_RUNNING = RobotMode.RUNNING
_POWER_ON_BIT = int(RobotStatusBits.POWER_ON)
_PROGRAM_RUNNING_BIT = int(RobotStatusBits.PROGRAM_RUNNING)
_B = SafetyStatusBits
_SAFETY_BITS = {
    SafetyMode.NORMAL: int(_B.NORMAL_MODE),
    SafetyMode.PROTECTIVE_STOP: int(_B.PROTECTIVE_STOPPED | _B.STOPPED_DUE_TO_SAFETY),
    SafetyMode.SAFEGUARD_STOP: int(_B.SAFEGUARD_STOPPED | _B.STOPPED_DUE_TO_SAFETY),
    SafetyMode.ROBOT_EMERGENCY_STOP: int(
        _B.ROBOT_EMERGENCY_STOPPED | _B.EMERGENCY_STOPPED | _B.STOPPED_DUE_TO_SAFETY
    ),
    SafetyMode.SYSTEM_EMERGENCY_STOP: int(
        _B.SYSTEM_EMERGENCY_STOPPED | _B.EMERGENCY_STOPPED | _B.STOPPED_DUE_TO_SAFETY
    ),
    SafetyMode.RECOVERY: int(_B.RECOVERY_MODE),
    SafetyMode.FAULT: int(_B.FAULT | _B.STOPPED_DUE_TO_SAFETY),
}


class FaultError(ValueError):
    """An injection request names an unknown fault or has bad arguments."""


@dataclass
class Registers:
    """The RTDE general-purpose registers (input side written by clients)."""

    in_int: list[int] = field(default_factory=lambda: [0] * REGISTER_COUNT)
    in_double: list[float] = field(default_factory=lambda: [0.0] * REGISTER_COUNT)
    in_bits: int = 0  # input bit registers 0..63 as one 64-bit word
    in_bits_high: int = 0  # input bit registers 64..127 (the script's boolean registers 0..63)
    out_int: list[int] = field(default_factory=lambda: [0] * REGISTER_COUNT)
    out_double: list[float] = field(default_factory=lambda: [0.0] * REGISTER_COUNT)
    out_bits: int = 0  # output bit registers 0..63
    out_bits_high: int = 0  # output bit registers 64..127


@dataclass
class IOState:
    """Digital and analog I/O: outputs as set by RTDE inputs, inputs as set from outside.

    An input driven by a simulated device (the fusion machine) is *owned* by it: only its
    owner sets it (:meth:`set_input`).
    """

    standard_digital: int = 0
    configurable_digital: int = 0
    tool_digital: int = 0
    analog_out: list[float] = field(default_factory=lambda: [0.0, 0.0])
    speed_slider: float = 1.0
    digital_in: int = 0  # standard 0-7, configurable 8-15, tool 16-17 (RTDE's bit layout)
    analog_in: list[float] = field(default_factory=lambda: [0.0, 0.0])
    tool_analog_in: list[float] = field(default_factory=lambda: [0.0, 0.0])
    input_owners: dict[str, str] = field(default_factory=dict)  # "DI0" -> its owner

    @property
    def input_bits(self) -> int:
        """``actual_digital_input_bits``."""
        return self.digital_in

    def output(self, signal: Signal) -> bool:
        """The value of a digital output (``DO``, ``CO``, ``TO``)."""
        return bool(self.output_bits >> signal.bit & 1)

    def input(self, signal: Signal) -> float:
        """The value of an input (1.0/0.0 for digital ones)."""
        if signal.kind == "AI":
            return self.analog_in[signal.index]
        if signal.kind == "TAI":
            return self.tool_analog_in[signal.index]
        return float(self.digital_in >> signal.bit & 1)

    def set_input(self, signal: Signal, value: float, owner: str | None = None) -> None:
        """Set an input; an input owned by a device only by ``owner`` (else ValueError)."""
        if not signal.is_input:
            raise InvalidArgumentError(f"{signal} is an output: only the robot sets it")
        holder = self.input_owners.get(str(signal))
        if holder is not None and holder != owner:
            raise InvalidArgumentError(f"{signal} is driven by {holder}")
        if signal.kind == "AI":
            self.analog_in[signal.index] = float(value)
        elif signal.kind == "TAI":
            self.tool_analog_in[signal.index] = float(value)
        elif value:
            self.digital_in |= 1 << signal.bit
        else:
            self.digital_in &= ~(1 << signal.bit)

    @property
    def output_bits(self) -> int:
        return (
            (self.standard_digital & 0xFF)
            | (self.configurable_digital & 0xFF) << 8
            | (self.tool_digital & 0x3) << 16
        )


def program_name(path: str | None) -> str:
    return path.rsplit("/", 1)[-1] if path else "null"


class Controller:
    """The state of the simulated robot and its controller."""

    def __init__(
        self,
        arm: Arm,
        *,
        time_scale: float = 1.0,
        programs: ProgramStore | None = None,
        unlock_delay: float = UNLOCK_DELAY,
    ) -> None:
        self.arm = arm
        self.programs = programs or ProgramStore()
        self.time_scale = time_scale
        self.unlock_delay = unlock_delay
        self.time = 0.0  # controller time, s (ticks x 2 ms)
        self.ticks = 0
        self.robot_mode = RobotMode.POWER_OFF
        self.safety_mode = SafetyMode.NORMAL
        self.runtime_state = RuntimeState.STOPPED
        self.remote_control = True
        self.operational_mode = "NONE"
        self.loaded_program: str | None = None
        self.program_saved = True
        self.protective_stop_time: float | None = None
        self.registers = Registers()
        self.io = IOState()
        self.payload_mass = 0.0
        self.payload_cog = (0.0, 0.0, 0.0)
        self.tcp: tuple[float, ...] = (0.0,) * 6  # set by the program (set_tcp)
        self.gravity: tuple[float, ...] = (0.0, 0.0, 9.82)  # set_gravity: opposing gravity
        self.teach_mode = False  # freedrive: the arm follows a hand (`push` on the control port)
        self.free_axes: tuple[int, ...] = (1,) * 6  # freedrive_mode's freeAxes (x y z rx ry rz)
        self.freedrive_feature: tuple[float, ...] = (0.0,) * 6  # the frame those axes are in
        self.script: ControlScript | None = None  # ur_rtde's control script, emulated
        self.program: Program | None = None  # any other URScript program, interpreted
        self.kinematics_info_hidden = False  # fault: no calibration on the primary interface
        self.program_kind: str | None = None  # "urp" | "script" | None
        self.last_stop_reason = ""
        self.log_messages: list[str] = []
        self.faults: list[str] = []
        """Every fault of the session: safety stops (injected or the controller's own, such
        as a violation), injected faults, watchdog stops (tests count the unplanned ones)."""
        self.watchdog: tuple[str, float] | None = None  # (input variable, min frequency)
        self.watchdog_action = "stop"  # what a starved watchdog does: "stop" or "pause"
        self.watchdog_armed_at = 0.0
        self.input_updated: dict[str, float] = {}  # input variable -> last update time
        self.input_generation = 0  # bumped by every RTDE input packet
        self.rtde_stalled_until = 0.0
        self.client_host = "127.0.0.1"  # where the ExternalControl URCap asks for its program
        # Hooks the server installs.
        self.on_drop_rtde: Callable[[], None] = lambda: None
        self.on_shutdown: Callable[[], None] = lambda: None
        self.request_urcap_program: Callable[[], None] = lambda: None
        self.on_robot_message: Callable[[RobotMessage], None] = lambda message: None
        self._timers: list[tuple[float, int, Callable[[], None]]] = []
        self._timer_seq = 0
        self._pending: dict[str, int] = {}  # name -> timer seq, for cancellable transitions

    # ------------------------------------------------------------------ timing

    @property
    def digital_input_bits(self) -> int:
        """Standard 0-7, configurable 8-15, tool 16-17 (set from outside or by the machine)."""
        return self.io.input_bits

    def delay(self, name: str) -> float:
        return DELAYS[name] * self.time_scale

    def after(self, seconds: float, callback: Callable[[], None], name: str | None = None) -> None:
        """Run ``callback`` after ``seconds`` of controller time (a named one replaces its last)."""
        if name is not None:
            self.cancel(name)
        self._timer_seq += 1
        self._timers.append((self.time + seconds, self._timer_seq, callback))
        if name is not None:
            self._pending[name] = self._timer_seq

    def cancel(self, name: str) -> None:
        seq = self._pending.pop(name, None)
        if seq is not None:
            self._timers = [t for t in self._timers if t[1] != seq]

    def cycles_to_next_timer(self) -> int | None:
        """Control cycles until the earliest pending timer is due (at least 1); None
        without one."""
        if not self._timers:
            return None
        due = min(t[0] for t in self._timers)
        return max(1, math.ceil((due - self.time) / CONTROL_PERIOD - 1e-9))

    def _run_timers(self) -> None:
        if not self._timers:
            return
        due = [t for t in self._timers if t[0] <= self.time + 1e-9]
        if not due:
            return
        self._timers = [t for t in self._timers if t[0] > self.time + 1e-9]
        for _, seq, callback in sorted(due, key=lambda t: (t[0], t[1])):
            for name, s in list(self._pending.items()):
                if s == seq:
                    del self._pending[name]
            callback()

    @property
    def idle(self) -> bool:
        """Nothing changes from cycle to cycle but the clock (and pending timers)."""
        return (
            self.script is None
            and self.program is None
            and self.watchdog is None
            and not self.arm.active
        )

    def tick(self, steps: int = 1) -> None:
        """Advance ``steps`` control cycles: timers, watchdog, script, motion, safety."""
        if self.idle:  # only the clock and the timers move: one step for all
            self.ticks += steps
            self.time = self.ticks * CONTROL_PERIOD
            self._run_timers()
            return
        for _ in range(steps):
            self.ticks += 1
            self.time = self.ticks * CONTROL_PERIOD
            if self._timers:
                self._run_timers()
            if self.watchdog is not None and self.runtime_state == _PLAYING:
                self._check_watchdog()
            if self.runtime_state == _PLAYING:
                if self.script is not None:
                    self.script.step()
                elif self.program is not None:
                    self._step_program(self.program)
            self.arm.speed_fraction = self.io.speed_slider
            moving = self.robot_mode == _RUNNING
            violation = self.arm.step(CONTROL_PERIOD, enabled=moving)
            if violation is not None:
                self.protective_stop(violation)

    # ------------------------------------------------------------------ status words

    @property
    def robot_status_bits(self) -> int:
        bits = _POWER_ON_BIT if self.robot_mode in _POWERED else 0
        if self.runtime_state == RuntimeState.PLAYING:
            bits |= _PROGRAM_RUNNING_BIT
        return bits

    @property
    def safety_status_bits(self) -> int:
        return _SAFETY_BITS.get(self.safety_mode, 0)

    @property
    def joint_mode(self) -> int:
        return JOINT_MODE.get(self.robot_mode, 239)

    @property
    def program_state_name(self) -> str:
        if self.runtime_state in (RuntimeState.PLAYING, RuntimeState.RESUMING):
            return "PLAYING"
        if self.runtime_state in (RuntimeState.PAUSED, RuntimeState.PAUSING):
            return "PAUSED"
        return "STOPPED"

    @property
    def can_move(self) -> bool:
        return self.robot_mode == RobotMode.RUNNING and self.safety_mode == SafetyMode.NORMAL

    # ------------------------------------------------------------------ life cycle

    def power_on(self) -> None:
        if self.safety_mode != SafetyMode.NORMAL and self.safety_mode != SafetyMode.PROTECTIVE_STOP:
            return
        if self.robot_mode != RobotMode.POWER_OFF:
            return
        self.robot_mode = RobotMode.POWER_ON
        self.after(self.delay("power_on"), self._powered_on, name="power")

    def _powered_on(self) -> None:
        if self.robot_mode == RobotMode.POWER_ON:
            self.robot_mode = RobotMode.IDLE

    def power_off(self) -> None:
        self.cancel("power")
        self.cancel("brakes")
        self._stop_program("robot powered off")
        self.arm.halt()
        self.robot_mode = RobotMode.POWER_OFF

    def brake_release(self) -> None:
        if self.robot_mode != RobotMode.IDLE or self.safety_mode not in (SafetyMode.NORMAL,):
            return
        self.after(self.delay("brake_release"), self._brakes_released, name="brakes")

    def _brakes_released(self) -> None:
        if self.robot_mode == RobotMode.IDLE and self.safety_mode == SafetyMode.NORMAL:
            self.robot_mode = RobotMode.RUNNING

    def restart_safety(self) -> None:
        self.power_off()
        self.safety_mode = SafetyMode.RECOVERY
        self.protective_stop_time = None

        def done() -> None:
            self.safety_mode = SafetyMode.NORMAL

        self.after(self.delay("restart_safety"), done, name="safety")

    def unlock_protective_stop(self) -> str | None:
        """Clear a protective stop; returns why not (reply text) or None."""
        if self.safety_mode != SafetyMode.PROTECTIVE_STOP or self.protective_stop_time is None:
            return "Cannot unlock protective stop, safetymode is not PROTECTIVE_STOP"
        if self.time - self.protective_stop_time < self.unlock_delay:
            return (
                "Cannot unlock protective stop until 5s after occurrence. "
                "Always inspect cause of protective stop before unlocking"
            )
        self.safety_mode = SafetyMode.NORMAL
        self.protective_stop_time = None
        return None

    def shutdown(self) -> None:
        self.power_off()
        self.on_shutdown()

    # ------------------------------------------------------------------ programs

    def load_program(self, path: str) -> tuple[str, str]:
        """Load a ``.urp`` from the program store: ("loaded" | "missing" | "refused", the
        controller's path). Refused: not a program, or one is running."""
        full, file = self.programs.find(path)
        if not full.endswith(".urp") or self.runtime_state != RuntimeState.STOPPED:
            return "refused", full
        if file is None:
            return "missing", full
        self.loaded_program = full
        self.program_saved = True
        return "loaded", full

    def load_installation(self, path: str) -> str:
        """Load an ``.installation`` from the store: "loaded" | "missing" | "refused"."""
        full, file = self.programs.find(path)
        if not full.endswith(".installation") or self.runtime_state != RuntimeState.STOPPED:
            return "refused"
        return "loaded" if file is not None else "missing"

    def play(self) -> bool:
        if self.runtime_state in (RuntimeState.PAUSED, RuntimeState.PAUSING):
            if not self.can_move:
                return False
            self.runtime_state = RuntimeState.PLAYING
            self.arm.resume()
            return True
        if self.loaded_program is None or not self.can_move:
            return False
        if self.runtime_state != RuntimeState.STOPPED:
            return False
        program = None
        if program_name(self.loaded_program) != URCAP_PROGRAM:
            text = self.programs.script(self.loaded_program)
            if text is not None:  # the URScript PolyScope saved with the program
                try:
                    program = Program(self, text)
                except URScriptError as exc:
                    self.runtime_error(exc.message, exc.line, exc.column)
                    return False
        self.program_kind = "urp"
        self.runtime_state = RuntimeState.PLAYING  # PolyScope reports PLAYING at once
        if program is not None:
            self.program = program
            log.info("program %s started", self.loaded_program)
        elif program_name(self.loaded_program) == URCAP_PROGRAM:
            self.after(self.delay("program_start"), self.request_urcap_program, name="program")
        return True

    def stop(self, reason: str = "stopped") -> bool:
        if self.runtime_state == RuntimeState.STOPPED:
            return False
        self._stop_program(reason)
        self.arm.stop_motion()
        return True

    def pause(self) -> bool:
        if self.runtime_state != RuntimeState.PLAYING:
            return False
        self.runtime_state = RuntimeState.PAUSED
        self.arm.stop_motion(hold=True)
        return True

    def run_script(self, text: str, *, via_urcap: bool = False) -> bool:
        """A complete program arrived on a script port (or from the URCap)."""
        if not self.remote_control and not via_urcap:
            log.warning("script refused: robot is in local control")
            return False
        if text.lstrip().startswith("sec ") and not via_urcap:
            return self.run_secondary(text)
        if not self.can_move:
            log.warning(
                "script refused: robot mode %s, safety %s",
                self.robot_mode.name,
                self.safety_mode.name,
            )
            return False
        program: Program | None = None
        if not is_control_script(text):
            try:
                program = Program(self, text)
            except URScriptError as exc:  # the controller's compiler refuses it
                self.runtime_error(exc.message, exc.line, exc.column)
                return False
        if (
            self.script is not None
            or self.program is not None
            or (self.runtime_state != RuntimeState.STOPPED and not via_urcap)
        ):
            self._stop_program("replaced by a new program")
            self.arm.stop_motion()
        self.cancel("program")

        def start() -> None:
            if not self.can_move:
                self._stop_program("robot not ready when the program started")
                return
            if program is None:
                self.script = ControlScript(self, text)
            else:
                self.script = None
                self.program = program
                log.info("URScript program %s started", program.name)
            self.program_kind = "urp" if via_urcap else "script"
            self.runtime_state = RuntimeState.PLAYING

        if via_urcap:
            start()
        else:
            self.after(self.delay("program_start"), start, name="program")
        return True

    def run_secondary(self, text: str) -> bool:
        """A ``sec`` program: runs at once beside the main program (it cannot take time)."""
        try:
            program = Program(self, text, secondary=True)
        except URScriptError as exc:
            self.runtime_error(exc.message, exc.line, exc.column)
            return False
        log.info("secondary program %s runs", program.name)
        program.step()
        if program.error is not None:
            e = program.error
            self.runtime_error(e.message, e.line, e.column, stop=False)
            return False
        return True

    def _step_program(self, program: Program) -> None:
        if not program.step():
            return
        self.program = None
        if program.error is not None:
            e = program.error
            self.runtime_error(e.message, e.line, e.column)
        else:
            self._stop_program("program finished")

    def runtime_error(
        self, text: str, line: int = 0, column: int = 0, *, stop: bool = True
    ) -> None:
        """A runtime (or compile) error, reported as the controller does: a runtime exception
        message on the primary/secondary interfaces and the log; the program stops."""
        entry = f"Runtime exception: {text} (line {line}, column {column})"
        log.error("%s", entry)
        self.log_messages.append(entry)
        self.on_robot_message(RuntimeException(text, line, column, self.time))
        if stop:
            self._stop_program(f"runtime exception: {text}")
            self.arm.stop_motion()

    def report_error(self, text: str) -> None:
        """An error the program survives: the log and a text message to the clients."""
        log.error("%s", text)
        self.log_messages.append(f"error: {text}")
        self.on_robot_message(TextMessage(text, self.time))

    def text_message(self, text: str) -> None:
        """``textmsg``: the log and a text message to the primary/secondary clients."""
        log.info("textmsg: %s", text)
        self.log_messages.append(f"textmsg: {text}")
        self.on_robot_message(TextMessage(text, self.time))

    def enter_freedrive(
        self, axes: tuple[int, ...] = (1,) * 6, feature: list[float] | None = None
    ) -> None:
        """``teach_mode()`` / ``freedrive_mode(freeAxes, feature)``: the arm gives way to a
        hand along the free axes of ``feature`` (a pose in the base frame)."""
        self.teach_mode = True
        self.free_axes = axes
        self.freedrive_feature = tuple(feature) if feature is not None else (0.0,) * 6

    def end_freedrive(self) -> None:
        self.teach_mode = False
        self.free_axes = (1,) * 6
        self.freedrive_feature = (0.0,) * 6

    def set_digital_output(self, bit: int, value: bool) -> None:
        """Standard outputs are bits 0-7, configurable 8-15, tool 16-17."""
        io = self.io
        if bit < 8:
            io.standard_digital = (io.standard_digital & ~(1 << bit)) | (int(value) << bit)
        elif bit < 16:
            n = bit - 8
            io.configurable_digital = (io.configurable_digital & ~(1 << n)) | (int(value) << n)
        else:
            n = bit - 16
            io.tool_digital = (io.tool_digital & ~(1 << n)) | (int(value) << n)

    def script_finished(self, reason: str) -> None:
        """The control script ended by itself (stopScript, unsupported command, IK failure)."""
        self._stop_program(reason)

    def _stop_program(self, reason: str) -> None:
        self.cancel("program")
        self.end_freedrive()  # teach mode ends with the program, as on the controller
        if self.program is not None:
            self.program.terminate()
            self.program = None
        if self.runtime_state != RuntimeState.STOPPED or self.script is not None:
            log.info("program stopped: %s", reason)
            self.last_stop_reason = reason
            self.log_messages.append(f"program stopped: {reason}")
        if self.script is not None:
            self.script.terminate()
            self.script = None
        self.watchdog = None
        self.runtime_state = RuntimeState.STOPPED
        self.program_kind = None

    def _check_watchdog(self) -> None:
        assert self.watchdog is not None
        name, frequency = self.watchdog
        last = self.input_updated.get(name, self.watchdog_armed_at)
        if self.time - max(last, self.watchdog_armed_at) > 1.0 / frequency:
            log.warning("RTDE watchdog on %s starved: %s the program", name, self.watchdog_action)
            self.faults.append(f"RTDE watchdog on {name} starved")
            if self.watchdog_action == "pause":
                self.log_messages.append("RTDE watchdog timeout: program paused")
                self.watchdog_armed_at = self.time  # armed again when the program resumes
                self.pause()
            else:
                self.stop("RTDE watchdog timeout")

    def set_watchdog(self, variable: str, frequency: float, action: str = "stop") -> None:
        """``rtde_set_watchdog(variable, frequency, action)``: stop (or pause) the program
        when the input ``variable`` gets no update for ``1/frequency`` s while it runs."""
        self.watchdog = (variable, max(frequency, 1e-6))
        self.watchdog_action = action
        self.watchdog_armed_at = self.time

    # ------------------------------------------------------------------ safety and faults

    def protective_stop(self, reason: str) -> None:
        if self.safety_mode in (
            SafetyMode.PROTECTIVE_STOP,
            SafetyMode.ROBOT_EMERGENCY_STOP,
            SafetyMode.SYSTEM_EMERGENCY_STOP,
        ):
            return
        log.warning("protective stop: %s", reason)
        self.log_messages.append(f"protective stop: {reason}")
        self.faults.append(f"protective stop: {reason}")
        self.safety_mode = SafetyMode.PROTECTIVE_STOP
        self.protective_stop_time = self.time
        self.cancel("brakes")
        self._stop_program(f"protective stop: {reason}")
        self.arm.safety_stop()

    def state(
        self, *, late_cycles: int = 0, stalls: Sequence[tuple[float, float]] = ()
    ) -> SimulatorState:
        """The controller's own view of the robot: the control port's ``state`` reply."""
        return {
            "time": self.time,
            "robot_mode": self.robot_mode.name,
            "safety_mode": self.safety_mode.name,
            "runtime_state": self.runtime_state.name,
            "remote_control": self.remote_control,
            "q": self.arm.q.tolist(),
            "qd": self.arm.qd.tolist(),
            "tcp": list(self.tcp),
            "payload": self.payload_mass,
            "teach_mode": self.teach_mode,
            "program": self.loaded_program,
            "control_script": self.script is not None,
            "last_stop_reason": self.last_stop_reason,
            "late_cycles": late_cycles,
            "stalls": [list(stall) for stall in stalls],
            "log": self.log_messages[-20:],
            "faults": list(self.faults),
        }

    def inject(self, fault: str, args: list[str]) -> str:
        """Apply a fault injection; returns a short description."""
        if fault not in FAULTS:
            raise FaultError(f"unknown fault {fault!r}; known: {', '.join(FAULTS)}")
        if fault not in _NOT_FAULTS and fault != "protective_stop":  # that one counts itself
            self.faults.append(f"injected {fault} {' '.join(args)}".strip())
        if fault == "stall_rtde":
            if len(args) != 1:
                raise FaultError("stall_rtde needs SECONDS")
            try:
                seconds = float(args[0])
            except ValueError:
                raise FaultError(f"stall_rtde: not a number: {args[0]!r}") from None
            if not 0 <= seconds <= 3600:
                raise FaultError("stall_rtde: SECONDS must be in [0, 3600]")
            self.rtde_stalled_until = self.time + seconds
            return f"RTDE stalled for {seconds:g} s"
        if args:
            raise FaultError(f"{fault} takes no arguments")
        if fault == "protective_stop":
            self.protective_stop("injected")
        elif fault == "emergency_stop":
            self.log_messages.append("emergency stop")
            self.safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
            self.protective_stop_time = None
            self._stop_program("emergency stop")
            self.arm.safety_stop()
            self.cancel("power")
            self.cancel("brakes")
            self.robot_mode = RobotMode.POWER_OFF
        elif fault == "emergency_stop_release":
            if self.safety_mode in (
                SafetyMode.ROBOT_EMERGENCY_STOP,
                SafetyMode.SYSTEM_EMERGENCY_STOP,
            ):
                self.safety_mode = SafetyMode.NORMAL
        elif fault == "safeguard_stop":
            if self.safety_mode == SafetyMode.NORMAL:
                self.safety_mode = SafetyMode.SAFEGUARD_STOP
                if self.runtime_state == RuntimeState.PLAYING:
                    self.runtime_state = RuntimeState.PAUSED
                self.arm.stop_motion(hold=True)
        elif fault == "safeguard_stop_release":
            if self.safety_mode == SafetyMode.SAFEGUARD_STOP:
                self.safety_mode = SafetyMode.NORMAL
        elif fault == "local_control":
            self.remote_control = False
        elif fault == "remote_control":
            self.remote_control = True
        elif fault == "drop_rtde":
            self.on_drop_rtde()
        elif fault == "stop_program":
            self.stop("stopped on the teach pendant")
        elif fault == "hang_script":
            if self.script is None:
                raise FaultError("hang_script: no control script runs")
            self.script.hang()
        elif fault in ("hide_kinematics_info", "show_kinematics_info"):
            self.kinematics_info_hidden = fault == "hide_kinematics_info"
        elif fault == "power_loss":
            self.cancel("power")
            self.cancel("brakes")
            self._stop_program("arm power lost")
            self.arm.halt()
            self.robot_mode = RobotMode.POWER_OFF
        return fault.replace("_", " ")

    # ------------------------------------------------------------------ inputs

    def set_payload(self, mass: float, cog: tuple[float, float, float] | None) -> None:
        self.payload_mass = mass
        if cog is not None:
            self.payload_cog = cog
