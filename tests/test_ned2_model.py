"""The Ned2's model: FK agrees with Pinocchio on the shipped URDF, IK solves every
reachable pose and returns the solution nearest the seed (checked against a dense
multi-start reference)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from fxcell.errors import InvalidArgumentError, UnreachableError
from fxcell.geometry import Pose
from fxcell.motion import ned2
from fxcell.robots import KinematicModel

pytestmark = pytest.mark.timeout(300)
# two solutions closer than this (rad) are one: near a wrist singularity the solver stops
# within 1e-7 m/rad of the pose while the joints still differ by ~1e-5
SAME = 1e-4

joints = st.tuples(
    *[st.floats(float(lo), float(hi)) for lo, hi in zip(ned2.LOWER, ned2.UPPER, strict=True)]
).map(np.array)


def _reference(target: np.ndarray, seed: np.ndarray, n: int = 400) -> ned2.IkResult:
    rng = np.random.default_rng(7)
    dense = rng.uniform(ned2.LOWER, ned2.UPPER, size=(n, 6))
    return ned2.inverse(target, seed, extra_seeds=dense, iterations=120)


def test_zero_and_home_poses_follow_the_urdf_chain() -> None:
    # q = 0: upper arm up, forearm and hand along x
    x, y, z, roll, pitch, yaw = ned2.matrix_to_pose(ned2.forward([0.0] * 6))
    assert x == pytest.approx(0.012 + 0.065 + 0.17 + 0.0197 + 0.0285)
    assert z == pytest.approx(0.1013 + 0.065 + 0.221 + 0.0325 + 0.00925)
    assert y == pytest.approx(3.7961e-05)
    assert (roll, pitch, yaw) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)


def test_the_urdf_loads_in_pinocchio_with_collision_bodies_and_the_same_fk() -> None:
    pin = pytest.importorskip("pinocchio")
    model = pin.buildModelFromXML(ned2.urdf())
    geoms = pin.buildGeomFromUrdfString(model, ned2.urdf(), pin.COLLISION)
    assert model.nq == 6
    assert {g.name.rsplit("_", 1)[0] for g in geoms.geometryObjects} >= {
        "base_link",
        "arm_link",
        "forearm_link",
        "hand_link",
        "gripper_link",
    }
    data = model.createData()
    tool = model.getFrameId("tool_link")
    rng = np.random.default_rng(3)
    for q in rng.uniform(ned2.LOWER, ned2.UPPER, size=(20, 6)):
        pin.framesForwardKinematics(model, data, q)
        assert np.allclose(data.oMf[tool].homogeneous, ned2.forward(q), atol=1e-12)
    assert np.allclose(model.lowerPositionLimit, ned2.LOWER)
    assert np.allclose(model.upperPositionLimit, ned2.UPPER)


@settings(max_examples=60, deadline=None)
@given(q=joints, noise=st.lists(st.floats(-0.6, 0.6), min_size=6, max_size=6))
def test_ik_solves_every_reachable_pose_and_fk_of_it_is_the_pose(
    q: np.ndarray, noise: list[float]
) -> None:
    target = ned2.forward(q)
    seed = np.clip(q + np.array(noise), ned2.LOWER, ned2.UPPER)
    result = ned2.inverse(target, seed)
    assert result.q is not None, f"no solution for a reachable pose (q = {q.tolist()})"
    assert ned2.within_limits(result.q)
    reached = ned2.forward(result.q)
    assert np.linalg.norm(reached[:3, 3] - target[:3, 3]) < 1e-6
    assert np.abs(reached[:3, :3] - target[:3, :3]).max() < 1e-6


@settings(max_examples=25, deadline=None)
@given(q=joints, seed=joints)
# the nearer solution has θ3 0.018 from its upper limit, where no branch start converged
# (found by Hypothesis)
@example(
    q=np.array([0.0, 0.0, 1.25, 1.0, 0.0, 1.0]), seed=np.array([0.0, 0.0, 0.0, -2.0, 0.0, 0.0])
)
# the TCP 9 mm from the base axis, its azimuth nothing like θ1 = -2.5 (Hypothesis)
@example(q=np.array([-2.5, 0.0, 1.5, -0.75, 0.0, 0.0]), seed=np.zeros(6))
def test_ik_returns_the_solution_nearest_the_seed_that_a_dense_search_finds(
    q: np.ndarray, seed: np.ndarray
) -> None:
    target = ned2.forward(q)
    ours = ned2.inverse(target, seed)
    reference = _reference(target, seed)
    assert ours.q is not None
    assert reference.q is not None
    assert np.linalg.norm(ours.q - seed) <= np.linalg.norm(reference.q - seed) + SAME


def test_an_unreachable_pose_has_no_solution() -> None:
    far = ned2.pose_to_matrix([1.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    assert ned2.inverse(far, ned2.HOME).q is None


@pytest.mark.parametrize("bad", [[0.0] * 5, [math.nan] * 6])
def test_bad_seeds_and_targets_are_refused(bad: list[float]) -> None:
    with pytest.raises(InvalidArgumentError):
        ned2.inverse(ned2.forward(ned2.HOME), bad)
    with pytest.raises(InvalidArgumentError):
        ned2.inverse(bad, ned2.HOME)


@given(q=joints)
def test_pose_round_trips_through_niryo_rpy(q: np.ndarray) -> None:
    t = ned2.forward(q)
    assert np.allclose(ned2.pose_to_matrix(ned2.matrix_to_pose(t)), t, atol=1e-9)


# ---------------------------------------------------------------- the planner's model

TCP = Pose([0.075, 0.0, 0.0], np.eye(3))  # Gripper 1's finger centre along tool_link's x


@settings(max_examples=60, deadline=None)
@given(q=joints)
def test_the_planners_model_inverts_its_forward_with_the_tcp(q: np.ndarray) -> None:
    model: KinematicModel = ned2.Ned2Kinematics(TCP)
    pose = model.forward(q)
    assert np.linalg.norm(pose.position) <= model.reach
    tool = ned2.forward(q)
    assert pose.position == pytest.approx(tool[:3, 3] + 0.075 * tool[:3, 0], abs=1e-12)
    found = model.inverse(pose, seed=q)
    assert np.max(np.abs(found - q)) < SAME  # the seed's own branch
    assert np.linalg.norm(model.forward(found).position - pose.position) < 1e-6
    assert found.tolist() == model.inverse_all(pose, seed=q)[0].tolist()


@given(q=joints, step=st.lists(st.floats(-0.01, 0.01), min_size=6, max_size=6))
# next to the wrist singularity: solved to 1e-7 the wrist's two joints were 7e-4 rad off
@example(q=np.array([0.0, -1.3125, 0.0, 0.0, 0.0, 0.0]), step=[0, 0, 0, 0, 0.0078125, 0.0078125])
def test_a_paths_next_point_is_solved_on_the_seeds_branch(q: np.ndarray, step: list[float]) -> None:
    # a straight line's knots: the next pose is a small step from the seed's
    model = ned2.Ned2Kinematics(TCP)
    nxt = np.clip(q + np.asarray(step), ned2.LOWER, ned2.UPPER)
    pose = model.forward(nxt)
    found = model.inverse_near(pose, q)
    assert model.forward(found).distance(pose) < 1e-6
    assert model.forward(found).angle_to(pose) < 1e-6
    assert np.max(np.abs(found - nxt)) < SAME  # continuous with the seed, not another branch


def test_the_planners_model_keeps_to_narrower_limits_and_says_what_it_cannot_reach() -> None:
    q = np.array([0.6, -0.3, 0.2, 0.4, -0.5, 0.3])
    pose = ned2.Ned2Kinematics().forward(q)
    narrow = ned2.Ned2Kinematics(lower=ned2.LOWER, upper=[*ned2.UPPER[:1], -0.4, *ned2.UPPER[2:]])
    for solution in narrow.inverse_all(pose, seed=q):
        assert solution[1] <= -0.4
    with pytest.raises(UnreachableError, match="Ned2"):
        ned2.Ned2Kinematics().inverse(Pose([0.9, 0.0, 0.2], np.eye(3)))
    with pytest.raises(InvalidArgumentError):
        ned2.Ned2Kinematics(lower=ned2.UPPER, upper=ned2.LOWER)
