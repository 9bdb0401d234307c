"""Event-loop lag while the robot link connects, streams, starts control and reconnects.

A probe task sleeps 1 ms at a time and records how late it wakes: that lateness is the
lag every other task of the loop (a daemon's HTTP handlers, a move's supervision)
would suffer. Phases, each against the embedded simulator:

- connect: ``LinkClient.start()`` (the link process builds the ur_rtde clients);
- stream: 5 s of the 500 Hz state stream delivered to a subscriber (rate, gaps);
- control: ``start_control`` (the link process builds ``RTDEControlInterface``);
- reconnect: the link process is killed; the client notices and starts a new one.

Peer, same run: the naive design, constructing ``RTDEReceiveInterface`` and
``RTDEControlInterface`` in the asyncio process itself (inside ``asyncio.to_thread``,
which does not help: ur_rtde holds the GIL while it connects).

Targets: p99 <= 5 ms, max <= 20 ms; stream >= 499 Hz with no gaps.
"""

from __future__ import annotations

import asyncio
import itertools
import os
import statistics
import sys
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from typing import Any

from _harness import Targets

from fxcell.link import LinkClient
from fxcell.protocol import CONTROL_PERIOD
from fxcell.testing import SimulatorHandle, simulator

PROBE_PERIOD = 0.001
ROUNDS = 5


class LagProbe:
    def __init__(self) -> None:
        self.lags: list[float] = []
        self._task: asyncio.Task[None] | None = None

    async def _run(self) -> None:
        while True:
            t0 = time.perf_counter()
            await asyncio.sleep(PROBE_PERIOD)
            self.lags.append(max(0.0, time.perf_counter() - t0 - PROBE_PERIOD))

    @asynccontextmanager
    async def measuring(self) -> AsyncIterator[LagProbe]:
        self.lags = []
        self._task = asyncio.create_task(self._run())
        try:
            yield self
        finally:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def report(name: str, lags: list[float]) -> dict[str, float]:
    ms = [x * 1000 for x in lags]
    row = {
        "p50": statistics.median(ms) if ms else float("nan"),
        "p99": pct(ms, 0.99),
        "max": max(ms) if ms else float("nan"),
    }
    print(
        f"  {name:<28} n={len(ms):>6}  p50 {row['p50']:6.2f} ms  p99 {row['p99']:6.2f} ms  "
        f"max {row['max']:7.2f} ms"
    )
    return row


async def timed(
    probe: LagProbe, name: str, action: Callable[[], Awaitable[Any]]
) -> dict[str, float]:
    async with probe.measuring():
        await asyncio.sleep(0.05)
        await action()
        await asyncio.sleep(0.05)
    return report(name, probe.lags)


async def rounds(
    probe: LagProbe,
    name: str,
    action: Callable[[], Awaitable[Any]],
    n: int,
    between: Callable[[], Awaitable[Any]] | None = None,
) -> dict[str, float]:
    """Lag while ``action`` runs, pooled over ``n`` rounds (``between`` runs unmeasured)."""
    lags: list[float] = []
    for _ in range(n):
        if between is not None:
            await between()
        async with probe.measuring():
            await asyncio.sleep(0.02)
            await action()
            await asyncio.sleep(0.02)
        lags += probe.lags
    return report(f"{name} (x{n})", lags)


