"""The simulator's RTDE server, seen by the real ur_rtde receive/IO interfaces and a raw client."""

from __future__ import annotations

import math
import os
import signal
import socket
import struct
import time

import numpy as np
import pytest
from rtde_io import RTDEIOInterface
from rtde_receive import RTDEReceiveInterface
from waiting import wait_until

from fxcell.sim.server import default_calibration
from fxcell.testing import SimulatorHandle

# UR3e DH parameters as UR publishes them, written out here independently of fxcell.
D = (0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921)
A = (0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0)
ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
# The simulator presents a calibrated arm by default: its shipped factory deltas (UR's
# calibration.conf) added to those parameters.
_CAL = default_calibration()
CAL_THETA = _CAL.delta_theta
CAL_D = tuple(v + dv for v, dv in zip(D, _CAL.delta_d, strict=True))
CAL_A = tuple(v + dv for v, dv in zip(A, _CAL.delta_a, strict=True))
CAL_ALPHA = tuple(v + dv for v, dv in zip(ALPHA, _CAL.delta_alpha, strict=True))


def dh_forward(q: list[float]) -> np.ndarray:
    """Flange pose of the default simulator's (calibrated) arm."""
    return _chain([v + t for v, t in zip(q, CAL_THETA, strict=True)], CAL_D, CAL_A, CAL_ALPHA)


def nominal_dh_forward(q: list[float]) -> np.ndarray:
    """Flange pose of the nominal UR3e."""
    return _chain(q, D, A, ALPHA)


def _chain(
    q: list[float], ds: tuple[float, ...], as_: tuple[float, ...], alphas: tuple[float, ...]
) -> np.ndarray:
    T = np.eye(4)
    for theta, d, a, alpha in zip(q, ds, as_, alphas, strict=True):
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        T = T @ np.array(
            [
                [ct, -st * ca, st * sa, a * ct],
                [st, ct * ca, -ct * sa, a * st],
                [0, sa, ca, d],
                [0, 0, 0, 1],
            ]
        )
    return T


def rotvec_matrix(r: list[float]) -> np.ndarray:
    v = np.asarray(r, dtype=float)
    angle = float(np.linalg.norm(v))
    if angle < 1e-15:
        return np.eye(3)
    k = v / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


class RawRTDE:
    """A minimal RTDE client on a plain socket."""

    def __init__(self, host: str) -> None:
        self.sock = socket.create_connection((host, 30004), timeout=5)
        self.buf = b""

    def send(self, kind: bytes, payload: bytes = b"") -> None:
        self.sock.sendall(struct.pack(">HB", len(payload) + 3, kind[0]) + payload)

    def recv(self) -> tuple[int, bytes]:
        while len(self.buf) < 3 or len(self.buf) < struct.unpack_from(">H", self.buf)[0]:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("closed")
            self.buf += chunk
        size, kind = struct.unpack_from(">HB", self.buf)
        payload, self.buf = self.buf[3:size], self.buf[size:]
        return kind, payload

    def ask(self, kind: bytes, payload: bytes = b"") -> bytes:
        self.send(kind, payload)
        while True:
            k, p = self.recv()
            if k == kind[0]:
                return p

    def close(self) -> None:
        self.sock.close()


def read_until_error(c: RawRTDE) -> Exception:
    while True:
        try:
            c.recv()
        except (OSError, ConnectionError) as exc:
            return exc


def test_receive_default_recipe_streams_at_500_hz(sim: SimulatorHandle) -> None:
    r = RTDEReceiveInterface(sim.host)
    try:
        assert r.isConnected()
        stamps = []
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            t = r.getTimestamp()
            if not stamps or t != stamps[-1]:
                stamps.append(t)
            time.sleep(0.0003)
        # The client keeps only the newest packet: a test process that a busy machine
        # deschedules misses some (it saw 248 of 500 once), so the rate is read from the
        # controller's timestamps: packets one 2 ms cycle apart, gaps only whole cycles,
        # and a controller clock that kept pace with the second of sampling.
        cycles = np.diff(stamps) / 0.002
        assert np.allclose(cycles, np.round(cycles), atol=1e-6)
        assert cycles.min() == pytest.approx(1.0, abs=1e-6)
        assert stamps[-1] - stamps[0] > 0.8
        assert r.getRobotMode() == 3
        assert r.getSafetyMode() == 1
        assert r.getRuntimeState() == 1
        assert r.getJointMode() == [239] * 6
        assert r.getSafetyStatusBits() == 1
        assert r.getPayloadCog() == [0.0, 0.0, 0.0]
    finally:
        r.disconnect()


