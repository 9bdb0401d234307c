"""The command table: its agreement with the statechart, Cell/RemoteCell parity, derived
routes and CLI, and one behaviour suite run against both Cell and RemoteCell."""

from __future__ import annotations

import asyncio
import inspect
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from waiting import controller_time_passes, until

from fxcell.cell import Cell, CellState
from fxcell.cell.statemachine import load_statechart
from fxcell.client import RemoteCell
from fxcell.commands import COMMANDS, CellCommands
from fxcell.config import CellConfig
from fxcell.errors import (
    InvalidArgumentError,
    InvalidStateError,
    MoveStoppedError,
    NothingGraspedError,
)
from fxcell.protocol import ProgramState, RobotMode, SafetyMode
from fxcell.results import GripResult, MoveResult, ProgramStatus
from fxcell.testing import FakeRobot, SimulatorHandle, simulator

TIME_SCALE = 0.05
TOKEN = "commands-test-token-0123456789"
CELL = pytest.StashKey[Cell]()


# ----------------------------------------------------------------- the table


def test_the_guards_of_the_table_are_the_statecharts_commands() -> None:
    chart = load_statechart()
    guards = {c.guard for c in COMMANDS.values() if c.guard is not None}
    assert guards == set(chart.commands)


def test_cell_and_remote_cell_have_the_tables_signatures_and_result_types() -> None:
    for name, entry in COMMANDS.items():
        declared = inspect.signature(getattr(CellCommands, name))
        assert inspect.signature(getattr(Cell, name)) == declared, name
        assert name in vars(Cell), f"Cell does not implement {name}()"
        # RemoteCell runs every command through the table (the Protocol's bodies).
        assert getattr(RemoteCell, name) is getattr(CellCommands, name), name
        assert declared.return_annotation == entry.result.annotation, name
        assert [a.name for a in entry.args] == [p for p in declared.parameters if p != "self"]
    table_methods = {n for n, f in vars(CellCommands).items() if hasattr(f, "__fxcell_command__")}
    assert table_methods == set(COMMANDS)


# Public coroutines of Cell that are the library's own plumbing, not commands: opening and
# closing the session, waiting on the state machine, running a table command by name, checking
# whether a table command by name would be admitted, running a caller's coroutine as the
# Cell's move (it takes a Python callable), and the job's typed view of check_placement.
NOT_COMMANDS = {
    "open",
    "close",
    "wait_for_state",
    "run_command",
    "check_command",
    "run_move",
    "inspect_placement",
}


def test_every_public_cell_coroutine_is_a_command_of_the_table() -> None:
    public = {
        name
        for name, fn in inspect.getmembers(Cell, inspect.iscoroutinefunction)
        if not name.startswith("_")
    }
    missing = public - set(COMMANDS) - NOT_COMMANDS
    assert not missing, f"public Cell coroutines outside the command table: {sorted(missing)}"
    assert public >= NOT_COMMANDS  # the exceptions still exist (else drop them)


# Arguments the guarded commands are called with (valid names and values: the checks of
# arguments against the configuration come before the guard).
GUARDED_ARGS: dict[str, dict[str, Any]] = {
    "move_joint": {"target": [0.0, -1.57, 0.0, -1.57, 0.0, 0.0]},
    "move_pose": {"target": [-0.25, -0.2, 0.12, 3.14159, 0.0, 0.0]},
    "move_distance": {"distance": [0.0, 0.0, 0.01]},
    "move_relative": {
        "start_pose": [-0.25, -0.2, 0.12, 3.14159, 0.0, 0.0],
        "target_pose": [-0.25, -0.2, 0.1, 3.14159, 0.0, 0.0],
    },
    "move_to": {"name": "home"},
    "pick": {"station": "rack", "slot": "B2"},
    "place": {"station": "machine", "slot": "A1"},
    "gripper_move": {"width": 0.02},
    "io_set": {"signal": "machine_start", "value": True},
    "io_wait_for": {"signal": "machine_done", "value": True, "timeout": 1.0},
    "teach": {"name": "p1"},
    "teach_frame_point": {"station": "rack", "point": "origin"},
}
# States a Cell on the in-process fake robot is brought to, in the order they are tried:
# each guarded command is called in the first of them its guard refuses.
SCENES = (
    CellState.POWER_OFF,
    CellState.EXTERNAL_CONTROL_READY,
    CellState.MOVING,
    CellState.DISCONNECTED,
)


