"""Framing of the messages between the robot-link process and its asyncio client.

Each frame is a 4-byte big-endian length followed by a pickled tuple whose first item
names the message. Both ends are fxcell code of the same user, joined by a private
socketpair, so pickle is safe here. State samples travel as plain tuples (no enums) to
keep the 500 Hz stream compact; trajectories as raw float64 bytes, so that the link
process needs no numpy (it starts faster, which shortens a reconnect).
"""

from __future__ import annotations

import dataclasses
import pickle
import struct
from collections.abc import Sequence
from typing import Any

from fxcell.protocol import RobotMode, RobotState, RuntimeState, SafetyMode

HEADER = struct.Struct(">I")
MAX_FRAME = 64 * 1024 * 1024

# client -> link process
CALL = "call"  # (CALL, request_id, request): a fxcell.link.contract request dataclass
TRAJ_START = "traj_start"  # (TRAJ_START, contract.StartTrajectory)
TRAJ_REPLACE = "traj_replace"  # (TRAJ_REPLACE, contract.ReplaceTrajectory)
TRAJ_STOP = "traj_stop"  # (TRAJ_STOP, contract.StopTrajectory): the link brakes to rest itself
# (a reason is a contract.StopReason's value; SETTLED, the robot at the target, keeps servo mode)
BEAT = "beat"  # (BEAT,): the client is alive (sent every 10 ms while a trajectory runs)

# link process -> client
HELLO = "hello"  # (HELLO, {"pid": ..., "wire": contract.WIRE_VERSION, "scheduling": ...})
CONNECTED = "connected"  # (CONNECTED, info)
FATAL = "fatal"  # (FATAL, message, {part: why}) then the process exits
STATE = "state"  # (STATE, state_tuple)
REPLY = "reply"  # (REPLY, request_id, ok, value | (contract.ErrorKind, message))
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


_SAMPLE = struct.Struct("=6d")  # one sample as pack_samples writes it (native float64)


def unpack_samples(packed: tuple[int, bytes]) -> Samples:
    n, data = packed
    if len(data) != _SAMPLE.size * n:
        raise ValueError(f"trajectory of {n} samples carries {len(data) / 8:g} numbers")
    return list(_SAMPLE.iter_unpack(data))


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


# state_from_tuple builds a RobotState positionally: the tuple's fields, then received_at
if tuple(f.name for f in dataclasses.fields(RobotState)) != (*_FIELDS, "received_at"):
    raise ImportError("RobotState's last field must be received_at (see state_from_tuple)")
# (position in the tuple, the enum's members by value, default) of each enum field
_ENUM_SLOTS = tuple(
    (_FIELDS.index(name), {int(m.value): m for m in cls}, _DEFAULTS[name])
    for name, cls in _ENUMS.items()
)


def state_from_tuple(t: tuple[Any, ...], received_at: float) -> RobotState:
    # positional, enums by table: this runs for every 500 Hz sample
    if len(t) != len(_FIELDS):
        raise ValueError(f"a state tuple has {len(_FIELDS)} fields, got {len(t)}")
    values = list(t)
    for i, members, default in _ENUM_SLOTS:
        try:
            values[i] = members.get(values[i], default)
        except TypeError:  # unhashable: not a member
            values[i] = default
    values.append(received_at)
    return RobotState(*values)
