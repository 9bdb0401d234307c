"""Compile fxcell's native modules (a build hook, and a script for ./dev).

- ``fxcell/motion/kinematics.py`` with mypyc. The same source runs interpreted when it is not
  compiled: compilation changes speed, not results (tests/test_native.py compares the two).
  The wrist-singular continuum search is ~2.4x faster compiled, which is what keeps its p99
  within the 100 µs target of ``bench/ik.py``.
- ``fxcell/motion/_dhchain.c``, a small C extension (setuptools' ``build_ext``): the
  calibrated arm's DH chain, Newton and Levenberg-Marquardt refinement, which the
  calibrated inverse kinematics runs a few times per call. Without it
  :class:`fxcell.motion.kinematics.DHChain` (the same computations in Python, ~30x slower)
  takes its place; tests/test_native.py checks the two agree.
- ``fxcell/link/_beat.c``, the thread that beats to the robot link process without taking
  the GIL (:mod:`fxcell.link.beats`; a Python thread, which a GIL holder can silence,
  takes its place where it is not built).

- ``./dev`` runs ``python hatch_build.py`` whenever a module's source no longer matches the
  stamp its last compilation left (``<module>.sha256``), so the extension imported from the
  checkout (Python prefers it to the ``.py`` beside it) is never older than its source.
- Wheel builds (``pip wheel .``, ``python -m build``) run :class:`NativeBuildHook`, which
  puts the extensions in a platform wheel. Without a C compiler the build warns and falls
  back to a pure-Python wheel (``FXCELL_REQUIRE_NATIVE=1`` makes that an error).
  Editable installs stay pure Python unless ``./dev`` (or this script) compiles in place.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path
from typing import Any

try:
    from hatchling.builders.hooks.plugin.interface import BuildHookInterface
except ImportError:  # run as a script, outside a build
    BuildHookInterface = object  # type: ignore[assignment,misc]

NATIVE = ("fxcell/motion/kinematics.py", "fxcell/motion/_dhchain.c", "fxcell/link/_beat.c")
"""Native modules, relative to the project root: ``.py`` compiled with mypyc, ``.c`` a C
extension of its own."""

# a C extension built by setuptools in a scratch directory (argv: source, module name);
# no contraction into fused multiply-adds, so it rounds as DHChain's Python does
_BUILD_EXT = """\
import sys
from setuptools import Extension, setup
source, name = sys.argv.pop(1), sys.argv.pop(1)
setup(
    name=name.rpartition(".")[2],
    ext_modules=[Extension(name, [source], extra_compile_args=["-O2", "-ffp-contract=off"])],
    script_args=["build_ext", "--inplace", "--quiet"],
)
"""

# mypy settings for the compilation only. The project's [tool.mypy] loads the pydantic
# plugin, which an isolated build environment does not have; without it mypy misreads the
# pydantic models' constructors, so fxcell.config is not followed (its types become Any).
_MYPY_CONFIG = """\
[mypy]
ignore_missing_imports = True
follow_imports = silent
[mypy-fxcell.config]
follow_imports = skip
"""


_NOT_SOURCE = shutil.ignore_patterns("__pycache__", "*.so", "*.pyd", "*.sha256", "static")


def _suffix() -> str:
    return str(sysconfig.get_config_var("EXT_SUFFIX"))


def _stamp_of(source: Path) -> str:
    """What a compiled module's stamp must say: its source's hash and the interpreter's ABI."""
    return f"{hashlib.sha256(source.read_bytes()).hexdigest()} {_suffix()}\n"


def extensions(root: Path, module: str) -> list[Path]:
    """The extension files built for ``module`` (a path relative to ``root``)."""
    source = root / module
    names = (f"{source.stem}{_suffix()}", f"{source.stem}__mypyc{_suffix()}")
    return [path for name in names if (path := source.parent / name).is_file()]


def is_current(root: Path, module: str) -> bool:
    """Whether ``module``'s extension exists and was built from its present source."""
    source = root / module
    stamp = source.with_suffix(".sha256")
    return (
        bool(extensions(root, module))
        and stamp.is_file()
        and stamp.read_text() == _stamp_of(source)
    )


def compile_native(root: Path, *, force: bool = False) -> list[Path]:
    """Compile every module of :data:`NATIVE` in place that is not current; the extensions.

    Raises ``RuntimeError`` (stale extensions removed) if mypyc or the C compiler fails; the
    modules compiled before stay.
    """
    out: list[Path] = []
    for module in NATIVE:
        source = root / module
        if not force and is_current(root, module):
            out += extensions(root, module)
            continue
        stamp = source.with_suffix(".sha256")
        for old in extensions(root, module):  # never leave one that shadows newer source
            old.unlink()
        stamp.unlink(missing_ok=True)
        # in a scratch copy of the package: mypyc's setuptools run must not read our
        # pyproject.toml (hatchling's), nor leave a build/ tree in the checkout
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            shutil.copytree(root / "fxcell", work / "fxcell", ignore=_NOT_SOURCE)
            if source.suffix == ".c":
                (work / "build_ext.py").write_text(_BUILD_EXT)
                name = module.removesuffix(".c").replace("/", ".")
                command = [sys.executable, "build_ext.py", module, name]
                tool = "the C compiler"
            else:
                (work / "mypy.ini").write_text(_MYPY_CONFIG)
                command = [sys.executable, "-m", "mypyc", "--config-file", "mypy.ini", module]
                tool = "mypyc"
            done = subprocess.run(
                command, cwd=work, capture_output=True, text=True, check=False
            )
            built = extensions(work, module)
            if done.returncode != 0 or not built:
                tail = "\n".join((done.stdout + done.stderr).splitlines()[-20:])
                raise RuntimeError(f"{tool} could not compile {module}:\n{tail}")
            for path in built:  # new files: a running process keeps its mapped old ones
                shutil.copy2(path, source.parent / path.name)
            stamp.write_text(_stamp_of(work / module))  # the source it was built from
        out += extensions(root, module)
    return out


class NativeBuildHook(BuildHookInterface):  # type: ignore[misc,valid-type]
    """Hatch build hook: a wheel with the compiled modules, or a pure one with a warning."""

    PLUGIN_NAME = "custom"

    def initialize(self, version: str, build_data: dict[str, Any]) -> None:
        if self.target_name != "wheel" or version == "editable":
            return
        root = Path(self.root)
        try:
            built = compile_native(root)
        except (RuntimeError, OSError) as exc:
            if os.environ.get("FXCELL_REQUIRE_NATIVE") == "1":
                raise
            self.app.display_warning(f"{exc}\nbuilding a pure-Python wheel (slower IK)")
            return
        for path in built:
            build_data["force_include"][str(path)] = path.relative_to(root).as_posix()
        build_data["pure_python"] = False
        build_data["infer_tag"] = True


def main() -> int:
    root = Path(__file__).resolve().parent
    force = "--force" in sys.argv[1:]
    try:
        for path in compile_native(root, force=force):
            print(path.relative_to(root))
    except RuntimeError as exc:
        print(exc, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
