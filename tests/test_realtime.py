"""Real-time scheduling of the robot-link process: asked for where permitted, refused quietly
with the reason, and told by ``fxcell info``."""

from __future__ import annotations

import errno
import os
import threading
from collections.abc import Callable

import pytest

from fxcell.info import link_scheduling
from fxcell.link.realtime import (
    Scheduling,
    at_normal_priority,
    lower_realtime,
    probe,
    request_realtime,
)


def _in_a_thread(priority: int) -> tuple[Scheduling, int]:
    """The request's answer and the policy the thread then has (its own, not the test's)."""
    out: list[tuple[Scheduling, int]] = []

    def run() -> None:
        out.append((request_realtime(priority), os.sched_getscheduler(0)))

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    return out[0]


def test_a_granted_request_makes_the_thread_sched_fifo() -> None:
    expected = probe(10)
    got, policy = _in_a_thread(10)
    assert got == expected
    if got.realtime:
        assert policy == os.SCHED_FIFO
        assert got.describe() == "SCHED_FIFO priority 10"
    else:
        assert policy == os.SCHED_OTHER
        assert "RLIMIT_RTPRIO" in got.detail


def test_a_refused_request_falls_back_with_the_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_: object) -> None:
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    got = request_realtime(80)
    assert not got.realtime
    assert got.policy == "SCHED_OTHER"
    assert got.detail.startswith("Operation not permitted; RLIMIT_RTPRIO ")
    assert "needs 80 or CAP_SYS_NICE" in got.detail
    assert "normal, not real time" in link_scheduling(80)


def test_priority_zero_turns_the_request_off() -> None:
    got, policy = _in_a_thread(0)
    assert not got.realtime
    assert "turned off" in got.detail
    assert policy == os.SCHED_OTHER


def test_the_probe_leaves_the_callers_scheduling_alone() -> None:
    before = os.sched_getscheduler(0)
    probe(10)
    assert os.sched_getscheduler(0) == before


Seen = Callable[[], None]


def _in_a_real_time_thread(priority: int, body: Callable[[Seen], None]) -> list[tuple[int, int]]:
    """Run ``body(seen)`` in a thread started at real-time ``priority``; each ``seen()``
    records the thread's (policy, priority) at that point."""
    if not probe(priority).realtime:
        pytest.skip("real-time scheduling is not permitted here")
    out: list[tuple[int, int]] = []

    def seen() -> None:
        out.append((os.sched_getscheduler(0), os.sched_getparam(0).sched_priority))

    thread = threading.Thread(target=lambda: (request_realtime(priority), body(seen)))
    thread.start()
    thread.join()
    return out


def test_a_vendor_call_runs_at_normal_priority_then_the_thread_is_real_time_again() -> None:
    def body(seen: Seen) -> None:
        with at_normal_priority():
            seen()
        seen()

    assert _in_a_real_time_thread(20, body) == [(os.SCHED_OTHER, 0), (os.SCHED_FIFO, 20)]


def test_lowering_a_real_time_thread_keeps_it_real_time_and_at_least_priority_1() -> None:
    def body(seen: Seen) -> None:
        lower_realtime(5)
        seen()
        lower_realtime(50)
        seen()

    assert _in_a_real_time_thread(20, body) == [(os.SCHED_FIFO, 15), (os.SCHED_FIFO, 1)]


def test_a_normal_thread_stays_normal_through_both() -> None:
    out: list[int] = []

    def run() -> None:
        lower_realtime(5)
        with at_normal_priority():
            out.append(os.sched_getscheduler(0))
        out.append(os.sched_getscheduler(0))

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    assert out == [os.SCHED_OTHER, os.SCHED_OTHER]
