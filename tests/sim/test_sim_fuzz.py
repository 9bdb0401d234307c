"""Whatever a client sends, the simulator answers it or closes the connection cleanly, and
never logs an unhandled exception: Hypothesis over the RTDE and Dashboard request grammars.

The simulator runs in this process (its own event loop in a thread, as in its process), so
an exception escaping a socket callback reaches the loop's exception handler here.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import struct
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fxcell.link.embedded import free_loopback_host
from fxcell.sim.rtde import INPUTS, OUTPUTS
from fxcell.sim.server import SimServer, new_event_loop

pytestmark = pytest.mark.timeout(300)

REPLY_TIMEOUT = 3.0  # s: a request not answered by then is a hang


@dataclass
class Trouble:
    """What the simulator's loop and loggers reported that they should not have."""

    loop_errors: list[dict[str, Any]] = field(default_factory=list)
    records: list[logging.LogRecord] = field(default_factory=list)


class _Catch(logging.Handler):
    def __init__(self, trouble: Trouble) -> None:
        super().__init__(logging.DEBUG)
        self.trouble = trouble

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info or (record.name == "asyncio" and record.levelno >= logging.ERROR):
            self.trouble.records.append(record)


@dataclass
class InProcessSimulator:
    host: str
    server: SimServer
    trouble: Trouble


@dataclass
class _Started:
    host: str
    server: SimServer
    loop: asyncio.AbstractEventLoop
    thread: threading.Thread
    error: OSError | None = None


def _start(host: str, programs: Path, trouble: Trouble) -> _Started:
    """A simulator serving on ``host`` from its own loop in a thread, once it listens."""
    server = SimServer(host, time_scale=0.05, programs=programs)
    loop = new_event_loop()
    loop.set_exception_handler(lambda _loop, context: trouble.loop_errors.append(context))
    listening = threading.Event()
    started = _Started(host, server, loop, threading.Thread(target=lambda: None))

    def run() -> None:
        try:
            loop.run_until_complete(
                server.serve(announce=False, handle_signals=False, on_listening=listening.set)
            )
        except OSError as exc:  # the address was taken meanwhile
            started.error = exc
            listening.set()
        finally:
            loop.close()

    started.thread = threading.Thread(target=run, name="in-process-simulator", daemon=True)
    started.thread.start()
    assert listening.wait(30)
    if started.error is not None:
        started.thread.join(10)
    return started


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InProcessSimulator]:
    # a program store without external_control.urp: playing it would make the simulator
    # ask the machine-wide port 50002 (another test's ExternalControl server) for a program
    programs = tmp_path_factory.mktemp("programs")
    (programs / "fxcell.urp").write_text("<URProgram/>")
    trouble = Trouble()
    for _ in range(5):  # another simulator may take the free address first
        started = _start(free_loopback_host(), programs, trouble)
        if started.error is None:
            break
    else:
        pytest.fail(f"the in-process simulator found no free address: {started.error}")
    handler = _Catch(trouble)
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield InProcessSimulator(started.host, started.server, trouble)
    finally:
        started.loop.call_soon_threadsafe(started.server.request_stop)
        started.thread.join(10)
        root.removeHandler(handler)


def no_trouble(sim: InProcessSimulator) -> None:
    t = sim.trouble
    assert not t.loop_errors, t.loop_errors
    assert not t.records, [r.getMessage() for r in t.records]


# ------------------------------------------------------------------ RTDE


class RTDEClient:
    def __init__(self, host: str) -> None:
        self.sock = socket.create_connection((host, 30004), timeout=REPLY_TIMEOUT)
        self.buf = b""
        self.closed = False

    def send(self, data: bytes) -> None:
        try:
            self.sock.sendall(data)
        except (BrokenPipeError, ConnectionResetError):
            self.closed = True

    def reply(self, kind: int) -> bytes | None:
        """The next packet of ``kind`` (others, like streamed data, skipped); None if the
        server closed the connection. A timeout (no answer) raises."""
        while True:
            while len(self.buf) >= 3:
                size, k = struct.unpack_from(">HB", self.buf)
                assert size >= 3, self.buf[:8]
                if len(self.buf) < size:
                    break
                payload, self.buf = self.buf[3:size], self.buf[size:]
                if k == kind:
                    return payload
            try:
                chunk = self.sock.recv(65536)
            except ConnectionResetError:
                chunk = b""
            if not chunk:
                self.closed = True
                return None
            self.buf += chunk

    def close(self) -> None:
        self.sock.close()


def packet(kind: int, payload: bytes) -> bytes:
    return struct.pack(">HB", len(payload) + 3, kind) + payload


