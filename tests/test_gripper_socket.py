"""The URCap gripper socket client: cancellation and timeouts, on stand-in streams."""

from __future__ import annotations

import asyncio

import pytest

from fxcell.errors import RobotTimeoutError
from fxcell.link.gripper import URCapGripperClient


class _Writer:
    """A stand-in StreamWriter that records what was sent."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []
        self.closed = False
        self.wrote = asyncio.Event()

    def write(self, data: bytes) -> None:
        self.sent.append(data)
        self.wrote.set()

    async def drain(self) -> None:
        return None

    def close(self) -> None:
        self.closed = True

    async def wait_closed(self) -> None:
        return None


class _Reader:
    """A stand-in StreamReader whose next line is a future the test resolves."""

    def __init__(self) -> None:
        self.line: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()

    def readline(self) -> asyncio.Future[bytes]:
        return self.line


def _connected(timeout: float = 2.0) -> tuple[URCapGripperClient, _Reader, _Writer]:
    client = URCapGripperClient("127.0.0.1", 1, timeout=timeout)
    reader, writer = _Reader(), _Writer()
    client._reader, client._writer = reader, writer  # type: ignore[assignment]
    return client, reader, writer


async def test_a_cancel_arriving_with_the_reply_still_cancels_the_request() -> None:
    # asyncio.wait_for on Python 3.11 returned the reply and dropped this cancel, so a
    # cancelled grasp kept closing the fingers (a CI failure of test_gripper).
    client, reader, writer = _connected()
    request = asyncio.create_task(client.get("POS"))
    await writer.wrote.wait()
    reader.line.set_result(b"POS 12\n")
    request.cancel()
    with pytest.raises(asyncio.CancelledError):
        await request
    assert writer.closed, "a cancelled request leaves the stream out of step: it is dropped"


async def test_a_reply_is_parsed_when_nothing_cancels() -> None:
    client, reader, writer = _connected()
    request = asyncio.create_task(client.get("POS"))
    await writer.wrote.wait()
    reader.line.set_result(b"POS 12\n")
    assert await request == 12
    assert writer.sent == [b"GET POS\n"]
    assert not writer.closed


async def test_a_silent_socket_times_out_with_a_typed_error() -> None:
    client, _reader, writer = _connected(timeout=0.05)
    with pytest.raises(RobotTimeoutError, match="did not answer 'GET OBJ'"):
        await client.get("OBJ")
    assert writer.closed
