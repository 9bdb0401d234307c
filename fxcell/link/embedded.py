"""Launch the embedded UR3e controller simulator as a subprocess.

The simulator runs in its own process (``python -m fxcell.sim``): ur_rtde holds the GIL
while it connects, so an in-process simulator would deadlock its clients. Its ports are
fixed, so each simulator gets its own loopback address (127.0.0.2 … 127.0.0.253; .254 is
kept free so that tests can name an address where no controller ever answers),
picked at random and checked by binding every port. This module never imports
``fxcell.sim``; it talks to the process over its control port (fault injection, state).
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, ClassVar, TypedDict, cast

from fxcell.config import SIMULATOR_CAMERA_PORT
from fxcell.errors import InvalidArgumentError, SimulatorError

SIM_MODULE = "fxcell.sim"
CONTROL_PORT = 29990  # the simulator's control port (fault injection, state)
# 63352: Robotiq URCap gripper; SIMULATOR_CAMERA_PORT: the rendered camera (GET /snapshot.jpg)
PORTS = (29999, 30004, 30001, 30002, 30003, 63352, CONTROL_PORT, SIMULATOR_CAMERA_PORT)
FAULTS = (
    "protective_stop",
    "emergency_stop",
    "emergency_stop_release",
    "safeguard_stop",
    "safeguard_stop_release",
    "local_control",
    "remote_control",
    "drop_rtde",
    "stall_rtde",
    "stop_program",
    "hang_script",  # ur_rtde's control script stops answering (blocked in a call); it plays on
    "power_loss",
    "gripper_fault",  # [CODE]: the Hand-E reports FLT CODE (default 0x0E) and stops
    "gripper_drop",  # the held object slips out of the fingers
    "machine_error",  # the fusion machine aborts its cycle (no beads) and reports error
    "machine_reset",  # clears the fusion machine's error
    "door_open",  # the fusion machine's door opens: error, not ready (aborts a cycle)
    "door_close",
    "place_offset",  # DX DY: the next object the gripper releases lands that far off (m)
    "hide_kinematics_info",  # the primary interface's robot state lacks the calibration
    "show_kinematics_info",
)
BIND_FAILED = 2  # the simulator's exit code when it cannot listen


def address_is_free(host: str, ports: Sequence[int] = PORTS) -> bool:
    """Whether every simulator port can be bound on ``host`` right now."""
    for port in ports:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((host, port))
            except OSError:
                return False
    return True


def free_loopback_host(
    rng: random.Random | None = None,
    attempts: int = 200,
    *,
    ports: Sequence[int] = PORTS,
    what: str = "simulator",
) -> str:
    """A random 127.0.0.x address (x in 2..253) on which every one of ``ports`` (by default
    the UR simulator's) is free (127.0.0.254 stays free: tests use it as an unreachable
    controller); ``what`` names the simulator in the error when none is."""
    rng = rng or random.SystemRandom()
    for _ in range(attempts):
        host = f"127.0.0.{rng.randint(2, 253)}"
        if address_is_free(host, ports):
            return host
    raise SimulatorError(f"no free loopback address for the {what} (127.0.0.2-253 all busy)")


def control_request(
    host: str, line: str, *, port: int = CONTROL_PORT, timeout: float = 5.0, what: str = "simulator"
) -> str:
    """One line to a simulator's control port and its one-line answer (every robot kind's
    simulator speaks this; SimulatorError naming ``what`` when it does not answer)."""
    try:
        with socket.create_connection((host, port), timeout=timeout) as s:
            s.sendall(line.encode() + b"\n")
            data = b""
            while not data.endswith(b"\n"):
                chunk = s.recv(65536)
                if not chunk:
                    break
                data += chunk
    except OSError as exc:
        raise SimulatorError(f"{what} at {host} does not answer: {exc}") from None
    return data.decode("utf-8", "replace").strip()


def _request(host: str, line: str, timeout: float) -> str:
    return control_request(host, line, timeout=timeout)


def inject(host: str, fault: str, *args: object, timeout: float = 5.0) -> str:
    """Inject ``fault`` (see :data:`FAULTS`) into the simulator at ``host``."""
    if fault not in FAULTS:
        raise InvalidArgumentError(f"unknown fault {fault!r}; known: {', '.join(FAULTS)}")
    answer = _request(host, " ".join(["inject", fault, *map(str, args)]), timeout)
    if not answer.startswith("ok"):
        raise InvalidArgumentError(f"simulator refused {fault}: {answer}")
    return answer[3:].strip()


class SimulatorState(TypedDict):
    """The simulator's own view of the robot: the control port's ``state`` reply, and what
    the in-process fake robot's ``state()`` returns (one schema, built in one place:
    ``fxcell.sim.controller.Controller.state``)."""

    time: float  # controller time, s
    robot_mode: str  # a RobotMode name
    safety_mode: str  # a SafetyMode name
    runtime_state: str  # a RuntimeState name
    remote_control: bool
    q: list[float]  # rad
    qd: list[float]  # rad/s
    tcp: list[float]  # the TCP offset set by the program (x y z rx ry rz)
    payload: float  # kg
    teach_mode: bool  # freedrive
    program: str | None  # the loaded program
    control_script: bool  # ur_rtde's control script is running
    last_stop_reason: str
    late_cycles: int  # control cycles the simulator ran late (0 in the fake)
    stalls: list[list[float]]  # [wall time it ended (s), length (s)] of its newest stalls
    log: list[str]  # the newest controller log lines
    faults: list[str]  # every fault of the session (tests count the ones they did not inject)


def state(host: str, timeout: float = 5.0) -> SimulatorState:
    """The simulator's own view of the robot (modes, joints, recent log)."""
    answer = _request(host, "state", timeout)
    try:
        result = json.loads(answer)
    except ValueError:
        raise SimulatorError(f"simulator at {host} sent a bad state reply: {answer!r}") from None
    return cast(SimulatorState, result)


