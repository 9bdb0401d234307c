import contextlib
import fcntl
import inspect
import json
import os
import subprocess
import tempfile
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import settings

from fxcell.link import collector

# sila2 compiles SiLAFramework.proto and adds it to protobuf's default pool when it is first
# imported; with protobuf's upb backend that fails ("duplicate file name
# SiLAFramework.proto") once google.protobuf.message_factory has been imported, as
# tests/test_recorder.py does. The daemon never imports that module; here sila2 goes first.
with contextlib.suppress(ImportError):
    import sila2.framework  # noqa: F401

pytest_plugins = ["fxcell.testing", "pytester"]

# CI runs the property tests on fixed examples (a red CI run always reproduces); developers'
# runs keep exploring new ones (`FXCELL_HYPOTHESIS=explore` forces that in CI too).
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
if os.environ.get("CI") and os.environ.get("FXCELL_HYPOTHESIS") != "explore":
    settings.load_profile("ci")

# Taught positions and job databases of the shipped config go to a scratch directory, never
# to the developer's ~/.local/state/fxcell (subprocesses such as the daemon inherit it).
os.environ["FXCELL_STATE_DIR"] = tempfile.mkdtemp(prefix="fxcell-test-state-")
# Simulators keep their 2 ms cycle on a busy machine as a real controller does (SCHED_FIFO
# where permitted, else reniced): a starved simulator pausing its state stream for 100 ms
# made the cell declare the robot disconnected mid-test under load.
os.environ.setdefault("FXCELL_SIM_PRIORITY", "realtime")
# tmp_path on tmpfs where there is one: the job store commits with synchronous=FULL, and
# thousands of fsyncs to a disk shared with other work made the crash-recovery tests wait
# on the disk for most of their time (57 s of a 14 s file on a busy machine). The store
# still fsyncs; tmpfs answers at once. (pytest's own knob, read when tmp_path is first
# used; `PYTEST_DEBUG_TEMPROOT=/somewhere` chooses another root.)
if (
    "PYTEST_DEBUG_TEMPROOT" not in os.environ
    and os.path.isdir("/dev/shm")
    and os.access("/dev/shm", os.W_OK | os.X_OK)
):
    os.environ["PYTEST_DEBUG_TEMPROOT"] = "/dev/shm"


# ----------------------------------------------------------------- system tests
# A test that starts a simulator, a daemon, a robot link or any other subprocess is a
# *system* test (`pytest -m "not system"` leaves them out). Marked here, at collection: a
# test is one when it, one of its fixtures, or a function or class of their module they
# use names one of SYSTEM_NAMES (or carries @pytest.mark.system itself). The guard below
# fails any unmarked test that starts a subprocess anyway, so the fast run stays honest.

SYSTEM_NAMES = frozenset(
    {
        "simulator",  # fxcell.testing.simulator(): a simulator process
        "EmbeddedSimulator",
        "DaemonProcess",
        "LinkClient",  # the robot-link process
        "subprocess",
        "create_subprocess_exec",
        "create_subprocess_shell",
        "runpytest_subprocess",
    }
)


def _names(obj: Any, seen: set[int]) -> set[str]:
    """Global names ``obj`` (a function, class or code object) refers to, following the
    functions and classes of its own module that it uses."""
    if id(obj) in seen:
        return set()
    seen.add(id(obj))
    if isinstance(obj, type):
        found: set[str] = set()
        for member in vars(obj).values():
            found |= _names(member, seen)
        return found
    func = inspect.unwrap(obj) if callable(obj) else obj
    code = getattr(func, "__code__", None)
    if code is None:
        return set()
    found = set()
    codes = [code]
    while codes:
        c = codes.pop()
        found.update(c.co_names)
        codes.extend(k for k in c.co_consts if isinstance(k, types.CodeType))
    module = getattr(func, "__module__", None)
    scope = getattr(func, "__globals__", {})
    for name in list(found):
        target = scope.get(name)
        if getattr(target, "__module__", None) == module and (
            inspect.isfunction(target) or isinstance(target, type)
        ):
            found |= _names(target, seen)
    return found


def _starts_processes(item: pytest.Function) -> bool:
    seen: set[int] = set()
    names = _names(item.obj, seen)
    for defs in item._fixtureinfo.name2fixturedefs.values():
        for fixturedef in defs:
            names |= _names(fixturedef.func, seen)
    return not SYSTEM_NAMES.isdisjoint(names)


@pytest.hookimpl(tryfirst=True)  # before -m deselects and before xdist reads the groups
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if (
            isinstance(item, pytest.Function)
            and item.get_closest_marker("system") is None
            and _starts_processes(item)
        ):
            item.add_marker(pytest.mark.system)
    _into_work_units_longest_first(items)


_popen_init = subprocess.Popen.__init__


def _refuse_popen(self: Any, *args: Any, **kwargs: Any) -> None:
    self._child_created = False  # so that Popen.__del__ has nothing to clean up
    self.returncode = None
    raise RuntimeError(
        "this test starts a subprocess but is not marked `system`: add "
        "@pytest.mark.system (or a name from SYSTEM_NAMES in tests/conftest.py)"
    )


@contextlib.contextmanager
def _no_subprocess(item: pytest.Item) -> Iterator[None]:
    """While an unmarked test sets up and runs, starting a subprocess fails it."""
    if item.get_closest_marker("system") is not None:
        yield
        return
    subprocess.Popen.__init__ = _refuse_popen  # type: ignore[method-assign]
    try:
        yield
    finally:
        subprocess.Popen.__init__ = _popen_init  # type: ignore[method-assign]


@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item: pytest.Item) -> Iterator[None]:
    with _no_subprocess(item):
        return (yield)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
    with _no_subprocess(item):
        return (yield)


