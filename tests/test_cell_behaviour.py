"""The shared Cell behaviour suite: the same tests, unchanged, on every robot kind fxcell
ships (the UR3e and the Ned2), each on its embedded simulator. A command the kind cannot
do is skipped by the command table (its features), never by the test's own choice, and
checked to be refused instead. Each kind runs on its shipped cell (`config/cell.yaml`,
`config/ned2-cell.yaml`).

What each test asserts is robot-neutral: targets are reached by the robot's own joints
and the Cell's pose, poses are taken from the arm itself (move to joints, read the pose,
go elsewhere, come back by pose), and a stop is judged by the arm at rest short of its
target."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from fxcell import Cell, CellState
from fxcell.commands import COMMANDS
from fxcell.config import CONFIG_DIR, CellConfig
from fxcell.errors import (
    InvalidArgumentError,
    MoveStoppedError,
    UnreachableError,
    UnsupportedCommandError,
)
from fxcell.geometry import Pose
from fxcell.layout import Layout, Station
from fxcell.robots import kind_names
from fxcell.testing import SimulatorHandle, brisk, simulator
from fxcell.testing.ned2 import Ned2SimulatorHandle, ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

POSITION_TOLERANCE = 1e-3  # m: a pose move lands within 1 mm by the Cell's own pose
JOINT_TOLERANCE = 1e-4  # rad


@dataclass(frozen=True)
class Arm:
    """What the suite needs to know of a kind: its shipped cell (with a lamp output and
    quicker limits where the shipped ones are the seed's slow ones), two collision-free
    joint positions far enough apart that a move between them is under way for a while,
    a slot to pick from and one to place at, and how its simulator is given an object and
    tells where the object is."""

    kind: str
    config: CellConfig
    a: tuple[float, ...]
    b: tuple[float, ...]
    pick: tuple[str, str]
    place: tuple[str, str]
    put: Callable[[Any, str, Station, str], None]
    where: Callable[[Any, str], np.ndarray]


def _ur3e_put(sim: SimulatorHandle, name: str, station: Station, slot: str) -> None:
    obj, grip = station.kind, station.grip_pose(slot).position
    sim.add_object(
        name, station.config.holds, width=obj.width, height=obj.height, mass=obj.mass,
        position=grip.tolist(),
    )  # fmt: skip


def _ned2_put(sim: Ned2SimulatorHandle, name: str, station: Station, slot: str) -> None:
    sim.add_object(name, station.grip_pose(slot).position.tolist(), station.kind.width)


def _ur3e() -> Arm:
    config = CellConfig.load()
    io = config.io.model_copy(update={"signals": {**config.io.signals, "lamp": "DO5"}})
    return Arm(
        "ur3e",
        brisk(config).model_copy(update={"io": io}),
        (0.0, -1.8, 1.4, -1.2, -1.57, 0.0),
        (0.9, -1.4, 1.0, -1.2, -1.57, 0.5),
        ("rack", "B2"),
        ("rack", "C3"),
        _ur3e_put,
        lambda sim, name: np.array(sim.objects()[name]["pose"][:3]),
    )


def _ned2() -> Arm:
    config = CellConfig.load(CONFIG_DIR / "ned2-cell.yaml")
    io = config.io.model_copy(update={"signals": {**config.io.signals, "lamp": "DO2"}})
    return Arm(
        "ned2",
        config.model_copy(update={"io": io}),
        (0.0, 0.3, -0.6, 0.0, -0.8, 0.0),
        (0.8, 0.1, -0.4, 0.3, -0.9, 0.4),
        ("rack", "A2"),
        ("rack", "C3"),
        _ned2_put,
        lambda sim, name: np.array(sim.state()["objects"][name]),
    )


@pytest.fixture(scope="module", params=["ur3e", "ned2"])
def arm(request: pytest.FixtureRequest) -> Iterator[tuple[Arm, Any]]:
    """One simulator per kind for the module (the Cell is opened afresh per test)."""
    if request.param == "ur3e":
        with simulator(time_scale=0.2) as sim:
            yield _ur3e(), sim
    else:
        with ned2_simulator(time_scale=1.0, calibrated=True) as ned2_sim:
            yield _ned2(), ned2_sim


@pytest.fixture
async def cell(arm: tuple[Arm, Any]) -> AsyncIterator[Cell]:
    spec, sim = arm
    async with Cell(config=spec.config, host=sim.host, record=None) as c:
        await c.init()
        assert c.state is CellState.EXTERNAL_CONTROL_READY
        yield c
        if c.held is not None:
            await c.gripper_open()


@pytest.fixture
def spec(arm: tuple[Arm, Any]) -> Arm:
    return arm[0]


@pytest.fixture
def sim(arm: tuple[Arm, Any]) -> Any:
    return arm[1]


def _supported(cell: Cell, command: str) -> None:
    if not cell.kind.capabilities.supports(command):
        pytest.skip(
            f"a {cell.kind.name} cannot {command} (command table: {COMMANDS[command].requires})"
        )


def _near(actual: tuple[float, ...], target: tuple[float, ...]) -> float:
    return Pose.parse(actual).distance(Pose.parse(target))


async def test_init_is_idempotent(cell: Cell) -> None:
    await cell.init()
    assert cell.state is CellState.EXTERNAL_CONTROL_READY


async def test_move_joint_lands_on_its_target_by_the_robots_own_joints(
    cell: Cell, spec: Arm
) -> None:
    result = await cell.move_joint(list(spec.a))
    assert result.joint_error < JOINT_TOLERANCE
    joints = await cell.get_current_joint_values()
    assert np.max(np.abs(np.subtract(joints, spec.a))) < JOINT_TOLERANCE


async def test_the_state_streams_the_tcp_pose_the_cell_reports(cell: Cell, spec: Arm) -> None:
    # the page, the recorder and the daemon's status show the streamed pose: the configured
    # TCP, as get_current_pose (the planner's model) has it
    await cell.move_joint(list(spec.a))
    with cell.robot_states(maxsize=1) as states:
        async with asyncio.timeout(2.0):
            sample = await anext(aiter(states))
    streamed = Pose.from_ur(sample.actual_tcp_pose)
    reported = Pose.parse(await cell.get_current_pose())
    assert streamed.distance(reported) < 1e-4
    assert streamed.angle_to(reported) < 1e-4


async def test_go_home_goes_to_the_configured_home(cell: Cell, spec: Arm) -> None:
    await cell.move_joint(list(spec.a))
    await cell.go_home()
    joints = await cell.get_current_joint_values()
    assert np.max(np.abs(np.subtract(joints, spec.config.home))) < JOINT_TOLERANCE


@pytest.mark.parametrize("linear", [False, True], ids=["joint-space", "linear"])
async def test_move_pose_comes_back_to_a_pose_read_from_the_arm(
    cell: Cell, spec: Arm, linear: bool
) -> None:
    await cell.move_joint(list(spec.a))
    pose = await cell.get_current_pose()
    await cell.move_joint(list(spec.b))
    assert _near(await cell.get_current_pose(), pose) > 0.02
    await cell.move_pose(pose, linear=linear)
    assert _near(await cell.get_current_pose(), pose) < POSITION_TOLERANCE
    assert Pose.parse(await cell.get_current_pose()).angle_to(Pose.parse(pose)) < 1e-3


async def test_move_distance_moves_the_tcp_by_the_distance(cell: Cell, spec: Arm) -> None:
    await cell.move_joint(list(spec.a))
    before = Pose.parse(await cell.get_current_pose())
    await cell.move_distance([0.02, 0.0, -0.03])
    after = Pose.parse(await cell.get_current_pose())
    moved = after.position - before.position
    assert np.linalg.norm(moved - [0.02, 0.0, -0.03]) < POSITION_TOLERANCE
    assert after.angle_to(before) < 1e-3


async def test_move_relative_visits_both_poses(cell: Cell, spec: Arm) -> None:
    await cell.move_joint(list(spec.a))
    first = await cell.get_current_pose()
    await cell.move_joint(list(spec.b))
    second = await cell.get_current_pose()
    await cell.go_home()
    await cell.move_relative(first, second)
    assert _near(await cell.get_current_pose(), second) < POSITION_TOLERANCE


async def test_a_stop_brakes_the_arm_to_rest_short_of_its_target(cell: Cell, spec: Arm) -> None:
    await cell.move_joint(list(spec.a))
    move = asyncio.create_task(cell.move_joint(list(spec.b)))
    async with asyncio.timeout(10.0):
        with cell.robot_states(maxsize=8) as states:
            async for sample in states:
                if np.max(np.abs(sample.actual_qd)) > 0.2:
                    break
    assert await cell.stop() is True
    with pytest.raises(MoveStoppedError):
        await move
    with cell.robot_states(maxsize=1) as states:  # stop() returns with the arm at rest
        async with asyncio.timeout(2.0):
            sample = await anext(aiter(states))
    assert np.max(np.abs(sample.actual_qd)) < 1e-3
    joints = await cell.get_current_joint_values()
    assert np.max(np.abs(np.subtract(joints, spec.b))) > 0.05  # short of the target
    assert cell.state is CellState.EXTERNAL_CONTROL_READY
    await cell.move_joint(list(spec.b))  # and it moves again


async def test_factors_are_kept_and_bad_ones_refused_before_anything_moves(cell: Cell) -> None:
    await cell.set_velocity_factor(0.5)
    await cell.set_acceleration_factor(0.25)
    assert await cell.get_velocity_factor() == 0.5
    assert await cell.get_acceleration_factor() == 0.25
    sent = cell._link().messages_sent
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(InvalidArgumentError):
            await cell.set_velocity_factor(bad)
    assert await cell.get_velocity_factor() == 0.5
    assert cell._link().messages_sent == sent


async def test_an_unreachable_pose_is_refused_and_nothing_moves(cell: Cell, spec: Arm) -> None:
    await cell.move_joint(list(spec.a))
    before = await cell.get_current_joint_values()
    sent = cell._link().messages_sent
    with pytest.raises(UnreachableError):
        await cell.move_pose([5.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    assert cell._link().messages_sent == sent
    # still by the robot's own joints (a settled arm's readings wander by ~1e-8 rad)
    assert await cell.get_current_joint_values() == pytest.approx(before, abs=1e-6)


async def test_freedrive_starts_and_stops(cell: Cell) -> None:
    _supported(cell, "freedrive_start")
    await cell.freedrive_start()
    assert cell.state is CellState.FREEDRIVE
    await cell.freedrive_stop()
    await cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY)


async def test_what_the_kind_cannot_do_is_refused_naming_it(cell: Cell) -> None:
    unsupported = sorted(cell.kind.capabilities.unsupported)
    assert unsupported == sorted(n for n in COMMANDS if not cell.kind.capabilities.supports(n))
    sent = cell._link().messages_sent
    for name in unsupported:
        with pytest.raises(UnsupportedCommandError, match=cell.kind.name):
            await cell.run_command(name)
    assert cell._link().messages_sent == sent
    assert cell.state is CellState.EXTERNAL_CONTROL_READY


async def test_the_gripper_opens_and_closes_on_nothing(cell: Cell) -> None:
    _supported(cell, "gripper_close")
    await cell.gripper_activate()
    opened = await cell.gripper_open()
    assert not opened.holding
    assert opened.width > 0.02
    closed = await cell.gripper_close()
    assert not closed.holding
    assert closed.width < 1e-3
    assert await cell.get_gripper_width() == pytest.approx(closed.width, abs=1e-3)


async def test_an_output_set_by_its_configured_name_reads_back(cell: Cell) -> None:
    _supported(cell, "io_set")
    for level in (True, False):
        await cell.io_set("lamp", level)
        assert (await cell.get_io())["lamp"] is level


async def test_an_object_picked_from_a_slot_lands_in_another_within_1_mm(
    cell: Cell, spec: Arm, sim: Any
) -> None:
    _supported(cell, "pick")
    layout = Layout(spec.config.layout)
    source, target = layout.station(spec.pick[0]), layout.station(spec.place[0])
    await cell.gripper_activate()
    await asyncio.to_thread(spec.put, sim, "sample-1", source, spec.pick[1])
    picked = await cell.pick(*spec.pick)
    assert picked.holding
    holding = cell.held
    assert holding == source.config.holds
    released = await cell.place(*spec.place)
    assert not released.holding
    assert cell.held is None
    landed = await asyncio.to_thread(spec.where, sim, "sample-1")
    assert np.linalg.norm(landed - target.grip_pose(spec.place[1]).position) < POSITION_TOLERANCE


def test_the_suite_runs_on_every_kind_fxcell_ships() -> None:
    # a kind registered without joining this suite's parameters fails here
    assert set(kind_names()) == {_ur3e().kind, _ned2().kind}