def stats(host: str, *, reset: bool = False, timeout: float = 5.0) -> dict[str, Any]:
    """The simulator's own timing: period between RTDE send cycles, late cycles."""
    answer = _request(host, "stats reset" if reset else "stats", timeout)
    if reset:
        return {}
    try:
        result: dict[str, Any] = json.loads(answer)
    except ValueError:
        raise SimulatorError(f"simulator at {host} sent a bad stats reply: {answer!r}") from None
    return result


def push(host: str, delta: Sequence[float], timeout: float = 5.0) -> None:
    """Move the simulated arm by hand while it is in freedrive: the TCP by (dx, dy, dz) m in
    the base frame, or the joints by six deltas (rad)."""
    answer = _request(host, "push " + " ".join(repr(float(v)) for v in delta), timeout)
    if not answer.startswith("ok"):
        raise SimulatorError(f"simulator refused push: {answer}")


def gripper_state(host: str, timeout: float = 5.0) -> dict[str, Any]:
    """The simulated Hand-E's registers, finger width (m) and the name of the held object."""
    return _json_request(host, "gripper", timeout)


def objects(host: str, timeout: float = 5.0) -> dict[str, dict[str, Any]]:
    """Every object of the simulated world: kind, size, mass, pose (UR vector), held."""
    return _json_request(host, "objects", timeout)


def add_object(
    host: str,
    name: str,
    kind: str,
    *,
    width: float,
    height: float,
    mass: float,
    position: Sequence[float],
    timeout: float = 5.0,
) -> None:
    """Place an upright object (grip point at ``position``) in the simulated world."""
    words = ["add_object", name, kind, *(repr(float(v)) for v in (width, height, mass))]
    words += [repr(float(v)) for v in position]
    answer = _request(host, " ".join(words), timeout)
    if not answer.startswith("ok"):
        raise SimulatorError(f"simulator refused add_object: {answer}")


