"""The cell's beats to its link process (fxcell.link.beats): only while a trajectory runs and
the event loop has run lately, and, from the native thread, even while another thread holds
the GIL (the Python fallback cannot: that is why the native one exists)."""

from __future__ import annotations

import os
import select
import socket
import time
from collections.abc import Iterator

import pytest

from fxcell.link import beats
from fxcell.link.beats import LOOP_STALL_AFTER, Beats
from fxcell.link.realtime import probe

PERIOD = 0.005


@pytest.fixture(params=["native", "python"])
def kind(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    if request.param == "native":
        if not beats.NATIVE:
            if os.environ.get("FXCELL_REQUIRE_NATIVE") == "1":
                pytest.fail("fxcell.link._beat is not built (run ./dev, see hatch_build.py)")
            pytest.skip("fxcell.link._beat is not built here (./dev builds it)")
    else:
        monkeypatch.setattr(beats, "NATIVE", False)
    return str(request.param)


@pytest.fixture
def channel() -> Iterator[tuple[socket.socket, socket.socket]]:
    ours, link = socket.socketpair()
    with link:
        yield ours, link


def _arrives(link: socket.socket, within: float) -> bytes:
    """What arrives on the link's end within ``within`` seconds (b"" at end of file)."""
    ready, _, _ = select.select([link], [], [], within)
    if not ready:
        return b"-"  # nothing arrived
    return link.recv(4096)


def _drain(link: socket.socket) -> int:
    link.setblocking(False)
    try:
        count = 0
        while True:
            try:
                got = link.recv(4096)
            except BlockingIOError:
                return count
            if not got:
                return count
            count += len(got)
    finally:
        link.setblocking(True)


def _beating(
    channel: tuple[socket.socket, socket.socket], stall_after: float = LOOP_STALL_AFTER
) -> tuple[Beats, socket.socket]:
    """Beats on our end as while a trajectory runs, once the first has reached the link's
    end; the beats and the link's end."""
    ours, link = channel
    beater = Beats(ours, priority=0, period=PERIOD, stall_after=stall_after)
    beater.loop_ran()
    beater.set_running(True)
    assert _arrives(link, 5.0).startswith(b"b")
    return beater, link


def test_beats_come_only_while_a_trajectory_runs(
    kind: str, channel: tuple[socket.socket, socket.socket]
) -> None:
    ours, link = channel
    beater = Beats(ours, priority=0, period=PERIOD)
    try:
        assert beater.native == (kind == "native")
        assert _arrives(link, 10 * PERIOD) == b"-"
        beater.loop_ran()
        beater.set_running(True)
        assert _arrives(link, 5.0).startswith(b"b")
        _drain(link)
        beater.set_running(False)
        late = b""
        while (got := _arrives(link, 10 * PERIOD)) != b"-":
            late += got
        assert len(late) <= 1  # one beat decided before the change may still come
    finally:
        beater.close()


def test_beats_stop_while_the_event_loop_has_not_run_and_resume_once_it_has(
    kind: str, channel: tuple[socket.socket, socket.socket]
) -> None:
    beater, link = _beating(channel, stall_after=0.05)
    try:
        deadline = time.monotonic() + 10.0  # the loop "stalls" from here: no loop_ran
        while _arrives(link, 0.2) != b"-":  # until 0.2 s go by without a beat
            assert time.monotonic() < deadline, "the beats went on without the loop"
        beater.loop_ran()
        assert _arrives(link, 5.0).startswith(b"b")
    finally:
        beater.close()


def test_closing_ends_the_beats_and_closes_the_channel(
    kind: str, channel: tuple[socket.socket, socket.socket]
) -> None:
    beater, link = _beating(channel)
    beater.close()
    beater.close()  # idempotent
    link.settimeout(5.0)  # a channel left open times out here (TimeoutError)
    received = b""
    while chunk := link.recv(4096):  # the beats sent before, then end of file
        received += chunk
    assert set(received) <= set(b"b")


def _hold_the_gil(seconds: float) -> float:
    """Hold the GIL for about ``seconds`` in one C call (``sum`` over a range never lets
    another thread run); the time it was held."""
    start = time.perf_counter()
    sum(range(200_000))
    per_item = (time.perf_counter() - start) / 200_000
    items = min(int(seconds / per_item), 500_000_000)
    start = time.perf_counter()
    sum(range(items))
    return time.perf_counter() - start


def test_native_beats_go_on_while_another_thread_holds_the_gil(
    kind: str, channel: tuple[socket.socket, socket.socket]
) -> None:
    # A thread building a model in C++, or a normal-priority thread preempted while it
    # holds the GIL on a busy machine, must not silence a live cell (the link would brake
    # a healthy move as "cell_silent"): the native thread beats on regardless.
    ours, link = channel
    beater = Beats(ours, priority=probe(10).priority, period=PERIOD)
    try:
        beater.loop_ran()
        beater.set_running(True)
        assert _arrives(link, 5.0).startswith(b"b")
        _drain(link)
        held = _hold_the_gil(0.3)
        beats_meanwhile = _drain(link)
    finally:
        beater.close()
    expected = held / PERIOD
    if kind == "native":
        assert beats_meanwhile >= expected / 3, (beats_meanwhile, held)
    else:  # the fallback waits for the GIL: at most the beat it sends on getting it
        assert beats_meanwhile <= 2, (beats_meanwhile, held)
