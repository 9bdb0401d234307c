"""The RTDE reader tells how much the controller sent that it has not read yet.

A trajectory that brakes on a stalled state stream logs this: bytes unread mean the
link process stalled, not the controller.
"""

from __future__ import annotations

import socket

import pytest

from fxcell.link.rtde_stream import HEADER, RTDEStream

pytestmark = pytest.mark.timeout(10)


def test_unread_counts_bytes_waiting_in_the_socket_and_a_partial_packet() -> None:
    stream = RTDEStream("127.0.0.1")
    controller, link = socket.socketpair()
    with controller, link:
        stream._sock = link
        assert stream.unread() == 0
        packet = HEADER.pack(HEADER.size + 4, ord("U")) + b"\0" * 4
        controller.sendall(packet * 3)
        assert stream.unread() == 3 * len(packet)
        stream._buffer += link.recv(len(packet) + 2)  # as the reader holds a partial packet
        assert stream.unread() == 3 * len(packet)
        stream._sock = None


def test_unread_is_zero_for_a_stream_never_connected() -> None:
    assert RTDEStream("127.0.0.1").unread() == 0
