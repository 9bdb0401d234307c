"""MotionPlanner: every bad target is refused before anything moves; good ones are planned."""

from __future__ import annotations

import asyncio
import math
from typing import Any

import numpy as np
import pytest

from fxcell.config import CellConfig
from fxcell.errors import (
    CollisionError,
    FxcellError,
    InvalidArgumentError,
    InvalidFactorError,
    InvalidTargetError,
    UnreachableError,
)
from fxcell.geometry import Pose
from fxcell.link.capabilities import UR3E
from fxcell.motion.moves import MotionController, MotionPlanner, MovePlan, lead_setpoints
from fxcell.motion.runner import (
    DistanceTarget,
    JointTarget,
    MoveTarget,
    PoseTarget,
    RelativeTarget,
)
from fxcell.motion.trajectory import Limits, rest_to_rest

CONFIG = CellConfig.load()
DT = UR3E.sample_period  # the UR3e's trajectories: one sample per 2 ms servo cycle
HOME = np.array(CONFIG.home)
DOWN = Pose.from_rpy([0, 0, 0], [math.pi, 0, 0])
WORK = np.array([0.4, -1.4, 1.6, -1.8, -1.57, 0.0])  # gripper down over the table


@pytest.fixture(scope="module")
def planner() -> MotionPlanner:
    return MotionPlanner(CONFIG)


@pytest.mark.parametrize(
    "target",
    [
        [0, -1.5, 0, -1.5, 0, math.nan],
        [0, -1.5, 0, -1.5, 0, math.inf],
        [0, -1.5, 0, -1.5, 0],
        [0, -1.5, 0, -1.5, 0, 0, 0],
        "home",
        None,
        [0, -1.5, 0, -1.5, 0, "x"],
        [7.0, -1.5, 0, -1.5, 0, 0],  # beyond +2π
        [0, -1.5, 0, -1.5, 0, -6.5],
    ],
)
def test_bad_joint_targets_are_refused(planner: MotionPlanner, target: object) -> None:
    with pytest.raises(InvalidTargetError) as info:
        planner.plan_joint(HOME, target)
    assert isinstance(info.value, ValueError)
    assert isinstance(info.value, FxcellError)


def test_a_joint_target_in_collision_is_refused(planner: MotionPlanner) -> None:
    with pytest.raises(CollisionError):
        planner.plan_joint(HOME, [0.0, -1.57, 2.6, 0.0, 0.0, 0.0])  # wrist folded onto the arm


@pytest.mark.parametrize("factor", [-5, -1.4, 0, 2, 10, math.nan, math.inf, "1", None, True])
def test_bad_factors_are_refused(planner: MotionPlanner, factor: object) -> None:
    with pytest.raises(InvalidFactorError):
        planner.plan_joint(HOME, WORK, velocity_factor=factor)  # type: ignore[arg-type]
    with pytest.raises(InvalidFactorError):
        planner.plan_joint(HOME, WORK, acceleration_factor=factor)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "target",
    [[0.1, 0.2], [0.1, 0.2, 0.3, 0.0, 0.0, math.nan], [0.1, 0.2, 0.3, "a", 0, 0], "pose"],
)
def test_malformed_poses_are_refused(planner: MotionPlanner, target: object) -> None:
    with pytest.raises(InvalidTargetError):
        planner.plan_pose(WORK, target)


def test_a_pose_out_of_reach_is_refused(planner: MotionPlanner) -> None:
    with pytest.raises(UnreachableError):
        planner.plan_pose(WORK, [0.9, 0.0, 0.2, math.pi, 0.0, 0.0])


def test_a_pose_inside_the_table_is_refused(planner: MotionPlanner) -> None:
    with pytest.raises(CollisionError):
        planner.plan_pose(WORK, [-0.25, -0.25, -0.02, math.pi, 0.0, 0.0])


def test_a_pose_inside_the_fusion_machine_is_refused(planner: MotionPlanner) -> None:
    with pytest.raises(CollisionError):
        planner.plan_pose(WORK, [0.0, 0.40, 0.10, math.pi, 0.0, 0.0])


@pytest.mark.parametrize(
    "target",
    [
        [-0.2275, -0.2786, 0.0310, -0.707827, -0.706385, -0.000130, 0.000584],  # quaternion
        [-0.25, -0.20, 0.12, math.pi, 0.0, 0.3],  # roll, pitch, yaw
        Pose([-0.30, -0.10, 0.20], DOWN.rotation),
    ],
)
def test_a_pose_plan_ends_exactly_at_the_pose(planner: MotionPlanner, target: object) -> None:
    plan = planner.plan_pose(WORK, target)
    pose = target if isinstance(target, Pose) else Pose.parse(target)
    reached = planner.kinematics.forward(plan.trajectory.positions[-1])
    assert reached.isclose(pose, position_tol=1e-9, angle_tol=1e-9)
    assert not planner.checker.in_collision(plan.target_joints)


