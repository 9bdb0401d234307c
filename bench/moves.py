"""Move overhead (call to return minus planned duration) and daemon memory over many moves.

1. Library: ``Cell.move_joint`` against a simulator process, 100 small moves (the last
   wrist joint ±0.005 rad, 0.25 s each): wall time from the call to its return minus the
   move's planned duration (``MoveResult.planned_duration``). This is what planning,
   streaming start-up, settling and supervision add to the motion itself.
2. Daemon: ``fxcell daemon`` on its embedded simulator, the same moves over HTTP
   (``POST /api/cell/move_joint?wait=true``), 1000 of them (``--moves``); overhead as
   above from the HTTP client, and the daemon process's resident memory (VmRSS) every 50
   moves. Warm-up: the first 100 moves. The daemon records (MCAP), as it does by default
   (it did not here before 2026-11-23: the harness started it with --no-record). An idle
   recording daemon's RSS went from 138.4 to 139.3 MiB between its first and sixth minute
   (measured 2026-11-23); glibc's malloc fragmenting its heap with the recorder's chunk
   buffers, fixed since 2026-11-25 (``fxcell.daemon.server.fix_mmap_threshold``: +1.8 MiB
   idle over 4.5 minutes before, +0.3 MiB after).

No peer (absolute targets). Targets: every daemon move succeeds; library and daemon
median overhead <= 10 ms; daemon RSS after the 1000 moves within ±2 MiB of its value
after warm-up.

    ./dev bench moves [--moves N] [--long]   (--long: 5000 moves)
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
import time
from pathlib import Path

import httpx
from _harness import Targets

from fxcell.cell import Cell
from fxcell.config import CellConfig
from fxcell.daemon.process import DaemonProcess
from fxcell.testing import simulator

TOKEN = "bench-token-0123456789abcdef0123"
STEP = 0.005  # rad, the last wrist joint
WARMUP = 100


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def rss_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


def describe(name: str, ms: list[float]) -> str:
    return (
        f"  {name:<26} n={len(ms):5d}  median {statistics.median(ms):6.2f} ms  "
        f"p90 {pct(ms, 0.9):6.2f} ms  p99 {pct(ms, 0.99):6.2f} ms  max {max(ms):7.2f} ms"
    )


async def library(n: int) -> list[float]:
    config = CellConfig.load()
    home = list(config.home)
    out: list[float] = []
    with simulator(joints=home) as sim:
        async with Cell(sim.host, config=config) as cell:
            await cell.init()
            for k in range(n + 5):
                target = [*home[:5], home[5] + (STEP if k % 2 == 0 else 0.0)]
                t0 = time.perf_counter()
                result = await cell.move_joint(target)
                took = time.perf_counter() - t0
                if k >= 5:  # the first moves warm the caches
                    out.append((took - result.planned_duration) * 1e3)
    return out


def daemon(n: int) -> tuple[list[float], list[tuple[int, float]], list[str]]:
    overhead: list[float] = []
    failures: list[str] = []
    memory: list[tuple[int, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "cell.yaml"
        config.write_text(f"robot:\n  host: null\ndaemon:\n  token_file: {tmp}/token\n")
        with DaemonProcess.start(config, token=TOKEN, log_dir=Path(tmp) / "logs") as d:
            d.wait_connected()
            pid = d.proc.pid
            headers = {"Authorization": f"Bearer {TOKEN}", "X-Fxcell-Client": "bench"}
            with httpx.Client(base_url=d.url, headers=headers, timeout=60) as http:
                r = http.post("/api/cell/init")
                r.raise_for_status()
                http.headers["X-Fxcell-Lease"] = r.headers["X-Fxcell-Lease"]
                q = http.get("/api/state").json()["robot"]["q"]
                memory.append((0, rss_mib(pid)))
                for k in range(1, n + 1):
                    target = [*q[:5], q[5] + (STEP if k % 2 else 0.0)]
                    t0 = time.perf_counter()
                    r = http.post(
                        "/api/cell/move_joint", params={"wait": "true"}, json={"target": target}
                    )
                    took = time.perf_counter() - t0
                    body = r.json()
                    if r.status_code != 200 or body.get("status") != "succeeded":
                        failures.append(f"move {k}: HTTP {r.status_code}: {str(body)[:300]}")
                        r = http.post("/api/cell/init")  # recover (e.g. after a stop)
                        continue
                    overhead.append((took - body["result"]["planned_duration"]) * 1e3)
                    if k % 50 == 0:
                        memory.append((k, rss_mib(pid)))
    return overhead, memory, failures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--moves", type=int, default=1000)
    parser.add_argument("--library-moves", type=int, default=100)
    parser.add_argument("--long", action="store_true", help="5000 daemon moves")
    args = parser.parse_args()
    n = 5000 if args.long else args.moves
    lib = asyncio.run(library(args.library_moves))
    print("move overhead: call to return minus planned duration")
    print(describe("library Cell.move_joint", lib))
    ours, memory, failures = daemon(n)
    print(describe("daemon over HTTP", ours))
    for failure in failures[:5]:
        print("  failed:", failure)
    print("daemon RSS (MiB) by moves done: " + ", ".join(f"{k}: {m:.1f}" for k, m in memory))
    warm = next(m for k, m in memory if k >= WARMUP)
    final = memory[-1][1]
    targets = Targets("moves")
    targets.check("daemon moves succeeded", n - len(failures), "==", n)
    targets.check("library median overhead", statistics.median(lib), "<=", 10.0, "ms")
    targets.check("daemon median overhead (HTTP)", statistics.median(ours), "<=", 10.0, "ms")
    targets.check(f"daemon RSS change, moves {WARMUP} to {n}", abs(final - warm), "<=", 2.0, "MiB")
    return targets.finish()


if __name__ == "__main__":
    raise SystemExit(main())
