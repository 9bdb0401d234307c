"""The job's memory: an embedded SQLite database that outlives crashes.

Tables: ``runs`` (the validated run as JSON, the job state last recorded), ``samples``,
``locations`` (where each sample's crucible and, once it exists, its bead is: ``rack:A1``,
``gripper``, ``machine:A2``, ``mould:A2``, ``tray:C4``) and ``steps`` (every attempt at a
step of the plan: start, end, outcome). The database runs in WAL mode with
``synchronous=FULL``: a committed transaction survives power loss.

The write discipline that makes recovery possible: a step's start commits before the robot
moves (:meth:`JobStore.begin_step`); its end, the locations it changed and the job state
commit in one transaction (:meth:`JobStore.end_step`). A step with a start and no end was
interrupted; the locations are then those before the step.

Calls are synchronous and short; the runner runs them in a worker thread so that an fsync
never stalls the event loop. One lock serialises them.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fxcell.errors import JobStoreError
from fxcell.job.spec import Run, Sample

SCHEMA_VERSION = 2
"""1: runs, samples, locations, steps; 2: placement_checks (migrated by creating it)."""
CRUCIBLE = "crucible"
BEAD = "bead"
GRIPPER = "gripper"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL,
    spec TEXT NOT NULL,
    state TEXT NOT NULL,
    message TEXT NOT NULL DEFAULT '',
    created REAL NOT NULL,
    finished REAL
);
CREATE TABLE IF NOT EXISTS samples (
    run_id INTEGER NOT NULL REFERENCES runs(id),
    idx INTEGER NOT NULL,
    sample_id TEXT NOT NULL,
    rack TEXT NOT NULL,
    machine TEXT NOT NULL,
    tray TEXT NOT NULL,
    cycle INTEGER NOT NULL,
    PRIMARY KEY (run_id, idx)
);
CREATE TABLE IF NOT EXISTS locations (
    run_id INTEGER NOT NULL,
    idx INTEGER NOT NULL,
    object TEXT NOT NULL CHECK (object IN ('crucible', 'bead')),
    location TEXT NOT NULL,
    step_id INTEGER REFERENCES steps(id),
    updated REAL NOT NULL,
    PRIMARY KEY (run_id, idx, object),
    FOREIGN KEY (run_id, idx) REFERENCES samples(run_id, idx)
);
CREATE TABLE IF NOT EXISTS steps (
    id INTEGER PRIMARY KEY,
    run_id INTEGER NOT NULL REFERENCES runs(id),
    seq INTEGER NOT NULL,
    kind TEXT NOT NULL,
    idx INTEGER,
    started REAL NOT NULL,
    ended REAL,
    duration REAL,
    outcome TEXT,
    detail TEXT NOT NULL DEFAULT ''
);
CREATE INDEX IF NOT EXISTS steps_by_run ON steps (run_id, seq);
CREATE TABLE IF NOT EXISTS placement_checks (
    id INTEGER PRIMARY KEY,
    run_id INTEGER NOT NULL REFERENCES runs(id),
    seq INTEGER NOT NULL,
    time REAL NOT NULL,
    ok INTEGER NOT NULL,
    reason TEXT NOT NULL,
    verdict TEXT NOT NULL,
    image BLOB NOT NULL
);
CREATE INDEX IF NOT EXISTS placement_checks_by_run ON placement_checks (run_id, id);
"""

Key = tuple[int, str]
"""A tracked object: (sample index, ``crucible`` or ``bead``)."""


@dataclass(frozen=True)
class Change:
    """One object moving from ``old`` (``None``: it did not exist) to ``new``."""

    key: Key
    old: str | None
    new: str


@dataclass(frozen=True)
class StepRecord:
    """One attempt at a step of the plan."""

    id: int
    seq: int
    kind: str
    idx: int | None
    started: float
    ended: float | None
    duration: float | None
    outcome: str | None
    detail: str


