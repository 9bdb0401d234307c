"""The seam between the SiLA server's threads and the daemon's asyncio loop.

The reference ``sila2`` server is synchronous: gRPC calls run in a thread pool, observable
commands and property subscriptions in threads of their own. Nothing of the cell is touched
from those threads: every call is a coroutine handed to the daemon's loop
(:meth:`LoopBridge.run`, ``asyncio.run_coroutine_threadsafe``) while the gRPC thread waits on
its future, so the loop is never blocked by them and the cell keeps one owner. What flows
the other way (property values, intermediate responses) goes through the thread-safe queues
the ``sila2`` package reads.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import Callable, Coroutine, Mapping
from pathlib import Path
from queue import Queue
from typing import Any, TypeVar

from sila2.framework import DefinedExecutionError, Feature

from fxcell import errors
from fxcell.errors import ConnectionLostError, FxcellError

T = TypeVar("T")

FEATURES = Path(__file__).resolve().parent / "features"
"""The feature definitions (FDL) the server implements, kept in the package."""


def load_feature(identifier: str) -> Feature:
    """A feature of :data:`FEATURES` (parsed and validated by ``sila2``)."""
    return Feature((FEATURES / f"{identifier}.sila.xml").read_text(encoding="utf-8"))


class LoopBridge:
    """Runs coroutines on the daemon's loop for the SiLA server's threads."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._loop_thread = threading.get_ident()

    def run(self, make: Callable[[], Coroutine[Any, Any, T]]) -> T:
        """Run ``make()`` on the loop and return its result (its exception is raised here).

        Called from a gRPC thread; never from the loop (it would wait on itself)."""
        if threading.get_ident() == self._loop_thread:
            raise RuntimeError("LoopBridge.run called on the event loop's own thread")
        if self.loop.is_closed():
            raise ConnectionLostError("the daemon is stopping")
        future = asyncio.run_coroutine_threadsafe(make(), self.loop)
        try:
            return future.result()
        except concurrent.futures.CancelledError:
            raise ConnectionLostError("the call was cancelled: the daemon is stopping") from None

    def call_soon(self, fn: Callable[[], object]) -> None:
        """Run ``fn`` on the loop soon (from any thread)."""
        self.loop.call_soon_threadsafe(fn)


class ErrorMap:
    """A feature's defined execution errors for the cell's typed errors.

    ``kinds`` maps an error class of :mod:`fxcell.errors` to the identifier of the feature's
    defined execution error (the most specific class wins); errors of no listed kind become
    ``default``. The message keeps the typed name: ``InvalidStateError: ... run init``.
    """

    def __init__(self, feature: Feature, kinds: Mapping[type[FxcellError], str], default: str):
        self.feature = feature
        self.kinds = dict(kinds)
        self.default = default
        for identifier in (*self.kinds.values(), default):
            if identifier not in feature.defined_execution_errors:
                raise ValueError(f"{feature._identifier} defines no error {identifier!r}")

    def identifier(self, exc: FxcellError) -> str:
        for kind in type(exc).__mro__:
            if kind in self.kinds:
                return self.kinds[kind]
        return self.default

    def translate(self, exc: FxcellError) -> DefinedExecutionError:
        node = self.feature.defined_execution_errors[self.identifier(exc)]
        return DefinedExecutionError(node, f"{type(exc).__name__}: {exc}")

    def error(self, identifier: str, message: str) -> DefinedExecutionError:
        return DefinedExecutionError(self.feature.defined_execution_errors[identifier], message)


CELL_ERRORS: dict[type[FxcellError], str] = {
    errors.InvalidStateError: "InvalidState",
    errors.ControlHeldError: "ControlHeld",
    errors.InvalidArgumentError: "InvalidArgument",
    errors.MoveError: "MoveFailed",
    errors.PlanningError: "MoveFailed",
    errors.InterlockError: "MoveFailed",
    errors.SafetyStopError: "SafetyStop",
    errors.GripperError: "GripperFailed",
    errors.ConnectionLostError: "ConnectionLost",
}


class PropertyQueue:
    """The producer queue of an observable property: the latest value goes to subscribers.

    ``offer`` (from the loop) queues a value only when it differs from the last one."""

    def __init__(self, initial: object) -> None:
        self.queue: Queue[object] = Queue()
        self._last: object = initial
        self.queue.put(initial)

    def offer(self, value: object) -> None:
        if value != self._last:
            self._last = value
            self.queue.put(value)

    @property
    def last(self) -> object:
        return self._last
