"""The simulator's RTDE server as UR documents it: UR's own Python client with UR's own recipe
file, protocol version 1, the upper bit registers, the recipe size limit, the speed slider."""

from __future__ import annotations

import itertools
import json
import math
import re
import struct
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from rtde_control import RTDEControlInterface
from rtde_io import RTDEIOInterface
from rtde_receive import RTDEReceiveInterface

from fxcell.testing import SimulatorHandle, simulator

from .test_sim_primary import Messages
from .test_sim_rtde import ALPHA, A, D, RawRTDE

pytestmark = pytest.mark.timeout(120)

VENDOR = Path(__file__).parent / "vendor"
RECORD_CONFIGURATION = VENDOR / "record_configuration.xml"
START = [0.1, -1.2, 1.2, -1.57, -1.57, 0.3]


@pytest.fixture(scope="module")
def ur_rtde_module() -> Iterator[object]:
    sys.path.insert(0, str(VENDOR))
    try:
        import rtde.rtde as ur_rtde_client

        yield ur_rtde_client
    finally:
        sys.path.remove(str(VENDOR))


@pytest.fixture(scope="module")
def running() -> Iterator[SimulatorHandle]:
    with simulator() as sim:
        sim.set_joints(START)
        sim.bring_up()
        yield sim


def recipe_fields(key: str, *, commented: bool) -> list[tuple[str, str]]:
    """(name, type) of a recipe in UR's file, its commented-out fields too if asked."""
    text = RECORD_CONFIGURATION.read_text()
    if not commented:
        text = re.sub(r"<!--.*?-->", "", text, flags=re.S)
    start = text.index(f'<recipe key="{key}">')
    end = text.index("</recipe>", start)
    return re.findall(r'name="([^"]+)" type="([^"]+)"', text[start:end])


def chunks(fields: list[tuple[str, str]], limit: int = 2000) -> Iterator[list[tuple[str, str]]]:
    chunk: list[tuple[str, str]] = []
    for field in fields:
        if chunk and len(",".join(n for n, _ in [*chunk, field])) > limit:
            yield chunk
            chunk = []
        chunk.append(field)
    if chunk:
        yield chunk


def test_urs_record_recipe_sets_up_with_urs_types_and_streams(
    running: SimulatorHandle, ur_rtde_module: object
) -> None:
    rtde = ur_rtde_module
    fields = recipe_fields("out", commented=False)
    names, types = [n for n, _ in fields], [t for _, t in fields]
    con = rtde.RTDE(running.host, 30004)  # type: ignore[attr-defined]
    con.connect()
    try:
        version = con.get_controller_version()
        assert version[:2] == (5, 25)
        assert con.send_output_setup(names, types, frequency=500)  # False on any type mismatch
        assert con.send_start()
        samples = [con.receive() for _ in range(20)]
        assert all(s is not None for s in samples)
        stamps = np.array([s.timestamp for s in samples])
        assert np.all(np.diff(stamps) > 0)
        last = samples[-1]
        assert np.allclose(last.actual_q, running.state()["q"], atol=1e-12)
        assert isinstance(last.joint_position_deviation_ratio, float)
        assert last.robot_mode == 7
        con.send_pause()
    finally:
        con.disconnect()


@pytest.mark.parametrize("key", ["out", "in"])
def test_every_field_of_urs_recipe_file_has_urs_type(
    running: SimulatorHandle, ur_rtde_module: object, key: str
) -> None:
    rtde = ur_rtde_module
    fields = recipe_fields(key, commented=True)
    assert len(fields) > 100
    for chunk in chunks(fields):
        con = rtde.RTDE(running.host, 30004)  # type: ignore[attr-defined]
        con.connect()
        try:
            names, types = [n for n, _ in chunk], [t for _, t in chunk]
            if key == "out":
                assert con.send_output_setup(names, types, frequency=10), chunk
            else:
                assert con.send_input_setup(names, types) is not None, chunk
        finally:
            con.disconnect()


def test_protocol_version_1_is_answered_as_version_1(running: SimulatorHandle) -> None:
    c = RawRTDE(running.host)
    try:
        assert c.ask(b"V", struct.pack(">H", 1)) == b"\x01"
        # version 1: names only, types only (no recipe id), data without recipe id at 125 Hz
        assert c.ask(b"O", b"timestamp,actual_q") == b"DOUBLE,VECTOR6D"
        assert c.ask(b"I", b"input_int_register_7") == b"\x01INT32"
        assert c.ask(b"S") == b"\x01"
        stamps = []
        while len(stamps) < 12:
            kind, payload = c.recv()
            if kind == ord("U"):
                assert len(payload) == 8 + 48
                stamps.append(struct.unpack_from(">d", payload)[0])
        gaps = np.round(np.diff(stamps) / 0.008, 6)
        assert np.median(gaps) == 1
        assert c.ask(b"P") == b"\x01"
    finally:
        c.close()