@dataclass(frozen=True)
class PlacementRecord:
    """A placement check the job made before starting the machine (its image apart)."""

    id: int
    run_id: int
    seq: int
    """The plan step it guarded (the machine's start)."""
    time: float
    ok: bool
    reason: str
    verdict: dict[str, Any]


@dataclass(frozen=True)
class RunRecord:
    id: int
    run: Run
    state: str
    message: str
    created: float
    finished: float | None


class JobStore:
    """The job database at ``path`` (created on first use; ``:memory:`` for a throwaway)."""

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        if self.path != ":memory:":
            Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        try:
            self._db = sqlite3.connect(
                self.path, isolation_level=None, check_same_thread=False, timeout=10.0
            )
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
            self._db.executescript(_SCHEMA)
            row = self._db.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
            if row is None:
                self._db.execute("INSERT INTO meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
            elif int(row[0]) < SCHEMA_VERSION:
                # 1 -> 2: the placement_checks table, created by the script above
                self._db.execute(
                    "UPDATE meta SET value=? WHERE key='schema'", (str(SCHEMA_VERSION),)
                )
            elif int(row[0]) != SCHEMA_VERSION:
                raise JobStoreError(
                    f"{self.path}: job database schema {row[0]}, this fxcell reads {SCHEMA_VERSION}"
                )
        except sqlite3.Error as exc:
            raise JobStoreError(f"cannot open the job database {self.path}: {exc}") from None
        self._lock = threading.Lock()

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One transaction (``BEGIN IMMEDIATE`` ... ``COMMIT``), rolled back on any error."""
        with self._lock:
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    yield self._db
                except BaseException:
                    self._db.execute("ROLLBACK")
                    raise
                self._db.execute("COMMIT")
            except sqlite3.Error as exc:
                raise JobStoreError(f"job database {self.path}: {exc}") from None

    def _query(self, sql: str, args: Iterable[object] = ()) -> list[Any]:
        with self._lock:
            try:
                return list(self._db.execute(sql, tuple(args)))
            except sqlite3.Error as exc:
                raise JobStoreError(f"job database {self.path}: {exc}") from None

    # -- runs

    def create_run(self, run: Run, state: str, locations: Mapping[Key, str]) -> int:
        """Store a new run, its samples and their initial locations; returns its id."""
        now = time.time()
        with self._tx() as db:
            cur = db.execute(
                "INSERT INTO runs (name, spec, state, created) VALUES (?, ?, ?, ?)",
                (run.name, json.dumps(run.to_dict()), state, now),
            )
            run_id = int(cur.lastrowid or 0)
            db.executemany(
                "INSERT INTO samples VALUES (?, ?, ?, ?, ?, ?, ?)",
                [(run_id, s.index, s.id, s.rack, s.machine, s.tray, s.cycle) for s in run.samples],
            )
            db.executemany(
                "INSERT INTO locations VALUES (?, ?, ?, ?, NULL, ?)",
                [(run_id, idx, obj, loc, now) for (idx, obj), loc in locations.items()],
            )
        return run_id

    def run(self, run_id: int) -> RunRecord:
        rows = self._query(
            "SELECT id, name, state, message, created, finished FROM runs WHERE id=?", (run_id,)
        )
        if not rows:
            raise JobStoreError(f"no run {run_id} in {self.path}")
        rid, name, state, message, created, finished = rows[0]
        samples = self._query(
            "SELECT idx, sample_id, rack, machine, tray, cycle FROM samples"
            " WHERE run_id=? ORDER BY idx",
            (run_id,),
        )
        run = Run(
            str(name),
            tuple(
                Sample(int(i), str(sid), str(r), str(m), str(t), int(c))
                for i, sid, r, m, t, c in samples
            ),
        )
        return RunRecord(
            int(rid),
            run,
            str(state),
            str(message),
            float(created),
            None if finished is None else float(finished),
        )

    def unfinished_run(self) -> int | None:
        """The newest run not yet finished (done), if any."""
        rows = self._query("SELECT id FROM runs WHERE finished IS NULL ORDER BY id DESC LIMIT 1")
        return int(rows[0][0]) if rows else None

    def set_state(self, run_id: int, state: str, message: str = "", finished: bool = False) -> None:
        with self._tx() as db:
            self._set_state(db, run_id, state, message, finished)

    @staticmethod
    def _set_state(
        db: sqlite3.Connection, run_id: int, state: str, message: str, finished: bool
    ) -> None:
        db.execute(
            "UPDATE runs SET state=?, message=?, finished=? WHERE id=?",
            (state, message, time.time() if finished else None, run_id),
        )

    # -- steps and locations

    def begin_step(
        self,
        run_id: int,
        seq: int,
        kind: str,
        idx: int | None,
        state: tuple[str, str] | None = None,
    ) -> int:
        """Record a step's start (committed before the robot moves) and optionally the job
        state ``(state, message)`` it enters; returns the step id."""
        with self._tx() as db:
            cur = db.execute(
                "INSERT INTO steps (run_id, seq, kind, idx, started) VALUES (?, ?, ?, ?, ?)",
                (run_id, seq, kind, idx, time.time()),
            )
            if state is not None:
                self._set_state(db, run_id, state[0], state[1], False)
            return int(cur.lastrowid or 0)

    def end_step(
        self,
        step_id: int,
        outcome: str,
        changes: Iterable[Change] = (),
        *,
        detail: str = "",
        duration: float | None = None,
        state: tuple[str, str] | None = None,
    ) -> None:
        """Record a step's end, the locations it changed and (optionally) the job state
        ``(state, message)``, all in one transaction.

        Each change is checked against the stored location: a mismatch rolls everything back
        and raises :class:`JobStoreError` (the records would no longer add up).
        """
        now = time.time()
        with self._tx() as db:
            row = db.execute("SELECT run_id, ended FROM steps WHERE id=?", (step_id,)).fetchone()
            if row is None:
                raise JobStoreError(f"no step {step_id}")
            run_id = int(row[0])
            if row[1] is not None:
                raise JobStoreError(f"step {step_id} has already ended")
            db.execute(
                "UPDATE steps SET ended=?, duration=?, outcome=?, detail=? WHERE id=?",
                (now, duration, outcome, detail, step_id),
            )
            self._apply(db, run_id, changes, step_id, now)
            if state is not None:
                self._set_state(db, run_id, state[0], state[1], False)

    @staticmethod
    def _apply(
        db: sqlite3.Connection, run_id: int, changes: Iterable[Change], step_id: int, now: float
    ) -> None:
        for ch in changes:
            idx, obj = ch.key
            cur = db.execute(
                "SELECT location FROM locations WHERE run_id=? AND idx=? AND object=?",
                (run_id, idx, obj),
            ).fetchone()
            old = None if cur is None else str(cur[0])
            if old != ch.old:
                raise JobStoreError(
                    f"sample {idx + 1} {obj}: recorded at {old}, the step expected {ch.old}"
                )
            db.execute(
                "INSERT INTO locations VALUES (?, ?, ?, ?, ?, ?)"
                " ON CONFLICT (run_id, idx, object) DO UPDATE SET"
                " location=excluded.location, step_id=excluded.step_id, updated=excluded.updated",
                (run_id, idx, obj, ch.new, step_id, now),
            )
        taken = db.execute(
            "SELECT location, COUNT(*) FROM locations WHERE run_id=? GROUP BY location"
            " HAVING COUNT(*) > 1",
            (run_id,),
        ).fetchone()
        if taken is not None:
            raise JobStoreError(f"{taken[1]} objects recorded at {taken[0]}")

    def close_open_steps(self, run_id: int, outcome: str, detail: str = "") -> int:
        """End every open step of the run with ``outcome`` (no location change); how many."""
        with self._tx() as db:
            cur = db.execute(
                "UPDATE steps SET ended=?, outcome=?, detail=? WHERE run_id=? AND ended IS NULL",
                (time.time(), outcome, detail, run_id),
            )
            return cur.rowcount

    def steps(self, run_id: int) -> list[StepRecord]:
        rows = self._query(
            "SELECT id, seq, kind, idx, started, ended, duration, outcome, detail FROM steps"
            " WHERE run_id=? ORDER BY id",
            (run_id,),
        )
        return [
            StepRecord(
                int(r[0]),
                int(r[1]),
                str(r[2]),
                None if r[3] is None else int(r[3]),
                float(r[4]),
                None if r[5] is None else float(r[5]),
                None if r[6] is None else float(r[6]),
                None if r[7] is None else str(r[7]),
                str(r[8]),
            )
            for r in rows
        ]

    def locations(self, run_id: int) -> dict[Key, str]:
        rows = self._query(
            "SELECT idx, object, location FROM locations WHERE run_id=? ORDER BY idx, object",
            (run_id,),
        )
        return {(int(i), str(o)): str(loc) for i, o, loc in rows}

    def mean_durations(self, limit: int = 200) -> dict[str, float]:
        """Mean measured duration per step kind over the newest ``limit`` completed steps."""
        rows = self._query(
            "SELECT kind, AVG(duration) FROM (SELECT kind, duration FROM steps"
            " WHERE outcome='done' AND duration IS NOT NULL ORDER BY id DESC LIMIT ?)"
            " GROUP BY kind",
            (limit,),
        )
        return {str(k): float(d) for k, d in rows}

    def record_answer(
        self,
        run_id: int,
        seq: int,
        kind: str,
        idx: int | None,
        changes: Iterable[Change],
        detail: str,
    ) -> None:
        """Record the operator's answer about interrupted step ``seq`` in one transaction.

        Any open step is closed as ``interrupted``; with ``changes`` (the step had in fact
        completed) a ``done`` record of the step is added with the locations it changed.
        """
        changes = list(changes)
        now = time.time()
        with self._tx() as db:
            db.execute(
                "UPDATE steps SET ended=?, outcome='interrupted' WHERE run_id=? AND ended IS NULL",
                (now, run_id),
            )
            if changes:
                cur = db.execute(
                    "INSERT INTO steps (run_id, seq, kind, idx, started, ended, outcome, detail)"
                    " VALUES (?, ?, ?, ?, ?, ?, 'done', ?)",
                    (run_id, seq, kind, idx, now, now, detail),
                )
                self._apply(db, run_id, changes, int(cur.lastrowid or 0), now)
            else:
                db.execute(
                    "UPDATE steps SET detail=? WHERE id=(SELECT MAX(id) FROM steps"
                    " WHERE run_id=? AND seq=?)",
                    (detail, run_id, seq),
                )

    # -- placement checks

    def add_placement_check(
        self, run_id: int, seq: int, verdict: Mapping[str, Any], image: bytes
    ) -> int:
        """Keep a check's verdict (JSON) and annotated image (JPEG) beside the run."""
        with self._tx() as db:
            cur = db.execute(
                "INSERT INTO placement_checks (run_id, seq, time, ok, reason, verdict, image) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    run_id,
                    seq,
                    float(verdict.get("time", time.time())),
                    int(bool(verdict.get("ok"))),
                    str(verdict.get("reason", "")),
                    json.dumps(verdict),
                    image,
                ),
            )
            return int(cur.lastrowid or 0)

    def placement_checks(self, run_id: int) -> list[PlacementRecord]:
        """The run's checks, oldest first."""
        rows = self._query(
            "SELECT id, run_id, seq, time, ok, reason, verdict FROM placement_checks "
            "WHERE run_id=? ORDER BY id",
            (run_id,),
        )
        return [
            PlacementRecord(i, r, q, t, bool(ok), reason, json.loads(v))
            for i, r, q, t, ok, reason, v in rows
        ]

    def placement_image(self, check_id: int) -> bytes:
        """The annotated image of check ``check_id``."""
        rows = self._query("SELECT image FROM placement_checks WHERE id=?", (check_id,))
        if not rows:
            raise JobStoreError(f"no placement check {check_id} in {self.path}")
        return bytes(rows[0][0])
