"""Ruckig time parameterisation: limits, optimality, waypoint blending, braking."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from fxcell.config import CellConfig
from fxcell.errors import FxcellError, InvalidFactorError, PlanningError
from fxcell.link.capabilities import UR3E
from fxcell.motion.trajectory import (
    NEGLIGIBLE_MOVE,
    Limits,
    Trajectory,
    along_path,
    braking,
    braking_duration,
    minimum_duration,
    rest_to_rest,
    through_waypoints,
    validate_factor,
    waypoint_velocities,
)

CONFIG = CellConfig.load()
DT = UR3E.sample_period  # the UR3e's trajectories: one sample per 2 ms servo cycle
LIMITS = Limits.from_config(CONFIG.limits, period=DT)
HOME = np.array(CONFIG.home)


def at(*offset: float) -> np.ndarray:
    """Joints at ``offset`` from home."""
    return HOME + np.array(offset)


def assert_within_limits(traj: Trajectory, limits: Limits, slack: float = 1e-6) -> None:
    assert np.all(np.abs(traj.velocities) <= limits.velocity * (1 + slack) + 1e-9)
    assert np.all(np.abs(traj.accelerations) <= limits.acceleration * (1 + slack) + 1e-9)
    # Finite-difference velocity agrees with the reported one (the samples are one motion).
    fd = np.diff(traj.positions, axis=0) / np.diff(traj.times)[:, None]
    mid = 0.5 * (traj.velocities[1:] + traj.velocities[:-1])
    assert np.max(np.abs(fd - mid)) < 0.02 * float(np.max(limits.velocity))


@pytest.mark.parametrize("bad", [-5, -1.4, 0, 2, 10, math.nan, math.inf, -math.inf])
def test_factor_outside_unit_interval_is_rejected(bad: float) -> None:
    with pytest.raises(InvalidFactorError) as info:
        validate_factor("velocity_factor", bad)
    assert isinstance(info.value, ValueError)
    assert isinstance(info.value, FxcellError)


@pytest.mark.parametrize("bad", ["0.5", None, True, [0.5], object()])
def test_factor_of_wrong_type_is_rejected(bad: object) -> None:
    with pytest.raises(InvalidFactorError):
        validate_factor("acceleration_factor", bad)


def test_factors_from_a_tenth_to_one_are_accepted() -> None:
    for f in np.linspace(0.1, 1.0, 10):
        assert validate_factor("velocity_factor", f) == pytest.approx(f)


def test_factors_scale_the_limits() -> None:
    scaled = Limits.from_config(CONFIG.limits, 0.5, 0.25, period=DT)
    np.testing.assert_allclose(scaled.velocity, LIMITS.velocity * 0.5)
    np.testing.assert_allclose(scaled.acceleration, LIMITS.acceleration * 0.25)
    np.testing.assert_allclose(scaled.jerk, LIMITS.jerk * 0.25)


@pytest.mark.parametrize("velocity", [1.5, 0.5, 0.1])
def test_base_quarter_turn_is_time_optimal(velocity: float) -> None:
    limits = LIMITS.with_velocity([velocity, *LIMITS.velocity[1:]])
    target = at(math.pi / 2, 0, 0, 0, 0, 0)
    traj = rest_to_rest(HOME, target, limits)
    # A single moving joint: the straight line is the unconstrained optimum.
    assert traj.duration == pytest.approx(minimum_duration(HOME, target, limits), rel=1e-9)
    # Lower bound from the velocity limit alone (cruise the whole way).
    assert traj.duration > (math.pi / 2) / velocity
    assert len(traj) == math.ceil(traj.duration / DT) + 1
    np.testing.assert_array_equal(traj.positions[-1], target)
    np.testing.assert_array_equal(traj.positions[0], HOME)
    assert_within_limits(traj, limits)


joint_vectors = st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6).map(np.array)


TINY = HOME + np.array([3.3e-13, 0, 0, 0, 0, 0])
JUST_MOVING = HOME + np.array([0, 0, 0, 0, 0, 2 * NEGLIGIBLE_MOVE])


@settings(max_examples=40, deadline=None, derandomize=True)
@given(start=joint_vectors, target=joint_vectors, vf=st.floats(0.05, 1.0), af=st.floats(0.05, 1.0))
@example(start=HOME, target=TINY, vf=1.0, af=1.0)
@example(start=HOME, target=JUST_MOVING, vf=1.0, af=1.0)
@example(start=HOME, target=HOME, vf=0.5, af=0.5)
def test_direct_move_stays_on_the_joint_line_within_limits(
    start: np.ndarray, target: np.ndarray, vf: float, af: float
) -> None:
    limits = Limits.from_config(CONFIG.limits, vf, af, period=DT)
    traj = rest_to_rest(start, target, limits)
    delta = target - start
    np.testing.assert_array_equal(traj.positions[-1], target)
    if np.max(np.abs(delta)) <= NEGLIGIBLE_MOVE:
        assert traj.duration == 0.0
        assert len(traj) == 1
        return
    assert traj.duration > 0.0
    s = (traj.positions - start) @ delta / (delta @ delta)
    off_line = traj.positions - (start + s[:, None] * delta)
    assert np.max(np.abs(off_line)) < 1e-9
    assert np.all(np.diff(s) >= -1e-12)  # never backs up
    assert_within_limits(traj, limits)
    # Staying on the line can only cost time against Ruckig's free (curved) optimum.
    assert traj.duration >= minimum_duration(start, target, limits) - 1e-9


FIVE_JOINTS_4MS = Limits(
    velocity=np.array([1.0, 1.0, 1.5, 2.0, 2.0]),
    acceleration=np.array([2.0, 2.0, 3.0, 4.0, 4.0]),
    jerk=np.full(5, 20.0),
    position_min=np.full(5, -3.0),
    position_max=np.full(5, 3.0),
    period=0.004,
)
"""Another robot kind's timing: five joints, a sample every 4 ms."""


