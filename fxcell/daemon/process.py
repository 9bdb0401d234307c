"""Starting a daemon as a child process and waiting until it serves (tests, benchmarks).

``with DaemonProcess.start(config_path, token=...) as daemon: daemon.url`` runs
``python -m fxcell daemon`` on a free loopback port (``--port 0``: the daemon binds it and
prints its address, so no other socket can take it in between) and stops it (SIGTERM) on
exit.
"""

from __future__ import annotations

import contextlib
import os
import queue
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import ClassVar

from fxcell.errors import FxcellError

_SERVING = re.compile(r"serving (http://\S+?)/?$")


_SERVER_PORTS = range(15000, 25000)
"""Where :func:`free_port` looks first: below Linux's ephemeral range (32768-60999 unless
configured), away from the UR ports (29999-30004) and fxcell's defaults."""
_given: set[int] = set()


def free_port(host: str = "127.0.0.1") -> int:
    """A port free now on ``host``, for a server that cannot take port 0 itself.

    Another socket may still take it before that server binds it; one below the kernel's
    ephemeral range (:data:`_SERVER_PORTS`, unless that range reaches down there) can only
    be taken by a server binding it explicitly, not by any outgoing connection, so that is
    where it is looked for first. A port this process was given before is not given again."""
    lowest_ephemeral = 32768
    with contextlib.suppress(OSError, ValueError):
        text = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text()
        lowest_ephemeral = int(text.split()[0])
    candidates = [p for p in _SERVER_PORTS if p < lowest_ephemeral and p not in _given]
    for port in [*random.sample(candidates, min(len(candidates), 64)), 0]:  # 0: any port
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            try:
                sock.bind((host, port))
            except OSError:
                continue
            port = int(sock.getsockname()[1])
        _given.add(port)
        return port
    raise OSError(f"no free port on {host}")


def _die_with_parent() -> None:
    """In the child: get SIGTERM when the parent dies (Linux), so no daemon is orphaned."""
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class DaemonProcess:
    """A running ``fxcell daemon`` child process."""

    observers: ClassVar[list[Callable[[DaemonProcess], None]]] = []
    """Called with every daemon once it serves (``fxcell.testing`` watches their logs)."""

    def __init__(self, proc: subprocess.Popen[str], url: str, token: str) -> None:
        self.proc = proc
        self.url = url
        self.token = token
        self.output: list[str] = []
        self._reader = threading.Thread()
        self._lines: queue.Queue[str | None] = queue.Queue()

    @classmethod
    def start(
        cls,
        config: str | Path,
        *,
        token: str,
        log_dir: str | Path | None = None,
        token_file: str | Path | None = None,
        extra_args: Sequence[str] = (),
        env: dict[str, str] | None = None,
        startup_timeout: float = 40.0,
    ) -> DaemonProcess:
        """Start a daemon on a free port; returns once it serves (or raises with its output)."""
        verbose = ["-v"] if {**os.environ, **(env or {})}.get("FXCELL_DAEMON_VERBOSE") else []
        args = [sys.executable, "-m", "fxcell", *verbose, "daemon", "--config", str(config)]
        args += ["--port", "0"]
        args += ["--log-dir", str(log_dir)] if log_dir else ["--no-record"]
        args += list(extra_args)
        environ = {**os.environ, **(env or {}), "FXCELL_TOKEN": token, "PYTHONUNBUFFERED": "1"}
        proc = subprocess.Popen(
            args,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=environ,
            start_new_session=True,
            preexec_fn=_die_with_parent,
        )
        daemon = cls(proc, "", token)
        daemon._drain()
        deadline = time.monotonic() + startup_timeout
        try:
            while time.monotonic() < deadline:
                try:
                    line = daemon._lines.get(timeout=0.2)
                except queue.Empty:
                    if proc.poll() is not None and not daemon._reader.is_alive():
                        break
                    continue
                if line is None:  # end of output: the daemon exited
                    break
                match = _SERVING.search(line.strip())
                if match:
                    daemon.url = match.group(1)
                    for observer in tuple(DaemonProcess.observers):
                        observer(daemon)
                    return daemon
        except BaseException:  # e.g. a test timeout: leave no daemon behind
            daemon.stop(signal.SIGKILL, timeout=5)
            raise
        lines = daemon.output
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(5)
        daemon._reader.join(5)
        if proc.stdout is not None:
            proc.stdout.close()
        raise FxcellError("the daemon did not start:\n" + "\n".join(lines[-40:]))

    def wait_connected(self, within: float = 60.0) -> dict[str, object]:
        """Wait until the daemon's Cell is connected; returns the state snapshot."""
        import httpx

        deadline = time.monotonic() + within
        while True:
            snapshot: dict[str, object] = httpx.get(f"{self.url}/api/state", timeout=5).json()
            if snapshot["connected"] and snapshot["state"] != "disconnected":
                return snapshot
            if self.proc.poll() is not None or time.monotonic() > deadline:
                tail = "\n".join(self.output[-30:])
                raise FxcellError(f"the daemon's cell did not connect: {snapshot}\n{tail}")
            time.sleep(0.05)

    def _drain(self) -> None:
        """Keep reading the daemon's output so that a full pipe never blocks it."""
        stdout = self.proc.stdout
        assert stdout is not None

        def pump() -> None:
            with contextlib.suppress(ValueError, OSError):
                for line in stdout:
                    self.output.append(line.rstrip())
                    self._lines.put(line.rstrip())
            self._lines.put(None)

        self._reader = threading.Thread(target=pump, name="fxcell daemon output", daemon=True)
        self._reader.start()

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int:
        """Signal the daemon and wait for its exit code (killed if it overstays)."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        if self._reader.ident is not None:
            self._reader.join(5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return self.proc.returncode

    def __enter__(self) -> DaemonProcess:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
