"""The daemon's HTTP + WebSocket API (FastAPI): every Cell function, operations, control.

Layout of the API (the OpenAPI document is at ``/api/openapi.json``, browsable at
``/api/docs``):

- ``GET /api/state``: one snapshot (cell state, robot mode, joints, TCP, control, operations)
  from the newest 500 Hz sample — no robot round trip.
- ``GET /api/cell/<query>``: the Cell's general and kinematic queries (``get_robot_mode``, ...).
- ``POST /api/cell/<command>``: commands that change the robot. They need the bearer token
  and control; each runs as an operation, once the Cell's admission
  (``Cell.check_command``) has passed: a refusal is the answer (409/422) whatever ``wait``
  is. General commands answer when done (``wait`` defaults to true), moves answer at once
  with 202 and the operation (``wait=true`` to block).
- ``/api/operations``: list, get, wait on and cancel operations (cancel = stop).
- ``/api/control``: who controls the cell; take (``force`` to take over) and release it.
- ``/api/statechart``: the robot-mode state machine as data, with the states each command needs.
- ``WS /api/stream``: robot state at a chosen rate, transitions, commands, operations.
"""

# No "from __future__ import annotations": FastAPI reads the request models of the
# routes built in loops from their evaluated annotations.
import asyncio
import contextlib
import json
import time
from collections.abc import Awaitable, Callable
from importlib import resources
from typing import Any

from fastapi import APIRouter, Body, FastAPI, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException

from fxcell._version import __version__
from fxcell.client import CLIENT_HEADER, decode_client_name
from fxcell.commands import COMMANDS, Command
from fxcell.daemon import models
from fxcell.daemon.control import LEASE_HEADER
from fxcell.daemon.encoding import error_info, jsonable
from fxcell.daemon.guard import RequestGuard, same_origin
from fxcell.daemon.jobs import JOB_COMMANDS
from fxcell.daemon.service import CellService
from fxcell.daemon.stream import PING_PERIOD, parse_rate, parse_topics
from fxcell.errors import FxcellError, NotAuthorizedError, RemoteError
from fxcell.events import COMMAND_ORIGIN

CLIENT_KEY = CLIENT_HEADER.lower().encode()
STATIC = resources.files("fxcell.daemon") / "static"


def _validation_message(exc: RequestValidationError) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err.get("loc", ()) if p != "body") or "body"
        parts.append(f"{loc}: {err.get('msg', 'invalid')}")
    return "invalid request: " + "; ".join(parts)


def _unparsable(cause: BaseException | None) -> str:
    """Why a request body could not be decoded (FastAPI's parse error names no cause)."""
    if isinstance(cause, UnicodeDecodeError):
        return f"the body is not UTF-8 (byte 0x{cause.object[cause.start]:02x} at {cause.start})"
    if isinstance(cause, RecursionError):
        return "the body is nested too deeply"
    if isinstance(cause, ValueError) and "digits" in str(cause):
        return "a number in the body has too many digits"
    return "the body is not valid JSON"


def _error_body(kind: str, message: str, status: int) -> dict[str, Any]:
    return {"error": {"type": kind, "message": message, "status": status, "detail": {}}}


def _arguments(body: Any) -> dict[str, Any]:
    """A request body's arguments (those left out take the command's defaults)."""
    return {} if body is None else dict(body.model_dump(exclude_none=True))


