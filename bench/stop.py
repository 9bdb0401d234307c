"""Cell.stop() during a base move: time and distance to rest against the braking bound.

A +2.5 rad base move (full speed, configured limits) runs against the embedded simulator;
``stop()`` is called at several moments (accelerating, near peak speed, decelerating).
Measured from the ``stop()`` call to the first 500 Hz state sample with every joint slower
than 1e-4 rad/s; distance = base travel in that time.

Peer, same run: the physical bound — the jerk-limited time-optimal braking from the
robot's state at the ``stop()`` call (the planned state where the plan passes the robot's
position then) under the configured braking limits (Ruckig), and its distance.
(The seed slept v/a after MoveIt's stop.)

Target: time to rest <= bound + 10 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import statistics
import time

import numpy as np

from fxcell.cell import Cell
from fxcell.config import CellConfig
from fxcell.errors import MoveStoppedError
from fxcell.events import StateEvent
from fxcell.motion.trajectory import Limits, braking, braking_duration, rest_to_rest
from fxcell.protocol import RobotState
from fxcell.testing import simulator

CONFIG = CellConfig.load()
MOVE_LIMITS = Limits.from_config(CONFIG.limits)  # what the move is planned with
BRAKING = Limits.for_braking(CONFIG.limits)  # what stop() brakes with
REST = 1e-4  # rad/s: a jerk-limited stop crosses 1e-3 rad/s some 14 ms before its end


async def trial(cell: Cell, target: list[float], after: float) -> dict[str, float]:
    states: list[RobotState] = []

    def record(event: object) -> None:
        if isinstance(event, StateEvent):
            states.append(event.sample)

    unsubscribe = cell.bus.subscribe(record)
    try:
        with cell.robot_states() as stream:
            move = asyncio.create_task(cell.move_joint(target))
            started = None
            async with asyncio.timeout(10):
                async for s in stream:
                    if started is None and abs(s.actual_qd[0]) > 1e-6:
                        started = s.received_at
                    if started is not None and time.monotonic() - started >= after:
                        break
            at_stop = states[-1]
            called = time.monotonic()
            await cell.stop()
            returned = time.monotonic()
            with contextlib.suppress(MoveStoppedError):
                await move
            async with asyncio.timeout(5):
                async for s in stream:
                    if max(map(abs, s.actual_qd)) < REST:
                        break
    finally:
        unsubscribe()
    rest = next(s for s in states if s.received_at > called and max(map(abs, s.actual_qd)) < REST)
    # The robot follows the planned trajectory (servoJ lag compensated): its state at the
    # stop() call is the planned state where the plan passes its position (a busy machine
    # may stretch the timing, never the path).
    planned = rest_to_rest(states[0].actual_q, target, MOVE_LIMITS)
    index = int(np.searchsorted(planned.positions[:, 0], at_stop.actual_q[0]))
    p, qd, qdd = planned.state(index)
    bound = braking_duration(qd, qdd, BRAKING)
    profile = braking(p, qd, qdd, BRAKING)
    return {
        "speed": float(abs(qd[0])),
        "time": rest.received_at - called,
        "bound": bound,
        "distance": abs(rest.actual_q[0] - at_stop.actual_q[0]),
        "bound_distance": abs(profile.positions[-1][0] - p[0]),
        "returned": returned - called,
    }


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--moments", type=float, nargs="*", default=[0.4, 1.0, 1.8, 2.6, 3.2])
    args = parser.parse_args()
    home = list(CONFIG.home)
    target = [home[0] + 2.5, *home[1:]]
    rows = []
    with simulator(joints=home) as sim:
        async with Cell(sim.host, config=CONFIG) as cell:
            await cell.init()
            for after in args.moments:
                await cell.move_joint(home)
                rows.append((after, await trial(cell, target, after)))
    print(f"{'stop at':>8} {'speed':>7} {'to rest':>8} {'bound':>7} {'over':>7} "
          f"{'dist':>8} {'bound d':>8} {'stop() ret':>10}")  # fmt: skip
    for after, r in rows:
        over = (r["time"] - r["bound"]) * 1e3
        print(f"{after:7.1f}s {r['speed']:7.3f} {r['time']:8.3f} {r['bound']:7.3f} {over:+6.1f}ms "
              f"{r['distance']:8.4f} {r['bound_distance']:8.4f} {r['returned']:10.3f}")  # fmt: skip
    overs = [(r["time"] - r["bound"]) * 1e3 for _, r in rows]
    print(
        f"overhead over the bound: median {statistics.median(overs):+.1f} ms, "
        f"max {max(overs):+.1f} ms; target <= +10 ms: "
        f"{'met' if max(overs) <= 10 else 'NOT met'}"
    )


if __name__ == "__main__":
    asyncio.run(main())
