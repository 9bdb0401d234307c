"""Joint-space planning (direct line, OMPL around obstacles) and Cartesian straight lines."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.config import CellConfig
from fxcell.errors import CollisionError, PlanningError, SingularityError, UnreachableError
from fxcell.geometry import Pose
from fxcell.link.capabilities import UR3E
from fxcell.motion.collision import CollisionChecker
from fxcell.motion.kinematics import Kinematics
from fxcell.motion.moves import MotionPlanner
from fxcell.motion.planning import JointPlanner, cartesian_line, interpolate_pose
from fxcell.motion.trajectory import Limits

CONFIG = CellConfig.load()
HOME = np.array(CONFIG.home)
KIN = Kinematics.ur3e(tcp=CONFIG.tool.tcp, limits=CONFIG.limits)
LIMITS = Limits.from_config(CONFIG.limits, period=UR3E.sample_period)
DOWN = Pose.from_rpy([0, 0, 0], [math.pi, 0, 0]).rotation

# Left of the fusion machine to right of it, gripper low: the straight joint line swings
# the arm through the machine.
LEFT_OF_MACHINE = np.array([-1.042, -1.271, 1.482, -1.781, -1.571, 2.099])
RIGHT_OF_MACHINE = np.array([-2.792, -1.255, 1.46, -1.776, -1.571, 0.35])


@pytest.fixture(scope="module")
def checker() -> CollisionChecker:
    return CollisionChecker.for_config(CONFIG)


@pytest.fixture(scope="module")
def planner(checker: CollisionChecker) -> JointPlanner:
    return JointPlanner(checker, CONFIG.limits.position_min, CONFIG.limits.position_max)


def test_a_free_straight_line_is_taken_without_planning(planner: JointPlanner) -> None:
    target = HOME + np.array([0.8, 0.3, -0.4, 0.2, 0.5, 1.0])
    path = planner.plan(HOME, target)
    assert path.planner == "direct"
    np.testing.assert_array_equal(path.waypoints, [HOME, target])


def test_a_move_blocked_by_the_machine_is_planned_around_it(
    planner: JointPlanner, checker: CollisionChecker
) -> None:
    assert not checker.in_collision(LEFT_OF_MACHINE)
    assert not checker.in_collision(RIGHT_OF_MACHINE)
    midway = 0.5 * (LEFT_OF_MACHINE + RIGHT_OF_MACHINE)
    assert any("machine" in p for p in checker.colliding_pairs(midway))

    path = planner.plan(LEFT_OF_MACHINE, RIGHT_OF_MACHINE)
    assert path.planner == "RRTConnect"
    assert len(path.waypoints) >= 3
    np.testing.assert_array_equal(path.waypoints[0], LEFT_OF_MACHINE)
    np.testing.assert_array_equal(path.waypoints[-1], RIGHT_OF_MACHINE)
    # The planner's promise: free at its own resolution, with the scene's safety margin.
    # Between two checked states no point moves more than the resolution, so it stays
    # within half of it of one of them; the margin (5 mm) exceeds that (3 mm), so the
    # real obstacles (no margin), checked four times as densely, are never touched.
    exact = CollisionChecker.for_config(CONFIG, resolution=checker.resolution / 4, scene_margin=0.0)
    assert checker.scene_margin > checker.resolution / 2
    for a, b in itertools.pairwise(path.waypoints):
        assert checker.motion_free(a, b)
        assert exact.motion_free(a, b)

    # Timed as a move plans it: blends the sample check rejects become stops, and a path
    # whose straight segment grazes the margin between the line check's points is
    # replaced by another (MotionPlanner.plan_joint; timing one such random path directly
    # raised "left the collision-free corridor" once in ten loaded full runs).
    plan = MotionPlanner(CONFIG).plan_joint(LEFT_OF_MACHINE, RIGHT_OF_MACHINE)
    assert len(plan.waypoints) >= 3
    assert checker.first_collision(plan.trajectory.positions) is None
    assert exact.first_collision(plan.trajectory.positions) is None
    np.testing.assert_array_equal(plan.trajectory.positions[-1], RIGHT_OF_MACHINE)


def test_a_target_in_collision_is_refused_before_planning(planner: JointPlanner) -> None:
    folded = np.array([0.0, -1.57, 2.6, 0.0, 0.0, 0.0])
    with pytest.raises(CollisionError, match="target"):
        planner.plan(HOME, folded)


def test_the_table_and_the_folded_elbow_are_walls_of_the_free_space(
    checker: CollisionChecker,
) -> None:
    walls = checker.walls()
    # the upper arm hanging into the table (θ2 = π/2 - 2πk) and the elbow folded (θ3 = ±π)
    assert {j for j, _ in walls} == {1, 2}
    assert any(abs(v - math.pi / 2) < 0.05 for j, v in walls if j == 1)
    assert any(abs(v + 3 * math.pi / 2) < 0.05 for j, v in walls if j == 1)
    assert sorted(round(abs(v), 1) for j, v in walls if j == 2) == [3.1, 3.1]


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    which=st.integers(0, 3),
    others=st.lists(st.floats(-2 * math.pi, 2 * math.pi), min_size=6, max_size=6),
)
def test_every_configuration_on_a_wall_collides(
    checker: CollisionChecker, which: int, others: list[float]
) -> None:
    walls = checker.walls()
    joint, value = walls[which % len(walls)]
    q = np.array(others)
    q[joint] = value
    assert checker.in_collision(q)


def test_a_query_across_a_wall_fails_without_a_search(planner: JointPlanner) -> None:
    # The same arm pose with the shoulder turned a full turn: joint space is not a circle
    # (±2π limits), so the move would have to swing the upper arm through the table.
    across = HOME + np.array([0, 2 * math.pi, 0, 0, 0, 0])
    assert not planner.checker.in_collision(across)
    with pytest.raises(PlanningError, match=r"joint 2 at 1\.5"):
        planner.plan(HOME, across)


def test_another_ompl_planner_can_be_chosen(checker: CollisionChecker) -> None:
    planner = JointPlanner(
        checker, CONFIG.limits.position_min, CONFIG.limits.position_max, planner="BKPIECE1"
    )
    path = planner.plan(LEFT_OF_MACHINE, RIGHT_OF_MACHINE)
    assert path.planner == "BKPIECE1"
    with pytest.raises(ValueError, match="unknown planner"):
        JointPlanner(checker, CONFIG.limits.position_min, CONFIG.limits.position_max, planner="X")


def _start(x: float, y: float, z: float) -> np.ndarray:
    q = KIN.inverse(Pose([x, y, z], DOWN), seed=np.array([0.4, -1.4, 1.6, -1.8, -1.57, 0.0]))
    return np.asarray(q)


def test_a_cartesian_line_keeps_the_tcp_on_the_segment(checker: CollisionChecker) -> None:
    q0 = _start(-0.25, -0.25, 0.10)
    start = KIN.forward(q0)
    target = Pose(start.position + np.array([0.05, -0.03, 0.04]), start.rotation)
    line = cartesian_line(KIN, checker, q0, target)
    for s in np.linspace(0, 1, 37):
        pose = KIN.forward(line.joints(float(s)))
        on_line = start.position + s * (target.position - start.position)
        np.testing.assert_allclose(pose.position, on_line, atol=1e-9)
        assert pose.angle_to(start) < 1e-9
    assert KIN.forward(line.target_joints).isclose(target, position_tol=1e-9, angle_tol=1e-9)
    # consecutive knots stay on one IK branch
    assert np.max(np.abs(np.diff(line.knots, axis=0))) < 0.05


def test_a_cartesian_line_also_turns_the_tool(checker: CollisionChecker) -> None:
    q0 = _start(-0.25, -0.25, 0.10)
    start = KIN.forward(q0)
    turned = Pose(
        start.position + np.array([0.0, 0.0, 0.03]),
        start.rotation @ Pose.from_rpy([0, 0, 0], [0, 0, 0.5]).rotation,
    )
    line = cartesian_line(KIN, checker, q0, turned)
    half = KIN.forward(line.joints(0.5))
    assert half.isclose(interpolate_pose(start, turned, 0.5), position_tol=1e-9, angle_tol=1e-9)
    assert abs(half.angle_to(start) - 0.25) < 1e-9


def test_a_line_into_the_table_is_refused(checker: CollisionChecker) -> None:
    q0 = _start(-0.25, -0.25, 0.10)
    start = KIN.forward(q0)
    with pytest.raises(CollisionError, match="straight line collides"):
        cartesian_line(
            KIN, checker, q0, Pose(start.position - np.array([0, 0, 0.12]), start.rotation)
        )


def test_a_line_out_of_reach_is_refused(checker: CollisionChecker) -> None:
    q0 = _start(-0.25, -0.25, 0.10)
    start = KIN.forward(q0)
    with pytest.raises((UnreachableError, SingularityError)):
        cartesian_line(
            KIN, checker, q0, Pose(start.position + np.array([-0.5, -0.5, 0.0]), start.rotation)
        )
