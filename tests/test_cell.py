"""The Cell against the simulator: life cycle, guards, observed safety events, recovery."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable, Iterator
from typing import Any

import numpy as np
import pytest
from waiting import until

from fxcell import Cell, CellState, RobotMode, SafetyMode
from fxcell.cell.statemachine import load_statechart
from fxcell.config import CellConfig
from fxcell.errors import (
    ConnectionLostError,
    InvalidStateError,
    MoveInProgressError,
    MoveStoppedError,
    NotInRemoteControlError,
    ProgramStoppedError,
    ProtectiveStopError,
    ProtectiveStopUnlockTooSoonError,
    RobotTimeoutError,
)
from fxcell.events import CommandEvent, StateEvent, TransitionEvent
from fxcell.protocol import CONTROL_PERIOD, ProgramState
from fxcell.testing import (
    URCAP_PORT,
    SimulatorHandle,
    brisk,
    simulator,
    urcap_port,
    uses_urcap_port,
)

TIME_SCALE = 0.05
OBSERVE_WITHIN = 0.05  # s from the simulator's change to cell.state


UNLOCK_DELAY = 2.0
"""s of controller time before the shared simulator unlocks a protective stop: the real
controller's 5 s rule is tested in tests/sim/test_sim_safety.py and test_cell_fake.py; 2 s
still leave a busy machine time to ask too soon once."""


@pytest.fixture(scope="module")
def shared_sim() -> Iterator[SimulatorHandle]:
    args = ["--unlock-delay", str(UNLOCK_DELAY), "--urcap-port", str(URCAP_PORT)]
    with simulator(time_scale=TIME_SCALE, extra_args=args) as handle:
        yield handle


def _reset(sim: SimulatorHandle) -> None:
    """Bring the shared simulator back to POWER_OFF, normal safety, Remote control."""
    sim.inject("remote_control")
    state = sim.state()
    if state["safety_mode"] in ("ROBOT_EMERGENCY_STOP", "SYSTEM_EMERGENCY_STOP"):
        sim.inject("emergency_stop_release")
    if state["safety_mode"] == "SAFEGUARD_STOP":
        sim.inject("safeguard_stop_release")
    if sim.state()["safety_mode"] != "NORMAL":
        sim.dashboard("restart safety")
        sim.wait_for("safety_mode", "NORMAL")
    if sim.state()["runtime_state"] != "STOPPED":
        sim.dashboard("stop")
    if sim.state()["robot_mode"] != "POWER_OFF":
        sim.dashboard("power off")
    sim.wait_for("robot_mode", "POWER_OFF")


@pytest.fixture
async def cell(shared_sim: SimulatorHandle) -> AsyncIterator[Cell]:
    await asyncio.to_thread(_reset, shared_sim)
    async with Cell(host=shared_sim.host, config=brisk(CellConfig.load())) as c:
        await c.wait_for_state(CellState.POWER_OFF)
        yield c


async def _inject(sim: SimulatorHandle, fault: str, *args: object) -> float:
    """Inject a fault; returns the wall-clock time just before the request left."""
    t0 = time.time()
    await asyncio.to_thread(sim.inject, fault, *args)
    return t0


async def _transition_to(cell: Cell, dest: CellState, within: float = 2.0) -> TransitionEvent:
    """The next TransitionEvent into ``dest`` (or a synthetic one if already there)."""
    with cell.transitions() as events:
        if cell.state is dest:
            return TransitionEvent(time.time(), dest.value, dest.value, "", "observed")
        async with asyncio.timeout(within):
            async for event in events:
                assert isinstance(event, TransitionEvent)
                if event.dest == dest.value:
                    return event
    raise AssertionError("unreachable")


# ----------------------------------------------------------------- life cycle


@pytest.mark.injects_faults("shutdown takes the controller, and so the link, down")
async def test_full_life_cycle_from_power_off_to_shutdown(sim: SimulatorHandle) -> None:
    async with Cell(host=sim.host) as cell:
        await cell.wait_for_state(CellState.POWER_OFF)
        assert await cell.get_robot_mode() is RobotMode.POWER_OFF
        await cell.init()
        assert cell.state is CellState.EXTERNAL_CONTROL_READY
        assert await cell.get_robot_mode() is RobotMode.RUNNING
        assert await cell.get_safety_status() is SafetyMode.NORMAL
        assert (await cell.get_program_state()).state is ProgramState.PLAYING
        assert await cell.is_in_remote_control() is True
        sent = cell._link().messages_sent
        await cell.init()  # idempotent: nothing to do, nothing sent
        assert cell._link().messages_sent == sent
        assert cell.state is CellState.EXTERNAL_CONTROL_READY
        await cell.power_off()
        assert cell.state is CellState.POWER_OFF
        assert sim.state()["robot_mode"] == "POWER_OFF"
        await cell.shutdown()
        assert cell.state is CellState.DISCONNECTED


async def test_commands_publish_start_and_end_events(cell: Cell) -> None:
    seen: list[Any] = []
    unsubscribe = cell.bus.subscribe(seen.append)
    try:
        await cell.power_on()
        with pytest.raises(InvalidStateError):
            await cell.start_external_control()
    finally:
        unsubscribe()
    commands = [e for e in seen if isinstance(e, CommandEvent)]
    assert [(e.name, e.outcome) for e in commands] == [
        ("power_on", "started"),
        ("power_on", "ok"),
        ("start_external_control", "started"),
        ("start_external_control", "error"),
    ]
    assert commands[-1].error_type == "InvalidStateError"
    assert all(e.ended is not None and e.ended >= e.started for e in commands[1::2])
    transitions = [e.dest for e in seen if isinstance(e, TransitionEvent)]
    assert transitions[-2:] == ["powering_on", "idle"]
    assert any(isinstance(e, StateEvent) for e in seen)


async def test_robot_state_stream_and_pose_queries(cell: Cell) -> None:
    stamps = []
    with cell.robot_states() as states:
        async for sample in states:
            stamps.append(sample.timestamp)
            if len(stamps) == 50:
                break
    assert np.all(np.diff(stamps) > 0)
    q = await cell.get_current_joint_values()
    pose = await cell.get_current_pose()
    rpy = await cell.get_current_rpy()
    pose_rpy = await cell.get_current_pose_rpy()
    assert len(q) == 6
    assert len(pose) == 7
    assert len(rpy) == 3
    assert np.isclose(np.linalg.norm(pose[3:]), 1.0)
    assert pose_rpy == (*pose[:3], *rpy)
    assert await cell.get_velocity() == (0.0,) * 6


# ----------------------------------------------------------------- guards


GUARDED: dict[str, Callable[[Cell], Any]] = {
    "power_on": lambda c: c.power_on(),
    "brake_release": lambda c: c.brake_release(),
    "power_off": lambda c: c.power_off(),
    "init": lambda c: c.init(),
    "start_external_control": lambda c: c.start_external_control(),
    "stop_external_control": lambda c: c.stop_external_control(),
    "unlock_protective_stop": lambda c: c.unlock_protective_stop(),
    "shutdown": lambda c: c.shutdown(),
    "get_robot_mode": lambda c: c.get_robot_mode(),
    "get_safety_status": lambda c: c.get_safety_status(),
    "get_program_state": lambda c: c.get_program_state(),
    "is_in_remote_control": lambda c: c.is_in_remote_control(),
    "get_current_joint_values": lambda c: c.get_current_joint_values(),
    "get_current_pose": lambda c: c.get_current_pose(),
    "get_velocity": lambda c: c.get_velocity(),
    "move_joint": lambda c: c.move_joint([0.0, -1.57, 0.0, -1.57, 0.0, 0.0]),
    "go_home": lambda c: c.go_home(),
    "move_pose": lambda c: c.move_pose([-0.25, -0.2, 0.12, 3.14159, 0.0, 0.0]),
    "move_distance": lambda c: c.move_distance([0.0, 0.0, 0.01]),
    "move_relative": lambda c: c.move_relative(
        [-0.25, -0.2, 0.12, 3.14159, 0.0, 0.0], [-0.25, -0.2, 0.1, 3.14159, 0.0, 0.0]
    ),
}
GUARD = dict.fromkeys(
    ("move_joint", "go_home", "move_pose", "move_distance", "move_relative"), "move"
)


async def _enter(cell: Cell, sim: SimulatorHandle, state: CellState) -> asyncio.Task[Any] | None:
    """Bring the cell to ``state``; for ``running.moving``, returns the move's task."""
    move = None
    if state is CellState.IDLE:
        await cell.power_on()
    elif state is CellState.PROGRAM_STOPPED:
        await cell.power_on()
        await cell.brake_release()
    elif state is CellState.EXTERNAL_CONTROL_READY:
        await cell.init()
    elif state is CellState.SAFEGUARD_STOP:
        await cell.init()
        await _inject(sim, "safeguard_stop")
    elif state is CellState.EMERGENCY_STOP:
        await cell.init()
        await _inject(sim, "emergency_stop")
    elif state is CellState.PROTECTIVE_STOP:
        await cell.init()
        await _inject(sim, "protective_stop")
    elif state is CellState.DISCONNECTED:
        await _inject(sim, "stall_rtde", 1.0)
    elif state is CellState.MOVING:
        await cell.init()
        move = asyncio.create_task(cell.run_move("move_joint", {}, _slow_move(cell, 4.0)))
    await cell.wait_for_state(state, timeout=5)
    return move


