"""The robot link against the simulator: state stream, calls, supervision, trajectories."""

from __future__ import annotations

import asyncio
import gc
import os
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fxcell.errors import InvalidArgumentError, RobotLinkError
from fxcell.link import LinkClient, LinkStatus, collector
from fxcell.link.process import CALLS_BELOW
from fxcell.link.realtime import probe
from fxcell.protocol import CONTROL_PERIOD, RobotMode, RuntimeState
from fxcell.testing import simulator

TIME_SCALE = 0.05


@pytest.fixture(scope="module")
def sim() -> Iterator[Any]:
    # a protective stop unlocks after 0.5 s of controller time, not the real 5 s (tested in
    # tests/sim/test_sim_safety.py): no test here is about that rule
    with simulator(time_scale=TIME_SCALE, extra_args=["--unlock-delay", "0.5"]) as handle:
        yield handle


@pytest.fixture
async def link(sim: Any) -> AsyncIterator[LinkClient]:
    async with LinkClient(sim.host, connect_timeout=20) as client:
        yield client


async def _until(predicate: Any, within: float = 10.0, what: str = "condition") -> None:
    deadline = time.monotonic() + within
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.002)


async def _ready_for_control(link: LinkClient) -> None:
    """Bring the simulated robot to RUNNING with the control script playing."""
    assert link.latest is not None
    if link.latest.robot_mode != RobotMode.RUNNING:
        await link.dashboard("power on")
        await _until(lambda: link.latest is not None and link.latest.robot_mode == RobotMode.IDLE)
        await link.dashboard("brake release")
        await _until(
            lambda: link.latest is not None and link.latest.robot_mode == RobotMode.RUNNING
        )
    await link.start_control("script", "external_control.urp", 10.0)
    assert link.control_ready


async def test_state_stream_delivers_every_sample_the_controller_sent(
    link: LinkClient, sim: Any
) -> None:
    late_before = (await asyncio.to_thread(sim.state))["late_cycles"]
    stamps: list[float] = []
    with link.subscribe() as sub:
        async for sample in sub:
            stamps.append(sample.timestamp)
            if len(stamps) == 250:
                break
    late = (await asyncio.to_thread(sim.state))["late_cycles"] - late_before
    steps = np.round(np.diff(stamps) / CONTROL_PERIOD).astype(int)
    assert np.all(steps >= 1)
    # cycles the simulator skipped while it ran late (a busy machine) were never sent
    assert int(np.sum(steps - 1)) <= late


async def test_the_link_process_says_how_it_is_scheduled(link: LinkClient) -> None:
    # SCHED_FIFO where this user may (the probe asks the same of a short-lived thread)
    assert link.scheduling is not None
    assert link.scheduling.realtime == probe(link.realtime_priority).realtime
    assert link.pid is not None
    policy = os.sched_getscheduler(link.pid)
    assert policy == (os.SCHED_FIFO if link.scheduling.realtime else os.SCHED_OTHER)


def _thread_names(pid: int) -> dict[int, str]:
    tasks = Path(f"/proc/{pid}/task")
    return {int(t.name): (t / "comm").read_text().strip() for t in tasks.iterdir()}


async def test_the_link_process_answers_calls_below_its_other_threads(link: LinkClient) -> None:
    # Between calls the calls' thread is real time below the state, trajectory and pulse
    # threads (a normal thread preempted while it holds the GIL silences the process);
    # inside ur_rtde's commands, which busy-wait for the control script, at normal
    # priority (tests/test_realtime.py)
    assert link.pid is not None
    await link.dashboard("robotmode")  # the calls' thread has started
    names = await asyncio.to_thread(_thread_names, link.pid)
    (calls,) = (tid for tid, name in names.items() if name == "link-calls")
    if link.scheduling is not None and link.scheduling.realtime:
        assert os.sched_getscheduler(link.pid) == os.SCHED_FIFO
        assert os.sched_getscheduler(calls) == os.SCHED_FIFO
        process = os.sched_getparam(link.pid).sched_priority
        assert os.sched_getparam(calls).sched_priority == process - CALLS_BELOW
    else:
        assert os.sched_getscheduler(calls) == os.SCHED_OTHER


