"""Cell behaviour on the in-process fake robot (``fxcell.testing.FakeRobot``): fast unit tests.

The same controller model as the simulator (modes, safety stops, control program, servoJ
tracking) without sockets or subprocesses; the system tests in test_cell.py and
test_moves.py run the same behaviour through ur_rtde against the simulator process.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np
import pytest

from fxcell import Cell, CellState, RobotMode
from fxcell.errors import (
    ConnectionLostError,
    InvalidStateError,
    LinkBrakeError,
    MoveStoppedError,
    NotInRemoteControlError,
    ProgramStoppedError,
    ProtectiveStopError,
    ProtectiveStopUnlockTooSoonError,
    TrackingError,
)
from fxcell.events import TransitionEvent
from fxcell.geometry import Pose
from fxcell.link.embedded import SimulatorState
from fxcell.protocol import ProgramState, RuntimeState
from fxcell.testing import FakeLink, FakeRobot

HOME = np.array([0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0])
QUARTER_TURN = HOME + np.array([math.pi / 2, 0, 0, 0, 0, 0])


@pytest.fixture
async def off_cell(fake_robot: FakeRobot) -> AsyncIterator[Cell]:
    """A Cell on the fake robot, left powered off."""
    async with Cell(link_factory=fake_robot.link_factory, record=None) as cell:
        await cell.wait_for_state(CellState.POWER_OFF)
        yield cell


async def _until(cell: Cell, predicate: Callable[[], bool], within: float = 5.0) -> None:
    """Wait (checking at every state sample) until ``predicate()`` holds."""
    async with asyncio.timeout(within):
        with cell.robot_states(maxsize=8) as states:
            while not predicate():
                await anext(states)


async def _moving(cell: Cell, joint: int = 0, speed: float = 0.2) -> None:
    """Wait until ``joint`` turns faster than ``speed`` rad/s."""

    def fast() -> bool:
        state = cell.robot_state
        return state is not None and abs(state.actual_qd[joint]) > speed

    await _until(cell, fast)


def _at_rest(robot: FakeRobot) -> bool:
    return bool(np.all(np.abs(robot.arm.qd) < 1e-3))


# ----------------------------------------------------------------- life cycle


async def test_the_fakes_state_has_the_simulators_schema(
    off_cell: Cell, fake_robot: FakeRobot
) -> None:
    assert set(fake_robot.state()) == SimulatorState.__required_keys__
    assert fake_robot.state()["control_script"] is False
    await off_cell.init()  # ur_rtde's control script running: the same key says so
    assert fake_robot.state()["control_script"] is True
    assert fake_robot.state()["robot_mode"] == "RUNNING"


def _transitions(cell: Cell) -> list[str]:
    """The destination of every transition the cell makes from now on, as it makes it."""
    seen: list[str] = []
    cell.bus.subscribe(lambda e: seen.append(e.dest) if isinstance(e, TransitionEvent) else None)
    return seen


async def test_init_walks_the_modes_to_external_control_and_sets_the_tool(
    off_cell: Cell, fake_robot: FakeRobot
) -> None:
    seen = _transitions(off_cell)
    await off_cell.init()
    assert off_cell.state is CellState.EXTERNAL_CONTROL_READY
    for state in ("powering_on", "idle", "running.program_stopped"):
        assert state in seen
    assert seen.index("powering_on") < seen.index("idle") < seen.index("running.program_stopped")
    assert seen[-1] == "running.external_control_ready"
    model = fake_robot.state()
    assert (model["robot_mode"], model["runtime_state"]) == ("RUNNING", "PLAYING")
    assert model["tcp"] == pytest.approx(list(off_cell.config.tool.tcp))
    assert model["payload"] == pytest.approx(off_cell.config.tool.payload)
    assert (await off_cell.get_program_state()).state is ProgramState.PLAYING


async def test_a_late_event_loop_still_sees_the_brief_booting_mode(
    off_cell: Cell, fake_robot: FakeRobot
) -> None:
    # POWER_ON lasts 50 cycles here (20 ms at 5x): a loop late by more than that once
    # advanced the idle controller past it in one step and never published it.
    seen = _transitions(off_cell)
    await off_cell._link().power(True)
    time.sleep(0.2)  # noqa: ASYNC251 (holds the event loop up on purpose)
    await off_cell.wait_for_state(CellState.IDLE, timeout=5)
    assert seen.index("powering_on") < seen.index("idle")


async def test_power_off_from_external_control_ends_the_program(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    await fake_cell.power_off()
    assert fake_cell.state is CellState.POWER_OFF
    assert await fake_cell.get_robot_mode() is RobotMode.POWER_OFF
    assert fake_robot.controller.runtime_state is RuntimeState.STOPPED
    assert not fake_cell._link().control_ready


async def test_external_control_stops_and_starts_again(fake_cell: Cell) -> None:
    await fake_cell.stop_external_control()
    assert fake_cell.state is CellState.PROGRAM_STOPPED
    await fake_cell.start_external_control()
    assert fake_cell.state is CellState.EXTERNAL_CONTROL_READY


async def test_the_background_local_remote_poll_is_not_counted_as_a_request_sent(
    fake_cell: Cell,
) -> None:
    """Tests of "a refused command sends nothing" count the link's requests; the cell's
    Local/Remote poll goes out at moments of its own (every REMOTE_POLL), so it must not
    count: on two busy workers it once fell inside such a window."""
    link = fake_cell._link()
    sent = link.messages_sent
    assert await link.remote_control() is True
    assert link.messages_sent == sent
    await link.program_status()
    assert link.messages_sent == sent + 1  # every other request counts


@pytest.mark.parametrize(
    ("command", "args"),
    [
        ("brake_release", ()),
        ("start_external_control", ()),
        ("unlock_protective_stop", ()),
        ("move_joint", (list(QUARTER_TURN),)),
        ("go_home", ()),
        ("freedrive_start", ()),
    ],
)
async def test_commands_are_refused_while_powered_off_without_reaching_the_robot(
    off_cell: Cell, fake_robot: FakeRobot, command: str, args: tuple[Any, ...]
) -> None:
    sent = off_cell._link().messages_sent
    with pytest.raises(InvalidStateError) as info:
        await getattr(off_cell, command)(*args)
    assert info.value.state == "power_off"
    assert off_cell._link().messages_sent == sent
    assert fake_robot.controller.robot_mode is RobotMode.POWER_OFF
    assert off_cell.state is CellState.POWER_OFF


async def test_local_control_refuses_power_on_and_the_robot_stays_off(
    off_cell: Cell, fake_robot: FakeRobot
) -> None:
    fake_robot.inject("local_control")
    assert await off_cell.is_in_remote_control() is False
    with pytest.raises(NotInRemoteControlError):
        await off_cell.power_on()
    assert fake_robot.controller.robot_mode is RobotMode.POWER_OFF
    fake_robot.inject("remote_control")
    await off_cell.power_on()
    assert off_cell.state is CellState.IDLE


# ----------------------------------------------------------------- safety stops


async def test_protective_stop_is_observed_and_unlocked_after_five_seconds(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    fake_robot.inject("protective_stop")
    await fake_cell.wait_for_state(CellState.PROTECTIVE_STOP, timeout=1.0)
    with pytest.raises(ProtectiveStopUnlockTooSoonError):
        await fake_cell.unlock_protective_stop()
    assert fake_cell.state is CellState.PROTECTIVE_STOP
    await fake_cell.unlock_protective_stop(wait=True)
    # the controller's 5 s rule held (its own clock) and external control came back
    assert fake_robot.controller.time >= 5.0
    assert fake_cell.state is CellState.EXTERNAL_CONTROL_READY


@pytest.mark.parametrize(
    ("fault", "error", "dest"),
    [
        ("protective_stop", ProtectiveStopError, CellState.PROTECTIVE_STOP),
        ("stop_program", ProgramStoppedError, CellState.PROGRAM_STOPPED),
    ],
)
async def test_a_safety_or_program_stop_aborts_the_move_with_its_error(
    fake_cell: Cell,
    fake_robot: FakeRobot,
    fault: str,
    error: type[Exception],
    dest: CellState,
) -> None:
    move = asyncio.create_task(fake_cell.move_joint(list(QUARTER_TURN)))
    await _moving(fake_cell)
    fake_robot.inject(fault)
    with pytest.raises(error):
        await move
    assert fake_cell.state is dest
    await _until(fake_cell, lambda: _at_rest(fake_robot))
    assert fake_robot.arm.q[0] < QUARTER_TURN[0] - 0.1


async def test_a_lost_link_aborts_the_move_and_external_control_comes_back(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    move = asyncio.create_task(fake_cell.move_joint(list(QUARTER_TURN)))
    await _moving(fake_cell)
    fake_robot.inject("drop_rtde")
    with pytest.raises(ConnectionLostError):
        await move
    await fake_cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY, timeout=5.0)
    assert _at_rest(fake_robot)


# ----------------------------------------------------------------- moves


async def test_move_joint_reaches_its_target(fake_cell: Cell, fake_robot: FakeRobot) -> None:
    target = HOME + np.array([0.3, 0.2, -0.2, 0.0, 0.1, 0.0])
    result = await fake_cell.move_joint(list(target))
    assert result.joint_error < 1e-5
    assert not result.stopped
    np.testing.assert_allclose(fake_robot.arm.q, target, atol=1e-5)
    await fake_cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY, timeout=1.0)


async def test_a_move_stretched_by_a_slow_controller_clock_still_arrives() -> None:
    # The link sends one setpoint per controller cycle it sees; starved of CPU it sees
    # fewer and the move takes longer than planned (never faster). Here the controller's
    # clock runs at 0.2 of the wall clock: the move takes 5x its plan, longer than the
    # plan + margins, and keeps reporting progress all along.
    robot = FakeRobot(time_scale=0.01, speed=0.2)
    async with Cell(link_factory=robot.link_factory, record=None) as cell:
        await cell.init()
        loop = asyncio.get_running_loop()
        started = loop.time()
        result = await cell.move_joint(list(HOME + np.array([0.1, 0, 0, 0, 0, 0])))
        took = loop.time() - started
    assert took > result.planned_duration + 2 * 0.5 + 1.0  # past the old fixed patience
    assert result.joint_error < 1e-5
    assert not result.stopped


async def test_move_pose_reaches_the_pose_on_the_controllers_tcp(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    await fake_cell.move_joint([0.4, -1.4, 1.6, -1.8, -1.57, 0.0])
    start = Pose.from_ur(fake_robot.sample().actual_tcp_pose)
    target = Pose(start.position + np.array([0.05, -0.03, 0.02]), start.rotation)
    result = await fake_cell.move_pose(target)
    assert result.position_error < 1e-5
    reached = Pose.from_ur(fake_robot.sample().actual_tcp_pose)  # the TCP set at init
    assert np.linalg.norm(reached.position - target.position) < 1e-5


async def test_stop_brakes_the_move_to_rest_before_its_target(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    move = asyncio.create_task(fake_cell.move_joint(list(QUARTER_TURN)))
    await _moving(fake_cell, speed=0.3)
    at_stop = float(fake_robot.arm.q[0])
    assert await fake_cell.stop() is True
    with pytest.raises(MoveStoppedError) as info:
        await move
    assert info.value.result.stopped  # type: ignore[attr-defined]
    await _until(fake_cell, lambda: _at_rest(fake_robot))
    q0 = float(fake_robot.arm.q[0])
    assert at_stop < q0 < QUARTER_TURN[0] - 0.1  # braked on the way, short of the target
    await fake_cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY, timeout=2.0)
    assert await fake_cell.stop() is False  # nothing left to stop
    # and the cell moves again
    result = await fake_cell.move_joint(list(HOME))
    assert result.joint_error < 1e-5


async def test_stop_also_ends_the_moves_waiting_in_the_queue(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    running = asyncio.create_task(fake_cell.move_joint(list(QUARTER_TURN)))
    await _moving(fake_cell)
    queued = [
        asyncio.create_task(fake_cell.move_joint(list(HOME), queue=True)),
        asyncio.create_task(fake_cell.go_home(queue=True)),
    ]
    await _until(fake_cell, fake_cell._move_queue.locked)  # they wait in the queue
    assert not any(task.done() for task in queued)
    at_stop = float(fake_robot.arm.q[0])
    await fake_cell.stop()
    for task in (running, *queued):
        with pytest.raises(MoveStoppedError):
            await task
    # every move has ended: the queued moves home never started
    await _until(fake_cell, lambda: _at_rest(fake_robot))
    assert fake_robot.arm.q[0] >= at_stop  # braked forward, never turned back home


async def test_a_queued_move_starts_where_the_running_one_ends(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    first = HOME + np.array([0.3, 0, 0, 0, 0, 0])
    second = HOME + np.array([0.3, 0.2, 0, 0, 0, 0])
    running = asyncio.create_task(fake_cell.move_joint(list(first)))
    await _moving(fake_cell, speed=0.05)
    queued = await fake_cell.move_joint(list(second), queue=True)
    done = await running
    np.testing.assert_allclose(done.reached_joints, first, atol=1e-5)
    np.testing.assert_allclose(queued.reached_joints, second, atol=1e-5)


async def test_freedrive_puts_the_controller_in_teach_mode_and_back(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    await fake_cell.freedrive_start()
    assert fake_cell.state is CellState.FREEDRIVE
    assert fake_robot.controller.teach_mode
    with pytest.raises(InvalidStateError):
        await fake_cell.move_joint(list(HOME))
    await fake_cell.freedrive_stop()
    assert not fake_robot.controller.teach_mode
    assert fake_cell.state is CellState.EXTERNAL_CONTROL_READY


# ----------------------------------------------------------------- IO


async def test_an_output_set_by_name_reaches_the_controller_and_an_input_wakes_wait_for(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    await fake_cell.io_set("machine_start", True)
    assert fake_robot.controller.io.standard_digital & 1
    assert (await fake_cell.get_io())["machine_start"] is True
    waiter = asyncio.create_task(fake_cell.io_wait_for("machine_done", True, timeout=5.0))
    link = fake_cell._link()
    assert isinstance(link, FakeLink)
    # waiting: it subscribed to the state stream (besides _until's own subscription)
    await _until(fake_cell, lambda: len(link._subscriptions) >= 2)
    assert not waiter.done()
    fake_robot.set_input(2, True)  # DI2
    # woken by the samples that show it: within 1 s, where a missed wake-up takes its 5 s
    await _until(fake_cell, waiter.done, within=1.0)
    assert fake_cell.io.get("machine_done") is True
    assert waiter.exception() is None


# ----------------------------------------------------------------- races and recovery


async def test_a_move_body_that_hears_of_a_stop_before_its_sample_gets_the_stops_error(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    # The link's end report of a refused trajectory can overtake the state sample that
    # shows the protective stop: the body fails first, the Cell has not seen the stop yet.
    async def body() -> None:
        fake_robot.inject("protective_stop")  # on the controller; its sample comes later
        assert fake_cell.state is not CellState.PROTECTIVE_STOP  # not observed yet
        raise TrackingError("trajectory failed: protective_stop")

    with pytest.raises(ProtectiveStopError):
        await fake_cell.run_move("move_joint", {}, body)


async def test_a_move_body_that_fails_by_itself_keeps_its_own_error(fake_cell: Cell) -> None:
    async def body() -> None:
        raise TrackingError("the body's own failure")

    with pytest.raises(TrackingError, match="own failure"):
        await fake_cell.run_move("move_joint", {}, body)
    assert fake_cell.state is CellState.EXTERNAL_CONTROL_READY


async def test_restore_control_after_a_lost_link_waits_for_the_arm_at_rest(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    fake_robot.inject("drop_rtde")
    await fake_cell.wait_for_state(CellState.DISCONNECTED)
    assert fake_cell.link_losses == 1
    await fake_cell.restore_control(timeout=10)
    assert fake_cell.state is CellState.EXTERNAL_CONTROL_READY
    sample = fake_cell.robot_state
    assert sample is not None
    assert max(map(abs, sample.actual_qd)) < 1e-3
    await fake_cell.move_joint(QUARTER_TURN)  # and it moves again


async def test_restore_control_in_a_protective_stop_raises_its_error(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    fake_robot.inject("protective_stop")
    await fake_cell.wait_for_state(CellState.PROTECTIVE_STOP)
    with pytest.raises(ProtectiveStopError):
        await fake_cell.restore_control(timeout=5)


async def test_a_move_the_link_brakes_for_a_paused_stream_says_so(
    fake_cell: Cell, fake_robot: FakeRobot
) -> None:
    # 90 ms without state: the link process's guard brakes (80 ms), the link stays up (100 ms)
    task = asyncio.create_task(fake_cell.move_joint(QUARTER_TURN))
    await _moving(fake_cell)
    fake_robot.inject("stall_rtde", 0.09)
    with pytest.raises(LinkBrakeError, match="stopped at"):
        await task
    assert fake_cell.link_losses == 0
    await fake_cell.move_joint(QUARTER_TURN)  # made again from where it braked: arrives