def _view(sim: SimulatorHandle, moving: bool = False) -> dict[str, Any]:
    state = sim.state()
    keys = ("robot_mode", "safety_mode", "runtime_state", "program", *(() if moving else ("q",)))
    return {k: state[k] for k in keys}


@pytest.mark.injects_faults("safety stops and a stalled stream, one per state")
@pytest.mark.parametrize(
    "state",
    [
        CellState.POWER_OFF,
        CellState.IDLE,
        CellState.PROGRAM_STOPPED,
        CellState.EXTERNAL_CONTROL_READY,
        CellState.MOVING,
        CellState.SAFEGUARD_STOP,
        CellState.EMERGENCY_STOP,
        CellState.PROTECTIVE_STOP,
        CellState.DISCONNECTED,
    ],
    ids=lambda s: s.value,
)
async def test_each_command_is_refused_in_each_wrong_state_without_touching_the_robot(
    cell: Cell, shared_sim: SimulatorHandle, state: CellState
) -> None:
    chart = load_statechart()
    move = await _enter(cell, shared_sim, state)
    moving = move is not None  # another move is refused earlier: MoveInProgressError
    refused = [
        name
        for name in GUARDED
        if state not in chart.allowed(GUARD.get(name, name)) and not (moving and name in GUARD)
    ]
    assert refused, f"no command is refused in {state.value}?"
    before_sim = await asyncio.to_thread(_view, shared_sim, moving)
    link = cell._link()
    sent = link.messages_sent
    for name in refused:
        with pytest.raises(InvalidStateError) as info:
            await GUARDED[name](cell)
        assert info.value.state == state.value, name
        assert info.value.command == name
    assert link.messages_sent == sent, "a refused command sent something to the link"
    assert await asyncio.to_thread(_view, shared_sim, moving) == before_sim
    assert cell.state is state
    if move is not None:
        await cell.stop()
        with pytest.raises(MoveStoppedError):
            await move


