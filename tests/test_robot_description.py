"""Each robot kind's description for the views (the page's arm, the recorder's /tf and
URDF) composes to that kind's own kinematics, and a URDF that is no serial arm is refused."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.errors import InvalidArgumentError
from fxcell.geometry import Pose
from fxcell.motion import ned2
from fxcell.motion.kinematics import LINK_NAMES, Kinematics
from fxcell.recorder.frames import LinkFrames
from fxcell.robots import UR3E_KIND
from fxcell.robots.description import ArmDescription, from_urdf
from fxcell.robots.ned2 import ned2_description
from fxcell.robots.ur3e import ur3e_description

UR_TCP = (-0.00025, 0.00245, 0.14789, 0.0, 0.0, -1.5708)
NED2_TCP = (0.05, 0.0, 0.01, 0.0, 0.2, 0.0)
angles = st.lists(st.floats(-math.pi, math.pi), min_size=6, max_size=6)


def _chain_tool(arm: ArmDescription, q: list[float]) -> np.ndarray:
    """The tool frame as the page composes it from :meth:`ArmDescription.chain_json`."""
    model = arm.chain_json()
    frame = np.eye(4)
    joints = model["joints"]
    assert isinstance(joints, list)
    for joint, angle in zip(joints, q, strict=True):
        frame = frame @ np.array(joint["origin"]).reshape(4, 4)
        frame = frame @ Pose.from_rotvec((0, 0, 0), np.array(joint["axis"]) * angle).matrix
    return frame @ np.array(model["tool"]).reshape(4, 4)


def _composed(frames: LinkFrames, q: list[float], root: str) -> dict[str, np.ndarray]:
    transforms = frames.transforms(q, {"sec": 1, "nsec": 2})
    assert transforms is not None
    encoded = frames.transforms_json(q, 1, 2)
    assert encoded is not None
    assert json.loads(encoded) == {"transforms": transforms}  # the fast path agrees
    world = {root: np.eye(4)}
    for t in transforms:
        tr, rot = t["translation"], t["rotation"]
        local = Pose.from_quaternion(
            [tr["x"], tr["y"], tr["z"]], [rot["x"], rot["y"], rot["z"], rot["w"]]
        ).matrix
        world[t["child_frame_id"]] = world[t["parent_frame_id"]] @ local
    return world


@settings(max_examples=60, deadline=None)
@given(angles)
def test_the_ur3es_description_composes_to_its_kinematics(q: list[float]) -> None:
    arm = ur3e_description(Pose.from_ur(UR_TCP))
    assert arm.frames == ("base", *LINK_NAMES, "flange", "tcp")  # Foxglove layouts name them
    kinematics = Kinematics.ur3e(UR_TCP)
    expected = kinematics.joint_frames(np.array(q))
    world = _composed(LinkFrames(UR_TCP), q, "base")
    np.testing.assert_allclose(world["flange"], expected[6], atol=1e-12)
    np.testing.assert_allclose(world["tcp"], expected[7], atol=1e-12)
    np.testing.assert_allclose(arm.poses(q)["tcp"].matrix, expected[7], atol=1e-12)
    np.testing.assert_allclose(_chain_tool(arm, q), expected[6], atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(angles)
def test_the_ned2s_description_composes_to_its_kinematics(q: list[float]) -> None:
    arm = ned2_description(Pose.from_ur(NED2_TCP))
    assert [j.name for j in arm.revolute] == list(ned2.JOINT_NAMES)
    world = _composed(LinkFrames(arm=arm), q, "base_link")
    np.testing.assert_allclose(world["tool_link"], ned2.forward(q), atol=1e-12)
    tcp = ned2.Ned2Kinematics(Pose.from_ur(NED2_TCP)).forward(q).matrix
    np.testing.assert_allclose(world["tcp"], tcp, atol=1e-12)
    np.testing.assert_allclose(_chain_tool(arm, q), ned2.forward(q), atol=1e-12)


def test_the_recorder_attaches_each_kinds_urdf_under_its_name() -> None:
    assert LinkFrames(UR_TCP).attachment == "ur3e.urdf"
    assert LinkFrames(arm=ned2_description(Pose.identity())).attachment == "ned2.urdf"
    assert UR3E_KIND.description is not None
    assert UR3E_KIND.description(Pose.from_ur(UR_TCP)).urdf == LinkFrames(UR_TCP).urdf()


def test_a_fixed_joint_between_two_revolute_ones_folds_into_the_pages_chain() -> None:
    urdf = """<robot name="toy">
      <link name="a"/><link name="b"/><link name="c"/><link name="d"/><link name="e"/>
      <joint name="j1" type="revolute"><parent link="a"/><child link="b"/>
        <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/></joint>
      <joint name="fix" type="fixed"><parent link="b"/><child link="c"/>
        <origin xyz="0.2 0 0" rpy="0.3 0 0"/></joint>
      <joint name="j2" type="continuous"><parent link="c"/><child link="d"/>
        <origin xyz="0 0.1 0" rpy="0 0.5 0"/><axis xyz="0 1 0"/></joint>
      <joint name="tool" type="fixed"><parent link="d"/><child link="e"/>
        <origin xyz="0.05 0 0" rpy="0 0 0"/></joint>
    </robot>"""
    arm = from_urdf("toy", "Toy", urdf, "e", Pose.identity())
    assert [j.name for j in arm.revolute] == ["j1", "j2"]
    for q in ([0.0, 0.0], [0.7, -1.1]):
        model = arm.chain_json()
        frame = np.eye(4)
        joints = model["joints"]
        assert isinstance(joints, list)
        for joint, angle in zip(joints, q, strict=True):
            frame = frame @ np.array(joint["origin"]).reshape(4, 4)
            frame = frame @ Pose.from_rotvec((0, 0, 0), np.array(joint["axis"]) * angle).matrix
        frame = frame @ np.array(model["tool"]).reshape(4, 4)
        np.testing.assert_allclose(frame, arm.poses(q)["e"].matrix, atol=1e-12)


@pytest.mark.parametrize(
    ("urdf", "message"),
    [
        ("<robot", "does not parse"),
        (
            '<robot name="r"><link name="a"/><link name="b"/><joint name="p" type="prismatic">'
            '<parent link="a"/><child link="b"/></joint></robot>',
            "no revolute or fixed joint",
        ),
        ('<robot name="r"><link name="a"/><link name="b"/></robot>', "2 root links"),
        (
            '<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="fixed">'
            '<parent link="a"/><child link="b"/><origin xyz="1 2" rpy="0 0 0"/></joint></robot>',
            "expected 3 numbers",
        ),
    ],
)
def test_a_urdf_that_is_no_serial_arm_is_refused(urdf: str, message: str) -> None:
    with pytest.raises(InvalidArgumentError, match=message):
        from_urdf("x", "X", urdf, "b", Pose.identity())


def test_a_tool_frame_the_arm_lacks_is_refused() -> None:
    with pytest.raises(InvalidArgumentError, match="no frame of the Ned2"):
        from_urdf("ned2", "Ned2", ned2.urdf(), "flange", Pose.identity())


def test_joint_positions_must_match_the_arms_joints() -> None:
    with pytest.raises(InvalidArgumentError, match="6 joints, got 5"):
        ned2_description(Pose.identity()).poses([0.0] * 5)
    assert (
        LinkFrames(arm=ned2_description(Pose.identity())).transforms_json([0.0] * 5, 0, 0) is None
    )
