"""Layers only depend downward, and the runtime never imports the simulator.

user API → cell → motion → robot link → protocol/base. The simulator (``fxcell.sim``)
and test support (``fxcell.testing``) sit outside: they may import the runtime's
pure parts, but no runtime module imports them (the daemon starts the simulator as a
separate process by module name through ``fxcell.link.embedded``).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "fxcell"

# Lower number = lower layer. A module may import its own layer and the ones below.
LAYERS: dict[str, int] = {
    "fxcell.errors": 0,
    "fxcell._version": 0,
    "fxcell.protocol": 0,
    "fxcell.config": 0,
    "fxcell.geometry": 0,
    "fxcell.events": 0,
    "fxcell.resources": 0,
    "fxcell.jsonable": 0,
    "fxcell.results": 0,
    "fxcell.commands": 0,
    "fxcell.calibration": 0,
    "fxcell.settling": 0,
    "fxcell.layout": 0,
    "fxcell.signals": 0,
    "fxcell.link": 1,
    "fxcell.link.embedded": 1,
    "fxcell.vision": 1,
    "fxcell.motion": 2,
    "fxcell.motion.kinematics": 2,
    "fxcell.motion.calibration": 2,
    "fxcell.motion.robot_model": 2,
    "fxcell.motion.collision": 2,
    "fxcell.motion.planning": 2,
    "fxcell.motion.trajectory": 2,
    "fxcell.motion.moves": 2,
    "fxcell.motion.runner": 2,
    "fxcell.cell": 3,
    "fxcell.cell.statemachine": 3,
    "fxcell.cell.cell": 3,
    "fxcell.recorder": 3,
    "fxcell.compat": 4,
    "fxcell.client": 4,
    "fxcell.daemon": 4,
    "fxcell.daemon.sila": 4,
    "fxcell.replay": 4,
    "fxcell.info": 4,
    "fxcell.cli": 4,
    "fxcell.job": 4,
    "fxcell": 4,
    "fxcell.__main__": 4,
}
OUTSIDE = ("fxcell.sim", "fxcell.testing")
NAMES = ("base", "robot link", "motion", "cell", "user API")


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _layer(module: str) -> int | None:
    """The layer of a module: its own entry or that of its closest listed package."""
    parts = module.split(".")
    for i in range(len(parts), 0, -1):
        name = ".".join(parts[:i])
        if name in LAYERS and (i == len(parts) or name != "fxcell"):
            return LAYERS[name]
    return None


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
    return {m for m in found if m == "fxcell" or m.startswith("fxcell.")}


def _runtime_modules() -> list[tuple[str, Path]]:
    modules = [(_module_name(p), p) for p in sorted(PACKAGE.rglob("*.py"))]
    return [(m, p) for m, p in modules if not m.startswith(OUTSIDE)]


def test_every_runtime_module_has_a_layer() -> None:
    unplaced = [m for m, _ in _runtime_modules() if _layer(m) is None]
    assert not unplaced, f"add these modules to LAYERS in {__file__}: {unplaced}"


@pytest.mark.parametrize(("module", "path"), _runtime_modules(), ids=lambda v: str(v))
def test_module_imports_only_its_layer_and_below(module: str, path: Path) -> None:
    own = _layer(module)
    assert own is not None
    for imported in _imports(path):
        assert not imported.startswith(OUTSIDE), f"{module} imports {imported}"
        target = _layer(imported)
        if target is None:  # e.g. "from fxcell import errors" resolves through the submodule
            continue
        assert target <= own, (
            f"{module} ({NAMES[own]}) imports {imported} ({NAMES[target]}), a higher layer"
        )


def test_importing_the_whole_runtime_loads_no_simulator_code() -> None:
    runtime = [m for m, _ in _runtime_modules() if m not in ("fxcell.__main__",)]
    code = (
        "import importlib, sys\n"
        f"for m in {runtime!r}: importlib.import_module(m)\n"
        "bad = sorted(m for m in sys.modules if m.startswith(('fxcell.sim', 'fxcell.testing')))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == ""


def test_the_daemon_and_the_cell_load_opencv_only_when_the_camera_is_used() -> None:
    """The daemon imports the Cell on its event loop: OpenCV (seconds to load on a busy
    machine) must wait for the first placement check, which imports it in a worker thread."""
    code = (
        "import sys\n"
        "import fxcell, fxcell.cell, fxcell.job, fxcell.daemon.server, fxcell.daemon.jobs\n"
        "print('cv2' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "False"