async def test_dashboard_call_returns_the_reply_line(link: LinkClient) -> None:
    reply = await link.dashboard("robotmode")
    assert reply.startswith("Robotmode: ")
    assert link.latest is not None
    assert reply.split(": ")[1] == RobotMode(link.latest.robot_mode).name


async def test_unreachable_controller_reports_each_failed_client() -> None:
    client = LinkClient("127.0.0.254", connect_timeout=10)
    try:
        await client.start(wait=False)
        await _until(lambda: "dashboard" in client.last_failure, 20.0, "a failure report")
        assert "rtde_receive" in client.last_failure
        assert client.status is not LinkStatus.UP
        with pytest.raises(RobotLinkError) as info:
            await client.wait_up(0.05)
        assert "dashboard" in str(info.value)
    finally:
        await client.close()


@pytest.mark.injects_faults("the link process killed")
async def test_killed_link_process_is_detected_and_restarted(link: LinkClient) -> None:
    old_pid = link.pid
    seen: list[LinkStatus] = []
    t0 = time.monotonic()
    link.kill_process()
    await _until(lambda: not link.up, 1.0, "link down")
    detected = time.monotonic() - t0
    seen.append(link.status)
    await link.wait_up(20)
    assert detected < 0.1
    assert seen == [LinkStatus.DOWN]
    assert link.pid != old_pid
    assert link.latest is not None


@pytest.mark.injects_faults("a stalled state stream")
async def test_stalled_rtde_marks_the_link_down_then_up(sim: Any) -> None:
    down_at: list[float] = []

    def on_status(status: LinkStatus, reason: str) -> None:
        if status is LinkStatus.DOWN:
            down_at.append(time.monotonic())

    async with LinkClient(sim.host, connect_timeout=20, on_status=on_status) as link:
        await asyncio.to_thread(sim.inject, "stall_rtde", "0.5")
        await _until(lambda: bool(down_at), 1.0, "link down")
        silent = down_at[0] - link.last_sample_time
        assert 0.1 <= silent < 0.15  # reported 100 ms after the last sample (+ loop lag)
        await link.wait_up(10)


@pytest.mark.injects_faults("a stalled state stream")
async def test_a_link_mute_for_seconds_is_restarted(link: LinkClient, sim: Any) -> None:
    restarts, pid = link.restarts, link.pid
    await asyncio.to_thread(sim.inject, "stall_rtde", "3.5")
    await _until(lambda: not link.up, 1.0, "link down")
    await _until(lambda: link.pid != pid, 6.0, "a new link process")
    await link.wait_up(10)
    assert link.restarts == restarts + 1


@pytest.mark.injects_faults("the control program stopped")
async def test_control_ready_follows_the_control_program(link: LinkClient, sim: Any) -> None:
    await _ready_for_control(link)
    await asyncio.to_thread(sim.inject, "stop_program")
    await _until(lambda: not link.control_ready, 1.0, "control reported lost")
    await link.start_control("script", "external_control.urp", 10.0)  # re-uploads the script
    assert link.control_ready
    # the reply (worker thread) may overtake the state sample that shows PLAYING (pump)
    await _until(
        lambda: link.latest is not None and link.latest.runtime_state == RuntimeState.PLAYING,
        1.0,
        "a PLAYING sample",
    )


async def test_bad_trajectory_is_refused_before_sending(link: LinkClient) -> None:
    with pytest.raises(InvalidArgumentError):
        await link.execute_trajectory(np.zeros((10, 5)))
    with pytest.raises(InvalidArgumentError):
        await link.execute_trajectory(np.full((10, 6), np.nan))
    with pytest.raises(InvalidArgumentError):
        await link.execute_trajectory(np.zeros((10, 6)), gain=5)


def _ramp(q0: Any, dq: float, seconds: float) -> np.ndarray:
    n = round(seconds / CONTROL_PERIOD)
    s = 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, n))
    samples = np.repeat(np.asarray(q0, dtype=float)[None, :], n, axis=0)
    samples[:, 0] += dq * s
    return samples


