"""The wrist-singular continuum solver against the one it replaced, and a dense scan.

Random configurations with θ5 exactly 0, ±π or ±2π (and the other joints uniform within
±2π) → forward kinematics → ``Kinematics._branches`` from a random seed. At such a pose each
shoulder/elbow branch is a continuum (θ6 free) and ``_singular_arms`` returns the member
nearest the seed. Compared, per branch, with the previous solver (a 24-point grid over θ6
per reachable interval, then a 40-step golden-section search around the best point, for
each elbow; kept below) and, on every tenth pose, with a scan of 4000 θ6 values (every joint
shifted by 2π to the equivalent nearest the seed within the limits). Reports how often the
new solver is farther from the seed than the old one or the scan by more than 1e-9, and the
time of ``_branches`` (median, p99) for both. Not part of ``bench/all.py`` (the old solver
takes ~2 ms a pose):

    .venv/bin/python bench/ik_singular.py [--poses N] [--tcp flange|seed|both] [--seed S]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable

import numpy as np

from fxcell.config import SEED_TCP, JointLimits
from fxcell.geometry import Pose
from fxcell.motion.kinematics import _CLIP_EPS, _WRIST_EPS, TWO_PI, Kinematics, _compose

Branches = dict[tuple[float, float, int], float]


def _golden(
    fn: Callable[[float], tuple[float, list[float]] | None], lo: float, hi: float
) -> tuple[float, list[float]] | None:
    g = (math.sqrt(5.0) - 1.0) / 2.0
    worst: tuple[float, list[float]] = (math.inf, [])
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = fn(a) or worst, fn(b) or worst
    for _ in range(40):
        if fa[0] < fb[0]:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = fn(a) or worst
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = fn(b) or worst
    best = fa if fa[0] < fb[0] else fb
    return best if best[1] else None


class OldSingular(Kinematics):
    """Kinematics with the previous continuum solver (grid + golden section per elbow)."""

    def _singular_arms(
        self,
        f: list[float],
        p5x: float,
        p5y: float,
        p5z: float,
        t1: float,
        s1: float,
        c1: float,
        s5: float,
        c5: float,
        seed: list[float],
    ) -> list[list[float]]:
        out = []
        for elbow in (1, -1):
            sol = self._old_arm(f, p5x, p5y, p5z, t1, s1, c1, s5, c5, elbow, seed)
            if sol is not None:
                out.append(sol)
        return out

    def _old_arm(
        self,
        f: list[float],
        p5x: float,
        p5y: float,
        p5z: float,
        t1: float,
        s1: float,
        c1: float,
        s5: float,
        c5: float,
        elbow: int,
        seed: list[float],
    ) -> list[float] | None:
        r00, r01, _, r10, r11, _, r20, r21 = f[:8]
        d1, d5 = self.dh.d[0], self.dh.d[4]
        a2, a3 = self.dh.a[1], self.dh.a[2]
        X5, Y5 = c1 * p5x + s1 * p5y, p5z - d1
        D = math.hypot(X5, Y5)
        ex, ey = (X5 / D, Y5 / D) if D > 0.0 else (1.0, 0.0)
        A = (c1 * r00 + s1 * r10) * ex + r20 * ey
        B = (c1 * r01 + s1 * r11) * ex + r21 * ey
        k, gamma = math.hypot(A, B), math.atan2(A, B)
        den = 2.0 * d5 * D * k
        if den < 1e-15:
            intervals = [(gamma - math.pi, gamma + math.pi)]
        else:
            lo_c = ((a2 - a3) ** 2 - D * D - d5 * d5) / den
            hi_c = ((a2 + a3) ** 2 - D * D - d5 * d5) / den
            if lo_c > 1.0 + _CLIP_EPS or hi_c < -1.0 - _CLIP_EPS:
                return None
            near = math.acos(min(max(hi_c, -1.0), 1.0))
            far = math.acos(min(max(lo_c, -1.0), 1.0))
            intervals = [(gamma + near, gamma + far), (gamma - far, gamma - near)]

        def solve(t6: float) -> tuple[float, list[float]] | None:
            found: list[list[float]] = []
            self._arm(f, p5x, p5y, p5z, t1, s1, c1, s5, c5, t6, found, elbow)
            return self._nearest(found[0], seed) if found else None

        best: tuple[float, list[float]] | None = None
        for lo, hi in intervals:
            n = 24
            step = (hi - lo) / n
            scored = [
                (c[0], t6)
                for t6 in (lo + i * step for i in range(n + 1))
                if (c := solve(t6)) is not None
            ]
            if not scored:
                continue
            _, t_best = min(scored)
            a_lo, a_hi = max(lo, t_best - step), min(hi, t_best + step)
            cands = [c for c in (solve(t_best), _golden(solve, a_lo, a_hi)) if c is not None]
            for c in cands:
                if best is None or c[0] < best[0]:
                    best = c
        return None if best is None else best[1]


def _near(v: np.ndarray, s: float, lo: float, hi: float) -> np.ndarray:
    """``fxcell.motion.kinematics._near`` on arrays (NaN where no equivalent fits)."""
    w = v + TWO_PI * np.round((s - v) / TWO_PI)
    w = np.where(w > hi, np.where(w - hi < 1e-12, hi, w - TWO_PI * np.ceil((w - hi) / TWO_PI)), w)
    w = np.where(w < lo, np.where(lo - w < 1e-12, lo, w + TWO_PI * np.ceil((lo - w) / TWO_PI)), w)
    return np.where((w < lo) | (w > hi), np.nan, w)


def scan(kin: Kinematics, pose: Pose, seed: list[float], n: int = 4000) -> Branches:
    """Smallest distance to the seed per singular (shoulder, elbow) branch, over n θ6."""
    lo, hi = np.array(kin.lower), np.array(kin.upper)
    f = [*pose.rotation.ravel().tolist(), *pose.position.tolist()]
    if not kin._tcp_is_identity:
        f = _compose(f, kin._tcp_inv)
    r00, r01, r02, r10, r11, r12, r20, r21, r22, px, py, pz = f
    d1, d4, d5, d6, a2, a3 = kin._geom
    p5x, p5y, p5z = px - d6 * r02, py - d6 * r12, pz - d6 * r22
    h = math.sqrt(max(p5x * p5x + p5y * p5y - d4 * d4, 0.0))
    phi = math.atan2(p5y, p5x)
    t = np.linspace(-math.pi, math.pi, n, endpoint=False)
    s6, c6 = np.sin(t), np.cos(t)
    res: Branches = {}
    for hs in (h, -h) if h > 0 else (h,):
        t1 = phi + math.atan2(d4, hs)
        s1, c1 = math.sin(t1), math.cos(t1)
        if math.hypot(r00 * s1 - r10 * c1, r01 * s1 - r11 * c1) > _WRIST_EPS:
            continue  # not singular in this shoulder branch
        c5 = 1.0 if r02 * s1 - r12 * c1 >= 0 else -1.0
        z4x, z4y, z4z = -(s6 * r00 + c6 * r01), -(s6 * r10 + c6 * r11), -(s6 * r20 + c6 * r21)
        x4x, x4y, x4z = (c5 * (r * c6 - q * s6) for r, q in ((r00, r01), (r10, r11), (r20, r21)))
        t234 = np.arctan2(x4z, c1 * x4x + s1 * x4y)
        X = c1 * (p5x - d5 * z4x) + s1 * (p5y - d5 * z4y)
        Y = p5z - d5 * z4z - d1
        c3 = (X * X + Y * Y - a2 * a2 - a3 * a3) / (2 * a2 * a3)
        ok = np.abs(c3) <= 1.0
        c3 = np.clip(c3, -1.0, 1.0)
        w1 = _near(np.array(t1), seed[0], lo[0], hi[0])
        w5 = _near(np.array(math.atan2(0.0, c5)), seed[4], lo[4], hi[4])
        fixed = float((w1 - seed[0]) ** 2 + (w5 - seed[4]) ** 2)
        for e in (1, -1):
            s3 = e * np.sqrt(1 - c3 * c3)
            t3 = np.arctan2(s3, c3)
            t2 = np.arctan2(Y, X) - np.arctan2(a3 * s3, a2 + a3 * c3)
            joints = ((1, t2), (2, t3), (3, t234 - t2 - t3), (5, t))
            fv = sum((_near(v, seed[j], lo[j], hi[j]) - seed[j]) ** 2 for j, v in joints)
            fv = np.where(ok, fv, np.nan)
            if not np.all(np.isnan(fv)):
                res[(round(c1, 9), round(s1, 9), e)] = math.sqrt(float(np.nanmin(fv)) + fixed)
    return res


def by_branch(sols: list[list[float]], seed: list[float]) -> Branches:
    """Distance to the seed per (shoulder, elbow sign) branch."""
    out: Branches = {}
    for q in sols:
        key = (round(math.cos(q[0]), 9), round(math.sin(q[0]), 9), 1 if math.sin(q[2]) > 0 else -1)
        out[key] = min(math.dist(q, seed), out.get(key, math.inf))
    return out


def _get(found: Branches, key: tuple[float, float, int]) -> float | None:
    """The branch's distance; a solution at full stretch or fold (θ3 = 0, π) serves both."""
    d = found.get(key)
    return d if d is not None else found.get((key[0], key[1], -key[2]))


