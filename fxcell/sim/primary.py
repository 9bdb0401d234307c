"""The controller's client interfaces: primary 30001, secondary 30002, real-time 30003.

As on a PolyScope 5 controller (``POLYSCOPE_VERSION``), every client of these ports may send
URScript (the script text goes to the simulator's program dispatch) and receives state:

- 30001 / 30002: a *version message* (type 20, robot message type 3) on connect, then a
  *robot state message* (type 16) at 10 Hz made of sub-packages, each a ``>iB`` length
  (header included) and type: robot mode data (0), joint data (1), tool data (2),
  masterboard data (3, with the digital I/O bits), cartesian info (4), kinematics info (5,
  the calibrated DH parameters, see :mod:`fxcell.calibration`), configuration data (6),
  force mode data (7) and additional info (8), in the e-series 5.x layouts. Runtime
  errors and ``textmsg`` output go out as robot messages (type 20) too.
- 30003: the real-time packet at 500 Hz, the layout of 5.10 and later: an ``int32`` length
  (1220) and 152 doubles.

A client that does not read (ur_rtde's control interface only writes its script to 30003)
is skipped while its send buffer is full, as the controller drops packets for it. A new
client is first sent anything ``GREETING_DELAY`` after it connected: a client that writes a
script and closes at once would otherwise answer our first bytes with a reset that discards
its script before it is read.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import socket
import struct
from collections.abc import Callable
from typing import TYPE_CHECKING

from fxcell.protocol import RobotMode, RuntimeState, SafetyMode
from fxcell.sim.constants import POLYSCOPE_BUILD_DATE, POLYSCOPE_VERSION
from fxcell.sim.events import RobotMessage, RuntimeException, TextMessage

if TYPE_CHECKING:
    from fxcell.calibration import Calibration
    from fxcell.sim.controller import Controller
    from fxcell.sim.rtde import StreamState

log = logging.getLogger(__name__)

PRIMARY_PORT = 30001
ROBOT_STATE = 16
ROBOT_MESSAGE = 20
PRIMARY_PERIOD_CYCLES = 50  # 10 Hz at the 2 ms control cycle
GREETING_DELAY = 0.02  # s of controller time before a new client is sent anything
MAX_BACKLOG = 64 * 1024  # bytes a non-reading client may have queued before packets are dropped
SEND_BUFFER = 32 * 1024  # SO_SNDBUF of a client connection (the kernel doubles it)

# robot message types (type 20) and sources
MESSAGE_TEXT = 0
MESSAGE_VERSION = 3
MESSAGE_RUNTIME_EXCEPTION = 10
SOURCE_CONTROLLER = -2

UR3_ROBOT_TYPE = 2  # robotType in the configuration data (UR5 1, UR3 2, UR10 3, UR16 4)
CONTROLLER_BOX_TYPE = 6
ROBOT_SUB_TYPE = 1

_HEADER = struct.Struct(">iB")
_ROBOT_MODE = struct.Struct(">iBQ???????BBdddB")
_JOINT = struct.Struct(">dddffffB")
_TOOL = struct.Struct(">iBbbddfBffB")
_MASTERBOARD = struct.Struct(">iBiibbddbbddffffBBbIBBB")
_CARTESIAN = struct.Struct(">iB12d")
_FORCE_MODE = struct.Struct(">iB7d")
_ADDITIONAL = struct.Struct(">iB???B")
_CONFIG_BODY = struct.Struct(">12d12d5d24d4i")
REALTIME_DOUBLES = 152
REALTIME = struct.Struct(f">i{REALTIME_DOUBLES}d")  # 1220 bytes
_REALTIME_PACK = REALTIME.pack

_POWERED = (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
_ESTOPS = (SafetyMode.ROBOT_EMERGENCY_STOP, SafetyMode.SYSTEM_EMERGENCY_STOP)


def robot_message(kind: int, body: bytes, timestamp: float) -> bytes:
    """A robot message (type 20): ``>iB`` header, uint64 timestamp (µs), source, kind, body."""
    payload = struct.pack(">Qbb", int(timestamp * 1e6), SOURCE_CONTROLLER, kind) + body
    return _HEADER.pack(_HEADER.size + len(payload), ROBOT_MESSAGE) + payload


def version_message(version: tuple[int, int, int, int], timestamp: float = 0.0) -> bytes:
    """The version message a client of 30001/30002 gets on connect."""
    name = b"URControl"
    body = (
        struct.pack(">b", len(name))
        + name
        + struct.pack(">BBii", version[0], version[1], version[2], version[3])
        + f"{POLYSCOPE_BUILD_DATE:%d-%m-%Y, %H:%M:%S}".encode()
    )
    return robot_message(MESSAGE_VERSION, body, timestamp)


def text_message(text: str, timestamp: float) -> bytes:
    """A text message (``textmsg``) as a robot message."""
    return robot_message(MESSAGE_TEXT, text.encode("utf-8", "replace"), timestamp)


def runtime_exception_message(text: str, line: int, column: int, timestamp: float) -> bytes:
    """A runtime exception message: script line and column, then the text."""
    body = struct.pack(">ii", line, column) + text.encode("utf-8", "replace")
    return robot_message(MESSAGE_RUNTIME_EXCEPTION, body, timestamp)


def encode_robot_message(message: RobotMessage) -> bytes:
    """The controller's typed message as the primary/secondary interfaces send it."""
    match message:
        case TextMessage(text, time):
            return text_message(text, time)
        case RuntimeException(text, line, column, time):
            return runtime_exception_message(text, line, column, time)


