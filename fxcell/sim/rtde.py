"""RTDE server (port 30004, protocol version 2) of the simulator.

Packets are ``>H`` size (header included), ``B`` type, payload. Output recipes are
compiled once into a single ``struct`` call (generated code, no per-field Python work
per sample); the controller's state is published into a :class:`StreamState` each cycle
and every started connection packs and writes its recipes at its own frequency.

Recipe ids are numbered per connection and per direction from 1, the way ur_rtde
numbers its input recipes. An input variable belongs to the first connection that sets
it up: another connection asking for it gets ``IN_USE`` (recipe id 0), until the owner
disconnects. Unknown names are answered ``NOT_FOUND``. Oversized input packets are
accepted (the recipe's fields are read from their start).
"""

from __future__ import annotations

import asyncio
import logging
import math
import socket
import struct
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from fxcell.protocol import CONTROL_PERIOD
from fxcell.sim.constants import POLYSCOPE_VERSION, REGISTER_COUNT

if TYPE_CHECKING:
    from fxcell.sim.controller import Controller

log = logging.getLogger(__name__)

HEADER = struct.Struct(">HB")
TYPE_CODES = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
VECTOR_TYPES = frozenset({"VECTOR3D", "VECTOR6D", "VECTOR6INT32", "VECTOR6UINT32"})
MAX_WRITE_BUFFER = 4 * 1024 * 1024  # a client this far behind is dropped
QUIET_CYCLES = 250  # a started client silent this long is read by the event loop instead
MAX_RECIPE_NAMES = 2048  # bytes: the RTDE guide's limit on a recipe's list of names
MAX_RECIPES = 255  # per connection and direction: a recipe id is a uint8 and 0 means "failed"
V1_FREQUENCY = 125.0  # Hz: protocol version 1 outputs have no frequency of their own