def run(tcp_name: str, n: int, seed: int) -> int:
    tcp = None if tcp_name == "flange" else SEED_TCP
    rng = np.random.default_rng(seed)
    limits = JointLimits()
    lo, hi = np.array(limits.position_min), np.array(limits.position_max)
    new, old = Kinematics.ur3e(tcp, limits), OldSingular.ur3e(tcp, limits)
    farther = nearer = missing = scanned = farther_scan = old_farther_scan = 0
    t_new: list[float] = []
    t_old: list[float] = []
    done = 0
    while done < n:
        q = rng.uniform(lo, hi)
        q[4] = rng.choice((0.0, math.pi, -math.pi, TWO_PI, -TWO_PI))
        s = rng.uniform(lo, hi).tolist()
        pose = new.forward(q)
        t0 = time.perf_counter_ns()
        b_new = new._branches(pose, s)
        t1 = time.perf_counter_ns()
        b_old = old._branches(pose, s)
        t2 = time.perf_counter_ns()
        if not b_new and not b_old:
            continue
        done += 1
        t_new.append((t1 - t0) / 1e3)
        t_old.append((t2 - t1) / 1e3)
        d_new, d_old = by_branch(b_new, s), by_branch(b_old, s)
        for key, d in d_old.items():
            mine = _get(d_new, key)
            if mine is None:
                missing += 1
            elif mine > d + 1e-9:
                farther += 1
                print(f"  farther than the old solver by {mine - d:.3g}: q={q.tolist()} seed={s}")
            elif mine < d - 1e-9:
                nearer += 1
        if done % 10 == 0:
            scanned += 1
            for key, d in scan(new, pose, s).items():
                if (mine := _get(d_new, key)) is not None and mine > d + 1e-9:
                    farther_scan += 1
                    print(f"  farther than the scan by {mine - d:.3g}: q={q.tolist()} seed={s}")
                if (theirs := _get(d_old, key)) is not None and theirs > d + 1e-9:
                    old_farther_scan += 1

    def p99(v: list[float]) -> float:
        return sorted(v)[min(len(v) - 1, int(0.99 * len(v)))]

    print(
        f"TCP {tcp_name}: {n} exactly wrist-singular poses, branch by branch: "
        f"new farther than the old solver by > 1e-9: {farther}, nearer: {nearer}, "
        f"missing: {missing}\n"
        f"  against a 4000-point θ6 scan ({scanned} poses): new farther by > 1e-9: "
        f"{farther_scan}, old farther: {old_farther_scan}\n"
        f"  _branches: new median {statistics.median(t_new):.1f} µs, p99 {p99(t_new):.1f} µs;"
        f" old median {statistics.median(t_old):.1f} µs, p99 {p99(t_old):.1f} µs"
    )
    return farther + missing


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=20_000)
    parser.add_argument("--tcp", choices=("flange", "seed", "both"), default="both")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    names = ("flange", "seed") if args.tcp == "both" else (args.tcp,)
    bad = sum(run(name, args.poses, args.seed) for name in names)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