async def test_trajectory_streams_to_its_target_with_progress(link: LinkClient) -> None:
    await _ready_for_control(link)
    assert link.latest is not None
    q0 = np.asarray(link.latest.actual_q)
    samples = _ramp(q0, 0.2, 0.4)
    handle = await link.execute_trajectory(samples, lookahead_time=0.05, gain=500)
    progress = await handle.next_progress()
    assert progress is not None
    assert progress.total == len(samples)
    result = await handle.wait()
    assert result.status == "completed", result
    assert result.index == len(samples)
    await _until(
        lambda: link.latest is not None and abs(link.latest.actual_q[0] - samples[-1, 0]) < 2e-3,
        2.0,
        "robot at the last sample",
    )


@pytest.mark.injects_faults("the link process killed mid-trajectory")
async def test_the_garbage_collector_waits_while_a_trajectory_streams(link: LinkClient) -> None:
    # A full collection in a big heap stops the process for 100-300 ms, longer than the
    # link process waits for a beat: it must not run mid-move, and must run again after.
    await _ready_for_control(link)
    assert link.latest is not None
    assert gc.isenabled()
    q0 = np.asarray(link.latest.actual_q)
    handle = await link.execute_trajectory(_ramp(q0, 0.1, 0.3))
    assert not gc.isenabled()
    assert (await handle.wait()).status == "completed"
    assert gc.isenabled()
    # a trajectory that ends because the link died also gives the collector back
    handle = await link.execute_trajectory(_ramp(np.asarray(link.latest.actual_q), -0.1, 2.0))
    await handle.next_progress()
    assert not gc.isenabled()
    link.kill_process()
    assert (await handle.wait()).reason == "link_lost"
    assert gc.isenabled()
    assert collector.holds() == 0
    await link.wait_up(10)


async def test_replace_remaining_ends_the_trajectory_early(link: LinkClient) -> None:
    await _ready_for_control(link)
    assert link.latest is not None
    q0 = np.asarray(link.latest.actual_q)
    samples = _ramp(q0, -0.3, 2.0)
    handle = await link.execute_trajectory(samples)
    await handle.next_progress()
    hold = np.repeat(np.asarray(link.latest.actual_q)[None, :], 10, axis=0)
    assert await handle.replace_remaining(hold) is True
    result = await handle.wait()
    assert result.status == "completed"
    assert result.duration < 1.5


@pytest.mark.injects_faults("a protective stop")
async def test_trajectory_fails_on_protective_stop(link: LinkClient, sim: Any) -> None:
    await _ready_for_control(link)
    assert link.latest is not None
    samples = _ramp(link.latest.actual_q, 0.3, 2.0)
    handle = await link.execute_trajectory(samples)
    await handle.next_progress()
    sim.inject("protective_stop")
    result = await handle.wait()
    assert result.status == "failed"
    assert result.reason == "protective_stop"
    assert link.latest is not None
    assert link.latest.runtime_state == RuntimeState.STOPPED
    # leave the shared simulator usable: it allows unlocking after its unlock delay
    deadline = time.monotonic() + 8
    while "releasing" not in (await link.dashboard("unlock protective stop")).lower():
        assert time.monotonic() < deadline
        await asyncio.sleep(0.25)


async def test_ur_rtde_receive_interface_streams_state_and_drives_a_trajectory(sim: Any) -> None:
    """The link works on ur_rtde's own RTDEReceiveInterface too (``receiver="ur_rtde"``)."""
    async with LinkClient(sim.host, connect_timeout=20, receiver="ur_rtde") as link:
        stamps: list[float] = []
        with link.subscribe() as sub:
            async for sample in sub:
                stamps.append(sample.timestamp)
                if len(stamps) == 100:
                    break
        steps = np.round(np.diff(stamps) / CONTROL_PERIOD).astype(int)
        assert np.all(steps >= 1)  # distinct samples, in order
        # mostly every cycle; RTDEReceiveInterface keeps only the newest sample, so on a
        # busy machine (two CPU burners on two cores) its late polls skip every other one
        assert np.median(steps) <= 2
        await _ready_for_control(link)
        assert link.latest is not None
        samples = _ramp(np.asarray(link.latest.actual_q), -0.15, 0.3)
        handle = await link.execute_trajectory(samples, lookahead_time=0.05, gain=500)
        result = await handle.wait()
        assert result.status == "completed", result
        await _until(
            lambda: (
                link.latest is not None and abs(link.latest.actual_q[0] - samples[-1, 0]) < 2e-3
            ),
            2.0,
            "robot at the last sample",
        )