def place_object(
    host: str,
    name: str,
    kind: str,
    station: str,
    slot: str,
    contents: str | None = None,
    timeout: float = 5.0,
) -> str:
    """Put an object at a layout slot (grip point at the slot's grip pose), or move it there
    (it keeps its contents); a new crucible carries a sample unless ``contents`` is ``"-"``."""
    words = ["place_object", name, kind, station, slot] + ([contents] if contents else [])
    answer = _request(host, " ".join(words), timeout)
    if not answer.startswith("ok"):
        raise SimulatorError(f"simulator refused place_object: {answer}")
    return answer[3:].strip()


def offset_object(
    host: str,
    name: str,
    dx: float,
    dy: float,
    tilt_deg: float = 0.0,
    azimuth_deg: float = 0.0,
    timeout: float = 5.0,
) -> str:
    """Shift a standing object by (dx, dy) m along the base axes and lean it ``tilt_deg``
    towards ``azimuth_deg`` (a misplaced crucible, for the camera's placement check)."""
    line = f"offset_object {name} {dx!r} {dy!r} {tilt_deg!r} {azimuth_deg!r}"
    answer = _request(host, line, timeout)
    if not answer.startswith("ok"):
        raise SimulatorError(f"simulator refused offset_object: {answer}")
    return answer[3:].strip()


def set_input(host: str, signal: str, value: object, timeout: float = 5.0) -> str:
    """Set a controller input (``DI5``/``5``, ``CI2``, ``TI0``: 0 or 1; ``AI0``, ``TAI1``: a
    number) as a wired device would; inputs the fusion machine drives are refused."""
    answer = _request(host, f"set_input {signal} {value}", timeout)
    if not answer.startswith("ok"):
        raise SimulatorError(f"simulator refused set_input: {answer}")
    return answer[3:].strip()


def machine_state(host: str, timeout: float = 5.0) -> dict[str, Any]:
    """The simulated fusion machine: state, time left, positions, moulds, IO bits, log."""
    answer = _request(host, "machine", timeout)
    if answer.startswith("error"):
        raise SimulatorError(answer)
    try:
        result: dict[str, Any] = json.loads(answer)
    except ValueError:
        raise SimulatorError(f"simulator at {host} sent a bad machine reply: {answer!r}") from None
    return result


def _json_request(host: str, line: str, timeout: float) -> dict[str, Any]:
    answer = _request(host, line, timeout)
    try:
        result: dict[str, Any] = json.loads(answer)
    except ValueError:
        raise SimulatorError(f"simulator at {host} sent a bad {line} reply: {answer!r}") from None
    return result


def set_joints(host: str, q: Sequence[float], timeout: float = 5.0) -> None:
    """Place the (resting) simulated arm at joint positions ``q`` without moving."""
    answer = _request(host, "set_joints " + " ".join(repr(float(v)) for v in q), timeout)
    if not answer.startswith("ok"):
        raise SimulatorError(f"simulator refused set_joints: {answer}")