@pytest.mark.injects_faults("the pendant switched to Local")
async def test_local_control_refuses_commands_without_changing_the_robot(
    cell: Cell, shared_sim: SimulatorHandle
) -> None:
    await _inject(shared_sim, "local_control")
    try:
        assert await cell.is_in_remote_control() is False
        with pytest.raises(NotInRemoteControlError):
            await cell.power_on()
        with pytest.raises(NotInRemoteControlError):
            await cell.init()
        assert shared_sim.state()["robot_mode"] == "POWER_OFF"
        assert cell.state is CellState.POWER_OFF
    finally:
        await _inject(shared_sim, "remote_control")


# ----------------------------------------------------------------- observed events


@pytest.mark.injects_faults("each controller event is injected")
@pytest.mark.parametrize(
    ("fault", "dest", "after"),
    [
        ("stop_program", CellState.PROGRAM_STOPPED, None),
        ("emergency_stop", CellState.EMERGENCY_STOP, "emergency_stop_release"),
        ("safeguard_stop", CellState.SAFEGUARD_STOP, "safeguard_stop_release"),
        ("protective_stop", CellState.PROTECTIVE_STOP, None),
        ("drop_rtde", CellState.DISCONNECTED, None),
    ],
)
async def test_controller_events_reach_cell_state_within_50_ms(
    cell: Cell, shared_sim: SimulatorHandle, fault: str, dest: CellState, after: str | None
) -> None:
    await cell.init()
    waiter = asyncio.create_task(_transition_to(cell, dest))
    await asyncio.sleep(0)
    t0 = await _inject(shared_sim, fault)
    event = await waiter
    assert cell.state is dest or fault == "drop_rtde"
    assert event.cause == "observed"
    latency = event.time - t0  # includes the injection's round trip: an upper bound
    assert latency < OBSERVE_WITHIN, f"{fault}: {latency * 1000:.1f} ms"
    if after is not None:
        await _inject(shared_sim, after)
    if fault == "drop_rtde":  # the link comes back by itself
        await cell.wait_for_state(CellState.PROGRAM_STOPPED, CellState.EXTERNAL_CONTROL_READY)