# ----------------------------------------------------------------- a machine to itself
# A test that loads the machine on purpose (CPU burners beside the cell, `@pytest.mark.alone`)
# measures the cell against exactly that load. On parallel workers every other test holds a
# shared lock on one file of the machine while it sets up, runs and tears down, and an
# `alone` test holds it exclusively: it waits for the other workers' running tests to end and
# they wait for it (its burners never meet another worker's simulator or planner). In one
# process the lock is not taken.
# flock grants a shared lock while an exclusive one waits, so behind the workers' overlapping
# tests an `alone` test could wait for ever: a gate lets it in first. Every test passes the
# gate (shared, for the moment of taking its lock); an `alone` test closes it (exclusive)
# until it has run, so the tests that come after it wait there while the running ones end.
MACHINE_LOCK = Path(tempfile.gettempdir()) / "fxcell-tests-machine.lock"
MACHINE_GATE = Path(tempfile.gettempdir()) / "fxcell-tests-machine.gate"


@pytest.hookimpl(tryfirst=True, wrapper=True)  # outermost: the wait is not the test's time
def pytest_runtest_protocol(item: pytest.Item) -> Iterator[object]:
    if "PYTEST_XDIST_WORKER" not in os.environ:
        return (yield)
    alone = item.get_closest_marker("alone") is not None
    with open(MACHINE_GATE, "a+") as gate, open(MACHINE_LOCK, "a+") as lock:
        fcntl.flock(gate, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        finally:
            if not alone:
                fcntl.flock(gate, fcntl.LOCK_UN)
        try:
            return (yield)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
            if alone:
                fcntl.flock(gate, fcntl.LOCK_UN)


@pytest.fixture(autouse=True)
def _collector_given_back() -> Iterator[None]:
    """Fail a test that ends with Python's garbage collector still paused by a trajectory."""
    yield
    if collector.holds():
        while collector.holds():
            collector.release()
        pytest.fail("a trajectory's pause of the garbage collector outlived the test")


# ----------------------------------------------------------------- parallel workers
# `./dev test` runs the suite on pytest-xdist workers (`--dist loadgroup`). A test that uses
# a fixture shared by its module or class (a simulator, a cell, a daemon started once for
# the file) goes with the rest of its file to one worker; any other test is a work unit of
# its own. Units are handed out in collection order (`--no-loadscope-reorder`) and a worker
# takes its next unit when it ends one, so the run ends soonest when the longest units go
# first: they are ordered by the seconds their tests took in a measured run
# (tests/test_durations.json: setup + call + teardown of each test over 0.5 s, from
# `./dev test --durations=0`; stale figures cost only speed), the same in every worker and
# every run. Tests keep their order within a unit.
_DURATIONS = Path(__file__).with_name("test_durations.json")  # absent in pytester's copies
TEST_DURATIONS: dict[str, float] = json.loads(_DURATIONS.read_text()) if _DURATIONS.exists() else {}
_MEASURED_FILES = {nodeid.split("::")[0] for nodeid in TEST_DURATIONS}
UNDER = 0.05  # s: a test of a measured file that is not listed (it took under 0.5 s)
UNMEASURED = {"slow": 10.0, "system": 1.0}  # s: a test of a file not measured yet
UNMEASURED_UNIT = 0.02
_SHARED_SCOPES = frozenset({"module", "class", "package"})


def _seconds(item: pytest.Item) -> float:
    if item.nodeid in TEST_DURATIONS:
        return TEST_DURATIONS[item.nodeid]
    if item.nodeid.split("::")[0] in _MEASURED_FILES:
        return UNDER
    for mark, seconds in UNMEASURED.items():
        if item.get_closest_marker(mark) is not None:
            return seconds
    return UNMEASURED_UNIT


def _work_unit(item: pytest.Item) -> str:
    """The group a test declares (``@pytest.mark.xdist_group``), else the file of a test that
    shares a module or class fixture, else the test itself."""
    declared = item.get_closest_marker("xdist_group")
    if declared is not None:
        return str(declared.args[0] if declared.args else declared.kwargs["name"])
    path = item.nodeid.split("::")[0]
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return path
    for defs in info.name2fixturedefs.values():
        if any(d.scope in _SHARED_SCOPES for d in defs):
            return path
    return item.nodeid


def _into_work_units_longest_first(items: list[pytest.Item]) -> None:
    units = {id(item): _work_unit(item) for item in items}
    seconds: dict[str, float] = {}
    for item in items:
        seconds[units[id(item)]] = seconds.get(units[id(item)], 0.0) + _seconds(item)
    rank = {unit: (-s, i) for i, (unit, s) in enumerate(seconds.items())}
    items.sort(key=lambda item: rank[units[id(item)]])
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(units[id(item)]))


def pytest_xdist_node_collection_finished(node: Any, ids: list[str]) -> None:
    """Stop a `--dist loadgroup` run whose work units pytest-xdist could not mark: it names a
    test's group in the node id a worker reports (``nodeid@group``), which some pytest
    releases do not let it change (pyproject.toml pins them out). Without the groups every
    test would be a unit of its own: a file's shared simulator started on each worker, tests
    of one machine-wide port side by side."""
    if node.config.getoption("dist") != "loadgroup":
        return
    unmarked = [nodeid for nodeid in ids if "@" not in nodeid]
    if unmarked:
        pytest.exit(
            f"pytest {pytest.__version__} and pytest-xdist's loadgroup: the work units are not "
            f"marked (e.g. {unmarked[0]}); install the versions pyproject.toml pins",
            returncode=pytest.ExitCode.USAGE_ERROR,
        )