V6 = "VECTOR6D"
# name -> (RTDE type, Python expression over the StreamState ``s`` and registers ``r``)
OUTPUTS: dict[str, tuple[str, str]] = {
    "timestamp": ("DOUBLE", "s.timestamp"),
    "target_q": (V6, "s.target_q"),
    "target_qd": (V6, "s.target_qd"),
    "target_qdd": (V6, "s.target_qdd"),
    "target_current": (V6, "s.current"),
    "target_moment": (V6, "s.moment"),
    "actual_q": (V6, "s.actual_q"),
    "actual_qd": (V6, "s.actual_qd"),
    "actual_current": (V6, "s.current"),
    "actual_current_window": (V6, "s.zero6"),
    "joint_control_output": (V6, "s.zero6"),
    "actual_TCP_pose": (V6, "s.actual_tcp_pose"),
    "actual_TCP_speed": (V6, "s.tcp_speed"),
    "actual_TCP_force": (V6, "s.zero6"),
    "target_TCP_pose": (V6, "s.target_tcp_pose"),
    "target_TCP_speed": (V6, "s.tcp_speed"),
    "actual_digital_input_bits": ("UINT64", "s.digital_input_bits"),
    "joint_temperatures": (V6, "s.temperatures"),
    "actual_execution_time": ("DOUBLE", "s.execution_time"),
    "robot_mode": ("INT32", "s.robot_mode"),
    "joint_mode": ("VECTOR6INT32", "s.joint_mode"),
    "safety_mode": ("INT32", "s.safety_mode"),
    "safety_status": ("INT32", "s.safety_mode"),
    "actual_tool_accelerometer": ("VECTOR3D", "s.accelerometer"),
    "speed_scaling": ("DOUBLE", "s.speed_scaling"),
    "target_speed_fraction": ("DOUBLE", "s.target_speed_fraction"),
    "actual_momentum": ("DOUBLE", "0.0"),
    "actual_main_voltage": ("DOUBLE", "s.main_voltage"),
    "actual_robot_voltage": ("DOUBLE", "s.robot_voltage"),
    "actual_robot_current": ("DOUBLE", "s.robot_current"),
    "actual_joint_voltage": (V6, "s.joint_voltage"),
    "actual_digital_output_bits": ("UINT64", "s.digital_output_bits"),
    "runtime_state": ("UINT32", "s.runtime_state"),
    "elbow_position": ("VECTOR3D", "s.elbow_position"),
    "elbow_velocity": ("VECTOR3D", "s.zero3"),
    "robot_status_bits": ("UINT32", "s.robot_status_bits"),
    "safety_status_bits": ("UINT32", "s.safety_status_bits"),
    "analog_io_types": ("UINT32", "0"),
    "standard_analog_input0": ("DOUBLE", "s.analog_in[0]"),
    "standard_analog_input1": ("DOUBLE", "s.analog_in[1]"),
    "standard_analog_output0": ("DOUBLE", "s.analog_out[0]"),
    "standard_analog_output1": ("DOUBLE", "s.analog_out[1]"),
    "io_current": ("DOUBLE", "0.0"),
    "euromap67_input_bits": ("UINT32", "0"),
    "euromap67_output_bits": ("UINT32", "0"),
    "euromap67_24V_voltage": ("DOUBLE", "0.0"),
    "euromap67_24V_current": ("DOUBLE", "0.0"),
    "tool_mode": ("UINT32", "0"),
    "tool_analog_input_types": ("UINT32", "0"),
    "tool_analog_input0": ("DOUBLE", "s.tool_analog_in[0]"),
    "tool_analog_input1": ("DOUBLE", "s.tool_analog_in[1]"),
    "tool_output_voltage": ("INT32", "24"),
    "tool_output_current": ("DOUBLE", "0.0"),
    "tool_temperature": ("DOUBLE", "30.0"),
    "tcp_force_scalar": ("DOUBLE", "0.0"),
    "output_bit_registers0_to_31": ("UINT32", "r.out_bits & 0xFFFFFFFF"),
    "output_bit_registers32_to_63": ("UINT32", "(r.out_bits >> 32) & 0xFFFFFFFF"),
    "input_bit_registers0_to_31": ("UINT32", "r.in_bits & 0xFFFFFFFF"),
    "input_bit_registers32_to_63": ("UINT32", "(r.in_bits >> 32) & 0xFFFFFFFF"),
    "tool_output_mode": ("UINT8", "0"),
    "tool_digital_output0_mode": ("UINT8", "0"),
    "tool_digital_output1_mode": ("UINT8", "0"),
    "payload": ("DOUBLE", "s.payload"),
    "payload_cog": ("VECTOR3D", "s.payload_cog"),
    "payload_inertia": (V6, "s.zero6"),
    "script_control_line": ("UINT32", "0"),
    "ft_raw_wrench": (V6, "s.zero6"),
    "joint_position_deviation_ratio": ("DOUBLE", "0.0"),
    "collision_detection_ratio": ("DOUBLE", "0.0"),
    "time_scale_source": ("INT32", "0"),
    "tcp_offset": (V6, "s.tcp_offset"),
    "actual_configurable_digital_input_bits": ("UINT64", "(s.digital_input_bits >> 8) & 0xFF"),
    "actual_configurable_digital_output_bits": ("UINT64", "(s.digital_output_bits >> 8) & 0xFF"),
    "encoder0_raw": ("INT32", "0"),
    "encoder1_raw": ("INT32", "0"),
    # Outputs of newer PolyScope 5 versions (see POLYSCOPE_VERSION). The arm has no contact
    # and a fixed base: the wrench estimated from the currents and the base acceleration are
    # zero, as a real arm's are when nothing touches it.
    "target_execution_time": ("DOUBLE", "s.target_execution_time"),
    "wrench_calc_from_currents": (V6, "s.zero6"),
    "target_base_acceleration": (V6, "s.zero6"),
    "target_gravity": ("VECTOR3D", "s.clock.gravity"),
    "control_step": ("UINT64", "s.clock.ticks"),
    "actual_robot_energy_consumed": ("DOUBLE", "s.energy_consumed()"),
    "actual_robot_braking_energy_dissipated": ("DOUBLE", "0.0"),
    # computed from the arm's dynamic model, only while a recipe asks for them (DYNAMICS)
    "actual_current_as_torque": (V6, "s.joint_torque"),
    "actual_TCP_acceleration": (V6, "s.tcp_acceleration"),
    "target_TCP_acceleration": (V6, "s.tcp_acceleration"),
    "target_base_wrench": (V6, "s.base_wrench"),
}
DYNAMICS = frozenset(
    {
        "actual_current_as_torque",
        "actual_TCP_acceleration",
        "target_TCP_acceleration",
        "target_base_wrench",
    }
)
"""Outputs the server computes each cycle only while some recipe holds one of them."""
for _i in range(REGISTER_COUNT):
    OUTPUTS[f"output_int_register_{_i}"] = ("INT32", f"r.out_int[{_i}]")
    OUTPUTS[f"output_double_register_{_i}"] = ("DOUBLE", f"r.out_double[{_i}]")
    OUTPUTS[f"input_int_register_{_i}"] = ("INT32", f"r.in_int[{_i}]")
    OUTPUTS[f"input_double_register_{_i}"] = ("DOUBLE", f"r.in_double[{_i}]")
