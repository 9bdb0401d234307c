"""Poses and rotation conversions: round trips, awkward angles, parsing of move targets."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.errors import InvalidArgumentError, InvalidTargetError
from fxcell.geometry import (
    Pose,
    matrix_to_quaternion,
    matrix_to_rotvec,
    matrix_to_rpy,
    quaternion_to_matrix,
    rotation_angle,
    rotvec_to_matrix,
    rpy_to_matrix,
)

FAST = settings(max_examples=40)

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)
angles = st.floats(-math.pi, math.pi, allow_nan=False)
unit_vectors = (
    st.tuples(finite, finite, finite)
    .map(np.array)
    .filter(lambda v: np.linalg.norm(v) > 1e-3)
    .map(lambda v: v / np.linalg.norm(v))
)
quaternions = (
    st.tuples(finite, finite, finite, finite)
    .map(np.array)
    .filter(lambda q: np.linalg.norm(q) > 1e-3)
)


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _assert_rotation(R: np.ndarray) -> None:
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-14)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)


@given(unit_vectors, st.floats(0.0, math.pi))
@FAST
def test_rotation_vector_round_trips_for_every_angle(axis: np.ndarray, angle: float) -> None:
    R = rotvec_to_matrix(axis * angle)
    _assert_rotation(R)
    assert np.allclose(rotvec_to_matrix(matrix_to_rotvec(R)), R, atol=1e-14)
    if angle < math.pi - 1e-6:  # at π, v and -v are the same rotation
        assert np.allclose(matrix_to_rotvec(R), axis * angle, atol=1e-13)


@given(unit_vectors, st.floats(0.0, 1e-7))
@FAST
def test_rotation_vector_is_exact_near_zero(axis: np.ndarray, angle: float) -> None:
    v = axis * angle
    R = rotvec_to_matrix(v)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    # second order Taylor expansion; the rest is below θ³/6 < 2e-22
    assert np.allclose(R, np.eye(3) + K + K @ K / 2, rtol=0, atol=1e-21)
    assert np.allclose(matrix_to_rotvec(R), v, rtol=1e-9, atol=1e-22)


@given(unit_vectors, st.floats(0.0, 1e-7))
@FAST
def test_rotation_vector_is_stable_near_pi(axis: np.ndarray, eps: float) -> None:
    angle = math.pi - eps
    R = rotvec_to_matrix(axis * angle)
    v = np.array(matrix_to_rotvec(R))
    assert np.linalg.norm(v) == pytest.approx(angle, abs=1e-12)
    assert abs(abs(float(v @ axis)) - angle) < 1e-12  # same axis up to sign
    assert np.allclose(rotvec_to_matrix(v), R, atol=1e-14)


def test_rotation_vector_conventions_match_axis_rotations() -> None:
    assert np.allclose(rotvec_to_matrix([0.3, 0, 0]), _rot_x(0.3))
    assert np.allclose(rotvec_to_matrix([0, -0.7, 0]), _rot_y(-0.7))
    assert np.allclose(rotvec_to_matrix([0, 0, 2.5]), _rot_z(2.5))
    assert matrix_to_rotvec(np.eye(3)) == (0.0, 0.0, 0.0)
    v = matrix_to_rotvec(_rot_z(math.pi))
    assert np.allclose(np.abs(v), [0, 0, math.pi], atol=1e-15)


@given(quaternions)
@FAST
def test_quaternion_round_trips_up_to_sign(q: np.ndarray) -> None:
    R = quaternion_to_matrix(q)
    _assert_rotation(R)
    back = np.array(matrix_to_quaternion(R))
    unit = q / np.linalg.norm(q)
    assert back[3] >= 0.0
    assert np.allclose(back, unit, atol=1e-12) or np.allclose(back, -unit, atol=1e-12)


def test_quaternion_is_x_y_z_w() -> None:
    s = math.sin(0.25)
    assert np.allclose(quaternion_to_matrix([0, 0, s, math.cos(0.25)]), _rot_z(0.5))
    assert np.allclose(matrix_to_quaternion(_rot_x(0.5)), [s, 0, 0, math.cos(0.25)])


@given(angles, st.floats(-math.pi / 2, math.pi / 2), angles)
@FAST
def test_rpy_is_rz_ry_rx_and_round_trips(roll: float, pitch: float, yaw: float) -> None:
    R = rpy_to_matrix((roll, pitch, yaw))
    assert np.allclose(R, _rot_z(yaw) @ _rot_y(pitch) @ _rot_x(roll), atol=1e-15)
    r, p, y = matrix_to_rpy(R)
    assert -math.pi / 2 <= p <= math.pi / 2
    assert np.allclose(rpy_to_matrix((r, p, y)), R, atol=1e-14)


@given(angles, angles, st.sampled_from([-1.0, 1.0]), st.floats(0.0, 1e-9))
@FAST
def test_rpy_reproduces_the_rotation_at_gimbal_lock(
    roll: float, yaw: float, side: float, eps: float
) -> None:
    R = rpy_to_matrix((roll, side * (math.pi / 2 - eps), yaw))
    assert np.allclose(rpy_to_matrix(matrix_to_rpy(R)), R, atol=1e-14)


@given(unit_vectors, st.floats(0.0, math.pi))
@FAST
def test_rotation_angle_is_the_rotation_vector_norm(axis: np.ndarray, angle: float) -> None:
    assert rotation_angle(rotvec_to_matrix(axis * angle)) == pytest.approx(angle, abs=1e-12)


poses = st.builds(
    lambda p, axis, angle: Pose.from_rotvec(p, axis * angle),
    st.tuples(finite, finite, finite),
    unit_vectors,
    st.floats(0.0, math.pi),
)


@given(poses)
@FAST
def test_pose_forms_round_trip(pose: Pose) -> None:
    for other in (
        Pose.from_ur(pose.as_ur()),
        Pose.from_quaternion(pose.position, pose.quaternion),
        Pose.from_rpy(pose.position, pose.rpy),
        Pose.from_matrix(pose.matrix),
        Pose.parse(pose.as_quaternion_list()),
        Pose.parse(pose.as_rpy_list()),
    ):
        assert other.isclose(pose, position_tol=1e-14, angle_tol=1e-12)


@given(poses, poses)
@settings(max_examples=50)
def test_pose_composition_matches_matrices(a: Pose, b: Pose) -> None:
    assert np.allclose((a @ b).matrix, a.matrix @ b.matrix, atol=1e-12)
    assert (a @ a.inverse()).isclose(Pose.identity(), position_tol=1e-13, angle_tol=1e-13)
    assert np.allclose(a.transform_point(b.position), (a @ b).position, atol=1e-12)
    assert a.distance(b) == pytest.approx(float(np.linalg.norm(a.position - b.position)))
    assert a.angle_to(b) == pytest.approx(rotation_angle(a.rotation.T @ b.rotation))


def test_pose_is_immutable() -> None:
    pose = Pose.from_ur([0.1, 0.2, 0.3, 0, 0, 1])
    with pytest.raises(AttributeError):
        pose.foo = 1  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="read-only"):
        pose.position[0] = 5.0


def test_parse_takes_seed_lists_as_quaternion_or_rpy() -> None:
    q = Pose.parse([0.1, 0.2, 0.3, 0.0, 0.0, math.sin(0.5), math.cos(0.5)])
    assert np.allclose(q.rotation, _rot_z(1.0))
    assert np.allclose(q.position, [0.1, 0.2, 0.3])
    r = Pose.parse([0.1, 0.2, 0.3, 0.0, 0.0, 1.0])  # yaw, not a rotation vector... same here
    assert np.allclose(r.rotation, _rot_z(1.0))
    r2 = Pose.parse([0, 0, 0, 0.5, 0.0, 1.0])
    assert np.allclose(r2.rotation, _rot_z(1.0) @ _rot_x(0.5))
    assert Pose.parse(np.array([0, 0, 0, 0, 0, 0, 2.0])).isclose(Pose.identity())
    pose = Pose.identity()
    assert Pose.parse(pose) is pose


@pytest.mark.parametrize(
    "bad",
    [
        [0, 0, 0, 0, 0],
        [0, 0, 0, 0, 0, 0, 0, 0],
        [0, 0, 0, 0, 0, 0, 0],  # zero quaternion
        [0, 0, 0, 1e-9, 0, 0, 0],
        [math.nan, 0, 0, 0, 0, 0],
        [0, 0, math.inf, 0, 0, 0, 1],
        [0, 0, 0, 0, 0, -math.inf],
        ["0", 0, 0, 0, 0, 0],
        [True, 0, 0, 0, 0, 0],
        [[0, 0, 0], [0, 0, 0]],
        "0,0,0,0,0,0",
        None,
        3.0,
        {"x": 1},
    ],
)
def test_parse_rejects_bad_targets(bad: object) -> None:
    with pytest.raises(InvalidTargetError):
        Pose.parse(bad)


def test_bad_targets_are_value_errors_of_the_hierarchy() -> None:
    with pytest.raises(ValueError, match="non-finite") as info:
        Pose.from_ur([0, 0, math.nan, 0, 0, 0])
    assert isinstance(info.value, InvalidArgumentError)


@pytest.mark.parametrize(
    "matrix",
    [
        np.diag([1.0, 1.0, -1.0, 1.0]),  # reflection
        np.diag([2.0, 1.0, 1.0, 1.0]),  # scaling
        np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]),  # bad last row
    ],
)
def test_from_matrix_rejects_non_rigid_transforms(matrix: np.ndarray) -> None:
    with pytest.raises(InvalidTargetError):
        Pose.from_matrix(matrix)


def test_from_matrix_cleans_up_rounding_in_the_rotation() -> None:
    T = np.eye(4)
    T[:3, :3] = _rot_z(0.3) + 1e-9
    R = Pose.from_matrix(T).rotation
    _assert_rotation(R)
    assert np.allclose(R, _rot_z(0.3), atol=1e-8)


junk = st.one_of(
    st.none(),
    st.text(max_size=8),
    st.floats(),
    st.lists(st.one_of(st.floats(), st.integers(), st.text(max_size=2), st.none()), max_size=9),
    st.dictionaries(st.text(max_size=2), st.floats(), max_size=3),
)


@given(junk)
@FAST
def test_parse_gives_a_pose_or_an_invalid_target_error(obj: object) -> None:
    try:
        pose = Pose.parse(obj)
    except InvalidTargetError:
        return
    assert isinstance(obj, list)
    assert len(obj) in (6, 7)
    assert np.all(np.isfinite(pose.matrix))
    _assert_rotation(pose.rotation)


def test_pose_survives_pickling_and_copying() -> None:
    import copy
    import pickle

    pose = Pose.from_ur([0.1, -0.2, 0.3, 0.4, -0.5, 0.6])
    for other in (pickle.loads(pickle.dumps(pose)), copy.deepcopy(pose)):
        assert other == pose
        assert hash(other) == hash(pose)
        assert not other.position.flags.writeable
