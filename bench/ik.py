"""Inverse kinematics of the UR3e on random reachable poses, against two peers.

Poses: joint vectors of five families → forward kinematics → inverse kinematics from a
random seed (uniform within the limits). Families: ``uniform`` within the joint limits
(±2π); near each UR singularity — ``wrist`` (θ5 ≈ 0 or ±π), ``elbow`` (θ3 ≈ 0, full
stretch), ``shoulder`` (wrist centre on the plane of axes 1 and 2, θ2 found by bisection)
— at log-uniform distances from 1e-9 to 1e-2 (5 % exactly on it); ``limits``: 1 to 3
joints within 1e-2 rad of ±2π. The solvers take turns
by blocks of 250 poses in one loop, so machine noise hits them alike (``--interleave``:
turns at every pose, which leaves every call with cold caches):

- ``fxcell``: ``Kinematics.inverse(pose, seed)`` (closed form, nearest solution to the seed);
- ``ur_analytic_ik``: ``inverse_kinematics_closest`` (C++ via nanobind). It uses UR's base
  frame and the same UR3e parameters as fxcell (its forward kinematics is checked to agree
  to 1e-12 below), so no ``base_link`` conversion is needed; the TCP case uses its
  ``*_with_tcp`` variant with the 4×4 TCP matrix;
- ``pinocchio CLIK``: damped least squares on the Pinocchio model's TCP frame (``log6``
  error, Newton steps, damping 1e-10), restarts from random configurations after 100
  iterations, 50 ms budget per pose.

Solved = position error < 1e-6 m, rotation error < 1e-6 rad (checked with fxcell's forward
kinematics) and every joint within ±2π. Each call is timed alone (perf_counter_ns, GC off);
the pose is built beforehand in each solver's own input type (fxcell ``Pose``, 4×4 array).
A second figure, the mean per call over the least disturbed of 20 passes of 1000 poses, is
less sensitive to other processes on a busy machine than the per-call median.

fxcell's figures are those of the module in use, which the first line of output names:
compiled with mypyc (``./dev`` builds it, see ``hatch_build.py``) or interpreted.

Targets: 100 % solved and p99 ≤ 100 µs in every family (ur_analytic_ik's figures beside);
on the uniform family, fxcell median ≤ 1.5 × ur_analytic_ik's (issue 5).

Calibrated arm (issues 14, 26): a factory calibration with random deltas up to 2 mm and
0.002 rad; poses of each family made by its forward kinematics, solved by
``CalibratedKinematics.inverse`` (the nominal closed form's branches refined by Newton steps
on the calibrated chain, next to the wrist singularity searched along the self-motion; the
whole hot path one call in C, ``fxcell/motion/_dhchain.c``) and, in the same loop, by
``ur_analytic_ik`` on the nominal model (for the time; its solutions miss the calibrated
poses). Targets per family: 100 % solved, 100 %
nearest the seed against a reference (on the first ``--reference`` poses: the thorough search
of ``inverse_all``, the joints the pose was made from and, next to the wrist singularity, a
dense search along the wrist's self-motion, ``_self_motion_roots``), median ≤ 1.5 ×
ur_analytic_ik's, p99 ≤ 200 µs, max ≤ 2 ms. ``inverse_all`` walks the same valleys as the
solver and misses the same solutions there; the dense search finds most of them.

    ./dev bench ik [--poses N] [--tcp flange|seed|both] [--family F ...] [--clik-poses N]
                   [--interleave] [--reference N] [--ned2-poses N]

The last rows are the Niryo Ned2's (``bench/ik_ned2.py``: its solver against a dense
reference and pinocchio's generic CLIK, in the same run).
"""

from __future__ import annotations

import argparse
import gc
import math
import statistics
import time
from collections.abc import Callable
from importlib.machinery import EXTENSION_SUFFIXES

import ik_ned2
import numpy as np
import pinocchio as pin
import ur_analytic_ik
from _harness import Targets

from fxcell.calibration import Calibration
from fxcell.config import SEED_TCP, JointLimits
from fxcell.errors import UnreachableError
from fxcell.geometry import Pose
from fxcell.motion import calibration, kinematics
from fxcell.motion.calibration import CalibratedKinematics
from fxcell.motion.kinematics import Kinematics
from fxcell.motion.robot_model import RobotModel

