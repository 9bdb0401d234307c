"""The simulated fusion machine and controller inputs, seen over RTDE by ur_rtde's interfaces.

The simulator runs in its own process; ``RTDEReceiveInterface`` watches the machine's signals
(``actual_digital_input_bits``) and ``RTDEIOInterface`` gives its start signal (DO0).
"""

from __future__ import annotations

import socket
import struct
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from rtde_io import RTDEIOInterface
from rtde_receive import RTDEReceiveInterface

from fxcell.config import CellConfig
from fxcell.errors import SimulatorError
from fxcell.geometry import Pose
from fxcell.layout import Layout
from fxcell.link.embedded import free_loopback_host
from fxcell.testing import TEST_TIME_SCALE, SimulatorHandle, simulator

# 10 s × 0.05 = 0.5 s of fusion, and as long for cooling
MACHINE_ARGS = ["--fusion-time", "10", "--cooling-time", "10"]
PHASE = 10 * TEST_TIME_SCALE
READY, BUSY, DONE, ERROR = 0, 1, 2, 3


def wait_until(predicate: Callable[[], bool], timeout: float = 10.0, what: str = "it") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.002)


def wait_controller_time(sim: SimulatorHandle, seconds: float) -> None:
    """Wait until the machine has been ticked ``seconds`` of controller time from now."""
    start = sim.machine()["time"]
    wait_until(lambda: sim.machine()["time"] >= start + seconds, what="controller time")


@pytest.fixture(scope="module")
def layout() -> Layout:
    return Layout(CellConfig.load().layout)


@pytest.fixture
def sim() -> Iterator[SimulatorHandle]:
    with simulator(extra_args=[*MACHINE_ARGS, "--crucibles", "4"]) as s:
        yield s


@pytest.fixture
def receive(sim: SimulatorHandle) -> Iterator[RTDEReceiveInterface]:
    r = RTDEReceiveInterface(sim.host)
    yield r
    r.disconnect()


@pytest.fixture
def io(sim: SimulatorHandle) -> Iterator[RTDEIOInterface]:
    client = RTDEIOInterface(sim.host)
    yield client
    client.disconnect()


def bits(r: RTDEReceiveInterface) -> tuple[bool, bool, bool, bool]:
    return (
        r.getDigitalInState(READY),
        r.getDigitalInState(BUSY),
        r.getDigitalInState(DONE),
        r.getDigitalInState(ERROR),
    )


def pose_of(obj: dict[str, Any]) -> Pose:
    return Pose.from_ur(obj["pose"])


def load(sim: SimulatorHandle, rack_slots: list[str]) -> None:
    """Move the crucibles of these rack slots into machine positions A1, A2, ..."""
    for slot, position in zip(rack_slots, ["A1", "A2", "A3", "A4"], strict=False):
        sim.place_object(f"crucible-{slot}", "crucible", "machine", position)


def test_crucibles_option_puts_sample_crucibles_in_the_rack_slots(
    sim: SimulatorHandle, layout: Layout
) -> None:
    rack = layout.station("rack")
    objects = sim.objects()
    assert sorted(objects) == [f"crucible-{s}" for s in ("A1", "A2", "A3", "A4")]
    for name, obj in objects.items():
        slot = name.removeprefix("crucible-")
        assert (obj["station"], obj["slot"], obj["kind"]) == ("rack", slot, "crucible")
        assert obj["contents"] == "sample"
        assert np.allclose(pose_of(obj).position, rack.grip_pose(slot).position, atol=1e-9)
        assert obj["width"] == layout.config.objects["crucible"].width


def test_full_cycle_over_rtde_pours_beads_into_the_moulds(
    sim: SimulatorHandle,
    receive: RTDEReceiveInterface,
    io: RTDEIOInterface,
    layout: Layout,
) -> None:
    wait_until(lambda: bits(receive) == (True, False, False, False), what="ready")
    load(sim, ["A1", "A3"])  # positions A1 and A2
    wait_until(lambda: sim.machine()["state"] == "loaded", what="loaded")

    assert io.setStandardDigitalOut(0, True)
    wait_until(lambda: receive.getDigitalInState(BUSY), what="busy")
    started = time.monotonic()
    assert bits(receive) == (False, True, False, False)
    assert sim.machine()["state"] == "fusing"
    assert io.setStandardDigitalOut(0, False)
    wait_until(lambda: sim.machine()["state"] == "cooling", what="cooling")
    wait_until(lambda: receive.getDigitalInState(DONE), what="done")
    elapsed = time.monotonic() - started
    assert bits(receive) == (False, False, True, False)
    # the controller's clock follows the wall clock: fusion + cooling, within a busy machine's lag
    assert 2 * PHASE - 0.05 <= elapsed <= 2 * PHASE + 2.0

    moulds = layout.station("moulds")
    objects = sim.objects()
    for crucible, mould in (("crucible-A1", "A1"), ("crucible-A3", "A2")):
        bead = objects[f"{crucible}.bead"]
        assert (bead["kind"], bead["station"], bead["slot"]) == ("bead", "moulds", mould)
        assert np.allclose(pose_of(bead).position, moulds.grip_pose(mould).position, atol=1e-9)
        assert bead["contents"] == "sample"
        assert objects[crucible]["contents"] is None
    assert objects["crucible-A2"]["contents"] == "sample"  # stayed in the rack
    report = sim.machine()
    assert report["moulds"] == {
        "A1": "crucible-A1.bead",
        "A2": "crucible-A3.bead",
        "A3": None,
        "A4": None,
    }

    # unloading: done until both moulds are empty, then loaded (crucibles), then idle
    sim.place_object("crucible-A1.bead", "bead", "tray", "A1")
    assert sim.objects()["crucible-A1.bead"]["contents"] == "sample"  # moved, still itself
    wait_controller_time(sim, 0.1)  # the machine sees one mould empty: it stays done
    assert receive.getDigitalInState(DONE)
    sim.place_object("crucible-A3.bead", "bead", "tray", "A2")
    wait_until(lambda: sim.machine()["state"] == "loaded", what="loaded again")
    wait_until(lambda: bits(receive) == (True, False, False, False), what="ready again")
    for slot in ("A1", "A3"):
        sim.place_object(f"crucible-{slot}", "crucible", "rack", slot)
    wait_until(lambda: sim.machine()["state"] == "idle", what="idle")


