"""Quality gates are wired: leaks, warnings and hangs fail tests; CI rejects empty runs."""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
INNER_OPTS = (
    "-o",
    "asyncio_mode=auto",
    "-o",
    "asyncio_default_fixture_loop_scope=function",
)


def test_the_projects_pytest_settings_run_async_tests_and_fail_on_warnings(
    pytester: pytest.Pytester,
) -> None:
    """The project's own [tool.pytest.ini_options] (no options given here): an unmarked
    ``async def`` test runs (asyncio_mode auto) and a warning fails its test."""
    pytester.makepyprojecttoml((ROOT / "pyproject.toml").read_text())
    path = pytester.makepyfile(
        """
        import asyncio
        import warnings

        async def test_unmarked_coroutine():
            await asyncio.sleep(0)

        def test_warns():
            warnings.warn("deprecated thing", DeprecationWarning)
        """
    )
    result = pytester.runpytest(str(path), "-p", "no:cacheprovider")
    result.assert_outcomes(passed=1, failed=1)
    result.stdout.fnmatch_lines(["*DeprecationWarning: deprecated thing", "FAILED *::test_warns*"])
    # The per-test timeout, as pytest-timeout reads it (a hang fails: see below).
    assert 0 < float(pytester.parseconfig(str(path)).getini("timeout")) <= 120


def test_mypy_with_the_projects_configuration_is_strict_over_the_package(tmp_path: Path) -> None:
    """mypy's own reading of pyproject.toml: it checks the package when run without
    arguments (as ./dev does), and it refuses an untyped function (strict)."""
    from mypy import api
    from mypy.config_parser import parse_config_file
    from mypy.options import Options

    options = Options()
    strict: list[bool] = []
    config = str(ROOT / "pyproject.toml")
    parse_config_file(options, lambda: strict.append(True), config, io.StringIO(), io.StringIO())
    assert options.files == ["fxcell"]
    assert strict == [True]
    assert options.warn_unreachable
    untyped = tmp_path / "untyped.py"
    untyped.write_text("def double(x):\n    return 2 * x\n")
    out, _, status = api.run(
        ["--config-file", config, "--cache-dir", str(ROOT / ".mypy_cache"),
         str(untyped)]
    )  # fmt: skip
    assert status == 1, out
    assert "Function is missing a type annotation" in out


GATES = (
    ("ruff", "check fxcell tests bench"),
    ("ruff", "format --check fxcell tests bench"),
    ("mypy", ""),
    ("pytest", "-n 4 --dist loadgroup --no-loadscope-reorder -q tests/test_x.py"),
)


def _dev_with_recording_tools(tmp_path: Path, failing: str | None) -> tuple[int, list[str]]:
    """Run a copy of ./dev's ``test`` command over a .venv of stand-ins that record their
    arguments (``failing``: the one that exits 1); its exit status and the calls."""
    shutil.copy(ROOT / "dev", tmp_path / "dev")
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    venv = tmp_path / ".venv"
    (venv / "bin").mkdir(parents=True)
    stamp = hashlib.sha256((ROOT / "pyproject.toml").read_bytes() + (ROOT / "dev").read_bytes())
    (venv / ".fxcell-installed").write_text(stamp.hexdigest() + "\n")  # no reinstall
    log = tmp_path / "calls"
    for tool in ("python", "ruff", "mypy", "pytest"):
        stand_in = venv / "bin" / tool
        stand_in.write_text(
            "#!/usr/bin/env bash\n"
            f'args="$*"; echo "{tool} ${{args//$\'\\n\'/ }}" >>{log}\n'
            f'[ "{tool} $1" != "{failing}" ] && [ "{tool}" != "{failing}" ]\n'
        )
        stand_in.chmod(0o755)
    env = {**os.environ, "FXCELL_CHROMIUM": "/bin/true"}  # never install a browser here
    env.pop("PYTEST_ADDOPTS", None)
    env.pop("FXCELL_TEST_WORKERS", None)
    status = subprocess.run(
        [str(tmp_path / "dev"), "test", "-q", "tests/test_x.py"],
        env=env, capture_output=True, timeout=60,
    ).returncode  # fmt: skip
    calls = [c.strip() for c in log.read_text().splitlines() if not c.startswith("python")]
    return status, calls


