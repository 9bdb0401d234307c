"""Moves beside CPU burners: how many brake on a stalled state stream, and where it stalled.

Setup: a UR3e simulator process, a Cell on it (its robot-link process), and ``--burners``
CPU burners (default 2: one per core of the CI machine; each a bounded busy loop). Then
``--moves`` joint moves of the base (±0.2 rad at 0.3 of full speed, about 0.6 s each),
each awaited. A move the link process braked on ``state_stalled`` (no state sample for the
guard's ``stall_timeout``, 80 ms) counts as a stall.

Where each hop stood, for the diagnosis:

* the simulator: its own RTDE send period (control port ``stats``: median, p99, max) and
  the controller-time gaps the client saw in the stream (``LinkClient.gaps``: > 20 ms);
* the link process: its ``state stalled`` lines (how old the newest sample was, how many
  bytes the controller had sent that the pump had not read yet, and how long the
  trajectory thread itself had not run). Bytes unread mean the stall was in the link
  process, not in the controller.

``--sim`` and ``--link`` choose each process's scheduling (``realtime``: SCHED_FIFO, as the
test suite asks for the simulator and as the link process asks for itself where
permitted; ``normal``: SCHED_OTHER; ``starved``: SCHED_OTHER at nice 19, a link process that
loses every contest for a CPU, as on a machine much busier than the burners make it). The
bench sets ``--link``'s policy on every thread of
the running link process from outside (root only), so it measures either policy whatever
the link process asked for itself.

``--camera`` also takes a frame from the simulator's camera every ``--camera`` seconds
during the moves (the rendering runs inside the simulator process, as during a job's
placement checks).

    ./dev bench stall [--moves N] [--burners N] [--sim realtime|normal]
                      [--link realtime|normal|starved] [--camera S]

Target: no move braked on a stall. Exits 1 otherwise. Takes about a minute.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import subprocess
import sys
import threading
import time
import urllib.request
from dataclasses import dataclass
from typing import Any

from _harness import Targets

from fxcell.cell import Cell
from fxcell.config import SIMULATOR_CAMERA_PORT, CellConfig
from fxcell.errors import FxcellError
from fxcell.link import embedded
from fxcell.testing import simulator

BURN_SECONDS = 300  # a burner ends by itself even if this bench is killed


def burners(n: int) -> list[subprocess.Popen[bytes]]:
    code = f"import time\nend = time.monotonic() + {BURN_SECONDS}\n"
    code += "while time.monotonic() < end: pass"
    return [subprocess.Popen([sys.executable, "-c", code]) for _ in range(n)]


class Snapshots(threading.Thread):
    """Takes a frame from the simulator's camera every ``period`` s until stopped."""

    def __init__(self, host: str, period: float) -> None:
        super().__init__(daemon=True)
        self.url = f"http://{host}:{SIMULATOR_CAMERA_PORT}/snapshot.jpg"
        self.period = period
        self.halt = threading.Event()
        self.frames = 0

    def run(self) -> None:
        while not self.halt.wait(self.period):
            with urllib.request.urlopen(self.url, timeout=10) as reply:
                reply.read()
            self.frames += 1


def schedule_threads(pid: int, policy: str, priority: int = 80) -> None:
    """SCHED_FIFO at ``priority`` (``realtime``) or SCHED_OTHER (``normal``) for every
    thread of process ``pid``; the threads it starts later inherit their creator's."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        if policy == "realtime":
            os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
        else:
            os.sched_setscheduler(int(tid), os.SCHED_OTHER, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, int(tid), 19 if policy == "starved" else 0)


class Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


async def recover(cell: Cell) -> bool:
    """Init again once the Cell allows it (the braked move ends, the link is back);
    False if it did not within 60 s."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            await cell.init()
        except FxcellError:
            # 25 state samples (50 ms) or 0.5 s without any (the link is down), then again
            with contextlib.suppress(TimeoutError), cell.robot_states() as states:
                async with asyncio.timeout(0.5):
                    n = 0
                    async for _ in states:
                        n += 1
                        if n >= 25:
                            break
        else:
            return True
    return False


@dataclass
class Outcome:
    elapsed: float
    stalled: int
    failed: int
    sim: dict[str, Any]
    gaps: int
    warnings: list[str]


async def run(args: argparse.Namespace) -> Outcome:
    config = CellConfig.load()
    home = list(config.home)
    lines = Lines()
    logging.getLogger("fxcell").addHandler(lines)
    failed = 0
    with simulator(joints=home) as sim:
        async with Cell(sim.host, config=config) as cell:
            await cell.init()
            await cell.set_velocity_factor(0.3)
            link = cell.link
            pid = getattr(link, "pid", None)
            if pid is not None:
                schedule_threads(pid, args.link)
            procs = burners(args.burners)
            camera = Snapshots(sim.host, args.camera) if args.camera > 0 else None
            if camera is not None:
                camera.start()
            try:
                embedded.stats(sim.host, reset=True)
                gaps_before = getattr(link, "gaps", 0)
                t0 = time.monotonic()
                for k in range(args.moves):
                    target = [home[0] + (0.2 if k % 2 == 0 else 0.0), *home[1:]]
                    try:
                        await cell.move_joint(target)
                    except FxcellError as exc:
                        failed += 1
                        print(f"  move {k}: {type(exc).__name__}: {exc}"[:200], flush=True)
                        if not await recover(cell):
                            print("  the Cell did not recover within 60 s: run ended")
                            failed += args.moves - k - 1
                            break
                        pid = getattr(link, "pid", None)  # a link that went down restarted
                        if pid is not None:
                            schedule_threads(pid, args.link)
                elapsed = time.monotonic() - t0
                sim_stats = embedded.stats(sim.host)
                gaps = getattr(link, "gaps", 0) - gaps_before
            finally:
                if camera is not None:
                    camera.halt.set()
                    camera.join()
                    print(f"  camera frames taken: {camera.frames}")
                for p in procs:
                    p.kill()
                for p in procs:
                    p.wait()
    logging.getLogger("fxcell").removeHandler(lines)
    stalled = sum("state_stalled" in line for line in lines.lines)
    return Outcome(elapsed, stalled, failed, sim_stats, gaps, lines.lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--moves", type=int, default=40)
    parser.add_argument("--burners", type=int, default=2)
    parser.add_argument("--sim", choices=("realtime", "normal"), default="realtime")
    parser.add_argument("--link", choices=("realtime", "normal", "starved"), default="realtime")
    parser.add_argument("--camera", type=float, default=0.0, metavar="S")
    args = parser.parse_args()
    os.environ["FXCELL_SIM_PRIORITY"] = args.sim
    with open("/proc/loadavg") as f:
        load = f.read().split()[0]
    out = asyncio.run(run(args))
    sim = out.sim
    print(
        f"{args.moves} moves in {out.elapsed:.0f} s beside {args.burners} burners "
        f"(load average {load}; simulator {args.sim}, link {args.link})"
    )
    print(
        f"  simulator send period: median {sim['period_ms_median']:.2f} ms, "
        f"p99 {sim['period_ms_p99']:.2f} ms, max {sim['period_ms_max']:.2f} ms, "
        f"late cycles {sim['late_cycles']}; stream gaps seen by the client: {out.gaps}"
    )
    for line in out.warnings:
        print(f"  warning: {line}"[:300])
    print(f"  braked on a stall: {out.stalled}; failed moves: {out.failed}")
    targets = Targets("stall")
    targets.check("moves braked on a stalled state stream", out.stalled, "==", 0)
    targets.check("failed moves", out.failed, "==", 0)
    return targets.finish()


if __name__ == "__main__":
    sys.exit(main())
