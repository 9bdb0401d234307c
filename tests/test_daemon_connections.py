"""The daemon's HTTP server closes connections too slow to send a request.

uvicorn, with the daemon's protocol (``fxcell.daemon.connection``), serves the daemon's app
in this process on a free loopback port; the clients are raw sockets.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import time
from collections.abc import AsyncIterator, Iterator

import pytest
import uvicorn
import websockets

from fxcell.config import CellConfig
from fxcell.daemon.app import create_app
from fxcell.daemon.connection import guarded_protocol
from fxcell.daemon.service import CellService

TOKEN = "s3cret-token-for-tests-0123456789"
HEADER_TIMEOUT = 0.5
BODY_TIMEOUT = 0.8


class _Server(uvicorn.Server):
    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:  # the test process keeps its signals
        yield


@pytest.fixture
async def server() -> AsyncIterator[tuple[str, int]]:
    service = CellService(CellConfig.from_dict({"robot": {"command_timeout": 0.3}}), TOKEN)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(1024)
    sock.setblocking(False)
    config = uvicorn.Config(
        create_app(service),
        log_level="warning",
        lifespan="off",
        ws="websockets-sansio",
        ws_ping_interval=None,
        http=guarded_protocol(HEADER_TIMEOUT, BODY_TIMEOUT),
        timeout_keep_alive=1,
        timeout_graceful_shutdown=1,
    )
    srv = _Server(config)
    # the socket listens already: connections made before uvicorn runs wait in its backlog
    task = asyncio.create_task(srv.serve(sockets=[sock]))
    try:
        yield sock.getsockname()
    finally:
        srv.should_exit = True
        await task
        sock.close()


async def _closed_by_server(reader: asyncio.StreamReader) -> float:
    """Read until the server closes the connection; returns when (monotonic). A reset is a
    close too: a server that times a connection out before its loop read the bytes already
    received (a busy machine, 400 at once) closes it with data unread, which is an RST."""
    with contextlib.suppress(ConnectionResetError):
        while await reader.read(4096):
            pass
    return time.monotonic()


async def test_400_half_open_connections_are_closed_after_the_header_timeout(
    server: tuple[str, int],
) -> None:
    host, port = server
    streams, opened = [], []
    for _ in range(400):
        opened.append(time.monotonic())  # before the server can have accepted it
        reader, writer = await asyncio.open_connection(host, port)
        writer.write(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Fxcell-Cli")
        streams.append((reader, writer))
    last = time.monotonic()
    async with asyncio.timeout(HEADER_TIMEOUT + 5.0):  # bounded: never hangs the suite
        closed = await asyncio.gather(*(_closed_by_server(r) for r, _ in streams))
    for _, writer in streams:
        writer.close()
    # none closed before its deadline; all within a few seconds of the last one's
    assert min(c - t for c, t in zip(closed, opened, strict=True)) >= HEADER_TIMEOUT
    assert max(closed) - last < HEADER_TIMEOUT + 3.0


async def test_a_body_that_stops_coming_is_cut_off(server: tuple[str, int]) -> None:
    host, port = server
    reader, writer = await asyncio.open_connection(host, port)
    writer.write(
        b"POST /api/cell/move_joint HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        + f"Authorization: Bearer {TOKEN}\r\n".encode()
        + b'Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{"target": ['
    )
    sent = time.monotonic()
    async with asyncio.timeout(BODY_TIMEOUT + 5.0):
        closed = await _closed_by_server(reader)
    writer.close()
    assert BODY_TIMEOUT - 0.05 <= closed - sent < BODY_TIMEOUT + 3.0


async def test_requests_sent_in_time_are_served_on_a_kept_alive_connection(
    server: tuple[str, int],
) -> None:
    host, port = server
    reader, writer = await asyncio.open_connection(host, port)
    for _ in range(3):
        writer.write(b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        await asyncio.sleep(HEADER_TIMEOUT / 3)  # a slow but punctual client
        writer.write(b"\r\n")
        status = await reader.readline()
        assert status.startswith(b"HTTP/1.1 200"), status
        length = 0
        while (line := await reader.readline()) != b"\r\n":
            if line.lower().startswith(b"content-length:"):
                length = int(line.split(b":")[1])
        assert json.loads(await reader.readexactly(length))["version"]
        await asyncio.sleep(HEADER_TIMEOUT * 1.5)  # idle between requests: keep-alive's 1 s
    writer.close()


async def test_the_deadlines_end_with_a_websocket_upgrade(server: tuple[str, int]) -> None:
    host, port = server
    async with websockets.connect(f"ws://{host}:{port}/api/stream?topics=control") as ws:
        assert json.loads(await ws.recv())["type"] == "hello"
        await asyncio.sleep(2 * BODY_TIMEOUT)  # past both deadlines
        async with asyncio.timeout(5):
            await (await ws.ping())  # still open: the server answers


async def test_a_stream_ignores_messages_it_cannot_read(server: tuple[str, int]) -> None:
    host, port = server
    async with websockets.connect(f"ws://{host}:{port}/api/stream?topics=control") as ws:
        assert json.loads(await ws.recv())["type"] == "hello"
        for text in (
            "[" * 100_000 + "]" * 100_000,  # deeper than the JSON parser goes
            '{"rate": ' + "9" * 5000 + "}",
            '{"rate": 1' + "0" * 400 + "}",  # a number no float holds
            '{"rate": "fast"}',
            "[1, 2]",
            "\udcff".encode("utf-8", "surrogatepass").decode("latin-1"),
        ):
            await ws.send(text)
        with pytest.raises(TimeoutError):  # the server keeps the stream open
            await asyncio.wait_for(ws.wait_closed(), 1.0)
