"""A minimal RTDE output reader that keeps every 500 Hz sample.

ur_rtde's ``RTDEReceiveInterface`` keeps only the newest packet, so a reader that
wakes late (two cores shared with everything else) loses samples. This reader owns
its own RTDE connection (protocol version 2: ``V``, ``O``, ``S``, then ``U`` packets,
all big-endian) and decodes every packet the kernel has buffered, so the link process
forwards each controller cycle exactly once. It runs in the robot-link process only.
"""

from __future__ import annotations

import contextlib
import fcntl
import socket
import struct
import sys
import termios
from collections.abc import Iterator

from fxcell.protocol import RTDE_PORT, RTDE_STATE_OUTPUTS, RobotState

HEADER = struct.Struct(">HB")
PROTOCOL_VERSION = 2
_V, _O, _S, _U, _M = ord("V"), ord("O"), ord("S"), ord("U"), ord("M")

_ATTRS: tuple[str, ...] = tuple(attr for attr, _ in RTDE_STATE_OUTPUTS)
FIELDS: tuple[str, ...] = tuple(output for _, output in RTDE_STATE_OUTPUTS)

# ur_rtde names its RTDEReceiveInterface getters after the outputs ("actual_TCP_pose" ->
# ``getActualTCPPose``), with these exceptions.
_UR_RTDE_EXCEPTIONS = {"robot_status_bits": "getRobotStatus"}


def ur_rtde_getter(output: str) -> str:
    """The name of ur_rtde's ``RTDEReceiveInterface`` getter for an RTDE output."""
    exception = _UR_RTDE_EXCEPTIONS.get(output)
    if exception is not None:
        return exception
    return "get" + "".join(word[:1].upper() + word[1:] for word in output.split("_"))


UR_RTDE_GETTERS: tuple[tuple[str, str], ...] = tuple(
    (attr, ur_rtde_getter(output)) for attr, output in RTDE_STATE_OUTPUTS
)
"""The :class:`RobotState` fields with the ur_rtde getter each is polled from when the link
reads through ur_rtde instead of :class:`RTDEStream`: derived from the one list of outputs."""
_CODES = {
    "BOOL": ("?", 1),
    "UINT8": ("B", 1),
    "UINT32": ("I", 1),
    "UINT64": ("Q", 1),
    "INT32": ("i", 1),
    "DOUBLE": ("d", 1),
    "VECTOR3D": ("3d", 3),
    "VECTOR6D": ("6d", 6),
    "VECTOR6INT32": ("6i", 6),
    "VECTOR6UINT32": ("6I", 6),
}


class RTDEError(ConnectionError):
    """The RTDE session could not be set up or broke."""


class RTDEStream:
    """One RTDE output session on ``host``; iterate :meth:`samples` in a thread."""

    def __init__(self, host: str, frequency: float = 500.0, timeout: float = 2.0) -> None:
        self.host = host
        self.frequency = frequency
        self.timeout = timeout
        self._sock: socket.socket | None = None
        self._buffer = bytearray()
        self._struct: struct.Struct | None = None
        self._widths: list[int] = []

    def connect(self) -> None:
        sock = socket.create_connection((self.host, RTDE_PORT), timeout=self.timeout)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        self._request(_V, struct.pack(">H", PROTOCOL_VERSION))
        if not self._reply(_V)[0]:
            raise RTDEError(f"controller refused RTDE protocol version {PROTOCOL_VERSION}")
        self._request(_O, struct.pack(">d", self.frequency) + ",".join(FIELDS).encode())
        reply = self._reply(_O)
        types = reply[1:].decode().split(",")
        missing = [n for n, t in zip(FIELDS, types, strict=False) if t == "NOT_FOUND"]
        if missing or len(types) != len(FIELDS):
            raise RTDEError(f"controller lacks RTDE outputs {missing or types}")
        fmt = ">B"
        self._widths = []
        for t in types:
            code, width = _CODES[t]
            fmt += code
            self._widths.append(width)
        self._struct = struct.Struct(fmt)
        self._request(_S, b"")
        if not self._reply(_S)[0]:
            raise RTDEError("controller refused to start the RTDE stream")
        sock.settimeout(None)

    def unread(self) -> int:
        """Bytes the controller sent that the reader has not taken yet (the kernel's
        receive queue and this reader's partial packet; any thread may ask): a stream
        that stalled with bytes unread stalled in this process, not in the controller."""
        sock = self._sock
        waiting = 0
        if sock is not None:
            with contextlib.suppress(OSError, ValueError):
                raw = fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0" * 4)
                waiting = int.from_bytes(raw, sys.byteorder, signed=True)
        return waiting + len(self._buffer)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _request(self, kind: int, payload: bytes) -> None:
        assert self._sock is not None
        self._sock.sendall(HEADER.pack(HEADER.size + len(payload), kind) + payload)

    def _reply(self, kind: int) -> bytes:
        for got, payload in self._packets():
            if got == kind:
                return payload
            if got not in (_M, _U):
                raise RTDEError(
                    f"unexpected RTDE reply {chr(got)!r} while waiting for {chr(kind)!r}"
                )
        raise RTDEError("RTDE connection closed during setup")

    def _packets(self) -> Iterator[tuple[int, bytes]]:
        """Every packet, reading the socket when the buffer holds no complete one."""
        assert self._sock is not None
        buf = self._buffer
        while True:
            while len(buf) >= HEADER.size:
                size, kind = HEADER.unpack_from(buf)
                if size < HEADER.size:
                    raise RTDEError(f"malformed RTDE packet of size {size}")
                if len(buf) < size:
                    break
                payload = bytes(buf[HEADER.size : size])
                del buf[:size]
                yield kind, payload
            chunk = self._sock.recv(65536)
            if not chunk:
                return
            buf += chunk

    def samples(self) -> Iterator[RobotState]:
        """Every state sample until the connection closes (then raises RTDEError)."""
        assert self._struct is not None
        unpack = self._struct.unpack_from
        need = self._struct.size
        widths = self._widths
        for kind, payload in self._packets():
            if kind != _U or len(payload) < need:
                continue
            flat = unpack(payload)
            values: list[object] = []
            i = 1
            for w in widths:
                values.append(flat[i] if w == 1 else flat[i : i + w])
                i += w
            yield RobotState(**dict(zip(_ATTRS, values, strict=True)))  # type: ignore[arg-type]
        raise RTDEError("RTDE connection closed by the controller")