@pytest.mark.injects_faults("a protective stop")
async def test_protective_stop_recovery_restores_external_control(
    cell: Cell, shared_sim: SimulatorHandle
) -> None:
    await cell.init()
    await _inject(shared_sim, "protective_stop")
    await cell.wait_for_state(CellState.PROTECTIVE_STOP, timeout=1)
    with pytest.raises(ProtectiveStopUnlockTooSoonError) as info:
        await cell.unlock_protective_stop()
    assert 0 < info.value.remaining <= 5
    assert cell.state is CellState.PROTECTIVE_STOP
    await cell.unlock_protective_stop(wait=True)
    assert cell.state is CellState.EXTERNAL_CONTROL_READY
    assert shared_sim.state()["safety_mode"] == "NORMAL"


@pytest.mark.injects_faults("the link process killed")
async def test_link_crash_under_external_control_reconnects_and_restores_control(
    cell: Cell,
) -> None:
    await cell.init()
    cell._link().kill_process()
    await cell.wait_for_state(CellState.DISCONNECTED, timeout=1)
    await cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY, timeout=20)
    assert cell._link().control_ready


@pytest.mark.injects_faults("the control script hung: it stops answering commands")
async def test_a_call_the_controller_never_answers_restarts_the_link_and_control_comes_back(
    cell: Cell, shared_sim: SimulatorHandle
) -> None:
    # ur_rtde waits up to 300 s for its script to finish a command, in the link process's
    # one call worker: every call after it would time out too, heal after heal.
    await cell.init()
    bare = shared_sim.state()["payload"]
    link = cell._link()
    stuck = link.pid
    cell.command_timeout = 1.0
    await _inject(shared_sim, "hang_script")
    with pytest.raises(RobotTimeoutError, match="SetTool"):
        await cell.declare_held("crucible")  # the controller's payload: a SetTool call
    await until(lambda: link.pid not in (stuck, None), "a fresh link process", 10.0)
    await cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY, timeout=20)
    await cell.declare_held(None)
    await cell.declare_held("crucible")  # answered now: the fresh process's script runs
    assert shared_sim.state()["payload"] > bare


@pytest.mark.injects_faults("the link process killed")
async def test_killed_link_process_goes_disconnected_then_reconnects(cell: Cell) -> None:
    await cell.power_on()
    waiter = asyncio.create_task(_transition_to(cell, CellState.DISCONNECTED))
    await asyncio.sleep(0)
    t0 = time.time()
    cell._link().kill_process()
    event = await waiter
    assert event.time - t0 < 0.1
    assert event.detail
    await cell.wait_for_state(CellState.IDLE, timeout=15)


# ----------------------------------------------------------------- external control modes


@uses_urcap_port
async def test_external_control_through_the_urcap_program(shared_sim: SimulatorHandle) -> None:
    await asyncio.to_thread(_reset, shared_sim)
    config = CellConfig.load()
    config = config.model_copy(
        update={"robot": config.robot.model_copy(update={"urcap_port": URCAP_PORT})}
    )
    with urcap_port():  # the PC side binds the machine-wide URCAP_PORT
        async with Cell(host=shared_sim.host, config=config, external_control="urcap") as cell:
            await cell.wait_for_state(CellState.POWER_OFF)
            await cell.init()
            assert cell.state is CellState.EXTERNAL_CONTROL_READY
            status = await cell.get_program_state()
            assert status.state is ProgramState.PLAYING
            assert status.program.endswith("external_control.urp")
            await cell.stop_external_control()
            assert cell.state is CellState.PROGRAM_STOPPED
            assert shared_sim.state()["runtime_state"] == "STOPPED"


async def test_external_control_by_script_upload_stops_and_restarts(cell: Cell) -> None:
    await cell.init()
    seen: list[str] = []
    unsubscribe = cell.bus.subscribe(
        lambda e: seen.append(e.dest) if isinstance(e, TransitionEvent) else None
    )
    try:
        for _ in range(2):
            await cell.stop_external_control()
            assert cell.state is CellState.PROGRAM_STOPPED
            await cell.start_external_control()
            assert cell.state is CellState.EXTERNAL_CONTROL_READY
    finally:
        unsubscribe()
    # the link's blocking ur_rtde calls (it replies after them) are announced as holds
    assert "disconnected" not in seen


# ----------------------------------------------------------------- moves


