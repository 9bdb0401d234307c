"""Reading the arm's calibration from the controller's primary interface (30001)."""

from __future__ import annotations

import contextlib
import json
import socket
import struct
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from fxcell.calibration import Calibration
from fxcell.cli import main
from fxcell.errors import CalibrationError
from fxcell.link.primary import kinematics_info_of, read_calibration

pytestmark = pytest.mark.timeout(30)

CALIBRATION = Calibration(
    delta_theta=(0.001, -0.002, 0.0, 0.0005, 0.0, -0.001),
    delta_a=(0.0, 0.0015, -0.002, 0.0, 0.0004, 0.0),
    delta_d=(0.0012, 0.0, 0.0, -0.0018, 0.0, 0.0009),
    delta_alpha=(0.0, 0.0007, 0.0, -0.0011, 0.002, 0.0),
)


def _message(kind: int, body: bytes) -> bytes:
    return struct.pack(">IB", 5 + len(body), kind) + body


def _robot_state(*subpackages: bytes) -> bytes:
    return _message(16, b"".join(subpackages))


def _subpackage(kind: int, body: bytes) -> bytes:
    return struct.pack(">IB", 5 + len(body), kind) + body


VERSION = _message(20, struct.pack(">QbB", 0, -1, 7) + b"URControl" + bytes(10))
ROBOT_MODE = _subpackage(0, bytes(41))
JOINTS = _subpackage(1, bytes(6 * 41))


@contextlib.contextmanager
def primary_server(*messages: bytes, chunk: int = 7) -> Iterator[int]:
    """A listener that sends ``messages`` in ``chunk``-byte pieces to each client."""
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    stop = threading.Event()

    def serve() -> None:
        with server:
            server.settimeout(0.1)
            while not stop.is_set():
                try:
                    conn, _ = server.accept()
                except TimeoutError:
                    continue
                with conn:
                    data = b"".join(messages)
                    for i in range(0, len(data), chunk):
                        conn.sendall(data[i : i + chunk])
                    stop.wait(2.0)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield port
    finally:
        stop.set()
        thread.join(5)


def test_reads_the_kinematics_info_of_the_first_robot_state_that_has_one() -> None:
    without = _robot_state(ROBOT_MODE, JOINTS)
    with_info = _robot_state(ROBOT_MODE, JOINTS, CALIBRATION.kinematics_info())
    with primary_server(VERSION, without, with_info) as port:
        calibration = read_calibration("127.0.0.1", port, timeout=5.0)
    assert calibration.checksum == CALIBRATION.checksum
    assert calibration.delta_d == pytest.approx(CALIBRATION.delta_d, abs=1e-15)


def test_no_kinematics_info_in_time_is_a_calibration_error() -> None:
    with (
        primary_server(VERSION, _robot_state(ROBOT_MODE)) as port,
        pytest.raises(CalibrationError, match="no kinematics info"),
    ):
        read_calibration("127.0.0.1", port, timeout=0.3)


def test_a_refused_connection_is_a_calibration_error() -> None:
    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]
    with pytest.raises(CalibrationError, match="cannot read the calibration"):
        read_calibration("127.0.0.1", port, timeout=1.0)


def test_a_corrupted_kinematics_info_is_refused() -> None:
    package = bytearray(CALIBRATION.kinematics_info())
    package[100] ^= 0x40
    with (
        primary_server(VERSION, _robot_state(JOINTS, bytes(package))) as port,
        pytest.raises(CalibrationError, match="checksum mismatch"),
    ):
        read_calibration("127.0.0.1", port, timeout=5.0)


def test_a_sub_package_running_past_its_message_is_malformed() -> None:
    body = struct.pack(">IB", 500, 1) + bytes(20)
    with pytest.raises(CalibrationError, match="malformed"):
        kinematics_info_of(body)


def test_calibration_show_prints_the_deltas_and_checksum(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "calibration.conf"
    path.write_text(CALIBRATION.to_conf())
    assert main(["calibration", "show", "--file", str(path), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["checksum"] == CALIBRATION.checksum
    assert shown["delta_a"] == list(CALIBRATION.delta_a)
    assert shown["source"] == str(path)
    assert main(["calibration", "show", "--file", str(path)]) == 0
    text = capsys.readouterr().out
    assert CALIBRATION.checksum in text
    assert "-0.002000000" in text  # joint 3's delta a
    with primary_server(VERSION, _robot_state(CALIBRATION.kinematics_info())) as port:
        assert main(["calibration", "show", "--host", "127.0.0.1", "--port", str(port)]) == 0
    assert f"controller 127.0.0.1: checksum {CALIBRATION.checksum}" in capsys.readouterr().out
    assert main(["calibration", "show", "--file", str(tmp_path / "missing.conf")]) == 1
    assert "cannot read calibration file" in capsys.readouterr().err
