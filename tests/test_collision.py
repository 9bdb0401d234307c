"""Collision model: UR3e capsules, Hand-E gripper, table and fusion machine (coal via Pinocchio)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.config import CellConfig, SceneConfig, SceneObject
from fxcell.errors import CollisionError, InvalidTargetError
from fxcell.geometry import Pose
from fxcell.motion.collision import HAND_E, CollisionChecker
from fxcell.motion.kinematics import Kinematics

CONFIG = CellConfig.load()
HOME = np.array(CONFIG.home)
KIN = Kinematics.ur3e(tcp=CONFIG.tool.tcp, limits=CONFIG.limits)
DOWN = Pose.from_rpy([0, 0, 0], [math.pi, 0, 0]).rotation


@pytest.fixture(scope="module")
def checker() -> CollisionChecker:
    return CollisionChecker.for_config(CONFIG)


def tcp_down_at(x: float, y: float, z: float, seed: np.ndarray = HOME) -> np.ndarray:
    """Joints putting the TCP at (x, y, z) pointing down, elbow up, nearest ``seed``."""
    solutions = KIN.inverse_all(Pose([x, y, z], DOWN), seed=seed)
    up = [q for q in solutions if KIN.joint_frames(q)[2][2, 3] > 0.25]  # elbow above 0.25 m
    return up[0]


def test_home_and_zero_configurations_are_free(checker: CollisionChecker) -> None:
    assert checker.colliding_pairs(HOME) == []
    assert checker.colliding_pairs(np.zeros(6)) == []


def test_only_links_two_joints_apart_and_scene_pairs_are_checked(checker: CollisionChecker) -> None:
    names = checker.names
    pairs = {
        frozenset((names[p.first], names[p.second])) for p in checker.geometry_model.collisionPairs
    }
    # Adjacent links always touch at their joint: never checked.
    assert frozenset(("upper_arm", "forearm")) not in pairs
    assert frozenset(("wrist_2_link", "gripper_body")) not in pairs
    assert frozenset(("base", "table")) not in pairs  # the base stands on the table
    # Links two joints apart, the gripper against the arm, everything against the scene.
    assert frozenset(("upper_arm", "gripper_body")) in pairs
    assert frozenset(("shoulder_column", "forearm")) in pairs
    assert frozenset(("gripper_fingers", "table")) in pairs
    assert frozenset(("shoulder_column", "machine")) in pairs
    assert frozenset(("base", "wrist_1_link")) in pairs


def test_the_gripper_is_attached_at_the_flange() -> None:
    checker = CollisionChecker.for_config(CONFIG)
    rng = np.random.default_rng(1)
    body = checker.names.index("gripper_body")
    for q in rng.uniform(-math.pi, math.pi, (20, 6)):
        checker.in_collision(q)  # updates the placements
        placed = checker.geometry_data.oMg[body]
        flange = KIN.forward_flange(q)
        expected = flange.transform_point(HAND_E[0].center)
        np.testing.assert_allclose(placed.translation, expected, atol=1e-12)
        np.testing.assert_allclose(placed.rotation, flange.rotation, atol=1e-12)


def test_fingers_below_the_table_top_collide_with_the_table(checker: CollisionChecker) -> None:
    above = tcp_down_at(-0.25, -0.25, 0.03)
    below = tcp_down_at(-0.25, -0.25, -0.005)
    assert not checker.in_collision(above)
    assert ("gripper_fingers", "table") in checker.colliding_pairs(below)


def test_the_scene_margin_keeps_the_gripper_off_the_table(checker: CollisionChecker) -> None:
    # TCP 2 mm above the table: the fingertips (5 mm past the TCP) are within the margin.
    assert checker.in_collision(tcp_down_at(-0.25, -0.25, 0.002))


def test_reaching_into_the_fusion_machine_collides_with_it(checker: CollisionChecker) -> None:
    q = tcp_down_at(0.0, 0.35, 0.12, seed=np.array([-1.6, -1.5, 1.5, -1.6, -1.6, 0]))
    assert any("machine" in pair for pair in checker.colliding_pairs(q))


def test_folding_the_wrist_into_the_upper_arm_is_a_self_collision(
    checker: CollisionChecker,
) -> None:
    q = np.array([0.0, -1.57, 2.6, 0.0, 0.0, 0.0])  # elbow folded, wrist back onto the arm
    pairs = checker.colliding_pairs(q)
    assert pairs, "expected a self-collision"
    assert all("table" not in p and "machine" not in p for p in pairs)
    with pytest.raises(CollisionError, match="in collision"):
        checker.check(q)


def test_a_box_added_to_the_scene_is_an_obstacle() -> None:
    q = tcp_down_at(-0.25, -0.25, 0.10)
    tcp = KIN.forward(q).position
    scene = SceneConfig(objects=(SceneObject(name="crucible_rack", size=(0.05, 0.05, 0.05),
                                             position=tuple(tcp)),))  # fmt: skip
    assert CollisionChecker.for_config(CONFIG.model_copy(update={"scene": scene})).in_collision(q)
    assert not CollisionChecker.for_config(CONFIG).in_collision(q)


def test_first_collision_finds_where_a_motion_enters_the_table(checker: CollisionChecker) -> None:
    a = tcp_down_at(-0.25, -0.25, 0.10)
    b = tcp_down_at(-0.25, -0.25, -0.05, seed=a)
    samples = a + np.linspace(0, 1, 201)[:, None] * (b - a)
    hit = checker.first_collision(samples)
    assert hit is not None
    assert checker.in_collision(samples[hit])
    assert checker.first_collision(samples[: max(hit - 5, 1)]) is None
    assert not checker.motion_free(a, b)
    assert checker.motion_free(a, samples[max(hit - 5, 1)])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-math.pi, math.pi), min_size=6, max_size=6))
def test_a_state_collides_exactly_when_some_pair_does(q: list[float]) -> None:
    checker = _shared()
    assert checker.in_collision(q) == bool(checker.colliding_pairs(q))


_CHECKER: list[CollisionChecker] = []


def _shared() -> CollisionChecker:
    if not _CHECKER:
        _CHECKER.append(CollisionChecker.for_config(CONFIG))
    return _CHECKER[0]


def test_joint_targets_are_checked_as_finite_vectors() -> None:
    with pytest.raises(InvalidTargetError):
        KIN.forward([0, 0, math.nan, 0, 0, 0])
