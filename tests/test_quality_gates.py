"""Quality gates are wired: leaks, warnings and hangs fail tests; CI rejects empty runs."""

from __future__ import annotations

import os
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
INNER_OPTS = (
    "-o",
    "asyncio_mode=auto",
    "-o",
    "asyncio_default_fixture_loop_scope=function",
)


def _pyproject() -> dict:  # type: ignore[type-arg]
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_pytest_is_configured_strictly() -> None:
    opts = _pyproject()["tool"]["pytest"]["ini_options"]
    assert opts["asyncio_mode"] == "auto"
    assert opts["filterwarnings"] == ["error"]
    assert 0 < opts["timeout"] <= 120


def test_type_checker_covers_the_package_strictly() -> None:
    mypy = _pyproject()["tool"]["mypy"]
    assert mypy["files"] == ["fxcell"]
    assert mypy["strict"] is True


def test_the_test_command_runs_every_gate() -> None:
    script = (ROOT / "dev").read_text()
    test_section = script.split("test)", 1)[1].split(";;", 1)[0]
    for gate in ("ruff check", "ruff format --check", "mypy", "pytest"):
        assert gate in test_section


def test_a_test_that_leaks_a_task_fails(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio

        async def test_leaks():
            asyncio.get_running_loop().create_task(asyncio.sleep(3600), name="forgotten")
        """
    )
    result = pytester.runpytest("-p", "fxcell.testing", *INNER_OPTS)
    result.assert_outcomes(passed=1, errors=1)
    result.stdout.fnmatch_lines(["*leaked 1 asyncio task(s): forgotten*"])


def test_a_test_that_cleans_up_its_tasks_passes(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio

        async def test_tidy():
            task = asyncio.get_running_loop().create_task(asyncio.sleep(3600))
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        """
    )
    result = pytester.runpytest("-p", "fxcell.testing", *INNER_OPTS)
    result.assert_outcomes(passed=1)


def test_warnings_fail_tests(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import warnings

        def test_warns():
            warnings.warn("deprecated thing", DeprecationWarning)
        """
    )
    result = pytester.runpytest("-W", "error", *INNER_OPTS)
    result.assert_outcomes(failed=1)


def test_a_hanging_test_times_out(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import time

        def test_hangs():
            time.sleep(30)
        """
    )
    result = pytester.runpytest_subprocess("--timeout=1", *INNER_OPTS)
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(["*Timeout*"])


@pytest.mark.parametrize(("inner_rc", "passes"), [(0, True), (1, False), (5, False)])
def test_ci_fails_when_tests_fail_or_none_ran(tmp_path: Path, inner_rc: int, passes: bool) -> None:
    (tmp_path / ".ci").mkdir()
    shutil.copy(ROOT / ".ci" / "run", tmp_path / ".ci" / "run")
    fake_dev = tmp_path / "dev"
    fake_dev.write_text(f"#!/usr/bin/env bash\nexit {inner_rc}\n")
    fake_dev.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k != "PYTEST_ADDOPTS"}
    rc = subprocess.run(["bash", str(tmp_path / ".ci" / "run")], env=env, timeout=30).returncode
    assert (rc == 0) is passes


def test_tests_that_start_processes_are_system_tests_and_the_fast_run_has_none(
    pytester: pytest.Pytester,
) -> None:
    pytester.makeconftest((ROOT / "tests" / "conftest.py").read_text())
    pytester.makepyfile(
        """
        import importlib
        import subprocess
        import sys

        def test_pure():
            assert 1 + 1 == 2

        def test_on_the_simulator_fixture(sim):
            pass

        def _helper():
            subprocess.run([sys.executable, "-c", "pass"], check=True)

        def test_through_a_helper():
            _helper()

        def test_unmarked_yet_starting_a_process():
            runner = importlib.import_module("subprocess")
            runner.run([sys.executable, "-c", "pass"], check=True)
        """
    )
    result = pytester.runpytest("-m", "not system", "-p", "no:cacheprovider", *INNER_OPTS)
    result.assert_outcomes(passed=1, failed=1, deselected=2)
    result.stdout.fnmatch_lines(["*test_unmarked_yet_starting_a_process*", "*mark*system*"])
