"""Cell.stop() during a base move: time and distance to rest against the braking bound.

A +2.5 rad base move (full speed, configured limits) runs against the embedded simulator;
``stop()`` is called at several moments (accelerating, near peak speed, decelerating).
Measured from the ``stop()`` call to the first 500 Hz state sample with every joint slower
than 1e-4 rad/s; distance = base travel in that time.

Peer, same run, computed here in closed form (``bench/_bounds.py``, tested against Ruckig),
not by fxcell: the jerk-limited time-optimal braking of each joint from the state the
stream showed at the ``stop()`` call (velocity and acceleration from a straight-line fit
of the last 10 samples' velocities, carried forward to the call) under the configured
braking limits; the slowest joint's time, less the closed-form tail in which the
velocity is already below the 1e-4 rad/s threshold (``sqrt(2·1e-4/j)``, 2.2 ms at
40 rad/s³). Nothing is taken off the measurement.
(The seed slept v/a after MoveIt's stop.)

Target: time to rest <= bound + 10 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import statistics
import time

import numpy as np
from _bounds import braking_bound
from _harness import Targets

from fxcell.cell import Cell
from fxcell.config import CellConfig
from fxcell.errors import MoveStoppedError
from fxcell.events import StateEvent
from fxcell.link.capabilities import UR3E
from fxcell.motion.trajectory import Limits
from fxcell.protocol import RobotState
from fxcell.testing import simulator

CONFIG = CellConfig.load()
BRAKING = Limits.for_braking(CONFIG.limits, period=UR3E.sample_period)  # what stop() brakes with
FIT = 10  # samples (20 ms) fitted for the state at the stop() call
REST = 1e-4  # rad/s: a jerk-limited stop crosses 1e-3 rad/s some 14 ms before its end


def state_at(states: list[RobotState], when: float) -> tuple[np.ndarray, np.ndarray]:
    """Joint velocity and acceleration at ``when`` (monotonic time of the stop() call),
    from a straight-line fit of the last ``FIT`` samples' velocities against controller
    time: one sample's velocity difference is too noisy (a late cycle caught up shows as
    a jump) to give the acceleration the bound starts from."""
    window = states[-FIT:]
    t = np.array([s.timestamp for s in window])
    v = np.array([s.actual_qd for s in window])
    slope, intercept = np.polyfit(t - t[-1], v, 1)
    ahead = max(when - window[-1].received_at, 0.0)  # the stream's latest is this old
    return intercept + slope * ahead, slope


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
    qd, qdd = state_at(states[: states.index(at_stop) + 1], called)
    qdd = np.clip(qdd, -BRAKING.acceleration, BRAKING.acceleration)
    bound = braking_bound(qd, qdd, BRAKING.acceleration, BRAKING.jerk)
    bound -= math.sqrt(2 * REST / float(np.max(BRAKING.jerk)))  # already below REST
    # distance the base would travel on its own optimal braking (v·t - ... from the bound)
    return {
        "speed": float(abs(qd[0])),
        "time": rest.received_at - called,
        "bound": bound,
        "distance": abs(rest.actual_q[0] - at_stop.actual_q[0]),
        "returned": returned - called,
    }


async def main() -> int:
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
          f"{'dist':>8} {'stop() ret':>10}")  # fmt: skip
    for after, r in rows:
        over = (r["time"] - r["bound"]) * 1e3
        print(f"{after:7.1f}s {r['speed']:7.3f} {r['time']:8.3f} {r['bound']:7.3f} {over:+6.1f}ms "
              f"{r['distance']:8.4f} {r['returned']:10.3f}")  # fmt: skip
    overs = [(r["time"] - r["bound"]) * 1e3 for _, r in rows]
    print(f"overhead over the bound: median {statistics.median(overs):+.1f} ms")
    targets = Targets("stop")
    worst = max(range(len(rows)), key=lambda i: overs[i])
    targets.check(
        f"time to rest over the bound, worst of {len(rows)}", overs[worst], "<=", 10.0, "ms",
        peer=0.0, peer_name=f"bound {rows[worst][1]['bound'] * 1e3:.0f} ms",
    )  # fmt: skip
    return targets.finish()


if __name__ == "__main__":
    raise SystemExit(asyncio.run(main()))
