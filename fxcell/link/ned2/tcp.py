"""An asyncio client of the Ned2's TCP server (port 40001), the protocol pyniryo speaks.

A frame is a 2-byte length (``struct '@H'``) then JSON: a request ``{"command": NAME,
"param_list": [...]}``; an answer ``{"status": "OK", "command", "list_ret_param",
"payload_size"}`` followed by ``payload_size`` raw bytes, or ``{"status": "KO",
"message"}``. Enums travel by name, booleans as ``"TRUE"``/``"FALSE"`` (and come back as
``"True"``/``"False"`` strings: :func:`robot_bool`). The server serves one client at a
time and answers a command once it has finished, so :meth:`NiryoTcpClient.command` holds
the connection for a whole move; a stop comes through the rosbridge.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from fxcell.errors import (
    ConnectionLostError,
    InvalidArgumentError,
    RobotCommandError,
    RobotCommandStatusError,
    RobotTimeoutError,
)
from fxcell.link.ned2 import TCP_PORT

__all__ = ["PROTOCOL_VERSION", "NiryoTcpClient", "Reply", "robot_bool"]

PROTOCOL_VERSION = "1.2.5"  # the pyniryo release whose protocol this client speaks
LENGTH = struct.Struct("@H")
_STATUS = re.compile(r"Error Code : (-?\d+)\s*Message : (.*)", re.DOTALL)


@dataclass(frozen=True)
class Reply:
    """An OK answer: the command's return values and its raw payload (images)."""

    values: list[Any]
    payload: bytes = b""


def robot_bool(value: object) -> bool:
    """A boolean as the robot answers it (``"True"``/``"False"`` strings, or a bool)."""
    if isinstance(value, bool):
        return value
    if value in ("True", "TRUE", "true"):
        return True
    if value in ("False", "FALSE", "false"):
        return False
    raise RobotCommandError(f"the robot answered {value!r} where a boolean was expected")


def _param(value: object) -> object:
    if isinstance(value, bool):
        return "TRUE" if value else "FALSE"
    if value is None:
        return "None"
    return value


def refusal(message: str) -> RobotCommandError:
    """The typed error of a KO answer: with the robot's status code where it gives one."""
    found = _STATUS.search(message)
    if found is not None:
        return RobotCommandStatusError(int(found.group(1)), found.group(2).strip())
    return RobotCommandError(message.strip())


class NiryoTcpClient:
    """One connection to the robot's TCP server; commands are serialised (the server
    answers them in order, one at a time)."""

    def __init__(self, host: str, port: int = TCP_PORT) -> None:
        self.host = host
        self.port = port
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._lock = asyncio.Lock()

    @property
    def connected(self) -> bool:
        return self._writer is not None and not self._writer.is_closing()

    async def connect(self, within: float = 5.0) -> None:
        """Connect and make the handshake (a robot that predates it answers "Unknown
        command", which is accepted as pyniryo accepts it)."""
        try:
            async with asyncio.timeout(within):
                self._reader, self._writer = await asyncio.open_connection(self.host, self.port)
        except TimeoutError:
            raise RobotTimeoutError(
                f"the Ned2 at {self.host}:{self.port} did not accept a connection "
                f"within {within:g} s"
            ) from None
        except OSError as exc:
            raise ConnectionLostError(
                f"cannot reach the Ned2 at {self.host}:{self.port}: {exc.strerror or exc}"
            ) from None
        try:
            await self.command("HANDSHAKE", PROTOCOL_VERSION, within=within)
        except RobotCommandError as exc:
            if "Unknown command" not in str(exc):
                await self.close()
                raise

    async def close(self) -> None:
        writer, self._writer, self._reader = self._writer, None, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(OSError):  # the robot had dropped the connection
                await writer.wait_closed()

    async def command(self, name: str, *params: object, within: float | None = 5.0) -> Reply:
        """Send one command and wait for its answer (``within`` seconds; None: however
        long it takes, e.g. a move). A KO answer raises :class:`RobotCommandError`
        (:class:`RobotCommandStatusError` with the robot's status code)."""
        body = json.dumps({"command": name, "param_list": [_param(p) for p in params]}).encode()
        if len(body) > 0xFFFF:
            raise InvalidArgumentError(f"{name}: the request is {len(body)} bytes (max 65535)")
        async with self._lock:
            reader, writer = self._reader, self._writer
            if reader is None or writer is None or writer.is_closing():
                raise ConnectionLostError(f"not connected to the Ned2 at {self.host}")
            try:
                writer.write(LENGTH.pack(len(body)) + body)
                await writer.drain()
                async with asyncio.timeout(within):
                    answer, payload = await self._read(reader)
            except TimeoutError:
                await self.close()  # the answer may still come: the stream is out of step
                raise RobotTimeoutError(
                    f"{name}: no answer from the Ned2 within {within:g} s"
                ) from None
            except (OSError, asyncio.IncompleteReadError) as exc:
                await self.close()
                raise ConnectionLostError(
                    f"{name}: the Ned2 dropped the connection ({exc})"
                ) from None
        if answer.get("status") != "OK":
            raise refusal(str(answer.get("message", answer)))
        values = answer.get("list_ret_param", [])
        return Reply(values if isinstance(values, list) else [values], payload)

    @staticmethod
    async def _read(reader: asyncio.StreamReader) -> tuple[dict[str, Any], bytes]:
        head = await reader.readexactly(LENGTH.size)
        body = await reader.readexactly(LENGTH.unpack(head)[0])
        try:
            answer = json.loads(body)
        except ValueError:
            raise RobotCommandError(
                f"the Ned2 answered a frame that is not JSON: {body[:80]!r}"
            ) from None
        if not isinstance(answer, dict):
            raise RobotCommandError(f"the Ned2 answered {answer!r}, not an object")
        size = answer.get("payload_size", 0)
        payload = await reader.readexactly(size) if isinstance(size, int) and size > 0 else b""
        return answer, payload


def joints(values: Sequence[Any]) -> list[float]:
    """Six joint positions from an answer's values (GET_JOINTS)."""
    if len(values) != 6 or not all(isinstance(v, (int, float)) for v in values):
        raise RobotCommandError(f"the Ned2 answered {list(values)!r} for six joint positions")
    return [float(v) for v in values]