class StateSource:
    """Packs the primary and real-time packets from the controller and the RTDE stream state."""

    def __init__(
        self, controller: Controller, state: StreamState, calibration: Calibration
    ) -> None:
        self.c = controller
        self.s = state
        self.kinematics_info = calibration.kinematics_info()
        theta, a, d, alpha = calibration.dh()
        limits = [v for _ in range(6) for v in (-2 * math.pi, 2 * math.pi)]
        speeds = [math.pi] * 3 + [2 * math.pi] * 3
        accelerations = [v * 5.0 for v in speeds]
        motion = [v for pair in zip(speeds, accelerations, strict=True) for v in pair]
        defaults = [1.05, 1.4, 0.25, 1.2, 0.02]  # vJoint, aJoint, vTool, aTool, eqRadius
        body = _CONFIG_BODY.pack(
            *limits,
            *motion,
            *defaults,
            *a,
            *d,
            *alpha,
            *theta,
            3,
            CONTROLLER_BOX_TYPE,
            UR3_ROBOT_TYPE,
            ROBOT_SUB_TYPE,
        )
        self.configuration = _HEADER.pack(_HEADER.size + len(body), 6) + body

    def robot_state(self) -> bytes:
        """One robot state message (type 16)."""
        c, s = self.c, self.s
        powered = c.robot_mode in _POWERED
        io = c.io
        parts = [
            _ROBOT_MODE.pack(
                _ROBOT_MODE.size,
                0,
                int(c.time * 1e6),
                True,
                True,
                powered,
                c.safety_mode in _ESTOPS,
                c.safety_mode == SafetyMode.PROTECTIVE_STOP,
                c.runtime_state == RuntimeState.PLAYING,
                c.runtime_state in (RuntimeState.PAUSED, RuntimeState.PAUSING),
                int(c.robot_mode) & 0xFF,
                1 if c.teach_mode else 0,  # control mode: teach (freedrive) or position
                io.speed_slider,
                s.speed_scaling,
                1.0,
                0,
            ),
            _HEADER.pack(_HEADER.size + 6 * _JOINT.size, 1)
            + b"".join(
                _JOINT.pack(
                    s.actual_q[j],
                    s.target_q[j],
                    s.actual_qd[j],
                    s.current[j],
                    s.joint_voltage[j],
                    s.temperatures[j],
                    0.0,
                    c.joint_mode,
                )
                for j in range(6)
            ),
            _TOOL.pack(_TOOL.size, 2, 0, 0, 0.0, 0.0, 48.0 if powered else 0.0, 24, 0.0, 30.0, 253),
            _MASTERBOARD.pack(
                _MASTERBOARD.size,
                3,
                s.digital_input_bits & 0x3FFFF,
                io.output_bits & 0x3FFFF,
                0,
                0,
                0.0,
                0.0,
                0,
                0,
                io.analog_out[0],
                io.analog_out[1],
                35.0,
                s.robot_voltage,
                s.robot_current,
                0.0,
                int(c.safety_mode) & 0xFF,
                0,
                0,  # no Euromap67 interface: its fields are absent
                0,
                0,
                0,
                0,
            ),
            _CARTESIAN.pack(_CARTESIAN.size, 4, *s.actual_tcp_pose, *c.tcp),
            b"" if c.kinematics_info_hidden else self.kinematics_info,
            self.configuration,
            _FORCE_MODE.pack(_FORCE_MODE.size, 7, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
            _ADDITIONAL.pack(_ADDITIONAL.size, 8, False, False, False, 0),
        ]
        body = b"".join(parts)
        return _HEADER.pack(_HEADER.size + len(body), ROBOT_STATE) + body

    def realtime(self) -> bytes:
        """One real-time packet (30003), the 5.10+ layout of 152 doubles.

        One ``pack`` call on the fields as they are (struct packs the integer fields as
        doubles, exactly): this runs every cycle.
        """
        c, s = self.c, self.s
        z6 = s.zero6
        return _REALTIME_PACK(
            REALTIME.size,
            s.timestamp,
            *s.target_q,
            *s.target_qd,
            *s.target_qdd,
            *s.current,
            *s.moment,
            *s.actual_q,
            *s.actual_qd,
            *s.current,
            *z6,  # I control
            *s.actual_tcp_pose,
            *s.tcp_speed,
            *z6,  # TCP force
            *s.target_tcp_pose,
            *s.tcp_speed,
            s.digital_input_bits,
            *s.temperatures,
            s.execution_time / 1000.0,  # controller timer, s
            0.0,  # test value
            s.robot_mode,
            *s.joint_mode,
            s.safety_mode,
            *z6,  # used by UR software only
            *s.accelerometer,
            *z6,  # used by UR software only
            s.speed_scaling,
            0.0,  # linear momentum norm
            0.0,
            0.0,  # used by UR software only
            s.main_voltage,
            s.robot_voltage,
            s.robot_current,
            *s.joint_voltage,
            s.digital_output_bits,
            s.runtime_state,
            *s.elbow_position,
            *s.zero3,  # elbow velocity
            s.safety_status_bits,
            0.0,
            0.0,
            0.0,  # used by UR software only
            c.payload_mass,
            *c.payload_cog,
            *z6,  # payload inertia
        )


class StateConnection(asyncio.Protocol):
    """A client of 30001, 30002 or 30003: its script text goes to ``on_script``."""

    def __init__(self, hub: ClientInterfaces, realtime: bool, on_script: Callable[[bytes], None]):
        self.hub = hub
        self.realtime = realtime
        self.on_script = on_script
        self.transport: asyncio.Transport | None = None
        self.dropped = 0
        self.greet_at = math.inf  # controller time from which it is sent packets

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            # A kernel send buffer of a few hundred packets, not Linux's megabytes: a client
            # that never reads (ur_rtde's control interface on 30003) is found backlogged
            # within ~0.1 s instead of being sent ~6 s of 500 Hz packets first.
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        self.hub.connected(self)

    def connection_lost(self, exc: Exception | None) -> None:
        self.hub.disconnected(self)
        self.transport = None

    def data_received(self, data: bytes) -> None:
        self.on_script(data)

    @property
    def backlogged(self) -> bool:
        """Closed, or so far behind that packets for it are dropped (it does not read)."""
        t = self.transport
        return t is None or t.is_closing() or t.get_write_buffer_size() > MAX_BACKLOG

    def send(self, packet: bytes) -> None:
        if self.backlogged:
            self.dropped += 1  # the client does not read: drop, as the controller does
            return
        assert self.transport is not None
        self.transport.write(packet)


class ClientInterfaces:
    """Every client of 30001/30002/30003 and what they are sent each control cycle."""

    def __init__(self, source: StateSource) -> None:
        self.source = source
        self.primary: set[StateConnection] = set()
        self.realtime: set[StateConnection] = set()
        self.pending: set[StateConnection] = set()  # connected, not yet greeted
        self._last_primary_slot = -1
        self.on_activity: Callable[[], None] = lambda: None

    @property
    def streaming(self) -> bool:
        """Some client gets the 500 Hz real-time packet (the cycle must not idle)."""
        return bool(self.realtime or self.pending)

    def connected(self, conn: StateConnection) -> None:
        conn.greet_at = self.source.c.time + GREETING_DELAY
        self.pending.add(conn)
        self.on_activity()

    def _greet(self, now: float) -> None:
        for conn in [c for c in self.pending if c.greet_at <= now]:
            self.pending.discard(conn)
            if conn.transport is None:
                continue
            if conn.realtime:
                self.realtime.add(conn)
            else:
                self.primary.add(conn)
                conn.send(version_message(POLYSCOPE_VERSION, now))
                conn.send(self.source.robot_state())

    def disconnected(self, conn: StateConnection) -> None:
        self.pending.discard(conn)
        self.primary.discard(conn)
        self.realtime.discard(conn)

    def broadcast(self, message: RobotMessage) -> None:
        """A robot message (text, runtime error) to every primary/secondary client."""
        if not self.primary:
            return
        packet = encode_robot_message(message)
        for conn in list(self.primary):
            conn.send(packet)

    def stream(self) -> None:
        """Send what is due at the controller's current time (call after each advance)."""
        if self.pending:
            self._greet(self.source.c.time)
        readers = [conn.transport for conn in self.realtime if not conn.backlogged]
        if readers:  # ur_rtde's control interface never reads 30003: no packing for it
            packet = self.source.realtime()
            for transport in readers:
                transport.write(packet)  # type: ignore[union-attr]  # not backlogged: open
        if self.primary:
            slot = self.source.c.ticks // PRIMARY_PERIOD_CYCLES
            if slot != self._last_primary_slot:
                self._last_primary_slot = slot
                packet = self.source.robot_state()
                for conn in list(self.primary):
                    conn.send(packet)

    def close(self) -> None:
        for conn in list(self.primary | self.realtime | self.pending):
            if conn.transport is not None:
                conn.transport.close()


__all__ = [
    "PRIMARY_PORT",
    "REALTIME",
    "ClientInterfaces",
    "StateConnection",
    "StateSource",
    "encode_robot_message",
    "robot_message",
    "runtime_exception_message",
    "text_message",
    "version_message",
]
