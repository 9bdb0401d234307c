"""Running the daemon: the Cell under supervision, the HTTP server, signals and systemd.

:func:`serve` runs until SIGTERM or SIGINT. Then it cancels every operation (a move
brakes to a stop), closes the Cell (which finishes the MCAP file and stops the
embedded simulator) and stops the HTTP server, all within :data:`SHUTDOWN_BUDGET`
seconds, and returns 0. The Cell is (re)opened with backoff whenever opening it
fails or it dies; the HTTP API keeps serving meanwhile (state ``disconnected``).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import faulthandler
import ipaddress
import logging
import os
import platform
import signal
import socket
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import uvicorn

from fxcell.config import CellConfig
from fxcell.daemon.app import create_app
from fxcell.daemon.auth import MIN_REMOTE_TOKEN_LENGTH, load_or_create_token
from fxcell.daemon.connection import guarded_protocol
from fxcell.daemon.notify import Notifier
from fxcell.daemon.service import CellService
from fxcell.errors import ConfigError, FxcellError

log = logging.getLogger(__name__)

SHUTDOWN_BUDGET = 2.5  # s; the issue allows 3 s from the signal to the exit
HARD_EXIT_AFTER = 2.9  # s after the signal: exit(1) without cleanup if still running
BACKOFF_START = 0.5


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_bind(host: str, allow_remote: bool, token: str) -> None:
    """Refuse a non-loopback address unless allowed explicitly (and the token is strong)."""
    if is_loopback(host):
        return
    if not allow_remote:
        raise ConfigError(
            f"daemon.host: {host} is not a loopback address; binding to it exposes the robot "
            "to the network: pass --allow-remote (daemon.allow_remote: true) to do it"
        )
    if len(token) < MIN_REMOTE_TOKEN_LENGTH:
        raise ConfigError(
            f"daemon.host: a non-loopback address needs a token of at least "
            f"{MIN_REMOTE_TOKEN_LENGTH} characters"
        )


class _Server(uvicorn.Server):
    """uvicorn without its own signal handling: the daemon owns SIGTERM/SIGINT."""

    @contextlib.contextmanager
    def capture_signals(self) -> Any:
        yield


class Daemon:
    """The daemon's parts and their life cycle (use :func:`serve` to run one)."""

    def __init__(
        self,
        config: CellConfig,
        *,
        record: Path | None,
        simulator_options: Mapping[str, Any] | None = None,
    ) -> None:
        self.config = config
        self.record = record
        self.simulator_options = dict(simulator_options or {})
        self.token = load_or_create_token(config.daemon.token_file)
        check_bind(config.daemon.host, config.daemon.allow_remote, self.token)
        self.service = CellService(config, self.token)
        self.app = create_app(self.service)
        self.notifier = Notifier()
        self.stopping = asyncio.Event()
        self._url: str | None = None
        self._ready_how: str | None = None
        self._ready_sent = False
        self._cell: Any = None
        self.sila: Any = None
        """The SiLA 2 server (daemon.sila.enabled), a fxcell.daemon.sila.server.SilaCellServer."""

    async def _start_sila(self) -> None:
        from fxcell.daemon.sila.server import SilaCellServer

        sila = SilaCellServer(self.service, self.config, self.token)
        await sila.start()
        self.sila = sila
        how = "plain gRPC, daemon.sila.insecure" if self.config.daemon.sila.insecure else "TLS"
        identity = sila.identity
        print(
            f"fxcell daemon: SiLA 2 server {self.config.daemon.sila.server_name!r} on "
            f"{sila.address} ({how}; server UUID {identity.server_uuid if identity else '?'}; "
            f"certificate SHA-256 {identity.fingerprint if identity else '?'})",
            flush=True,
        )

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self._on_signal, sig)
        daemon = self.config.daemon
        server = _Server(
            uvicorn.Config(
                self.app,
                host=daemon.host,
                port=daemon.port,
                log_level="warning",
                lifespan="off",
                ws="websockets-sansio",
                ws_ping_interval=None,
                timeout_graceful_shutdown=1,
                # half-open connections are closed (fxcell.daemon.connection)
                http=guarded_protocol(daemon.header_timeout, daemon.body_timeout),
                timeout_keep_alive=daemon.idle_timeout,
            )
        )
        sock = self._bind()
        server_task = asyncio.create_task(server.serve(sockets=[sock]), name="fxcell http")
        supervisor = asyncio.create_task(self._supervise(), name="fxcell cell supervisor")
        watchdog = asyncio.create_task(self._watchdog(), name="fxcell watchdog")
        try:
            while not server.started:
                if server_task.done():
                    server_task.result()
                    raise FxcellError("the HTTP server stopped while starting")
                await asyncio.sleep(0.01)
            if self.config.daemon.sila.enabled:
                await self._start_sila()
            url = f"http://{self.config.daemon.host}:{sock.getsockname()[1]}/"
            log.info("fxcell daemon serving %s (robot: %s)", url, self.service.robot_description)
            print(f"fxcell daemon: serving {url}", flush=True)
            where = (
                "$FXCELL_TOKEN"
                if os.environ.get("FXCELL_TOKEN")
                else str(self.config.daemon.token_file)
            )
            print(
                f"fxcell daemon: bearer token in {where}; "
                "'fxcell token --page-url' prints the page address that logs in",
                flush=True,
            )
            self._url = url
            if self._ready_how is not None:
                self._announce_ready(self._ready_how)
            await self.stopping.wait()
        finally:
            deadline = time.monotonic() + SHUTDOWN_BUDGET
            self.notifier.stopping()
            sila, self.sila = self.sila, None
            if sila is not None:  # no new SiLA calls; running ones end (runs stay resumable)
                await sila.stop(within=0.5)
            await self._shutdown(deadline)
            server.should_exit = True
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                async with asyncio.timeout(max(0.1, deadline - time.monotonic())):
                    await asyncio.shield(server_task)
            server.force_exit = True
            for task in (supervisor, watchdog, server_task):
                task.cancel()
            await asyncio.gather(supervisor, watchdog, server_task, return_exceptions=True)
            sock.close()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)
        return 0

    def _bind(self) -> socket.socket:
        host, port = self.config.daemon.host, self.config.daemon.port
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        # Accepted connections inherit it: without it Nagle + delayed ACKs add ~40 ms to
        # every response that uvicorn writes in two parts (headers, body).
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            sock.close()
            raise ConfigError(f"daemon: cannot listen on {host}:{port}: {exc.strerror}") from None
        sock.listen(128)
        sock.setblocking(False)
        return sock

    def _on_signal(self, sig: int) -> None:
        log.info("received %s: stopping", signal.Signals(sig).name)
        if not self.stopping.is_set():
            # Last resort if some part will not finish: never overstay the 3 s promise.
            timer = threading.Timer(HARD_EXIT_AFTER, _hard_exit)
            timer.daemon = True
            timer.start()
        self.stopping.set()

    async def _shutdown(self, deadline: float) -> None:
        """Stop motion, then close the Cell (finishing the MCAP file)."""
        t0 = time.monotonic()
        with contextlib.suppress(TimeoutError):  # the running step brakes; the run stays resumable
            async with asyncio.timeout(max(0.1, deadline - t0 - 1.0)):
                await self.service.jobs.detach()
        await self.service.operations.cancel_all(within=max(0.1, deadline - time.monotonic()))
        log.info("shutdown: operations ended after %.3f s", time.monotonic() - t0)
        cell, self._cell = self._cell, None
        self.service.detach("the daemon is stopping")
        if cell is not None:
            # asyncio.wait, not wait_for: a close() that shields itself from cancellation
            # must not hold the exit past the budget.
            closing = asyncio.ensure_future(cell.close())
            done, _ = await asyncio.wait({closing}, timeout=max(0.1, deadline - time.monotonic()))
            if not done:
                log.error("closing the cell took longer than the shutdown budget")
            elif (exc := closing.exception()) is not None:
                log.error("closing the cell failed: %r", exc)
            log.info("shutdown: cell closed after %.3f s", time.monotonic() - t0)

    async def _supervise(self) -> None:
        """Open the Cell, serve it, and reopen it with backoff when it fails or dies."""
        backoff = BACKOFF_START
        while not self.stopping.is_set():
            started = time.monotonic()
            try:
                cell = open_cell(self.config, self.record, self.simulator_options)
                self._cell = cell
                await cell.open()
                self.service.attach(cell)
                await self.service.jobs.attach(cell)
                self._announce_ready(f"cell connected: {self.service.robot_description}")
                self.notifier.status(f"cell open: {self.service.robot_description}")
                # The Cell reconnects its robot link itself; it is reopened only if
                # opening it fails (robot unreachable at start, simulator failed).
                await self.stopping.wait()
                return
            except Exception as exc:  # whatever failed, keep serving and retry
                log.error("cell: %s; reopening in %.1f s", exc, backoff)
                self.service.detach(str(exc))
                self._announce_ready(f"cell down: {exc}")
                self.notifier.status(f"cell down: {exc}")
                await self._discard_cell()
                if time.monotonic() - started > 30:
                    backoff = BACKOFF_START
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(backoff):
                        await self.stopping.wait()
                backoff = min(backoff * 2, self.config.robot.reconnect_backoff_max)

    def _announce_ready(self, how: str) -> None:
        """READY to systemd once the first attempt to open the cell has ended (so that
        commands sent after READY find the cell connected, or fail at once saying why)."""
        if self._ready_sent:
            return
        self._ready_how = how
        if self._url is None:
            return  # the HTTP server is not up yet: run() announces it then
        self._ready_sent = True
        log.info("fxcell daemon ready: %s", how)
        print(f"fxcell daemon: ready ({how})", flush=True)
        self.notifier.ready(f"serving {self._url}; {how}")

    async def _discard_cell(self) -> None:
        cell, self._cell = self._cell, None
        if cell is not None:
            with contextlib.suppress(FxcellError, TimeoutError):
                async with asyncio.timeout(2.0):
                    await cell.close()

    async def _watchdog(self) -> None:
        interval = self.notifier.watchdog_interval
        if interval is None:
            return
        while True:
            self.notifier.watchdog()
            await asyncio.sleep(interval)


