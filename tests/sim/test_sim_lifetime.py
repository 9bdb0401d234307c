"""A simulator started with ``--exit-with-parent`` ends with the process that launched it;
its control cycle runs above the robot link's priority when real time, and its other work
below it."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

from fxcell.link.embedded import free_loopback_host
from fxcell.link.realtime import LINK_PRIORITY, normal_priority
from fxcell.sim import server

LAUNCHER = """
import subprocess, sys
sim = subprocess.Popen(
    [sys.executable, "-m", "fxcell.sim", "--host", sys.argv[1], "--exit-with-parent"],
    stdout=subprocess.PIPE,
)
assert b"listening" in sim.stdout.readline()
print(sim.pid, flush=True)
sys.stdin.read()  # until killed
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1][0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_simulator_ends_with_the_process_that_launched_it() -> None:
    host = free_loopback_host()
    launcher = subprocess.Popen(
        [sys.executable, "-c", LAUNCHER, host],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert launcher.stdout is not None
    sim_pid = 0
    try:
        line = launcher.stdout.readline()
        assert line.strip().isdigit(), f"the launcher did not start a simulator on {host}"
        sim_pid = int(line)
        assert _alive(sim_pid)
        launcher.kill()  # SIGKILL: the launcher cannot stop the simulator itself
        launcher.wait(10)
        deadline = time.monotonic() + 10.0
        while _alive(sim_pid) and time.monotonic() < deadline:
            time.sleep(0.02)  # poll step of a wait with a deadline
        assert not _alive(sim_pid), "the simulator outlived the process that launched it"
    finally:
        if sim_pid and _alive(sim_pid):
            os.kill(sim_pid, 9)
        if launcher.poll() is None:  # it failed before it was killed: no process left behind
            launcher.kill()
            launcher.wait(10)
        for stream in (launcher.stdin, launcher.stdout):
            if stream is not None:
                stream.close()


def test_a_real_time_simulator_runs_above_the_robot_link(monkeypatch: pytest.MonkeyPatch) -> None:
    asked: list[tuple[int, int]] = []
    monkeypatch.setattr(
        server.os,
        "sched_setscheduler",
        lambda pid, policy, p: asked.append((policy, p.sched_priority)),
    )
    monkeypatch.delenv(server.PRIORITY_ENV, raising=False)
    server._raise_priority(realtime=True)
    assert len(asked) == 1
    policy, priority = asked[0]
    assert policy == os.SCHED_FIFO
    assert priority > LINK_PRIORITY


def test_work_off_the_control_cycle_runs_at_normal_priority() -> None:
    # the thread that imports and builds the dynamic model (and the robot link's call
    # worker) inherits the real-time priority of the thread that starts it: it steps down
    seen: list[int | None] = []

    def thread() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except PermissionError:
            seen.append(None)
            return
        normal_priority()
        seen.append(os.sched_getscheduler(0))

    worker = threading.Thread(target=thread)
    worker.start()
    worker.join()
    if seen == [None]:
        pytest.skip("no privilege for real-time scheduling here")
    assert seen == [os.SCHED_OTHER]
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the caller's own thread untouched
