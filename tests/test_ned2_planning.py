"""fxcell's motion planner on the Ned2's own model: OMPL finds a path around an obstacle
in the cell's scene that the straight joint line would hit, Ruckig times it within the
Ned2's joint limits, sampled at the kind's period, and every sample is collision free by
the Ned2's collision model; a pose move lands the Ned2's TCP on the pose."""

from __future__ import annotations

import numpy as np
import pytest

from fxcell.config import CellConfig, JointLimits, SceneConfig, SceneObject
from fxcell.geometry import Pose
from fxcell.link.capabilities import RobotCapabilities
from fxcell.motion import ned2
from fxcell.motion.collision import CollisionChecker
from fxcell.motion.moves import MotionPlanner

TABLE = SceneObject(name="table", size=(1.0, 1.0, 0.05), position=(0.0, 0.0, -0.025))
POST = SceneObject(name="post", size=(0.06, 0.06, 0.30), position=(0.25, 0.0, 0.15))
LEFT = np.array([1.0, -0.6, 0.3, 0.0, -1.0, 0.0])
RIGHT = np.array([-1.0, -0.6, 0.3, 0.0, -1.0, 0.0])
PERIOD = 0.01


@pytest.fixture(scope="module")
def planner() -> MotionPlanner:
    limits = JointLimits(
        position_min=tuple(ned2.LOWER),
        position_max=tuple(ned2.UPPER),
        velocity=tuple(ned2.VELOCITY_LIMITS),
        acceleration=tuple(ned2.ACCELERATION_LIMITS),
    )
    config = CellConfig().model_copy(
        update={"limits": limits, "scene": SceneConfig(objects=(TABLE, POST))}
    )
    return MotionPlanner(
        config,
        kinematics=lambda cfg, calibration: ned2.Ned2Kinematics(),
        collision=lambda cfg: CollisionChecker.from_urdf(
            ned2.urdf(), cfg.scene, tool_frame="tool_link", never=ned2.NEVER_IN_CONTACT
        ),
        capabilities=RobotCapabilities(kind="ned2", joints=6, sample_period=PERIOD),
        seed=1,
    )


def test_a_path_around_the_post_timed_within_the_ned2s_limits(planner: MotionPlanner) -> None:
    assert not planner.checker.motion_free(LEFT, RIGHT)  # the straight line hits the post
    plan = planner.plan_joint(LEFT, RIGHT)
    assert plan.planner != "direct"
    assert len(plan.waypoints) > 2
    traj = plan.trajectory
    assert traj.period == PERIOD
    assert traj.positions[0].tolist() == LEFT.tolist()
    assert traj.positions[-1] == pytest.approx(RIGHT, abs=1e-9)
    assert planner.checker.first_collision(traj.positions) is None
    assert np.all(np.abs(traj.velocities) <= ned2.VELOCITY_LIMITS * (1 + 1e-6))
    assert np.all(np.abs(traj.accelerations) <= ned2.ACCELERATION_LIMITS * (1 + 1e-6))
    # the samples themselves move no faster than the limits between two periods
    steps = np.abs(np.diff(traj.positions, axis=0)) / PERIOD
    assert np.all(steps <= ned2.VELOCITY_LIMITS * 1.01)


def test_a_pose_move_lands_the_ned2s_tool_on_the_pose(planner: MotionPlanner) -> None:
    goal = Pose.from_matrix(ned2.forward(RIGHT))
    plan = planner.plan_pose(LEFT, goal)
    end = ned2.forward(plan.trajectory.positions[-1])
    assert np.linalg.norm(end[:3, 3] - goal.position) < 1e-6
    assert planner.checker.first_collision(plan.trajectory.positions) is None
