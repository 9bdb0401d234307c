"""RTDE setup requests held while the arm's dynamic model loads: answered once it is, in the
order they came (in process: the connection on a socket pair, the load finished by hand)."""

from __future__ import annotations

import socket
import struct
from collections.abc import Callable

from fxcell.sim.controller import Controller
from fxcell.sim.motion import Arm
from fxcell.sim.rtde import RTDEConnection, RTDEHub


def packet(kind: bytes, payload: bytes = b"") -> bytes:
    return struct.pack(">HB", len(payload) + 3, kind[0]) + payload


def replies(sock: socket.socket) -> list[tuple[int, bytes]]:
    sock.setblocking(False)
    data = b""
    try:
        while chunk := sock.recv(65536):
            data += chunk
    except BlockingIOError:
        pass
    out = []
    while data:
        size, kind = struct.unpack_from(">HB", data)
        out.append((kind, data[3:size]))
        data = data[size:]
    return out


def test_a_setup_for_model_outputs_is_answered_after_the_model_loads_then_the_rest() -> None:
    from fxcell.motion.kinematics import Kinematics

    hub = RTDEHub(Controller(Arm(Kinematics.ur3e())))
    waiting: list[Callable[[], None]] = []
    hub.load_dynamics = waiting.append
    ours, theirs = socket.socketpair()
    try:
        ours.setblocking(False)
        conn = RTDEConnection(hub, ours, "test")
        hub.connections.add(conn)
        conn.data_received(
            packet(b"O", struct.pack(">d", 500.0) + b"timestamp,actual_current_as_torque")
            + packet(b"I", b"input_int_register_3")
            + packet(b"v")
        )
        assert replies(theirs) == []  # held: the model is loading
        assert len(waiting) == 1
        hub.dynamics_ready = True
        waiting[0]()
        got = replies(theirs)
        assert [kind for kind, _ in got] == [ord("O"), ord("I"), ord("v")]
        assert got[0][1] == b"\x01DOUBLE,VECTOR6D"
        assert got[1][1] == b"\x01INT32"
        assert hub.dynamics_fields == {"actual_current_as_torque"}
        # once loaded, nothing waits
        conn.data_received(packet(b"O", struct.pack(">d", 10.0) + b"target_base_wrench"))
        assert replies(theirs) == [(ord("O"), b"\x02VECTOR6D")]
        assert hub.dynamics_fields == {"actual_current_as_torque", "target_base_wrench"}
    finally:
        ours.close()
        theirs.close()