def _hard_exit() -> None:
    log.critical("the daemon did not stop within %.1f s of the signal: exit 1", HARD_EXIT_AFTER)
    faulthandler.dump_traceback(all_threads=True)  # where it hung, for the log
    logging.shutdown()
    os._exit(1)


def open_cell(config: CellConfig, record: Path | None, simulator_options: Mapping[str, Any]) -> Any:
    """The daemon's Cell: commands it sends are recorded with origin ``daemon``."""
    from fxcell.cell import Cell
    from fxcell.events import Origin

    return Cell(
        config=config, record=record, origin=Origin.DAEMON, simulator_options=simulator_options
    )


MMAP_THRESHOLD = 128 * 1024
"""Bytes from which glibc's malloc maps each block of its own (glibc's initial value)."""


def fix_mmap_threshold() -> bool:
    """Keep glibc's malloc from letting the daemon's resident memory creep (True if set).

    glibc raises its mmap threshold each time a mapped block is freed, up to 32 MiB; after
    that the recorder's chunk-sized buffers (an MCAP chunk and its compressed copy, every
    second or so) come from the heap, which they fragment. An idle recording daemon grew
    1.8 MiB in 4.5 minutes that way, and 0.26 MiB with the threshold fixed (measured
    2026-11-25). A threshold set explicitly is never raised.
    """
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(-3, MMAP_THRESHOLD))  # -3: M_MMAP_THRESHOLD (malloc.h)


def serve(
    config: CellConfig,
    *,
    record: Path | None,
    simulator_options: Mapping[str, Any] | None = None,
) -> int:
    """Run the daemon until SIGTERM/SIGINT; the exit code (0 after a clean stop)."""
    fix_mmap_threshold()

    async def main() -> int:
        daemon = Daemon(config, record=record, simulator_options=simulator_options)
        return await daemon.run()

    return asyncio.run(main())