for _i in range(64, 128):  # the upper bit registers: a word of their own (r.*_bits_high)
    OUTPUTS[f"output_bit_register_{_i}"] = ("BOOL", f"bool((r.out_bits_high >> {_i - 64}) & 1)")
    OUTPUTS[f"input_bit_register_{_i}"] = ("BOOL", f"bool((r.in_bits_high >> {_i - 64}) & 1)")

# Inputs: name -> RTDE type. Registers are written straight into the register file;
# the I/O fields are collected per packet and applied together (mask + value).
INPUTS: dict[str, str] = {
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}
for _i in range(REGISTER_COUNT):
    INPUTS[f"input_int_register_{_i}"] = "INT32"
    INPUTS[f"input_double_register_{_i}"] = "DOUBLE"
for _i in range(64, 128):
    INPUTS[f"input_bit_register_{_i}"] = "BOOL"


class StreamState:
    """The values the output recipes read, refreshed by the server once per cycle."""

    def __init__(self) -> None:
        z6: tuple[float, ...] = (0.0,) * 6
        self.zero6 = z6
        self.zero3: tuple[float, ...] = (0.0, 0.0, 0.0)
        self.timestamp = 0.0
        self.target_q = z6
        self.target_qd = z6
        self.target_qdd = z6
        self.actual_q = z6
        self.actual_qd = z6
        self.current = z6
        self.moment = z6
        self.actual_tcp_pose = z6
        self.target_tcp_pose = z6
        self.tcp_speed = z6
        self.digital_input_bits = 0
        self.digital_output_bits = 0
        self.temperatures = (30.0,) * 6
        self.execution_time = 0.3
        self.robot_mode = 0
        self.joint_mode = (239,) * 6
        self.safety_mode = 1
        self.runtime_state = 1
        self.robot_status_bits = 0
        self.safety_status_bits = 1
        self.accelerometer = (0.0, 0.0, 9.81)
        self.speed_scaling = 1.0
        self.target_speed_fraction = 1.0
        self.main_voltage = 48.0
        self.robot_voltage = 0.0
        self.robot_current = 0.0
        self.joint_voltage = z6
        self.elbow_position = self.zero3
        self.analog_out = [0.0, 0.0]
        self.analog_in = [0.0, 0.0]
        self.tool_analog_in = [0.0, 0.0]
        self.payload = 0.0
        self.payload_cog = self.zero3
        self.tcp_offset = z6
        self.target_execution_time = 2.0  # ms: the control cycle's budget
        self.clock: Any = None  # the Controller (its step counter and gravity), set by the hub
        self.powered_ticks = 0  # control steps the arm was powered, before ``powered_since``
        self.powered_since: int | None = None
        self.power = 0.0  # W drawn by the arm while powered (robot voltage x current)
        # DYNAMICS, refreshed by the server while some recipe uses them
        self.joint_torque = z6
        self.tcp_acceleration = z6
        self.base_wrench = z6

    def energy_consumed(self) -> float:
        """``actual_robot_energy_consumed`` (J): the arm's electrical power over the time it
        has been powered since the controller started."""
        ticks = self.powered_ticks
        if self.powered_since is not None and self.clock is not None:
            ticks += self.clock.ticks - self.powered_since
        return ticks * CONTROL_PERIOD * self.power


