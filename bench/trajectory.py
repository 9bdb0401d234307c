"""The seed's base-joint test (thesis table 5.3.3): +π/2 from home at 1.5, 0.5, 0.1 rad/s.

Each move runs through the whole stack against the embedded simulator (Cell.move_joint:
plan, Ruckig, 500 Hz servoJ from the robot-link process). Executed duration = from the
first state sample in which the base moves to the first in which it is within 1e-5 rad of
the target and at rest, read from the 500 Hz state stream.

Peers: the time-optimal bound under the same limits (Ruckig, jerk-limited), and the seed's
MoveIt stack on the real UR3e (3.634 s / 6.339 s / 31.489 s, acceleration limits off).
The base's acceleration limit is the configured one (0.7 rad/s², the seed's
joint_limits.yaml) unless --base-acceleration is given (1.4 = PolyScope's default, the
figure behind the anchors' 2.263 / 3.639 / 15.908 s bounds).

Target: executed within 2 % of the bound.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import statistics

import numpy as np

from fxcell.cell import Cell
from fxcell.config import CellConfig
from fxcell.events import StateEvent
from fxcell.motion.trajectory import Limits, minimum_duration
from fxcell.testing import simulator

SEED = {1.5: 3.634, 0.5: 6.339, 0.1: 31.489}
BASE = CellConfig.load()


def config_for(velocity: float, acceleration: float | None) -> CellConfig:
    limits = BASE.limits
    v = list(limits.velocity)
    v[0] = velocity
    a = list(limits.acceleration)
    if acceleration is not None:
        a[0] = acceleration
    new = limits.model_copy(update={"velocity": tuple(v), "acceleration": tuple(a)})
    return BASE.model_copy(update={"limits": new})


async def run_once(host: str, config: CellConfig) -> tuple[float, float, float]:
    home = np.array(config.home)
    target = home + np.array([math.pi / 2, 0, 0, 0, 0, 0])
    samples: list[tuple[float, float, float]] = []
    async with Cell(host, config=config) as cell:
        await cell.init()
        await cell.move_joint(list(home))

        def record(event: object) -> None:
            if isinstance(event, StateEvent):
                s = event.sample
                samples.append((s.received_at, s.actual_q[0], max(map(abs, s.actual_qd))))

        unsubscribe = cell.bus.subscribe(record)
        result = await cell.move_joint(list(target))
        await asyncio.sleep(0.05)  # a few more samples after the move returned
        unsubscribe()
    t = np.array(samples)
    start = t[np.flatnonzero(t[:, 2] > 1e-6)[0], 0]
    arrived = (np.abs(t[:, 1] - target[0]) <= 1e-5) & (t[:, 2] < 1e-3)
    not_yet = np.flatnonzero(~arrived)
    end = t[not_yet[-1] + 1, 0] if len(not_yet) and not_yet[-1] + 1 < len(t) else t[-1, 0]
    return end - start, result.executed_duration, result.joint_error


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--base-acceleration", type=float, default=None)
    parser.add_argument("--repeat", type=int, default=2, help="runs per speed (0.1 rad/s: 1)")
    args = parser.parse_args()
    home = np.array(BASE.home)
    target = home + np.array([math.pi / 2, 0, 0, 0, 0, 0])
    with simulator() as sim:
        late_before = int(sim.state()["late_cycles"])
        print(f"{'rad/s':>6} {'bound':>8} {'executed':>9} {'vs bound':>9} "
              f"{'seed':>8} {'seed/ours':>9} {'send→settle':>12} {'joint err':>10}")  # fmt: skip
        for velocity in (1.5, 0.5, 0.1):
            config = config_for(velocity, args.base_acceleration)
            bound = minimum_duration(home, target, Limits.from_config(config.limits))
            runs = [
                await run_once(sim.host, config)
                for _ in range(1 if velocity < 0.2 else args.repeat)
            ]
            executed = statistics.median(r[0] for r in runs)
            settle = statistics.median(r[1] for r in runs)
            err = max(r[2] for r in runs)
            over = 100 * (executed / bound - 1)
            seed = SEED[velocity]
            print(f"{velocity:6.1f} {bound:8.3f} {executed:9.3f} {over:+8.1f}% "
                  f"{seed:8.3f} {seed / executed:8.2f}x {settle:12.3f} {err:10.1e}")  # fmt: skip
        late = int(sim.state()["late_cycles"]) - late_before
        print(f"simulator cycles run late during the bench: {late} (CPU contention)")


if __name__ == "__main__":
    asyncio.run(main())