def test_the_test_command_runs_every_gate_then_pytest(tmp_path: Path) -> None:
    status, calls = _dev_with_recording_tools(tmp_path, failing=None)
    assert status == 0
    assert calls == [f"{tool} {args}".strip() for tool, args in GATES]


@pytest.mark.parametrize("failing", ["ruff check", "ruff format", "mypy"])
def test_a_failing_gate_fails_the_test_command_before_pytest_runs(
    tmp_path: Path, failing: str
) -> None:
    status, calls = _dev_with_recording_tools(tmp_path, failing=failing)
    assert status != 0
    assert calls[-1].startswith(failing)
    assert not any(c.startswith("pytest") for c in calls)


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


def test_parallel_work_units_keep_shared_fixtures_together_and_go_longest_first(
    pytester: pytest.Pytester,
) -> None:
    """A file whose tests share a module fixture is one xdist work unit, any other test is
    its own; the units are collected longest first by tests/test_durations.json."""
    pytester.makeconftest((ROOT / "tests" / "conftest.py").read_text())
    durations = {"test_short.py::test_long_alone": 9.0, "test_shared.py::test_b": 5.0}
    (pytester.path / "test_durations.json").write_text(json.dumps(durations))
    pytester.makepyfile(
        test_shared="""
        import pytest

        @pytest.fixture(scope="module")
        def shared():
            return object()

        def test_a(shared):
            pass

        def test_b(shared):
            pass
        """,
        test_short="""
        def test_quick():
            pass

        def test_long_alone():
            pass
        """,
    )
    result = pytester.runpytest("--collect-only", "-q", "-p", "no:cacheprovider", *INNER_OPTS)
    order = [line for line in result.outlines if "::" in line]
    assert order == [
        "test_short.py::test_long_alone",  # 9 s, a unit of its own
        "test_shared.py::test_a",  # 5 s + 0.05 s, one unit: its module fixture
        "test_shared.py::test_b",
        "test_short.py::test_quick",
    ]
    pytester.makeconftest(
        (ROOT / "tests" / "conftest.py").read_text()
        + "\n\ndef pytest_collection_finish(session):\n"
        + "    import json, pathlib\n"
        + "    pathlib.Path('groups.json').write_text(json.dumps({i.nodeid: "
        + "i.get_closest_marker('xdist_group').args[0] for i in session.items}))\n"
    )
    pytester.runpytest("--collect-only", "-q", "-p", "no:cacheprovider", *INNER_OPTS)
    items = json.loads((pytester.path / "groups.json").read_text())
    assert items == {
        "test_short.py::test_long_alone": "test_short.py::test_long_alone",
        "test_shared.py::test_a": "test_shared.py",
        "test_shared.py::test_b": "test_shared.py",
        "test_short.py::test_quick": "test_short.py::test_quick",
    }


def test_a_failed_test_reports_the_last_lines_of_its_daemons(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        from fxcell.daemon.process import DaemonProcess

        class Running:
            def poll(self):
                return None

        def started(url, lines):
            daemon = DaemonProcess(Running(), url, "token")
            daemon.output.extend(lines)
            for observer in DaemonProcess.observers:  # as DaemonProcess.start does
                observer(daemon)
            return daemon

        def test_fails_beside_a_daemon():
            daemon = started("http://127.0.0.1:1", [f"line {i}" for i in range(100)])
            assert daemon.output[-1] == "it went well"
        """
    )
    result = pytester.runpytest("-p", "fxcell.testing", *INNER_OPTS)
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(
        ["*daemon http://127.0.0.1:1 (running): its last 40 lines*", "line 60", "*line 99"]
    )
    result.stdout.no_fnmatch_line("line 59")