def test_move_distance_is_a_straight_line_keeping_the_orientation(planner: MotionPlanner) -> None:
    plan = planner.plan_distance(WORK, [0.005, 0.005, 0.005])
    assert plan.planner == "cartesian"
    start = planner.kinematics.forward(WORK)
    for q in plan.trajectory.positions[:: max(len(plan.trajectory) // 20, 1)]:
        pose = planner.kinematics.forward(q)
        offset = pose.position - start.position
        # along (1, 1, 1) only, orientation unchanged
        assert np.max(np.abs(offset - offset.mean())) < 1e-9
        assert pose.angle_to(start) < 1e-9
    end = planner.kinematics.forward(plan.trajectory.positions[-1])
    np.testing.assert_allclose(end.position - start.position, [0.005] * 3, atol=1e-9)


@pytest.mark.parametrize("distance", [[0.1, 0.2], [0.0, 0.0, math.nan], "up"])
def test_bad_distance_vectors_are_refused(planner: MotionPlanner, distance: object) -> None:
    with pytest.raises(InvalidArgumentError):
        planner.plan_distance(WORK, distance)


def test_move_relative_plans_both_legs_before_moving(planner: MotionPlanner) -> None:
    first = [-0.25, -0.20, 0.15, math.pi, 0.0, 0.0]
    second = [-0.20, -0.25, 0.10, math.pi, 0.0, 0.0]
    legs = planner.plan_relative(WORK, first, second)
    assert len(legs) == 2
    np.testing.assert_array_equal(legs[1].start_joints, legs[0].target_joints)
    with pytest.raises(CollisionError):  # the second leg is bad: nothing is returned
        planner.plan_relative(WORK, first, [-0.20, -0.25, -0.05, math.pi, 0.0, 0.0])


def test_each_move_target_type_plans_its_kind_of_move(planner: MotionPlanner) -> None:
    first = [-0.25, -0.20, 0.15, math.pi, 0.0, 0.0]
    second = [-0.20, -0.25, 0.10, math.pi, 0.0, 0.0]
    cases: list[tuple[MoveTarget, list[str]]] = [
        (JointTarget(CONFIG.home), ["joint"]),
        (PoseTarget(first), ["pose"]),
        (PoseTarget(first, linear=True), ["linear"]),
        (DistanceTarget([0.0, 0.0, 0.01]), ["distance"]),
        (RelativeTarget(first, second), ["pose", "pose"]),
    ]
    for target, kinds in cases:
        plans = planner.plan(target, WORK, 0.5, 0.5)
        assert [p.kind for p in plans] == kinds, target
        assert all(p.velocity_factor == 0.5 for p in plans)
    with pytest.raises(InvalidArgumentError, match="not a move target"):
        planner.plan("plan_joint", WORK)  # type: ignore[arg-type]


def test_lower_factors_make_slower_moves(planner: MotionPlanner) -> None:
    fast = planner.plan_joint(HOME, WORK)
    slow = planner.plan_joint(HOME, WORK, velocity_factor=0.3, acceleration_factor=0.3)
    assert slow.duration > 1.5 * fast.duration  # acceleration-bound: about 1/√0.3
    assert (
        np.max(np.abs(slow.trajectory.velocities) / np.asarray(CONFIG.limits.velocity))
        <= 0.3 + 1e-9
    )


def test_lead_setpoints_undo_a_critically_damped_lag() -> None:
    traj = rest_to_rest(HOME, WORK, Limits.from_config(CONFIG.limits, period=DT))
    lag = 0.02
    omega = 2 / lag
    sp = lead_setpoints(traj, lag)
    # Step the tracker the way a 2 ms servo cycle does and compare with the plan.
    q, qd = traj.positions[0].copy(), np.zeros(6)
    worst = 0.0
    for k in range(len(sp) - 1):
        qdd = omega * omega * (sp[k] - q) - 2 * omega * qd
        qd = qd + qdd * DT
        q = q + qd * DT
        worst = max(worst, float(np.max(np.abs(q - traj.positions[k + 1]))))
    assert worst < 1e-6
    np.testing.assert_array_equal(sp[-1], traj.positions[-1])


async def test_the_planner_for_blocked_moves_can_be_chosen() -> None:
    controller = MotionController(CONFIG)
    controller.use_planner("BKPIECE1")
    left = [-1.042, -1.271, 1.482, -1.781, -1.571, 2.099]
    right = [-2.792, -1.255, 1.46, -1.776, -1.571, 0.35]  # the machine is in between
    (plan,) = await controller.plan(JointTarget(right), left, 1.0, 1.0)
    assert isinstance(plan, MovePlan)
    assert plan.planner == "BKPIECE1"
    with pytest.raises(InvalidArgumentError):
        controller.use_planner("NoSuchPlanner")


async def test_a_short_free_joint_move_is_planned_without_a_worker_thread(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the hand-offs to and from a thread cost more than planning a short free line
    controller = MotionController(CONFIG)
    threaded: list[object] = []
    real = asyncio.to_thread

    async def to_thread(func: Any, /, *args: Any) -> Any:
        threaded.append(func)
        return await real(func, *args)

    monkeypatch.setattr("fxcell.motion.moves.asyncio.to_thread", to_thread)
    short = HOME + np.array([0, 0, 0, 0, 0, 0.01])
    (plan,) = await controller.plan(JointTarget(short.tolist()), HOME, 1.0, 1.0)
    assert plan.planner == "direct"
    assert not threaded
    far = HOME + np.array([0.6, 0, 0, 0, 0, 0])
    (plan,) = await controller.plan(JointTarget(far.tolist()), HOME, 1.0, 1.0)
    assert plan.planner == "direct"
    assert len(threaded) == 1
    with pytest.raises(InvalidArgumentError):  # bad input: the same typed error inline
        await controller.plan(JointTarget([0.0] * 5), HOME, 1.0, 1.0)
