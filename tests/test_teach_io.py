"""cell.io, freedrive and teach-in against the simulator, read back by ur_rtde's own clients."""

from __future__ import annotations

import asyncio
import sys
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from fxcell import Cell
from fxcell.cell.statemachine import CellState
from fxcell.config import CellConfig
from fxcell.errors import (
    InvalidArgumentError,
    InvalidStateError,
    IOTimeoutError,
    UnknownPositionError,
    UnknownSignalError,
)
from fxcell.testing import SimulatorHandle, brisk, simulator

WORK = [0.0, -1.2, 1.2, -1.57, -1.57, 0.0]


@pytest.fixture(scope="module")
def sim() -> Iterator[SimulatorHandle]:
    with simulator() as s:
        yield s


@pytest.fixture
def config(tmp_path: Path) -> CellConfig:
    base = CellConfig.load()
    io = base.io.model_copy(update={"signals": {**base.io.signals, "door_sensor": "DI5"}})
    return brisk(base).model_copy(update={"positions_file": tmp_path / "positions.yaml", "io": io})


@pytest.fixture
async def cell(sim: SimulatorHandle, config: CellConfig) -> AsyncIterator[Cell]:
    async with Cell(host=sim.host, config=config) as c:
        await c.init()
        yield c
        if c.state is CellState.FREEDRIVE:
            await c.freedrive_stop()


async def _run_python(code: str) -> str:
    """Run ``code`` in a separate interpreter (ur_rtde clients hold the GIL while connecting)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        code,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode == 0, err.decode()
    return out.decode().strip()


async def test_an_output_set_by_name_is_read_by_ur_rtde_receive_interface(
    sim: SimulatorHandle, cell: Cell
) -> None:
    for value in (True, False):
        await cell.io_set("machine_start", value)
        assert cell.io.get("machine_start") is value
        seen = await _run_python(
            "import rtde_receive\n"
            f"r = rtde_receive.RTDEReceiveInterface({sim.host!r})\n"
            "print(r.getDigitalOutState(0))\n"
            "r.disconnect()\n"
        )
        assert seen == str(value)
    assert (await cell.get_io())["machine_start"] is False


async def test_a_second_rtde_io_client_is_refused_as_on_a_real_controller(
    sim: SimulatorHandle, cell: Cell
) -> None:
    """fxcell's link owns the IO recipe's inputs; the controller lets one client own them."""
    await cell.io_set("machine_start", False)
    code = (
        "import rtde_io\n"
        f"try:\n    rtde_io.RTDEIOInterface({sim.host!r})\n"
        "except RuntimeError as exc:\n    print('refused:', exc)\n"
    )
    assert "already in use" in await _run_python(code)


# A wake-up from the state stream comes within a few 2 ms samples; a waiter that missed it
# would return only at its 30 s timeout. 2 s is the bound between the two, far above a
# busy machine's scheduling delays.
WAKE_UP_WITHIN = 2.0


async def _pending_through_samples(cell: Cell, waiting: asyncio.Task[float], name: str) -> None:
    """Fail unless ``waiting`` is still pending after 10 state samples in which ``name`` read
    False (the waiter reads every sample: it had 10 chances to return wrongly)."""
    signal = cell.io.signal(name)
    with cell.robot_states() as states:
        for _ in range(10):
            sample = await states.next_within(5.0)
            assert signal.read(sample) is False
            await asyncio.sleep(0)  # let the waiter read the same sample
    assert not waiting.done(), f"io_wait_for({name!r}, True) returned while it read False"


async def _woken_promptly(waiting: asyncio.Task[float]) -> float:
    """The waiter's result; fails if it needs more than WAKE_UP_WITHIN after the change."""
    try:
        return await asyncio.wait_for(asyncio.shield(waiting), WAKE_UP_WITHIN)
    except TimeoutError:
        waiting.cancel()
        await asyncio.gather(waiting, return_exceptions=True)
        raise AssertionError(
            f"io_wait_for did not return within {WAKE_UP_WITHIN} s of the signal reading True "
            "(the change did not wake it)"
        ) from None


async def test_wait_for_waits_while_the_signal_reads_false_and_wakes_when_it_changes(
    cell: Cell,
) -> None:
    await cell.io_set("machine_start", False)
    created = time.monotonic()
    waiting = asyncio.create_task(cell.io_wait_for("machine_start", True, timeout=30.0))
    await _pending_through_samples(cell, waiting, "machine_start")
    await cell.io_set("machine_start", True)  # returns once a sample shows it True
    waited = await _woken_promptly(waiting)
    assert 0.0 < waited <= time.monotonic() - created  # the seconds it actually waited
    await cell.io_set("machine_start", False)


async def test_an_input_set_from_outside_wakes_wait_for(sim: SimulatorHandle, cell: Cell) -> None:
    await asyncio.to_thread(sim.set_input, "DI5", 0)
    await cell.io_wait_for("door_sensor", False, timeout=5.0)  # the cell has seen it low
    waiting = asyncio.create_task(cell.io_wait_for("door_sensor", True, timeout=30.0))
    await _pending_through_samples(cell, waiting, "door_sensor")
    await asyncio.to_thread(sim.set_input, "DI5", 1)  # as `fxcell sim set-input DI5 1` does
    await _woken_promptly(waiting)
    assert cell.io.get("door_sensor") is True
    await asyncio.to_thread(sim.set_input, "DI5", 0)


