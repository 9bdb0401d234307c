"""Plan + simplify + time-parameterise joint moves in the cell scene.

Queries: pairs of random collision-free configurations with the gripper over the table
or the machine (the cell's working space), plus pairs on either side of the fusion
machine whose straight joint line runs through it. Each query goes through
``MotionPlanner.plan_joint``: collision checks, the direct line if free (else OMPL
RRTConnect, shortcutting, a fine re-check), Ruckig timing validated on the samples.

Peer, same run: the plain OMPL pipeline on the same queries — RRTConnect on every
query (no direct-line shortcut), OMPL's ``simplifySolution``, the same Ruckig timing.

Targets: median <= 20 ms; every feasible query solved within 1 s.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np

from fxcell.config import CellConfig
from fxcell.errors import FxcellError
from fxcell.geometry import Pose
from fxcell.motion.moves import MotionPlanner
from fxcell.motion.planning import JointPlanner
from fxcell.motion.trajectory import Limits, through_waypoints

CONFIG = CellConfig.load()


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(int(q * len(s)), len(s) - 1)]


def queries(
    planner: MotionPlanner, n: int, blocked: int, seed: int
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    kin, checker = planner.kinematics, planner.checker
    down = Pose.from_rpy([0, 0, 0], [math.pi, 0, 0]).rotation

    def random_config() -> np.ndarray:
        while True:
            r, a = rng.uniform(0.2, 0.45), rng.uniform(-math.pi, math.pi)
            p = [r * math.cos(a), r * math.sin(a), rng.uniform(0.03, 0.35)]
            yaw = Pose.from_rpy([0, 0, 0], [0, 0, rng.uniform(-math.pi, math.pi)]).rotation
            sols = kin.inverse_all(Pose(p, down @ yaw), seed=np.array(CONFIG.home))
            free = [q for q in sols if not checker.in_collision(q)]
            if free:
                return free[int(rng.integers(len(free)))]

    out = [("random", random_config(), random_config()) for _ in range(n)]
    left = np.array([-1.042, -1.271, 1.482, -1.781, -1.571, 2.099])
    right = np.array([-2.792, -1.255, 1.46, -1.776, -1.571, 0.35])
    for k in range(blocked):
        a, b = (left, right) if k % 2 == 0 else (right, left)
        jitter = rng.uniform(-0.05, 0.05, 6)
        if not checker.in_collision(a + jitter) and not checker.in_collision(b - jitter):
            out.append(("machine", a + jitter, b - jitter))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument("--blocked", type=int, default=40)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()

    planner = MotionPlanner(CONFIG)
    qs = queries(planner, args.queries, args.blocked, args.seed)
    limits = Limits.from_config(CONFIG.limits)
    peer = JointPlanner(
        planner.checker, CONFIG.limits.position_min, CONFIG.limits.position_max,
        simplify_timeout=1.0, window=math.inf, planner_range=0.0,
    )  # fmt: skip

    ours: dict[str, list[float]] = {"random": [], "machine": []}
    theirs: dict[str, list[float]] = {"random": [], "machine": []}
    failures: list[str] = []
    direct = 0
    for kind, a, b in qs:
        t0 = time.perf_counter()
        try:
            plan = planner.plan_joint(a, b)
            ours[kind].append(time.perf_counter() - t0)
            direct += plan.planner == "direct"
        except FxcellError as exc:
            failures.append(f"ours {kind}: {type(exc).__name__}: {exc}")
        t0 = time.perf_counter()
        try:
            path = peer._search(a, b, 1.0, None)[0]  # OMPL every time, its own simplifier
            through_waypoints(path, limits, validate=planner.checker.first_collision)
            theirs[kind].append(time.perf_counter() - t0)
        except FxcellError as exc:
            failures.append(f"peer {kind}: {type(exc).__name__}: {exc}")

    def row(name: str, values: list[float]) -> str:
        if not values:
            return f"{name:34s} (none)"
        ms = [v * 1e3 for v in values]
        return (
            f"{name:34s} n={len(ms):4d}  median {statistics.median(ms):7.2f} ms  "
            f"p99 {pct(ms, 0.99):7.2f} ms  max {max(ms):7.2f} ms"
        )

    everything = ours["random"] + ours["machine"]
    peer_all = theirs["random"] + theirs["machine"]
    n_random, n_machine = len(ours["random"]), len(ours["machine"])
    print(f"cell scene: {len(CONFIG.scene.objects)} boxes + UR3e capsules + Hand-E gripper")
    print(f"{len(qs)} queries: {n_random} random pairs, {n_machine} through the machine")
    print(row("fxcell plan_joint, all", everything))
    print(row("fxcell plan_joint, random pairs", ours["random"]))
    print(row("fxcell plan_joint, machine-blocked", ours["machine"]))
    print(row("peer OMPL+simplify+Ruckig, all", peer_all))
    print(row("peer, machine-blocked", theirs["machine"]))
    print(f"direct line taken: {direct}/{len(everything)}")
    if everything and peer_all:
        ratio = statistics.median(peer_all) / statistics.median(everything)
        print(f"median speed-up vs peer: {ratio:.1f}x")
    worst = max(everything) if everything else math.inf
    ours_failed = [f for f in failures if f.startswith("ours")]
    median_ok = bool(everything) and statistics.median(everything) <= 0.020
    all_ok = not ours_failed and worst <= 1.0
    print(f"target median <= 20 ms: {'met' if median_ok else 'NOT met'}")
    print(f"target every feasible query within 1 s: {'met' if all_ok else 'NOT met'}")
    for f in failures[:10]:
        print("failure:", f)


if __name__ == "__main__":
    main()