names = st.one_of(
    st.sampled_from(sorted(OUTPUTS)),
    st.sampled_from(sorted(INPUTS)),
    st.text(max_size=30).filter(lambda s: "," not in s),
)
name_lists = st.lists(names, max_size=40).map(lambda ns: ",".join(ns).encode("utf-8"))
frequencies = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([125.0, 500.0])
ANSWERED = {ord(c) for c in "VvOISP"}  # requests the controller answers with their own type

rtde_requests = st.one_of(
    st.tuples(st.just(ord("V")), st.integers(0, 65535).map(lambda v: struct.pack(">H", v))),
    st.tuples(st.just(ord("v")), st.just(b"")),
    st.tuples(
        st.just(ord("O")),
        st.tuples(frequencies, name_lists).map(lambda t: struct.pack(">d", t[0]) + t[1]),
    ),
    st.tuples(st.just(ord("O")), st.binary(max_size=12)),  # short or odd payloads
    st.tuples(st.just(ord("I")), name_lists),
    st.tuples(st.just(ord("S")), st.just(b"")),
    st.tuples(st.just(ord("P")), st.just(b"")),
    st.tuples(st.just(ord("U")), st.binary(max_size=300)),
    st.tuples(st.sampled_from([ord(c) for c in "VvOISPUM"]), st.binary(max_size=64)),
    st.tuples(st.integers(0, 255), st.binary(max_size=64)),
    st.tuples(st.just(ord("O")), st.binary(min_size=2000, max_size=2200)),  # over the limit
)


@settings(
    max_examples=120,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    requests=st.lists(rtde_requests, min_size=1, max_size=12),
    bad_header=st.booleans(),
)
def test_rtde_answers_every_request_or_closes_and_raises_nothing(
    simulated: InProcessSimulator, requests: list[tuple[int, bytes]], bad_header: bool
) -> None:
    c = RTDEClient(simulated.host)
    try:
        for kind, payload in requests:
            if len(payload) + 3 > 65535:
                continue
            c.send(packet(kind, payload))
            if c.closed:
                break
            if kind in ANSWERED and c.reply(kind) is None:
                break  # closed: allowed, but then nothing more is read
        if bad_header and not c.closed:
            c.send(struct.pack(">HB", 2, ord("V")))  # a size below the header's own
            assert c.reply(0xFFFF) is None  # the server closes the connection
    finally:
        c.close()
    no_trouble(simulated)


# ------------------------------------------------------------------ Dashboard

COMMANDS = [
    "power on",
    "power off",
    "brake release",
    "play",
    "stop",
    "pause",
    "unlock protective stop",
    "close safety popup",
    "close popup",
    "robotmode",
    "safetymode",
    "safetystatus",
    "programState",
    "running",
    "get loaded program",
    "isProgramSaved",
    "PolyscopeVersion",
    "version",
    "get serial number",
    "get robot model",
    "is in remote control",
    "get operational mode",
    "clear operational mode",
    "saveLog",
    "restart safety",
    "load",
    "load installation",
    "popup",
    "addToLog",
    "set operational mode",
    "generate support file",
]
line_text = st.text(
    alphabet=st.characters(exclude_characters="\n", exclude_categories=("Cs",)),
    max_size=80,
)
dashboard_lines = st.one_of(
    st.sampled_from(COMMANDS),
    st.tuples(st.sampled_from(COMMANDS), line_text).map(lambda t: f"{t[0]} {t[1]}"),
    st.tuples(st.sampled_from(["load ", "load installation "]), line_text).map("".join),
    st.sampled_from(["load /programs/../../etc/passwd", "load " + "x" * 5000 + ".urp"]),
    line_text,
)


def blank(line: bytes) -> bool:
    """A line the server skips (as it reads lines)."""
    return not line.decode("utf-8", "replace").rstrip("\r").strip()


@settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(lines=st.lists(dashboard_lines, min_size=1, max_size=10), quit_at_end=st.booleans())
def test_dashboard_answers_every_line_with_one_line_and_raises_nothing(
    simulated: InProcessSimulator, lines: list[str], quit_at_end: bool
) -> None:
    sock = socket.create_connection((simulated.host, 29999), timeout=REPLY_TIMEOUT)
    f = sock.makefile("rwb")
    try:
        assert f.readline() == b"Connected: Universal Robots Dashboard Server\n"
        for text in [*lines, *(["quit"] if quit_at_end else [])]:
            raw = text.encode("utf-8", "surrogateescape")
            f.write(raw + b"\n")
            f.flush()
            if blank(raw):
                continue
            reply = f.readline()
            assert reply.endswith(b"\n"), (text, reply)
            assert reply.strip(), text
            if text.strip().lower() == "quit":
                assert reply == b"Disconnected\n"
                assert f.readline() == b""  # then the server closes
                break
    finally:
        f.close()
        sock.close()
    no_trouble(simulated)
