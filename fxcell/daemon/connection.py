"""Deadlines for reading a request: a connection that is too slow to send one is closed.

uvicorn closes a connection that stays idle between requests (``timeout_keep_alive``), but
not one that sent part of a request and then nothing: a local process could hold the
daemon's file descriptors with connections that never finish their headers. The daemon's
HTTP protocol is uvicorn's httptools protocol with two deadlines more:

- ``header_timeout``: from the connection (or the first byte of a next request on a kept-alive
  connection) until the request's headers are complete;
- ``body_timeout``: from the end of the headers until the body is complete.

A connection that misses one is closed (an app still reading the body sees the client
disconnect). A WebSocket upgrade ends the deadlines: the stream has its own pings.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

log = logging.getLogger(__name__)

DEFAULT_HEADER_TIMEOUT = 3.0
DEFAULT_BODY_TIMEOUT = 10.0


def guarded_protocol(header_timeout: float, body_timeout: float) -> type[HttpToolsProtocol]:
    """uvicorn's httptools protocol with these deadlines (pass it as ``Config(http=...)``)."""

    class Protocol(_DeadlineProtocol):
        pass

    Protocol.header_timeout = header_timeout
    Protocol.body_timeout = body_timeout
    return Protocol


class _DeadlineProtocol(HttpToolsProtocol):
    header_timeout = DEFAULT_HEADER_TIMEOUT
    body_timeout = DEFAULT_BODY_TIMEOUT

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._deadline: asyncio.TimerHandle | None = None

    def _arm(self, seconds: float, what: str) -> None:
        self._disarm()
        self._deadline = self.loop.call_later(seconds, self._expired, what)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _expired(self, what: str) -> None:
        self._deadline = None
        if not self.transport.is_closing():
            log.info("closing a connection from %s: %s not received in time", self.client, what)
            self.transport.close()

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm(self.header_timeout, "request headers")

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._deadline is None and (self.cycle is None or self.cycle.response_complete):
            # the first bytes of a next request on a kept-alive connection
            self._arm(self.header_timeout, "request headers")
        super().data_received(data)

    def on_headers_complete(self) -> None:
        self._arm(self.body_timeout, "request body")
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        self._disarm()
        super().on_message_complete()

    def handle_websocket_upgrade(self) -> None:
        self._disarm()
        super().handle_websocket_upgrade()
