"""Python's cyclic garbage collector, paused while a trajectory streams.

A full (generation 2) collection stops every thread of the process; in a process that
holds a large heap it takes 100–300 ms (measured in the test process: up to 265 ms).
That is longer than the link process waits for the client's beat before it brakes
(``robot.heartbeat_timeout``), so a collection during a move would brake a healthy
move as ``cell_silent``. While any trajectory streams the collector is paused;
reference counting still frees almost everything, and the collector runs again once
the last trajectory has ended. The pause is process-wide and counted, so several
clients (or cells) in one process share it.
"""

from __future__ import annotations

import gc
import threading

_lock = threading.Lock()
_holds = 0
_was_enabled = False


def hold() -> None:
    """Pause automatic collection until the matching :func:`release`."""
    global _holds, _was_enabled
    with _lock:
        if _holds == 0:
            _was_enabled = gc.isenabled()
            gc.disable()
        _holds += 1


def release() -> None:
    """End one :func:`hold`; the last one re-enables collection if it was enabled."""
    global _holds
    with _lock:
        if _holds == 0:
            return
        _holds -= 1
        if _holds == 0 and _was_enabled:
            gc.enable()


def holds() -> int:
    """How many holds are active (tests)."""
    return _holds