def test_tcp_pose_matches_an_independent_dh_forward_kinematics(sim: SimulatorHandle) -> None:
    rng = np.random.default_rng(7)
    r = RTDEReceiveInterface(sim.host)
    try:
        for _ in range(4):
            q = rng.uniform(-math.pi, math.pi, 6).tolist()
            sim.set_joints(q)
            deadline = time.monotonic() + 2
            while r.getActualQ() != pytest.approx(q, abs=0) and time.monotonic() < deadline:
                time.sleep(0.005)
            assert r.getActualQ() == q
            T = dh_forward(q)
            for pose in (r.getActualTCPPose(), r.getTargetTCPPose()):
                assert np.abs(np.asarray(pose[:3]) - T[:3, 3]).max() < 1e-9
                assert np.abs(rotvec_matrix(pose[3:]) - T[:3, :3]).max() < 1e-9
                assert np.linalg.norm(pose[3:]) <= math.pi + 1e-12
    finally:
        r.disconnect()


def test_unknown_output_variable_is_not_found(sim: SimulatorHandle) -> None:
    with pytest.raises(RuntimeError, match=r"not found by the controller: \[no_such_variable\]"):
        RTDEReceiveInterface(sim.host, 500.0, ["timestamp", "no_such_variable"])


def test_raw_protocol_versions_recipes_and_frequency(sim: SimulatorHandle) -> None:
    c = RawRTDE(sim.host)
    try:
        assert c.ask(b"V", struct.pack(">H", 3)) == b"\x00"
        assert c.ask(b"V", struct.pack(">H", 2)) == b"\x01"
        assert struct.unpack(">IIII", c.ask(b"v")) == (5, 25, 1, 1)
        out = c.ask(b"O", struct.pack(">d", 125.0) + b"timestamp,actual_q,robot_mode")
        assert out == b"\x01DOUBLE,VECTOR6D,INT32"
        assert c.ask(b"I", b"input_int_register_5") == b"\x01INT32"
        assert c.ask(b"I", b"input_double_register_5,no_such_input") == b"\x00DOUBLE,NOT_FOUND"
        assert c.ask(b"I", b"input_double_register_5") == b"\x02DOUBLE"
        assert c.ask(b"S") == b"\x01"
        stamps = []
        end = time.monotonic() + 0.7  # > 250 cycles: a silent client is then read on wake-up
        while time.monotonic() < end:
            kind, payload = c.recv()
            if kind == ord("U"):
                assert payload[0] == 1
                stamps.append(struct.unpack_from(">d6di", payload, 1)[0])
        gaps = np.round(np.diff(stamps) / 0.008, 6)
        assert len(stamps) > 30
        assert np.median(gaps) == 1  # every 8 ms of controller time,
        assert np.mean(gaps == 1) > 0.8  # but a loaded machine may make the simulator late
        # an oversized input packet (more bytes than the recipe) is accepted
        c.send(b"U", bytes([1]) + struct.pack(">i", 42) + b"\x00" * 8)
        c.send(b"U", bytes([2]) + struct.pack(">d", 1.5))
        assert c.ask(b"P") == b"\x01"
        other = RawRTDE(sim.host)
        try:
            out2 = other.ask(
                b"O", struct.pack(">d", 500.0) + b"input_int_register_5,input_double_register_5"
            )
            assert out2 == b"\x01INT32,DOUBLE"
            assert other.ask(b"S") == b"\x01"
            _, payload = other.recv()
            assert struct.unpack_from(">id", payload, 1) == (42, 1.5)
            # the registers belong to the first connection
            assert other.ask(b"I", b"input_int_register_5") == b"\x00IN_USE"
            c.close()  # the simulator frees them once it sees the connection gone
            wait_until(
                lambda: other.ask(b"I", b"input_int_register_5") == b"\x01INT32",
                what="the closed connection's registers to be free again",
            )
        finally:
            other.close()
    finally:
        c.close()


