"""Real-time scheduling for the robot-link process, where the machine permits it.

The link process streams a servoJ setpoint every 2 ms and forwards every 500 Hz state sample;
on a busy cell PC a thread that waits its turn behind a compiler or a browser for a few
milliseconds makes the controller see late setpoints. As ur_rtde recommends for its control
interface, the process asks Linux for ``SCHED_FIFO`` (a fixed real-time priority) for its main
thread before it starts any other: threads inherit the policy, so the pump, trajectory,
worker and reader threads and ur_rtde's own run with it. Where the user may not (no
``CAP_SYS_NICE``, ``RLIMIT_RTPRIO`` below the priority) the process carries on with normal
scheduling and says so: ``fxcell info`` and the link's warning in the log.

Grant it with the systemd unit's ``LimitRTPRIO=`` (``contrib/fxcell.service``) or
``/etc/security/limits.d`` for an interactive user; see ``docs/guides/real-robot.md``.
"""

from __future__ import annotations

import contextlib
import os
import resource
import threading
from collections.abc import Iterator
from dataclasses import dataclass

LINK_PRIORITY = 80
"""SCHED_FIFO priority asked for the link process (1-99; 0 turns the request off)."""


@dataclass(frozen=True)
class Scheduling:
    """How a thread is scheduled: real time (``SCHED_FIFO``) or not, and why not."""

    realtime: bool
    policy: str
    priority: int
    detail: str = ""

    def describe(self) -> str:
        if self.realtime:
            return f"{self.policy} priority {self.priority}"
        return f"{self.policy} (not real time: {self.detail})"


def rtprio_limit() -> str:
    """The soft ``RLIMIT_RTPRIO`` of this process ("unlimited" or a number)."""
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return "unlimited" if soft == resource.RLIM_INFINITY else str(soft)


def request_realtime(priority: int = LINK_PRIORITY) -> Scheduling:
    """Ask ``SCHED_FIFO`` at ``priority`` for the calling thread (threads it starts later
    inherit it); never raises: a refusal comes back as a :class:`Scheduling` saying why."""
    if priority <= 0:
        return Scheduling(False, "SCHED_OTHER", 0, "turned off (robot.realtime_priority: 0)")
    if not hasattr(os, "sched_setscheduler"):
        return Scheduling(False, "SCHED_OTHER", 0, "not supported on this platform")
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        return Scheduling(
            False,
            "SCHED_OTHER",
            0,
            f"{why}; RLIMIT_RTPRIO {rtprio_limit()}, needs {priority} or CAP_SYS_NICE",
        )
    return Scheduling(True, "SCHED_FIFO", priority)


def lower_realtime(below: int) -> None:
    """Run the calling thread ``below`` its real-time priority (at least 1), if it has one;
    a thread at normal priority stays so."""
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            priority = max(1, os.sched_getparam(0).sched_priority - below)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))


@contextlib.contextmanager
def at_normal_priority() -> Iterator[None]:
    """Run the block at normal priority, then go back to the thread's real-time priority:
    for a vendor call that releases the GIL and may busy-wait in it (ur_rtde's commands
    spin until the control script is ready for them). Outside such calls the thread keeps
    a real-time priority: a normal thread preempted while it holds the GIL stalls every
    real-time thread of its process until a busy machine gives it a CPU again."""
    try:
        policy = os.sched_getscheduler(0)
        param = os.sched_getparam(0)
    except (OSError, AttributeError):
        policy = None
    if policy != os.SCHED_FIFO:
        yield
        return
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, param)


def normal_priority() -> None:
    """Run the calling thread at normal priority (``SCHED_OTHER``; it may have inherited a
    real-time one): for work that can wait or spin on something else. A real-time thread
    that busy-waits holds its CPU above every normal process of the machine (ur_rtde's
    commands spin without sleeping until the control script is ready for them)."""
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def name_thread(name: str) -> None:
    """Give the calling thread ``name`` where the system shows it (Linux: ``top -H``,
    ``/proc/PID/task/TID/comm``; at most 15 characters); elsewhere nothing."""
    with contextlib.suppress(OSError):
        path = f"/proc/self/task/{threading.get_native_id()}/comm"
        with open(path, "w") as comm:
            comm.write(name[:15])


def probe(priority: int = LINK_PRIORITY) -> Scheduling:
    """Whether a link process started now by this user would get real-time scheduling:
    the request, made in a short-lived thread (Linux schedules threads one by one), so
    the caller's own scheduling is left alone."""
    result: list[Scheduling] = []
    thread = threading.Thread(target=lambda: result.append(request_realtime(priority)))
    thread.start()
    thread.join()
    return result[0]
