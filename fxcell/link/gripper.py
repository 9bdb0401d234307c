"""The gripper seam: what ``cell.gripper`` needs of a robot kind's gripper
(:class:`GripperDriver`, described by a :class:`GripperSpec`), and the UR3e's: the Robotiq
Hand-E through the Robotiq URCap's socket (:class:`HandEGripper` over
:class:`URCapGripperClient`, port 63352 of the controller).

A driver speaks SI units (widths in m, speeds in m/s, forces in N) and its tool's own
protocol; the Cell's :class:`~fxcell.cell.gripper.Gripper` checks every argument against the
driver's spec before anything is sent, keeps the state machine and records the commands.
A kind names its driver factory in its :class:`~fxcell.robots.RobotKind` (``gripper``).

The URCap serves one ASCII request per line: ``SET VAR value [VAR value ...]`` answered by
``ack``, ``GET VAR`` answered by ``VAR value``. One connection, one request at a time (a lock
keeps concurrent callers' replies apart); every request has a timeout, and a lost or silent
connection raises :class:`~fxcell.errors.ConnectionLostError` / :class:`RobotTimeoutError`
and is reopened by the next request.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from fxcell.commands import GRIP_FORCE_RANGE, GRIP_SPEED_RANGE, GRIP_WIDTH_RANGE
from fxcell.errors import (
    ConnectionLostError,
    GripperError,
    GripperFaultError,
    RobotTimeoutError,
)
from fxcell.results import GripResult

__all__ = [
    "HAND_E",
    "GripperDriver",
    "GripperFactory",
    "GripperReading",
    "GripperSpec",
    "HandEGripper",
    "URCapGripperClient",
    "hand_e",
]

URCAP_GRIPPER_PORT = 63352
REQUEST_TIMEOUT = 2.0  # s for one request and its reply
POLL = 0.01  # s between two status reads while the fingers move


@dataclass(frozen=True)
class GripperSpec:
    """What a gripper can do, in SI units: the Cell refuses anything else before it sends."""

    name: str
    """The tool as its maker names it (``Robotiq Hand-E``, ``Niryo Gripper 1``)."""
    stroke: float
    """Finger opening when fully open (m); 0 is closed."""
    speed_range: tuple[float, float] | None
    """Finger speeds it takes (m/s); None: it has no speed setting (its own is used)."""
    force_range: tuple[float, float] | None
    """Grip forces it takes (N); None: it has no force setting in newtons."""
    default_speed: float | None
    default_force: float | None
    continuous: bool = True
    """Any opening in [0, stroke]; False: only closed (0) and fully open (``stroke``)."""
    detects_objects: bool = True
    """Whether the tool tells that its fingers stopped on an object."""

    def opening(self, width: float) -> float:
        """The opening the gripper goes to when at least ``width`` is asked for: ``width``
        itself (at most the stroke) for a continuous gripper, its stroke otherwise."""
        return min(self.stroke, width) if self.continuous else self.stroke


@dataclass(frozen=True)
class GripperReading:
    """One read of the gripper."""

    active: bool
    """It takes commands (the Hand-E: activated, ``STA`` 3; a tool that needs no
    activation: connected)."""
    fault: int
    """The tool's fault code, 0: none."""
    width: float
    """Finger opening (m)."""
    holding: bool
    """The fingers stopped on an object (as far as the tool tells)."""


class GripperDriver(Protocol):
    """A robot kind's gripper as ``cell.gripper`` drives it. Every call raises typed
    fxcell errors (:class:`~fxcell.errors.GripperError` and its kinds,
    ConnectionLostError, RobotTimeoutError); ``guard`` is called while the driver waits
    (it raises to abandon the wait, e.g. when the arm loses power)."""

    @property
    def spec(self) -> GripperSpec: ...

    async def read(self) -> GripperReading:
        """The gripper's state now."""

    async def activate(self, within: float, guard: Callable[[], None]) -> None:
        """Reset and activate it; return once it takes commands."""

    async def move(
        self,
        width: float,
        speed: float | None,
        force: float | None,
        *,
        within: float,
        guard: Callable[[], None],
    ) -> GripResult:
        """Move the fingers to ``width`` (within the spec: checked by the caller) and wait
        until they stop; GripperFaultError when the tool faults meanwhile."""

    async def halt(self) -> None:
        """Stop the fingers where they are (a cancelled move); a tool that cannot stop
        mid-stroke finishes it."""

    async def close(self) -> None:
        """Close the connection (the next call reopens it)."""


GripperFactory = Callable[[str], GripperDriver]
"""A kind's gripper driver for the controller at ``host``."""

HAND_E = GripperSpec(
    name="Robotiq Hand-E",
    stroke=GRIP_WIDTH_RANGE[1],
    speed_range=GRIP_SPEED_RANGE,
    force_range=GRIP_FORCE_RANGE,
    default_speed=GRIP_SPEED_RANGE[1],
    default_force=GRIP_FORCE_RANGE[1],
)
"""The Hand-E: 0..50 mm, 20..150 mm/s, 20..185 N, object detection (``OBJ``)."""


