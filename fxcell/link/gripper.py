"""The Robotiq URCap's gripper socket (port 63352 of the controller), from asyncio.

The URCap serves one ASCII request per line: ``SET VAR value [VAR value ...]`` answered by
``ack``, ``GET VAR`` answered by ``VAR value``. One connection, one request at a time (a lock
keeps concurrent callers' replies apart); every request has a timeout, and a lost or silent
connection raises :class:`~fxcell.errors.ConnectionLostError` / :class:`RobotTimeoutError`
and is reopened by the next request.
"""

from __future__ import annotations

import asyncio
import contextlib

from fxcell.errors import ConnectionLostError, GripperError, RobotTimeoutError

URCAP_GRIPPER_PORT = 63352
REQUEST_TIMEOUT = 2.0  # s for one request and its reply


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
