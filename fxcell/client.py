"""``RemoteCell``: the Cell's await-style API over the network, against a running daemon.

```python
async with RemoteCell("http://127.0.0.1:8040", token) as cell:
    await cell.init()
    await cell.move_joint([0, -1.5708, 0, -1.5708, 0, 0])   # returns when the move ended
    op = await cell.start("move_joint", target=[...])       # or run it as an operation
    await op.cancel()                                        # = stop
```

Errors the daemon reports are raised as the same :mod:`fxcell.errors` classes the
Cell raises (``InvalidStateError``, ``MoveStoppedError``, ...); refusals of the
daemon itself are :class:`~fxcell.errors.NotAuthorizedError` and
:class:`~fxcell.errors.ControlHeldError`. Cancelling a task that awaits a move
cancels the move's operation, which stops the robot.
"""

from __future__ import annotations

import asyncio
import contextlib
import getpass
import json
import os
import socket
import urllib.parse
from collections.abc import AsyncIterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx

from fxcell import errors
from fxcell.commands import CellCommands, get_command

DEFAULT_URL = "http://127.0.0.1:8040"
CLIENT_HEADER = "X-Fxcell-Client"
LEASE_HEADER = "X-Fxcell-Lease"  # = fxcell.daemon.control.LEASE_HEADER (no daemon import here)


_EXT_VALUE = "utf-8''"


def encode_client_name(name: str) -> str:
    """``name`` as the value of the ``X-Fxcell-Client`` header: as it is when printable
    ASCII, else an RFC 8187 ext-value (``UTF-8''`` and the percent-encoded UTF-8 bytes),
    since header values are bytes that servers and browsers read as Latin-1."""
    if name.isascii() and name.isprintable() and not name.lower().startswith(_EXT_VALUE):
        return name
    return "UTF-8''" + urllib.parse.quote(name, safe="")


def decode_client_name(raw: bytes) -> str:
    """The client name an ``X-Fxcell-Client`` header value carries (see
    :func:`encode_client_name`); raw UTF-8 bytes are read as UTF-8 too, anything else
    that is not UTF-8 as Latin-1."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    text = text.strip()
    if text.lower().startswith(_EXT_VALUE):
        text = urllib.parse.unquote(text[len(_EXT_VALUE) :], errors="replace")
    return "".join(c for c in text if c.isprintable())


def default_client_name(program: str = "RemoteCell") -> str:
    """``user@host (program, pid N)``: how the daemon names this client to others."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = "unknown"
    return f"{user}@{socket.gethostname()} ({program}, pid {os.getpid()})"


def raise_error(body: Any, status: int) -> None:
    """Raise the fxcell error a daemon error body describes."""
    info = body.get("error") if isinstance(body, dict) else None
    if not isinstance(info, dict):
        raise errors.RemoteError(f"daemon answered HTTP {status}: {body!r}", status=status)
    raise build_error(info, status)


def build_error(info: dict[str, Any], status: int = 0) -> errors.FxcellError:
    """The exception an error record ``{"type", "message", "detail"}`` stands for."""
    name = str(info.get("type", "RemoteError"))
    message = str(info.get("message", ""))
    cls = getattr(errors, name, None)
    if not (isinstance(cls, type) and issubclass(cls, errors.FxcellError)):
        return errors.RemoteError(f"{name}: {message}", status=status or 500)
    exc = cls.__new__(cls)
    Exception.__init__(exc, message)
    for key, value in (info.get("detail") or {}).items():
        with contextlib.suppress(AttributeError):
            setattr(exc, key, tuple(value) if isinstance(value, list) else value)
    if isinstance(exc, errors.RemoteError):
        exc.status = status
    return exc


class RemoteOperation:
    """A command running in the daemon: wait for it, cancel it (a move stops)."""

    def __init__(self, cell: RemoteCell, record: dict[str, Any]) -> None:
        self._cell = cell
        self.record = record

    @property
    def id(self) -> str:
        return str(self.record["id"])

    @property
    def status(self) -> str:
        return str(self.record["status"])

    @property
    def done(self) -> bool:
        return self.status != "running"

    async def refresh(self) -> dict[str, Any]:
        self.record = await self._cell._request("GET", f"/api/operations/{self.id}")
        return self.record

    async def wait(self) -> Any:
        """Wait until the operation ends; its result, or its error raised.

        Cancelling the waiting task (e.g. by ``asyncio.timeout``) cancels the operation:
        a move brakes to a stop.
        """
        while not self.done:
            # The wait request is shielded: interrupting httpx mid-response leaves its
            # connection unclosed. On cancellation the operation is cancelled in the
            # daemon, which ends the pending wait request promptly and cleanly.
            request = asyncio.ensure_future(
                self._cell._request(
                    "POST", f"/api/operations/{self.id}/wait", params={"timeout": 20.0}
                )
            )
            try:
                self.record = await asyncio.shield(request)
            except asyncio.CancelledError:
                with contextlib.suppress(errors.FxcellError, httpx.HTTPError):
                    await self.cancel()
                with contextlib.suppress(Exception, asyncio.CancelledError):
                    async with asyncio.timeout(5.0):
                        await request
                raise
        return self.result()

    def result(self) -> Any:
        if self.record.get("error"):
            raise build_error(self.record["error"], int(self.record["error"].get("status", 0)))
        return self.record.get("result")

    async def cancel(self) -> dict[str, Any]:
        """Cancel the operation and return its final record."""
        self.record = await self._cell._request(
            "POST", f"/api/operations/{self.id}/cancel", auth=True
        )
        return self.record