def create_app(service: CellService) -> FastAPI:
    """The FastAPI application serving ``service`` (API, stream and the operator page)."""
    app = FastAPI(
        title="fxcell daemon",
        version=__version__,
        description=(
            "Network API of the fxcell cell daemon. Commands that change the robot need "
            "`Authorization: Bearer <token>` and control of the cell; name your client with "
            f"the `{CLIENT_HEADER}` header."
        ),
        openapi_url="/api/openapi.json",
        docs_url="/api/docs",
        redoc_url=None,
    )
    app.state.service = service
    daemon = service.config.daemon
    app.add_middleware(
        RequestGuard,
        authorized=service.authorized,
        max_body=daemon.max_body_size,
        allowed_hosts=(daemon.host, *daemon.allowed_hosts),
    )

    @app.exception_handler(FxcellError)
    async def _fxcell_error(request: Request, exc: FxcellError) -> JSONResponse:
        info = error_info(exc)
        headers = {"WWW-Authenticate": "Bearer"} if info["status"] == 401 else None
        return JSONResponse({"error": info}, status_code=info["status"], headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        message = _validation_message(exc)
        return JSONResponse(_error_body("InvalidArgumentError", message, 422), status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _framework(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        # The framework's own refusals, in the same typed form as every other error.
        if exc.status_code == 400:  # a body FastAPI could not decode (bad UTF-8, ...)
            message = "invalid request: " + _unparsable(exc.__cause__)
            return JSONResponse(_error_body("InvalidArgumentError", message, 422), status_code=422)
        if exc.status_code == 404:
            message = f"no such path: {request.method} {request.url.path}"
        elif exc.status_code == 405:
            message = f"{request.url.path} does not take {request.method}"
        else:
            message = str(exc.detail)
        return JSONResponse(
            _error_body("RemoteError", message, exc.status_code),
            status_code=exc.status_code,
            headers=exc.headers,
        )

    @app.exception_handler(Exception)
    async def _bug(request: Request, exc: Exception) -> JSONResponse:
        info = error_info(exc)  # a bug: typed too, with the exception named
        return JSONResponse({"error": info}, status_code=500)

    def client_of(request: Request) -> str:
        # From the raw bytes: Starlette reads header values as Latin-1, which garbles UTF-8.
        raw = next((v for k, v in request.scope["headers"] if k.lower() == CLIENT_KEY), b"")
        name = decode_client_name(raw)
        if name:
            return name[:200]
        host = request.client.host if request.client else "unknown"
        return f"anonymous@{host}"

    def authorize(request: Request) -> str:
        if not service.authorized(request.headers.get("Authorization")):
            raise NotAuthorizedError(
                "this command changes the robot: send 'Authorization: Bearer <token>' "
                "(the token is in the daemon's token file, or FXCELL_TOKEN)",
                status=401,
            )
        return client_of(request)

    api = APIRouter(prefix="/api")
    op_responses: dict[int | str, dict[str, Any]] = {
        401: {"model": models.ErrorResponse},
        409: {"model": models.ErrorResponse},
        422: {"model": models.ErrorResponse},
        503: {"model": models.ErrorResponse},
    }

    async def respond(
        request: Request,
        name: str,
        args: dict[str, Any],
        call: Callable[[], Awaitable[Any]],
        *,
        wait: bool,
        needs_control: bool = True,
    ) -> JSONResponse:
        client = authorize(request)
        lease = None
        if needs_control:  # refuse a second client before anything else
            lease = service.control.acquire(client, request.headers.get(LEASE_HEADER)).lease
        headers = {LEASE_HEADER: lease} if lease else None
        try:
            # Everything knowable before the operation exists is the answer (409/422),
            # whatever ``wait`` is: arguments, guard, Local control, factors, reach.
            await service.check(name, args, client)
            op = service.start_operation(name, args, client, call, lease=lease)
        except FxcellError as exc:  # refused: the client still learns its lease
            info = error_info(exc)
            return JSONResponse({"error": info}, status_code=info["status"], headers=headers)
        if not wait:
            return JSONResponse(op.describe(), status_code=202, headers=headers)
        # The operation is its own task: a client that hangs up does not cancel it.
        await asyncio.shield(op.done.wait())
        return _finished(op, headers)

    def _finished(op: Any, headers: dict[str, str] | None = None) -> JSONResponse:
        """An ended operation: its record, or its error with the error's status (a move
        that did not reach its goal is never a 200)."""
        if op.error is not None:
            return JSONResponse(
                {"error": op.error, "operation": op.describe()},
                status_code=op.error["status"],
                headers=headers,
            )
        return JSONResponse(op.describe(), headers=headers)

    # ------------------------------------------------------------- state and info

    @api.get("/state", summary="Snapshot of the cell (no robot round trip)")
    async def get_state() -> Response:
        # Serialised directly: this is the hot path of pollers (see bench/api.py).
        return Response(json.dumps(service.snapshot()), media_type="application/json")

    @api.get("/info", summary="Daemon version, robot and configuration")
    async def get_info() -> dict[str, Any]:
        return service.info()

    @api.get(
        "/robot/model",
        summary="The arm's kinematic chain as the page draws it (m, rad)",
        description=(
            "The configured robot kind's joints from the base to the tool frame: each an "
            "origin (4x4, row-major, in the previous joint's frame) and an axis; then the tool "
            "frame's transform from the last joint (the TCP, `tcp` of /api/info, is on it)."
        ),
    )
    async def get_robot_model() -> dict[str, object]:
        return service.arm_model()

    @api.get("/statechart", summary="The robot-mode state machine as data")
    async def get_statechart() -> dict[str, Any]:
        return service.statechart_data()

    # ------------------------------------------------------------- the command table
    # One route per entry of fxcell.commands.COMMANDS: queries GET, the rest POST with
    # the request model derived from the entry (no body needed when no field is).

    def add_query(command: Command) -> None:
        name = command.name

        async def query() -> dict[str, Any]:
            return {"result": jsonable(await service.query(name))}

        api.add_api_route(
            f"/cell/{name}",
            query,
            methods=["GET"],
            summary=command.summary,
            description=command.doc,
            name=name,
            responses={409: {"model": models.ErrorResponse}, 503: {"model": models.ErrorResponse}},
        )

    def add_command(command: Command) -> None:
        name = command.name
        model = models.REQUEST_MODELS[name]
        move = command.kind == "move"
        wait_doc = "answer when the move has ended" if move else "answer when done"

        if model is None:

            async def run(
                request: Request, wait: bool = Query(not move, description=wait_doc)
            ) -> JSONResponse:
                return await respond(
                    request,
                    name,
                    {},
                    lambda: service.call(name),
                    wait=wait,
                    needs_control=command.needs_control,
                )

        else:
            # A body is needed only when some argument is (go_home takes none).
            required = any(arg.required for arg in command.args)
            body_type = model if required else model | None
            body_param = Body(...) if required else Body(None)

            async def run(  # type: ignore[misc]
                request: Request,
                body: body_type = body_param,  # type: ignore[valid-type]
                wait: bool = Query(not move, description=wait_doc),
            ) -> JSONResponse:
                args = _arguments(body)
                return await respond(
                    request,
                    name,
                    args,
                    lambda: service.call(name, **args),
                    wait=wait,
                    needs_control=command.needs_control,
                )

        needs = "the token" + (" and control" if command.needs_control else ", not control")
        api.add_api_route(
            f"/cell/{name}",
            run,
            methods=["POST"],
            summary=command.summary + (" Runs as an operation (202)." if move else ""),
            description=f"{command.doc}\n\nNeeds {needs}.",
            name=name,
            status_code=202 if move else 200,
            responses=op_responses,
            response_model=models.OperationModel,
        )

    for command in COMMANDS.values():
        if command.kind == "query":
            add_query(command)
        else:
            add_command(command)

    # ------------------------------------------------------------- the job

    @api.get("/job", summary="The fusion-machine job: state, progress, samples, questions")
    async def job_status() -> dict[str, Any]:
        return service.jobs.status()

    optional_body = Body(None)

    def add_job_command(name: str) -> None:
        async def run(
            request: Request, body: dict[str, Any] | None = optional_body
        ) -> JSONResponse:
            client = authorize(request)
            lease = service.control.acquire(client, request.headers.get(LEASE_HEADER)).lease
            token = COMMAND_ORIGIN.set(client)
            try:
                status = await service.jobs.command(name, body or {})
            finally:
                COMMAND_ORIGIN.reset(token)
            return JSONResponse(jsonable(status), headers={LEASE_HEADER: lease})

        api.add_api_route(
            f"/job/{name}",
            run,
            methods=["POST"],
            summary=f"Job {name} (needs the token and control); answers with the job's status",
            name=f"job_{name}",
            responses=op_responses,
        )

    for job_command in JOB_COMMANDS:
        add_job_command(job_command)

    # ------------------------------------------------------------- the camera

    jpeg: dict[int | str, dict[str, Any]] = {200: {"content": {"image/jpeg": {}}}}

    @api.get(
        "/job/placement/{check_id}.jpg",
        summary="The annotated image of a placement check the job made (its job database)",
        response_class=Response,
        responses=jpeg,
    )
    async def job_placement_image(check_id: int) -> Response:
        job = await service.jobs.require()
        try:
            data = await asyncio.to_thread(job.store.placement_image, check_id)
        except FxcellError as exc:
            raise RemoteError(str(exc), status=404) from None
        return Response(data, media_type="image/jpeg", headers={"Cache-Control": "no-store"})

    @api.get(
        "/camera/placement.jpg",
        summary="The annotated image of the cell's last placement check",
        response_class=Response,
        responses=jpeg,
    )
    async def camera_placement_image() -> Response:
        cell = service.cell
        last = None if cell is None else cell.camera.last
        if last is None:
            raise RemoteError("no placement check yet: run check_placement", status=404)
        return Response(last.image, media_type="image/jpeg", headers={"Cache-Control": "no-store"})

    @api.get("/cell/state", summary="The state machine's current state")
    async def cell_state() -> dict[str, Any]:
        return {"result": service.machine_state()}

    @api.get("/commands", summary="The command table: arguments, units, guards, results")
    async def get_commands() -> dict[str, Any]:
        return service.commands_data()

    # ------------------------------------------------------------- operations

    @api.get("/operations", summary="Running and recent operations")
    async def list_operations(running: bool = False) -> list[dict[str, Any]]:
        return [op.describe() for op in service.operations.all(running_only=running)]

    def find(op_id: str) -> Any:
        op = service.operations.get(op_id)
        if op is None:
            raise RemoteError(f"no operation {op_id!r}", status=404)
        return op

    @api.get("/operations/{op_id}", response_model=models.OperationModel)
    async def get_operation(op_id: str) -> dict[str, Any]:
        return find(op_id).describe()  # type: ignore[no-any-return]

    @api.post(
        "/operations/{op_id}/wait",
        summary="Wait until the operation ends (at most timeout s)",
        response_model=models.OperationModel,
    )
    async def wait_operation(
        op_id: str, within: float = Query(30.0, gt=0, le=3600, alias="timeout")
    ) -> Response:
        op = find(op_id)
        await asyncio.shield(service.operations.wait(op, within))
        if op.done.is_set():
            return _finished(op)
        return JSONResponse(op.describe())

    @api.post(
        "/operations/{op_id}/cancel",
        summary="Cancel the operation (a move brakes to a stop)",
        response_model=models.OperationModel,
        responses=op_responses,
    )
    async def cancel_operation(request: Request, op_id: str) -> dict[str, Any]:
        authorize(request)
        op = find(op_id)
        await asyncio.shield(service.cancel_operation(op))
        return op.describe()  # type: ignore[no-any-return]

    # ------------------------------------------------------------- control

    @api.get("/control", summary="Who controls the cell (null: nobody)")
    async def get_control() -> dict[str, Any] | None:
        return service.control.describe()

    @api.post("/control", summary="Take control (force: take over)", responses=op_responses)
    async def take_control(
        request: Request, body: models.ControlRequest | None = None
    ) -> dict[str, Any] | None:
        client = authorize(request)
        holder = service.control.acquire(
            client, request.headers.get(LEASE_HEADER), force=body.force if body else False
        )
        return {"client": holder.client, "since": holder.since, "lease": holder.lease}

    @api.delete("/control", summary="Release control", responses=op_responses)
    async def release_control(request: Request) -> dict[str, Any]:
        authorize(request)
        return {"released": service.control.release(request.headers.get(LEASE_HEADER))}

    # ------------------------------------------------------------- stream

    @api.websocket("/stream")
    async def stream(websocket: WebSocket) -> None:
        params = websocket.query_params
        origin = websocket.headers.get("origin")
        if origin and not same_origin(origin, websocket.url.scheme, websocket.headers.get("host")):
            # Browsers send Origin: another site's page (or the same host and port under
            # another scheme) must not watch the robot.
            await websocket.close(code=1008, reason="cross-origin stream refused")
            return
        try:
            rate = parse_rate(params.get("rate"))
            topics = parse_topics(params.get("topics"))
        except ValueError as exc:
            await websocket.close(code=1008, reason=str(exc)[:120])
            return
        await websocket.accept()
        watcher = service.hub.add(topics, rate, params.get("client"), params.get("lease"))
        await websocket.send_text(json.dumps({"type": "hello", "snapshot": service.snapshot()}))

        async def receive() -> None:
            while True:
                text = await websocket.receive_text()
                # a client's malformed message is ignored (too deep or huge numbers too)
                with contextlib.suppress(
                    ValueError, TypeError, KeyError, AttributeError, RecursionError, OverflowError
                ):
                    message = json.loads(text)
                    if message.get("type") == "pong":
                        watcher.last_pong = time.monotonic()
                    elif "rate" in message:
                        watcher.set_rate(parse_rate(message["rate"]))

        async def ping() -> None:
            while True:  # a frozen client stops answering: it keeps no lease alive
                await asyncio.sleep(PING_PERIOD)
                watcher.offer_control(json.dumps({"type": "ping", "t": time.time()}))

        async def send() -> None:
            while True:
                for text in await watcher.next_batch():
                    await websocket.send_text(text)
                if watcher.overflowed:
                    await websocket.close(code=1011, reason="watcher too slow: backlog overflow")
                    return

        tasks = [asyncio.create_task(f()) for f in (receive, send, ping)]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            service.hub.remove(watcher)
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, Exception):
                    await task

    app.include_router(api)

    # ------------------------------------------------------------- operator page

    @app.get("/", include_in_schema=False)
    async def index() -> Response:
        return FileResponse(str(STATIC / "index.html"), headers={"Cache-Control": "no-cache"})

    app.mount("/static", StaticFiles(directory=str(STATIC)), name="static")
    return app