def compile_output_recipe(
    names: list[str], recipe_id: int, *, with_id: bool = True
) -> Callable[[Any, Any], bytes]:
    """A function ``pack(s, r) -> bytes`` writing one whole ``U`` packet for ``names``
    (protocol version 1 packets carry no recipe id: ``with_id=False``)."""
    fmt = ">HBB" if with_id else ">HB"
    args = []
    for name in names:
        rtde_type, expr = OUTPUTS[name]
        fmt += TYPE_CODES[rtde_type]
        args.append(f"*{expr}" if rtde_type in VECTOR_TYPES else expr)
    packer = struct.Struct(fmt)
    source = (
        "def pack(s, r, _pack=_pack):\n"
        f"    return _pack({packer.size}, 85, {f'{recipe_id}, ' if with_id else ''}"
        f"{', '.join(args)})\n"
    )
    namespace: dict[str, Any] = {"_pack": packer.pack}
    exec(compile(source, f"<rtde recipe {recipe_id}>", "exec"), namespace)
    pack: Callable[[Any, Any], bytes] = namespace["pack"]
    return pack


class InputRecipe:
    """One input recipe: how a ``U`` packet with its id writes into the controller.

    Compiled like the output recipes: :meth:`apply` is generated straight-line code (a
    streaming client sends one packet per cycle).
    """

    def __init__(self, names: list[str]) -> None:
        self.names = names
        self.struct = struct.Struct(">" + "".join(TYPE_CODES[INPUTS[n]] for n in names))
        self.watched = [n for n in names if "_register_" in n]
        lines = [
            "def apply(controller, payload):",
            "    values = _unpack(payload, 1)",
            "    regs = controller.registers",
            "    in_int, in_double = regs.in_int, regs.in_double",
        ]
        io: list[str] = []  # the I/O fields, collected and applied together
        pos = 0
        for n in names:
            width = 6 if INPUTS[n] == "VECTOR6D" else 1
            if n.startswith("input_int_register_"):
                lines.append(f"    in_int[{int(n.rsplit('_', 1)[1])}] = values[{pos}]")
            elif n.startswith("input_double_register_"):
                lines.append(f"    in_double[{int(n.rsplit('_', 1)[1])}] = values[{pos}]")
            else:
                value = f"values[{pos}:{pos + width}]" if width > 1 else f"values[{pos}]"
                io.append(f"{n!r}: {value}")
            pos += width
        if io:
            lines.append(f"    io = {{{', '.join(io)}}}")
        lines += [
            "    controller.input_generation += 1",
            "    now = controller.time",
            "    updated = controller.input_updated",
            *(f"    updated[{n!r}] = now" for n in self.watched),
        ]
        if io:
            lines.append("    _apply_io(controller, io)")
        namespace: dict[str, Any] = {"_unpack": self.struct.unpack_from, "_apply_io": _apply_io}
        exec(compile("\n".join(lines) + "\n", "<rtde input recipe>", "exec"), namespace)
        self.apply: Callable[[Controller, bytes], None] = namespace["apply"]