def _refused_in(state: CellState) -> list[str]:
    chart = load_statechart()
    return [
        name
        for name, entry in COMMANDS.items()
        if entry.guard is not None
        and next((s for s in SCENES if s not in chart.allowed(entry.guard)), None) is state
    ]


def test_every_guarded_command_is_tried_where_its_guard_refuses_it() -> None:
    chart = load_statechart()
    tried = {name for state in SCENES for name in _refused_in(state)}
    untried = {n for n, e in COMMANDS.items() if e.guard is not None} - tried
    # only a guard that admits every state (stop) is never refused
    assert all(set(chart.allowed(COMMANDS[n].guard or "")) == set(CellState) for n in untried)
    assert untried == {"stop"}
    for name in tried:
        required = [a.name for a in COMMANDS[name].args if a.required]
        assert set(required) <= set(GUARDED_ARGS.get(name, {})), name


@pytest.mark.parametrize("state", SCENES, ids=lambda s: s.value)
async def test_a_command_its_guard_refuses_raises_and_sends_nothing(
    state: CellState, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The guard of the command table, applied by the Cell itself: every command is refused
    with InvalidStateError in a state its guard does not admit, and nothing reaches the
    robot (no request on the link, the gripper's socket never opened)."""
    import fxcell.link.gripper

    opened: list[str] = []

    class NoGripper:
        def __init__(self, host: str) -> None:
            opened.append(host)

    monkeypatch.setattr(fxcell.link.gripper, "URCapGripperClient", NoGripper)
    robot = FakeRobot(time_scale=TIME_SCALE)
    config = CellConfig.load().model_copy(update={"positions_file": tmp_path / "p.yaml"})
    async with Cell(link_factory=robot.link_factory, config=config, record=None) as cell:
        release = asyncio.Event()
        move: asyncio.Task[None] | None = None
        if state is not CellState.POWER_OFF:
            await cell.init()
        if state is CellState.MOVING:
            move = asyncio.create_task(cell.run_move("move_joint", {}, release.wait))
            await cell.wait_for_state(CellState.MOVING)
        if state is CellState.DISCONNECTED:
            await cell.shutdown()
        assert cell.state is state
        link = cell.link
        assert link is not None
        sent: list[object] = []
        send = link.request

        async def request(message: Any) -> object:
            task = asyncio.current_task()
            if task is None or task.get_name() != "remote watch":  # the Local/Remote poll
                sent.append(message)
            return await send(message)

        monkeypatch.setattr(link, "request", request)
        refused = _refused_in(state)
        assert refused
        for name in refused:
            with pytest.raises(InvalidStateError) as info:
                await cell.run_command(name, **GUARDED_ARGS.get(name, {}))
            assert (info.value.command, info.value.state) == (name, state.value)
        assert sent == [], "a refused command sent something to the robot"
        assert opened == [], "a refused command opened the gripper's socket"
        assert cell.state is state
        if move is not None:
            await cell.stop()
            with pytest.raises(MoveStoppedError):
                await move


def test_the_operator_page_names_only_commands_of_the_table() -> None:
    import re
    from importlib import resources

    html = (resources.files("fxcell.daemon") / "static" / "index.html").read_text()
    named = set(re.findall(r'data-command="([a-z_]+)"', html))
    assert named
    assert named <= set(COMMANDS)


def test_the_table_and_the_client_import_without_the_motion_stack() -> None:
    code = (
        "import sys\n"
        "for m in ('numpy', 'pinocchio', 'rtde_control', 'rtde_receive', 'ompl', 'ruckig',"
        " 'transitions', 'fastapi', 'pydantic', 'yaml'):\n"
        "    sys.modules[m] = None\n"
        "from fxcell.commands import COMMANDS\n"
        "from fxcell.client import RemoteCell\n"
        "print(len(COMMANDS))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False
    )
    assert out.returncode == 0, out.stderr
    assert int(out.stdout) == len(COMMANDS)


def test_every_command_has_a_route_and_a_cli_subcommand() -> None:
    from fxcell.cli import build_parser
    from fxcell.config import CellConfig
    from fxcell.daemon.app import create_app
    from fxcell.daemon.service import CellService

    app = create_app(CellService(CellConfig(), TOKEN))
    paths = app.openapi()["paths"]
    parser = build_parser()
    for name, entry in COMMANDS.items():
        method = "get" if entry.kind == "query" else "post"
        assert method in paths[f"/api/cell/{name}"], name
        parsed = parser.parse_args([name.replace("_", "-"), *_cli_args(entry)])
        assert callable(parsed.func)
    schema = paths["/api/cell/move_relative"]["post"]
    assert "then to" in schema["description"]  # it is not a displacement between two poses


def _cli_args(entry: Any) -> list[str]:
    """Values for the required arguments: positional when one or all scalars, else options."""
    required = [a for a in entry.args if a.required]
    positional = len(required) == 1 or all(a.type.length is None for a in required)
    out: list[str] = []
    for arg in required:
        values = ["0.1"] * (arg.type.length[0] if arg.type.length else 1)
        flag = [] if positional else [f"--{arg.name.replace('_', '-')}"]
        out += flag + values
    return out


async def test_unknown_arguments_are_refused_before_anything_is_sent() -> None:
    remote = RemoteCell("http://127.0.0.1:9", TOKEN)  # nothing listens there
    try:
        with pytest.raises(InvalidArgumentError, match="takes no argument mode"):
            await remote.run_command("start_external_control", mode="script")
        with pytest.raises(InvalidArgumentError, match="unknown command"):
            await remote.run_command("fly")
    finally:
        await remote.close(release=False)


# ----------------------------------------------------------------- one suite, two cells


@pytest.fixture(scope="module")
def shared_sim() -> Iterator[SimulatorHandle]:
    with simulator(time_scale=TIME_SCALE) as handle:
        yield handle


def _reset(sim: SimulatorHandle) -> None:
    sim.inject("remote_control")
    if sim.state()["runtime_state"] != "STOPPED":
        sim.dashboard("stop")
    if sim.state()["robot_mode"] != "POWER_OFF":
        sim.dashboard("power off")
    sim.wait_for("robot_mode", "POWER_OFF")


@pytest.fixture(params=["Cell", "RemoteCell"])
async def api(request: pytest.FixtureRequest, shared_sim: SimulatorHandle) -> AsyncIterator[Any]:
    """The same commands, in process (Cell) and through the daemon's app (RemoteCell)."""
    await asyncio.to_thread(_reset, shared_sim)
    async with Cell(host=shared_sim.host) as cell:
        await cell.wait_for_state(CellState.POWER_OFF)
        request.node.stash[CELL] = cell
        if request.param == "Cell":
            yield cell
            return
        from fxcell.daemon.app import create_app
        from fxcell.daemon.service import CellService

        service = CellService(cell.config, TOKEN)
        service.attach(cell)
        transport = httpx.ASGITransport(app=create_app(service))
        async with RemoteCell("http://127.0.0.1:8040", TOKEN, transport=transport) as remote:
            yield remote
        await service.operations.cancel_all()
        service.detach()


async def test_queries_return_the_same_types(api: CellCommands) -> None:
    assert await api.get_robot_mode() is RobotMode.POWER_OFF
    assert await api.get_safety_status() is SafetyMode.NORMAL
    assert await api.is_in_remote_control() is True
    status = await api.get_program_state()
    assert isinstance(status, ProgramStatus)
    assert status.state is ProgramState.STOPPED
    for floats in (
        await api.get_current_joint_values(),
        await api.get_current_pose(),
        await api.get_current_rpy(),
        await api.get_velocity(),
        await api.get_max_acceleration(),
    ):
        assert isinstance(floats, tuple)
        assert all(isinstance(v, float) for v in floats)
    assert len(await api.get_current_pose()) == 7
    assert isinstance(await api.get_velocity_factor(), float)


async def test_refusals_and_stop_without_a_move(api: CellCommands) -> None:
    with pytest.raises(InvalidStateError) as refused:
        await api.go_home()
    assert "external_control_ready" in str(refused.value.allowed)
    assert await api.stop() is False  # a bool on both (RemoteCell returned None before)


async def test_go_home_without_arguments_then_a_stop_ends_the_queued_move(
    api: CellCommands, shared_sim: SimulatorHandle, request: pytest.FixtureRequest
) -> None:
    await api.init()
    await api.move_joint([0.2, -1.4, 0.2, -1.6, 0.0, 0.0], 0.5, 0.5)
    result = await api.go_home()  # no arguments: it failed with 422 over HTTP before
    assert isinstance(result, MoveResult)
    assert result.joint_error < 1e-3
    assert result.target_joints == pytest.approx((0, -1.5708, 0, -1.5708, 0, 0), abs=1e-4)

    first = asyncio.create_task(api.move_joint([0.6, -1.4, 0.2, -1.6, 0.0, 0.0], 0.2, 0.2))

    async def streaming() -> bool:
        return max(abs(v) for v in await api.get_velocity()) > 0.01

    await until(streaming, "the first move to stream")
    queued = asyncio.create_task(api.go_home(queue=True))
    cell = request.node.stash[CELL]  # the Cell behind `api` (itself, or the daemon's)
    await until(cell._move_queue.locked, "go_home(queue=True) to wait in the Cell's queue")
    assert await api.stop() is True
    with pytest.raises(MoveStoppedError):
        await first
    with pytest.raises(MoveStoppedError, match="waiting in the queue"):
        await queued  # ended in the queue: it never started
    # Nor does anything start later: the arm rests 0.3 s of the simulator's time on.
    await controller_time_passes(shared_sim, 0.3)
    assert max(abs(v) for v in await api.get_velocity()) < 1e-4


async def test_gripper_commands_answer_the_same_on_both(api: CellCommands) -> None:
    with pytest.raises(InvalidStateError):
        await api.gripper_activate()  # the arm is off: no tool power
    await api.init()
    await api.gripper_activate()
    opened = await api.gripper_open()
    assert isinstance(opened, GripResult)
    assert opened == GripResult(pytest.approx(0.05), False)  # type: ignore[arg-type]
    moved = await api.gripper_move(0.02, speed=0.15, grip_force=50.0)
    assert moved.width == pytest.approx(0.02, abs=2e-4)
    assert await api.get_gripper_width() == pytest.approx(0.02, abs=2e-4)
    with pytest.raises(NothingGraspedError):
        await api.gripper_close(expect_object=True)
    with pytest.raises(InvalidArgumentError):
        await api.gripper_move(0.08)


async def test_a_command_whose_argument_is_called_name_runs_through_run_command(
    fake_cell: Any,
) -> None:
    # run_command takes the command's name positionally: move_to's and teach's own argument
    # is called ``name`` too (the daemon and the SiLA server call them so).
    await fake_cell.init()
    taught = await fake_cell.run_command("teach", name="p1")
    assert taught["joints"]
    result = await fake_cell.run_command("move_to", name="p1")
    assert result.target_joints == pytest.approx(taught["joints"])
