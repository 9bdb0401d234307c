"""Streaming details the moves rely on, against the simulator: the braking splice.

``TrajectoryHandle.replace_remaining(samples, at_index)`` must put ``samples[0]`` in place
of the trajectory's sample ``at_index`` (the samples before it still streamed), so a
braking profile computed from the planned state at ``at_index`` continues the motion
without a jump.
"""

from __future__ import annotations

import asyncio

import numpy as np

from fxcell.cell import Cell
from fxcell.config import CellConfig
from fxcell.link.capabilities import UR3E
from fxcell.motion.trajectory import Limits, braking, rest_to_rest
from fxcell.testing import simulator

CONFIG = CellConfig.load()
DT = UR3E.sample_period  # the UR3e's trajectories: one sample per 2 ms servo cycle
HOME = np.array(CONFIG.home)
LIMITS = Limits.from_config(CONFIG.limits, 0.5, 1.0, period=DT)


async def test_a_replacement_at_an_index_continues_from_that_sample() -> None:
    traj = rest_to_rest(HOME, HOME + np.array([0.8, 0, 0, 0, 0, 0]), LIMITS)
    at = len(traj) // 2
    # the braking profile from sample `at` (within the limits, so the link's limit check
    # leaves it alone): a splice one sample off would stop ~1.8 mrad elsewhere
    stop = braking(*traj.state(at), Limits.for_braking(CONFIG.limits, period=DT))
    end = stop.positions[-1][0]
    hold = np.repeat(stop.positions[-1:], 150, axis=0)  # servoJ converges onto its end
    with simulator(joints=list(HOME)) as sim:
        async with Cell(sim.host, config=CONFIG) as cell:
            await cell.init()
            link = cell.link
            assert link is not None
            peak = 0.0
            with link.subscribe() as states:
                handle = await link.execute_trajectory(traj.positions, lookahead_time=0.03)
                # well before the link reaches `at` (it sends one sample per 2 ms)
                assert (
                    await handle.replace_remaining(
                        np.concatenate([stop.positions, hold]), at_index=at
                    )
                    is True
                )
                async with asyncio.timeout(at * DT + 3.0):
                    while not handle.done:
                        s = await states.__anext__()
                        peak = max(peak, s.actual_q[0])
                result = await handle.wait()
            assert result.status == "completed"
            q = np.array(link.latest.actual_q if link.latest else HOME)
    # It stopped where the braking profile from sample `at` ends, no farther.
    assert abs(q[0] - end) < 1e-5
    assert peak <= end + 1e-3
    assert peak >= end - 1e-5


def test_a_braking_profile_from_a_sample_starts_there() -> None:
    traj = rest_to_rest(HOME, HOME + np.array([0.8, 0, 0, 0, 0, 0]), LIMITS)
    at = len(traj) // 2
    p, v, a = traj.state(at)
    stop = braking(p, v, a, Limits.for_braking(CONFIG.limits, period=DT))
    spliced = np.concatenate([traj.positions[:at], stop.positions])
    steps = np.abs(np.diff(spliced[:, 0]))
    # no step larger than the planned speed allows in one 2 ms sample
    assert float(np.max(steps)) <= float(np.max(np.abs(traj.velocities[:, 0]))) * DT * 1.01