def test_another_kinds_trajectories_have_its_joints_and_sample_period() -> None:
    start, target = np.zeros(5), np.array([0.8, -0.5, 0.3, 1.0, -1.2])
    line = rest_to_rest(start, target, FIVE_JOINTS_4MS)
    assert line.positions.shape == (math.ceil(line.duration / 0.004) + 1, 5)
    assert line.period == 0.004
    np.testing.assert_allclose(np.diff(line.times[:-1]), 0.004)
    assert_within_limits(line, FIVE_JOINTS_4MS)  # velocities agree with 4 ms differences
    corner = np.array([0.8, 0.5, 0.3, 0.0, 0.0])
    path = through_waypoints([start, corner, target], FIVE_JOINTS_4MS)
    assert path.positions.shape[1] == 5
    assert path.period == 0.004
    assert_within_limits(path, FIVE_JOINTS_4MS)
    stop = braking(*line.state(len(line) // 3), FIVE_JOINTS_4MS)
    assert stop.positions.shape[1] == 5
    assert stop.period == 0.004
    assert not stop.velocities[-1].any()
    assert stop.duration == pytest.approx(
        braking_duration(*line.state(len(line) // 3)[1:], FIVE_JOINTS_4MS), rel=1e-6
    )


def test_a_sample_period_must_be_positive() -> None:
    with pytest.raises(ValueError, match="period"):
        Limits.from_config(CONFIG.limits, period=0.0)


def test_a_negligible_move_has_no_trajectory() -> None:
    traj = rest_to_rest(HOME, TINY, LIMITS)
    assert traj.duration == 0.0
    np.testing.assert_array_equal(traj.positions, [TINY])
    # Ruckig alone would time it as a fraction of a millisecond.
    assert 0.0 < minimum_duration(HOME, TINY, LIMITS) < DT


def test_a_negligible_last_segment_is_merged_and_the_path_ends_at_the_target() -> None:
    wp = np.array([HOME, at(0.3, 0.1, 0, 0, 0, 0), at(0.6, 0.1, 0, 0, 0, 0)])
    wp = np.vstack([wp, wp[-1] + 0.5 * NEGLIGIBLE_MOVE])
    traj = through_waypoints(wp, LIMITS)
    assert traj.segments == 2
    np.testing.assert_array_equal(traj.positions[-1], wp[-1])


def test_waypoints_in_one_direction_are_passed_without_stopping() -> None:
    wp = np.array([at(0.4 * k, 0.1 * k, -0.05 * k, 0, 0, 0) for k in range(4)])
    wp[2, 1] += 0.05  # a bend, but no joint reverses
    blended = through_waypoints(wp, LIMITS)
    stopped = through_waypoints(wp, LIMITS, blend=False)
    assert blended.stops == 0
    assert stopped.stops == 2
    assert blended.duration < 0.8 * stopped.duration
    speed = np.linalg.norm(blended.velocities, axis=1)
    # Speed never drops to rest between the ends.
    assert np.min(speed[len(speed) // 10 : -len(speed) // 10]) > 0.05
    assert_within_limits(blended, LIMITS)
    np.testing.assert_array_equal(blended.positions[-1], wp[-1])


SLOW = Limits(
    velocity=np.full(6, 0.3 * math.pi),  # the UR3e's base at a velocity factor of 0.3
    acceleration=np.full(6, 0.7),
    jerk=np.full(6, 20.0),
    position_min=np.full(6, -2 * math.pi),
    position_max=np.full(6, 2 * math.pi),
    period=DT,
)
ROUNDS_PAST = -2.449402126823381
"""A base step whose cruise velocity, d * (limit / |d|), rounds one ulp past the limit."""


def test_a_waypoint_velocity_that_rounds_past_its_limit_is_held_at_it() -> None:
    wp = np.array([[2.4 + k * ROUNDS_PAST, -1.5, 1.0, -1.0, -1.5, 0.1 * k] for k in range(3)])
    assert abs(ROUNDS_PAST * (SLOW.velocity[0] / abs(ROUNDS_PAST))) > SLOW.velocity[0]
    v = waypoint_velocities(wp, SLOW)
    assert v[1, 0] == -SLOW.velocity[0]
    traj = through_waypoints(wp, SLOW)  # Ruckig refused the rounded one (a RuckigError)
    assert traj.stops == 0
    assert_within_limits(traj, SLOW)


@given(
    st.lists(st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6), min_size=3, max_size=6),
    st.floats(0.05, 1.0),
)
@settings(max_examples=200, deadline=None)
def test_waypoint_velocities_never_exceed_the_joint_limits(
    points: list[list[float]], factor: float
) -> None:
    limits = Limits.from_config(CONFIG.limits, period=DT, velocity_factor=factor)
    v = waypoint_velocities(np.array(points), limits)
    assert np.all(np.abs(v) <= limits.velocity)


def test_a_reversing_joint_stops_at_its_waypoint_only() -> None:
    wp = np.array([HOME, at(0.5, 0.3, 0, 0, 0, 0), at(1.0, 0.0, 0, 0, 0, 0)])
    traj = through_waypoints(wp, LIMITS)
    # Joint 1 reverses: its velocity crosses zero; the base keeps moving throughout.
    assert np.min(traj.velocities[1:-1, 0]) > 0
    assert np.any(traj.velocities[:, 1] > 0.01)
    assert np.any(traj.velocities[:, 1] < -0.01)
    assert_within_limits(traj, LIMITS)


def _off_polyline(samples: np.ndarray, wp: np.ndarray) -> np.ndarray:
    """Distance of each sample to the nearest straight segment of the waypoint polyline."""
    best = np.full(len(samples), np.inf)
    for p, q in itertools.pairwise(wp):
        d = q - p
        s = np.clip((samples - p) @ d / (d @ d), 0, 1)
        best = np.minimum(best, np.linalg.norm(samples - (p + s[:, None] * d), axis=1))
    return best


def test_a_blend_rejected_by_the_validator_is_replaced_by_the_straight_segments() -> None:
    wp = np.array([HOME, at(0.6, 0.1, 0, 0, 0, 0), at(0.8, 0.8, 0, 0, 0, 0)])

    def corridor(samples: np.ndarray) -> int | None:
        bad = np.flatnonzero(_off_polyline(samples, wp) > 1e-9)
        return int(bad[0]) if len(bad) else None

    free = through_waypoints(wp, LIMITS)
    assert free.stops == 0
    assert corridor(free.positions) is not None  # the blend cuts the corner
    traj = through_waypoints(wp, LIMITS, validate=corridor)
    assert corridor(traj.positions) is None
    assert traj.stops == 1
    assert traj.duration > free.duration


def test_a_validator_rejecting_the_straight_path_raises() -> None:
    wp = np.array([HOME, at(0.3, 0, 0, 0, 0, 0), at(0.6, 0.1, 0, 0, 0, 0)])
    with pytest.raises(PlanningError):
        through_waypoints(wp, LIMITS, validate=lambda samples: len(samples) // 2)


def test_along_path_follows_a_curved_path_within_limits() -> None:
    def path(s: float) -> np.ndarray:
        return HOME + np.array([0.8 * s, 0.3 * math.sin(math.pi * s), 0.2 * s * s, 0, 0, 0])

    knots = np.array([path(s) for s in np.linspace(0, 1, 41)])
    traj = along_path(path, knots, LIMITS)
    # Every sample is a point of the path: recover s from joint 0 and compare.
    s = (traj.positions[:, 0] - HOME[0]) / 0.8
    expected = np.array([path(float(x)) for x in s])
    np.testing.assert_allclose(traj.positions, expected, atol=1e-12)
    assert np.all(np.diff(s) >= -1e-12)
    assert_within_limits(traj, LIMITS, slack=0.05)
    np.testing.assert_allclose(traj.positions[-1], path(1.0))


@settings(max_examples=30, deadline=None)
@given(
    v=st.lists(st.floats(-0.6, 0.6), min_size=6, max_size=6),
    a=st.lists(st.floats(-0.6, 0.6), min_size=6, max_size=6),
)
def test_braking_reaches_rest_in_the_minimum_time(v: list[float], a: list[float]) -> None:
    traj = braking(HOME, v, a, LIMITS)
    np.testing.assert_array_equal(traj.positions[0], HOME)
    np.testing.assert_allclose(traj.velocities[0], v, atol=1e-9)
    assert np.all(traj.velocities[-1] == 0)
    bound = braking_duration(v, a, LIMITS)
    assert traj.duration == pytest.approx(bound, abs=1e-9)
    assert np.all(np.abs(traj.accelerations) <= LIMITS.acceleration + 1e-6)