def test_bit_registers_64_to_127_are_separate_from_0_to_63(running: SimulatorHandle) -> None:
    writer, reader = RawRTDE(running.host), RawRTDE(running.host)
    try:
        assert writer.ask(b"V", struct.pack(">H", 2)) == b"\x01"
        inputs = b"input_bit_registers0_to_31,input_bit_register_64,input_bit_register_127"
        assert writer.ask(b"I", inputs) == b"\x01UINT32,BOOL,BOOL"
        assert writer.ask(b"S") == b"\x01"
        writer.send(b"U", bytes([1]) + struct.pack(">I??", 0b101, True, True))
        assert reader.ask(b"V", struct.pack(">H", 2)) == b"\x01"
        outputs = (
            b"input_bit_registers0_to_31,input_bit_registers32_to_63,input_bit_register_64,"
            b"input_bit_register_65,input_bit_register_127,output_bit_register_64"
        )
        reply = reader.ask(b"O", struct.pack(">d", 500.0) + outputs)
        assert reply == b"\x01UINT32,UINT32,BOOL,BOOL,BOOL,BOOL"
        assert reader.ask(b"S") == b"\x01"
        deadline = time.monotonic() + 5
        while True:
            kind, payload = reader.recv()
            if kind != ord("U"):
                continue
            values = struct.unpack_from(">II????", payload, 1)
            if values == (0b101, 0, True, False, True, False):
                break
            assert time.monotonic() < deadline, values
    finally:
        writer.close()
        reader.close()


def test_an_over_long_recipe_is_refused_at_once_and_the_session_goes_on(
    running: SimulatorHandle,
) -> None:
    c = RawRTDE(running.host)
    try:
        assert c.ask(b"V", struct.pack(">H", 2)) == b"\x01"
        names = ",".join(f"output_double_register_{i % 48}" for i in range(120)).encode()
        assert len(names) > 2048
        c.send(b"O", struct.pack(">d", 500.0) + names)
        kind, message = c.recv()
        assert kind == ord("M")
        text = message[1 : 1 + message[0]].decode()
        assert "2048" in text
        kind, reply = c.recv()
        assert (kind, reply) == (ord("O"), b"\x00" + b",".join([b"NOT_FOUND"] * 120))
        assert c.ask(b"I", b"input_int_register_9," * 200) == b"\x00" + b",".join(
            [b"NOT_FOUND"] * 200
        )
        assert c.ask(b"O", struct.pack(">d", 500.0) + b"timestamp") == b"\x01DOUBLE"
    finally:
        c.close()


def test_urs_client_reads_the_refusal_of_an_over_long_recipe_and_goes_on(
    running: SimulatorHandle, ur_rtde_module: object
) -> None:
    rtde = ur_rtde_module
    names = [f"output_double_register_{i % 48}" for i in range(120)]
    con = rtde.RTDE(running.host, 30004)  # type: ignore[attr-defined]
    con.connect()
    try:
        # the reply is the documented failed setup: every name NOT_FOUND, which UR's client
        # turns into its error for an unknown variable (not a parse failure on empty types)
        with pytest.raises(ValueError, match=r"Unknown data type: NOT_FOUND$"):
            con.send_output_setup(names, frequency=10)
        assert con.send_output_setup(["timestamp"], ["DOUBLE"], frequency=10)
    finally:
        con.disconnect()


def test_the_speed_slider_reaches_programs_and_the_primary_interface(
    running: SimulatorHandle,
) -> None:
    io = RTDEIOInterface(running.host)
    r = RTDEReceiveInterface(running.host)
    try:
        assert io.setSpeedSlider(0.25)
        deadline = time.monotonic() + 5
        while r.getTargetSpeedFraction() != 0.25:
            assert time.monotonic() < deadline
            time.sleep(0.005)
        m = Messages(running.host, 30001)
        try:
            mode = struct.unpack(">Q???????BBdddB", m.robot_state()[0])
        finally:
            m.close()
        assert mode[10] == 0.25  # target speed fraction
        # a move at a quarter of the programmed speed: joint speed never above v/4
        with Messages(running.host, 30002).sock as s:
            s.sendall(b"movej([0.4, -1.2, 1.2, -1.57, -1.57, 0.3], a=4, v=0.8)\n")
        peak = 0.0
        deadline = time.monotonic() + 15
        started = False
        while time.monotonic() < deadline:
            qd = max(abs(v) for v in r.getActualQd())
            peak = max(peak, qd)
            started = started or qd > 0
            if started and r.getRuntimeState() == 1 and qd == 0:
                break
            time.sleep(0.002)
        assert started, json.dumps(running.state())
        assert 0.19 < peak <= 0.2 + 1e-9
        assert io.setSpeedSlider(1.0)
    finally:
        io.disconnect()
        r.disconnect()


