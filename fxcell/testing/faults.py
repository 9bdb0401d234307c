"""Unplanned faults fail a test: link drops and simulator faults are measured, not accepted.

While a system test runs, :class:`FaultWatch` counts

- robot-link losses of this process (a link's ``robot link to ... down`` warning, any kind)
  and the moves its link process braked on its own guard (a stalled state stream, a silent
  cell: ``robot link to ... braked a move by itself``),
- the steps it healed (:mod:`fxcell.cell.healing`'s ``... interrupted (why): recovering``):
  a move that lost its robot state while the link stayed up is healed, and counted, only
  there,
- those of the daemons the test talks to (the same line in their output), and
- the faults of the simulators it uses (the simulator's own fault log: safety stops, its
  own or injected, watchdog stops, injected faults),

and the test fails if any happened that it did not inject. A test that injects faults says
so: around the injection with :func:`injected_faults` (what happens inside the ``with``
block is expected), or for the whole test with ``@pytest.mark.injects_faults("why")``.
"""

from __future__ import annotations

import contextlib
import logging
import re
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from fxcell.daemon.process import DaemonProcess
from fxcell.link.embedded import EmbeddedSimulator, SimulatorState

_LINK_DOWN = re.compile(r"robot link to \S+ (down|braked a move by itself): (.*)")
_HEALED = re.compile(r"\S.*? interrupted \((.*)\): recovering, attempt \d+")
LINK_LOGGER = "fxcell.link"
"""Where every robot kind's link says it went down (the UR's client, the Ned2's link)."""
HEAL_LOGGER = "fxcell.cell.healing"
"""Where a cell says it heals a step that a lost link interrupted."""


@dataclass
class _Counts:
    link: list[str] = field(default_factory=list)
    daemons: dict[int, list[str]] = field(default_factory=dict)
    sims: dict[int, list[str]] = field(default_factory=dict)

    def total(self) -> list[str]:
        out = [f"link {r}" for r in self.link]
        for lines in self.daemons.values():
            out += [f"daemon's link {r}" for r in lines]
        for faults in self.sims.values():
            out += [f"simulator: {f}" for f in faults]
        return out


class FaultWatch(logging.Handler):
    """Counts the link losses and simulator faults of one test (see the module's doc)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self._link: list[str] = []
        self._daemons: dict[int, DaemonProcess] = {}
        self._sims: dict[int, EmbeddedSimulator] = {}
        self._sim_final: dict[int, list[str]] = {}
        self._baseline = _Counts()
        self._unplanned: list[str] = []
        self.injected: list[str] = []
        """Faults the test said it injected (with :func:`injected_faults`)."""

    # -- what is watched

    def emit(self, record: logging.LogRecord) -> None:
        fault = _fault(record.getMessage())
        if fault is not None:
            self._link.append(fault)

    def _on_daemon(self, daemon: DaemonProcess) -> None:
        self._daemons[id(daemon)] = daemon

    def _on_simulator(self, sim: EmbeddedSimulator, event: str) -> None:
        self._sims[id(sim)] = sim
        if event == "stopping":
            with contextlib.suppress(Exception):
                self._sim_final[id(sim)] = _faults(sim.state())

    def adopt(self, objects: Any) -> None:
        """Watch simulators and daemons that were started before the test (module fixtures)."""
        for obj in objects:
            if isinstance(obj, DaemonProcess):
                self._daemons[id(obj)] = obj
            elif isinstance(obj, EmbeddedSimulator) and obj.running:
                self._sims[id(obj)] = obj

    def _counts(self) -> _Counts:
        counts = _Counts(list(self._link))
        for key, daemon in self._daemons.items():
            lines = [f for f in map(_fault, list(daemon.output)) if f is not None]
            counts.daemons[key] = lines
        for key, sim in self._sims.items():
            if key in self._sim_final:
                counts.sims[key] = self._sim_final[key]
            elif sim.running:
                with contextlib.suppress(Exception):
                    counts.sims[key] = _faults(sim.state())
        return counts

    # -- what is expected

    def begin(self) -> None:
        self._baseline = self._counts()

    def _new_since(self, base: _Counts) -> list[str]:
        now = self._counts()
        new = [f"link {r}" for r in now.link[len(base.link) :]]
        for key, lines in now.daemons.items():
            new += [f"daemon's link {r}" for r in lines[len(base.daemons.get(key, [])) :]]
        for key, faults in now.sims.items():
            new += [f"simulator: {f}" for f in faults[len(base.sims.get(key, [])) :]]
        return new

    @contextlib.contextmanager
    def expecting(self) -> Iterator[None]:
        self._unplanned += self._new_since(self._baseline)
        self.begin()
        try:
            yield
        finally:
            self.injected += self._new_since(self._baseline)
            self.begin()

    def unplanned(self) -> list[str]:
        return self._unplanned + self._new_since(self._baseline)

    def host_stalls(self) -> list[str]:
        """The watched simulators' own stalls (a busy host), to explain a fault with."""
        out = []
        for sim in self._sims.values():
            if not sim.running:
                continue
            with contextlib.suppress(Exception):
                for ended, length in sim.state().get("stalls", []):
                    at = time.strftime("%H:%M:%S", time.localtime(ended))
                    out.append(f"{length * 1e3:.0f} ms until {at}.{int(ended % 1 * 1e3):03d}")
        return out

    # -- installation

    def install(self) -> None:
        logging.getLogger(LINK_LOGGER).addHandler(self)
        logging.getLogger(HEAL_LOGGER).addHandler(self)
        DaemonProcess.observers.append(self._on_daemon)
        EmbeddedSimulator.observers.append(self._on_simulator)

    def uninstall(self) -> None:
        logging.getLogger(LINK_LOGGER).removeHandler(self)
        logging.getLogger(HEAL_LOGGER).removeHandler(self)
        with contextlib.suppress(ValueError):
            DaemonProcess.observers.remove(self._on_daemon)
        with contextlib.suppress(ValueError):
            EmbeddedSimulator.observers.remove(self._on_simulator)


