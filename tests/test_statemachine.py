"""The robot-mode state machine: definition, diagram, guards and observed re-sync."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import replace

import pytest

from fxcell.cell.statemachine import (
    DOC,
    DOC_BEGIN,
    DOC_END,
    STATECHART,
    CellState,
    RobotStateMachine,
    diagram_path,
    load_statechart,
    observed_state,
    to_mermaid,
    with_diagram,
)
from fxcell.cli import main as cli_main
from fxcell.errors import InvalidStateError
from fxcell.events import TransitionEvent
from fxcell.protocol import RobotMode, RobotState, RuntimeState, SafetyMode


def test_statechart_diagram_is_current() -> None:
    drawn = to_mermaid(load_statechart())
    assert diagram_path(STATECHART).read_text() == drawn, "run `fxcell statechart`, commit it"
    doc = DOC.read_text()
    assert DOC_BEGIN in doc
    assert with_diagram(doc, drawn) == doc, "run `fxcell statechart`: the docs' copy is stale"


def test_diagram_goes_between_the_markers_only() -> None:
    doc = f"intro\n{DOC_BEGIN}\nold\n{DOC_END}\noutro\n"
    new = with_diagram(doc, "stateDiagram-v2\n")
    assert new == f"intro\n{DOC_BEGIN}\n```mermaid\nstateDiagram-v2\n```\n{DOC_END}\noutro\n"
    assert with_diagram("no markers", "x") == "no markers"


def test_statechart_cli_check_reports_current(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["statechart", "--check"]) == 0
    assert "is current" in capsys.readouterr().out


def test_every_cell_state_is_drawn() -> None:
    text = to_mermaid(load_statechart())
    for state in CellState:
        assert f'"{state.value.split(".")[-1]}"' in text


def test_every_command_guard_names_known_states() -> None:
    chart = load_statechart()
    assert chart.allowed("move") == (CellState.EXTERNAL_CONTROL_READY,)
    assert CellState.MOVING in chart.allowed("brake_release")
    assert CellState.DISCONNECTED not in chart.allowed("power_on")


RUNNING = RobotState(
    robot_mode=RobotMode.RUNNING,
    safety_mode=SafetyMode.NORMAL,
    runtime_state=RuntimeState.PLAYING,
)


@pytest.mark.parametrize(
    ("sample", "flags", "expected"),
    [
        (None, {}, CellState.DISCONNECTED),
        (replace(RUNNING, robot_mode=RobotMode.BOOTING), {}, CellState.BOOTING),
        (replace(RUNNING, robot_mode=RobotMode.POWER_OFF), {}, CellState.POWER_OFF),
        (replace(RUNNING, robot_mode=RobotMode.POWER_ON), {}, CellState.POWERING_ON),
        (replace(RUNNING, robot_mode=RobotMode.IDLE), {}, CellState.IDLE),
        (replace(RUNNING, robot_mode=RobotMode.BACKDRIVE), {}, CellState.BACKDRIVE),
        (RUNNING, {}, CellState.PROGRAM_STOPPED),
        (RUNNING, {"control_ready": True}, CellState.EXTERNAL_CONTROL_READY),
        (
            replace(RUNNING, runtime_state=RuntimeState.STOPPED),
            {"control_ready": True},
            CellState.PROGRAM_STOPPED,
        ),
        (RUNNING, {"control_ready": True, "moving": True}, CellState.MOVING),
        (RUNNING, {"control_ready": True, "moving": True, "stopping": True}, CellState.STOPPING),
        (replace(RUNNING, safety_mode=SafetyMode.PROTECTIVE_STOP), {}, CellState.PROTECTIVE_STOP),
        (replace(RUNNING, safety_mode=SafetyMode.SAFEGUARD_STOP), {}, CellState.SAFEGUARD_STOP),
        (
            replace(RUNNING, safety_mode=SafetyMode.ROBOT_EMERGENCY_STOP),
            {},
            CellState.EMERGENCY_STOP,
        ),
        (replace(RUNNING, safety_mode=SafetyMode.FAULT), {}, CellState.FAULT),
        (replace(RUNNING, safety_mode=SafetyMode.VIOLATION), {}, CellState.FAULT),
        (RUNNING, {"shutting_down": True}, CellState.SHUTTING_DOWN),
    ],
)
def test_observed_state_maps_robot_and_safety_modes(
    sample: RobotState | None, flags: dict[str, bool], expected: CellState
) -> None:
    assert observed_state(sample, **flags) is expected


@pytest.fixture
async def machine() -> AsyncIterator[tuple[RobotStateMachine, list[TransitionEvent]]]:
    events: list[TransitionEvent] = []
    m = RobotStateMachine(on_transition=events.append)
    task = asyncio.create_task(m.run())
    yield m, events
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


async def _settle(m: RobotStateMachine, target: CellState) -> None:
    async with asyncio.timeout(1):
        while m.state is not target:
            await m.wait_changed()


async def test_machine_follows_observed_states_through_declared_transitions(
    machine: tuple[RobotStateMachine, list[TransitionEvent]],
) -> None:
    m, events = machine
    assert m.state is CellState.DISCONNECTED
    for target in (
        CellState.POWER_OFF,
        CellState.POWERING_ON,
        CellState.IDLE,
        CellState.PROGRAM_STOPPED,
        CellState.EXTERNAL_CONTROL_READY,
        CellState.PROTECTIVE_STOP,
        CellState.DISCONNECTED,
    ):
        m.sync(target)
        await _settle(m, target)
    triggers = [e.trigger for e in events]
    assert "observe_powering_on" in triggers
    assert "observe_external_control_ready" in triggers
    assert "observe_protective_stop" in triggers
    assert all(e.cause == "observed" for e in events)
    assert events[-1].dest == "disconnected"


async def test_machine_resyncs_without_a_declared_transition(
    machine: tuple[RobotStateMachine, list[TransitionEvent]],
) -> None:
    m, events = machine
    m.sync(CellState.IDLE)
    await _settle(m, CellState.IDLE)
    m.sync(CellState.SHUTTING_DOWN)  # only the shutdown trigger leads there
    await _settle(m, CellState.SHUTTING_DOWN)
    assert events[-1].trigger in ("resync", "shutdown")


async def test_move_triggers_are_guarded(
    machine: tuple[RobotStateMachine, list[TransitionEvent]],
) -> None:
    m, _ = machine
    m.sync(CellState.IDLE)
    await _settle(m, CellState.IDLE)
    assert await m.fire("start_move") is False
    assert m.state is CellState.IDLE
    m.sync(CellState.EXTERNAL_CONTROL_READY)
    await _settle(m, CellState.EXTERNAL_CONTROL_READY)
    assert await m.fire("start_move") is True
    assert m.state is CellState.MOVING
    assert await m.fire("stop_move") is True
    assert await m.fire("move_ended") is True
    assert m.state is CellState.EXTERNAL_CONTROL_READY


async def test_check_names_state_and_allowed_states(
    machine: tuple[RobotStateMachine, list[TransitionEvent]],
) -> None:
    m, _ = machine
    with pytest.raises(InvalidStateError) as info:
        m.check("power_on")
    assert info.value.state == "disconnected"
    assert "power_off" in info.value.allowed
    assert "needs" in str(info.value)


def test_every_state_says_what_to_do_next() -> None:
    chart = load_statechart()
    missing = [s.value for s in CellState if not chart.next_step(s)]
    assert not missing, f"states without a `next` in statecharts/robot.yaml: {missing}"


async def test_a_refused_move_in_idle_tells_the_operator_to_run_init(
    machine: tuple[RobotStateMachine, list[TransitionEvent]],
) -> None:
    m, _ = machine
    m.sync(CellState.IDLE)
    await _settle(m, CellState.IDLE)
    with pytest.raises(InvalidStateError) as info:
        m.check("move", "move_joint")
    assert info.value.next_step.startswith("run init")
    assert str(info.value).startswith("move_joint() is refused: the robot is idle: run init (")