def test_io_interface_sets_outputs_and_owns_its_registers(sim: SimulatorHandle) -> None:
    io = RTDEIOInterface(sim.host)
    r = RTDEReceiveInterface(sim.host)
    try:
        assert io.setStandardDigitalOut(1, True)
        assert io.setToolDigitalOut(0, True)
        assert io.setSpeedSlider(0.5)
        deadline = time.monotonic() + 2
        while r.getActualDigitalOutputBits() != (1 << 1 | 1 << 16) and time.monotonic() < deadline:
            time.sleep(0.005)
        assert r.getActualDigitalOutputBits() == 1 << 1 | 1 << 16
        assert r.getTargetSpeedFraction() == 0.5
        with pytest.raises(RuntimeError, match="already in use"):
            RTDEIOInterface(sim.host)
    finally:
        io.disconnect()
        r.disconnect()


@pytest.mark.injects_faults("a stalled and a dropped RTDE stream")
def test_stall_rtde_pauses_the_stream_and_drop_rtde_closes_it(sim: SimulatorHandle) -> None:
    c = RawRTDE(sim.host)
    try:
        c.ask(b"O", struct.pack(">d", 500.0) + b"timestamp")
        c.ask(b"S")
        c.recv()
        sim.inject("stall_rtde", 0.3)
        c.buf = b""
        c.sock.settimeout(0.2)
        assert isinstance(read_until_error(c), TimeoutError)  # after what was already sent
        c.sock.settimeout(5)
        assert c.recv()[0] == ord("U")  # the stream resumes by itself
        sim.inject("drop_rtde")
        assert isinstance(read_until_error(c), ConnectionError)
    finally:
        c.close()


@pytest.mark.parametrize(("env", "reniced"), [(None, True), ("normal", False), ("NORMAL ", False)])
def test_the_simulator_raises_its_priority_unless_told_to_stay_normal(
    monkeypatch: pytest.MonkeyPatch, env: str | None, reniced: bool
) -> None:
    from fxcell.sim import server

    calls: list[tuple[int, int, int]] = []
    monkeypatch.setattr(server.os, "setpriority", lambda *a: calls.append(a))
    if env is None:
        monkeypatch.delenv(server.PRIORITY_ENV, raising=False)
    else:
        monkeypatch.setenv(server.PRIORITY_ENV, env)
    server._raise_priority()
    assert bool(calls) is reniced


@pytest.mark.injects_faults("the simulator's process stopped for 0.2 s (SIGSTOP)")
def test_a_simulator_that_did_not_get_to_run_reports_its_stall(sim: SimulatorHandle) -> None:
    c = RawRTDE(sim.host)
    try:
        assert c.ask(b"V", struct.pack(">H", 2)) == b"\x01"
        assert c.ask(b"O", struct.pack(">d", 500.0) + b"timestamp") == b"\x01DOUBLE"
        assert c.ask(b"S") == b"\x01"
        before = len(sim.state()["stalls"])  # a busy machine may have stalled it already
        os.kill(sim.pid, signal.SIGSTOP)
        time.sleep(0.2)  # the length of the stall itself
        os.kill(sim.pid, signal.SIGCONT)
        c.recv()  # the controller runs again
        stalls = sim.state()["stalls"][before:]
        assert stalls, "the simulator did not report the 0.2 s it was stopped"
        ended, length = max(stalls, key=lambda stall: stall[1])
        assert 0.19 <= length < 2.0
        assert abs(ended - time.time()) < 5.0
    finally:
        c.close()
