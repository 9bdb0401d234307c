"""Helpers for testing fxcell and cell scripts built on it.

Use as a pytest plugin (``-p fxcell.testing`` or ``pytest_plugins = ["fxcell.testing"]``)
to get these fixtures:

- ``sim``: a fresh simulator process (:func:`simulator`, time scale 0.05) on its own
  loopback address; ``cell``: a :class:`fxcell.Cell` on it, initialised. These run the
  real robot link (ur_rtde in its process) against the simulator's sockets: system tests.
- ``fake_robot``: a :class:`FakeRobot`, the simulator's controller model in this process
  (no sockets, no subprocess; controller time 5x the wall clock); ``fake_cell``: a Cell
  on it through its fake link (``Cell(link_factory=fake_robot.link_factory)``),
  initialised. Fast unit tests of cell behaviour; no gripper (see
  :mod:`fxcell.testing.fake`).
- ``fxcell_no_leaked_tasks`` (automatic): fails a test that leaves asyncio tasks running.
- ``fxcell_no_unplanned_faults`` (automatic, system tests): fails a test that saw a robot-link
  drop or a simulator fault it did not inject (:mod:`fxcell.testing.faults`); declare the
  test's own with :func:`injected_faults` or ``@pytest.mark.injects_faults("why")``.
- a failed test's report ends with the last lines of the daemons (``DaemonProcess``) still
  running, and of any that ended on its own.

This package is test support: the runtime never imports it.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import os
import signal
import socket
import tempfile
import time
import weakref
from collections.abc import AsyncIterator, Generator, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
import pytest_asyncio

from fxcell.daemon.process import DaemonProcess
from fxcell.errors import SimulatorError
from fxcell.link import embedded
from fxcell.link.embedded import EmbeddedSimulator, SimulatorState
from fxcell.testing.fake import FakeLink, FakeRobot, FakeTrajectory
from fxcell.testing.faults import injected_faults, watching_test
from fxcell.testing.handles import ProcessHandle

if TYPE_CHECKING:
    from fxcell.config import CellConfig

__all__ = [
    "FakeLink",
    "FakeRobot",
    "FakeTrajectory",
    "SimulatorHandle",
    "brisk",
    "brisk_limits",
    "injected_faults",
    "simulator",
    "thread_scheduling",
    "urcap_port",
    "uses_urcap_port",
]

TEST_TIME_SCALE = 0.05  # controller delays in tests: power on 0.1 s, brake release 75 ms

BRISK_LIMITS: dict[str, tuple[float, ...]] = {
    "acceleration": (3.0, 3.0, 3.0, 6.0, 6.0, 6.0),
    "jerk": (30.0,) * 6,
}
"""UR3e joint accelerations (rad/s²) and jerks (rad/s³) for tests whose subject is not the
arm's pace: about 4x the shipped limits (the seed's conservative ones), still under the
braking limits that every stop uses; a pick, a place or a transfer takes about half as long.
In a cell file: ``limits: {acceleration: [...], jerk: [...]}`` with these values."""


def brisk(config: CellConfig) -> CellConfig:
    """``config`` with the joint limits of :data:`BRISK_LIMITS`."""
    return config.model_copy(update={"limits": config.limits.model_copy(update=BRISK_LIMITS)})


def brisk_limits() -> dict[str, list[float]]:
    """:data:`BRISK_LIMITS` as a cell file's ``limits`` section."""
    return {name: list(values) for name, values in BRISK_LIMITS.items()}


def thread_scheduling(pid: int, name: str) -> list[tuple[int, int]]:
    """(policy, real-time priority) of each thread of process ``pid`` that the system shows
    as ``name`` (``/proc/PID/task/TID/comm``; Linux only)."""
    found: list[tuple[int, int]] = []
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except FileNotFoundError:  # the process is gone
        return found
    for task in tasks:
        try:
            if (task / "comm").read_text().strip() != name:
                continue
            stat = (task / "stat").read_text()
        except OSError:  # the thread ended meanwhile
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        found.append((int(fields[38]), int(fields[37])))  # stat's 41st and 40th fields
    return found


def _describe(task: asyncio.Task[object]) -> str:
    coro = task.get_coro()
    where = getattr(coro, "__qualname__", repr(coro))
    return f"{task.get_name()} ({where})"


def pytest_configure(config: pytest.Config) -> None:
    if _daemon_started not in DaemonProcess.observers:
        DaemonProcess.observers.append(_daemon_started)
    config.addinivalue_line(
        "markers",
        "injects_faults(why): the test drops links or makes the simulator fault on purpose "
        "(else an unplanned link drop or simulator fault fails a system test)",
    )


DAEMON_LOG_LINES = 40
"""Lines of each daemon's output a failed test's report shows."""
_daemons: weakref.WeakSet[DaemonProcess] = weakref.WeakSet()
_daemons_shown: weakref.WeakSet[DaemonProcess] = weakref.WeakSet()


