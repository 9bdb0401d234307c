"""A Cell on a Ned2 sees its link go down and reaches the robot again by itself, as on the
UR3e: a network drop, a robot that stops publishing (a stalled robot computer) and a power
loss each take the Cell to ``disconnected`` with the reason logged as a link loss; once the
robot answers again the Cell is back where the robot is (ready after a drop or a stall, idle
and needing init after a power loss, which costs a Ned2 its calibration)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Iterator

import pytest

from fxcell import Cell, CellState
from fxcell.config import CellConfig
from fxcell.errors import FxcellError, InvalidStateError
from fxcell.link.ned2.link import STALE_AFTER
from fxcell.settling import REST_VELOCITY
from fxcell.testing import injected_faults
from fxcell.testing.faults import watching
from fxcell.testing.ned2 import Ned2SimulatorHandle, ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

# rad: where a Ned2 move ends by the simulator's own joints. The cell ends a Ned2 move with a
# stop once its joint states show the arm settled (SETTLE_POSITION, SETTLE_VELOCITY); the
# arm goes on until the stop arrives (1.2e-6 rad past the target seen on 3 busy workers).
ARRIVED = 1e-5
TARGET = [0.4, -0.2, 0.1, 0.3, -0.4, 0.2]
BACK = [0.2, -0.1, 0.0, 0.1, -0.2, 0.1]
REACHED = 10.0  # s: the Cell sees the link down, or the robot again, well within this


@pytest.fixture
def sim() -> Iterator[Ned2SimulatorHandle]:
    with ned2_simulator(time_scale=1.0, calibrated=True) as handle:
        yield handle


@pytest.fixture
async def cell(sim: Ned2SimulatorHandle) -> AsyncIterator[Cell]:
    config = CellConfig.from_dict({"robot": {"kind": "ned2"}, "tool": {"tcp": [0.0] * 6}})
    async with Cell(config=config, host=sim.host, record=None) as c:
        await c.init()
        yield c


async def _down_then(cell: Cell, *states: CellState) -> CellState:
    await cell.wait_for_state(CellState.DISCONNECTED, timeout=REACHED)
    return await cell.wait_for_state(*states, timeout=REACHED)


async def test_after_a_network_drop_the_cell_reaches_the_ned2_again_and_moves(
    cell: Cell, sim: Ned2SimulatorHandle, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, "fxcell.link"), injected_faults("the network drops"):
        sim.inject("drop_connection")
        back = await _down_then(cell, CellState.EXTERNAL_CONTROL_READY)
    assert back is CellState.EXTERNAL_CONTROL_READY
    assert cell.link_losses == 1
    assert any(f"robot link to {sim.host} down" in r.getMessage() for r in caplog.records)
    await cell.move_joint(TARGET)
    assert sim.state()["joints"] == pytest.approx(TARGET, abs=ARRIVED)


async def test_a_ned2_that_stops_publishing_counts_as_down_until_it_publishes_again(
    cell: Cell, sim: Ned2SimulatorHandle, caplog: pytest.LogCaptureFixture
) -> None:
    with (
        caplog.at_level(logging.WARNING, "fxcell.link"),
        injected_faults("the robot's computer stalls"),
    ):
        sim.inject("stall", 3 * STALE_AFTER)
        await _down_then(cell, CellState.EXTERNAL_CONTROL_READY)
    said = [r.getMessage() for r in caplog.records if "down" in r.getMessage()]
    assert len(said) == 1, said
    assert "no joint state for" in said[0]
    await cell.move_joint(BACK)
    assert sim.state()["joints"] == pytest.approx(BACK, abs=ARRIVED)


async def test_a_ned2_back_from_a_power_loss_needs_init_before_it_moves(
    cell: Cell, sim: Ned2SimulatorHandle
) -> None:
    with injected_faults("the robot goes dark, then boots again"):
        sim.inject("power_loss")
        await cell.wait_for_state(CellState.DISCONNECTED, timeout=REACHED)
        sim.inject("power_restore")
        assert await cell.wait_for_state(CellState.IDLE, timeout=REACHED) is CellState.IDLE
    with pytest.raises(InvalidStateError, match="init"):
        await cell.move_joint(TARGET)
    assert sim.state()["calibrated"] is False
    await cell.init()  # calibrates it again
    await cell.move_joint(TARGET)
    assert sim.state()["joints"] == pytest.approx(TARGET, abs=ARRIVED)


@pytest.mark.injects_faults("it reads what a watch of its own reports of the drop")
async def test_an_unplanned_drop_of_a_ned2_link_is_what_the_fault_watch_reports(
    cell: Cell, sim: Ned2SimulatorHandle
) -> None:
    # what the suite's watch of every system test sees of a Ned2: the simulator's faults
    # and the link's losses, each failing a test that did not inject it
    with watching([sim._sim]) as watch:
        sim.inject("drop_connection")
        await _down_then(cell, CellState.EXTERNAL_CONTROL_READY)
        unplanned = watch.unplanned()
    assert "simulator: injected drop_connection" in unplanned
    assert [u for u in unplanned if u.startswith("link down: ")] != [], unplanned


async def test_a_move_the_ned2_still_runs_after_a_drop_is_stopped_before_the_link_is_up(
    cell: Cell, sim: Ned2SimulatorHandle, caplog: pytest.LogCaptureFixture
) -> None:
    # A Ned2 holds the whole trajectory and finishes it without its client: the link that
    # lost track of it stops it, and is up again only once the arm is idle.
    far = [-1.2, 0.3, -0.5, 1.0, 0.8, 1.0]
    move = asyncio.create_task(cell.move_joint(far))
    with caplog.at_level(logging.WARNING, "fxcell.link"), injected_faults("the network drops"):
        await asyncio.to_thread(sim.wait_for, "moving", True)
        sim.inject("drop_connection")
        with pytest.raises(FxcellError):
            await move
        await _down_then(cell, CellState.EXTERNAL_CONTROL_READY)
    # up again only with the arm at rest, by the robot's own joint states
    with cell.robot_states(maxsize=16) as states:
        first = await states.next_within(1.0)
        samples = [first, *[await states.next_within(1.0) for _ in range(4)]]
    assert all(max(map(abs, s.actual_qd)) < REST_VELOCITY for s in samples)
    assert all(s.actual_q == first.actual_q for s in samples)
    state = sim.state()
    assert state["moving"] is False  # stopped, not left to run its course
    assert max(abs(a - b) for a, b in zip(state["joints"], far, strict=True)) > 0.05
    assert any("still runs a command" in r.getMessage() for r in caplog.records)
    await cell.move_joint(TARGET)  # and the next move is taken
    assert sim.state()["joints"] == pytest.approx(TARGET, abs=ARRIVED)


async def test_a_ned2_move_whose_joint_states_stop_is_stopped_while_the_robot_still_stalls(
    cell: Cell, sim: Ned2SimulatorHandle
) -> None:
    # A Ned2 holds the whole trajectory and runs it without its client. When its joint
    # states stop (its computer stalls, its services still answer), the move is stopped at
    # the kind's state patience, not left to run unwatched until the robot publishes again.
    far = [-1.2, 0.3, -0.5, 1.0, 0.8, 1.0]
    stall = 6.0  # s: longer than the move would take from where the stall catches it
    loop = asyncio.get_running_loop()
    move = asyncio.create_task(cell.move_joint(far))
    with injected_faults("the robot's computer stops publishing during a move"):
        await asyncio.to_thread(sim.wait_for, "moving", True)
        sim.inject("stall", stall)
        stalled_at = loop.time()
        with pytest.raises(FxcellError):
            await move
        await asyncio.to_thread(sim.wait_for, "moving", False, stall)
        stopped_after = loop.time() - stalled_at
        await _down_then(cell, CellState.EXTERNAL_CONTROL_READY)
    state = sim.state()
    assert max(abs(a - b) for a, b in zip(state["joints"], far, strict=True)) > 0.05
    assert stopped_after < stall - 1.0, f"the arm ran on for {stopped_after:.1f} s"
    await cell.move_joint(TARGET)  # and the next move is taken
    assert sim.state()["joints"] == pytest.approx(TARGET, abs=ARRIVED)
