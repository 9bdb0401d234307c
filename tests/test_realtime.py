"""Real-time scheduling of the robot-link process: asked for where permitted, refused quietly
with the reason, and told by ``fxcell info``."""

from __future__ import annotations

import errno
import os
import threading

import pytest

from fxcell.info import link_scheduling
from fxcell.link.realtime import Scheduling, probe, request_realtime


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
