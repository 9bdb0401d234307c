"""fxcell.motion.kinematics compiled with mypyc (hatch_build.py) is its source, only faster.

Python imports the extension in preference to the ``.py`` beside it, so a stale one would
silently run old code: ``./dev`` recompiles when the source's hash changes, and the first
test here fails a run that bypassed it. The second runs the same source interpreted
(loaded under another name) and compares its solutions with the compiled module's.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import math
import os
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from fxcell.motion import kinematics

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


def test_the_compiled_kinematics_is_built_from_the_present_source() -> None:
    _require_compiled()
    build = _load("fxcell_hatch_build", ROOT / "hatch_build.py")
    assert build.is_current(ROOT, "fxcell/motion/kinematics.py"), (
        "fxcell/motion/kinematics.py changed since it was compiled: run ./dev (or "
        "python hatch_build.py) to rebuild it"
    )


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