def test_start_without_crucibles_is_ignored(
    sim: SimulatorHandle, receive: RTDEReceiveInterface, io: RTDEIOInterface
) -> None:
    assert io.setStandardDigitalOut(0, True)
    wait_until(
        lambda: any("no crucible" in m for m in sim.machine()["log"]), what="the refusal log"
    )
    assert bits(receive) == (True, False, False, False)
    assert sim.machine()["state"] == "idle"


def test_machine_error_aborts_the_cycle_until_reset(
    sim: SimulatorHandle, receive: RTDEReceiveInterface, io: RTDEIOInterface
) -> None:
    load(sim, ["A2"])
    wait_until(lambda: sim.machine()["state"] == "loaded", what="loaded")
    assert io.setStandardDigitalOut(0, True)
    wait_until(lambda: receive.getDigitalInState(BUSY), what="busy")
    assert sim.inject("machine_error") == "machine error"
    wait_until(lambda: bits(receive) == (False, False, False, True), what="error")
    wait_controller_time(sim, 2 * PHASE + 0.1)  # past the aborted cycle's end: still no bead
    assert not any(o["kind"] == "bead" for o in sim.objects().values())
    assert bits(receive) == (False, False, False, True)
    assert sim.inject("machine_reset") == "machine reset"
    wait_until(lambda: bits(receive) == (True, False, False, False), what="ready after reset")
    assert sim.machine()["state"] == "loaded"


def test_door_open_reports_error_and_not_ready_until_closed(
    sim: SimulatorHandle, receive: RTDEReceiveInterface
) -> None:
    sim.inject("door_open")
    wait_until(lambda: bits(receive) == (False, False, False, True), what="door error")
    assert sim.machine()["door_open"] is True
    sim.inject("door_close")
    wait_until(lambda: bits(receive) == (True, False, False, False), what="ready")


def test_taking_a_crucible_out_while_fusing_is_a_machine_error(
    sim: SimulatorHandle, receive: RTDEReceiveInterface, io: RTDEIOInterface
) -> None:
    load(sim, ["A1", "A2"])
    wait_until(lambda: sim.machine()["state"] == "loaded", what="loaded")
    assert io.setStandardDigitalOut(0, True)
    wait_until(lambda: receive.getDigitalInState(BUSY), what="busy")
    sim.place_object("crucible-A2", "crucible", "rack", "A2")
    wait_until(lambda: receive.getDigitalInState(ERROR), what="error")
    report = sim.machine()
    assert report["state"] == "error"
    assert "taken out or put in" in report["fault"]


def test_set_input_is_read_back_by_rtde_receive(
    sim: SimulatorHandle, receive: RTDEReceiveInterface
) -> None:
    sim.set_input("5", 1)
    sim.set_input("CI2", 1)
    sim.set_input("TI1", 1)
    sim.set_input("AI0", 4.2)
    sim.set_input("AI1", -0.5)
    wait_until(lambda: receive.getStandardAnalogInput1() == -0.5, what="AI1")
    assert receive.getDigitalInState(5)
    assert receive.getDigitalInState(8 + 2)
    assert receive.getDigitalInState(16 + 1)
    assert not receive.getDigitalInState(4)
    assert receive.getActualDigitalInputBits() == 1 << 5 | 1 << 10 | 1 << 17 | 1 << READY
    assert receive.getStandardAnalogInput0() == 4.2
    sim.set_input("DI5", 0)
    wait_until(lambda: not receive.getDigitalInState(5), what="DI5 cleared")


