"""The Ned2's collision model: the arm and its Gripper 1 from its URDF's collision shapes,
a table, the pairs Niryo never checks left out. Home is free, an arm reaching into the
table or its own base collides by name, a joint motion through the table is not free,
and the lever arms bound how far any body point moves per joint step."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.config import SceneConfig, SceneObject
from fxcell.motion import ned2
from fxcell.motion.collision import CollisionChecker

TABLE = SceneObject(name="table", size=(1.0, 1.0, 0.05), position=(0.0, 0.0, -0.025))
DOWN = np.array([0.0, -1.5, 0.0, 0.0, 0.0, 0.0])  # the upper arm laid forward, wrist low
ABOVE = np.array([0.0, 0.0, 0.0, 0.0, -1.2, 0.0])  # reaching forward over the table


@pytest.fixture(scope="module")
def checker() -> CollisionChecker:
    return CollisionChecker.from_urdf(
        ned2.urdf(),
        SceneConfig(objects=(TABLE,)),
        tool_frame="tool_link",
        never=ned2.NEVER_IN_CONTACT,
    )


def test_the_arm_and_gripper_are_its_links_and_home_is_free(checker: CollisionChecker) -> None:
    assert checker.names[:8] == [
        "base_link", "shoulder_link", "arm_link", "elbow_link", "forearm_link",
        "wrist_link", "hand_link", "gripper_link",
    ]  # fmt: skip
    assert not checker.in_collision(ned2.HOME)
    assert not checker.in_collision(ABOVE)


def test_the_pairs_niryo_never_checks_are_not_checked(checker: CollisionChecker) -> None:
    checked = {
        frozenset((checker.names[p.first], checker.names[p.second]))
        for p in checker.geometry_model.collisionPairs
    }
    for a, b in ned2.NEVER_IN_CONTACT:
        assert frozenset((a, b)) not in checked
    assert frozenset(("base_link", "wrist_link")) in checked
    assert frozenset(("gripper_link", "table")) in checked


def test_an_arm_reaching_into_the_table_collides_and_says_with_what(
    checker: CollisionChecker,
) -> None:
    assert ned2.forward(DOWN)[2, 3] < 0  # the tool below the table top
    assert ("wrist_link", "table") in checker.colliding_pairs(DOWN)
    with pytest.raises(Exception, match="table"):
        checker.check(DOWN)


def test_a_joint_motion_through_the_table_is_not_free(checker: CollisionChecker) -> None:
    assert checker.motion_free(ned2.HOME, ABOVE)
    assert not checker.motion_free(ned2.HOME, DOWN)


@settings(max_examples=200, deadline=None)
@given(
    q=st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6),
    joint=st.integers(0, 5),
    step=st.floats(-0.05, 0.05),
)
def test_no_body_point_moves_farther_than_its_lever_arm_allows(
    checker: CollisionChecker, q: list[float], joint: int, step: float
) -> None:
    a = np.clip(np.asarray(q), ned2.LOWER, ned2.UPPER)
    b = a.copy()
    b[joint] += step
    model, data = checker.model, checker.model.createData()
    moved = []
    for g in checker.geometry_model.geometryObjects:
        if g.parentJoint == 0:
            continue
        g.geometry.computeLocalAABB()
        box = g.geometry.aabb_local
        lo, hi = np.asarray(box.min_), np.asarray(box.max_)
        corners = [np.where([i & 1, i & 2, i & 4], hi, lo) for i in range(8)]
        ends = []
        for qq in (a, b):
            pin.forwardKinematics(model, data, qq)
            m = data.oMi[g.parentJoint] * g.placement
            ends.append([m.act(c) for c in corners])
        moved += [float(np.linalg.norm(p - r)) for p, r in zip(*ends, strict=True)]
    assert max(moved) <= checker.lever_arms[joint] * abs(step) + 1e-9
