"""The link process's messages to the client never block the thread that sends them.

A client whose event loop stalls stops reading its socket; once the socket's buffer is
full, a blocking write held the sending thread, and the trajectory thread among them
stopped braking, then went on along its path when the client read again.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Iterator

import pytest

from fxcell.link import wire
from fxcell.link.process import _Outbox

pytestmark = pytest.mark.timeout(30)

STATE = (wire.STATE, tuple(range(40)))


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    mine, theirs = socket.socketpair()
    with mine, theirs:
        yield mine, theirs


def _read_all(sock: socket.socket, until: float = 0.5) -> list[tuple[object, ...]]:
    """Decode every message the client side receives until it is quiet for ``until`` s."""
    sock.settimeout(until)
    buf = bytearray()
    try:
        while chunk := sock.recv(1 << 16):
            buf += chunk
    except TimeoutError:
        pass
    messages = []
    while buf:
        (size,) = wire.HEADER.unpack_from(buf)
        end = wire.HEADER.size + size
        messages.append(tuple(wire.decode(bytes(buf[wire.HEADER.size : end]))))
        del buf[:end]
    return messages


def test_a_client_that_does_not_read_never_blocks_the_sender(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    mine, theirs = pair
    outbox = _Outbox(mine, threading.Event())
    data = wire.encode(STATE)
    sent = 3 * _Outbox.MAX_BACKLOG // len(data)  # far beyond any socket buffer
    started = time.monotonic()
    for _ in range(sent):
        outbox.put(wire.STATE, data)
    outbox.put(wire.TRAJ, wire.encode((wire.TRAJ, 7, "end", {"status": "stopped"})))
    assert time.monotonic() - started < 5.0  # a blocked put would hang until the timeout
    got = _read_all(theirs)
    assert outbox.dropped == 0  # reported, and counted from zero again
    # the writer may take a batch while samples are being dropped: a warning can come
    # before the end report as well as after it
    warnings = [m for m in got if m[0] == wire.LOG]
    assert warnings
    assert all(m[1] == logging.WARNING for m in warnings)
    assert all("state samples dropped" in str(m[2]) for m in warnings)
    dropped = sum(int(str(m[2]).split()[0]) for m in warnings)
    states = [m for m in got if m[0] == wire.STATE]
    assert all(m == STATE for m in states)
    assert dropped > 0
    assert len(states) + dropped == sent  # every sample arrived or was counted
    assert [m[:3] for m in got if m[0] == wire.TRAJ] == [(wire.TRAJ, 7, "end")]
    assert got.index(next(m for m in got if m[0] == wire.TRAJ)) > got.index(states[-1])
    outbox.close(1.0)


def test_messages_arrive_whole_and_in_order(pair: tuple[socket.socket, socket.socket]) -> None:
    mine, theirs = pair
    outbox = _Outbox(mine, threading.Event())
    for k in range(500):
        outbox.put(wire.PULSE, wire.encode((wire.PULSE, k, 0.0)))
    outbox.close(1.0)
    assert [m[1] for m in _read_all(theirs)] == list(range(500))


def test_what_is_queued_at_close_still_goes_out(pair: tuple[socket.socket, socket.socket]) -> None:
    mine, theirs = pair
    outbox = _Outbox(mine, threading.Event())
    outbox.put(wire.FATAL, wire.encode((wire.FATAL, "cannot connect", {})))
    outbox.close(1.0)
    assert _read_all(theirs) == [(wire.FATAL, "cannot connect", {})]


def test_a_closed_client_socket_sets_the_failure_event(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    mine, theirs = pair
    failed = threading.Event()
    outbox = _Outbox(mine, failed)
    theirs.close()
    for _ in range(100):
        outbox.put(wire.STATE, wire.encode(STATE))
        if failed.wait(0.01):
            break
    assert failed.is_set()
    outbox.close(1.0)