async def test_wait_for_gives_a_typed_timeout(cell: Cell) -> None:
    with pytest.raises(IOTimeoutError, match="machine_done"):
        await cell.io_wait_for("machine_done", True, timeout=0.1)


async def test_bad_signal_names_and_values_are_refused_before_anything_is_sent(
    cell: Cell,
) -> None:
    with pytest.raises(UnknownSignalError, match="known: door_sensor, machine_busy, machine_done"):
        await cell.io_set("lamp", True)
    with pytest.raises(InvalidArgumentError, match="is an input"):
        await cell.io_set("machine_done", True)
    with pytest.raises(InvalidArgumentError, match="digital"):
        await cell.io_set("machine_start", 0.5)


async def test_a_position_taught_after_a_freedrive_push_is_reached_again(
    sim: SimulatorHandle, cell: Cell
) -> None:
    await cell.move_joint(WORK)
    async with cell.freedrive():
        assert cell.state is CellState.FREEDRIVE
        with pytest.raises(InvalidStateError):
            await cell.go_home()
        await asyncio.to_thread(sim.push, [0.04, -0.03, -0.05])
        taught = await cell.teach("hand_guided")
    assert cell.state is CellState.EXTERNAL_CONTROL_READY
    await cell.go_home()
    result = await cell.move_to("hand_guided")
    assert cell.robot_state is not None
    reached = np.array(cell.robot_state.actual_tcp_pose[:3])  # as the controller reports it
    assert np.linalg.norm(reached - np.array(taught["pose"][:3])) < 1e-5
    assert result.joint_error < 1e-5


async def test_pushing_outside_freedrive_is_refused(sim: SimulatorHandle, cell: Cell) -> None:
    from fxcell.errors import SimulatorError

    with pytest.raises(SimulatorError, match="not in freedrive"):
        await asyncio.to_thread(sim.push, [0.01, 0.0, 0.0])


async def test_unknown_position_names_list_the_known_ones(cell: Cell) -> None:
    await cell.teach("p1")
    with pytest.raises(UnknownPositionError, match=r"known: p1\)"):
        await cell.move_to("p2")
    with pytest.raises(InvalidArgumentError):
        await cell.teach("no spaces")


async def test_re_teaching_keeps_the_previous_value_and_survives_a_restart(
    sim: SimulatorHandle, cell: Cell, config: CellConfig
) -> None:
    # from a pose of its own: the simulator's arm starts straight up, where 2 cm higher is
    # out of reach (the test passed only after another test had moved the arm)
    await cell.move_joint(WORK)
    first = await cell.teach("station")
    await cell.move_distance([0.0, 0.0, 0.02])
    second = await cell.teach("station")
    stored = yaml.safe_load(config.positions_file.read_text())["positions"]["station"]
    assert stored["joints"] == pytest.approx(second["joints"])
    assert stored["previous"]["joints"] == pytest.approx(first["joints"])
    async with Cell(host=sim.host, config=config) as again:
        positions = await again.get_positions()
    assert positions["station"]["pose"] == pytest.approx(second["pose"])


async def test_re_teaching_a_rack_frame_shifts_every_slot(cell: Cell, config: CellConfig) -> None:
    rack = cell.layout.station("rack")
    before = {slot: rack.seat(slot) for slot in rack.slots}
    # Points taught 3.5 cm higher (the fingers cannot touch the rack's seats in the model).
    shift = np.array([0.01, -0.015, 0.035])
    frame = rack.config.frame
    down = rack.grip_pose("A1").rotation
    for n, point in enumerate(("xy_point", "origin", "x_point")):
        target = np.asarray(getattr(frame, point)) + shift
        await cell.move_pose(list(target) + list(_quaternion(down)))
        answer = await cell.teach_frame_point("rack", point)
        # The frame changes only once its three points are re-taught.
        assert answer["applied"] is (n == 2)
        assert len(answer["pending"]) == (2 - n if n < 2 else 0)
        if n < 2:
            assert np.allclose(cell.layout.station("rack").seat("A1"), before["A1"])
    after = cell.layout.station("rack")
    for slot, seat in before.items():
        assert np.allclose(after.seat(slot), seat + shift, atol=2e-5), slot
    layout = await cell.get_layout()
    assert np.allclose(
        layout["stations"]["rack"]["slots"]["D4"]["seat"], before["D4"] + shift, atol=2e-5
    )
    # The re-taught frame is what a new Cell plans with.
    fresh = Cell(config=config)
    assert np.allclose(fresh.layout.station("rack").seat("B2"), before["B2"] + shift, atol=2e-5)


def _quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    from fxcell.geometry import matrix_to_quaternion

    return matrix_to_quaternion(rotation)
