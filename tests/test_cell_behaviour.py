"""The shared Cell behaviour suite: the same tests, unchanged, on every robot kind fxcell
ships (the UR3e and the Ned2), each on its embedded simulator. A command the kind cannot
do is skipped by the command table (its features), never by the test's own choice, and
checked to be refused instead.

What each test asserts is robot-neutral: targets are reached by the robot's own joints
and the Cell's pose, poses are taken from the arm itself (move to joints, read the pose,
go elsewhere, come back by pose), and a stop is judged by the arm at rest short of its
target."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from fxcell import Cell, CellState
from fxcell.commands import COMMANDS
from fxcell.config import CellConfig, JointLimits, SceneConfig, SceneObject
from fxcell.errors import (
    FxcellError,
    InvalidArgumentError,
    MoveStoppedError,
    UnreachableError,
    UnsupportedCommandError,
)
from fxcell.geometry import Pose
from fxcell.motion import ned2
from fxcell.robots import kind_names, register, robot_kind, unregister
from fxcell.robots.ned2 import NED2_KIND
from fxcell.testing import simulator
from fxcell.testing.handles import ProcessHandle
from fxcell.testing.ned2 import ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

POSITION_TOLERANCE = 1e-3  # m: a pose move lands within 1 mm by the Cell's own pose
JOINT_TOLERANCE = 1e-4  # rad


@dataclass(frozen=True)
class Arm:
    """What the suite needs to know of a kind: two collision-free joint positions far
    enough apart that a move between them is under way for a while, and its config."""

    kind: str
    config: CellConfig
    a: tuple[float, ...]
    b: tuple[float, ...]


def _ur3e() -> Arm:
    return Arm(
        "ur3e",
        CellConfig.load(),
        (0.0, -1.8, 1.4, -1.2, -1.57, 0.0),
        (0.9, -1.4, 1.0, -1.2, -1.57, 0.5),
    )


def _ned2() -> Arm:
    limits = JointLimits(
        position_min=tuple(ned2.LOWER),
        position_max=tuple(ned2.UPPER),
        velocity=tuple(ned2.VELOCITY_LIMITS),
        acceleration=tuple(ned2.ACCELERATION_LIMITS),
    )
    config = CellConfig()
    table = SceneObject(name="table", size=(1.0, 1.0, 0.05), position=(0.0, 0.0, -0.025))
    config = config.model_copy(
        update={
            "robot": config.robot.model_copy(update={"kind": "ned2"}),
            "tool": config.tool.model_copy(update={"tcp": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)}),
            "home": (0.0, 0.3, -1.3, 0.0, 0.0, 0.0),
            "limits": limits,
            "scene": SceneConfig(objects=(table,)),
        }
    )
    return Arm("ned2", config, (0.0, 0.3, -0.6, 0.0, -0.8, 0.0), (0.8, 0.1, -0.4, 0.3, -0.9, 0.4))


@pytest.fixture(scope="module")
def _ned2_registered() -> Iterator[None]:
    added = "ned2" not in kind_names()
    if added:
        register(NED2_KIND)
    try:
        yield
    finally:
        if added:
            unregister("ned2")


@pytest.fixture(scope="module", params=["ur3e", "ned2"])
def arm(request: pytest.FixtureRequest) -> Iterator[tuple[Arm, ProcessHandle]]:
    """One simulator per kind for the module (the Cell is opened afresh per test)."""
    if request.param == "ur3e":
        with simulator(time_scale=0.05) as sim:
            yield _ur3e(), sim
    else:
        request.getfixturevalue("_ned2_registered")
        with ned2_simulator(time_scale=1.0, calibrated=True) as ned2_sim:
            yield _ned2(), ned2_sim


@pytest.fixture
async def cell(arm: tuple[Arm, ProcessHandle]) -> AsyncIterator[Cell]:
    spec, sim = arm
    host = getattr(sim, "host")  # noqa: B009 - both handles name their controller's address
    async with Cell(config=spec.config, host=host, record=None) as c:
        await c.init()
        assert c.state is CellState.EXTERNAL_CONTROL_READY
        yield c


@pytest.fixture
def spec(arm: tuple[Arm, ProcessHandle]) -> Arm:
    return arm[0]


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


def test_the_suite_covers_every_kind_fxcell_registers() -> None:
    # a kind registered without joining this suite's parameters fails here
    shipped = {"ur3e", "ned2"}
    assert set(kind_names()) - {"ned2"} <= shipped
    assert robot_kind("ur3e").name == "ur3e"
    assert issubclass(UnsupportedCommandError, FxcellError)
