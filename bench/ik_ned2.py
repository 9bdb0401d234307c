"""Inverse kinematics of the Niryo Ned2 on random reachable poses, against a dense
reference and a generic solver measured in the same run.

Poses: joint vectors uniform within the Ned2's limits → forward kinematics; each is solved
from a random seed (uniform within the limits) by:

- ``fxcell``: ``fxcell.motion.ned2.inverse(pose, seed)`` (batched damped least squares
  from the seed and 288 branch seeds; every converged solution within the limits, the one
  nearest the seed returned);
- ``pinocchio CLIK``: damped least squares on the shipped URDF's ``tool_link`` (``log6``
  error, damping 1e-10), clamped to the limits, restarts from random configurations after
  100 iterations, 50 ms budget per pose: a generic solver that returns the first solution
  it finds, not the nearest;
- ``dense reference``: ``inverse`` with 400 more uniform random starts and 120
  iterations: the solution nearest the seed that a dense search finds.

Solved = position error < 1e-6 m and rotation error < 1e-6 rad (by fxcell's forward
kinematics) and every joint within the limits. "Nearest" = fxcell's solution is no
farther from the seed (Euclidean, rad) than the dense reference's (+1e-4: the same
solution). The three take turns pose by pose, so machine noise hits them alike. Each call
is timed alone.

Targets: 100 % solved, 100 % nearest (issue 29); fxcell's median and p99 are printed
beside CLIK's (a ratio, no bound: CLIK answers with any solution, fxcell with the
nearest).

    ./dev bench ik_ned2 [--poses N]     (also the last rows of ./dev bench ik)
"""

from __future__ import annotations

import argparse
import gc
import statistics
import time

import numpy as np
import pinocchio as pin
from _harness import Targets

from fxcell.motion import ned2

TOL = 1e-6
# two solutions closer than this (rad) are one: near a wrist singularity the solver stops
# within 1e-7 m/rad of the pose while the joints still differ by ~1e-5
SAME = 1e-4


class Clik:
    """Pinocchio closed-loop IK (damped least squares) with random restarts."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.model = pin.buildModelFromXML(ned2.urdf())
        self.data = self.model.createData()
        self.fid = self.model.getFrameId("tool_link")
        self.rng = rng

    def solve(
        self, target: pin.SE3, seed: np.ndarray, *, iterations: int = 100, budget: float = 0.05
    ) -> np.ndarray | None:
        model, data, fid = self.model, self.data, self.fid
        deadline = time.perf_counter() + budget
        q = seed.copy()
        eye = np.eye(6)
        while True:
            for _ in range(iterations):
                pin.forwardKinematics(model, data, q)
                pin.updateFramePlacement(model, data, fid)
                i_m_d = data.oMf[fid].actInv(target)
                err = pin.log6(i_m_d).vector
                if np.linalg.norm(err[:3]) < 1e-9 and np.linalg.norm(err[3:]) < 1e-9:
                    return q
                jac = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL)
                jac = -pin.Jlog6(i_m_d.inverse()) @ jac
                q = np.clip(q - jac.T @ np.linalg.solve(jac @ jac.T + 1e-10 * eye, err),
                            ned2.LOWER, ned2.UPPER)  # fmt: skip
            if time.perf_counter() > deadline:
                return None
            q = self.rng.uniform(ned2.LOWER, ned2.UPPER)


def _solved(q: np.ndarray | None, target: np.ndarray) -> bool:
    if q is None or not ned2.within_limits(q):
        return False
    t = ned2.forward(q)
    return bool(
        np.linalg.norm(t[:3, 3] - target[:3, 3]) < TOL
        and np.abs(t[:3, :3] - target[:3, :3]).max() < TOL
    )


def _ms(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) * 1e3


def measure(poses: int) -> dict[str, object]:
    """Solve ``poses`` random reachable poses with the three solvers, taking turns."""
    rng = np.random.default_rng(29)
    clik = Clik(np.random.default_rng(30))
    dense_starts = np.random.default_rng(31).uniform(ned2.LOWER, ned2.UPPER, size=(400, 6))
    qs = rng.uniform(ned2.LOWER, ned2.UPPER, size=(poses, 6))
    seeds = rng.uniform(ned2.LOWER, ned2.UPPER, size=(poses, 6))
    times: dict[str, list[float]] = {"fxcell": [], "clik": [], "reference": []}
    solved = dict.fromkeys(times, 0)
    nearest = 0
    gc.disable()
    try:
        for q, seed in zip(qs, seeds, strict=True):
            target = ned2.forward(q)
            se3 = pin.SE3(target[:3, :3].copy(), target[:3, 3].copy())
            t0 = time.perf_counter()
            ours = ned2.inverse(target, seed).q
            t1 = time.perf_counter()
            generic = clik.solve(se3, seed)
            t2 = time.perf_counter()
            ref = ned2.inverse(target, seed, extra_seeds=dense_starts, iterations=120).q
            t3 = time.perf_counter()
            times["fxcell"].append(t1 - t0)
            times["clik"].append(t2 - t1)
            times["reference"].append(t3 - t2)
            for name, sol in (("fxcell", ours), ("clik", generic), ("reference", ref)):
                solved[name] += _solved(sol, target)
            if ours is not None and ref is not None:
                nearest += bool(np.linalg.norm(ours - seed) <= np.linalg.norm(ref - seed) + SAME)
    finally:
        gc.enable()
    return {"poses": poses, "times": times, "solved": solved, "nearest": nearest}


def report(result: dict[str, object], targets: Targets) -> None:
    """Print the table and check the targets (rows ``ned2 ...``) into ``targets``."""
    n = int(result["poses"])  # type: ignore[call-overload]
    times: dict[str, list[float]] = result["times"]  # type: ignore[assignment]
    solved: dict[str, int] = result["solved"]  # type: ignore[assignment]
    nearest = int(result["nearest"])  # type: ignore[call-overload]
    print(f"Ned2 IK on {n} random reachable poses, seeds uniform within the limits")
    print(f"{'solver':<16}{'solved':>9}{'median ms':>12}{'p99 ms':>10}")
    for name, label in (("fxcell", "fxcell"), ("clik", "pinocchio CLIK"),
                        ("reference", "dense reference")):  # fmt: skip
        print(
            f"{label:<16}{100.0 * solved[name] / n:>8.1f}%"
            f"{_ms(times[name], 50):>12.2f}{_ms(times[name], 99):>10.2f}"
        )
    print(f"fxcell nearest the seed as the dense reference: {100.0 * nearest / n:.1f} %")
    median_ratio = statistics.median(times["fxcell"]) / statistics.median(times["clik"])
    print(f"fxcell median / CLIK median: {median_ratio:.2f}")
    targets.check("ned2 solved (fxcell)", 100.0 * solved["fxcell"] / n, ">=", 100.0, "%")
    targets.check("ned2 nearest the seed (vs dense)", 100.0 * nearest / n, ">=", 100.0, "%")
    targets.check(
        "ned2 median (fxcell)",
        _ms(times["fxcell"], 50),
        "<=",
        50.0,
        "ms",
        peer=_ms(times["clik"], 50),
        peer_name="pinocchio CLIK",
    )
    targets.check(
        "ned2 p99 (fxcell)",
        _ms(times["fxcell"], 99),
        "<=",
        100.0,
        "ms",
        peer=_ms(times["clik"], 99),
        peer_name="pinocchio CLIK",
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=200)
    args = parser.parse_args()
    targets = Targets("ik_ned2")
    report(measure(args.poses), targets)
    return targets.finish()


if __name__ == "__main__":
    raise SystemExit(main())
