"""Joint-move planning in the cell scene: feasible, infeasible and uniform random queries.

Scene: config/scene.yaml (table, fusion machine) with the UR3e capsules and the Hand-E.
Each query goes through ``MotionPlanner.plan_joint``: collision checks, the direct line
if free, the free-space walls (a joint value at which every configuration collides), else
OMPL RRTConnect (1 s budget), shortcutting, a fine re-check, Ruckig timing.

Query sets (seeded):

- ``work``: pairs of random collision-free configurations with the gripper pointing
  down over the table or the machine (the cell's working space, IK from random poses);
- ``machine``: random pairs on opposite sides of the fusion machine (gripper low, left
  and right of it), most of whose straight lines run through it;
- ``infeasible``: a collision-free configuration and the same arm pose with the shoulder
  (θ2) or the elbow (θ3) turned a full turn: joint space is not a circle (±2π limits),
  so any path must swing the upper arm through the table (θ2 = π/2) or fold the forearm
  through the upper arm (θ3 = ±π) — infeasible by geometry, not by fxcell's word;
- ``uniform``: pairs of collision-free configurations uniform within the joint limits,
  feasibility unknown: reported (solved, proven infeasible, failed at the budget).

Peer, same run: the plain OMPL pipeline on the work and machine queries — RRTConnect on
every query (no direct line, no walls), OMPL's ``simplifySolution``, the same Ruckig
timing.

Targets: every work and machine query solved (within 1 s) and their median <= 20 ms;
every infeasible query refused in <= 50 ms.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np
from _harness import Targets

from fxcell.config import CellConfig
from fxcell.errors import FxcellError
from fxcell.geometry import Pose
from fxcell.link.capabilities import UR3E
from fxcell.motion.moves import MotionPlanner
from fxcell.motion.planning import JointPlanner
from fxcell.motion.trajectory import Limits, through_waypoints

CONFIG = CellConfig.load()
Query = tuple[str, np.ndarray, np.ndarray]


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(int(q * len(s)), len(s) - 1)]


def queries(planner: MotionPlanner, n: int, seed: int) -> dict[str, list[Query]]:
    rng = np.random.default_rng(seed)
    kin, checker = planner.kinematics, planner.checker
    lo, hi = np.array(CONFIG.limits.position_min), np.array(CONFIG.limits.position_max)
    down = Pose.from_rpy([0, 0, 0], [math.pi, 0, 0]).rotation

    def at(p: list[float]) -> np.ndarray | None:
        yaw = Pose.from_rpy([0, 0, 0], [0, 0, rng.uniform(-math.pi, math.pi)]).rotation
        sols = kin.inverse_all(Pose(p, down @ yaw), seed=np.array(CONFIG.home))
        free = [q for q in sols if not checker.in_collision(q)]
        return free[int(rng.integers(len(free)))] if free else None

    def work() -> np.ndarray:
        while True:
            r, a = rng.uniform(0.2, 0.45), rng.uniform(-math.pi, math.pi)
            q = at([r * math.cos(a), r * math.sin(a), rng.uniform(0.03, 0.35)])
            if q is not None:
                return q

    def beside_machine(side: float) -> np.ndarray:
        # the machine spans x in [-0.2, 0.2] at y >= 0.295 (scene.yaml): low beside it
        while True:
            x = side * rng.uniform(0.27, 0.4)
            q = at([x, rng.uniform(0.22, 0.4), rng.uniform(0.04, 0.15)])
            if q is not None:
                return q

    def uniform() -> np.ndarray:
        while True:
            q = rng.uniform(lo, hi)
            if not checker.in_collision(q):
                return q

    def turned(q: np.ndarray) -> Query | None:
        joint = int(rng.integers(1, 3))
        other = q.copy()
        other[joint] += 2 * math.pi if q[joint] < 0 else -2 * math.pi
        if checker.in_collision(other):
            return None  # cannot happen for the same pose; kept as a guard
        return (f"infeasible θ{joint + 1}", q, other)

    out: dict[str, list[Query]] = {
        "work": [("work", work(), work()) for _ in range(n)],
        "machine": [],
        "infeasible": [],
        "uniform": [("uniform", uniform(), uniform()) for _ in range(n // 4)],
    }
    for k in range(n // 4):
        a, b = beside_machine(1.0), beside_machine(-1.0)
        out["machine"].append(("machine", a, b) if k % 2 else ("machine", b, a))
    while len(out["infeasible"]) < n // 4:
        if (item := turned(work())) is not None:
            out["infeasible"].append(item)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--queries", type=int, default=200, help="work pairs; others n/4")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()

    planner = MotionPlanner(CONFIG)
    sets = queries(planner, args.queries, args.seed)
    limits = Limits.from_config(CONFIG.limits, period=UR3E.sample_period)
    peer = JointPlanner(
        planner.checker, CONFIG.limits.position_min, CONFIG.limits.position_max,
        simplify_timeout=1.0, window=math.inf, planner_range=0.0,
    )  # fmt: skip

    ours: dict[str, list[float]] = {k: [] for k in sets}
    failed: dict[str, list[float]] = {k: [] for k in sets}
    theirs: list[float] = []
    peer_failed = 0
    direct = 0
    notes: list[str] = []
    for name, items in sets.items():
        for _kind, a, b in items:
            t0 = time.perf_counter()
            try:
                plan = planner.plan_joint(a, b)
                ours[name].append(time.perf_counter() - t0)
                direct += plan.planner == "direct"
            except FxcellError as exc:
                failed[name].append(time.perf_counter() - t0)
                if name in ("work", "machine"):
                    notes.append(f"ours {name}: {type(exc).__name__}: {exc}")
            if name not in ("work", "machine"):
                continue
            t0 = time.perf_counter()
            try:
                path = peer._search(a, b, 1.0, None)[0]  # OMPL every time, its own simplifier
                through_waypoints(path, limits, validate=planner.checker.first_collision)
                theirs.append(time.perf_counter() - t0)
            except FxcellError:
                peer_failed += 1

    def row(name: str, values: list[float]) -> str:
        if not values:
            return f"{name:40s} (none)"
        ms = [v * 1e3 for v in values]
        return (
            f"{name:40s} n={len(ms):4d}  median {statistics.median(ms):7.2f} ms  "
            f"p99 {pct(ms, 0.99):7.2f} ms  max {max(ms):7.2f} ms"
        )

    feasible = ours["work"] + ours["machine"]
    n_feasible = len(sets["work"]) + len(sets["machine"])
    print(f"cell scene: {len(CONFIG.scene.objects)} boxes + UR3e capsules + Hand-E gripper")
    print(f"walls of the free space (joint index, rad): {planner.checker.walls()}")
    print(row("fxcell, work pairs solved", ours["work"]))
    print(row("fxcell, machine pairs solved", ours["machine"]))
    print(row("fxcell, infeasible pairs refused", failed["infeasible"]))
    print(row("fxcell, infeasible pairs 'solved' (!)", ours["infeasible"]))
    print(row("peer OMPL+simplify+Ruckig, work+machine", theirs))
    print(f"direct line taken: {direct}/{len(feasible)} solved work+machine queries")
    fast = sum(1 for t in failed["uniform"] if t <= 0.05)
    print(
        f"uniform pairs: {len(ours['uniform'])}/{len(sets['uniform'])} solved, "
        f"{fast} proven infeasible in <= 50 ms, {len(failed['uniform']) - fast} failed "
        f"after the search budget"
    )
    print(row("  uniform, solved", ours["uniform"]))
    print(row("  uniform, failed", failed["uniform"]))
    for note in notes[:10]:
        print("failure:", note)

    targets = Targets("planning")
    peer_median = statistics.median(theirs) * 1e3 if theirs else None
    targets.check(
        "work+machine queries solved", 100 * len(feasible) / n_feasible, "==", 100.0, "%",
        peer=100 * len(theirs) / n_feasible, peer_name="plain OMPL",
    )  # fmt: skip
    targets.check(
        "work+machine median", statistics.median(feasible) * 1e3 if feasible else math.inf,
        "<=", 20.0, "ms", peer=peer_median, peer_name="plain OMPL",
    )  # fmt: skip
    targets.check(
        "work+machine max (within the 1 s budget)",
        max(feasible) * 1e3 if feasible else math.inf, "<=", 1000.0, "ms",
    )  # fmt: skip
    n_inf = len(sets["infeasible"])
    refused_fast = sum(1 for t in failed["infeasible"] if t <= 0.05)
    targets.check(
        "infeasible refused in <= 50 ms", 100 * refused_fast / n_inf, "==", 100.0, "%",
    )  # fmt: skip
    return targets.finish()


if __name__ == "__main__":
    raise SystemExit(main())
