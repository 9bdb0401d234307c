"""The simulator process: servers on one loopback address and the 500 Hz control cycle.

Everything runs on one asyncio loop built on ``select()`` (microsecond timeouts; epoll
rounds to milliseconds). The cycle is scheduled on absolute deadlines: each wake-up
first sends the due RTDE packets, then advances the controller by as many 2 ms steps as
have elapsed (so controller time follows the wall clock even after a late wake-up).

Ports: Dashboard 29999, RTDE 30004, script 30003 and 30002, the Robotiq URCap's gripper
socket 63352 (:mod:`fxcell.sim.gripper`), and the simulator's own control port 29990
(fault injection and state queries, one text line per request, see :data:`CONTROL_PORT`).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import gc
import json
import logging
import math
import os
import selectors
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fxcell.calibration import Calibration
from fxcell.config import SIMULATOR_CAMERA_PORT, CellConfig
from fxcell.errors import FxcellError, InvalidArgumentError
from fxcell.geometry import Pose, rows_to_rotvec
from fxcell.layout import Layout
from fxcell.link.embedded import CONTROL_PORT
from fxcell.link.realtime import LINK_PRIORITY, normal_priority
from fxcell.protocol import (
    CONTROL_PERIOD,
    DASHBOARD_PORT,
    RTDE_PORT,
    SCRIPT_PORT,
    SECONDARY_PORT,
    URCAP_SCRIPT_PORT,
    RobotMode,
)
from fxcell.sim.constants import DELAYS, UNLOCK_DELAY
from fxcell.sim.controller import Controller, FaultError
from fxcell.sim.dashboard import Dashboard, DashboardConnection
from fxcell.sim.fusion import (
    COOLING_TIME,
    FUSION_TIME,
    MOULDS_STATION,
    POSITIONS_STATION,
    SEAT_TOLERANCE,
    FusionMachine,
    object_at,
    slots_of,
)
from fxcell.sim.fusion import FAULTS as MACHINE_FAULTS
from fxcell.sim.fusion import OWNER as MACHINE_OWNER
from fxcell.sim.gripper import URCAP_GRIPPER_PORT, GripperConnection, HandE, SimObject
from fxcell.sim.motion import ZERO6, Arm, TableGuard
from fxcell.sim.primary import PRIMARY_PORT, ClientInterfaces, StateConnection, StateSource
from fxcell.sim.program_store import ProgramStore
from fxcell.sim.rtde import RTDEHub
from fxcell.sim.signals import Signal, parse_signal, parse_value

if TYPE_CHECKING:
    from fxcell.sim.dynamics import ArmDynamics

log = logging.getLogger(__name__)

# CONTROL_PORT (29990), shared with the launcher: "inject FAULT [ARGS]", "state", "set_joints q..."
PORTS = (
    DASHBOARD_PORT,
    RTDE_PORT,
    PRIMARY_PORT,
    SECONDARY_PORT,
    SCRIPT_PORT,
    URCAP_GRIPPER_PORT,
    CONTROL_PORT,
    SIMULATOR_CAMERA_PORT,
)
IDLE_PERIOD = 0.02  # s: cycle period while no client streams and nothing moves
URCAP_TIMEOUT = 5.0
_RATE = 1.0 / CONTROL_PERIOD  # per cycle -> per second
_HALF_RATE = 0.5 / CONTROL_PERIOD
_POWERED = (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
URCAP_END_MARKER = "# NODE_CONTROL_LOOP_ENDS"


def _program_end(text: str) -> int:
    """Index just past a complete ``def``/``sec`` program at the start of ``text``, or -1."""
    pos = 0
    while True:
        nl = text.find("\n", pos)
        if nl < 0:
            return -1
        line = text[pos:nl]
        if line.rstrip() == "end" and pos > 0:
            return nl + 1
        pos = nl + 1


async def _read_program(reader: asyncio.StreamReader) -> str:
    """The script an ExternalControl server sends: a ``def`` program or a bare body.

    The body has no closing ``end`` and the sender keeps the connection open, so the text
    is complete at the control-loop end marker, at a complete program, or after a pause.
    """
    text = ""
    deadline = time.monotonic() + URCAP_TIMEOUT
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError("no program received")
        try:
            async with asyncio.timeout(min(remaining, 0.2)):
                chunk = await reader.read(65536)
        except TimeoutError:
            if text.strip():
                return text.lstrip()  # a pause after some text: that was all of it
            continue
        if not chunk:
            if text.strip():
                return text.lstrip()
            raise ConnectionError("connection closed before a program was sent")
        text += chunk.decode("utf-8", "replace")
        if URCAP_END_MARKER in text or _program_end(text.lstrip()) >= 0:
            return text.lstrip()


class ScriptConnection(asyncio.Protocol):
    """Port 30003/30002: collects URScript text and runs each complete program."""

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        self.text = ""

    def data_received(self, data: bytes) -> None:
        self.text += data.decode("utf-8", "replace")
        while True:
            stripped = self.text.lstrip()
            if not stripped:
                self.text = ""
                return
            first = stripped.split("\n", 1)[0]
            if first.startswith(("def ", "sec ")):
                end = _program_end(stripped)
                if end < 0:
                    self.text = stripped
                    return
                program, self.text = stripped[:end], stripped[end:]
            else:
                if "\n" not in stripped:
                    self.text = stripped
                    return
                program, self.text = first + "\n", stripped.split("\n", 1)[1]
            log.info("script port: program of %d bytes received", len(program))
            self.controller.run_script(program)


class ControlConnection(asyncio.Protocol):
    """The simulator's own control port: fault injection and state, one line each."""

    def __init__(self, server: SimServer) -> None:
        self.server = server
        self.transport: asyncio.Transport | None = None
        self.buffer = b""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        while self.transport is not None and b"\n" in self.buffer:
            raw, self.buffer = self.buffer.split(b"\n", 1)
            answer = self.server.control_command(raw.decode("utf-8", "replace").strip())
            self.transport.write((answer + "\n").encode())


