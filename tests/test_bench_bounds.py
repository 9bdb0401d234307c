"""The benches' closed-form time-optimal bounds agree with Ruckig on single joints."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import ruckig
from hypothesis import given, settings
from hypothesis import strategies as st

_PATH = Path(__file__).resolve().parents[1] / "bench" / "_bounds.py"
_spec = importlib.util.spec_from_file_location("bench_bounds", _PATH)
assert _spec is not None
assert _spec.loader is not None
bounds = importlib.util.module_from_spec(_spec)
sys.modules["bench_bounds"] = bounds
_spec.loader.exec_module(bounds)


def ruckig_rest_to_rest(d: float, v: float, a: float, j: float) -> float:
    inp = ruckig.InputParameter(1)
    inp.current_position = [0.0]
    inp.target_position = [d]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [v], [a], [j]
    traj = ruckig.Trajectory(1)
    assert ruckig.Ruckig(1).calculate(inp, traj) in (ruckig.Result.Working, ruckig.Result.Finished)
    return float(traj.duration)


def ruckig_braking(v0: float, a0: float, amax: float, jmax: float) -> float:
    inp = ruckig.InputParameter(1)
    inp.control_interface = ruckig.ControlInterface.Velocity
    inp.current_position = [0.0]
    inp.current_velocity, inp.current_acceleration = [v0], [a0]
    inp.target_velocity, inp.target_acceleration = [0.0], [0.0]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [10.0], [amax], [jmax]
    traj = ruckig.Trajectory(1)
    assert ruckig.Ruckig(1).calculate(inp, traj) in (ruckig.Result.Working, ruckig.Result.Finished)
    return float(traj.duration)


@pytest.mark.parametrize(
    ("v", "expected"),
    # the performance anchors' base quarter turn, amax 1.4, jmax 10 (2.263 / 3.639 / 15.908 s)
    [(1.5, 2.263), (0.5, 3.639), (0.1, 15.908)],
)
def test_the_anchor_quarter_turns_have_the_published_bounds(v: float, expected: float) -> None:
    assert bounds.rest_to_rest(1.5707963267948966, v, 1.4, 10.0) == pytest.approx(
        expected, abs=1e-3
    )


@pytest.mark.parametrize(
    ("d", "regime"),
    [(2.0, "cruise"), (0.3, "acceleration limit"), (1e-3, "jerk only"), (0.098, "boundary")],
)
def test_each_regime_matches_ruckig(d: float, regime: str) -> None:
    v, a, j = 1.0, 0.7, 10.0
    assert bounds.rest_to_rest(d, v, a, j) == pytest.approx(ruckig_rest_to_rest(d, v, a, j), 1e-9)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(
    d=st.floats(1e-6, 12.0),
    v=st.floats(0.05, 6.3),
    a=st.floats(0.05, 20.0),
    j=st.floats(0.5, 200.0),
)
def test_rest_to_rest_matches_ruckig(d: float, v: float, a: float, j: float) -> None:
    assert bounds.rest_to_rest(d, v, a, j) == pytest.approx(
        ruckig_rest_to_rest(d, v, a, j), rel=1e-7, abs=1e-9
    )
    assert bounds.rest_to_rest(-d, v, a, j) == bounds.rest_to_rest(d, v, a, j)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(
    v0=st.floats(-3.0, 3.0),
    a0=st.floats(-4.0, 4.0),
    amax=st.floats(4.0, 10.0),
    jmax=st.floats(5.0, 100.0),
)
def test_braking_matches_ruckig(v0: float, a0: float, amax: float, jmax: float) -> None:
    assert bounds.braking(v0, a0, amax, jmax) == pytest.approx(
        ruckig_braking(v0, a0, amax, jmax), rel=1e-7, abs=1e-9
    )


def test_the_line_bound_is_never_below_the_free_bound() -> None:
    v, a, j = [3.14] * 3 + [6.28] * 3, [0.7] * 3 + [1.4] * 3, [10.0] * 6
    delta = [1.0, -0.4, 0.2, 2.5, 0.0, 0.1]
    free, line = bounds.free_bound(delta, v, a, j), bounds.line_bound(delta, v, a, j)
    assert line >= free - 1e-12
    # a single moving joint: the line is that joint's own profile
    only = [0.0, 0.0, 1.3, 0.0, 0.0, 0.0]
    assert bounds.line_bound(only, v, a, j) == pytest.approx(bounds.free_bound(only, v, a, j))
