"""Cell moves against the simulator: the seed's kinematic tests (thesis § 5.4.1) and more.

Every test runs the real ur_rtde clients (in the robot-link process) against the embedded
simulator, which executes the streamed servoJ setpoints in real time; motions are kept
short. One simulator serves the module; each test opens its own Cell with the arm placed
where the test starts.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator, Iterator, Sequence

import numpy as np
import pytest

from fxcell.cell import Cell
from fxcell.cell.statemachine import CellState
from fxcell.config import CellConfig
from fxcell.errors import (
    CollisionError,
    FxcellError,
    InvalidFactorError,
    InvalidTargetError,
    MoveInProgressError,
    MoveStoppedError,
    SimulatorError,
    UnreachableError,
)
from fxcell.events import MotionEvent
from fxcell.geometry import Pose
from fxcell.link.capabilities import UR3E
from fxcell.motion.trajectory import Limits, braking
from fxcell.testing import SimulatorHandle, brisk, simulator

CONFIG = brisk(CellConfig.load())  # the arm's pace is not these tests' subject
HOME = np.array(CONFIG.home)
LIMITS = Limits.from_config(CONFIG.limits, period=UR3E.sample_period)
BRAKING = Limits.for_braking(CONFIG.limits, period=UR3E.sample_period)
WORK = np.array([0.4, -1.4, 1.6, -1.8, -1.57, 0.0])  # gripper down over the table
POSITION_TOL = 1e-5  # m
ANGLE_TOL = 1e-4  # rad

# The seed's test pose (thesis § 5.3.5: x, y, z, qx, qy, qz, qw; gripper 2 cm above the
# table) and two more in the other notations.
SEED_POSE = [-0.22747267772, -0.2785657474, 0.0210341579,
             -0.707827193654, -0.706385380384, -0.000130225001698, 0.000584248530499]  # fmt: skip
POSES: list[object] = [
    SEED_POSE,
    [-0.25, -0.20, 0.12, math.pi, 0.0, 0.3],  # x, y, z, roll, pitch, yaw
    Pose([-0.30, -0.12, 0.18], Pose.from_rpy([0, 0, 0], [math.pi, 0.2, 0.0]).rotation),
]


class _Simulators:
    """One simulator for the module; a test that leaves it unusable (a safety stop, an arm
    still moving) fails the next one, never replaced by a fresh one."""

    def __init__(self) -> None:
        self.handle: SimulatorHandle | None = None

    def get(self, joints: Sequence[float]) -> SimulatorHandle:
        if self.handle is None:
            self.handle = simulator().start()
        state = self.handle.state()
        if str(state["safety_mode"]) != "NORMAL":
            raise SimulatorError(f"the module's simulator was left in {state['safety_mode']}")
        self.handle.set_joints(list(joints))
        return self.handle


@pytest.fixture(scope="module")
def simulators() -> Iterator[_Simulators]:
    pool = _Simulators()
    yield pool
    if pool.handle is not None:
        pool.handle.stop()


@pytest.fixture
def sim(simulators: _Simulators) -> _Simulators:
    return simulators


@contextlib.asynccontextmanager
async def ready_cell(
    sim: _Simulators, joints: Sequence[float] = WORK, *, velocity_factor: float = 0.3
) -> AsyncIterator[Cell]:
    """A Cell in external control with the arm resting at ``joints``.

    Moves default to 0.3 of full speed: the simulator treats a servoJ setpoint jump of more
    than 1.5× a joint's speed limit as a violation, and a simulator process stalled by a
    busy machine sees several setpoints at once.
    """
    handle = sim.get(joints)
    async with Cell(handle.host, config=CONFIG) as cell:
        await cell.init()
        await cell.set_velocity_factor(velocity_factor)
        yield cell


def pose_errors(actual: Pose, target: object) -> tuple[float, float]:
    t = target if isinstance(target, Pose) else Pose.parse(target)
    return float(np.linalg.norm(actual.position - t.position)), actual.angle_to(t)


async def current_pose(cell: Cell) -> Pose:
    x, y, z, qx, qy, qz, qw = await cell.get_current_pose()
    return Pose.from_quaternion([x, y, z], [qx, qy, qz, qw])


async def wait_until_moving(cell: Cell, joint: int, speed: float, within: float = 5.0) -> None:
    async with asyncio.timeout(within):
        with cell.robot_states() as states:
            async for s in states:
                if abs(s.actual_qd[joint]) > speed:
                    return


async def assert_at_rest(cell: Cell) -> None:
    qd = await cell.get_velocity()
    assert max(map(abs, qd)) < 1e-3, qd


# ----------------------------------------------------------------- the seed's tests


async def test_move_joint_reaches_three_joint_targets(sim: _Simulators) -> None:
    targets = [
        WORK + np.array([0.3, 0.1, -0.2, 0.1, 0.2, 0.5]),
        WORK + np.array([-0.2, 0.0, 0.1, -0.3, 0.0, -0.4]),
        WORK,
    ]
    async with ready_cell(sim) as cell:
        for target in targets:
            result = await cell.move_joint(list(target))
            joints = np.array(await cell.get_current_joint_values())
            assert np.max(np.abs(joints - target)) < 1e-5
            assert result.joint_error < 1e-5
            assert result.planner == "direct"
            assert result.executed_duration >= result.planned_duration * 0.9
            # follows the plan (the figure includes a few ms of timing uncertainty)
            assert result.max_tracking_error < 0.03
            await assert_at_rest(cell)


async def test_a_cell_on_ur_rtdes_receive_interface_reaches_its_target(sim: _Simulators) -> None:
    robot = CONFIG.robot.model_copy(update={"receiver": "ur_rtde"})
    config = CONFIG.model_copy(update={"robot": robot})
    handle = sim.get(WORK)
    async with Cell(handle.host, config=config) as cell:
        await cell.init()
        target = WORK + np.array([0.2, -0.1, 0.1, 0.0, 0.0, 0.0])
        result = await cell.move_joint(list(target), velocity_factor=0.3)
        assert result.joint_error < 1e-5
        assert result.position_error < 1e-5


async def test_go_home_reaches_the_home_joints(sim: _Simulators) -> None:
    async with ready_cell(sim, HOME + np.array([0.3, 0.2, -0.3, 0.2, 0.3, -0.4])) as cell:
        result = await cell.go_home()
        joints = np.array(await cell.get_current_joint_values())
        assert np.max(np.abs(joints - HOME)) < 1e-5
        np.testing.assert_allclose(result.target_joints, HOME)


async def test_move_pose_reaches_three_poses(sim: _Simulators) -> None:
    async with ready_cell(sim) as cell:
        for target in POSES:
            result = await cell.move_pose(target)
            position_error, angle_error = pose_errors(await current_pose(cell), target)
            assert position_error <= POSITION_TOL
            assert angle_error <= ANGLE_TOL
            assert result.position_error <= POSITION_TOL


async def test_a_reached_pose_fed_back_into_move_pose_stays_put(sim: _Simulators) -> None:
    async with ready_cell(sim) as cell:
        first = await cell.move_pose(POSES[1])
        # q and -q are the same rotation: with w ≈ 0 rounding picks either sign
        position_error, angle_error = pose_errors(await current_pose(cell), first.reached_pose)
        assert position_error <= 1e-6
        assert angle_error <= 1e-6
        again = await cell.move_pose(first.reached_pose)
        # A rotation vector read as roll, pitch, yaw was 0.71 rad off here.
        assert again.orientation_error <= ANGLE_TOL
        assert pose_errors(Pose.parse(again.reached_pose), first.reached_pose)[1] <= ANGLE_TOL
        assert np.max(np.abs(np.subtract(again.reached_joints, first.reached_joints))) < 1e-4


async def test_move_distance_moves_the_tcp_by_the_vector(sim: _Simulators) -> None:
    async with ready_cell(sim) as cell:
        for target in POSES:
            await cell.move_pose(target)
            before = await current_pose(cell)
            result = await cell.move_distance([0.005, 0.005, 0.005])
            after = await current_pose(cell)
            moved = after.position - before.position
            assert np.max(np.abs(moved - 0.005)) <= POSITION_TOL
            assert after.angle_to(before) <= ANGLE_TOL
            assert result.planner == "cartesian"


async def test_stop_during_a_quarter_turn_of_the_base_brakes_to_rest(
    sim: _Simulators,
) -> None:
    target = HOME + np.array([math.pi / 2, 0, 0, 0, 0, 0])
    async with ready_cell(sim, HOME) as cell:
        move = asyncio.create_task(cell.move_joint(list(target)))
        await wait_until_moving(cell, 0, 0.5)
        assert cell.robot_state is not None
        at_stop = cell.robot_state
        assert await cell.stop() is True
        with pytest.raises(MoveStoppedError) as info:
            await move
        await assert_at_rest(cell)
        q0 = (await cell.get_current_joint_values())[0]
        # It braked on the jerk-limited profile: no farther than the braking distance from
        # its speed then (plus what the acceleration at that moment can add).
        speed = abs(at_stop.actual_qd[0])
        bound = braking(
            at_stop.actual_q,
            [speed, 0, 0, 0, 0, 0],
            [CONFIG.limits.acceleration[0], 0, 0, 0, 0, 0],
            BRAKING,
        )
        assert q0 - at_stop.actual_q[0] <= bound.positions[-1][0] - at_stop.actual_q[0] + 0.05
        assert info.value.result.stopped  # type: ignore[attr-defined]
        assert 0.1 < q0 < math.pi / 2 - 0.1  # stopped on the way, not at either end
        await cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY, timeout=2.0)
        # and the cell moves again
        result = await cell.move_joint(list(HOME + np.array([q0 + 0.05, 0, 0, 0, 0, 0])))
        assert result.joint_error < 1e-5


@pytest.mark.parametrize("setter", ["set_velocity_factor", "set_acceleration_factor"])
async def test_factors_outside_the_unit_interval_are_refused(sim: _Simulators, setter: str) -> None:
    getter = setter.replace("set_", "get_")
    async with ready_cell(sim) as cell:
        for bad in [-5, -1.4, 0, 2, 10, math.nan, math.inf, "0.5", None, [0.5]]:
            with pytest.raises(InvalidFactorError) as info:
                await getattr(cell, setter)(bad)
            assert isinstance(info.value, ValueError)
            assert isinstance(info.value, FxcellError)
            assert await getattr(cell, getter)() == (0.3 if "velocity" in setter else 1.0)
        for good in np.linspace(0.1, 1.0, 10):
            await getattr(cell, setter)(float(good))
            assert await getattr(cell, getter)() == pytest.approx(good)
        before = await cell.get_current_joint_values()
        with pytest.raises(InvalidFactorError):
            await cell.move_joint(list(WORK + 0.2), **{setter[4:]: 2.0})
        assert await cell.get_current_joint_values() == before
        await assert_at_rest(cell)


async def test_max_acceleration_is_the_configured_limit(sim: _Simulators) -> None:
    async with ready_cell(sim) as cell:
        assert await cell.get_max_acceleration() == tuple(CONFIG.limits.acceleration)


# ----------------------------------------------------------------- beyond the seed


async def test_lower_factors_slow_the_move_down(sim: _Simulators) -> None:
    async with ready_cell(sim, velocity_factor=1.0) as cell:
        fast = await cell.move_joint(list(WORK + np.array([0.3, 0, 0, 0, 0, 0])))
        await cell.set_velocity_factor(0.3)
        await cell.set_acceleration_factor(0.3)
        slow = await cell.move_joint(list(WORK))
        assert slow.planned_duration > 1.3 * fast.planned_duration
        assert slow.joint_error < 1e-5


async def test_move_relative_goes_to_the_start_then_the_target_pose(sim: _Simulators) -> None:
    start = [-0.25, -0.20, 0.12, math.pi, 0.0, 0.0]
    target = [-0.22, -0.24, 0.08, math.pi, 0.0, 0.2]
    async with ready_cell(sim) as cell:
        events: list[MotionEvent] = []
        unsubscribe = cell.bus.subscribe(
            lambda e: events.append(e) if isinstance(e, MotionEvent) else None
        )
        result = await cell.move_relative(start, target)
        unsubscribe()
        position_error, angle_error = pose_errors(await current_pose(cell), target)
        assert position_error <= POSITION_TOL
        assert angle_error <= ANGLE_TOL
        results = [e for e in events if e.kind == "result"]
        assert len(results) == 2  # two legs
        first = Pose.parse(results[0].data["reached_pose"])
        assert pose_errors(first, start)[0] <= POSITION_TOL
        assert result.reached_pose == results[1].data["reached_pose"]


async def test_linear_move_pose_keeps_the_tcp_on_the_straight_line(sim: _Simulators) -> None:
    async with ready_cell(sim) as cell:
        await cell.move_pose(POSES[1])
        start = await current_pose(cell)
        target = Pose(start.position + np.array([0.06, -0.04, 0.03]), start.rotation)
        worst = 0.0
        with cell.robot_states() as states:
            move = asyncio.create_task(cell.move_pose(target, linear=True))
            while not move.done():
                async with asyncio.timeout(1.0):
                    s = await states.__anext__()
                p = Pose.from_ur(s.actual_tcp_pose).position  # the controller's own TCP
                d = target.position - start.position
                u = np.clip((p - start.position) @ d / (d @ d), 0, 1)
                worst = max(worst, float(np.linalg.norm(p - start.position - u * d)))
            result = await move
        assert result.planner == "cartesian"
        assert worst < 5e-4  # within half a millimetre of the line all the way
        position_error, angle_error = pose_errors(await current_pose(cell), target)
        assert position_error <= POSITION_TOL
        assert angle_error <= ANGLE_TOL


LEFT_OF_MACHINE = [-1.042, -1.271, 1.482, -1.781, -1.571, 2.099]
RIGHT_OF_MACHINE = [-2.792, -1.255, 1.46, -1.776, -1.571, 0.35]


async def test_a_move_blocked_by_the_fusion_machine_goes_around_it(sim: _Simulators) -> None:
    async with ready_cell(sim, LEFT_OF_MACHINE) as cell:
        paths: list[MotionEvent] = []
        cell.bus.subscribe(
            lambda e: paths.append(e) if isinstance(e, MotionEvent) and e.kind == "path" else None
        )
        result = await cell.move_joint(RIGHT_OF_MACHINE)
        assert result.planner == "RRTConnect"
        assert len(paths[0].data["waypoints"]) >= 3
        assert result.joint_error < 1e-5
        assert cell.state is not CellState.PROTECTIVE_STOP


async def test_cancelling_the_move_task_brakes_the_robot(sim: _Simulators) -> None:
    async with ready_cell(sim, HOME) as cell:
        move = asyncio.create_task(cell.move_joint(list(HOME + np.array([1.2, 0, 0, 0, 0, 0]))))
        await wait_until_moving(cell, 0, 0.4)
        move.cancel()
        with pytest.raises(asyncio.CancelledError):
            await move
        await assert_at_rest(cell)
        q0 = (await cell.get_current_joint_values())[0]
        assert 0.05 < q0 < 1.15
        await cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY, timeout=2.0)


async def test_a_second_move_while_one_runs_is_refused(sim: _Simulators) -> None:
    async with ready_cell(sim, HOME) as cell:
        move = asyncio.create_task(cell.move_joint(list(HOME + np.array([0.6, 0, 0, 0, 0, 0]))))
        await wait_until_moving(cell, 0, 0.1)
        with pytest.raises(MoveInProgressError):
            await cell.move_joint(list(HOME))
        result = await move  # the first move is unaffected
        assert result.joint_error < 1e-5


async def test_a_move_whose_encoders_never_read_exactly_on_target_still_arrives(
    sim: _Simulators,
) -> None:
    async with ready_cell(sim) as cell:
        cell.motion.options.settle_position = -1.0  # never close enough: the hold runs out
        result = await cell.move_joint(list(WORK + np.array([0.1, 0, 0, 0, 0, 0])))
        assert not result.stopped
        assert result.joint_error <= cell.motion.options.arrive_tolerance


async def test_a_queued_move_starts_when_the_running_one_ends(sim: _Simulators) -> None:
    first = HOME + np.array([0.4, 0, 0, 0, 0, 0])
    second = HOME + np.array([0.4, 0.2, 0, 0, 0, 0])
    async with ready_cell(sim, HOME) as cell:
        paths: list[MotionEvent] = []
        cell.bus.subscribe(
            lambda e: paths.append(e) if isinstance(e, MotionEvent) and e.kind == "path" else None
        )
        running = asyncio.create_task(cell.move_joint(list(first)))
        await wait_until_moving(cell, 0, 0.1)
        queued = await cell.move_joint(list(second), queue=True)
        done = await running
        np.testing.assert_allclose(done.reached_joints, first, atol=1e-5)
        np.testing.assert_allclose(queued.reached_joints, second, atol=1e-5)
        # the queued move was planned from where the first one ended
        assert len(paths) == 2
        np.testing.assert_allclose(paths[1].data["start_joints"], first, atol=1e-5)


BAD_TARGETS: list[tuple[str, dict[str, object], type[Exception]]] = [
    ("move_joint", {"target": [0.4, -1.4, 1.6, math.nan, -1.57, 0.0]}, InvalidTargetError),
    ("move_joint", {"target": [0.4, -1.4, 1.6, -1.8, -1.57, 7.0]}, InvalidTargetError),
    ("move_joint", {"target": [0.0, -1.57, 2.6, 0.0, 0.0, 0.0]}, CollisionError),
    ("move_pose", {"target": [0.9, 0.0, 0.2, math.pi, 0.0, 0.0]}, UnreachableError),
    ("move_pose", {"target": [-0.25, -0.25, -0.02, math.pi, 0.0, 0.0]}, CollisionError),
    ("move_pose", {"target": [0.0, 0.40, 0.10, math.pi, 0.0, 0.0]}, CollisionError),
    ("move_pose", {"target": [-0.25, -0.25, math.inf, math.pi, 0, 0]}, InvalidTargetError),
    ("move_distance", {"distance": [0.0, 0.0, -0.2]}, CollisionError),  # into the table
    ("move_distance", {"distance": [0.0, math.nan, 0.0]}, ValueError),
]


async def test_bad_targets_are_refused_before_anything_moves(sim: _Simulators) -> None:
    async with ready_cell(sim) as cell:
        streamed: list[MotionEvent] = []
        cell.bus.subscribe(
            lambda e: (
                streamed.append(e)
                if isinstance(e, MotionEvent) and e.kind == "trajectory"
                else None
            )
        )
        before = await cell.get_current_joint_values()
        for method, kwargs, error in BAD_TARGETS:
            with pytest.raises(error):
                await getattr(cell, method)(**kwargs)
            assert await cell.get_current_joint_values() == before, (method, kwargs)
        assert streamed == []
        await assert_at_rest(cell)
