"""The simulator's RTDE server as UR documents it: UR's own Python client with UR's own recipe
file, protocol version 1, the upper bit registers, the recipe size limit, the speed slider."""

from __future__ import annotations

import json
import re
import struct
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from rtde_io import RTDEIOInterface
from rtde_receive import RTDEReceiveInterface

from fxcell.testing import SimulatorHandle, simulator

from .test_sim_primary import Messages
from .test_sim_rtde import RawRTDE

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
        assert version[:2] == (5, 11)
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
        assert (kind, reply) == (ord("O"), b"\x00")
        assert c.ask(b"I", b"input_int_register_9," * 200) == b"\x00"
        assert c.ask(b"O", struct.pack(">d", 500.0) + b"timestamp") == b"\x01DOUBLE"
    finally:
        c.close()


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
