"""Request hygiene in front of the API: Host allow-list, token before body, body size limit.

A plain ASGI middleware, so that it acts on the headers before anything reads a body:

- **Host allow-list** (DNS rebinding): a request or WebSocket whose ``Host`` is a name
  that is neither ``localhost``, the bind address nor one of ``daemon.allowed_hosts`` is
  refused with 421. IP literals are always accepted: a rebinding attack needs a name.
- **Token before body**: a request that carries a body must show a valid bearer token in
  its headers, or it is refused with 401 before one byte of the body is read.
- **Body size**: a declared ``Content-Length`` above the limit is refused with 413 at once;
  a body without a declared length (chunked) is read here up to the limit, refused with 413
  beyond it, and handed on whole.

So a hostile upload costs the event loop nothing, and STOP is never queued behind it.
"""

from __future__ import annotations

import ipaddress
import json
import urllib.parse
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from typing import Any

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

DEFAULT_MAX_BODY = 1024 * 1024


def _error(status: int, kind: str, message: str) -> bytes:
    body = {"error": {"type": kind, "message": message, "status": status, "detail": {}}}
    return json.dumps(body).encode()


def host_name(header: str) -> str:
    """The name part of a ``Host`` header (no port, no IPv6 brackets), lower case."""
    header = header.strip().lower()
    if header.startswith("["):
        return header[1 : header.find("]")] if "]" in header else header[1:]
    return header.rsplit(":", 1)[0] if header.count(":") == 1 else header


_DEFAULT_PORTS = {"http": 80, "https": 443}
_PAGE_SCHEME = {"ws": "http", "wss": "https", "http": "http", "https": "https"}


def same_origin(origin: str, scheme: str, host: str | None) -> bool:
    """Whether a browser's ``Origin`` is the daemon's own: the page's scheme (``http`` for
    a ``ws`` connection, ``https`` for ``wss``, as uvicorn sees it, a TLS proxy's
    ``X-Forwarded-Proto`` included), host and port (default ports filled in) all equal."""
    try:
        page = urllib.parse.urlsplit(origin)
        page_port = page.port
        ours = urllib.parse.urlsplit(f"//{host or ''}")
        our_port = ours.port
    except ValueError:
        return False
    want = _PAGE_SCHEME.get(scheme)
    if want is None or page.scheme.lower() != want or not page.hostname or not ours.hostname:
        return False
    default = _DEFAULT_PORTS[want]
    return page.hostname.lower() == ours.hostname.lower() and (page_port or default) == (
        our_port or default
    )


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


class RequestGuard:
    """The ASGI middleware described in the module docstring."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        authorized: Callable[[str | None], bool],
        max_body: int = DEFAULT_MAX_BODY,
        allowed_hosts: Iterable[str] = (),
    ) -> None:
        self.app = app
        self.authorized = authorized
        self.max_body = max_body
        self.allowed_hosts = {"localhost"} | {host_name(h) for h in allowed_hosts}

    def host_allowed(self, header: str | None) -> bool:
        if header is None:
            return True  # HTTP/1.0 without Host: no browser sends that
        name = host_name(header)
        return _is_ip(name) or name in self.allowed_hosts or name.endswith(".localhost")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        if not self.host_allowed(headers.get("host")):
            refusal = f"host {headers.get('host')!r} is not served here (daemon.allowed_hosts)"
            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008, "reason": refusal[:120]})
                return
            await self._refuse(send, 421, "NotAuthorizedError", refusal)
            return
        if scope["type"] == "websocket":
            await self.app(scope, receive, send)
            return
        length = headers.get("content-length")
        has_body = (length is not None and length.strip() not in ("", "0")) or (
            "chunked" in headers.get("transfer-encoding", "").lower()
        )
        if has_body and not self.authorized(headers.get("authorization")):
            await self._refuse(
                send,
                401,
                "NotAuthorizedError",
                "send 'Authorization: Bearer <token>' with every request that has a body",
            )
            return
        if length is not None:
            try:
                declared = int(length)
            except ValueError:
                await self._refuse(send, 400, "InvalidArgumentError", "bad Content-Length")
                return
            if declared > self.max_body:
                await self._refuse(
                    send,
                    413,
                    "InvalidArgumentError",
                    f"request body of {declared} bytes exceeds the {self.max_body} allowed",
                )
                return
            await self.app(scope, receive, send)
            return
        if not has_body:
            await self.app(scope, receive, send)
            return
        # No declared length (chunked): read at most the limit here, then hand it on.
        chunks: list[bytes] = []
        seen = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                return  # the client went away
            chunk = message.get("body", b"")
            seen += len(chunk)
            if seen > self.max_body:
                await self._refuse(
                    send,
                    413,
                    "InvalidArgumentError",
                    f"request body exceeds the {self.max_body} bytes allowed",
                )
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    @staticmethod
    async def _refuse(send: Send, status: int, kind: str, message: str) -> None:
        body = _error(status, kind, message)
        headers = [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ]
        if status == 401:
            headers.append((b"www-authenticate", b"Bearer"))
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})
