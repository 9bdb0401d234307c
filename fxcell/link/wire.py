"""Framing of the messages between the robot-link process and its asyncio client.

Each frame is a 4-byte big-endian length followed by a pickled tuple whose first item
names the message. Both ends are fxcell code of the same user, joined by a private
socketpair, so pickle is safe here. State samples travel as plain tuples (no enums) to
keep the 500 Hz stream compact; trajectories as raw float64 bytes, so that the link
process needs no numpy (it starts faster, which shortens a reconnect).
"""

from __future__ import annotations

import array
import dataclasses
import pickle
import struct
from collections.abc import Sequence
from typing import Any, TypeVar

from fxcell.protocol import RobotMode, RobotState, RuntimeState, SafetyMode

_E = TypeVar("_E", RobotMode, SafetyMode, RuntimeState)

HEADER = struct.Struct(">I")
MAX_FRAME = 64 * 1024 * 1024

# client -> link process
CALL = "call"  # (CALL, request_id, method, kwargs)
TRAJ_START = "traj_start"  # (TRAJ_START, traj_id, samples, lookahead_time, gain, guard)
TRAJ_REPLACE = "traj_replace"  # (TRAJ_REPLACE, traj_id, samples[, at_index])
TRAJ_STOP = "traj_stop"  # (TRAJ_STOP, traj_id[, reason]): the link brakes to rest itself
SETTLED = "settled"  # TRAJ_STOP's reason when the robot is at the target: servo mode is kept
BEAT = "beat"  # (BEAT,): the client is alive (sent every 10 ms while a trajectory runs)

# link process -> client
HELLO = "hello"  # (HELLO, {"pid": ...})
CONNECTED = "connected"  # (CONNECTED, info)
FATAL = "fatal"  # (FATAL, message, {part: why}) then the process exits
STATE = "state"  # (STATE, state_tuple)
REPLY = "reply"  # (REPLY, request_id, ok, value | (error_type, message))
CONTROL = "control"  # (CONTROL, ready: bool, reason)
HOLD = "hold"  # (HOLD, bool): a blocking ur_rtde constructor runs; the stream pauses
TRAJ = "traj"  # (TRAJ, traj_id, kind, data) kind: progress | replaced | end
LOG = "log"  # (LOG, level, message)
PULSE = "pulse"  # (PULSE, link_monotonic, last_state_monotonic): every 10 ms


def encode(message: tuple[Any, ...]) -> bytes:
    body = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    return HEADER.pack(len(body)) + body


def decode(body: bytes) -> tuple[Any, ...]:
    message = pickle.loads(body)
    if not isinstance(message, tuple) or not message:
        raise ValueError(f"malformed link message: {message!r:.80}")
    return message


Samples = list[tuple[float, ...]]
"""A trajectory in the link process: one 6-tuple of joint positions per 2 ms."""


def pack_samples(samples: Any) -> tuple[int, bytes]:
    """An (N, 6) C-contiguous float64 array as ``(N, bytes)`` for the wire."""
    return len(samples), samples.tobytes()


def unpack_samples(packed: tuple[int, bytes]) -> Samples:
    n, data = packed
    flat = array.array("d")
    flat.frombytes(data)
    if len(flat) != 6 * n:
        raise ValueError(f"trajectory of {n} samples carries {len(flat)} numbers")
    return [tuple(flat[6 * k : 6 * k + 6]) for k in range(n)]


def max_abs_difference(a: Sequence[float], b: Sequence[float]) -> float:
    return max(abs(x - y) for x, y in zip(a, b, strict=True))


_FIELDS = tuple(f.name for f in dataclasses.fields(RobotState) if f.name != "received_at")
_ENUMS = {"robot_mode": RobotMode, "safety_mode": SafetyMode, "runtime_state": RuntimeState}
_DEFAULTS: dict[str, Any] = {
    "robot_mode": RobotMode.NO_CONTROLLER,
    "safety_mode": SafetyMode.UNDEFINED_SAFETY_MODE,
    "runtime_state": RuntimeState.STOPPED,
}


def state_to_tuple(s: RobotState) -> tuple[Any, ...]:
    """A sample as a plain tuple (enums as ints), in :class:`RobotState`'s field order."""
    return tuple(int(getattr(s, n)) if n in _ENUMS else getattr(s, n) for n in _FIELDS)


def state_from_tuple(t: tuple[Any, ...], received_at: float) -> RobotState:
    values = dict(zip(_FIELDS, t, strict=True))
    for name, cls in _ENUMS.items():
        values[name] = _enum(cls, values[name], _DEFAULTS[name])
    return RobotState(**values, received_at=received_at)


def _enum(cls: type[_E], value: int, default: _E) -> _E:
    try:
        return cls(value)
    except ValueError:
        return default