class RemoteCell(CellCommands):
    """The Cell's API against a daemon at ``url`` (``Authorization: Bearer token``).

    ``token`` defaults to ``$FXCELL_TOKEN``; without one, queries work and commands
    raise :class:`~fxcell.errors.NotAuthorizedError`. ``transport`` replaces the network
    (e.g. ``httpx.ASGITransport(app)`` for an in-process daemon app).
    """

    def __init__(
        self,
        url: str = DEFAULT_URL,
        token: str | None = None,
        *,
        name: str | None = None,
        timeout: float = 30.0,
        transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        self.url = url.rstrip("/")
        self.token = token if token is not None else os.environ.get("FXCELL_TOKEN")
        self.name = name or default_client_name()
        self.lease: str | None = None
        """The control lease this client holds (taken with its first command)."""
        self._http = httpx.AsyncClient(
            base_url=self.url,
            timeout=httpx.Timeout(timeout, connect=5.0),
            headers={CLIENT_HEADER: encode_client_name(self.name)},
            transport=transport,
        )

    async def __aenter__(self) -> RemoteCell:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self, *, release: bool = True) -> None:
        """Release control (if held) and close the connection."""
        if release and self.token:
            with contextlib.suppress(errors.FxcellError, httpx.HTTPError):
                await self.release_control()
        await self._http.aclose()

    # ------------------------------------------------------------- transport

    async def _request(
        self,
        method: str,
        path: str,
        *,
        json_body: Any = None,
        params: dict[str, Any] | None = None,
        auth: bool = False,
    ) -> Any:
        headers = {}
        if auth:
            if not self.token:
                raise errors.NotAuthorizedError(
                    "no token: pass RemoteCell(url, token) or set FXCELL_TOKEN", status=401
                )
            headers["Authorization"] = f"Bearer {self.token}"
            if self.lease:
                headers[LEASE_HEADER] = self.lease
        try:
            response = await self._http.request(
                method, path, json=json_body, params=params, headers=headers
            )
        except httpx.TransportError as exc:
            raise errors.ConnectionLostError(
                f"cannot reach the daemon at {self.url}: {exc}"
            ) from exc
        lease = response.headers.get(LEASE_HEADER)
        if lease:
            self.lease = lease
        try:
            body = response.json()
        except ValueError:
            body = response.text
        if response.status_code >= 400:
            raise_error(body, response.status_code)
        return body

    async def _query(self, name: str) -> Any:
        return (await self._request("GET", f"/api/cell/{name}"))["result"]

    async def start(self, command: str, /, **args: Any) -> RemoteOperation:
        """Start ``command`` as an operation and return at once."""
        record = await self._request(
            "POST",
            f"/api/cell/{command}",
            json_body=args,
            params={"wait": "false"},
            auth=True,
        )
        return RemoteOperation(self, record)

    async def _command(self, command: str, /, **args: Any) -> Any:
        op = await self.start(command, **args)
        return await op.wait()

    # ------------------------------------------------------------- daemon

    async def snapshot(self) -> dict[str, Any]:
        """The daemon's state snapshot (cell state, robot mode, joints, control, operations)."""
        return await self._request("GET", "/api/state")  # type: ignore[no-any-return]

    async def get_state(self) -> str:
        """The state machine's current state (``cell.state`` of the Cell)."""
        return str(await self._query("state"))

    async def wait_for_state(self, *states: str, timeout: float | None = None) -> str:  # noqa: ASYNC109
        """Wait until the cell is in one of ``states``; returns it (as ``Cell.wait_for_state``)."""
        wanted = {str(s) for s in states}
        try:
            async with asyncio.timeout(timeout):
                async for message in self.stream(topics=("transition",)):
                    state = (
                        message["snapshot"]["state"]
                        if message["type"] == "hello"
                        else message.get("dest")
                    )
                    if state in wanted:
                        return str(state)
        except TimeoutError:
            raise errors.RobotTimeoutError(
                f"the cell did not reach {sorted(wanted)} within {timeout} s"
            ) from None
        raise errors.ConnectionLostError("the daemon closed the stream")

    async def info(self) -> dict[str, Any]:
        return await self._request("GET", "/api/info")  # type: ignore[no-any-return]

    async def statechart(self) -> dict[str, Any]:
        return await self._request("GET", "/api/statechart")  # type: ignore[no-any-return]

    async def operations(self, *, running: bool = False) -> list[dict[str, Any]]:
        return await self._request(  # type: ignore[no-any-return]
            "GET", "/api/operations", params={"running": str(running).lower()}
        )

    async def operation(self, op_id: str) -> RemoteOperation:
        return RemoteOperation(self, await self._request("GET", f"/api/operations/{op_id}"))

    async def control(self) -> dict[str, Any] | None:
        return await self._request("GET", "/api/control")  # type: ignore[no-any-return]

    async def take_control(self, *, force: bool = False) -> dict[str, Any]:
        """Take control of the cell (``force``: over from its holder); the lease is kept."""
        holder: dict[str, Any] = await self._request(
            "POST", "/api/control", json_body={"force": force}, auth=True
        )
        self.lease = holder.pop("lease", None) or self.lease
        return holder

    async def release_control(self) -> bool:
        if not self.lease:
            return False
        body = await self._request("DELETE", "/api/control", auth=True)
        self.lease = None
        return bool(body["released"])

    # ------------------------------------------------------------- the job

    async def job_status(self) -> dict[str, Any]:
        """The fusion-machine job: state, progress, each sample's locations, questions."""
        result: dict[str, Any] = await self._request("GET", "/api/job")
        return result

    async def job_start(self, run: Mapping[str, Any] | str | Path) -> dict[str, Any]:
        """Start a run: a run file (YAML or JSON, read here) or the run as a mapping; it is
        validated by the daemon before anything moves (``JobSpecError``)."""
        if not isinstance(run, Mapping):
            run = read_run_file(run)
        return await self._job("start", {"run": dict(run)})

    async def job_pause(self) -> dict[str, Any]:
        """Pause at the next safe point (the current step finishes first)."""
        return await self._job("pause")

    async def job_resume(self, answers: Mapping[str, str] | None = None) -> dict[str, Any]:
        """Resume, answering the recovery questions (question id → place) if there are any."""
        return await self._job("resume", {"answers": dict(answers or {})})

    async def job_abort(self) -> dict[str, Any]:
        """Abort the current step (the arm brakes); the run stays resumable."""
        return await self._job("abort")

    async def job_confirm(self, prompt: str | None = None) -> dict[str, Any]:
        """Manual machine mode: confirm the machine was started, or is done."""
        return await self._job("confirm", {"prompt": prompt} if prompt else {})

    async def job_discard(self) -> dict[str, Any]:
        """Forget a paused or faulted run (the samples stay where the job says they are)."""
        return await self._job("discard")

    async def _job(self, name: str, body: Mapping[str, Any] | None = None) -> dict[str, Any]:
        result: dict[str, Any] = await self._request(
            "POST", f"/api/job/{name}", json_body=dict(body or {}), auth=True
        )
        return result

    async def stream(
        self, *, rate: float = 50.0, topics: Sequence[str] | None = None
    ) -> AsyncIterator[dict[str, Any]]:
        """Messages of the daemon's WebSocket stream (``hello`` first, then as they come)."""
        import websockets

        ws_url = self.url.replace("http://", "ws://", 1).replace("https://", "wss://", 1)
        params = {"rate": str(rate), "client": self.name}
        if self.lease:
            params["lease"] = self.lease
        if topics:
            params["topics"] = ",".join(topics)
        query = urllib.parse.urlencode(params)
        async with websockets.connect(f"{ws_url}/api/stream?{query}", max_size=None) as ws:
            async for text in ws:
                message = json.loads(text)
                if message.get("type") == "ping":  # the daemon checks we are alive
                    await ws.send('{"type": "pong"}')
                    continue
                yield message

    # ------------------------------------------------------------- commands
    # Every command method (power_on, move_joint, stop, ...) comes from CellCommands,
    # whose default bodies call run_command: the command table says how each goes over
    # HTTP and how its answer decodes.

    async def run_command(self, command: str, /, **args: Any) -> Any:
        """Run ``command`` of :data:`fxcell.commands.COMMANDS` in the daemon; its
        result decoded into the type the Cell returns."""
        entry = get_command(command)
        entry.check_args(args)
        if entry.kind == "query":
            value = await self._query(command)
        else:
            value = await self._command(
                command, **{k: _plain(v) for k, v in args.items() if v is not None}
            )
        return entry.result.decode(value)


def read_run_file(path: str | Path) -> dict[str, Any]:
    """A run file (YAML or JSON) as a mapping; :class:`InvalidArgumentError` if unreadable."""
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise errors.InvalidArgumentError(f"cannot read run file {path}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise errors.InvalidArgumentError(f"{path}: not valid YAML or JSON: {exc}") from None
    if not isinstance(data, dict):
        raise errors.InvalidArgumentError(f"{path}: a run is a mapping with a 'samples' list")
    return data


def _plain(value: Any) -> Any:
    """Sequences (numpy arrays, tuples) as JSON lists; a Pose as [x, y, z, qx, qy, qz, qw]."""
    if hasattr(value, "position") and hasattr(value, "quaternion"):
        return [float(v) for v in (*value.position, *value.quaternion)]
    tolist = getattr(value, "tolist", None)
    if callable(tolist):
        return tolist()
    if isinstance(value, tuple):
        return list(value)
    return value
