"""The Pinocchio UR3e model agrees with the closed-form kinematics and UR's conventions."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.config import SEED_TCP, JointLimits
from fxcell.motion.kinematics import Kinematics
from fxcell.motion.robot_model import (
    FLANGE_FRAME,
    JOINT_NAMES,
    LINK_NAMES,
    TCP_FRAME,
    UR3E_COMS,
    UR3E_MASSES,
    RobotModel,
    ur3e_model,
)

SEED_MODEL = RobotModel.ur3e(SEED_TCP)
FLANGE_MODEL = RobotModel.ur3e()
SEED_KIN = Kinematics.ur3e(SEED_TCP)

configurations = st.lists(
    st.floats(-2 * math.pi, 2 * math.pi, allow_nan=False), min_size=6, max_size=6
).map(np.array)


@given(configurations)
@settings(max_examples=60)
def test_tcp_and_flange_placements_equal_the_closed_form_forward_kinematics(q: np.ndarray) -> None:
    data = SEED_MODEL.create_data()
    assert np.allclose(SEED_MODEL.tcp_pose(q, data).matrix, SEED_KIN.forward(q).matrix, atol=1e-12)
    flange = SEED_MODEL.frame_pose(q, SEED_MODEL.flange_frame_id, data)
    assert np.allclose(flange.matrix, SEED_KIN.forward_flange(q).matrix, atol=1e-12)
    assert np.allclose(
        FLANGE_MODEL.tcp_pose(q).matrix, Kinematics.ur3e().forward(q).matrix, atol=1e-12
    )


@given(configurations)
@settings(max_examples=30)
def test_link_frames_are_the_dh_frames(q: np.ndarray) -> None:
    frames = SEED_KIN.joint_frames(q)
    data = SEED_MODEL.create_data()
    for k, fid in enumerate(SEED_MODEL.link_frame_ids):
        assert np.allclose(SEED_MODEL.frame_pose(q, fid, data).matrix, frames[k + 1], atol=1e-12)
    # joint k turns about z of DH frame k-1, at its origin
    pin.forwardKinematics(SEED_MODEL.model, data, q)
    for k, jid in enumerate(SEED_MODEL.joint_ids):
        oMi = data.oMi[jid]
        assert np.allclose(oMi.translation, frames[k][:3, 3], atol=1e-12)
        assert np.allclose(oMi.rotation[:, 2], frames[k][:3, 2], atol=1e-12)


@given(configurations)
@settings(max_examples=30)
def test_tcp_jacobian_equals_the_closed_form_jacobian(q: np.ndarray) -> None:
    assert np.allclose(SEED_MODEL.jacobian(q), SEED_KIN.jacobian(q), atol=1e-12)


def test_model_layout_names_joints_links_and_tool_frames() -> None:
    model = ur3e_model(SEED_TCP)
    assert model.nq == 6
    assert [model.names[j] for j in SEED_MODEL.joint_ids] == list(JOINT_NAMES)
    assert [model.frames[f].name for f in SEED_MODEL.link_frame_ids] == list(LINK_NAMES)
    assert model.frames[SEED_MODEL.flange_frame_id].name == FLANGE_FRAME
    assert model.frames[SEED_MODEL.tcp_frame_id].name == TCP_FRAME
    assert model.getFrameId(TCP_FRAME) == SEED_MODEL.tcp_frame_id
    for fid in (SEED_MODEL.flange_frame_id, SEED_MODEL.tcp_frame_id):
        assert model.frames[fid].parentJoint == SEED_MODEL.joint_ids[-1]
    flange = SEED_MODEL.flange_in_joint6
    assert np.allclose(flange.translation, [0.0, 0.0, 0.0921])


def test_joint_limits_come_from_the_config() -> None:
    lim = JointLimits()
    model = SEED_MODEL.model
    assert np.allclose(model.lowerPositionLimit, lim.position_min)
    assert np.allclose(model.upperPositionLimit, lim.position_max)
    assert np.allclose(model.velocityLimit, lim.velocity)
    narrow = JointLimits(position_min=(-1.0,) * 6, position_max=(1.0,) * 6)
    assert np.allclose(RobotModel.ur3e(limits=narrow).model.upperPositionLimit, 1.0)


def test_total_mass_is_the_published_arm_mass() -> None:
    data = SEED_MODEL.create_data()
    assert pin.computeTotalMass(SEED_MODEL.model, data) == pytest.approx(sum(UR3E_MASSES))


@pytest.mark.parametrize(
    "q", [[0, 0, 0, 0, 0, 0], [0.3, -1.2, 1.1, -0.7, 1.0, 0.4], [0, -math.pi / 2, 0, 0, 0, 0]]
)
def test_gravity_torques_match_the_published_masses_and_centres(q: list[float]) -> None:
    # hand sum: τ_j = Σ_links z_j × (c - o_j) · (m g ẑ), centres of mass in the DH link frames
    frames = SEED_KIN.joint_frames(q)
    expected = np.zeros(6)
    for k in range(6):
        c = frames[k + 1][:3, :3] @ np.array(UR3E_COMS[k]) + frames[k + 1][:3, 3]
        force = np.array([0.0, 0.0, UR3E_MASSES[k] * 9.81])
        for j in range(k + 1):
            z, o = frames[j][:3, 2], frames[j][:3, 3]
            expected[j] += np.cross(z, c - o) @ force
    tau = SEED_MODEL.gravity_torques(q)
    assert np.allclose(tau, expected, atol=1e-9)
    # arm stretched horizontally: the shoulder holds about 18 N·m
    if q == [0, 0, 0, 0, 0, 0]:
        assert 10.0 < abs(tau[1]) < 30.0
