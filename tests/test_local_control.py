"""The pendant's switch to Local control brakes a running move within 100 ms.

Judged by the simulator's own joint state (its control port, in controller time), not by
what fxcell believes: from the injection of ``local_control`` to the first controller cycle
at which the simulated arm slows down.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator

import pytest

from fxcell.cell import Cell
from fxcell.config import CellConfig
from fxcell.errors import NotInRemoteControlError
from fxcell.testing import SimulatorHandle, simulator

CONFIG = CellConfig.load()
WORK = [0.4, -1.4, 1.6, -1.8, -1.57, 0.0]
FAR = [2.4, -1.4, 1.6, -1.8, -1.57, 0.0]  # 2 rad of base rotation away
BOUND = 0.100  # s, as every other stop (protective stop, lost link: ≤ 0.11 s)


@pytest.fixture(scope="module")
def shared() -> Iterator[SimulatorHandle]:
    with simulator() as handle:
        yield handle


def _switch_to_local_and_watch(sim: SimulatorHandle) -> tuple[float, list[tuple[float, float]]]:
    """Inject Local control; the controller time just before it, and (time, |qd₁|) of the
    simulated arm until it stands still (at most 3 s)."""
    before = sim.state()["time"]
    sim.inject("local_control")
    samples: list[tuple[float, float]] = []
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        state = sim.state()
        samples.append((state["time"], abs(state["qd"][0])))
        if samples[-1][1] < 1e-6:
            break
    return before, samples


def braking_start(samples: list[tuple[float, float]], drop: float = 0.005) -> float:
    """Controller time of the first sample at which the speed has fallen ``drop`` rad/s
    below the highest seen so far (the move cruises: only a brake slows it)."""
    peak = 0.0
    for t, speed in samples:
        peak = max(peak, speed)
        if speed < peak - drop:
            return t
    raise AssertionError(f"the arm never slowed down: {samples[-5:]}")


@pytest.mark.injects_faults("the pendant switched to Local control mid-move")
async def test_switching_to_local_control_brakes_a_move_within_100_ms(
    shared: SimulatorHandle,
) -> None:
    await asyncio.to_thread(shared.inject, "remote_control")
    await asyncio.to_thread(shared.set_joints, WORK)
    async with Cell(shared.host, config=CONFIG) as cell:
        await cell.init()
        await cell.set_velocity_factor(0.3)
        move = asyncio.create_task(cell.move_joint(FAR))
        async with asyncio.timeout(10):  # cruising: well past the move's acceleration
            with cell.robot_states() as states:
                async for s in states:
                    if abs(s.actual_qd[0]) > 0.5:
                        break
        injected, samples = await asyncio.to_thread(_switch_to_local_and_watch, shared)
        with pytest.raises(NotInRemoteControlError, match="Local control"):
            await move
        assert samples[-1][1] < 1e-6, "the arm did not come to rest"
        latency = braking_start(samples) - injected
        assert latency <= BOUND, f"braking began {latency * 1e3:.0f} ms after the switch"
        await asyncio.to_thread(shared.inject, "remote_control")