def _slow_move(cell: Cell, seconds: float = 3.0) -> Callable[[], Any]:
    async def body() -> str:
        link = cell._link()
        assert link.latest is not None
        q0 = np.asarray(link.latest.actual_q)
        n = round(seconds / CONTROL_PERIOD)
        samples = np.repeat(q0[None, :], n, axis=0)
        samples[:, 0] += np.linspace(0.0, 0.3, n)
        handle = await link.execute_trajectory(samples)
        try:
            return (await handle.wait()).status
        finally:
            if not handle.done:
                await handle.stop()

    return body


async def test_moves_are_admitted_only_with_external_control(cell: Cell) -> None:
    with pytest.raises(InvalidStateError):
        await cell.run_move("move_joint", {}, _slow_move(cell))
    await cell.init()
    task = asyncio.create_task(cell.run_move("move_joint", {}, _slow_move(cell)))
    await cell.wait_for_state(CellState.MOVING, timeout=1)
    with pytest.raises(MoveInProgressError):
        await cell.run_move("move_joint", {}, _slow_move(cell))
    assert await cell.stop() is True
    with pytest.raises(MoveStoppedError):
        await task
    await cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY, timeout=1)


@pytest.mark.injects_faults("a protective stop")
async def test_protective_stop_cancels_the_running_move_with_its_error(
    cell: Cell, shared_sim: SimulatorHandle
) -> None:
    await cell.init()
    task = asyncio.create_task(cell.run_move("move_joint", {}, _slow_move(cell)))
    await cell.wait_for_state(CellState.MOVING, timeout=1)
    await _inject(shared_sim, "protective_stop")
    with pytest.raises(ProtectiveStopError):
        await task
    assert cell.state is CellState.PROTECTIVE_STOP


@pytest.mark.injects_faults("the program stopped on the pendant")
async def test_pendant_program_stop_cancels_the_running_move_with_its_error(
    cell: Cell, shared_sim: SimulatorHandle
) -> None:
    await cell.init()
    task = asyncio.create_task(cell.run_move("move_joint", {}, _slow_move(cell)))
    await cell.wait_for_state(CellState.MOVING, timeout=1)
    await _inject(shared_sim, "stop_program")
    with pytest.raises(ProgramStoppedError):
        await task
    assert cell.state is CellState.PROGRAM_STOPPED


@pytest.mark.injects_faults("the link process killed")
async def test_lost_link_cancels_the_running_move(cell: Cell) -> None:
    await cell.init()
    task = asyncio.create_task(cell.run_move("move_joint", {}, _slow_move(cell)))
    await cell.wait_for_state(CellState.MOVING, timeout=1)
    cell._link().kill_process()
    with pytest.raises(ConnectionLostError):
        await task


# ----------------------------------------------------------------- recording


async def test_record_writes_commands_transitions_and_states_to_mcap(
    shared_sim: SimulatorHandle, tmp_path: Any
) -> None:
    from mcap.reader import make_reader

    from fxcell.recorder import topics as recorder_topics

    await asyncio.to_thread(_reset, shared_sim)
    async with Cell(host=shared_sim.host, record=tmp_path) as cell:
        await cell.wait_for_state(CellState.POWER_OFF)
        await cell.power_on()
    files = sorted(tmp_path.glob("*.mcap"))
    assert len(files) == 1
    with files[0].open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert summary.statistics is not None
    topics = {
        c.topic: summary.statistics.channel_message_counts.get(c.id, 0)
        for c in summary.channels.values()
    }
    assert topics[recorder_topics.COMMANDS] == 2  # power_on started + ended
    assert topics[recorder_topics.TRANSITIONS] >= 2  # powering_on, idle
    assert topics[recorder_topics.ROBOT_STATE] > 10


# ----------------------------------------------------------------- configuration


@pytest.mark.system  # Cell() without a host starts the embedded simulator process
async def test_without_a_host_the_cell_runs_the_embedded_simulator(tmp_path: Any) -> None:
    config_file = tmp_path / "cell.yaml"
    config_file.write_text("robot:\n  command_timeout: 5\n")
    cell = Cell.from_config(config_file, simulator_options={"time_scale": TIME_SCALE})
    assert cell.host is None
    assert cell.command_timeout == 5
    async with cell:
        host = cell.host
        assert host is not None
        await cell.power_on()
        assert cell.state is CellState.IDLE
        simulator_process = cell._simulator.process
    assert cell.host is None
    assert simulator_process.poll() is not None  # stopped with the cell