def _apply_io(controller: Controller, io: dict[str, Any]) -> None:
    state = controller.io
    regs = controller.registers

    def masked(old: int, mask_key: str, value_key: str) -> int:
        mask = int(io.get(mask_key, 0xFF))
        return (old & ~mask) | (int(io.get(value_key, 0)) & mask)

    if "standard_digital_output" in io:
        state.standard_digital = masked(
            state.standard_digital, "standard_digital_output_mask", "standard_digital_output"
        )
    if "configurable_digital_output" in io:
        state.configurable_digital = masked(
            state.configurable_digital,
            "configurable_digital_output_mask",
            "configurable_digital_output",
        )
    if "tool_digital_output" in io:
        state.tool_digital = masked(
            state.tool_digital, "tool_digital_output_mask", "tool_digital_output"
        )
    if "speed_slider_fraction" in io and int(io.get("speed_slider_mask", 1)) & 1:
        fraction = float(io["speed_slider_fraction"])
        if math.isfinite(fraction):  # a NaN would stop nothing and poison the moves
            state.speed_slider = min(max(fraction, 0.0), 1.0)
    mask = int(io.get("standard_analog_output_mask", 0))
    for k in (0, 1):
        key = f"standard_analog_output_{k}"
        if key in io and mask & (1 << k):
            state.analog_out[k] = float(io[key])
    if "input_bit_registers0_to_31" in io:
        regs.in_bits = (regs.in_bits & ~0xFFFFFFFF) | int(io["input_bit_registers0_to_31"])
    if "input_bit_registers32_to_63" in io:
        regs.in_bits = (regs.in_bits & 0xFFFFFFFF) | int(io["input_bit_registers32_to_63"]) << 32
    for name, value in io.items():
        if name.startswith("input_bit_register_"):
            bit = int(name.rsplit("_", 1)[1]) - 64
            regs.in_bits_high = (regs.in_bits_high & ~(1 << bit)) | (int(bool(value)) << bit)


class OutputRecipe:
    def __init__(
        self, names: list[str], recipe_id: int, frequency: float, *, with_id: bool = True
    ) -> None:
        self.names = names
        self.pack = compile_output_recipe(names, recipe_id, with_id=with_id)
        self.step = frequency / 500.0
        self.phase = 1.0 - self.step  # the first cycle after start sends


class RTDEHub:
    """Every RTDE connection of the simulator, input ownership and the stream.

    The sockets are plain non-blocking sockets, not asyncio transports: while a client sets
    up its recipes the loop wakes on its data, but once it has started its stream its input
    is read at the start of each control cycle (like a controller reading its inputs), so a
    client streaming commands at 500 Hz costs no extra wake-ups.
    """

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        self.state = StreamState()
        self.state.clock = controller
        self.dynamics = False  # some recipe holds an output of DYNAMICS
        self.dynamics_fields: frozenset[str] = frozenset()  # which ones
        self.connections: set[RTDEConnection] = set()
        self.owners: dict[str, RTDEConnection] = {}
        self.packets_sent = 0
        self.on_activity: Callable[[], None] = lambda: None
        self.on_dynamics: Callable[[], None] = lambda: None  # DYNAMICS outputs wanted from now
        # The server loads the dynamic model (Pinocchio) off the loop the first time a recipe
        # asks for DYNAMICS, then calls back; that connection's setup is answered after it.
        self.dynamics_ready = False
        self.load_dynamics: Callable[[Callable[[], None]], None] = self._no_model
        self.loop: asyncio.AbstractEventLoop | None = None
        self.listener: socket.socket | None = None

    def _no_model(self, done: Callable[[], None]) -> None:
        """Without a server to load the model, the outputs answer with their initial values."""
        self.dynamics_ready = True
        done()

    @property
    def streaming(self) -> bool:
        return any(conn.started for conn in self.connections)

    def listen(self, loop: asyncio.AbstractEventLoop, host: str, port: int) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            sock.listen(16)
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self.loop = loop
        self.listener = sock
        loop.add_reader(sock, self._accept)

    def _accept(self) -> None:
        assert self.listener is not None
        assert self.loop is not None
        try:
            sock, address = self.listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = RTDEConnection(self, sock, f"{address[0]}:{address[1]}")
        self.connections.add(conn)
        self.loop.add_reader(sock, conn.read)
        log.debug("RTDE client %s connected", conn.peer)

    def poll(self) -> None:
        """Read what the streaming clients sent since the last cycle."""
        for conn in list(self.connections):
            if conn.started and not conn.watched:
                conn.poll()

    def stream(self, steps: int = 1) -> None:
        """Send every due output packet; ``steps`` control cycles passed since the last call.

        A recipe at frequency f is due each time the controller clock crosses a multiple
        of 1/f; after a late wake-up only the newest sample goes out (as the client keeps
        only the newest anyway).
        """
        if self.controller.time < self.controller.rtde_stalled_until:
            return
        s = self.state
        r = self.controller.registers
        for conn in list(self.connections):
            if not conn.started:
                continue
            for recipe in conn.outputs:
                recipe.phase += recipe.step * steps
                if recipe.phase >= 0.999999:
                    recipe.phase -= math.floor(recipe.phase + 1e-6)
                    conn.write(recipe.pack(s, r))
                    self.packets_sent += 1

    def drop_all(self) -> None:
        for conn in list(self.connections):
            conn.close()

    def close(self) -> None:
        self.drop_all()
        if self.listener is not None and self.loop is not None:
            self.loop.remove_reader(self.listener)
            self.listener.close()
            self.listener = None

    def release(self, conn: RTDEConnection) -> None:
        for name in [n for n, c in self.owners.items() if c is conn]:
            del self.owners[name]
        self.connections.discard(conn)
        self.recipes_changed()

    def recipes_changed(self) -> None:
        """Recompute whether the server must compute the DYNAMICS outputs each cycle (and
        compute them now when they were not kept up to date: the next packet has them)."""
        was = self.dynamics_fields
        self.dynamics_fields = frozenset(
            name for conn in self.connections for recipe in conn.outputs for name in recipe.names
        ).intersection(DYNAMICS)
        self.dynamics = bool(self.dynamics_fields)
        if self.dynamics_fields - was:
            self.on_dynamics()