class URCapGripperClient:
    """An asyncio client of the Robotiq URCap gripper socket at ``host:port``."""

    def __init__(
        self, host: str, port: int = URCAP_GRIPPER_PORT, *, timeout: float = REQUEST_TIMEOUT
    ) -> None:
        self.host = host
        self.port = port
        self.timeout = timeout
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._lock = asyncio.Lock()

    async def _request(self, line: str) -> str:
        async with self._lock:
            try:
                async with asyncio.timeout(self.timeout):
                    if self._writer is None:
                        self._reader, self._writer = await asyncio.open_connection(
                            self.host, self.port
                        )
                async with asyncio.timeout(self.timeout):
                    reader, writer = self._reader, self._writer
                    assert reader is not None
                    assert writer is not None
                    writer.write(line.encode("ascii") + b"\n")
                    await writer.drain()
                    raw = await reader.readline()
            except TimeoutError:
                await self._drop()
                raise RobotTimeoutError(
                    f"the gripper socket {self.host}:{self.port} did not answer {line!r} "
                    f"within {self.timeout:g} s"
                ) from None
            except asyncio.CancelledError:
                await self._drop()  # a reply may still come: the stream is out of step
                raise
            except OSError as exc:
                await self._drop()
                raise ConnectionLostError(
                    f"the gripper socket {self.host}:{self.port} is unreachable ({exc}); "
                    "is the Robotiq URCap installed and the gripper configured on the controller?"
                ) from None
            if not raw.endswith(b"\n"):
                await self._drop()
                raise ConnectionLostError(f"the gripper socket {self.host}:{self.port} closed")
            return raw.decode("ascii", "replace").strip()

    async def get(self, name: str) -> int:
        """The value of gripper variable ``name`` (``POS``, ``OBJ``, ``STA``, ...)."""
        reply = await self._request(f"GET {name}")
        words = reply.split()
        if len(words) != 2 or words[0] != name or not words[1].lstrip("-").isdigit():
            raise GripperError(f"the gripper answered GET {name} with {reply!r}")
        return int(words[1])

    async def set(self, **values: int) -> None:
        """Set gripper variables in one request, in the order given (``GTO`` last)."""
        line = "SET " + " ".join(f"{k} {int(v)}" for k, v in values.items())
        reply = await self._request(line)
        if reply != "ack":
            raise GripperError(f"the gripper answered {line!r} with {reply!r}")

    async def _drop(self) -> None:
        writer, self._writer, self._reader = self._writer, None, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    async def close(self) -> None:
        """Close the connection (the next request reopens it)."""
        async with self._lock:
            await self._drop()


def _register(value: float, lo: float, hi: float) -> int:
    return max(0, min(255, round(255.0 * (value - lo) / (hi - lo))))


def _width(position: int) -> float:
    return HAND_E.stroke * (1.0 - max(0, min(255, position)) / 255.0)


class HandEGripper:
    """The UR3e's gripper: the Robotiq Hand-E's registers (``ACT``, ``GTO``, ``POS``,
    ``SPE``, ``FOR``; ``STA``, ``FLT``, ``PRE``, ``OBJ``) in SI units."""

    def __init__(self, host: str, port: int = URCAP_GRIPPER_PORT) -> None:
        self.host = host
        self.io = URCapGripperClient(host, port)

    @property
    def spec(self) -> GripperSpec:
        return HAND_E

    async def read(self) -> GripperReading:
        io = self.io
        status, fault = await io.get("STA"), await io.get("FLT")
        width = _width(await io.get("POS"))
        return GripperReading(status == 3, fault, width, await io.get("OBJ") in (1, 2))

    async def activate(self, within: float, guard: Callable[[], None]) -> None:
        io = self.io
        await io.set(ACT=0)
        await io.set(ACT=1)
        deadline = time.monotonic() + within
        while await io.get("STA") != 3:
            if time.monotonic() > deadline:
                raise RobotTimeoutError(f"the gripper did not activate within {within:g} s")
            guard()
            await asyncio.sleep(POLL)

    async def move(
        self,
        width: float,
        speed: float | None,
        force: float | None,
        *,
        within: float,
        guard: Callable[[], None],
    ) -> GripResult:
        io = self.io
        position = round(255.0 * (1.0 - width / HAND_E.stroke))
        await io.set(
            POS=position,
            SPE=_register(GRIP_SPEED_RANGE[1] if speed is None else speed, *GRIP_SPEED_RANGE),
            FOR=_register(GRIP_FORCE_RANGE[1] if force is None else force, *GRIP_FORCE_RANGE),
            GTO=1,
        )
        deadline = time.monotonic() + within
        while True:
            fault = await io.get("FLT")
            if fault:
                raise GripperFaultError(fault, f"the gripper faulted (0x{fault:02X}) mid-motion")
            if await io.get("PRE") == position:
                obj = await io.get("OBJ")
                if obj != 0:
                    break
            if time.monotonic() > deadline:
                raise RobotTimeoutError(f"the fingers did not stop within {within:g} s")
            guard()
            await asyncio.sleep(POLL)
        return GripResult(_width(await io.get("POS")), obj in (1, 2))

    async def halt(self) -> None:
        await self.io.set(GTO=0)

    async def close(self) -> None:
        await self.io.close()


def hand_e(host: str) -> HandEGripper:
    """The UR3e kind's gripper factory."""
    return HandEGripper(host)