async def fxcell_run(sim: SimulatorHandle, stream_seconds: float) -> dict[str, dict[str, float]]:
    probe = LagProbe()
    rows: dict[str, dict[str, float]] = {}
    link = LinkClient(sim.host, connect_timeout=20)
    print("machine noise floor (the probe alone, nothing else running in the loop):")
    rows["idle"] = await timed(probe, "idle", lambda: asyncio.sleep(2.0))
    print("fxcell (robot-link process):")
    extra: list[LinkClient] = []

    async def connect() -> None:
        client = LinkClient(sim.host, connect_timeout=20)
        extra.append(client)
        await client.start()

    async def drop_extra() -> None:
        while extra:
            await extra.pop().close()

    try:
        rows["connect"] = await rounds(probe, "connect", connect, ROUNDS, drop_extra)
        await drop_extra()
        await link.start()

        timestamps: list[float] = []

        async def stream() -> None:
            with link.subscribe(maxsize=100_000) as sub:
                end = time.monotonic() + stream_seconds
                async for sample in sub:
                    timestamps.append(sample.timestamp)
                    if time.monotonic() > end:
                        break

        late_before = (await asyncio.to_thread(sim.state))["late_cycles"]
        rows["stream"] = await timed(probe, "stream", stream)
        late = (await asyncio.to_thread(sim.state))["late_cycles"] - late_before
        span = timestamps[-1] - timestamps[0]
        steps = [round((b - a) / CONTROL_PERIOD) for a, b in itertools.pairwise(timestamps)]
        gaps = sum(1 for s in steps if s != 1)
        rate = (len(timestamps) - 1) / span if span > 0 else 0.0
        missing = sum(s - 1 for s in steps if s > 1)
        lost = max(0, missing - late)  # cycles the simulator skipped (it ran late) were never sent
        sent_rate = len(timestamps) / (len(timestamps) + lost) * 500.0
        print(
            f"  stream delivery: {len(timestamps)} samples, {rate:.1f} Hz (controller time), "
            f"{gaps} gaps, {missing} cycles missing; the simulator skipped {late} late cycles, "
            f"so fxcell lost {lost} samples it was sent ({sent_rate:.1f} Hz of 500 delivered)"
        )
        rows["stream"]["rate"] = sent_rate
        rows["stream"]["gaps"] = lost
        rows["stream"]["raw_rate"] = rate

        await asyncio.to_thread(sim.bring_up)

        async def control() -> None:
            await link.start_control("script", "external_control.urp", 10.0)

        async def release() -> None:
            if link.control_ready:
                await link.stop_control("script")

        rows["control"] = await rounds(probe, "start_control", control, ROUNDS, release)

        detections: list[float] = []
        recoveries: list[float] = []

        async def reconnect() -> None:
            link.kill_process()
            t0 = time.monotonic()
            while link.up:  # noqa: ASYNC110
                await asyncio.sleep(0.0005)
            detections.append(time.monotonic() - t0)
            await link.wait_up(30)
            recoveries.append(time.monotonic() - t0)

        rows["reconnect"] = await rounds(probe, "kill + reconnect", reconnect, ROUNDS)
        print(
            f"  link death detected after {statistics.median(detections) * 1000:.1f} ms "
            f"(max {max(detections) * 1000:.1f}); up again after "
            f"{statistics.median(recoveries) * 1000:.0f} ms (median)"
        )
    finally:
        await link.close()
    return rows


async def peer_run(sim: SimulatorHandle) -> dict[str, dict[str, float]]:
    import rtde_control
    import rtde_receive

    probe = LagProbe()
    rows: dict[str, dict[str, float]] = {}
    print("peer (ur_rtde in the asyncio process, asyncio.to_thread):")
    holder: dict[str, Any] = {}

    async def connect() -> None:
        holder["r"] = await asyncio.to_thread(rtde_receive.RTDEReceiveInterface, sim.host)

    async def disconnect_receive() -> None:
        if "r" in holder:
            await asyncio.to_thread(holder.pop("r").disconnect)

    rows["connect"] = await rounds(probe, "connect", connect, ROUNDS, disconnect_receive)
    await disconnect_receive()

    async def control() -> None:
        holder["c"] = await asyncio.to_thread(rtde_control.RTDEControlInterface, sim.host)

    async def release() -> None:
        if "c" in holder:
            c = holder.pop("c")
            await asyncio.to_thread(c.stopScript)
            await asyncio.to_thread(c.disconnect)

    rows["control"] = await rounds(probe, "start_control", control, ROUNDS, release)
    await release()
    return rows


async def main() -> int:
    stream_seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 5.0
    async with simulator() as sim:
        ours = await fxcell_run(sim, stream_seconds)
    async with simulator() as sim:
        await asyncio.to_thread(sim.bring_up)
        peer = await peer_run(sim)
    print("ratio peer/fxcell (p99, max):")
    for phase in ("connect", "control"):
        a, b = ours[phase], peer[phase]
        print(f"  {phase:<14} p99 ×{b['p99'] / a['p99']:.1f}   max ×{b['max'] / a['max']:.1f}")
    worst_p99 = max(r["p99"] for k, r in ours.items() if k != "idle")
    worst_max = max(r["max"] for k, r in ours.items() if k != "idle")
    stream = ours["stream"]
    print(
        f"noise floor now: p99 {ours['idle']['p99']:.2f} ms, max {ours['idle']['max']:.2f} ms; "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    targets = Targets("loop_lag")
    targets.check(
        "event-loop lag, worst phase p99", worst_p99, "<=", 5.0, "ms",
        peer=max(peer["connect"]["p99"], peer["control"]["p99"]), peer_name="ur_rtde in-process",
    )  # fmt: skip
    targets.check(
        "event-loop lag, worst phase max", worst_max, "<=", 20.0, "ms",
        peer=max(peer["connect"]["max"], peer["control"]["max"]), peer_name="ur_rtde in-process",
    )  # fmt: skip
    targets.check("state stream delivered", stream["rate"], ">=", 499.0, "Hz")
    targets.check("state stream gaps (samples lost)", stream["gaps"], "==", 0)
    return targets.finish()


if __name__ == "__main__":
    raise SystemExit(asyncio.run(main()))
