"""UR3e forward/inverse kinematics: known poses, round trips, seeds, limits, singularities."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from fxcell.config import SEED_TCP, JointLimits
from fxcell.errors import InvalidTargetError, SingularityError, UnreachableError
from fxcell.geometry import Pose
from fxcell.motion.kinematics import UR3E_DH, Kinematics, dh_transform

FLANGE = Kinematics.ur3e()
SEED = Kinematics.ur3e(SEED_TCP)
HOME = [0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0]

joint_values = st.floats(-2 * math.pi, 2 * math.pi, allow_nan=False)
configurations = st.lists(joint_values, min_size=6, max_size=6).map(np.array)


def _pose_error(a: Pose, b: Pose) -> tuple[float, float]:
    return a.distance(b), a.angle_to(b)


def _tolerance(kin: Kinematics, q: np.ndarray) -> float:
    """Exact to rounding away from singularities; within 1e-10 (m, rad) next to them, where
    branches the closed form misses by rounding are polished by Newton steps."""
    shoulder, elbow, wrist = kin.singularity_margins(q)
    return 1e-12 if min(shoulder, elbow, wrist) > 1e-3 else 1e-10


def test_zero_configuration_matches_the_dh_table_by_hand() -> None:
    # all θ = 0: arm stretched along -x, rotation Rx(α1 + α4 + α5) = Rx(π/2)
    pose = FLANGE.forward([0.0] * 6)
    assert np.allclose(pose.position, [-0.45675, -0.22315, 0.0665], atol=1e-15)
    assert np.allclose(pose.as_ur()[3:], [math.pi / 2, 0.0, 0.0], atol=1e-15)


def test_home_pose_is_what_the_teach_pendant_shows() -> None:
    # arm straight up; the pendant shows (0, -223.15, 693.95) mm, rotvec ±(0, 2.2214, -2.2214)
    pose = FLANGE.forward(HOME)
    assert np.allclose(pose.position, [0.0, -0.22315, 0.69395], atol=1e-15)
    expected = Pose.from_ur(
        [0, -0.22315, 0.69395, 0, math.pi / math.sqrt(2), -math.pi / math.sqrt(2)]
    )
    assert pose.angle_to(expected) < 1e-14


@given(configurations)
@settings(max_examples=50)
def test_forward_is_the_product_of_dh_transforms_and_the_tcp(q: np.ndarray) -> None:
    T = np.eye(4)
    for theta, d, a, alpha in zip(q, UR3E_DH.d, UR3E_DH.a, UR3E_DH.alpha, strict=True):
        T = T @ dh_transform(theta, d, a, alpha)
    assert np.allclose(FLANGE.forward(q).matrix, T, atol=1e-15)
    tcp = Pose.from_ur(SEED_TCP)
    assert np.allclose(SEED.forward(q).matrix, T @ tcp.matrix, atol=1e-15)
    assert np.allclose(SEED.forward_flange(q).matrix, T, atol=1e-15)
    frames = SEED.joint_frames(q)
    assert len(frames) == 8
    T = np.eye(4)
    for k, (theta, d, a, alpha) in enumerate(
        zip(q, UR3E_DH.d, UR3E_DH.a, UR3E_DH.alpha, strict=True)
    ):
        assert np.allclose(frames[k], T, atol=1e-15)
        T = T @ dh_transform(theta, d, a, alpha)
    assert np.allclose(frames[6], T, atol=1e-15)
    assert np.allclose(frames[7], T @ tcp.matrix, atol=1e-15)


@pytest.mark.parametrize("kin", [FLANGE, SEED], ids=["flange", "seed_tcp"])
@given(q=configurations)
@settings(max_examples=60)
def test_inverse_of_forward_returns_the_configuration(kin: Kinematics, q: np.ndarray) -> None:
    pose = kin.forward(q)
    sol = kin.inverse(pose, seed=q)
    assert np.all(np.abs(sol) <= 2 * math.pi)
    dp, dr = _pose_error(kin.forward(sol), pose)
    assert dp < _tolerance(kin, q)
    assert dr < _tolerance(kin, q)
    # from its own configuration the nearest solution is that configuration (away from the
    # wrist continuum and the elbow, where 1e-16 of pose can be 1e-7 of joint angle)
    if min(kin.singularity_margins(q)[1:]) > 1e-3:
        assert np.allclose(sol, q, atol=1e-7)


@pytest.mark.parametrize("kin", [FLANGE, SEED], ids=["flange", "seed_tcp"])
@given(q=configurations, seed=configurations)
# stretched and next to the wrist singularity at once (found by Hypothesis): the joints are
# fixed only to ~3e-5 rad (θ5 = 1.2e-7) and ~1e-3 rad (θ5 = 1.1e-10)
@example(
    q=np.array([0.0, 0.0, 0.0, 1.0, 1.192092896e-07, 0.0]), seed=np.array([0, 0, 0, 1.0, 0, 0])
)
@example(q=np.array([0.0, 1.0, 1.192092896e-07, 1.0, 1.192092896e-07, 0.0]), seed=np.zeros(6))
@example(q=np.array([0.0, -5.0, 0.0, 0.0, 1.1e-10, 0.0]), seed=np.zeros(6))
# within a few 1e-12 of the wrist singularity (θ5 = 3.1e-12, 1.7e-12; Hypothesis)
@example(q=np.array([0.0, 0.0, 1.0, 0.0, 3.0964434259240957e-12, 0.0]), seed=np.zeros(6))
@example(q=np.array([3.5, 3.015625, 0.0, 0.0, -1.7296448626284881e-12, 0.0]), seed=np.zeros(6))
# stretched and θ5 = 1e-6: θ2 2.1e-6 (the resolution there, 1e-5) from its limit (Hypothesis)
@example(q=np.array([1.0, 1e-06, 0.0, 1.0, 1e-06, 0.0]), seed=np.array([0.0, 4.0, 0, 0, 0, 0]))
@settings(max_examples=60)
def test_every_solution_reaches_the_pose_and_the_nearest_is_picked(
    kin: Kinematics, q: np.ndarray, seed: np.ndarray
) -> None:
    pose = kin.forward(q)
    sols = kin.inverse_all(pose, seed=seed)
    assert 1 <= len(sols) <= 8
    tol = _tolerance(kin, q)
    for s in sols:
        dp, dr = _pose_error(kin.forward(s), pose)
        assert dp < tol
        assert dr < tol
        assert np.all(np.abs(s) <= 2 * math.pi)
        for shifted in (s + 2 * math.pi, s - 2 * math.pi):  # nearest 2π-equivalent per joint
            inside = np.abs(shifted) <= 2 * math.pi
            assert np.all(np.abs(s - seed)[inside] <= np.abs(shifted - seed)[inside] + 1e-12)
    best = kin.inverse(pose, seed=seed)
    dists = [float(np.linalg.norm(s - seed)) for s in sols]
    assert dists == sorted(dists)
    # next to the wrist singularity θ6 (and θ4) carry rounding ~1e-16 / |sin θ5|; stretched
    # (or folded) as well, the arm turns frame 4's move along its circle into its square
    # root of θ2..θ4: the pose fixes the joints only that well (every such solution reaches
    # it to ~1e-16; which one each search lands on is rounding)
    _, elbow, wrist = kin.singularity_margins(q)
    resolution = 0.0
    if 0.0 < wrist < 1e-6:
        resolution = math.sqrt(1e-16 / wrist) if elbow < 1e-3 else 1e-16 / wrist
    # the same branch (a stretched elbow turns rounding ε into √ε of joint angle, up to 1e-6,
    # or the resolution above, which decides on which side of a joint limit an equivalent
    # lands: skip those cases)
    near = max(1e-6, 3.0 * resolution)
    at_limit = any(np.any(np.abs(np.abs(s) - 2 * math.pi) < near) for s in [*sols, best])
    # within a few 1e-12 of the wrist singularity the closed form may treat a branch as
    # exactly singular (a continuum member, ~1e-12 off the pose) or not, by rounding, and
    # inverse() and inverse_all() round differently: skip those cases too
    at_limit = at_limit or 0.0 < wrist < 1e-11
    if not at_limit:
        slack = max(1e-5, 3.0 * resolution)
        assert float(np.linalg.norm(best - seed)) == pytest.approx(dists[0], abs=slack)
    assert kin.forward(best).isclose(pose, position_tol=tol, angle_tol=tol)


def test_generic_configuration_has_eight_distinct_solutions() -> None:
    q = np.array([0.3, -1.2, 1.1, -0.7, 1.0, 0.4])
    sols = FLANGE.inverse_all(FLANGE.forward(q))
    assert len(sols) == 8
    wrapped = {tuple(np.round(np.mod(s + math.pi, 2 * math.pi), 6)) for s in sols}
    assert len(wrapped) == 8


def test_solutions_are_shifted_by_two_pi_toward_the_seed() -> None:
    q = np.array([5.5, -1.2, 1.1, -5.0, 1.0, 6.0])
    sol = FLANGE.inverse(FLANGE.forward(q), seed=q + 0.01)
    assert np.allclose(sol, q, atol=1e-9)
    sol2 = FLANGE.inverse(FLANGE.forward(q), seed=q - 2 * math.pi + 0.01)
    assert np.allclose(sol2, np.clip(q - 2 * math.pi, -2 * math.pi, None), atol=1e-9) or np.all(
        np.abs(sol2) <= 2 * math.pi
    )


def test_a_seed_far_outside_the_limits_still_gets_the_solution_inside() -> None:
    q = np.array([0.3, -1.2, 1.1, -0.7, 1.0, 0.4])
    pose = FLANGE.forward(q)
    for far in (q + 6 * math.pi, q - 10 * math.pi):
        sol = FLANGE.inverse(pose, seed=far)
        assert np.all(np.abs(sol) <= 2 * math.pi)
        assert FLANGE.forward(sol).isclose(pose, position_tol=1e-12, angle_tol=1e-12)
        assert len(FLANGE.inverse_all(pose, seed=far)) == 8


def test_joint_limits_restrict_the_solutions() -> None:
    q = np.array([0.3, -1.2, 1.1, -0.7, 1.0, 0.4])
    pose = FLANGE.forward(q)
    lower = [-math.pi, -math.pi, 0.0, -math.pi, 0.0, -math.pi]  # elbow and wrist 2 positive
    narrow = Kinematics.ur3e(limits=(lower, [math.pi] * 6))
    sols = narrow.inverse_all(pose)
    assert sols
    assert all(s[2] >= 0.0 and s[4] >= 0.0 for s in sols)
    assert len(sols) < 8
    with pytest.raises(UnreachableError, match="joint limits"):
        Kinematics.ur3e(limits=([-0.1] * 6, [0.1] * 6)).inverse(pose)


@pytest.mark.parametrize(
    "limits",
    [([0.0] * 6, [0.0] * 6), ([math.nan] * 6, [1.0] * 6), ([-1.0] * 5, [1.0] * 5)],
)
def test_bad_limits_are_refused(limits: tuple[list[float], list[float]]) -> None:
    with pytest.raises(ValueError, match="joint limits"):
        Kinematics.ur3e(limits=limits)


def test_limits_come_from_the_config_by_default() -> None:
    lim = JointLimits()
    assert FLANGE.lower == lim.position_min
    assert FLANGE.upper == lim.position_max
    custom = JointLimits(position_min=(-1.0,) * 6, position_max=(1.0,) * 6)
    assert Kinematics.ur3e(limits=custom).upper == (1.0,) * 6


def test_validity_check_skips_rejected_solutions() -> None:
    q = np.array([0.3, -1.2, 1.1, -0.7, 1.0, 0.4])
    pose = FLANGE.forward(q)
    sol = FLANGE.inverse(pose, seed=q, valid=lambda c: bool(c[2] < 0.0))  # elbow down only
    assert sol[2] < 0.0
    assert FLANGE.forward(sol).isclose(pose, position_tol=1e-12, angle_tol=1e-12)
    with pytest.raises(UnreachableError, match="validity check"):
        FLANGE.inverse(pose, seed=q, valid=lambda c: False)


@pytest.mark.parametrize(
    "pose",
    [
        Pose.from_ur([0.6, 0.0, 0.2, 0, math.pi, 0]),  # beyond the 0.5 m reach
        Pose.from_ur([0.0, 0.0, 1.2, 0, 0, 0]),  # above the fully stretched arm
        Pose.from_ur([0.0, 0.0, 0.15, 0, 0, 0]),  # wrist centre inside the base cylinder
    ],
)
def test_unreachable_poses_raise(pose: Pose) -> None:
    with pytest.raises(UnreachableError):
        FLANGE.inverse(pose, seed=HOME)
    assert FLANGE.inverse_all(pose) == []


@pytest.mark.parametrize("kin", [FLANGE, SEED], ids=["flange", "seed_tcp"])
@pytest.mark.parametrize("seed_q6", [0.2, 0.7, 2.5, -2.0])
def test_wrist_singular_pose_gets_a_valid_solution(kin: Kinematics, seed_q6: float) -> None:
    # θ5 = 0: axes 2, 3, 4 and 6 are parallel, a continuum of solutions
    q = np.array([0.4, -1.3, 1.2, -1.0, 0.0, 0.7])
    pose = kin.forward(q)
    seed = np.array([0.4, -1.3, 1.2, -0.5, 0.0, seed_q6])
    sol = kin.inverse(pose, seed=seed)
    assert kin.forward(sol).isclose(pose, position_tol=1e-12, angle_tol=1e-12)
    # the nearest member of the continuum: no farther than q, and locally optimal in θ6
    assert np.linalg.norm(sol - seed) <= np.linalg.norm(q - seed) + 1e-9
    for dq6 in (-1e-3, 1e-3):
        other = kin.inverse(pose, seed=seed + np.array([0, 0, 0, 0, 0, dq6]))
        assert np.linalg.norm(other - seed) >= np.linalg.norm(sol - seed) - 1e-9
    with pytest.raises(SingularityError, match="wrist"):
        kin.check_singularity(sol)


@pytest.mark.parametrize("q5", [1e-13, 1e-9, -1e-7, math.pi - 1e-8])
@pytest.mark.parametrize("q3", [1.2, 1e-3])
def test_a_pose_next_to_the_wrist_singularity_is_solved_in_closed_form(
    q5: float, q3: float
) -> None:
    # θ6 then carries rounding error ~1e-16/|sin θ5|, but every joint is solved consistently
    # with it: the closed form reaches the pose, on the hot path (no polishing search), and
    # as near the seed as the general path (up to that rounding)
    q = np.array([0.4, -1.3, q3, -1.0, q5, 0.7])
    pose = FLANGE.forward(q)
    seed = q + np.array([0.3, -0.2, 0.1, 0.4, 0.2, -0.5])
    fast = FLANGE._fast_nearest(pose, seed.tolist())
    assert fast is not None
    sol = np.array(fast)
    assert FLANGE.forward(sol).isclose(pose, position_tol=1e-12, angle_tol=1e-12)
    general = FLANGE.inverse(pose, seed=seed, valid=lambda _: True)
    rounding = 1e-14 / abs(math.sin(q5))
    assert np.linalg.norm(sol - seed) == pytest.approx(np.linalg.norm(general - seed), abs=rounding)


def test_wrist_singular_pose_is_solved_whatever_the_seed_wrist() -> None:
    # stretched far out: only a range of θ6 lets the arm reach, the seed's is outside it
    q = np.array([0.0, -0.2, 0.15, 0.0, 0.0, 0.0])
    pose = FLANGE.forward(q)
    for q6 in np.linspace(-math.pi, math.pi, 13):
        sol = FLANGE.inverse(pose, seed=[0, 0, 0, 0, 0, q6])
        assert FLANGE.forward(sol).isclose(pose, position_tol=1e-12, angle_tol=1e-12)


def test_a_wrist_at_two_pi_with_the_arm_stretched_gets_the_solution_nearest_the_seed() -> None:
    # θ5 = ±2π is wrist-singular too, but its forward kinematics leaves |sin θ5| at ~1e-14
    # of rounding (θ1 at full stretch carries ~3e-14): taken for a regular wrist, θ6 then
    # came from that noise, a valid solution up to 3.6 rad farther from the seed than q
    rng = np.random.default_rng(3)
    for _ in range(3000):
        q = rng.uniform(-2 * math.pi, 2 * math.pi, 6)
        q[2], q[4] = 0.0, rng.choice((-1.0, 1.0)) * 2 * math.pi
        seed = q + rng.normal(0.0, 0.05, 6)
        pose = FLANGE.forward(q)
        sol = FLANGE.inverse(pose, seed)
        assert FLANGE.forward(sol).isclose(pose, position_tol=1e-10, angle_tol=1e-10)
        assert np.linalg.norm(sol - seed) <= np.linalg.norm(q - seed) + 1e-9, (q, seed)


def _continuum_scan(kin: Kinematics, pose: Pose, q1: float, q5: float, seed: np.ndarray) -> dict:
    """Brute force over a wrist-singular continuum (θ1 = q1, θ5 = q5 ∈ {0, ±π}): θ6 on a
    grid of 2000, θ2..θ4 from the planar 2R problem of frame 4 (public FK and DH only), each
    joint shifted by 2π to the equivalent nearest the seed within ±2π. The smallest distance
    to the seed per elbow sign (+1, -1), with the configuration reaching it."""
    d, a, alpha = UR3E_DH.d, UR3E_DH.a, UR3E_DH.alpha
    t = np.linspace(-math.pi, math.pi, 2000, endpoint=False)
    flange = pose.matrix @ np.linalg.inv(kin.tcp.matrix)
    # frame 4 = flange · T56(θ6)⁻¹ · T45⁻¹, with T56 = Rz(θ6)·Tz(d6) (a6 = α6 = 0)
    inv56 = np.zeros((t.size, 4, 4))
    c, s = np.cos(t), np.sin(t)
    inv56[:, 0, 0], inv56[:, 0, 1], inv56[:, 1, 0], inv56[:, 1, 1] = c, s, -s, c
    inv56[:, 2, 2], inv56[:, 2, 3], inv56[:, 3, 3] = 1.0, -d[5], 1.0
    inv45 = np.linalg.inv(dh_transform(q5, d[4], a[4], alpha[4]))
    in1 = np.linalg.inv(dh_transform(q1, d[0], a[0], alpha[0])) @ flange
    T14 = np.einsum("ij,njk,kl->nil", in1, inv56, inv45)
    x, y = T14[:, 0, 3], T14[:, 1, 3]
    phi = np.arctan2(T14[:, 1, 0], T14[:, 0, 0])  # θ2 + θ3 + θ4
    c3 = (x * x + y * y - a[1] ** 2 - a[2] ** 2) / (2 * a[1] * a[2])
    ok = np.abs(c3) <= 1.0
    c3 = np.clip(c3, -1.0, 1.0)

    def nearest(v: np.ndarray, s: float) -> np.ndarray:
        options = v[..., None] + 2 * math.pi * np.arange(-3, 4)
        options[np.abs(options) > 2 * math.pi] = np.inf
        return options[np.arange(v.size), np.argmin(np.abs(options - s), axis=-1)]

    best = {}
    for elbow in (1, -1):
        q3 = elbow * np.arccos(c3)
        q2 = np.arctan2(y, x) - np.arctan2(a[2] * np.sin(q3), a[1] + a[2] * c3)
        q = np.stack([np.full_like(t, q1), q2, q3, phi - q2 - q3, np.full_like(t, q5), t], 1)
        q = np.stack([nearest(q[:, j], seed[j]) for j in range(6)], 1)
        dist = np.where(ok, np.linalg.norm(q - seed, axis=1), np.inf)
        i = int(np.argmin(dist))
        if np.isfinite(dist[i]):
            best[elbow] = (float(dist[i]), q[i])
    return best


singular_configurations = st.tuples(configurations, st.sampled_from([0.0, math.pi, -math.pi])).map(
    lambda c: np.array([*c[0][:4], c[1], c[0][5]])
)


@pytest.mark.parametrize("kin", [FLANGE, SEED], ids=["flange", "seed_tcp"])
@given(q=singular_configurations, seed=configurations)
# a minimum 0.18 rad of θ3 from the stretch, past a rise of f from it (found by Hypothesis)
@example(q=np.array([0.0, 0.0, 1.0, -2.5, 0.0, 0.0]), seed=np.zeros(6))
# the other shoulder's nearest branch at full stretch, θ3 = 0 or ±3e-8 by rounding (Hypothesis)
@example(q=np.array([-0.375, 0.0, 0.0, 0.0, math.pi, 0.0]), seed=np.array([0, 1.0, 0, 3.0, 0, 0]))
# the nearest member 5e-14 of θ6 short of the stretched end, where θ2's shift toward the
# seed flips at its limit (-2π): Newton's steps stopped 3.6e-9 short, 2.6e-6 farther
# (Hypothesis)
@example(q=np.array([0.0, 0.0, -1.19e-7, 4.5, 0.0, 0.0]), seed=np.array([0, -4.0, 0, 2.0, 0, 0]))
# the seed on the continuum: Newton's steps stopped once the distance² fell by under 1e-13,
# 1.6e-7 and 4.2e-8 from it, or at u = 1e-7 from an end, 1.1e-7 from it (Hypothesis)
@example(
    q=np.array([0.0, 0.0, 1.192092896e-07, 0, 0, 0]),
    seed=np.array([0, 0, 1.192092896e-07, 0, 0, 0]),
)
@example(
    q=np.array([0.0, 0.0, -1.192092896e-07, 0, 0, 0]),
    seed=np.array([0, 0, -1.192092896e-07, 0, 0, 0]),
)
@example(q=np.array([0.0, 0.0, 1.984375, 0.0, 0.0, 0.0]), seed=np.array([0, 0, 1.984375, 0, 0, 0]))
@example(
    q=np.array([2.75, 3.0, 3.145322439166149, 2.375, 0.0, 3.0]),
    seed=np.array([2.75, 3.0, 3.145322439166149, 2.375, 0.0, 3.0]),
)
# a minimum 0.007 of u inside a stretched end, which a concave step leapt past (Hypothesis)
@example(
    q=np.array([0.0, 0.0, 0.0, 3.0, 0.0, -4.929154813057889]),
    seed=np.array([0.0, 0.0, 0.0078125, 3.0, 0.0, 1.0]),
)
# the nearest member at θ2's limit, where the closed form put θ2 1.1e-12 beyond it (θ3 = 1e-4:
# rounding amplified) and its shift flipped (Hypothesis)
@example(
    q=np.array([0.75, 0.0, 0.0001, 2.5, math.pi, 0.0]),
    seed=np.array([0.0, 6.0, 0.0, 3.0, 0.0, 0.0]),
)
# the nearest member in a sliver of θ6 next to a stretched end where θ2 and θ3 sit at 2π
# (Hypothesis)
@example(
    q=np.array([6.25, 0.0, 6.283185307179585, 0.0, 0.0, 0.0]), seed=np.array([0, 4.0, 4.0, 0, 0, 0])
)
# a dip 0.07 rad of θ6 past the grid point beside a stretched end, the end the grid's
# minimum (Hypothesis)
@example(
    q=np.array([0.0, 0.0, 0.0, 5.71875, 0.0, 4.875]),
    seed=np.array([0.0, 0.0, 0.0, 5.71875, 0.0, 5.71875]),
)
# a continuum 6e-6 rad of θ6 long, ending 3e-11 short of where θ6's shift flips at its limit,
# which reaches the pose (Hypothesis)
@example(
    q=np.array([0.0, 0.0, 0.0, -1.5708, 0.0, 0.0]), seed=np.array([0.0, 0.0, 0.0, 0.0, 0.0, -4.0])
)
@settings(max_examples=40, deadline=None)
def test_wrist_singular_solutions_are_no_farther_than_a_dense_scan(
    kin: Kinematics, q: np.ndarray, seed: np.ndarray
) -> None:
    # θ5 = 0 or ±π exactly: per shoulder and elbow a continuum, of which the member nearest
    # the seed must come back (no farther than the best of 2000 θ6 values, every joint
    # shifted by 2π toward the seed)
    # next to the shoulder singularity θ1 carries rounding ~4e-17 / h (h: the wrist centre's
    # distance from it, m), which tips the wrist off its singularity by as much: no
    # continuum to compare with there (h = 6e-7 m gave |sin θ5| = 9e-6; Hypothesis)
    assume(kin.singularity_margins(q)[0] > 1e-4)
    pose = kin.forward(q)
    sols = kin.inverse_all(pose, seed=seed)
    for s in sols:
        assert kin.forward(s).isclose(pose, position_tol=1e-10, angle_tol=1e-10)
    singular = [s for s in sols if abs(math.sin(s[4])) < 1e-12]
    assert singular  # q's own shoulder branch is singular
    for q1 in {round(math.remainder(s[0], 2 * math.pi), 9) for s in singular}:
        branch = [s for s in singular if abs(math.remainder(s[0] - q1, 2 * math.pi)) < 1e-6]
        scan = _continuum_scan(kin, pose, branch[0][0], branch[0][4], seed)
        for elbow, (dist, member) in scan.items():
            assert kin.forward(member).isclose(pose, position_tol=1e-9, angle_tol=1e-9)
            # the returned member of this elbow (at full stretch or fold: either elbow)
            mine = [s for s in branch if elbow * math.sin(s[2]) > -1e-6]
            assert mine
            # (1e-7: the scan's arccos at full stretch turns rounding into ~1e-8 rad)
            assert min(float(np.linalg.norm(s - seed)) for s in mine) <= dist + 1e-7
    best = kin.inverse(pose, seed=seed)
    nearest = min(sols, key=lambda s: float(np.linalg.norm(s - seed)))
    # at full stretch or fold the pose fixes θ2, θ3 and θ4 to ~1e-8 rad only (second order:
    # every θ3 within ~3e-8 of 0 reaches it to 1e-16), so which of these rounding gives
    # inverse() and inverse_all() may differ by as much
    stretched = min(abs(math.sin(best[2])), abs(math.sin(nearest[2]))) < 1e-6
    slack = 1e-7 if stretched else 1e-9
    assert np.linalg.norm(best - seed) <= np.linalg.norm(nearest - seed) + slack


def test_singularity_margin_skips_singular_solutions_or_raises() -> None:
    # straight up: θ1 has a single solution (shoulder), the elbow is stretched
    pose = FLANGE.forward(HOME)
    assert all(FLANGE.singularity(s) is not None for s in FLANGE.inverse_all(pose))
    assert FLANGE.singularity(FLANGE.inverse(pose, seed=HOME)) is not None
    with pytest.raises(SingularityError, match="singularity"):
        FLANGE.inverse(pose, seed=HOME, singularity_margin=1e-3)
    # wrist singular in the seed's shoulder branch only: the other shoulder is taken
    q = np.array([0.4, -1.3, 1.2, -1.0, 0.0, 0.7])
    pose = FLANGE.forward(q)
    assert FLANGE.singularity(q) == "wrist"
    sol = FLANGE.inverse(pose, seed=q, singularity_margin=1e-3)
    assert FLANGE.singularity(sol) is None
    assert FLANGE.forward(sol).isclose(pose, position_tol=1e-12, angle_tol=1e-12)
    # a singular candidate is skipped before the validity check sees it
    seen: list[np.ndarray] = []
    FLANGE.inverse(
        pose, seed=q, singularity_margin=1e-3, valid=lambda c: bool(seen.append(c)) or True
    )
    assert all(FLANGE.singularity(c) is None for c in seen)


def test_elbow_stretched_and_shoulder_singular_poses_are_solved() -> None:
    stretched = np.array([0.2, -0.9, 0.0, -1.0, 0.8, 0.3])
    pose = FLANGE.forward(stretched)
    sol = FLANGE.inverse(pose, seed=stretched)
    assert FLANGE.forward(sol).isclose(pose, position_tol=1e-10, angle_tol=1e-10)
    with pytest.raises(SingularityError, match="elbow"):
        FLANGE.check_singularity(stretched)
    # shoulder: wrist centre in the plane of axes 1 and 2 (straight up at home)
    assert FLANGE.singularity_margins(HOME)[0] < 1e-15
    assert len(FLANGE.inverse_all(FLANGE.forward(HOME), seed=HOME)) == 1  # branches coincide
    sol = FLANGE.inverse(FLANGE.forward(HOME), seed=HOME)
    assert np.allclose(sol, HOME, atol=1e-7)
    with pytest.raises(SingularityError, match="shoulder"):
        FLANGE.check_singularity(HOME)
    FLANGE.check_singularity([0.3, -1.2, 1.1, -0.7, 1.0, 0.4])  # no error


tiny = st.floats(1e-12, 1e-5).flatmap(lambda v: st.sampled_from([v, -v]))


@pytest.mark.parametrize("kin", [FLANGE, SEED], ids=["flange", "seed_tcp"])
@given(q=configurations, stretch=tiny, wrist=tiny, seed=configurations)
@settings(max_examples=60, deadline=None)
def test_a_stretched_arm_next_to_the_wrist_singularity_is_reached_without_newton_steps(
    kin: Kinematics,
    q: np.ndarray,
    stretch: float,
    wrist: float,
    seed: np.ndarray,
) -> None:
    # elbow at full stretch and wrist next to θ5 = 0 (both to ~1e-12): θ6's amplified
    # rounding can leave a branch just out of reach; θ6 brings it back, with no Newton steps
    q = np.array([q[0], q[1], stretch, q[3], wrist, q[5]])
    pose = kin.forward(q)

    def polish(*args: object) -> None:
        raise AssertionError("Newton steps taken")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Kinematics, "_polish", polish)
        sol = kin.inverse(pose, seed=seed)
    assert kin.forward(sol).isclose(pose, position_tol=1e-10, angle_tol=1e-10)


def test_a_branch_just_beyond_the_reach_away_from_the_singularities_is_not_polished(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the other shoulder's elbow-stretched branch misses its reach by ~1e-9: out of reach
    # (rounding is ~1e-15 here); Newton steps on it could only fail, after milliseconds
    q = np.array(
        [3.0751233148, -6.2831853072, -6.2831853043, 6.2831853054, 1.7355780336, -3.1375813934]
    )
    calls: list[object] = []
    monkeypatch.setattr(Kinematics, "_polish", lambda *args: calls.append(args))
    pose = FLANGE.forward(q)
    sol = FLANGE.inverse(pose, seed=[5.7676, -5.322, 1.0555, -6.0843, -0.6619, -1.5954])
    assert FLANGE.forward(sol).isclose(pose, position_tol=1e-10, angle_tol=1e-10)
    assert len(FLANGE.inverse_all(pose, seed=q)) == 2
    assert calls == []


@given(configurations)
@settings(max_examples=30)
def test_jacobian_matches_finite_differences(q: np.ndarray) -> None:
    J = SEED.jacobian(q)
    h = 1e-6
    p0 = SEED.forward(q)
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        p1 = SEED.forward(q + dq)
        v = (p1.position - p0.position) / h
        w = np.array(Pose(rotation=p1.rotation @ p0.rotation.T).rotvec) / h
        assert np.allclose(J[:3, i], v, atol=1e-5)
        assert np.allclose(J[3:, i], w, atol=1e-5)


def test_refine_converges_from_a_perturbed_solution() -> None:
    q = np.array([0.3, -1.2, 1.1, -0.7, 1.0, 0.4])
    pose = SEED.forward(q)
    refined = SEED.refine(q + 1e-4, pose)
    dp, dr = _pose_error(SEED.forward(refined), pose)
    assert dp < 1e-14
    assert dr < 1e-14
    assert np.allclose(SEED.inverse(pose, seed=q, refine=True), q, atol=1e-12)


@pytest.mark.parametrize("bad", [[0.0] * 5, [math.nan] + [0.0] * 5, ["0"] * 6, None, [[0.0] * 6]])
def test_bad_joint_vectors_are_rejected(bad: object) -> None:
    with pytest.raises(InvalidTargetError):
        FLANGE.forward(bad)  # type: ignore[arg-type]
    if bad is not None:  # no seed means zeros
        with pytest.raises(InvalidTargetError):
            FLANGE.inverse(FLANGE.forward(HOME), seed=bad)  # type: ignore[arg-type]


def test_inverse_accepts_seed_style_lists() -> None:
    pose = SEED.forward([0.3, -1.2, 1.1, -0.7, 1.0, 0.4])
    sol = SEED.inverse(pose.as_quaternion_list(), seed=HOME)
    assert SEED.forward(sol).isclose(pose, position_tol=1e-12, angle_tol=1e-12)
    with pytest.raises(InvalidTargetError):
        SEED.inverse([0.1, 0.2, math.nan, 0, 0, 0], seed=HOME)


def test_importing_kinematics_does_not_import_pinocchio() -> None:
    code = "import sys, fxcell.motion.kinematics; print('pinocchio' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@given(configurations)
@settings(max_examples=40)
def test_forward_agrees_with_an_independent_ur_implementation(q: np.ndarray) -> None:
    # ur_analytic_ik (C++, bench extra) computes UR's kinematics in UR's base frame as well
    ur_analytic_ik = pytest.importorskip("ur_analytic_ik")
    assert np.allclose(
        ur_analytic_ik.ur3e.forward_kinematics(*q), FLANGE.forward(q).matrix, atol=1e-12
    )
    tcp = Pose.from_ur(SEED_TCP).matrix
    theirs = ur_analytic_ik.ur3e.forward_kinematics_with_tcp(*q, tcp)
    assert np.allclose(theirs, SEED.forward(q).matrix, atol=1e-12)


def test_tcp_given_as_pose_or_list_and_swapped_with_with_tcp() -> None:
    tcp = Pose.from_ur(SEED_TCP)
    by_pose = Kinematics.ur3e(tcp)
    q = [0.3, -1.2, 1.1, -0.7, 1.0, 0.4]
    assert by_pose.forward(q).isclose(SEED.forward(q), position_tol=1e-15, angle_tol=1e-15)
    swapped = SEED.with_tcp(None)
    assert swapped.forward(q).isclose(FLANGE.forward(q), position_tol=1e-15, angle_tol=1e-15)
    assert swapped.lower == SEED.lower
    # the TCP offset is applied in the flange frame: 0.14789 m along the flange's z axis
    flange = FLANGE.forward(q)
    z_only = Kinematics.ur3e([0, 0, 0.14789, 0, 0, 0]).forward(q)
    assert np.allclose(z_only.position, flange.position + 0.14789 * flange.rotation[:, 2])
