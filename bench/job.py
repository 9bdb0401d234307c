"""The fusion-machine job: robot time per sample and a whole run, against the planned moves.

A 16-sample run (four fusion cycles) on the embedded simulator at the configured speeds: the
Cell and the Job in this process, the simulator (arm, Hand-E, fusion machine) in its own.
Figures:

- robot time per sample: the time the job spends in robot steps (pick, place, home), per
  sample; the machine's fusion and cooling are not robot time;
- whole run: wall time from start to done;
- overhead ratio: robot time over the sum of the planned durations of every move the run
  made (trajectory durations from the planner, as recorded on the ``/motion`` topic) — what
  grasping, planning, settling and the job's bookkeeping add to pure motion.

Targets: every bead on its tray slot and every crucible back in its rack slot (by the
simulator's object poses, within 1 mm), and an overhead ratio ≤ 1.5.

    ./dev bench job                  # 16 samples at the configured (the seed's) speeds
    ./dev bench job --samples 4      # one fusion cycle
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _harness import Targets

from fxcell import Cell
from fxcell.config import CellConfig
from fxcell.daemon.jobs import CellForJob
from fxcell.events import CommandEvent, MotionEvent
from fxcell.job import Job, JobStore
from fxcell.layout import Layout, slot_name
from fxcell.testing import simulator

ROBOT_STEPS = ("pick", "place", "go_home")


def run_spec(n: int) -> dict[str, Any]:
    slots = [slot_name(r, c) for r in range(4) for c in range(4)][:n]
    machine = ["A1", "A2", "A3", "A4"]
    return {
        "name": f"bench {n} samples",
        "samples": [
            {"id": f"S{i + 1:02d}", "rack": s, "machine": machine[i % 4], "tray": s}
            for i, s in enumerate(slots)
        ],
    }


async def bench(n: int, time_scale: float, fusion: float, cooling: float) -> int:
    tmp = Path(tempfile.mkdtemp(prefix="fxcell-bench-job-"))
    base = CellConfig.load()
    config = base.model_copy(
        update={
            "positions_file": tmp / "positions.yaml",
            "job": base.job.model_copy(update={"database": tmp / "job.sqlite3"}),
        }
    )
    layout = Layout(config.layout)
    spec = run_spec(n)
    args = ["--crucibles", str(n), "--fusion-time", str(fusion), "--cooling-time", str(cooling)]
    planned: list[float] = []
    robot: dict[str, list[float]] = {}
    faults: list[str] = []
    with simulator(time_scale=time_scale, extra_args=args) as sim:
        async with Cell(host=sim.host, config=config) as cell:
            await cell.init()
            await cell.gripper_activate()

            def on_event(event: object) -> None:
                if isinstance(event, MotionEvent) and event.kind == "trajectory":
                    planned.append(float(event.data["duration"]))
                elif (
                    isinstance(event, CommandEvent)
                    and event.ended is not None
                    and event.name in ROBOT_STEPS
                    and event.outcome == "ok"
                ):
                    robot.setdefault(event.name, []).append(event.ended - event.started)

            cell.bus.subscribe(on_event)
            store = JobStore(config.job.database)
            job = Job(CellForJob(cell), store, config.job)
            await job.recover()
            t0 = time.monotonic()
            await job.start(spec)
            last = ""
            faults: list[str] = []
            while job.state not in ("done", "paused"):
                if job.state == "fault":
                    # What the operator does after a stop that lost nothing: init, resume.
                    faults.append(job.status()["message"])
                    print(f"\nfault: {faults[-1]}; init and resume")
                    if len(faults) > 5:
                        break
                    await cell.init()
                    await job.resume()
                    continue
                status = job.status()
                p = status["progress"]
                line = f"\r{p['done']:3d}/{p['total']} steps  {status['step'] or ''}"[:100]
                if line != last:
                    print(line.ljust(100), end="", flush=True)
                    last = line
                await asyncio.sleep(0.2)
            wall = time.monotonic() - t0
            print()
            final = job.status()
            await job.close()
        world = sim.objects()

    in_place = 0
    for sample in spec["samples"]:
        crucible = world.get(f"crucible-{sample['rack']}")
        bead = world.get(f"crucible-{sample['rack']}.bead")
        if crucible is None or bead is None:
            continue
        rack = layout.station("rack").grip_pose(sample["rack"]).position
        tray = layout.station("tray").grip_pose(sample["tray"]).position
        ok_c = np.linalg.norm(np.array(crucible["pose"][:3]) - rack) < 1e-3
        ok_b = np.linalg.norm(np.array(bead["pose"][:3]) - tray) < 1e-3
        in_place += int(ok_c and ok_b)

    robot_time = sum(sum(v) for v in robot.values())
    ratio = robot_time / sum(planned) if planned else float("inf")
    picks = robot.get("pick", [])
    places = robot.get("place", [])
    print(f"job ended {final['state']}: {final['message']}")
    print(f"whole run ({n} samples, {(n + 3) // 4} fusion cycles): {wall:.1f} s wall")
    print(f"robot time: {robot_time:.1f} s, {robot_time / n:.1f} s per sample")
    if picks and places:
        print(
            f"pick median {statistics.median(picks):.2f} s ({len(picks)}), "
            f"place median {statistics.median(places):.2f} s ({len(places)})"
        )
    print(f"planned move time: {sum(planned):.1f} s in {len(planned)} moves")
    print(f"overhead ratio (robot time / planned move time): {ratio:.3f}")

    print(f"faults resumed by the operator: {len(faults)}")
    targets = Targets("job")
    targets.check("samples back in place", in_place, "==", n, "samples")
    targets.check("faults (the operator had to resume)", len(faults), "==", 0)
    targets.check("robot time per sample", robot_time / n, "<=", 120.0, "s")
    targets.check("overhead ratio vs planned moves", ratio, "<=", 1.5)
    return targets.finish()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", type=int, default=16, choices=range(1, 17), metavar="1..16")
    p.add_argument("--time-scale", type=float, default=0.05, help="simulator time scale")
    p.add_argument("--fusion-time", type=float, default=600.0, help="s, x time scale")
    p.add_argument("--cooling-time", type=float, default=300.0, help="s, x time scale")
    a = p.parse_args()
    raise SystemExit(asyncio.run(bench(a.samples, a.time_scale, a.fusion_time, a.cooling_time)))


if __name__ == "__main__":
    main()