def test_ur_rtde_receives_urs_record_recipe(running: SimulatorHandle) -> None:
    names = [n for n, _ in recipe_fields("out", commented=False)]
    r = RTDEReceiveInterface(running.host, 500.0, names)
    try:
        deadline = time.monotonic() + 5
        while r.getTimestamp() == 0.0:
            assert time.monotonic() < deadline
            time.sleep(0.005)
        assert np.allclose(r.getActualQ(), running.state()["q"], atol=1e-12)
        assert r.getRobotMode() == 7
    finally:
        r.disconnect()


# UR3e links as UR publishes them (link k in DH frame k): mass (kg), centre of mass (m)
LINK_MASSES = (1.98, 3.4445, 1.437, 0.871, 0.805, 0.261)
LINK_COMS = (
    (0.0, -0.02, 0.0),
    (0.13, 0.0, 0.1157),
    (0.05, 0.0, 0.0238),
    (0.0, 0.0, 0.01),
    (0.0, 0.0, 0.01),
    (0.0, 0.0, -0.02),
)
NEWER_OUTPUTS = [
    "timestamp",
    "actual_q",
    "actual_TCP_speed",
    "actual_current_as_torque",
    "actual_TCP_acceleration",
    "target_TCP_acceleration",
    "target_execution_time",
    "wrench_calc_from_currents",
    "target_gravity",
    "target_base_acceleration",
    "control_step",
    "target_base_wrench",
    "actual_robot_energy_consumed",
    "actual_robot_braking_energy_dissipated",
]


def holding_torques(q: list[float], payload: float = 0.0) -> np.ndarray:
    """Joint torques holding the arm still against gravity (statics on UR's DH chain)."""
    frames = [np.eye(4)]
    for k in range(6):
        frames.append(frames[-1] @ dh_link(q, k))
    weights = [
        (frames[k + 1] @ np.array([*LINK_COMS[k], 1.0]))[:3] for k in range(6)
    ]  # centres of mass in the base frame
    masses = list(LINK_MASSES)
    if payload:
        weights.append(frames[6][:3, 3])  # a point mass on the flange
        masses.append(payload)
    gravity = np.array([0.0, 0.0, -9.82])
    tau = np.zeros(6)
    for j in range(6):
        axis, origin = frames[j][:3, 2], frames[j][:3, 3]
        for k, (com, mass) in enumerate(zip(weights, masses, strict=True)):
            if k >= j:  # links j.. and the payload hang on joint j
                tau[j] -= np.dot(np.cross(com - origin, mass * gravity), axis)
    return tau


def dh_link(q: list[float], k: int) -> np.ndarray:
    """UR's DH transform of link ``k`` (0-based)."""
    ct, st = math.cos(q[k]), math.sin(q[k])
    ca, sa = math.cos(ALPHA[k]), math.sin(ALPHA[k])
    return np.array(
        [
            [ct, -st * ca, st * sa, A[k] * ct],
            [st, ct * ca, -ct * sa, A[k] * st],
            [0, sa, ca, D[k]],
            [0, 0, 0, 1],
        ]
    )


def test_outputs_of_newer_polyscope_versions_are_served_from_the_arm_model(
    running: SimulatorHandle, ur_rtde_module: object
) -> None:
    rtde = ur_rtde_module
    con = rtde.RTDE(running.host, 30004)  # type: ignore[attr-defined]
    con.connect()
    try:
        assert con.get_controller_version()[:2] == (5, 25)  # the version documenting them
        assert con.send_output_setup(NEWER_OUTPUTS, frequency=500)
        assert con.send_start()
        samples = [con.receive() for _ in range(30)]
        con.send_pause()
    finally:
        con.disconnect()
    first, last = samples[0], samples[-1]
    assert last.control_step == round(last.timestamp / 0.002)
    assert last.target_gravity == [0.0, 0.0, 9.82]
    assert last.target_execution_time > 0
    for zero in ("wrench_calc_from_currents", "target_base_acceleration"):
        assert getattr(last, zero) == [0.0] * 6  # nothing touches the arm; its base is fixed
    assert last.actual_robot_braking_energy_dissipated == 0.0
    # powered: the energy meter runs at the arm's power, 48 V x 0.6 A
    energy = last.actual_robot_energy_consumed - first.actual_robot_energy_consumed
    assert math.isclose(energy, 28.8 * (last.timestamp - first.timestamp), rel_tol=1e-6)
    # at rest: the torques hold the arm against gravity; the base carries its weight
    assert np.allclose(last.actual_TCP_acceleration, 0.0)
    expected = holding_torques(last.actual_q)
    assert np.allclose(last.actual_current_as_torque, expected, atol=0.05), expected
    wrench = np.array(last.target_base_wrench)
    assert np.allclose(wrench[:3], [0.0, 0.0, -9.82 * sum(LINK_MASSES)], atol=1e-6)