def read_outputs(host: str, names: str, fmt: str) -> tuple[Any, ...]:
    """One sample of an output recipe, read with a plain-socket RTDE (protocol 2) client."""
    with socket.create_connection((host, 30004), timeout=5) as sock:
        buf = b""

        def packet(kind: bytes, payload: bytes = b"") -> None:
            sock.sendall(struct.pack(">HB", len(payload) + 3, kind[0]) + payload)

        def reply(kind: bytes) -> bytes:
            nonlocal buf
            while True:
                while len(buf) < 3 or len(buf) < struct.unpack_from(">H", buf)[0]:
                    chunk = sock.recv(65536)
                    assert chunk, "connection closed"
                    buf += chunk
                size, k = struct.unpack_from(">HB", buf)
                payload, buf = buf[3:size], buf[size:]
                if k == kind[0]:
                    return payload

        packet(b"V", struct.pack(">H", 2))
        assert reply(b"V") == b"\x01"
        packet(b"O", struct.pack(">d", 125.0) + names.encode())
        assert reply(b"O")[0] == 1
        packet(b"S")
        assert reply(b"S") == b"\x01"
        return struct.unpack_from(">" + fmt, reply(b"U"), 1)


def test_tool_analog_inputs_are_served_where_a_controller_reports_them(
    sim: SimulatorHandle,
) -> None:
    sim.set_input("TAI1", 0.25)
    sim.set_input("AI1", 7.5)
    values = read_outputs(
        sim.host, "tool_analog_input0,tool_analog_input1,standard_analog_input1", "ddd"
    )
    assert values == (0.0, 0.25, 7.5)


def test_inputs_the_machine_drives_are_refused_naming_it(sim: SimulatorHandle) -> None:
    with pytest.raises(SimulatorError, match=r"DI1 is driven by the fusion machine \(busy\)"):
        sim.set_input("DI1", 1)
    with pytest.raises(SimulatorError, match="output"):
        sim.set_input("DO3", 1)
    with pytest.raises(SimulatorError, match="not a signal name"):
        sim.set_input("X-1", 1)


def test_without_the_machine_its_inputs_are_free() -> None:
    with simulator(extra_args=["--no-machine"]) as s:
        s.set_input("DI0", 1)
        s.set_input("DI3", 1)
        r = RTDEReceiveInterface(s.host)
        try:
            wait_until(lambda: r.getActualDigitalInputBits() == 0b1001, what="inputs")
        finally:
            r.disconnect()
        with pytest.raises(SimulatorError, match="no fusion machine"):
            s.machine()


def test_machine_io_option_rewires_the_signals() -> None:
    with simulator(extra_args=["--machine-io", "start=DO4,ready=DI6,error=CI0"]) as s:
        s.set_input("DI0", 1)
        io = s.machine()["io"]
        assert {k: v["signal"] for k, v in io.items()} == {
            "start": "DO4",
            "ready": "DI6",
            "busy": "DI1",
            "done": "DI2",
            "error": "CI0",
        }
        assert io["ready"]["value"] == 1


def test_place_object_puts_an_object_at_a_slot_and_refuses_bad_ones(
    sim: SimulatorHandle, layout: Layout
) -> None:
    sim.place_object("bead-x", "bead", "tray", "C4")
    obj = sim.objects()["bead-x"]
    tray = layout.station("tray")
    grip = pose_of(obj)
    assert np.allclose(grip.position, tray.grip_pose("C4").position, atol=1e-9)
    assert np.allclose(grip.rotation, tray.grip_pose("C4").rotation, atol=1e-9)
    assert (obj["station"], obj["slot"], obj["contents"]) == ("tray", "C4", None)
    refusals = [
        (("other", "bead", "tray", "C4"), "taken by bead-x"),
        (("c", "crucible", "tray", "A1"), "holds beads"),
        (("c", "crucible", "shelf", "A1"), "no station 'shelf'"),
        (("c", "crucible", "rack", "E1"), "A1..D4"),
        (("c", "anvil", "rack", "A1"), "unknown object kind"),
    ]
    for args, message in refusals:
        with pytest.raises(SimulatorError, match=message):
            sim.place_object(*args)
    sim.place_object("empty", "crucible", "rack", "D4", "-")
    assert sim.objects()["empty"]["contents"] is None


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fxcell", "sim", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_cli_set_input_place_object_inject_and_machine(sim: SimulatorHandle) -> None:
    done = run_cli("set-input", "--host", sim.host, "7", "1")
    assert (done.returncode, done.stdout.strip()) == (0, "DI7 = 1")
    refused = run_cli("set-input", "--host", sim.host, "DI2", "1")
    assert refused.returncode == 1
    assert "driven by the fusion machine (done)" in refused.stderr
    placed = run_cli("place-object", "--host", sim.host, "crucible-A1", "crucible", "machine", "A4")
    assert (placed.returncode, placed.stdout.strip()) == (0, "crucible-A1 placed in machine A4")
    injected = run_cli("inject", "--host", sim.host, "door_open")
    assert injected.returncode == 0
    shown = run_cli("machine", "--host", sim.host)
    assert shown.returncode == 0
    assert '"door_open": true' in shown.stdout
    assert '"crucible": "crucible-A1"' in shown.stdout
    assert sim.objects()["crucible-A1"]["slot"] == "A4"


def test_cli_refuses_a_bad_crucibles_option() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "fxcell.sim", "--host", free_loopback_host(), "--crucibles", "A9"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 2
    assert "A1..D4" in done.stderr