class EmbeddedSimulator:
    """One simulator subprocess. ``start()`` returns its address once it listens.

    ``host=None`` picks a free loopback address (and another one if that is taken
    before the simulator binds it). ``time_scale`` shortens controller delays.
    """

    observers: ClassVar[list[Callable[[EmbeddedSimulator, str], None]]] = []
    """Called with each simulator and ``started`` or ``stopping`` (``fxcell.testing`` counts
    the faults of a test's simulators)."""

    def __init__(
        self,
        host: str | None = None,
        *,
        time_scale: float = 1.0,
        config: str | Path | None = None,
        joints: Sequence[float] | None = None,
        startup_timeout: float = 30.0,
        python: str | None = None,
        extra_args: Sequence[str] = (),
        programs: str | Path | None = None,
    ) -> None:
        if not time_scale > 0:
            raise InvalidArgumentError(f"time_scale must be > 0, got {time_scale!r}")
        self.requested_host = host
        self.host: str | None = None
        self.time_scale = time_scale
        self.config = config
        self.joints = None if joints is None else [float(v) for v in joints]
        self.startup_timeout = startup_timeout
        self.python = python or sys.executable
        self.extra_args = list(extra_args)
        self.programs = programs  # the controller's program directory (default: shipped)
        self.process: subprocess.Popen[bytes] | None = None
        self._lines: queue.Queue[bytes] = queue.Queue()
        self._drainer: threading.Thread | None = None

    def command(self, host: str) -> list[str]:
        cmd = [
            self.python,
            "-m",
            SIM_MODULE,
            "--host",
            host,
            "--time-scale",
            repr(self.time_scale),
            "--exit-with-parent",
        ]
        if self.config is not None:
            cmd += ["--config", str(self.config)]
        if self.joints is not None:
            cmd += ["--joints", ",".join(repr(v) for v in self.joints)]
        if self.programs is not None:
            cmd += ["--programs", str(self.programs)]
        return cmd + self.extra_args

    def start(self) -> str:
        """Start the process and wait for its ``listening`` line; returns the address."""
        if self.process is not None:
            raise SimulatorError("simulator already started")
        attempts = 1 if self.requested_host is not None else 5
        last = ""
        for _ in range(attempts):
            host = self.requested_host or self._free_host()
            ok, last = self._launch(host)
            if ok:
                self.host = host
                self._listening()
                return host
        raise SimulatorError(f"{self.what} did not start: {last}")

    what: ClassVar[str] = "simulator"
    """How errors name this kind's simulator."""

    def _free_host(self) -> str:
        """A loopback address where this kind's simulator can bind every port it serves."""
        return free_loopback_host()

    def _listening(self) -> None:
        """Once the process listens: tell the observers (the tests' fault watch)."""
        for observer in tuple(EmbeddedSimulator.observers):
            observer(self, "started")

    def _launch(self, host: str) -> tuple[bool, str]:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            self.command(host),
            stdout=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            env=env,
            # its own process group: a Ctrl-C in the terminal reaches only the owner, which
            # brakes the arm and then stops the simulator itself
            process_group=0,
        )
        self.process = proc
        self._lines = queue.Queue()
        self._drainer = threading.Thread(
            target=self._drain, args=(proc, self._lines), daemon=True, name="simulator-stdout"
        )
        self._drainer.start()
        deadline = time.monotonic() + self.startup_timeout
        while True:
            try:
                line = self._lines.get(timeout=max(0.0, min(0.5, deadline - time.monotonic())))
            except queue.Empty:
                line = None
            if line is not None and b"listening" in line:
                return True, ""
            if line == b"" or proc.poll() is not None:
                code = proc.wait()
                self.process = None
                self._drainer.join(2.0)
                self._drainer = None
                if proc.stdout is not None:
                    proc.stdout.close()
                return False, f"exit code {code} on {host}"
            if time.monotonic() > deadline:
                self.stop()
                return False, f"no 'listening' line within {self.startup_timeout} s on {host}"

    @staticmethod
    def _drain(proc: subprocess.Popen[bytes], lines: queue.Queue[bytes]) -> None:
        assert proc.stdout is not None
        with contextlib.suppress(ValueError, OSError):  # closed by stop() meanwhile
            for line in proc.stdout:
                lines.put(line)
        lines.put(b"")

    def stop(self, timeout: float = 10.0) -> None:
        """Terminate the process (SIGTERM, then SIGKILL after ``timeout``)."""
        if self.process is not None and self.host is not None:
            self._stopping()
        proc, self.process = self.process, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if self._drainer is not None:
            self._drainer.join(2.0)  # it sees the end of the output, then ends
            self._drainer = None
        if proc.stdout is not None:
            with contextlib.suppress(OSError):
                proc.stdout.close()

    def _stopping(self) -> None:
        for observer in tuple(EmbeddedSimulator.observers):
            observer(self, "stopping")

    @property
    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def _host(self) -> str:
        if self.host is None:
            raise SimulatorError("simulator not started")
        return self.host

    def inject(self, fault: str, *args: object) -> str:
        return inject(self._host(), fault, *args)

    def state(self) -> SimulatorState:
        return state(self._host())

    def set_joints(self, q: Sequence[float]) -> None:
        set_joints(self._host(), q)

    def __enter__(self) -> EmbeddedSimulator:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
