"""The fusion machine the Ned2 simulator hosts (``--machine``), seen through Niryo's own
client, pyniryo 1.2.5, unmodified: the machine's signals are the Ned2's pins (start DO1;
ready DI1, busy DI2, done DI3, error DI5), a start pulse fuses the crucibles standing in its
positions and pours their beads into the moulds, and its faults (machine_error,
machine_reset, door_open, door_close) show on the pins as on the UR simulator's."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import pytest
from pyniryo import NiryoRobot, NiryoRobotException, PinID, PinState

from fxcell.errors import InvalidArgumentError
from fxcell.testing import injected_faults
from fxcell.testing.ned2 import TEST_TIME_SCALE, Ned2SimulatorHandle, ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

# 10 s x 0.05: half a second of fusion, as long for cooling
MACHINE = ["--machine", "--fusion-time", "10", "--cooling-time", "10"]
PHASE = 10 * TEST_TIME_SCALE
READY, BUSY, DONE, ERROR = PinID.DI1, PinID.DI2, PinID.DI3, PinID.DI5
START = PinID.DO1


def wait_until(predicate: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


@pytest.fixture
def sim() -> Iterator[Ned2SimulatorHandle]:
    with ned2_simulator(extra_args=[*MACHINE, "--crucibles", "2"]) as handle:
        yield handle


@pytest.fixture
def robot(sim: Ned2SimulatorHandle) -> Iterator[NiryoRobot]:
    r = NiryoRobot(sim.host, verbose=False)
    try:
        yield r
    finally:
        r.close_connection()


def pins(robot: NiryoRobot) -> tuple[bool, bool, bool, bool]:
    """ready, busy, done, error as the robot reads its inputs."""
    levels = {p.name: p.state == PinState.HIGH for p in robot.get_digital_io_state()}
    return (levels["DI1"], levels["DI2"], levels["DI3"], levels["DI5"])


def test_a_start_pulse_fuses_the_loaded_crucibles_into_beads_in_their_moulds(
    sim: Ned2SimulatorHandle, robot: NiryoRobot
) -> None:
    assert pins(robot) == (True, False, False, False)  # idle: ready
    sim.place_object("crucible-A1", "crucible", "machine", "A1")  # loaded, as the robot would
    sim.place_object("crucible-A2", "crucible", "machine", "A3")
    wait_until(lambda: sim.machine()["state"] == "loaded", "the machine to sense its crucibles")
    robot.digital_write(START, PinState.HIGH)
    wait_until(lambda: pins(robot)[1], "busy")
    assert pins(robot)[0] is False  # not ready while fusing
    robot.digital_write(START, PinState.LOW)
    wait_until(lambda: pins(robot)[2], "done", timeout=20 * PHASE + 10)
    assert pins(robot) == (False, False, True, False)
    objects = sim.objects()
    for crucible, mould in (("crucible-A1", "A1"), ("crucible-A2", "A3")):
        bead = objects[f"{crucible}.bead"]
        assert (bead["kind"], bead["station"], bead["slot"]) == ("bead", "moulds", mould)
        assert bead["contents"] == "sample"
        assert objects[crucible]["contents"] is None  # fused: empty now
    # done until the moulds are empty, then ready again (the crucibles still loaded)
    for n, bead in enumerate(("crucible-A1.bead", "crucible-A2.bead")):
        sim.place_object(bead, "bead", "tray", f"A{n + 1}")
    wait_until(lambda: pins(robot) == (True, False, False, False), "ready after unloading")


def test_a_start_pulse_with_nothing_loaded_is_ignored(
    sim: Ned2SimulatorHandle, robot: NiryoRobot
) -> None:
    robot.digital_write(START, PinState.HIGH)
    wait_until(lambda: "start ignored: no crucible loaded" in " ".join(sim.machine()["log"]), "log")
    assert pins(robot) == (True, False, False, False)


def test_door_open_reports_error_and_a_cycle_aborts_without_beads(
    sim: Ned2SimulatorHandle, robot: NiryoRobot
) -> None:
    with injected_faults("the machine's door opened"):
        sim.inject("door_open")
    assert pins(robot) == (False, False, False, True)
    sim.inject("door_close")
    assert pins(robot) == (True, False, False, False)
    sim.place_object("crucible-A1", "crucible", "machine", "A2")
    wait_until(lambda: sim.machine()["state"] == "loaded", "loaded")
    robot.digital_write(START, PinState.HIGH)
    wait_until(lambda: pins(robot)[1], "busy")
    with injected_faults("the machine's door opened"):
        sim.inject("door_open")  # mid-cycle
    assert pins(robot) == (False, False, False, True)
    sim.inject("door_close")
    assert pins(robot) == (False, False, False, True)  # the abort stays latched
    sim.inject("machine_reset")
    wait_until(lambda: pins(robot) == (True, False, False, False), "ready after the reset")
    assert "crucible-A1.bead" not in sim.objects()


def test_an_injected_machine_error_latches_until_reset(
    sim: Ned2SimulatorHandle, robot: NiryoRobot
) -> None:
    with injected_faults("a machine error"):
        sim.inject("machine_error")
    assert pins(robot) == (False, False, False, True)
    assert sim.machine()["fault"] == "machine error (injected)"
    sim.inject("machine_reset")
    assert pins(robot) == (True, False, False, False)


def test_the_machines_inputs_are_its_own(sim: Ned2SimulatorHandle, robot: NiryoRobot) -> None:
    for pin in ("DI1", "DI2", "DI3", "DI5"):
        with pytest.raises(InvalidArgumentError, match="driven by the fusion machine"):
            sim.set_input(pin, 0)
    sim.set_input("DI4", 1)  # the tool connector's input is free
    assert robot.digital_read(PinID.DI4) == PinState.HIGH
    with pytest.raises(NiryoRobotException):
        robot.digital_write(READY, PinState.LOW)  # an input, as on the robot


def test_a_bare_ned2_simulator_has_no_machine_and_every_pin_free() -> None:
    with ned2_simulator() as bare:
        with pytest.raises(InvalidArgumentError, match="no fusion machine"):
            bare.inject("door_open")
        with pytest.raises(InvalidArgumentError, match="no fusion machine"):
            bare.machine()
        bare.set_input("DI1", 1)
        assert bare.state()["digital_in"]["DI1"] is True
