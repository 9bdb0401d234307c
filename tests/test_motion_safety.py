"""An aborted move never keeps moving: the link process brakes by itself.

Each test runs a real move (ur_rtde in the link process, servoJ into the simulator) and
judges the arm by the simulator's own joint state (its control port), not by what fxcell
believes: after the move's caller hears of the abort, the simulated arm stands still.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator, Sequence

import numpy as np
import pytest
from waiting import controller_time_passed, until, wait_until

from fxcell.cell import Cell
from fxcell.cell.statemachine import CellState
from fxcell.config import CellConfig
from fxcell.errors import (
    ConnectionLostError,
    InvalidStateError,
    MoveStoppedError,
    NotInRemoteControlError,
)
from fxcell.link.beats import LOOP_STALL_AFTER
from fxcell.link.contract import Guard
from fxcell.link.follower import brake_duration
from fxcell.link.process import BUSY_CLIENT_LIMIT, process_runs
from fxcell.testing import SimulatorHandle, simulator

CONFIG = CellConfig.load()
WORK = [0.4, -1.4, 1.6, -1.8, -1.57, 0.0]
FAR = [2.4, -1.4, 1.6, -1.8, -1.57, 0.0]  # 2 rad of base rotation away


@pytest.fixture(scope="module")
def shared() -> Iterator[SimulatorHandle]:
    with simulator() as handle:
        yield handle


def _fresh(handle: SimulatorHandle, joints: Sequence[float]) -> None:
    if str(handle.state()["safety_mode"]) != "NORMAL" or handle.state()["remote_control"] is False:
        handle.inject("remote_control")
    # the simulator places only an arm with no joint speed at all: the previous test's arm,
    # braked to under 1e-6 rad/s, may still be settling on its last servo target
    wait_until(
        lambda: not any(handle.state()["qd"]), timeout=10.0, what="the previous test's arm at rest"
    )
    handle.set_joints(list(joints))


@contextlib.asynccontextmanager
async def ready_cell(handle: SimulatorHandle) -> AsyncIterator[Cell]:
    await asyncio.to_thread(_fresh, handle, WORK)
    async with Cell(handle.host, config=CONFIG) as cell:
        await cell.init()
        await cell.set_velocity_factor(0.3)
        yield cell


async def _moving(cell: Cell, speed: float = 0.2, within: float = 5.0) -> None:
    async with asyncio.timeout(within):
        with cell.robot_states() as states:
            async for s in states:
                if abs(s.actual_qd[0]) > speed:
                    return


def _until_at_rest(handle: SimulatorHandle, within: float = 5.0) -> None:
    """Wait until the simulated arm's own joint speeds are zero."""
    deadline = time.monotonic() + within
    while max(map(abs, handle.state()["qd"])) > 1e-6:
        assert time.monotonic() < deadline, "the simulated arm did not come to rest"
        time.sleep(0.01)


def _sim_motion(handle: SimulatorHandle, over: float = 0.05) -> float:
    """How far (rad, largest joint) the simulated arm moves during ``over`` seconds of its
    controller's own clock (a simulator starved by a busy machine still gets them)."""
    q0 = np.array(handle.state()["q"])
    controller_time_passed(handle, over)
    return float(np.max(np.abs(np.array(handle.state()["q"]) - q0)))


@pytest.mark.injects_faults("a stalled state stream")
async def test_a_stalled_state_stream_brakes_the_move_before_its_caller_hears(
    shared: SimulatorHandle, caplog: pytest.LogCaptureFixture
) -> None:
    async with ready_cell(shared) as cell:
        move = asyncio.create_task(cell.move_joint(FAR))
        await _moving(cell)
        q_at_stall = np.array(shared.state()["q"])
        await asyncio.to_thread(shared.inject, "stall_rtde", 0.5)
        with pytest.raises(ConnectionLostError):
            await move
        # the arm stood still when the caller heard (the simulator's own joints) ...
        assert await asyncio.to_thread(_sim_motion, shared, 0.05) < 1e-4
        # ... having braked where the stall caught it, not run on to the target
        travelled = float(np.max(np.abs(np.array(shared.state()["q"]) - q_at_stall)))
        assert travelled < 0.4, f"the arm went on for {travelled:.3f} rad after the stall"
        assert abs(shared.state()["q"][0] - FAR[0]) > 0.5
        # the stall ends: the link comes back, the arm at rest
        await cell.wait_for_state(
            CellState.EXTERNAL_CONTROL_READY, CellState.PROGRAM_STOPPED, timeout=10
        )
    # the hole in the state stream is on record (the recorder keeps fxcell's log records),
    # and so is the link process's own brake (a fault the fault watch counts)
    assert any("state stream gap" in r.getMessage() for r in caplog.records)
    braked = "braked a move by itself: state_stalled"
    assert any(braked in r.getMessage() for r in caplog.records)