def _daemon_started(daemon: DaemonProcess) -> None:
    _daemons.add(daemon)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    """A failed test's report ends with the last lines of every daemon still running, and
    of any that ended on its own since the last report showed it (a daemon runs in a
    process of its own: its log is otherwise lost with it)."""
    report = yield
    if report.failed:
        for daemon in list(_daemons):
            ended = daemon.proc.poll()
            if ended is not None and (ended in (0, -signal.SIGTERM) or daemon in _daemons_shown):
                continue
            _daemons_shown.add(daemon)
            state = "running" if ended is None else f"exited with {ended}"
            report.sections.append(
                (
                    f"daemon {daemon.url} ({state}): its last {DAEMON_LOG_LINES} lines",
                    "\n".join(daemon.output[-DAEMON_LOG_LINES:]),
                )
            )
    return report


@pytest.fixture(autouse=True)
def fxcell_no_unplanned_faults(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail a system test that saw a robot-link drop or a simulator fault it did not inject
    (see :mod:`fxcell.testing.faults`; ``@pytest.mark.injects_faults`` or
    :func:`injected_faults` declare the test's own)."""
    node = request.node
    if node.get_closest_marker("system") is None or node.get_closest_marker("injects_faults"):
        yield
        return
    with watching_test(request) as watch:
        yield
        unplanned = watch.unplanned()
        stalls = watch.host_stalls() if unplanned else []
    if unplanned:
        also = f" (the simulators' own stalls: {', '.join(stalls)})" if stalls else ""
        pytest.fail(
            "unplanned faults (not injected by the test): " + "; ".join(unplanned[:10]) + also,
            pytrace=False,
        )


@pytest_asyncio.fixture(autouse=True)
async def fxcell_no_leaked_tasks() -> AsyncIterator[None]:
    """Fail the test if it leaves asyncio tasks running after its fixtures are torn down."""
    before = set(asyncio.all_tasks())
    yield
    for _ in range(3):  # let tasks that are finishing right now finish
        await asyncio.sleep(0)
    current = asyncio.current_task()
    leaked = [t for t in asyncio.all_tasks() - before if t is not current and not t.done()]
    if leaked:
        names = ", ".join(_describe(t) for t in leaked)
        for task in leaked:
            task.cancel()
        await asyncio.gather(*leaked, return_exceptions=True)
        pytest.fail(f"test leaked {len(leaked)} asyncio task(s): {names}", pytrace=False)


# ----------------------------------------------------------------- the simulator


class SimulatorHandle(ProcessHandle):
    """A running simulator subprocess on its own loopback address (``.host``).

    Use it with ``with`` or ``async with`` (see :func:`simulator`). ``inject`` triggers
    a fault (``protective_stop``, ``emergency_stop``, ``stall_rtde``, 2.0, ...),
    ``dashboard`` sends one raw Dashboard command, ``bring_up`` powers on and releases
    the brakes, ``set_joints`` places the resting arm; ``add_object``, ``place_object``,
    ``objects`` and ``gripper`` place and report the simulated world's objects and the
    Hand-E; ``set_input`` plays a wired device; ``machine`` reports the fusion machine.
    """

    def __init__(self, time_scale: float, **options: Any) -> None:
        self._sim = EmbeddedSimulator(time_scale=time_scale, **options)

    @property
    def host(self) -> str:
        return self._sim._host()

    @property
    def running(self) -> bool:
        return self._sim.running

    @property
    def pid(self) -> int:
        """The simulator process's id (it must be running)."""
        process = self._sim.process
        if process is None:
            raise SimulatorError("simulator not started")
        return process.pid

    def start(self) -> SimulatorHandle:
        self._sim.start()
        return self

    def stop(self) -> None:
        self._sim.stop()

    def inject(self, fault: str, *args: object) -> str:
        return self._sim.inject(fault, *args)

    def state(self) -> SimulatorState:
        return self._sim.state()

    def set_joints(self, q: Sequence[float]) -> None:
        self._sim.set_joints(q)

    def push(self, delta: Sequence[float]) -> None:
        """Guide the arm by hand while it is in freedrive: the TCP by (dx, dy, dz) m in the
        base frame, or the joints by six deltas (rad)."""
        embedded.push(self.host, delta)

    def gripper(self) -> dict[str, Any]:
        """The simulated Hand-E: registers, finger ``width`` (m), ``held`` object name."""
        return embedded.gripper_state(self.host)

    def objects(self) -> dict[str, dict[str, Any]]:
        """Every simulated object: kind, width, height, mass, pose (UR vector), held."""
        return embedded.objects(self.host)

    def add_object(
        self,
        name: str,
        kind: str,
        *,
        width: float,
        height: float,
        mass: float,
        position: Sequence[float],
    ) -> None:
        """Place an upright object whose grip point is at ``position`` (base frame, m)."""
        embedded.add_object(
            self.host, name, kind, width=width, height=height, mass=mass, position=position
        )

    def place_object(
        self, name: str, kind: str, station: str, slot: str, contents: str | None = None
    ) -> None:
        """Put an object at a layout slot or move it there (see ``embedded.place_object``)."""
        embedded.place_object(self.host, name, kind, station, slot, contents)

    def set_input(self, signal: str, value: object) -> None:
        """Set a controller input (``"DI5"``, ``"CI2"``, ``"TI0"``, ``"AI0"``, ``"TAI1"``)."""
        embedded.set_input(self.host, signal, value)

    def machine(self) -> dict[str, Any]:
        """The simulated fusion machine's state (see ``fxcell.sim.fusion``)."""
        return embedded.machine_state(self.host)

    def dashboard(self, command: str, timeout: float = 5.0) -> str:
        """Send one Dashboard command on a fresh connection; returns the reply line."""
        with socket.create_connection((self.host, 29999), timeout=timeout) as s:
            f = s.makefile("rwb")
            f.readline()  # banner
            f.write(command.encode() + b"\n")
            f.flush()
            return f.readline().decode().strip()

    def wait_for(self, key: str, value: object, timeout: float = 10.0) -> None:
        """Wait until the simulator's ``state()[key] == value``."""
        deadline = time.monotonic() + timeout
        while True:
            current = self.state().get(key)
            if current == value:
                return
            if time.monotonic() > deadline:
                raise TimeoutError(f"simulator {key} is {current!r}, not {value!r}")
            time.sleep(0.01)

    def bring_up(self, timeout: float = 10.0) -> None:
        """Power on and release the brakes; returns once the robot mode is RUNNING."""
        self.dashboard("power on")
        self.wait_for("robot_mode", "IDLE", timeout)
        self.dashboard("brake release")
        self.wait_for("robot_mode", "RUNNING", timeout)


def simulator(
    time_scale: float = TEST_TIME_SCALE,
    *,
    config: str | Path | None = None,
    joints: Sequence[float] | None = None,
    programs: str | Path | None = None,
    **options: Any,
) -> SimulatorHandle:
    """A simulator on a free loopback address, for ``with`` and ``async with``.

    ``programs``: the controller's program directory (``/programs``, see
    :mod:`fxcell.sim.program_store`); by default the shipped store.

    >>> with simulator() as sim:  # doctest: +SKIP
    ...     DashboardClient(sim.host)
    """
    return SimulatorHandle(time_scale, config=config, joints=joints, programs=programs, **options)


@pytest.fixture
def sim() -> Iterator[SimulatorHandle]:
    """A fresh simulator (time scale 0.05) for one test; stopped afterwards."""
    with simulator() as handle:
        yield handle


@pytest_asyncio.fixture
async def cell(sim: SimulatorHandle) -> AsyncIterator[Any]:
    """A :class:`fxcell.Cell` on the ``sim`` fixture's simulator, initialised (powered on,
    brakes released, external control running); closed afterwards."""
    from fxcell.cell import Cell

    async with Cell(host=sim.host) as c:
        await c.init()
        yield c


@pytest.fixture
def fake_robot() -> FakeRobot:
    """An in-process simulated controller (time scale 0.05, 5x faster than real time)."""
    return FakeRobot(time_scale=TEST_TIME_SCALE)


@pytest_asyncio.fixture
async def fake_cell(fake_robot: FakeRobot) -> AsyncIterator[Any]:
    """A :class:`fxcell.Cell` on ``fake_robot`` (no simulator process), initialised (powered
    on, brakes released, external control running); closed afterwards."""
    from fxcell.cell import Cell

    async with Cell(link_factory=fake_robot.link_factory, record=None) as c:
        await c.init()
        yield c


URCAP_PORT = 32002
"""The cell computer's ExternalControl port in tests (``robot.urcap_port``, the simulator's
``--urcap-port``). Not the URCap's default 50002: that lies in Linux's ephemeral range
(32768-60999), where any server of the suite bound to port 0, or any outgoing connection,
may hold it for as long as it lives."""
uses_urcap_port = pytest.mark.xdist_group("urcap-port")
"""Marks a test that binds :data:`URCAP_PORT`: on parallel workers such tests go to one worker,
in turn (the lock of :func:`urcap_port` then never waits on another worker's test)."""


@contextlib.contextmanager
def urcap_port(timeout: float = 120.0, port: int = URCAP_PORT) -> Iterator[int]:
    """Hold the machine-wide ExternalControl port (the PC side, :data:`URCAP_PORT`) for a test.

    ur_rtde's ExternalControl server listens on every interface, so only one such test can
    run at a time on a machine. This waits (up to ``timeout``) for an exclusive lock shared
    by fxcell tests and for the port to be bindable, then yields it; it fails clearly if the
    port never frees.
    """
    path = os.path.join(tempfile.gettempdir(), f"fxcell-urcap-{port}.lock")
    deadline = time.monotonic() + timeout
    with open(path, "a+") as lock:
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    pytest.fail(f"another fxcell test held port {port} for {timeout:.0f} s")
                time.sleep(0.05)
        try:
            while True:
                with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
                    probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                    try:
                        probe.bind(("0.0.0.0", port))
                        break
                    except OSError:
                        pass
                if time.monotonic() > deadline:
                    pytest.fail(f"port {port} (ExternalControl) stayed in use for {timeout:.0f} s")
                time.sleep(0.05)
            yield port
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
