"""A simulator process ends with the process that launched it (``--exit-with-parent``)."""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time


def watch_parent() -> None:
    """Exit at once when the launching process is gone (nobody could stop us any more).

    The watching thread sleeps in the kernel until the parent ends (a pidfd, Linux 5.3+),
    never taking the GIL meanwhile. It is started before the simulator raises its own
    priority, so it runs at normal priority; a thread that woke every half second to
    check, as it did before, took the GIL from the real-time control cycle and, on a busy
    machine, kept it waiting behind other processes for 60-150 ms before handing it back
    (priority inversion through the GIL). Without pidfds it still polls.
    """
    parent = os.getppid()
    pidfd = -1
    with contextlib.suppress(OSError, AttributeError):
        pidfd = os.pidfd_open(parent)

    def watch() -> None:
        if pidfd >= 0:
            while os.getppid() == parent:  # readable once the parent has ended
                select.select([pidfd], [], [])
        else:
            while os.getppid() == parent:
                time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()