TOL = 1e-6
BLOCK = 250
Solver = Callable[[int], "np.ndarray | None"]


class Clik:
    """Pinocchio closed-loop IK (damped least squares) with random restarts."""

    def __init__(self, robot: RobotModel, rng: np.random.Generator) -> None:
        self.model = robot.model
        self.data = self.model.createData()
        self.fid = robot.tcp_frame_id
        self.rng = rng
        self.lo = self.model.lowerPositionLimit
        self.hi = self.model.upperPositionLimit

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
                iMd = data.oMf[fid].actInv(target)
                err = pin.log6(iMd).vector
                if np.linalg.norm(err[:3]) < 1e-9 and np.linalg.norm(err[3:]) < 1e-9:
                    return np.mod(q + np.pi, 2 * np.pi) - np.pi  # wrap into the limits
                J = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL)
                J = -pin.Jlog6(iMd.inverse()) @ J
                q = q - J.T @ np.linalg.solve(J @ J.T + 1e-10 * eye, err)
            if time.perf_counter() > deadline:
                return None
            q = self.rng.uniform(self.lo, self.hi)


FAMILIES = ("uniform", "wrist", "elbow", "shoulder", "limits")


def _offsets(rng: np.random.Generator, n: int) -> np.ndarray:
    """Signed distances from a singularity or limit: log-uniform in [1e-9, 1e-2], 5 % zero."""
    d = 10.0 ** rng.uniform(-9, -2, n) * rng.choice((-1.0, 1.0), n)
    d[rng.random(n) < 0.05] = 0.0
    return d


def _shoulder_offset(kin: Kinematics, q: np.ndarray) -> float:
    """Signed distance (m) of the wrist centre from the plane of axes 1 and 2."""
    f = kin.forward_flange(q).matrix
    d6 = kin.dh.d[5]
    x5, y5 = f[0, 3] - d6 * f[0, 2], f[1, 3] - d6 * f[1, 2]
    return math.cos(q[0]) * x5 + math.sin(q[0]) * y5


