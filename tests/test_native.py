"""The native modules (hatch_build.py) compute what their Python counterparts do, only faster.

fxcell.motion.kinematics compiled with mypyc is its source: Python imports the extension in
preference to the ``.py`` beside it, so a stale one would silently run old code; ``./dev``
recompiles when the source's hash changes, and the first test here fails a run that bypassed
it. The second runs the same source interpreted (loaded under another name) and compares its
solutions with the compiled module's. fxcell.motion._dhchain (C) is checked the same way
against :class:`~fxcell.motion.kinematics.DHChain`, which takes its place when it is not
built. fxcell.link._beat has no Python twin to compare with (tests/test_beats.py tests its
behaviour); the only check here is that it was built from its present source.
"""

from __future__ import annotations

import contextlib
import importlib.machinery
import importlib.util
import math
import os
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.calibration import Calibration
from fxcell.errors import UnreachableError
from fxcell.geometry import Pose
from fxcell.link import beats
from fxcell.motion import calibration, kinematics

ROOT = Path(__file__).resolve().parent.parent
SOURCE = ROOT / "fxcell" / "motion" / "kinematics.py"
COMPILED = kinematics.__file__ is not None and kinematics.__file__.endswith(
    tuple(importlib.machinery.EXTENSION_SUFFIXES)
)


def _require_compiled() -> None:
    if COMPILED:
        return
    if os.environ.get("FXCELL_REQUIRE_NATIVE") == "1":
        pytest.fail("fxcell.motion.kinematics is not compiled (run ./dev, see hatch_build.py)")
    pytest.skip("fxcell.motion.kinematics runs interpreted here (./dev compiles it)")


