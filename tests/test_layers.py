"""Layers only depend downward, the runtime never imports the simulator, no import cycles.

user API → cell → motion → robot link → protocol/base. The simulator (``fxcell.sim``)
and test support (``fxcell.testing``) sit outside: they may import the runtime's
pure parts, but no runtime module imports them (the daemon starts the simulator as a
separate process by module name through ``fxcell.link.embedded``).

Inside every package (the simulator and test support included) the modules import one
another one way: no cycle, also none hidden by an import inside a function. Imports under
``if TYPE_CHECKING:`` are annotations only and do not count.
"""

from __future__ import annotations

import ast
import functools
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
    "fxcell.robot_specs": 0,
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
    "fxcell.robots": 2,
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


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


@functools.cache
def _runtime_imports(path: Path, module: str) -> frozenset[str]:
    """Every fxcell module ``path`` imports at run time, wherever the import statement is
    (module level or inside a function), as absolute names; ``from p import m`` gives both
    ``p`` and ``p.m``. Imports under ``if TYPE_CHECKING:`` are left out."""
    tree = ast.parse(path.read_text(), str(path))
    is_package = path.name == "__init__.py"
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for branch in node.orelse:
                visit(branch)
            return
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = module.split(".")
                base = parts[: len(parts) - node.level + (1 if is_package else 0)]
                source = ".".join([*base, node.module] if node.module else base)
            else:
                source = node.module or ""
            found.add(source)
            found.update(f"{source}.{a.name}" for a in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return frozenset(m for m in found if m.startswith("fxcell."))


def _packages() -> list[str]:
    return sorted(_module_name(p.parent / "__init__.py") for p in PACKAGE.rglob("__init__.py"))


def _cycles_in(package: str) -> list[list[str]]:
    """The import cycles among the parts of ``package`` (its modules and subpackages; a
    subpackage counts as one part, its own inside is checked as a package of its own)."""
    depth = package.count(".") + 1
    modules = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}
    parts = {m.split(".")[depth] for m in modules if m.startswith(package + ".")}

    def part(name: str) -> str | None:
        if not name.startswith(package + "."):
            return None
        head = name.split(".")[depth]
        return head if head in parts else None

    edges: dict[str, set[str]] = {p: set() for p in parts}
    for name, path in modules.items():
        source = part(name)
        if source is None:  # the package's own __init__, or outside it
            continue
        for imported in _runtime_imports(path, name):
            target = part(imported)
            if target is not None and target != source:
                edges[source].add(target)

    cycles: list[list[str]] = []
    state: dict[str, int] = {}  # 1: on the current chain, 2: done
    chain: list[str] = []

    def walk(node: str) -> None:
        state[node] = 1
        chain.append(node)
        for nxt in sorted(edges[node]):
            if state.get(nxt) == 1:
                cycles.append([*chain[chain.index(nxt) :], nxt])
            elif nxt not in state:
                walk(nxt)
        chain.pop()
        state[node] = 2

    for node in sorted(edges):
        if node not in state:
            walk(node)
    return cycles


@pytest.mark.parametrize("package", _packages())
def test_no_import_cycle_inside_a_package(package: str) -> None:
    cycles = _cycles_in(package)
    assert not cycles, f"import cycles in {package}: " + "; ".join(" -> ".join(c) for c in cycles)


def test_the_cycle_check_sees_an_import_hidden_in_a_function(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from fxcell.sim.controller import Controller\n"
        "def f():\n    from fxcell.sim.primary import text_message\n"
        "    from . import rtde\n"
    )
    found = _runtime_imports(source, "fxcell.sim.m")
    assert {"fxcell.sim.primary", "fxcell.sim.rtde"} <= found
    assert "fxcell.sim.controller" not in found


CELL_PARTS = ("gripper", "io", "handling", "camera", "healing", "teach", "context")


@pytest.mark.parametrize("part", CELL_PARTS)
def test_the_cells_parts_do_not_import_the_cell(part: str) -> None:
    """The parts get a narrow context (``fxcell.cell.context``), not the Cell: none imports
    ``fxcell.cell.cell``, not even for annotations."""
    path = PACKAGE / "cell" / f"{part}.py"
    imported = _imports(path)
    assert "fxcell.cell.cell" not in imported
    assert "fxcell.cell.Cell" not in imported