def family_configs(
    family: str, kin: Kinematics, rng: np.random.Generator, n: int, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """``n`` joint vectors of a family: uniform within the limits, or near a singularity
    (wrist θ5 ≈ 0 or ±π, elbow θ3 ≈ 0, wrist centre on the plane of the shoulder axes)
    or near the joint limits (1 to 3 joints within 1e-2 rad of ±2π)."""
    qs = rng.uniform(lo, hi, size=(n, 6))
    offsets = _offsets(rng, n)
    if family == "wrist":
        qs[:, 4] = rng.choice((0.0, math.pi, -math.pi), n) + offsets
    elif family == "elbow":
        qs[:, 2] = offsets
    elif family == "shoulder":
        for i in range(n):
            q = qs[i]
            while True:  # θ2 where the wrist centre crosses the plane, found by bisection
                grid = np.linspace(-math.pi, math.pi, 65)
                g = []
                for t in grid:
                    q[1] = t
                    g.append(_shoulder_offset(kin, q))
                cross = [k for k in range(64) if g[k] * g[k + 1] < 0]
                if cross:
                    break
                q[:] = rng.uniform(lo, hi)
            a, b = grid[cross[0]], grid[cross[0] + 1]
            ga = g[cross[0]]
            for _ in range(60):
                q[1] = 0.5 * (a + b)
                gm = _shoulder_offset(kin, q)
                if gm * ga > 0:
                    a, ga = q[1], gm
                else:
                    b = q[1]
            q[1] += offsets[i]
    elif family == "limits":
        for i in range(n):
            joints = rng.choice(6, size=int(rng.integers(1, 4)), replace=False)
            for j in joints:
                side = rng.choice((-1.0, 1.0))
                qs[i, j] = side * (2 * math.pi - abs(_offsets(rng, 1)[0]))
    elif family != "uniform":
        raise ValueError(f"unknown family {family!r}")
    return qs


def _summary(name: str, times_ns: list[int], solved: int, attempted: int) -> dict[str, float]:
    us = sorted(t / 1000.0 for t in times_ns)
    med = statistics.median(us)
    p99 = us[min(len(us) - 1, int(0.99 * len(us)))]
    rate = 100.0 * solved / attempted
    print(
        f"  {name:<16} solved {solved:>6}/{attempted:<6} ({rate:7.3f} %)   "
        f"median {med:8.2f} µs   p99 {p99:8.2f} µs   max {us[-1]:9.1f} µs"
    )
    return {"median": med, "p99": p99, "rate": rate}


def run(
    tcp_name: str, family: str, n: int, n_clik: int, seed: int, interleave: bool = False
) -> dict[str, dict[str, float]]:
    tcp = None if tcp_name == "flange" else SEED_TCP
    rng = np.random.default_rng(seed)
    limits = JointLimits()
    lo, hi = np.array(limits.position_min), np.array(limits.position_max)
    kin = Kinematics.ur3e(tcp, limits)
    robot = RobotModel.ur3e(tcp, limits)
    tcp_matrix = np.ascontiguousarray(kin.tcp.matrix)
    ur = ur_analytic_ik.ur3e

    qs = family_configs(family, kin, rng, n, lo, hi)
    seeds = rng.uniform(lo, hi, size=(n, 6))
    poses = [kin.forward(q) for q in qs]
    matrices = [np.ascontiguousarray(p.matrix) for p in poses]
    se3s = [pin.SE3(p.rotation.copy(), p.position.copy()) for p in poses]
    seed_lists = [s.tolist() for s in seeds]

    # the peer's frame and parameters are fxcell's: its flange FK equals ours
    fk_gap = max(
        float(np.abs(ur.forward_kinematics(*q) - kin.forward_flange(q).matrix).max())
        for q in qs[:200]
    )
    assert fk_gap < 1e-12, f"ur_analytic_ik forward kinematics differs by {fk_gap}"

    def ours(i: int) -> np.ndarray | None:
        try:
            return kin.inverse(poses[i], seed_lists[i])
        except UnreachableError:
            return None

    if tcp is None:

        def peer(i: int) -> np.ndarray | None:
            sols = ur.inverse_kinematics_closest(matrices[i], *seed_lists[i])
            return sols[0] if sols else None
    else:

        def peer(i: int) -> np.ndarray | None:
            sols = ur.inverse_kinematics_closest_with_tcp(matrices[i], tcp_matrix, *seed_lists[i])
            return sols[0] if sols else None

    clik = Clik(robot, np.random.default_rng(seed + 1))

    def clik_solve(i: int) -> np.ndarray | None:
        return clik.solve(se3s[i], seeds[i])

    solvers: list[tuple[str, Solver, int]] = [
        ("fxcell", ours, n),
        ("ur_analytic_ik", peer, n),
    ]
    if n_clik:
        solvers.append(("pinocchio CLIK", clik_solve, min(n_clik, n)))
    times: dict[str, list[int]] = {name: [] for name, _, _ in solvers}
    results_q: dict[str, list[np.ndarray | None]] = {name: [] for name in times}
    for _name, fn, count in solvers:  # warm-up
        for i in range(min(count, 50)):
            fn(i)
    # Every call is timed on its own. By default the solvers take turns by blocks of poses
    # (as an application calls IK many times in a row, e.g. along a path); --interleave
    # switches solver at every pose instead, so each call starts with cold caches.
    step = 1 if interleave else BLOCK
    gc.collect()
    gc.disable()
    try:
        for start in range(0, n, step):
            for name, fn, count in solvers:
                for i in range(start, min(start + step, count)):
                    t0 = time.perf_counter_ns()
                    q = fn(i)
                    times[name].append(time.perf_counter_ns() - t0)
                    results_q[name].append(q)
    finally:
        gc.enable()
    solved = {}
    for name, found in results_q.items():
        solved[name] = sum(
            1 for i, q in enumerate(found) if q is not None and _is_solution(kin, q, poses[i])
        )

    # second view: mean per call over passes of 1000 poses, the best of 20 passes taken
    # alternately by the two closed forms (the least disturbed pass of each)
    m = min(n, 1000)
    batch = dict.fromkeys(("fxcell", "ur_analytic_ik"), math.inf)
    for _ in range(20):
        for name, fn, _count in solvers[:2]:
            t0 = time.perf_counter_ns()
            for i in range(m):
                fn(i)
            batch[name] = min(batch[name], (time.perf_counter_ns() - t0) / m / 1000.0)

    mode = "solvers interleaved per pose" if interleave else f"solvers in turns of {BLOCK} poses"
    print(
        f"\nTCP = {tcp_name}, family {family}: {n} reachable poses, random seeds within ±2π "
        f"({mode})"
    )
    results = {name: _summary(name, times[name], solved[name], count) for name, _, count in solvers}
    ratio = results["fxcell"]["median"] / results["ur_analytic_ik"]["median"]
    clik = ""
    if "pinocchio CLIK" in results:
        clik_ratio = results["fxcell"]["median"] / results["pinocchio CLIK"]["median"]
        clik = f"   fxcell / CLIK = {clik_ratio:.3f}"
    print(f"  median ratio fxcell / ur_analytic_ik = {ratio:.2f}{clik}")
    print(
        f"  best-pass mean per call: fxcell {batch['fxcell']:.2f} µs, ur_analytic_ik "
        f"{batch['ur_analytic_ik']:.2f} µs, ratio {batch['fxcell'] / batch['ur_analytic_ik']:.2f}"
    )
    return results


def run_calibrated(
    tcp_name: str, family: str, n: int, seed: int, reference: int
) -> dict[str, dict[str, float]]:
    """Reachable poses of a calibrated arm, one family: the calibrated solver and
    ur_analytic_ik (on the nominal model: the same poses, for the time) in turns by blocks;
    the calibrated solutions checked against a reference on the first ``reference`` poses."""
    tcp = None if tcp_name == "flange" else SEED_TCP
    rng = np.random.default_rng(seed + 14)
    limits = JointLimits()
    lo, hi = np.array(limits.position_min), np.array(limits.position_max)

    def deltas(bound: float) -> tuple[float, ...]:
        return tuple(rng.uniform(-bound, bound, 6).tolist())

    calibration = Calibration(deltas(0.002), deltas(0.002), deltas(0.002), deltas(0.002))
    kin = CalibratedKinematics.ur3e_calibrated(calibration, tcp, limits)
    ur = ur_analytic_ik.ur3e
    tcp_matrix = np.ascontiguousarray(kin.tcp.matrix)
    qs = family_configs(family, kin, rng, n, lo, hi)
    seeds = rng.uniform(lo, hi, size=(n, 6))
    poses = [kin.forward(q) for q in qs]
    matrices = [np.ascontiguousarray(p.matrix) for p in poses]
    seed_lists = [s.tolist() for s in seeds]

    def ours(i: int) -> np.ndarray | None:
        try:
            return kin.inverse(poses[i], seed_lists[i])
        except UnreachableError:
            return None

    def peer(i: int) -> np.ndarray | None:
        sols = ur.inverse_kinematics_closest_with_tcp(matrices[i], tcp_matrix, *seed_lists[i])
        return sols[0] if sols else None

    solvers: list[tuple[str, Solver]] = [("fxcell calibrated", ours), ("ur_analytic_ik", peer)]
    times: dict[str, list[int]] = {name: [] for name, _ in solvers}
    found: dict[str, list[np.ndarray | None]] = {name: [] for name in times}
    for _name, fn in solvers:
        for i in range(min(n, 50)):
            fn(i)
    kin.fallbacks = 0
    gc.collect()
    gc.disable()
    try:
        for start in range(0, n, BLOCK):
            for name, fn in solvers:
                for i in range(start, min(start + BLOCK, n)):
                    t0 = time.perf_counter_ns()
                    q = fn(i)
                    times[name].append(time.perf_counter_ns() - t0)
                    found[name].append(q)
    finally:
        gc.enable()
    fallbacks = kin.fallbacks
    # Reference: every calibrated solution the thorough search finds (each nominal branch of
    # the target, of the seed-corrected target and of targets moved and turned at the edge
    # of the workspace, refined), those of the dense search along the wrist's self-motion,
    # and the joints the pose was made from, each joint shifted by 2π toward the seed.
    # Nearest = no reference solution nearer by over 1e-7 rad.
    farther = 0
    checked = min(n, reference)
    for i in range(checked):
        q = found["fxcell calibrated"][i]
        if q is None:
            continue
        s = seeds[i]
        own = np.array([_toward(v, t) for v, t in zip(qs[i], s, strict=True)])
        refs = [*kin.inverse_all(poses[i], s), *_self_motion_roots(kin, poses[i], s), own]
        best = min(float(np.linalg.norm(r - s)) for r in refs)
        if float(np.linalg.norm(q - s)) > best + 1e-7:
            farther += 1
    print(
        f"\nCalibrated arm (deltas ≤ 2 mm, 0.002 rad; checksum {calibration.checksum}), "
        f"TCP = {tcp_name}, family {family}: {n} reachable poses, random seeds within ±2π"
    )
    results = {}
    for name, _ in solvers:
        solved = sum(
            1 for i, q in enumerate(found[name]) if q is not None and _is_solution(kin, q, poses[i])
        )
        results[name] = _summary(name, times[name], solved, n)
    results["fxcell calibrated"]["max"] = max(times["fxcell calibrated"]) / 1000.0
    results["fxcell calibrated"]["nearest"] = 100.0 * (checked - farther) / max(checked, 1)
    misses = [
        kin.forward(q).distance(poses[i])
        for i, q in enumerate(found["ur_analytic_ik"])
        if q is not None
    ]
    ratio = results["fxcell calibrated"]["median"] / results["ur_analytic_ik"]["median"]
    print(
        f"  median ratio fxcell calibrated / ur_analytic_ik (nominal) = {ratio:.2f}; "
        f"the nominal solutions miss by median {1e3 * statistics.median(misses):.2f} mm; "
        + (
            f"nearest the seed: {checked - farther}/{checked} against the reference; "
            if checked
            else "nearest the seed: not checked (--reference 0); "
        )
        + f"general path (hot path gave up): {fallbacks}/{n}"
    )
    return results


SELF_MOTION_STEP = 0.1
"""rad: the spacing of the dense reference's starts along the wrist's self-motion."""
SELF_MOTION_NEAR = 0.2
"""|sin θ5| of a nominal branch below which the dense reference searches its self-motion."""


def _self_motion_roots(kin: CalibratedKinematics, pose: Pose, seed: np.ndarray) -> list[np.ndarray]:
    """The calibrated reference's dense search next to the wrist singularity: from each
    nominal branch of ``pose`` and of the seed-corrected target (``nominal_target``) with
    |sin θ5| below SELF_MOTION_NEAR, starts turned along the wrist's self-motion (θ4 and θ6
    turning together, both ways) every SELF_MOTION_STEP over a whole turn, each refined by
    Levenberg-Marquardt (``solve(patient=True)``), each joint shifted toward ``seed``.

    The valley walks of the solver and of ``inverse_all`` miss solutions closer together
    than their points or next to the arm's fold; this finds most of them (bench's wrist
    family, seed TCP, --seed 1, first 100 poses: the joints a pose was made from were among
    its solutions for 88, among ``inverse_all``'s for 43), at ~50 ms per such pose."""
    s = seed.tolist()
    roots: list[np.ndarray] = []
    for target in (pose, kin.nominal_target(pose, seed)):
        for branch in kin.nominal.inverse_all(target, seed):
            if abs(math.sin(branch[4])) >= SELF_MOTION_NEAR:
                continue
            for turn in np.arange(0.0, 2.0 * math.pi, SELF_MOTION_STEP):
                for sign in (1.0, -1.0):
                    start = branch.copy()
                    start[3] += turn
                    start[5] -= sign * turn
                    q = kin.solve(start, pose, patient=True, seed=s)
                    if q is not None:
                        roots.append(q)
    return roots


def _toward(v: float, s: float) -> float:
    """The 2π-equivalent of ``v`` nearest ``s`` within ±2π."""
    w = v + 2 * math.pi * round((s - v) / (2 * math.pi))
    if w > 2 * math.pi:
        w -= 2 * math.pi
    elif w < -2 * math.pi:
        w += 2 * math.pi
    return w


def _is_solution(kin: Kinematics, q: np.ndarray, pose: Pose) -> bool:
    q = np.asarray(q, dtype=float)
    if q.shape != (6,) or not np.all(np.abs(q) <= 2 * math.pi):
        return False
    reached = kin.forward(q)
    return reached.distance(pose) < TOL and reached.angle_to(pose) < TOL


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=4_000, help="per family")
    parser.add_argument("--clik-poses", type=int, default=500, help="uniform family only")
    parser.add_argument("--tcp", choices=("flange", "seed", "both"), default="both")
    parser.add_argument("--family", choices=FAMILIES, nargs="*", default=list(FAMILIES))
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--reference", type=int, default=1000,
        help="calibrated poses per family checked against the reference search",
    )  # fmt: skip
    parser.add_argument(
        "--interleave", action="store_true", help="switch solver at every pose (cold caches)"
    )
    parser.add_argument(
        "--ned2-poses", type=int, default=200,
        help="the Ned2's rows (bench/ik_ned2.py): random poses; 0 leaves them out",
    )  # fmt: skip
    args = parser.parse_args()
    names = ("flange", "seed") if args.tcp == "both" else (args.tcp,)
    compiled = str(kinematics.__file__).endswith(tuple(EXTENSION_SUFFIXES))
    print(
        "fxcell.motion.kinematics: "
        + ("compiled with mypyc" if compiled else "interpreted (./dev compiles it: hatch_build.py)")
    )
    print(
        "fxcell.motion._dhchain (calibrated refinement): "
        + (
            "C extension"
            if calibration.NATIVE
            else "not built, DHChain in Python (./dev builds it)"
        )
    )
    targets = Targets("ik")
    for name in names:
        for family in args.family:
            clik = args.clik_poses if family == "uniform" else 0
            res = run(name, family, args.poses, clik, args.seed, args.interleave)
            ours, peer = res["fxcell"], res["ur_analytic_ik"]
            label = f"{name} {family}"
            targets.check(
                f"{label}: fxcell solved", ours["rate"], "==", 100.0, "%",
                peer=peer["rate"], peer_name="ur_analytic_ik",
            )  # fmt: skip
            targets.check(
                f"{label}: fxcell p99", ours["p99"], "<=", 100.0, "µs",
                peer=peer["p99"], peer_name="ur_analytic_ik",
            )  # fmt: skip
            if family == "uniform":
                targets.check(
                    f"{label}: median fxcell / ur_analytic_ik", ours["median"] / peer["median"],
                    "<=", 1.5, "x",
                )  # fmt: skip
        for family in args.family:
            cal = run_calibrated(name, family, args.poses, args.seed, args.reference)
            ours, peer = cal["fxcell calibrated"], cal["ur_analytic_ik"]
            label = f"{name} calibrated {family}"
            targets.check(
                f"{label}: solved", ours["rate"], "==", 100.0, "%",
                peer=peer["rate"], peer_name="ur_analytic_ik (nominal)",
            )  # fmt: skip
            if args.reference > 0:  # --reference 0: not checked, so neither met nor missed
                targets.check(f"{label}: nearest the seed", ours["nearest"], "==", 100.0, "%")
            targets.check(
                f"{label}: median / ur_analytic_ik (nominal)", ours["median"] / peer["median"],
                "<=", 1.5, "x",
            )  # fmt: skip
            targets.check(
                f"{label}: p99", ours["p99"], "<=", 200.0, "µs",
                peer=peer["p99"], peer_name="ur_analytic_ik (nominal)",
            )  # fmt: skip
            targets.check(f"{label}: max", ours["max"], "<=", 2000.0, "µs")
    if args.ned2_poses > 0:
        ik_ned2.report(ik_ned2.measure(args.ned2_poses), targets)
    return targets.finish()


if __name__ == "__main__":
    raise SystemExit(main())