class RTDEConnection:
    """One RTDE client connection on a non-blocking socket."""

    def __init__(self, hub: RTDEHub, sock: socket.socket, peer: str) -> None:
        self.hub = hub
        self.sock: socket.socket | None = sock
        self.peer = peer
        self.buffer = bytearray()
        self.pending = bytearray()  # output the socket did not take yet
        self.outputs: list[OutputRecipe] = []
        self.inputs: dict[int, InputRecipe] = {}
        self.started = False
        self.quiet = 0  # cycles without input while started
        self.watched = False  # started but read by the event loop (a silent client)
        self.protocol = 2  # the version the client negotiated (1 or 2)
        self.deferred: list[tuple[int, bytes]] | None = None  # requests held for a setup

    def poll(self) -> None:
        """The cycle's read. A client silent for a while (a receive-only client) is handed
        back to the event loop, so it costs no system call per cycle until it sends again."""
        if self.read():
            self.quiet = 0
            return
        self.quiet += 1
        if self.quiet > QUIET_CYCLES and self.sock is not None and self.hub.loop is not None:
            self.watched = True
            self.hub.loop.add_reader(self.sock, self._wake_read)

    def _wake_read(self) -> None:
        self.read()
        if self.started and self.watched and self.sock is not None and self.hub.loop is not None:
            self.hub.loop.remove_reader(self.sock)  # back to one read per cycle
            self.watched = False
            self.quiet = 0

    def read(self) -> bool:
        """Read and handle what the socket holds; whether anything came."""
        got = False
        sock = self.sock
        while sock is not None:
            try:
                data = sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return got
            except OSError:
                self.close()
                return True
            if not data:
                self.close()
                return True
            got = True
            self.data_received(data)
            sock = self.sock
            if len(data) < 65536:
                break
        return got

    def write(self, data: bytes) -> None:
        sock = self.sock
        if sock is None:
            return
        if self.pending:
            self.pending += data
            if len(self.pending) > MAX_WRITE_BUFFER:
                log.warning("RTDE client %s does not read: dropping it", self.peer)
                self.close()
            return
        try:
            sent = sock.send(data)
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError:
            self.close()
            return
        if sent < len(data):
            self.pending += data[sent:]
            assert self.hub.loop is not None
            self.hub.loop.add_writer(sock, self._flush)

    def _flush(self) -> None:
        sock = self.sock
        if sock is None:
            return
        try:
            sent = sock.send(self.pending)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self.close()
            return
        del self.pending[:sent]
        if not self.pending and self.hub.loop is not None:
            self.hub.loop.remove_writer(sock)

    def close(self) -> None:
        sock, self.sock = self.sock, None
        if sock is None:
            return
        loop = self.hub.loop
        if loop is not None:
            loop.remove_reader(sock)
            loop.remove_writer(sock)
        sock.close()
        self.started = False
        self.hub.release(self)
        log.debug("RTDE client %s disconnected", self.peer)

    def _send(self, kind: int, payload: bytes) -> None:
        self.write(HEADER.pack(len(payload) + 3, kind) + payload)

    def data_received(self, data: bytes) -> None:
        buf = self.buffer
        if not buf and len(data) >= 3 and HEADER.unpack_from(data)[0] == len(data):
            self._handle(data[2], data[3:])  # exactly one packet (a streaming client's cycle)
            return
        buf += data
        while len(buf) >= 3:
            size, kind = HEADER.unpack_from(buf)
            if size < 3:
                log.warning("RTDE client %s sent a bad header: closing", self.peer)
                self.close()
                return
            if len(buf) < size:
                break
            payload = bytes(buf[3:size])
            del buf[:size]
            self._handle(kind, payload)
            if self.sock is None:
                return

    def _handle(self, kind: int, payload: bytes) -> None:
        if self.deferred is not None:  # a setup waits for the dynamic model: in order after it
            self.deferred.append((kind, payload))
            return
        if kind == 85:  # 'U' data from the client
            recipe = self.inputs.get(payload[0]) if payload else None
            if recipe is None:
                log.debug("RTDE %s: data for unknown input recipe", self.peer)
                return
            if len(payload) - 1 != recipe.struct.size:
                log.debug(
                    "RTDE %s: recipe %d data has %d bytes, expected %d",
                    self.peer,
                    payload[0],
                    len(payload) - 1,
                    recipe.struct.size,
                )
            if len(payload) - 1 < recipe.struct.size:
                log.warning("RTDE %s: short data packet for recipe %d", self.peer, payload[0])
                return
            recipe.apply(self.hub.controller, payload)
            self.hub.on_activity()
        elif kind == 86:  # 'V' protocol version
            version = struct.unpack_from(">H", payload)[0] if len(payload) >= 2 else 0
            if version in (1, 2):
                self.protocol = version
            self._send(86, bytes([1 if version in (1, 2) else 0]))
        elif kind == 118:  # 'v' controller version
            self._send(118, struct.pack(">IIII", *POLYSCOPE_VERSION))
        elif kind == 79:  # 'O' output setup
            self._setup_outputs(payload)
        elif kind == 73:  # 'I' input setup
            self._setup_inputs(payload)
        elif kind == 83:  # 'S' start
            if not self.started and self.sock is not None and self.hub.loop is not None:
                self.hub.loop.remove_reader(self.sock)  # read once per cycle from now on
            self.started = True
            self.watched = False
            self.quiet = 0
            self.hub.on_activity()
            for output in self.outputs:
                output.phase = 1.0 - output.step
            self._send(83, b"\x01")
        elif kind == 80:  # 'P' pause
            if self.started and self.sock is not None and self.hub.loop is not None:
                self.hub.loop.add_reader(self.sock, self.read)  # replaces a silent-client reader
            self.started = False
            self.watched = False
            self._send(80, b"\x01")
        else:
            log.debug("RTDE %s: ignoring packet type %d", self.peer, kind)

    def text_message(self, text: str, level: int = 1) -> None:
        """An ``M`` packet (level 0 exception, 1 error, 2 warning, 3 info)."""
        msg = text.encode("ascii", "replace")[:255]
        if self.protocol == 1:
            self._send(77, bytes([level]) + msg)
        else:
            self._send(
                77, bytes([len(msg)]) + msg + bytes([len(b"RTDE")]) + b"RTDE" + bytes([level])
            )

    def _too_long(self, kind: int, names: bytes, *, with_id: bool = True) -> bool:
        """Refuse a recipe whose list of names exceeds the controller's limit: explained in an
        ``M`` message and answered as a failed setup (recipe id 0, ``NOT_FOUND`` for every
        name: the only failure a setup reply documents, so that clients parse it)."""
        if len(names) <= MAX_RECIPE_NAMES:
            return False
        log.warning("RTDE %s: recipe of %d bytes refused", self.peer, len(names))
        self.text_message(
            f"recipe refused: the list of names is {len(names)} bytes, "
            f"the limit is {MAX_RECIPE_NAMES}"
        )
        count = max(1, len([n for n in names.split(b",") if n.strip()]))
        self._send(kind, (b"\x00" if with_id else b"") + b",".join([b"NOT_FOUND"] * count))
        return True

    def _refuse_recipe(self, kind: int, types: list[str], direction: str) -> None:
        """A recipe beyond the 255 a connection can number: answered (recipe id 0, the
        failure id, with the types) and explained in an ``M`` message, never left unanswered."""
        log.warning("RTDE %s: %s recipe %d refused", self.peer, direction, MAX_RECIPES + 1)
        self.text_message(
            f"{direction} recipe refused: this connection already has {MAX_RECIPES} "
            f"{direction} recipes (recipe ids are 1-{MAX_RECIPES})"
        )
        self._send(kind, b"\x00" + ",".join(types).encode())

    def _setup_outputs(self, payload: bytes) -> None:
        v1 = self.protocol == 1
        if v1:  # version 1: names only, a fixed 125 Hz, no recipe id anywhere
            frequency, raw = V1_FREQUENCY, payload
        elif len(payload) < 8:
            self._send(79, b"\x00")
            return
        else:
            frequency, raw = struct.unpack_from(">d", payload)[0], payload[8:]
        if self._too_long(79, raw, with_id=not v1):
            return
        names = [n.strip() for n in raw.decode("ascii", "replace").split(",") if n.strip()]
        types = [OUTPUTS[n][0] if n in OUTPUTS else "NOT_FOUND" for n in names]
        if not names or "NOT_FOUND" in types or not frequency > 0:
            self._send(79, (b"" if v1 else b"\x00") + ",".join(types).encode())
            return
        frequency = min(frequency, 500.0)
        if not self.hub.dynamics_ready and not DYNAMICS.isdisjoint(names):
            self.deferred = []  # answered once the model is loaded, without stalling the cycle
            self.hub.load_dynamics(lambda: self._resume(79, payload))
            return
        if v1:
            self.outputs = [OutputRecipe(names, 0, frequency, with_id=False)]
            self.hub.recipes_changed()
            self._send(79, ",".join(types).encode())
            return
        if len(self.outputs) >= MAX_RECIPES:
            self._refuse_recipe(79, types, "output")
            return
        recipe_id = len(self.outputs) + 1
        self.outputs.append(OutputRecipe(names, recipe_id, frequency))
        self.hub.recipes_changed()
        self._send(79, bytes([recipe_id]) + ",".join(types).encode())

    def _resume(self, kind: int, payload: bytes) -> None:
        """Handle the held setup request, then whatever the client sent meanwhile."""
        held, self.deferred = self.deferred or [], None
        for k, p in [(kind, payload), *held]:
            if self.sock is None:
                return
            self._handle(k, p)

    def _setup_inputs(self, payload: bytes) -> None:
        if self._too_long(73, payload):
            return
        names = [n.strip() for n in payload.decode("ascii", "replace").split(",") if n.strip()]
        types = []
        for n in names:
            owner = self.hub.owners.get(n)
            if n not in INPUTS:
                types.append("NOT_FOUND")
            elif owner is not None and owner is not self:
                types.append("IN_USE")
            else:
                types.append(INPUTS[n])
        if not names or "NOT_FOUND" in types or "IN_USE" in types:
            self._send(73, b"\x00" + ",".join(types).encode())
            return
        if len(self.inputs) >= MAX_RECIPES:
            self._refuse_recipe(73, types, "input")
            return
        for n in names:
            self.hub.owners[n] = self
        recipe_id = len(self.inputs) + 1
        self.inputs[recipe_id] = InputRecipe(names)
        self._send(73, bytes([recipe_id]) + ",".join(types).encode())
