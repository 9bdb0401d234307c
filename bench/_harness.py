"""Targets every bench declares and checks, and the verdict it ends with.

A bench builds a :class:`Targets`, records each target with :meth:`Targets.check` (name,
figure, unit, comparison, bound, and the peer's figure when there is one) and ends with
``raise SystemExit(targets.finish())``: a table, then ``target met`` or
``target missed: <names>``, and a non-zero exit code on any miss. ``bench/all.py`` runs
every bench and collects these rows (through the file named by ``FXCELL_BENCH_RESULTS``)
into one table.
"""

from __future__ import annotations

import json
import math
import operator
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass

RESULTS_ENV = "FXCELL_BENCH_RESULTS"
# Simulators the benches start keep their parent's priority (fxcell.sim.server.PRIORITY_ENV):
# a peer measured beside them runs at the same priority. FXCELL_SIM_PRIORITY=raised in the
# environment gives them back their default nice -5.
os.environ.setdefault("FXCELL_SIM_PRIORITY", "normal")
OPS: dict[str, Callable[[float, float], bool]] = {
    "<=": operator.le,
    "<": operator.lt,
    ">=": operator.ge,
    ">": operator.gt,
    "==": operator.eq,
}


@dataclass(frozen=True)
class Target:
    """One target: ``figure op bound`` (in ``unit``), with the peer's figure if any."""

    bench: str
    name: str
    figure: float
    op: str
    bound: float
    unit: str
    peer: float | None = None
    peer_name: str = ""

    @property
    def met(self) -> bool:
        return math.isfinite(self.figure) and OPS[self.op](self.figure, self.bound)

    @property
    def text(self) -> str:
        return f"{self.name} {self.op} {_num(self.bound)} {self.unit}".rstrip()


def _num(x: float | None) -> str:
    if x is None:
        return "-"
    if not math.isfinite(x):
        return str(x)
    if x != 0 and (abs(x) >= 1e5 or abs(x) < 1e-3):
        return f"{x:.3g}"
    return f"{x:.4g}"


def table(rows: list[Target], with_bench: bool = False) -> str:
    """The rows as an aligned text table."""
    head = (["bench"] if with_bench else []) + ["target", "figure", "peer", "met?"]
    body = [
        ([t.bench] if with_bench else [])
        + [
            t.text,
            f"{_num(t.figure)} {t.unit}".rstrip(),
            f"{_num(t.peer)} {t.unit} ({t.peer_name})".rstrip() if t.peer is not None else "-",
            "yes" if t.met else "NO",
        ]
        for t in rows
    ]
    widths = [max(len(r[i]) for r in [head, *body]) for i in range(len(head))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in [head, *body]]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(line.rstrip() for line in lines)


class Targets:
    """The targets of one bench run."""

    def __init__(self, bench: str) -> None:
        self.bench = bench
        self.rows: list[Target] = []

    def check(
        self,
        name: str,
        figure: float,
        op: str,
        bound: float,
        unit: str = "",
        *,
        peer: float | None = None,
        peer_name: str = "",
    ) -> bool:
        """Record a target; returns whether it is met."""
        if op not in OPS:
            raise ValueError(f"unknown comparison {op!r}")
        row = Target(self.bench, name, float(figure), op, float(bound), unit, peer, peer_name)
        self.rows.append(row)
        return row.met

    def finish(self) -> int:
        """Print the table and the verdict; the exit code (1 on any miss or no target)."""
        print(f"\n== {self.bench}: targets")
        print(table(self.rows))
        path = os.environ.get(RESULTS_ENV)
        if path:
            with open(path, "a") as f:
                for row in self.rows:
                    f.write(json.dumps(asdict(row)) + "\n")
        missed = [t.text for t in self.rows if not t.met]
        if not self.rows:
            print("target missed: no target was checked")
            return 1
        if missed:
            print("target missed: " + "; ".join(missed))
            return 1
        print("target met")
        return 0


def load(path: str) -> list[Target]:
    """The rows a run wrote to ``path``."""
    with open(path) as f:
        return [Target(**json.loads(line)) for line in f if line.strip()]
