"""The cell's beats to its link process: "this process lives and its event loop runs".

While a trajectory runs, the link process brakes it to rest by itself when the beats stop
(``robot.heartbeat_timeout``, see :mod:`fxcell.link.process`). :class:`Beats` sends one
every :data:`BEAT_PERIOD` from a thread of its own, while a trajectory runs and the event
loop has said, within :data:`LOOP_STALL_AFTER`, that it ran. So a frozen process
(SIGSTOP, a swap storm) is caught within the beat timeout, a stalled loop within
LOOP_STALL_AFTER, and a loop that is merely late on a busy machine brakes nothing.

The thread is native (``fxcell/link/_beat.c``, built by hatch_build.py) and never takes
the GIL: a Python thread beats only when it gets the GIL, which a thread sitting in a long
C call (a model being built) or preempted while holding it (a normal-priority thread on a
busy machine) keeps from it for hundreds of milliseconds. Where the extension is not built
a Python thread beats instead, with that weakness.
"""

from __future__ import annotations

import socket
import threading
import time

from fxcell.link.realtime import request_realtime

BEAT_PERIOD = 0.01
"""Seconds between two beats to the link process while a trajectory runs."""
LOOP_STALL_AFTER = 0.5
"""Seconds the event loop may go without running before the beats stop (and the link
process brakes): nothing supervises a move while the loop stands still."""

try:
    from fxcell.link._beat import Beater

    NATIVE = True
    """Whether the beats come from the native thread (``fxcell/link/_beat.c``)."""
except ImportError:  # not built (no C compiler): a Python thread beats
    NATIVE = False


class Beats:
    """Beats on ``channel`` (which it owns) from a thread of its own until :meth:`close`.

    ``priority``: the thread's SCHED_FIFO priority where permitted (0: normal scheduling).
    It beats only after :meth:`set_running` (True) and while :meth:`loop_ran` is called
    at least every :data:`LOOP_STALL_AFTER`.
    """

    def __init__(
        self,
        channel: socket.socket,
        *,
        priority: int,
        period: float = BEAT_PERIOD,
        stall_after: float = LOOP_STALL_AFTER,
    ) -> None:
        self._channel = channel
        channel.setblocking(False)
        self._native: Beater | None = None
        self._thread: threading.Thread | None = None
        self._done = threading.Event()
        self._running = False
        self._loop_ran = time.monotonic()
        self._period, self._stall_after, self._priority = period, stall_after, priority
        if NATIVE:
            self._native = Beater(channel.fileno(), period, stall_after, priority)
        else:
            self._thread = threading.Thread(
                target=self._beat, name="fxcell link beats", daemon=True
            )
            self._thread.start()

    @property
    def native(self) -> bool:
        """Whether the beats come from the native thread, which never waits for the GIL."""
        return self._native is not None

    def loop_ran(self) -> None:
        """Say that the event loop runs (call it from the loop, at least every
        LOOP_STALL_AFTER, more often than that to keep beats steady)."""
        if self._native is not None:
            self._native.loop_ran()
        else:
            self._loop_ran = time.monotonic()

    def set_running(self, running: bool) -> None:
        """Beat (a trajectory runs) or not."""
        if self._native is not None:
            self._native.set_running(running)
        else:
            self._running = running

    def close(self) -> None:
        """Stop beating and close the channel, without waiting (idempotent).

        The native thread has ended when this returns; the fallback thread ends within
        BEAT_PERIOD and closes the channel itself (never a descriptor it might still use).
        """
        if self._native is not None:
            self._native.stop()
            self._channel.close()
        else:
            self._done.set()

    def _beat(self) -> None:
        """The fallback thread: what ``_beat.c`` does, but needing the GIL for each beat."""
        if self._priority > 0:
            request_realtime(self._priority)
        with self._channel:
            while not self._done.wait(self._period):
                if self._running and time.monotonic() - self._loop_ran < self._stall_after:
                    try:
                        self._channel.send(b"b")
                    except BlockingIOError:
                        pass  # the link process is behind: its buffer holds beats enough
                    except OSError:
                        return
