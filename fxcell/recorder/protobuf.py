"""The 500 Hz robot-state topic in protobuf, encoded and decoded by hand.

JSON costs about 20 µs per state message (performance anchors); the protobuf wire
format of a fixed-layout message is one :func:`struct.pack` call, a few µs. The
schema is a binary ``FileDescriptorSet`` built here from the same field table, so
Foxglove (and the ``protobuf`` library) decode the messages without generated code.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Iterable, Sequence
from typing import Any, Final

from fxcell.protocol import RobotMode, RobotState, RuntimeState, SafetyMode

# FieldDescriptorProto.Type and .Label values (google/protobuf/descriptor.proto)
_DOUBLE, _FIXED32, _STRING, _ENUM, _SFIXED32, _INT64, _INT32 = 1, 7, 9, 14, 15, 3, 5
_OPTIONAL, _REPEATED = 1, 3
_VARINT, _I64, _LEN, _I32 = 0, 1, 2, 5


def varint(value: int) -> bytes:
    """Protobuf base-128 varint (negative numbers as 64-bit two's complement)."""
    if value < 0:
        value += 1 << 64
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def key(number: int, wire_type: int) -> bytes:
    return varint(number << 3 | wire_type)


def _len_field(number: int, payload: bytes) -> bytes:
    return key(number, _LEN) + varint(len(payload)) + payload


def _str_field(number: int, text: str) -> bytes:
    return _len_field(number, text.encode())


def _int_field(number: int, value: int) -> bytes:
    return key(number, _VARINT) + varint(value)


# ----------------------------------------------------------------- descriptors


def field_descriptor(
    name: str, number: int, ftype: int, *, repeated: bool = False, type_name: str = ""
) -> bytes:
    """A serialized ``FieldDescriptorProto``."""
    body = _str_field(1, name) + _int_field(3, number)
    body += _int_field(4, _REPEATED if repeated else _OPTIONAL) + _int_field(5, ftype)
    if type_name:
        body += _str_field(6, type_name)
    return body


def enum_descriptor(name: str, values: Iterable[tuple[str, int]]) -> bytes:
    """A serialized ``EnumDescriptorProto``."""
    body = _str_field(1, name)
    for value_name, number in values:
        body += _len_field(2, _str_field(1, value_name) + _int_field(2, number))
    return body


def message_descriptor(name: str, fields: Iterable[bytes]) -> bytes:
    """A serialized ``DescriptorProto``."""
    return _str_field(1, name) + b"".join(_len_field(2, f) for f in fields)


def file_descriptor(
    name: str,
    package: str,
    messages: Iterable[bytes],
    enums: Iterable[bytes] = (),
    dependencies: Iterable[str] = (),
) -> bytes:
    """A serialized ``FileDescriptorProto`` (proto3)."""
    body = _str_field(1, name) + _str_field(2, package)
    body += b"".join(_str_field(3, d) for d in dependencies)
    body += b"".join(_len_field(4, m) for m in messages)
    body += b"".join(_len_field(5, e) for e in enums)
    return body + _str_field(12, "proto3")


def file_descriptor_set(files: Iterable[bytes]) -> bytes:
    """A serialized ``FileDescriptorSet``: the schema data of an MCAP protobuf channel."""
    return b"".join(_len_field(1, f) for f in files)


def _enum_values(prefix: str, cls: type[enum.IntEnum], zero: str | None) -> list[tuple[str, int]]:
    members = sorted(cls, key=lambda m: (m.value != 0, abs(m.value)))
    values = [(f"{prefix}_{m.name}", int(m.value)) for m in members]
    if zero is not None and all(v != 0 for _, v in values):
        values.insert(0, (f"{prefix}_{zero}", 0))  # proto3: the first value must be zero
    return values


# ----------------------------------------------------------------- fxcell.RobotState

VECTOR_FIELDS: Final = (
    "target_q",
    "target_qd",
    "target_qdd",
    "actual_q",
    "actual_qd",
    "actual_current",
    "target_tcp_pose",
    "actual_tcp_pose",
    "actual_tcp_speed",
)
_FIRST_VECTOR = 7  # field numbers 7..15
_SPEED_SCALING, _REGISTERS, _RECEIVED_AT = 16, 17, 18
_ENUMS: Final = (
    ("RobotMode", "ROBOT_MODE", RobotMode, None),
    ("SafetyMode", "SAFETY_MODE", SafetyMode, "UNSPECIFIED"),
    ("RuntimeState", "RUNTIME_STATE", RuntimeState, None),
)


def robot_state_schema() -> bytes:
    """``FileDescriptorSet`` of ``fxcell.RobotState`` (SI units, UR base frame)."""
    fields = [
        field_descriptor("controller_time", 1, _DOUBLE),
        field_descriptor("robot_mode", 2, _ENUM, type_name=".fxcell.RobotMode"),
        field_descriptor("safety_mode", 3, _ENUM, type_name=".fxcell.SafetyMode"),
        field_descriptor("runtime_state", 4, _ENUM, type_name=".fxcell.RuntimeState"),
        field_descriptor("robot_status_bits", 5, _FIXED32),
        field_descriptor("safety_status_bits", 6, _FIXED32),
    ]
    fields += [
        field_descriptor(name, _FIRST_VECTOR + i, _DOUBLE, repeated=True)
        for i, name in enumerate(VECTOR_FIELDS)
    ]
    fields += [
        field_descriptor("speed_scaling", _SPEED_SCALING, _DOUBLE),
        field_descriptor("output_int_registers", _REGISTERS, _SFIXED32, repeated=True),
        field_descriptor("received_at", _RECEIVED_AT, _DOUBLE),
    ]
    enums = [enum_descriptor(n, _enum_values(p, c, z)) for n, p, c, z in _ENUMS]
    return file_descriptor_set(
        [
            file_descriptor(
                "fxcell/RobotState.proto",
                "fxcell",
                [message_descriptor("RobotState", fields)],
                enums,
            )
        ]
    )


# Fixed part after the three enum varints: field keys are packed as bytes in place.
_STATE_FIXED = struct.Struct("<BdBIBI" + "BB6d" * 9 + "BBd" + "BBB3i" + "BBd")
_VECTOR_KEYS: Final = tuple((_FIRST_VECTOR + i) << 3 | _LEN for i in range(len(VECTOR_FIELDS)))
_K_TIME = 1 << 3 | _I64
_K_RSB = 5 << 3 | _I32
_K_SSB = 6 << 3 | _I32
_K2_SPEED = key(_SPEED_SCALING, _I64)
_K2_REGS = key(_REGISTERS, _LEN)
_K2_RECV = key(_RECEIVED_AT, _I64)
_enum_prefix_cache: dict[tuple[int, int, int], bytes] = {}


def _enum_prefix(modes: tuple[int, int, int]) -> bytes:
    prefix = _enum_prefix_cache.get(modes)
    if prefix is None:
        prefix = b"".join(_int_field(2 + i, int(v)) for i, v in enumerate(modes))
        _enum_prefix_cache[modes] = prefix
    return prefix


def encode_robot_state(s: RobotState) -> bytes:
    """Serialize one sample as ``fxcell.RobotState`` (a few µs)."""
    try:
        k = _VECTOR_KEYS
        fixed = _STATE_FIXED.pack(
            _K_TIME, s.timestamp, _K_RSB, s.robot_status_bits, _K_SSB, s.safety_status_bits,
            k[0], 48, *s.target_q, k[1], 48, *s.target_qd, k[2], 48, *s.target_qdd,
            k[3], 48, *s.actual_q, k[4], 48, *s.actual_qd, k[5], 48, *s.actual_current,
            k[6], 48, *s.target_tcp_pose, k[7], 48, *s.actual_tcp_pose,
            k[8], 48, *s.actual_tcp_speed,
            _K2_SPEED[0], _K2_SPEED[1], s.speed_scaling,
            _K2_REGS[0], _K2_REGS[1], 12, *s.output_int_registers,
            _K2_RECV[0], _K2_RECV[1], s.received_at,
        )  # fmt: skip
    except struct.error:  # unusual vector lengths or out-of-range bits: the general path
        return _encode_robot_state_general(s)
    return _enum_prefix((s.robot_mode, s.safety_mode, s.runtime_state)) + fixed


def _packed(number: int, fmt: str, values: Sequence[Any]) -> bytes:
    return _len_field(number, struct.pack(f"<{len(values)}{fmt}", *values))


def _encode_robot_state_general(s: RobotState) -> bytes:
    out = bytearray(_enum_prefix((s.robot_mode, s.safety_mode, s.runtime_state)))
    out += key(1, _I64) + struct.pack("<d", s.timestamp)
    out += key(5, _I32) + struct.pack("<I", s.robot_status_bits & 0xFFFFFFFF)
    out += key(6, _I32) + struct.pack("<I", s.safety_status_bits & 0xFFFFFFFF)
    for i, name in enumerate(VECTOR_FIELDS):
        out += _packed(_FIRST_VECTOR + i, "d", getattr(s, name))
    out += _K2_SPEED + struct.pack("<d", s.speed_scaling)
    out += _packed(_REGISTERS, "i", s.output_int_registers)
    out += _K2_RECV + struct.pack("<d", s.received_at)
    return bytes(out)


# ----------------------------------------------------------------- decoding


def _read_varint(data: bytes, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        byte = data[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return result, pos
        shift += 7


def _signed32(value: int) -> int:
    value &= 0xFFFFFFFFFFFFFFFF
    return value - (1 << 64) if value >= 1 << 63 else value


def iter_fields(data: bytes) -> Iterable[tuple[int, int, Any]]:
    """Walk a protobuf message: (field number, wire type, raw value) per field."""
    pos, end = 0, len(data)
    while pos < end:
        k, pos = _read_varint(data, pos)
        number, wire = k >> 3, k & 7
        value: Any
        if wire == _VARINT:
            value, pos = _read_varint(data, pos)
        elif wire == _I64:
            value, pos = data[pos : pos + 8], pos + 8
        elif wire == _LEN:
            n, pos = _read_varint(data, pos)
            value, pos = data[pos : pos + n], pos + n
        elif wire == _I32:
            value, pos = data[pos : pos + 4], pos + 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wire}")
        yield number, wire, value


def _enum_or_int(cls: type[enum.IntEnum], value: int) -> Any:
    try:
        return cls(value)
    except ValueError:
        return value


_FIXED_SIZE: Final = _STATE_FIXED.size
_MODE_TYPES: Final = (RobotMode, SafetyMode, RuntimeState)
_modes_cache: dict[bytes, tuple[Any, Any, Any]] = {}
"""Decoded (robot_mode, safety_mode, runtime_state) by the exact bytes of a message's enum
prefix: a log holds a handful of distinct prefixes, so the varints and enum lookups run once
per prefix instead of once per sample. Bounded; a miss is decoded in full."""
_MODES_CACHE_MAX: Final = 4096


def _decode_modes(head: bytes) -> tuple[Any, Any, Any]:
    """The three enum fields that make up all of ``head``, in field order; ValueError if not."""
    pos = 0
    modes = []
    for i, cls in enumerate(_MODE_TYPES):
        k, pos = _read_varint(head, pos)
        if k != (2 + i) << 3:
            raise ValueError
        v, pos = _read_varint(head, pos)
        modes.append(_enum_or_int(cls, _signed32(v)))
    if pos != len(head):
        raise ValueError
    out = (modes[0], modes[1], modes[2])
    if len(_modes_cache) < _MODES_CACHE_MAX:
        _modes_cache[head] = out
    return out


def decode_robot_state(data: bytes) -> RobotState:
    """Parse an ``fxcell.RobotState`` message back into a :class:`RobotState`."""
    if type(data) is not bytes:
        data = bytes(data)
    # fast path: three enum varints followed by the fixed layout this module writes
    head = len(data) - _FIXED_SIZE
    if head < 6:  # the shortest enum prefix: three one-byte keys and one-byte values
        return _decode_robot_state_general(data)
    prefix = data[:head]
    try:
        modes = _modes_cache.get(prefix) or _decode_modes(prefix)
    except (ValueError, IndexError):
        return _decode_robot_state_general(data)
    f = _STATE_FIXED.unpack_from(data, head)
    if f[0] != _K_TIME or f[6] != _VECTOR_KEYS[0] or f[87] != _K2_RECV[0]:
        return _decode_robot_state_general(data)
    # every field positionally, in declaration order (keyword arguments cost more than the rest
    # of the call); those the schema does not carry get their defaults, as in the general path
    return RobotState(
        f[1], modes[0], modes[1], modes[2], f[3], f[5],
        f[8:14], f[16:22], f[24:30], f[32:38], f[40:46], f[48:54], f[56:62], f[64:70], f[72:78],
        f[80], f[84:87], 0, 0, 0.0, 0.0, 0.0, 0.0, f[89],
    )  # fmt: skip


def _decode_robot_state_general(data: bytes) -> RobotState:
    s = RobotState()
    s.safety_mode = 0  # type: ignore[assignment]  # proto3 default when the field is absent
    for number, _wire, raw in iter_fields(data):
        if number == 1:
            s.timestamp = struct.unpack("<d", raw)[0]
        elif number in (2, 3, 4):
            cls = (RobotMode, SafetyMode, RuntimeState)[number - 2]
            name = ("robot_mode", "safety_mode", "runtime_state")[number - 2]
            setattr(s, name, _enum_or_int(cls, _signed32(raw)))
        elif number in (5, 6):
            name = "robot_status_bits" if number == 5 else "safety_status_bits"
            setattr(s, name, struct.unpack("<I", raw)[0])
        elif _FIRST_VECTOR <= number < _FIRST_VECTOR + len(VECTOR_FIELDS):
            values = struct.unpack(f"<{len(raw) // 8}d", raw)
            setattr(s, VECTOR_FIELDS[number - _FIRST_VECTOR], values)
        elif number == _SPEED_SCALING:
            s.speed_scaling = struct.unpack("<d", raw)[0]
        elif number == _REGISTERS:
            s.output_int_registers = struct.unpack(f"<{len(raw) // 4}i", raw)
        elif number == _RECEIVED_AT:
            s.received_at = struct.unpack("<d", raw)[0]
    return s