DEFAULT_CALIBRATION = "ur3e_calibration.conf"
"""The shipped ``calibration.conf`` (in the configuration directory) of the arm the
simulator presents unless told otherwise: typical factory deltas, so that every client's
default path (reading the calibration at connect) is exercised."""


def default_calibration() -> Calibration:
    """The simulated arm's calibration by default (:data:`DEFAULT_CALIBRATION`)."""
    from fxcell.resources import resource_dir

    return Calibration.load(resource_dir("config") / DEFAULT_CALIBRATION)


class SimServer:
    """The simulator: controller, servers and the control cycle.

    ``calibration``: the arm's factory calibration (None: :func:`default_calibration`;
    ``Calibration.nominal()`` for UR's published model)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        *,
        time_scale: float = 1.0,
        config: CellConfig | None = None,
        joints: Sequence[float] | None = None,
        urcap_port: int = URCAP_SCRIPT_PORT,
        calibration: Calibration | None = None,
        machine: bool = True,
        machine_io: Mapping[str, Signal] | None = None,
        fusion_time: float = FUSION_TIME,
        cooling_time: float = COOLING_TIME,
        crucibles: str | None = None,
        programs: str | Path | None = None,
        unlock_delay: float = UNLOCK_DELAY,
    ) -> None:
        from fxcell.motion.calibration import CalibratedKinematics
        from fxcell.motion.kinematics import Kinematics

        self.host = host
        self.config = config or CellConfig.load()
        self.urcap_port = urcap_port
        limits = (self.config.limits.position_min, self.config.limits.position_max)

        self.calibration = calibration if calibration is not None else default_calibration()
        cal = self.calibration

        def make_kinematics(tcp: Any) -> Kinematics:
            if cal.is_nominal:
                return Kinematics.ur3e(tcp, limits)
            # the controller's FK, actual_TCP_pose and its own moves use the calibrated model
            return CalibratedKinematics(cal, tcp, limits)

        table = next((o for o in self.config.scene.objects if o.name == "table"), None)
        guard = TableGuard(table.position, table.size) if table is not None else None
        start = joints if joints is not None else self.config.home
        self.arm = Arm(make_kinematics(None), start, table=guard, make_kinematics=make_kinematics)
        store = ProgramStore(programs) if programs is not None else ProgramStore()
        self.controller = Controller(
            self.arm, time_scale=time_scale, programs=store, unlock_delay=unlock_delay
        )
        self.controller.client_host = "127.0.0.1"
        self.hub = RTDEHub(self.controller)
        self.dashboard = Dashboard(self.controller)
        self.controller.on_drop_rtde = self.hub.drop_all
        self.controller.on_shutdown = self.request_stop
        self.controller.request_urcap_program = self._start_urcap_request
        self._servers: list[asyncio.Server] = []
        self._stopping: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._deadline = 0.0
        self._handle: asyncio.Handle | None = None
        self._urcap_task: asyncio.Task[None] | None = None
        self._fk_version = -1
        self._qd_published: object = None
        self._prev_tcp: tuple[list[float], list[float]] | None = None
        self._modes_published: tuple[object, ...] = ()
        self._dynamics: ArmDynamics | None = None
        self._dynamics_key: tuple[object, ...] = ()
        self.late_cycles = 0
        self.stalls: collections.deque[tuple[float, float]] = collections.deque(maxlen=64)
        """(wall time it ended, length in s) of the newest stalls of the control cycle."""
        self._sends = [0.0] * 16384  # wall times of cycles that sent RTDE packets
        self._send_count = 0
        self._idle = False
        self.hub.on_activity = self.wake
        self.hub.on_dynamics = lambda: self._publish_dynamics(0)
        self.hub.load_dynamics = self._load_dynamics
        self._dynamics_waiting: list[Callable[[], None]] = []
        self._dynamics_loader: threading.Thread | None = None
        # 30001/30002/30003: primary/secondary state at 10 Hz, real-time packets at 500 Hz
        self.clients = ClientInterfaces(StateSource(self.controller, self.hub.state, cal))
        self.clients.on_activity = self.wake
        self.controller.on_robot_message = self.clients.broadcast
        self.publish_state()
        self.gripper = HandE(
            time_scale=time_scale,
            tcp_pose=lambda: Pose.from_ur(self.hub.state.actual_tcp_pose),
            powered=lambda: self.controller.robot_mode in _POWERED,
        )
        self.layout = Layout(self.config.layout)
        # every slot's grip point, to tell where an object stands (the layout is fixed)
        self._slot_points = [
            (
                st.name,
                st.config.holds,
                st.slots,
                np.array([st.grip_pose(x).position for x in st.slots]),
            )
            for st in self.layout
        ]
        self.machine: FusionMachine | None = None
        stations = self.layout.stations
        if machine and POSITIONS_STATION in stations and MOULDS_STATION in stations:
            self.machine = FusionMachine(
                self.layout,
                self.gripper.objects,
                self.controller.io,
                time_scale=time_scale,
                fusion_time=fusion_time,
                cooling_time=cooling_time,
                signals=machine_io,
            )
        elif machine:
            log.warning(
                "no fusion machine: the layout has no %r and %r stations",
                POSITIONS_STATION,
                MOULDS_STATION,
            )
        self.camera = self._make_camera()
        if crucibles:
            rack = self.layout.station("rack")
            for slot in slots_of(rack, crucibles):
                self.place_object(f"crucible-{slot}", rack.config.holds, "rack", slot, "sample")
        self.publish_state()

    def _make_camera(self) -> Any:
        """The configured camera, rendering this world (None when the layout has no holder)."""
        from fxcell.sim.camera import Renderer, SimCamera
        from fxcell.vision.model import Deck, Intrinsics

        vision = self.config.vision
        try:
            deck = Deck.from_config(vision, self.layout)
        except FxcellError as exc:
            log.warning("no camera: %s", exc)
            return None
        tcp = self.controller

        def flange() -> Pose:
            return Pose.from_ur(self.hub.state.actual_tcp_pose) @ Pose.from_ur(tcp.tcp).inverse()

        grips = {name: kind.grip_height for name, kind in self.layout.config.objects.items()}
        return SimCamera(
            Renderer(deck, Intrinsics.from_config(vision.camera)),
            vision.camera,
            lambda: list(self.gripper.objects.values()),
            grips,
            flange,
        )

    # ------------------------------------------------------------------ state

    def publish_state(self) -> None:
        """Copy the controller's state into the RTDE stream state (FK only when q changed).

        Runs every cycle: plain floats throughout (FK as 12 floats, the pose's rotation
        vector and the TCP's angular speed from them).
        """
        c, arm, s = self.controller, self.arm, self.hub.state
        s.timestamp = c.time
        version, qd = arm.version, arm.qd
        if version != self._fk_version or qd is not self._qd_published:
            self._qd_published = qd
            q, qd_list, qdd_list = arm.lists()
            s.actual_qd = s.target_qd = tuple(qd_list)
            s.target_qdd = tuple(qdd_list)
        if version != self._fk_version:
            self._fk_version = version
            q = arm.lists()[0]
            s.actual_q = s.target_q = tuple(q)
            f = arm.kinematics.forward_rows(q)
            p = f[9:]
            R = f[:9]
            s.actual_tcp_pose = s.target_tcp_pose = (*p, *rows_to_rotvec(R))
            # arm.moving without numpy: a velocity not the resting ZERO6 with a non-zero entry
            if self._prev_tcp is not None and qd is not ZERO6 and any(s.actual_qd):
                p0, R0 = self._prev_tcp
                # rotation in one cycle is tiny: its vector is the skew part of D = R·R0ᵀ,
                # of which only the six off-diagonal entries are needed
                r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
                o00, o01, o02, o10, o11, o12, o20, o21, o22 = R0
                d01 = r00 * o10 + r01 * o11 + r02 * o12
                d02 = r00 * o20 + r01 * o21 + r02 * o22
                d10 = r10 * o00 + r11 * o01 + r12 * o02
                d12 = r10 * o20 + r11 * o21 + r12 * o22
                d20 = r20 * o00 + r21 * o01 + r22 * o02
                d21 = r20 * o10 + r21 * o11 + r22 * o12
                s.tcp_speed = (
                    (p[0] - p0[0]) * _RATE,
                    (p[1] - p0[1]) * _RATE,
                    (p[2] - p0[2]) * _RATE,
                    (d21 - d12) * _HALF_RATE,
                    (d02 - d20) * _HALF_RATE,
                    (d10 - d01) * _HALF_RATE,
                )
            else:
                s.tcp_speed = s.zero6
            self._prev_tcp = (p, R)
        elif s.tcp_speed is not s.zero6:
            s.tcp_speed = s.zero6
        modes = (c.robot_mode, c.safety_mode, c.runtime_state)
        if modes != self._modes_published:  # what follows from the three modes alone
            self._modes_published = modes
            powered = c.robot_mode in _POWERED
            s.robot_mode = int(c.robot_mode)
            s.safety_mode = int(c.safety_mode)
            s.runtime_state = int(c.runtime_state)
            s.robot_status_bits = c.robot_status_bits
            s.safety_status_bits = c.safety_status_bits
            s.joint_mode = (c.joint_mode,) * 6
            s.robot_voltage = 48.0 if powered else 0.0
            s.robot_current = 0.6 if powered else 0.0
            s.joint_voltage = (48.0,) * 6 if powered else s.zero6
            # the energy meter (actual_robot_energy_consumed) runs while the arm is powered
            if powered and s.powered_since is None:
                s.powered_since = c.ticks
                s.power = s.robot_voltage * s.robot_current
            elif not powered and s.powered_since is not None:
                s.powered_ticks += c.ticks - s.powered_since
                s.powered_since = None
        s.digital_output_bits = c.io.output_bits
        s.digital_input_bits = c.io.input_bits
        s.analog_in = c.io.analog_in
        s.tool_analog_in = c.io.tool_analog_in
        s.analog_out = c.io.analog_out
        s.target_speed_fraction = c.io.speed_slider
        s.payload = c.payload_mass
        s.payload_cog = c.payload_cog
        s.tcp_offset = c.tcp

    def _load_dynamics(self, done: Callable[[], None]) -> None:
        """Load the dynamic model in a thread (importing Pinocchio takes a few hundred ms:
        the control cycle must not wait for it), then call ``done`` on the loop."""
        self._dynamics_waiting.append(done)
        if self._dynamics_loader is not None:
            return
        loop = self._loop
        assert loop is not None

        def load() -> None:
            # at normal priority (it inherited the control cycle's real-time one): two
            # simulators building their models side by side at real-time priority held
            # both CPUs for some 0.3 s each and starved the robot links
            normal_priority()
            try:
                from fxcell.sim.dynamics import ArmDynamics

                model: ArmDynamics | None = ArmDynamics()
            except Exception:
                log.exception("the arm's dynamic model could not be built: its outputs stay 0")
                model = None
            loop.call_soon_threadsafe(self._dynamics_loaded, model)

        self._dynamics_loader = threading.Thread(target=load, name="sim-dynamics", daemon=True)
        self._dynamics_loader.start()

    def _dynamics_loaded(self, model: ArmDynamics | None) -> None:
        self._dynamics = model
        self.hub.dynamics_ready = True
        waiting, self._dynamics_waiting = self._dynamics_waiting, []
        for done in waiting:
            done()

    def _publish_dynamics(self, steps: int) -> None:
        """The outputs computed from the arm's dynamic model (only while a recipe asks)."""
        if self._dynamics is None:
            return
        dyn, c, s, arm, wanted = (
            self._dynamics,
            self.controller,
            self.hub.state,
            self.arm,
            self.hub.dynamics_fields,
        )
        # the torques change only with the joint state, the payload and gravity: at rest
        # nothing is computed
        # (the arrays are replaced, never changed in place: compared by identity)
        key = (arm.q, arm.qd, arm.qdd, c.payload_mass, c.payload_cog, c.gravity)
        last = self._dynamics_key
        if (
            steps == 0
            or not last
            or key[0] is not last[0]
            or key[1] is not last[1]
            or key[2] is not last[2]
            or key[3:] != last[3:]
        ):
            self._dynamics_key = key
            if not last or key[3:] != last[3:]:
                dyn.set_payload(c.payload_mass, c.payload_cog)
                dyn.set_gravity(c.gravity)
            s.joint_torque = dyn.torques(arm.q, arm.qd, arm.qdd)
            if "target_base_wrench" in wanted:
                s.base_wrench = dyn.base_wrench()
        if "actual_TCP_acceleration" in wanted or "target_TCP_acceleration" in wanted:
            s.tcp_acceleration = dyn.tcp_acceleration(s.tcp_speed, steps)

    # ------------------------------------------------------------------ cycle

    def _cycle(self) -> None:
        """One wake-up: stream, then advance by every 2 ms grid point passed since the last.

        ``_deadline`` is the wall-clock time of the next unprocessed grid point, so the
        controller clock follows the wall clock whatever the wake-up times.
        """
        loop = self._loop
        assert loop is not None
        now = loop.time()
        steps = 0
        while self._deadline <= now + 5e-5:
            self._deadline += CONTROL_PERIOD
            steps += 1
        if steps > 1250:  # stalled 2.5 s (suspended process): resynchronise, do not catch up
            self.late_cycles += steps
            self._deadline = now + CONTROL_PERIOD
            steps = 1
        elif steps > 1 and not self._idle:
            self.late_cycles += steps - 1
            if steps * CONTROL_PERIOD >= STALL_REPORTED:
                self._stalled(steps * CONTROL_PERIOD)
        self.hub.poll()
        sent = self.hub.packets_sent
        self.hub.stream(steps)
        if self.hub.packets_sent != sent:
            self._sends[self._send_count % len(self._sends)] = now
            self._send_count += 1
        if steps:
            self.controller.tick(steps)
            if self.machine is not None:
                self.machine.tick(self.controller.time)
            self.publish_state()
            if self.hub.dynamics:
                self._publish_dynamics(steps)
            self.gripper.tick(self.controller.time)
            self.clients.stream()
        # Nobody streaming and nothing moving: wake at 50 Hz (the controller clock catches
        # up in one step). Streaming or motion: every cycle.
        self._idle = self.controller.idle and not self.hub.streaming and not self.clients.streaming
        wake_at = self._deadline + (IDLE_PERIOD - CONTROL_PERIOD if self._idle else 0.0)
        self._handle = loop.call_at(wake_at, self._cycle)

    def _stalled(self, seconds: float) -> None:
        """The control cycle ran ``seconds`` late: this process did not get to run (a busy
        or frozen host), which a real controller never does. Clients saw no state meanwhile."""
        self.stalls.append((time.time(), seconds))
        log.warning("the simulated controller stalled for %.0f ms (its host)", seconds * 1e3)

    def wake(self) -> None:
        """Leave the idle rate now (a client started streaming or sent a command)."""
        if self._idle and self._handle is not None and self._loop is not None:
            self._idle = False
            self._handle.cancel()
            self._handle = self._loop.call_soon(self._cycle)

    # ------------------------------------------------------------------ control port

    def control_command(self, line: str) -> str:
        words = line.split()
        if not words:
            return "error: empty request"
        cmd, args = words[0].lower(), words[1:]
        c = self.controller
        if cmd == "inject" and args and args[0].lower() in ("gripper_fault", "gripper_drop"):
            return self._inject_gripper(args[0].lower(), args[1:])
        if cmd == "inject" and args and args[0].lower() in MACHINE_FAULTS:
            if self.machine is None:
                return "error: the simulator has no fusion machine"
            if len(args) > 1:
                return f"error: {args[0].lower()} takes no arguments"
            return "ok: " + self.machine.inject(args[0].lower())
        if cmd == "gripper":
            return json.dumps(self.gripper.state())
        if cmd == "objects":
            return json.dumps({n: self._object_json(o) for n, o in self.gripper.objects.items()})
        if cmd == "add_object":
            return self._add_object(args)
        if cmd == "place_object":
            return self._place_object(args)
        if cmd == "offset_object":
            return self._offset_object(args)
        if cmd == "inject" and args and args[0].lower() == "place_offset":
            return self._place_offset(args[1:])
        if cmd == "set_input":
            return self._set_input(args)
        if cmd == "machine":
            if self.machine is None:
                return "error: the simulator has no fusion machine"
            return json.dumps(self.machine.report())
        if cmd == "inject" and args:
            try:
                return "ok: " + c.inject(args[0].lower(), args[1:])
            except FaultError as exc:
                return f"error: {exc}"
        if cmd == "state":
            return json.dumps(c.state(late_cycles=self.late_cycles, stalls=self.stalls))
        if cmd == "stats":
            if args[:1] == ["reset"]:
                self._send_count = 0
                self.late_cycles = 0
                return "ok: stats reset"
            n = min(self._send_count, len(self._sends))
            times = np.roll(np.array(self._sends), -(self._send_count % len(self._sends)))[-n:]
            periods = np.diff(times) * 1e3 if n > 2 else np.zeros(1)
            return json.dumps(
                {
                    "send_cycles": int(self._send_count),
                    "period_ms_median": float(np.median(periods)),
                    "period_ms_p99": float(np.percentile(periods, 99)),
                    "period_ms_max": float(periods.max()),
                    "late_cycles": self.late_cycles,
                }
            )
        if cmd == "push":
            return self._push(args)
        if cmd == "set_joints":
            try:
                q = [float(v) for v in args]
            except ValueError:
                return "error: set_joints needs 6 numbers"
            if len(q) != 6 or not all(math.isfinite(v) and abs(v) <= 2 * math.pi for v in q):
                return "error: set_joints needs 6 finite joint positions within ±2π"
            if self.arm.moving or self.arm.generator is not None:
                return "error: the arm is moving"
            self.arm.set_state(q, None, None)
            self.publish_state()  # the reply means the new pose is what every port reports
            self.gripper.tick(c.time)
            return "ok: joints set"
        return (
            f"error: unknown request {line!r} (inject FAULT [ARGS] | state | stats | "
            "set_joints Q*6 | push DX DY DZ | push D1..D6 | gripper | objects | "
            "add_object NAME KIND W H M X Y Z)"
            "set_joints Q*6 | gripper | objects | add_object NAME KIND W H M X Y Z | "
            "place_object NAME KIND STATION SLOT [CONTENTS] | "
            "offset_object NAME DX DY [TILT [AZ]] | set_input SIGNAL VALUE | machine)"
        )

    def _push(self, args: list[str]) -> str:
        """Move the arm by hand in freedrive: the TCP by (dx, dy, dz) m in the base frame,
        or the joints by six deltas (rad)."""
        usage = "error: push DX DY DZ (m, TCP in the base frame) | push D1..D6 (rad)"
        try:
            delta = [float(v) for v in args]
        except ValueError:
            return usage
        if len(delta) not in (3, 6) or not all(math.isfinite(v) for v in delta):
            return usage
        if not self.controller.teach_mode:
            return "error: the arm is not in freedrive (teach mode): it resists being pushed"
        if self.arm.moving:
            return "error: the arm is moving"
        q = np.asarray(self.arm.q, float)
        free = self.controller.free_axes
        if len(delta) == 6:
            if not all(free):
                return "error: push: freedrive constrains axes, push the TCP (DX DY DZ)"
            target = q + np.asarray(delta)
        else:
            # freedrive_mode's constraint: only the free translations of its feature frame
            # follow the hand; the orientation is kept
            R = Pose.from_ur(self.controller.freedrive_feature).rotation
            moved = R @ (np.asarray(free[:3], float) * (R.T @ np.asarray(delta)))
            pose = self.arm.kinematics.forward(q)
            goal = Pose(pose.position + moved, pose.rotation)
            solutions = self.arm.kinematics.inverse_all(goal)
            if not solutions:
                return "error: push: the arm cannot reach there"
            target = min(
                (np.asarray(s) for s in solutions), key=lambda s: float(np.abs(s - q).max())
            )
            if float(np.abs(target - q).max()) > 0.5:
                return "error: push: that would flip the arm's configuration"
        if np.any(np.abs(target) > 2 * math.pi):
            return "error: push: beyond the joint limits"
        self.arm.set_state(target.tolist(), None, None)
        self.publish_state()
        self.gripper.tick(self.controller.time)
        return "ok: pushed"

    def _inject_gripper(self, fault: str, args: list[str]) -> str:
        if fault == "gripper_drop":
            if args:
                return "error: gripper_drop takes no arguments"
            return "ok: " + self.gripper.drop()
        if len(args) > 1:
            return "error: gripper_fault takes at most a CODE"
        try:
            code = int(args[0], 0) if args else 0x0E
        except ValueError:
            return f"error: gripper_fault: not a fault code: {args[0]!r}"
        if not 1 <= code <= 255:
            return "error: gripper_fault: CODE must be in 1..255"
        return "ok: " + self.gripper.inject_fault(code)

    def _add_object(self, args: list[str]) -> str:
        usage = "error: add_object NAME KIND WIDTH HEIGHT MASS X Y Z (m, kg; upright)"
        if len(args) != 8:
            return usage
        try:
            width, height, mass, x, y, z = (float(v) for v in args[2:])
        except ValueError:
            return usage
        values = (width, height, mass, x, y, z)
        if not all(math.isfinite(v) for v in values) or min(width, height, mass) <= 0:
            return "error: add_object: sizes and mass must be finite and > 0"
        if width >= 0.050:
            return "error: add_object: wider than the Hand-E's 50 mm stroke"
        self.gripper.add_object(
            SimObject(args[0], args[1], width, height, mass, Pose.from_ur([x, y, z, 0, 0, 0]))
        )
        return f"ok: {args[0]} placed"

    def _object_json(self, obj: SimObject) -> dict[str, object]:
        """An object's JSON plus the layout slot it stands in (``station``/``slot``, or None)."""
        data = obj.as_json()
        data["station"] = data["slot"] = None
        if obj.held_from is None:
            for station, kind, slots, points in self._slot_points:
                if kind != obj.kind:
                    continue
                distance = np.linalg.norm(points - obj.pose.position, axis=1)
                i = int(np.argmin(distance))
                if distance[i] <= SEAT_TOLERANCE:
                    data["station"], data["slot"] = station, slots[i]
                    break
        return data

    def place_object(
        self, name: str, kind: str, station: str, slot: str, contents: str | None = None
    ) -> str:
        """Put a new object (or move one) with its grip point at a layout slot's grip pose."""
        if kind not in self.layout.config.objects:
            known = ", ".join(sorted(self.layout.config.objects)) or "none"
            raise InvalidArgumentError(f"unknown object kind {kind!r} (known: {known})")
        st, slot = self.layout.slot(station, slot)
        if st.config.holds != kind:
            raise InvalidArgumentError(f"station {st.name!r} holds {st.config.holds}s, not {kind}s")
        there = object_at(self.gripper.objects, st, slot)
        if there is not None and there.name != name:
            raise InvalidArgumentError(f"{st.name} {slot} is taken by {there.name}")
        size = self.layout.config.objects[kind]
        self.gripper.add_object(
            SimObject(
                name,
                kind,
                size.width,
                size.height,
                size.mass,
                st.grip_pose(slot),
                contents=contents,
            )
        )
        return f"{name} placed in {st.name} {slot}"

    def _place_object(self, args: list[str]) -> str:
        if len(args) not in (4, 5):
            return "error: place_object NAME KIND STATION SLOT [CONTENTS]"
        name, kind, station, slot = args[:4]
        # an object moved keeps its contents; a new crucible comes with a sample ("-": empty)
        contents: str | None
        if len(args) == 5:
            contents = None if args[4] == "-" else args[4]
        elif name in self.gripper.objects:
            contents = self.gripper.objects[name].contents
        else:
            contents = "sample" if kind == "crucible" else None
        try:
            return "ok: " + self.place_object(name, kind, station, slot, contents)
        except InvalidArgumentError as exc:
            return f"error: place_object: {exc}"

    def _offset_object(self, args: list[str]) -> str:
        """``offset_object NAME DX DY [TILT_DEG [AZIMUTH_DEG]]``: shift a standing object by
        (dx, dy) m along the base axes and lean it ``TILT_DEG`` towards ``AZIMUTH_DEG`` (from
        base +x), turning about its bottom's edge (a crucible resting on its pocket's rim)."""
        usage = "error: offset_object NAME DX DY [TILT_DEG [AZIMUTH_DEG]]"
        if not 3 <= len(args) <= 5:
            return usage
        obj = self.gripper.objects.get(args[0])
        if obj is None:
            return f"error: offset_object: no object {args[0]!r}"
        if obj.held_from is not None:
            return f"error: offset_object: {args[0]} is in the gripper"
        try:
            dx, dy, tilt_deg, azimuth_deg = (float(v) for v in [*args[1:], "0", "0"][:4])
        except ValueError:
            return usage
        if not all(math.isfinite(v) for v in (dx, dy, tilt_deg, azimuth_deg)):
            return usage
        if abs(dx) > 0.2 or abs(dy) > 0.2 or not 0 <= tilt_deg < 60:
            return "error: offset_object: |DX|, |DY| <= 0.2 m and 0 <= TILT_DEG < 60"
        tilt, az = math.radians(tilt_deg), math.radians(azimuth_deg)
        grip = (
            self.layout.config.objects[obj.kind].grip_height
            if (obj.kind in self.layout.config.objects)
            else obj.height / 2
        )
        down = obj.pose.rotation[:, 2]
        bottom = obj.pose.position + down * grip + np.array([dx, dy, 0.0])
        lean = Pose.from_rotvec((0, 0, 0), np.array([-math.sin(az), math.cos(az), 0.0]) * tilt)
        # turn about the bottom's edge on the lean side: the bottom lifts and slides
        r = obj.width / 2 * 0.78
        bottom = bottom + np.array(
            [math.cos(az) * r * (1 - math.cos(tilt)), math.sin(az) * r * (1 - math.cos(tilt)),
             r * math.sin(tilt)]
        )  # fmt: skip
        rotation = lean.rotation @ obj.pose.rotation
        obj.pose = Pose(bottom - rotation[:, 2] * grip, rotation)
        return f"ok: {obj.name} moved by ({dx:g}, {dy:g}) m, leaning {tilt_deg:g}°"

    def _place_offset(self, args: list[str]) -> str:
        if len(args) != 2:
            return "error: inject place_offset DX DY (m, base frame)"
        try:
            dx, dy = float(args[0]), float(args[1])
        except ValueError:
            return "error: inject place_offset DX DY (m, base frame)"
        if not (math.isfinite(dx) and math.isfinite(dy)) or max(abs(dx), abs(dy)) > 0.05:
            return "error: place_offset: |DX|, |DY| <= 0.05 m"
        self.gripper.release_offset = (dx, dy)
        return f"ok: the next object released lands ({dx:g}, {dy:g}) m off"

    def _set_input(self, args: list[str]) -> str:
        if len(args) != 2:
            return "error: set_input SIGNAL VALUE (e.g. DI5 1, CI2 0, TI0 1, AI0 4.2)"
        try:
            signal = parse_signal(args[0])
            value = parse_value(signal, args[1])
            self.controller.io.set_input(signal, value)
        except InvalidArgumentError as exc:
            hint = ""
            if MACHINE_OWNER in str(exc):
                hint = " (free it with --no-machine or another --machine-io)"
            return f"error: set_input: {exc}{hint}"
        self.publish_state()  # the reply means every RTDE client gets the new value next
        return f"ok: {signal} = {value:g}"

    # ------------------------------------------------------------------ URCap

    def _start_urcap_request(self) -> None:
        if self._urcap_task is not None and not self._urcap_task.done():
            self._urcap_task.cancel()
        self._urcap_task = asyncio.ensure_future(self._request_urcap_program())

    async def _request_urcap_program(self) -> None:
        host = self.controller.client_host
        c = self.controller
        try:
            async with asyncio.timeout(URCAP_TIMEOUT):
                reader, writer = await asyncio.open_connection(host, self.urcap_port)
        except (OSError, TimeoutError) as exc:
            c.stop(
                f"ExternalControl: cannot reach the remote PC at {host}:{self.urcap_port} ({exc})"
            )
            return
        try:
            writer.write(b"request_program\n")
            await writer.drain()
            text = await _read_program(reader)
        except (OSError, TimeoutError, ConnectionError) as exc:
            c.stop(f"ExternalControl: program request failed ({exc})")
            return
        finally:
            writer.close()
        if c.runtime_state.name == "PLAYING" and c.script is None:
            log.info("ExternalControl: received a program of %d bytes", len(text))
            c.run_script(text.lstrip(), via_urcap=True)

    # ------------------------------------------------------------------ life

    def _client_interface(self, *, realtime: bool) -> StateConnection:
        script = ScriptConnection(self.controller)
        return StateConnection(self.clients, realtime, script.data_received)

    def request_stop(self) -> None:
        if self._stopping is not None:
            self._stopping.set()

    async def serve(
        self,
        *,
        boot_delay: float = 0.0,
        announce: bool = True,
        handle_signals: bool = True,
        on_listening: Callable[[], None] | None = None,
    ) -> None:
        """Serve until :meth:`request_stop` (SIGINT/SIGTERM with ``handle_signals``, which
        only the main thread can have); ``on_listening`` is called once every port listens."""
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._stopping = asyncio.Event()
        # ur_rtde's default receive recipe asks for actual_current_as_torque: load the
        # dynamic model now, while booting, rather than when the first client asks
        self._load_dynamics(lambda: None)
        try:
            await self._serve(self._stopping, boot_delay, announce, handle_signals, on_listening)
        finally:
            loader = self._dynamics_loader
            if loader is not None and loader.is_alive():
                # however serving ends (stopped, or a port taken): a daemon thread still
                # inside Pinocchio's C++ (its import takes a few hundred ms) when the
                # interpreter exits is unwound by force, which C++'s catch-all handlers
                # turn into an abort ("FATAL: exception not rethrown", exit code -6)
                await loop.run_in_executor(None, loader.join)

    async def _serve(
        self,
        stopping: asyncio.Event,
        boot_delay: float,
        announce: bool,
        handle_signals: bool,
        on_listening: Callable[[], None] | None,
    ) -> None:
        loop = asyncio.get_running_loop()
        if boot_delay > 0:
            await asyncio.sleep(boot_delay)
        factories: list[tuple[int, Any]] = [
            (DASHBOARD_PORT, lambda: DashboardConnection(self.dashboard, self.controller.shutdown)),
            (PRIMARY_PORT, lambda: self._client_interface(realtime=False)),
            (SECONDARY_PORT, lambda: self._client_interface(realtime=False)),
            (SCRIPT_PORT, lambda: self._client_interface(realtime=True)),
            (URCAP_GRIPPER_PORT, lambda: GripperConnection(self.gripper)),
            (CONTROL_PORT, lambda: ControlConnection(self)),
        ]
        if self.camera is not None:
            from fxcell.sim.camera import CameraConnection

            camera = self.camera
            factories.append((SIMULATOR_CAMERA_PORT, lambda: CameraConnection(camera.snapshot)))
        try:
            self.hub.listen(loop, self.host, RTDE_PORT)
            for port, factory in factories:
                server = await loop.create_server(factory, self.host, port, reuse_address=True)
                self._servers.append(server)
        except OSError:
            self.hub.close()
            for srv in self._servers:
                srv.close()
            raise
        signals = (signal.SIGINT, signal.SIGTERM) if handle_signals else ()
        for sig in signals:
            loop.add_signal_handler(sig, self.request_stop)
        self._deadline = loop.time() + CONTROL_PERIOD
        self._handle = loop.call_at(self._deadline, self._cycle)
        if announce:
            print(
                f"fxcell sim listening on {self.host}: dashboard {DASHBOARD_PORT}, rtde "
                f"{RTDE_PORT}, primary/secondary/real-time {PRIMARY_PORT}/{SECONDARY_PORT}/"
                f"{SCRIPT_PORT}, "
                f"gripper {URCAP_GRIPPER_PORT}, control {CONTROL_PORT}"
                + (f", camera {SIMULATOR_CAMERA_PORT}" if self.camera is not None else ""),
                flush=True,
            )
        if on_listening is not None:
            on_listening()
        try:
            await stopping.wait()
        finally:
            if self._handle is not None:
                self._handle.cancel()
            if self._urcap_task is not None:
                self._urcap_task.cancel()
            self.hub.close()
            self.clients.close()
            for srv in self._servers:
                srv.close()
            if self.camera is not None:
                self.camera.close()
            for sig in signals:
                loop.remove_signal_handler(sig)


STALL_REPORTED = 0.05
"""s: a control cycle that ran this late is a stall of the simulator itself (a real controller
never has one): logged and kept in the ``state`` reply's ``stalls``."""

PRIORITY_ENV = "FXCELL_SIM_PRIORITY"
"""Set to ``normal`` to keep the simulator at its parent's priority (benchmarks comparing
it with a peer at equal priority), to ``realtime`` to ask for SCHED_FIFO as ``--realtime``
does (the test suite: a real controller keeps its 2 ms cycle whatever the PC does);
anything else leaves the default (reniced)."""


REALTIME_PRIORITY = LINK_PRIORITY + 5
"""The simulator's SCHED_FIFO priority when real time: above the robot link's. A real
controller is a machine of its own, whose cycle no process on the cell PC can delay; at a
priority below the link's, the links of tests running side by side (their ur_rtde connects,
their imports) took the CPUs from the simulators and stalled their cycles by 70-110 ms."""


def _raise_priority(realtime: bool = False, nice: int = -5) -> None:
    """Best effort: a controller keeps time before other work (needs the privilege).

    ``realtime`` asks for SCHED_FIFO at :data:`REALTIME_PRIORITY` (the kernel still
    throttles real-time tasks at 95 % of a core); else the process is reniced. Nothing is
    changed when the environment sets ``FXCELL_SIM_PRIORITY=normal``.
    """
    mode = os.environ.get(PRIORITY_ENV, "").strip().lower()
    if mode == "normal":
        return
    if realtime or mode == "realtime":
        with contextlib.suppress(OSError, AttributeError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
            return
    with contextlib.suppress(OSError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, 0, nice)


def new_event_loop() -> asyncio.AbstractEventLoop:
    """An event loop whose timers have microsecond resolution (select, not epoll)."""
    return asyncio.SelectorEventLoop(selectors.SelectSelector())


def run(
    host: str,
    *,
    time_scale: float = 1.0,
    config: CellConfig | None = None,
    joints: Sequence[float] | None = None,
    urcap_port: int = URCAP_SCRIPT_PORT,
    realtime: bool = False,
    calibration: Calibration | None = None,
    **world: Any,
) -> int:
    """Run the simulator until SIGINT/SIGTERM or a dashboard ``shutdown``; exit code.

    ``world``: the fusion machine and objects (:class:`SimServer`'s ``machine``,
    ``machine_io``, ``fusion_time``, ``cooling_time``, ``crucibles``), the program
    store (``programs``) and the protective stop's ``unlock_delay``.
    """
    try:
        sim = SimServer(
            host,
            time_scale=time_scale,
            config=config,
            joints=joints,
            urcap_port=urcap_port,
            calibration=calibration,
            **world,
        )
    except InvalidArgumentError as exc:
        print(f"fxcell sim: {exc}", file=sys.stderr)
        return 2
    # Everything built so far lives as long as the process: keep it out of the cyclic
    # collector's full passes, which otherwise pause the control cycle for 20+ ms.
    gc.freeze()
    # Built at normal priority (a controller boots before it keeps time); the thread that
    # runs the control cycle from here on, and the threads it starts, run above it.
    _raise_priority(realtime)
    loop = new_event_loop()
    try:
        loop.run_until_complete(sim.serve(boot_delay=DELAYS["boot"] * time_scale))
    except OSError as exc:
        print(f"fxcell sim: cannot listen on {host}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    finally:
        loop.close()
    return 0