def _load(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the class is built
    try:
        spec.loader.exec_module(module)
    finally:
        del sys.modules[name]
    return module


def _require_native_chain() -> None:
    if calibration.NATIVE:
        return
    if os.environ.get("FXCELL_REQUIRE_NATIVE") == "1":
        pytest.fail("fxcell.motion._dhchain is not built (run ./dev, see hatch_build.py)")
    pytest.skip("fxcell.motion._dhchain is not built here (./dev builds it)")


def test_the_compiled_kinematics_is_built_from_the_present_source() -> None:
    _require_compiled()
    build = _load("fxcell_hatch_build", ROOT / "hatch_build.py")
    assert build.is_current(ROOT, "fxcell/motion/kinematics.py"), (
        "fxcell/motion/kinematics.py changed since it was compiled: run ./dev (or "
        "python hatch_build.py) to rebuild it"
    )


@pytest.mark.parametrize("module", ["fxcell/motion/_dhchain.c", "fxcell/link/_beat.c"])
def test_each_c_extension_is_built_from_its_present_source(module: str) -> None:
    if module.endswith("_dhchain.c"):
        _require_native_chain()
    elif not beats.NATIVE:
        if os.environ.get("FXCELL_REQUIRE_NATIVE") == "1":
            pytest.fail("fxcell.link._beat is not built (run ./dev, see hatch_build.py)")
        pytest.skip("fxcell.link._beat is not built here (./dev builds it)")
    build = _load("fxcell_hatch_build", ROOT / "hatch_build.py")
    assert build.is_current(ROOT, module), (
        f"{module} changed since it was built: run ./dev (or python hatch_build.py) to rebuild it"
    )


def test_a_changed_source_makes_its_build_stale(tmp_path: Path) -> None:
    build = _load("fxcell_hatch_build", ROOT / "hatch_build.py")
    module = "fxcell/motion/_dhchain.c"
    source = tmp_path / module
    source.parent.mkdir(parents=True)
    source.write_text("/* v1 */\n")
    assert not build.is_current(tmp_path, module)  # never built
    (source.parent / f"_dhchain{build._suffix()}").write_bytes(b"")
    source.with_suffix(".sha256").write_text(build._stamp_of(source))
    assert build.is_current(tmp_path, module)
    source.write_text("/* v2 */\n")
    assert not build.is_current(tmp_path, module)


def _configs(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Uniform, exactly and nearly wrist-singular, stretched, and next to the ±2π limits."""
    lim = 2.0 * math.pi
    out = []
    for i in range(n):
        q = rng.uniform(-lim, lim, 6)
        kind = i % 5
        if kind == 1:
            q[4] = rng.choice((0.0, math.pi, -math.pi))
        elif kind == 2:
            q[4] = rng.choice((0.0, math.pi)) + 10.0 ** rng.uniform(-9, -3)
        elif kind == 3:
            q[2] = 10.0 ** rng.uniform(-9, -2) * rng.choice((-1.0, 1.0))
        elif kind == 4:
            j = rng.integers(6)
            q[j] = math.copysign(lim - 10.0 ** rng.uniform(-9, -2), q[j])
        out.append(q)
    return out


@pytest.mark.parametrize("tcp", [None, (0.0, 0.0, 0.146, 0.0, 0.0, 0.0)], ids=["flange", "tcp"])
def test_compiled_and_interpreted_kinematics_find_the_same_solutions(
    tcp: tuple[float, ...] | None,
) -> None:
    _require_compiled()
    interpreted = _load("fxcell_kinematics_interpreted", SOURCE)
    assert not str(interpreted.__file__).endswith(".so")
    fast = kinematics.Kinematics.ur3e().with_tcp(tcp)
    slow = interpreted.Kinematics.ur3e().with_tcp(tcp)
    rng = np.random.default_rng(20261125)
    for q in _configs(rng, 1500):
        pose = fast.forward(q)
        np.testing.assert_allclose(slow.forward(q).matrix, pose.matrix, rtol=0, atol=1e-15)
        seed = rng.uniform(-2.0 * math.pi, 2.0 * math.pi, 6)
        got, want = fast.inverse(pose, seed), slow.inverse(pose, seed)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12, err_msg=f"q={q!r} seed={seed!r}")
        assert len(fast.inverse_all(pose)) == len(slow.inverse_all(pose)), f"q={q!r}"


def test_compiled_and_interpreted_calibrated_chains_agree() -> None:
    # DHChain (the calibrated inverse's Newton steps) lives in the compiled module too
    _require_compiled()
    interpreted = _load("fxcell_kinematics_interpreted", SOURCE)
    rng = np.random.default_rng(26)
    dh = [
        rng.uniform(-2e-3, 2e-3, 6),
        np.array(kinematics.UR3E_DH.a) + rng.uniform(-2e-3, 2e-3, 6),
        np.array(kinematics.UR3E_DH.d) + rng.uniform(-2e-3, 2e-3, 6),
        np.array(kinematics.UR3E_DH.alpha) + rng.uniform(-2e-3, 2e-3, 6),
    ]
    tcp = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.146]
    fast = kinematics.DHChain(*dh, tcp)
    slow = interpreted.DHChain(*dh, tcp)
    for _ in range(200):
        q = rng.uniform(-math.pi, math.pi, 6).tolist()
        goal = fast.frame(q)
        np.testing.assert_allclose(slow.frame(q), goal, rtol=0, atol=1e-15)
        start = (np.array(q) + rng.uniform(-0.05, 0.05, 6)).tolist()
        got, err = fast.newton(start, goal)
        want, err_slow = slow.newton(start, goal)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
        assert err == pytest.approx(err_slow, abs=1e-12)
        far = (np.array(q) + rng.uniform(-0.5, 0.5, 6)).tolist()
        got, err, gradient = fast.settle(far, goal)
        want, err_slow, gradient_slow = slow.settle(far, goal)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        assert err == pytest.approx(err_slow, abs=1e-12)
        assert gradient == pytest.approx(gradient_slow, rel=1e-6, abs=1e-12)


def _dh(rng: np.random.Generator) -> list[np.ndarray]:
    return [
        rng.uniform(-2e-3, 2e-3, 6),
        np.array(kinematics.UR3E_DH.a) + rng.uniform(-2e-3, 2e-3, 6),
        np.array(kinematics.UR3E_DH.d) + rng.uniform(-2e-3, 2e-3, 6),
        np.array(kinematics.UR3E_DH.alpha) + rng.uniform(-2e-3, 2e-3, 6),
    ]


_TCP = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.01, -0.02, 0.146]
_ANGLES = st.lists(st.floats(-2.0 * math.pi, 2.0 * math.pi), min_size=6, max_size=6)
_DELTAS = st.lists(st.floats(-0.3, 0.3), min_size=6, max_size=6)


@settings(max_examples=300, deadline=None)
@given(q=_ANGLES, delta=_DELTAS, far=_DELTAS, calibration_seed=st.integers(0, 2**32 - 1))
def test_the_c_chain_computes_what_dhchain_does(
    q: list[float], delta: list[float], far: list[float], calibration_seed: int
) -> None:
    _require_native_chain()
    dh = _dh(np.random.default_rng(calibration_seed))
    fast = calibration.Chain(*dh, _TCP)
    slow = kinematics.DHChain(*dh, _TCP)
    goal = slow.frame(q)
    assert fast.frame(q) == goal  # the same floating operations in the same order
    assert fast.frame_and_jacobian(q) == slow.frame_and_jacobian(q)
    start = [v + 0.1 * d for v, d in zip(q, delta, strict=True)]
    assert fast.newton(start, goal, 8, 1e-12, 1e-11) == slow.newton(start, goal, 8, 1e-12, 1e-11)
    wide = [v + 3.0 * d for v, d in zip(q, far, strict=True)]
    assert fast.settle(wide, goal, 60, 1e-12, 1e-6) == slow.settle(wide, goal, 60, 1e-12, 1e-6)
    seed = [v + 10.0 * d for v, d in zip(q, far, strict=True)]
    starts = [(0.0, start), (0.0, wide), (0.0, seed)]
    lower, upper = [-2.0 * math.pi] * 6, [2.0 * math.pi] * 6
    args = (starts, goal, seed, lower, upper, 8, 60, 1e-12, 1e-11, 1e-6, 1e-9, 3.0, 0.2)
    assert fast.nearest(*args) == slow.nearest(*args)
    # next to the wrist singularity, from a start turned along the wrist's self-motion
    bent = [*q[:4], 1e-3 * delta[4], q[5]]
    goal = slow.frame(bent)
    turned = [*start[:4], 0.0, start[5] + 3.0 * far[5]]
    assert fast.valley(turned, goal) == slow.valley(turned, goal)
    args = ([(0.0, turned), (0.0, wide)], goal, seed, lower, upper, 8, 60, 1e-12, 1e-11, 1e-6,
            1e-9, 3.0, 0.2)  # fmt: skip
    assert fast.nearest(*args) == slow.nearest(*args)


def test_the_c_chain_rejects_malformed_input() -> None:
    _require_native_chain()
    chain = calibration.Chain(*_dh(np.random.default_rng(1)), _TCP)
    with pytest.raises(ValueError, match="6 values"):
        chain.frame([0.0] * 5)
    with pytest.raises(TypeError):
        chain.newton([0.0] * 6)
    with pytest.raises(TypeError):
        chain.frame(["a"] * 6)
    lims = ([-7.0] * 6, [7.0] * 6)
    with pytest.raises(TypeError, match="pairs"):
        chain.nearest(
            [[0.0] * 6], [0.0] * 12, [0.0] * 6, *lims, 8, 60, 0.0, 0.0, 0.0, 0.0, 3.0, 0.2
        )


def _shoulder_pose(kin: calibration.CalibratedKinematics, q: np.ndarray, offset: float) -> Pose:
    """The pose at ``q`` moved so that its wrist centre is ``offset`` (m) off the nominal
    shoulder singularity (at d4 from axis 1)."""
    pose = kin.forward(q)
    flange = pose @ kin.tcp.inverse()
    d4, d6 = kinematics.UR3E_DH.d[3], kinematics.UR3E_DH.d[5]
    centre = flange.position - d6 * flange.rotation[:, 2]
    rho = math.hypot(centre[0], centre[1])
    scale = math.hypot(d4, offset) / rho if rho > 0.0 else 1.0
    shift = np.array([centre[0] * (scale - 1.0), centre[1] * (scale - 1.0), 0.0])
    return Pose(pose.position + shift, pose.rotation)


@pytest.mark.parametrize("tcp", [None, (0.01, -0.02, 0.146, 0.1, 0.0, 0.2)], ids=["flange", "tcp"])
def test_the_calibrated_hot_path_in_c_computes_what_the_python_one_does(
    tcp: tuple[float, ...] | None,
) -> None:
    # Chain.fast is CalibratedKinematics._nearest_python (the nominal closed form of
    # Kinematics.nearest_within, then Chain.nearest) in one C call, bit for bit, next to the
    # wrist singularity too (the continuum's members as starts)
    _require_native_chain()
    rng = np.random.default_rng(2026)
    compared = wrist_singular = 0
    for round_ in range(4):
        dh = rng.uniform(-2e-3, 2e-3, (4, 6))
        cal = Calibration(*(tuple(row.tolist()) for row in dh))
        kin = calibration.CalibratedKinematics.ur3e_calibrated(cal, tcp)
        configs = _configs(rng, 150)
        poses = [kin.forward(q) for q in configs]
        poses += [_shoulder_pose(kin, q, 10.0 ** rng.uniform(-9, -2)) for q in configs[:50]]
        for pose in poses:
            seed = rng.uniform(-2.0 * math.pi, 2.0 * math.pi, 6).tolist()
            if round_ % 2:  # seeds next to the pose's own joints, as a path's
                with contextlib.suppress(UnreachableError):
                    own = kin.inverse(pose, seed) + rng.uniform(-0.05, 0.05, 6)
                    seed = own.tolist()
            goal = calibration._rows(pose)
            got = kin._chain.fast(goal, seed)
            want = kin._nearest_python(pose, goal, seed)
            assert got == (None if want is None else want.tolist()), f"{pose!r} seed={seed!r}"
            compared += 1
            starts = kin._starts.nearest_within(pose, seed, math.inf, lenient=True)[1]
            if any(abs(math.sin(q[4])) < kinematics._LENIENT_WRIST for _, q in starts):
                wrist_singular += 1
    assert compared == 800
    assert wrist_singular > 20  # the continuum's members compared too


def _nearest_args(
    kin: calibration.CalibratedKinematics,
    starts: list[tuple[float, list[float]]],
    goal: list[float],
    seed: list[float],
) -> tuple[Any, ...]:
    """The arguments of ``Chain.nearest`` / ``DHChain.nearest`` as the calibrated inverse
    passes them."""
    return (
        starts, goal, seed, kin.lower, kin.upper, calibration._FAST_ITERATIONS,
        calibration._SETTLE_ITERATIONS, calibration.CONVERGED, calibration._ROUNDING,
        calibration._STATIONARY, calibration.ACCEPTED, calibration._RIVAL_FACTOR,
        calibration._NEAR_SINGULAR,
    )  # fmt: skip


def test_the_c_refinement_settles_what_the_valley_walk_misses_as_dhchain_does() -> None:
    # wrist-singular poses with the elbow next to full stretch: where the valley is cut, the
    # walk can miss every root; both chains then settle those starts, bit for bit alike
    _require_native_chain()
    rng = np.random.default_rng(26)
    compared = rescued = 0
    for _ in range(3):
        cal = Calibration(*(tuple(row.tolist()) for row in rng.uniform(-2e-3, 2e-3, (4, 6))))
        tcp = (0.01, -0.02, 0.146, 0.1, 0.0, 0.2)
        kin = calibration.CalibratedKinematics.ur3e_calibrated(cal, tcp)
        theta, a, d, alpha = cal.dh()
        fast = calibration.Chain(theta, a, d, alpha, kin._tcp)
        slow = kinematics.DHChain(theta, a, d, alpha, kin._tcp)
        for _ in range(60):
            q = rng.uniform(-2.0 * math.pi, 2.0 * math.pi, 6)
            q[4] = rng.choice((0.0, math.pi)) + 10.0 ** rng.uniform(-9, -3)
            q[2] = 10.0 ** rng.uniform(-6, -1) * rng.choice((-1.0, 1.0))
            pose = kin.forward(q)
            seed = rng.uniform(-2.0 * math.pi, 2.0 * math.pi, 6).tolist()
            starts = kin._starts.nearest_within(pose, seed, math.inf, lenient=True)[1]
            if not starts:
                continue
            goal = calibration._rows(pose)
            args = _nearest_args(kin, starts, goal, seed)
            got = fast.nearest(*args)
            assert got == slow.nearest(*args), f"q={q.tolist()!r} seed={seed!r}"
            compared += 1
            walked = [s for _, s in starts if abs(math.sin(s[4])) < kinematics._VALLEY_NEAR]
            if (
                got[0] is not None
                and len(walked) == len(starts)
                and not any(
                    fast.newton(s, goal, 8, 1e-12, 1e-11)[1] <= calibration.ACCEPTED
                    or any(e <= calibration.ACCEPTED for _, e in fast.valley(s, goal))
                    for s in walked
                )
            ):
                rescued += 1
    assert compared > 100
    assert rescued > 0, (compared, rescued)  # the settled starts were exercised


def test_the_c_refinement_skips_the_valleys_it_walked_as_dhchain_does() -> None:
    # wrist-singular poses: a start on a valley walked whole already is not walked again
    # (kinematics._on_walked), in both chains alike; such starts occur
    _require_native_chain()
    rng = np.random.default_rng(2614)
    compared = shared = 0
    cal = Calibration(*(tuple(row.tolist()) for row in rng.uniform(-2e-3, 2e-3, (4, 6))))
    kin = calibration.CalibratedKinematics.ur3e_calibrated(cal)
    theta, a, d, alpha = cal.dh()
    fast = calibration.Chain(theta, a, d, alpha, kin._tcp)
    slow = kinematics.DHChain(theta, a, d, alpha, kin._tcp)
    for _ in range(60):
        q = rng.uniform(-2.0 * math.pi, 2.0 * math.pi, 6)
        q[4] = rng.choice((0.0, math.pi)) + 10.0 ** rng.uniform(-9, -3)
        pose = kin.forward(q)
        seed = rng.uniform(-2.0 * math.pi, 2.0 * math.pi, 6).tolist()
        starts = kin._starts.nearest_within(pose, seed, math.inf, lenient=True)[1]
        goal = calibration._rows(pose)
        args = _nearest_args(kin, starts, goal, seed)
        assert fast.nearest(*args) == slow.nearest(*args), f"q={q.tolist()!r} seed={seed!r}"
        compared += 1
        floors: list[list[list[float]]] = []
        for _, s in starts:
            if abs(math.sin(s[4])) >= kinematics._VALLEY_NEAR:
                continue
            if any(kinematics._on_walked(s, f) for f in floors):
                shared += 1
                continue
            floor = slow._walk(s, goal, calibration.CONVERGED)[1]
            if floor is not None:
                floors.append(floor)
    assert compared == 60
    assert shared > 10, shared  # starts on a walked valley were exercised