def test_torques_carry_the_payload_and_tcp_acceleration_follows_the_speed(
    running: SimulatorHandle, ur_rtde_module: object
) -> None:
    rtde = ur_rtde_module
    c = RTDEControlInterface(running.host)
    con = rtde.RTDE(running.host, 30004)  # type: ignore[attr-defined]
    con.connect()
    try:
        assert c.setPayload(1.5, [0.0, 0.0, 0.0])
        assert con.send_output_setup(NEWER_OUTPUTS, frequency=500)
        assert con.send_start()
        rest = con.receive()
        expected = holding_torques(rest.actual_q, payload=1.5)
        assert np.allclose(rest.actual_current_as_torque, expected, atol=0.05), expected
        assert math.isclose(
            rest.target_base_wrench[2], -9.82 * (sum(LINK_MASSES) + 1.5), rel_tol=1e-9
        )
        target = [START[0] + 0.5, *START[1:]]
        assert c.moveJ(target, 1.0, 2.0, True)  # asynchronous: sample while it moves
        samples: list[object] = []
        while len(samples) < 200:
            samples.append(con.receive())
        con.send_pause()
        moving = [s for s in samples if any(abs(v) > 1e-3 for v in s.actual_TCP_speed)]
        assert len(moving) > 50
        checked = 0
        for before, now in itertools.pairwise(samples):
            dt = now.timestamp - before.timestamp
            if abs(dt - 0.002) > 1e-9:
                continue  # a skipped sample: the controller's own difference spans two
            slope = (np.array(now.actual_TCP_speed) - before.actual_TCP_speed) / dt
            assert np.allclose(now.actual_TCP_acceleration, slope, atol=1e-6)
            assert now.target_TCP_acceleration == now.actual_TCP_acceleration
            checked += 1
        assert checked > 50
        assert max(abs(v) for s in moving for v in s.actual_TCP_acceleration) > 0.1
    finally:
        c.stopJ(2.0)
        c.setPayload(0.0, [0.0, 0.0, 0.0])
        c.stopScript()
        c.disconnect()
        con.disconnect()


def test_the_256th_recipe_of_a_connection_is_answered_with_the_failure_id(
    running: SimulatorHandle, ur_rtde_module: object
) -> None:
    # recipe ids are a uint8 and 0 means failure: 255 recipes per connection and direction
    c = RawRTDE(running.host)
    try:
        assert c.ask(b"V", struct.pack(">H", 2)) == b"\x01"
        for n in range(1, 256):
            assert c.ask(b"O", struct.pack(">d", 10.0) + b"timestamp") == bytes([n]) + b"DOUBLE"
        c.send(b"O", struct.pack(">d", 10.0) + b"timestamp,actual_q")
        kind, message = c.recv()
        assert kind == ord("M")
        assert b"255 output recipes" in message
        assert c.recv() == (ord("O"), b"\x00DOUBLE,VECTOR6D")
        for n in range(1, 256):
            assert c.ask(b"I", f"input_int_register_{n % 24}".encode())[0] == n
        assert c.ask(b"I", b"input_int_register_30") == b"\x00INT32"
        assert c.ask(b"S") == b"\x01"  # the connection goes on with the recipes it has
        kind, payload = c.recv()
        while kind != ord("U"):
            kind, payload = c.recv()
        assert 1 <= payload[0] <= 255
    finally:
        c.close()
    # UR's own client gets its answer (it does not wait forever) and keeps working
    rtde = ur_rtde_module
    con = rtde.RTDE(running.host, 30004)  # type: ignore[attr-defined]
    con.connect()
    try:
        for _ in range(256):
            con.send_output_setup(["timestamp"], ["DOUBLE"], frequency=10)
        assert con.is_connected()
    finally:
        con.disconnect()