async def test_a_late_event_loop_does_not_stop_a_healthy_move(shared: SimulatorHandle) -> None:
    # 300 ms without the loop (a busy machine, a long callback) is three beat timeouts: the
    # beats come from a thread, so the link process keeps streaming and the move arrives.
    async with ready_cell(shared) as cell:
        move = asyncio.create_task(cell.move_joint(FAR))
        await _moving(cell)
        time.sleep(0.3)  # noqa: ASYNC251 (blocks this event loop on purpose)
        result = await move
        assert not result.stopped
        assert result.joint_error < 1e-3


def _hold_the_gil(seconds: float) -> float:
    """Hold the GIL for ``seconds`` of wall-clock time; the time it was held. Python lets
    another thread that asks for the GIL have it after the switch interval (5 ms): raised
    above ``seconds`` for the while, this thread keeps it until its deadline, as one long C
    call would, but for a given time, not for a given amount of work (a sort calibrated
    beforehand took three times as long when a busy machine took the CPU away)."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(10 * seconds)
    try:
        started = time.perf_counter()
        deadline = started + seconds
        while time.perf_counter() < deadline:
            pass
        return time.perf_counter() - started
    finally:
        sys.setswitchinterval(interval)


async def test_a_loop_holding_the_gil_a_while_does_not_stop_a_healthy_move(
    shared: SimulatorHandle,
) -> None:
    # 150 ms with the GIL kept (a long C call; on a busy machine: a thread descheduled while
    # it holds it): the beat thread cannot beat, but the kernel says the process runs, so
    # the link process gives it BUSY_CLIENT_LIMIT instead of braking after 100 ms.
    async with ready_cell(shared) as cell:
        move = asyncio.create_task(cell.move_joint(FAR))
        await _moving(cell)
        held = _hold_the_gil(0.15)
        assert 0.1 < held < BUSY_CLIENT_LIMIT, f"held the GIL {held:.3f} s"
        result = await move
        assert not result.stopped
        assert result.joint_error < 1e-3


def test_a_stopped_process_is_told_from_a_running_one() -> None:
    assert process_runs(os.getpid())
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        assert process_runs(child.pid)
        child.send_signal(signal.SIGSTOP)  # delivered asynchronously
        wait_until(lambda: not process_runs(child.pid), 5.0, "the child shown as stopped")
        child.send_signal(signal.SIGCONT)
        child.kill()
        child.wait(5)
        assert not process_runs(child.pid)  # reaped: gone
    finally:
        child.kill()
        child.wait(5)


@pytest.mark.injects_faults("the cell's event loop frozen for 1.5 s")
async def test_an_event_loop_stalled_for_long_brakes_the_move_by_itself(
    shared: SimulatorHandle,
) -> None:
    # Nothing supervises a move while the loop stands still: after LOOP_STALL_AFTER the
    # beats stop and the link process brakes, with the cell still frozen.
    async with ready_cell(shared) as cell:
        move = asyncio.create_task(cell.move_joint(FAR))
        await _moving(cell)
        q_at_stall = np.array(shared.state()["q"])
        time.sleep(LOOP_STALL_AFTER + 1.0)  # noqa: ASYNC251 (blocks the loop on purpose)
        assert _sim_motion(shared, 0.05) < 1e-4  # at rest before the loop ran again
        travelled = float(np.max(np.abs(np.array(shared.state()["q"]) - q_at_stall)))
        assert travelled < 1.0, f"the arm went on for {travelled:.3f} rad"
        assert abs(shared.state()["q"][0] - FAR[0]) > 0.5
        with pytest.raises(MoveStoppedError, match="stopped"):
            await move


async def test_a_link_process_frozen_mid_move_resumes_without_a_setpoint_jump(
    shared: SimulatorHandle,
) -> None:
    # Frozen for 60 ms at ~1 rad/s (SIGSTOP: a swap storm, a debugger), the link process
    # finds 30 state samples queued. Catching up all of that time at once would move the
    # target ~66 mrad within one controller cycle, which the controller refuses with a
    # protective stop (without CATCH_UP and the clock bound: 1 of 2 runs); the path waits
    # the backlog out instead. A burst answered sample by sample: test_link_hold.
    async with ready_cell(shared) as cell:
        await cell.set_velocity_factor(1.0)
        move = asyncio.create_task(cell.move_joint(FAR))
        await _moving(cell, speed=0.9)
        pid = cell._link().pid
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        try:
            time.sleep(0.06)  # noqa: ASYNC251 (the cell waits as long: nothing to hear)
        finally:
            os.kill(pid, signal.SIGCONT)
        result = await move
        assert result.joint_error < 1e-3
        assert str(shared.state()["safety_mode"]) == "NORMAL"
        assert await asyncio.to_thread(_sim_motion, shared, 0.05) < 1e-4


@pytest.mark.injects_faults("the cell's side of the link closed mid-move")
async def test_a_killed_cell_process_leaves_no_arm_moving(shared: SimulatorHandle) -> None:
    # The cell side vanishes mid-move (its socket to the link process closes): the link
    # brakes the trajectory along its path before it exits.
    async with ready_cell(shared) as cell:
        move = asyncio.create_task(cell.move_joint(FAR))
        await _moving(cell)
        link = cell._link()
        assert link._writer is not None
        link._writer.abort()  # as if the process holding it died
        with pytest.raises(ConnectionLostError):  # typed, whatever the link was doing
            await move
        await asyncio.to_thread(_until_at_rest, shared)
        assert await asyncio.to_thread(_sim_motion, shared, 0.05) < 1e-4
        assert abs(shared.state()["q"][0] - FAR[0]) > 0.5


@pytest.mark.injects_faults("the pendant switched to Local")
async def test_local_control_brakes_a_running_move_and_refuses_new_ones(
    shared: SimulatorHandle,
) -> None:
    async with ready_cell(shared) as cell:
        move = asyncio.create_task(cell.move_joint(FAR))
        await _moving(cell)
        await asyncio.to_thread(shared.inject, "local_control")
        with pytest.raises(NotInRemoteControlError, match="Local control"):
            await move
        assert await asyncio.to_thread(_sim_motion, shared, 0.05) < 1e-4
        assert abs(shared.state()["q"][0] - FAR[0]) > 0.5
        with pytest.raises((NotInRemoteControlError, InvalidStateError)):
            await cell.move_joint(WORK)
        await asyncio.to_thread(shared.inject, "remote_control")
        # the cell polls the switch every 0.25 s
        await until(lambda: not cell.local_control, "the cell to see Remote control", 5.0)


def test_the_link_brake_duration_respects_the_braking_limits() -> None:
    guard = Guard(brake_acceleration=(4.0,) * 6, brake_jerk=40.0)
    # 1 rad/s: decelerating at most 4 rad/s² needs ≥ 0.25 s; the cosine profile's peak
    # deceleration π·v/(2T) stays within 4 rad/s²
    t = brake_duration([1.0, 0, 0, 0, 0, 0], guard)
    assert np.pi * 1.0 / (2 * t) <= 4.0 + 1e-12
    assert np.pi**2 * 1.0 / (2 * t**2) <= 40.0 + 1e-9
    assert t < 0.5
    assert brake_duration([0.0] * 6, guard) == pytest.approx(0.004)


def test_a_tiny_speed_factor_is_refused_before_planning() -> None:
    from fxcell.errors import InvalidFactorError
    from fxcell.motion.moves import MotionController

    moves = MotionController(CONFIG)
    with pytest.raises(InvalidFactorError, match=r"\[0.01, 1\]"):
        moves.factors(1e-5, None)
    with pytest.raises(InvalidFactorError):
        moves.factors(None, 5e-324)
    assert moves.factors(0.01, 0.01) == (0.01, 0.01)


def test_a_move_longer_than_the_limit_is_refused_before_it_is_sampled() -> None:
    from fxcell.errors import MoveTooLongError
    from fxcell.link.capabilities import UR3E
    from fxcell.motion.trajectory import Limits, rest_to_rest

    slow = Limits.from_config(CONFIG.limits, 0.01, 0.01, period=UR3E.sample_period)
    assert slow.max_duration == CONFIG.limits.max_move_duration == 120.0
    start = np.array(WORK)
    with pytest.raises(MoveTooLongError, match="longer than the 120 s allowed"):
        rest_to_rest(start, start + np.array([4.0, 0, 0, 0, 0, 0]), slow)
    assert rest_to_rest(start, start + np.array([0.5, 0, 0, 0, 0, 0]), slow).duration < 120.0
