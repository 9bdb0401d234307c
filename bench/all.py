"""Run every bench one after another and print one combined table of their targets.

    ./dev bench all [--long] [--only NAME ...] [--skip NAME ...]

Each bench runs in its own process (its output is shown as it runs) and records its
targets through ``FXCELL_BENCH_RESULTS``; a bench that crashes counts as a miss. Exits 0
only when every target of every bench is met. ``--long`` gives the benches that have one
their long variant (the 10-minute recorder session). Not part of CI: timings belong here.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _harness import RESULTS_ENV, Target, load, table

HERE = Path(__file__).resolve().parent
# The load bench runs CPU burners: last, so that it disturbs no other bench.
BENCHES = (
    "ik",
    "ik_ned2",
    "planning",
    "trajectory",
    "stop",
    "sim_stream",
    "loop_lag",
    "api",
    "sila",
    "recorder",
    "moves",
    "placement",
    "load",
)
LONG = {"recorder", "moves"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--long", action="store_true")
    parser.add_argument("--only", nargs="*", default=None)
    parser.add_argument("--skip", nargs="*", default=[])
    args = parser.parse_args()
    names = [b for b in (args.only or BENCHES) if b not in args.skip]
    rows: list[Target] = []
    durations: dict[str, float] = {}
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            path = Path(tmp) / f"{name}.jsonl"
            path.touch()
            cmd = [sys.executable, str(HERE / f"{name}.py")]
            if args.long and name in LONG:
                cmd.append("--long")
            print(f"\n######## bench {name} (load average {os.getloadavg()[0]:.2f})", flush=True)
            t0 = time.monotonic()
            rc = subprocess.run(cmd, env={**os.environ, RESULTS_ENV: str(path)}).returncode
            durations[name] = time.monotonic() - t0
            got = load(str(path))
            if rc != 0 and all(t.met for t in got):
                got.append(Target(name, "bench exits 0", float(rc), "==", 0.0, ""))
            rows += got
    print(f"\n######## all benches ({', '.join(f'{n} {s:.0f} s' for n, s in durations.items())})")
    print(f"load average before {load_before[0]:.2f}, after {os.getloadavg()[0]:.2f}")
    print(table(rows, with_bench=True))
    missed = [f"{t.bench}: {t.text}" for t in rows if not t.met]
    if missed:
        print("target missed: " + "; ".join(missed))
        return 1
    print("target met")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