def _watchable(values: list[Any]) -> list[Any]:
    """The simulators and daemons among fixture values (or held by them)."""
    out: list[Any] = []
    for value in values:
        for candidate in (value, *(getattr(value, a, None) for a in _HOLDERS)):
            inner = getattr(candidate, "_sim", candidate)  # a testing SimulatorHandle
            if isinstance(inner, EmbeddedSimulator | DaemonProcess):
                out.append(inner)
    return out


_HOLDERS = ("handle", "sim", "daemon", "_simulator")


def _fault(line: str) -> str | None:
    """``down: why`` or ``braked a move by itself: why`` from a link's warning, ``healed:
    why`` from a cell's healing; None for any other line."""
    match = _LINK_DOWN.search(line)
    if match:
        return f"{match.group(1)}: {match.group(2)}"
    healed = _HEALED.search(line)
    return None if healed is None else f"healed: {healed.group(1)}"


def _faults(state: SimulatorState) -> list[str]:
    return list(state["faults"])


_current: FaultWatch | None = None


@contextlib.contextmanager
def injected_faults(why: str, **expected: int) -> Iterator[FaultWatch | None]:
    """The faults (link drops, simulator faults) within this block are the test's own.

    ``why`` says what the test injects; ``expected`` (e.g. ``link_losses=10``) documents
    counts (checked by the test itself). Outside a watched test it only runs the block.
    """
    del why, expected
    watch = _current
    if watch is None:
        yield None
        return
    with watch.expecting():
        yield watch


@contextlib.contextmanager
def watching_test(request: pytest.FixtureRequest) -> Iterator[FaultWatch]:
    """Watch one test: install a :class:`FaultWatch`; the simulators and daemons of its
    module- or session-scoped fixtures (already running) are watched from now on."""
    running: list[Any] = []
    definitions = request.node._fixtureinfo.name2fixturedefs
    for name in request.fixturenames:
        defs = definitions.get(name)
        if not defs or defs[-1].scope == "function":
            continue  # function-scoped simulators and daemons start inside the watch
        running.append(request.getfixturevalue(name))
    with watching(_watchable(running)) as watch:
        yield watch


@contextlib.contextmanager
def watching(objects: list[Any]) -> Iterator[FaultWatch]:
    """Install a :class:`FaultWatch` (watching ``objects``, simulators and daemons already
    running, too) as the one :func:`injected_faults` reports to."""
    global _current
    watch = FaultWatch()
    watch.install()
    watch.adopt(objects)
    watch.begin()
    _current = watch
    try:
        yield watch
    finally:
        _current = None
        watch.uninstall()
