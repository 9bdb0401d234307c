"""The job database: durable settings, one transaction per state change, records that add up."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest
from job_fakes import sample_run

from fxcell.errors import JobStoreError
from fxcell.job import JobStore, initial_locations
from fxcell.job.store import Change


@pytest.fixture
def store(tmp_path: Path) -> Iterator[JobStore]:
    s = JobStore(tmp_path / "job.sqlite3")
    yield s
    s.close()


def test_the_database_is_in_wal_mode_with_full_sync(store: JobStore) -> None:
    assert store._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert store._db.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL


def test_a_step_end_and_its_location_changes_commit_together(store: JobStore) -> None:
    run = sample_run(2)
    run_id = store.create_run(run, "running", initial_locations(run))
    step = store.begin_step(run_id, 0, "pick:rack", 0)
    assert store.steps(run_id)[0].ended is None  # the start is committed on its own
    bad = [Change((0, "crucible"), "rack:A1", "gripper"), Change((1, "crucible"), "rack:A9", "x")]
    with pytest.raises(JobStoreError, match="recorded at rack:A2, the step expected rack:A9"):
        store.end_step(step, "done", bad, state=("paused", "x"))
    assert store.locations(run_id)[(0, "crucible")] == "rack:A1"  # rolled back, all of it
    assert store.steps(run_id)[0].ended is None
    assert store.run(run_id).state == "running"
    store.end_step(step, "done", bad[:1], duration=1.5, state=("paused", "why"))
    assert store.locations(run_id)[(0, "crucible")] == "gripper"
    assert (store.steps(run_id)[0].outcome, store.steps(run_id)[0].duration) == ("done", 1.5)
    assert (store.run(run_id).state, store.run(run_id).message) == ("paused", "why")
    with pytest.raises(JobStoreError, match="already ended"):
        store.end_step(step, "done")


def test_two_objects_can_never_be_recorded_in_one_place(store: JobStore) -> None:
    run = sample_run(2)
    run_id = store.create_run(run, "running", initial_locations(run))
    step = store.begin_step(run_id, 0, "pick:rack", 0)
    store.end_step(step, "done", [Change((0, "crucible"), "rack:A1", "gripper")])
    step = store.begin_step(run_id, 1, "pick:rack", 1)
    with pytest.raises(JobStoreError, match="2 objects recorded at gripper"):
        store.end_step(step, "done", [Change((1, "crucible"), "rack:A2", "gripper")])
    assert store.locations(run_id)[(1, "crucible")] == "rack:A2"


def test_a_run_reads_back_as_it_was_stored(tmp_path: Path, store: JobStore) -> None:
    run = sample_run(6)
    run_id = store.create_run(run, "running", initial_locations(run))
    again = JobStore(tmp_path / "job.sqlite3")
    assert again.run(run_id).run == run
    assert again.unfinished_run() == run_id
    again.set_state(run_id, "done", "ok", finished=True)
    assert store.unfinished_run() is None
    again.close()


def test_a_database_of_another_schema_is_refused(tmp_path: Path) -> None:
    db = tmp_path / "old.sqlite3"
    JobStore(db).close()
    with sqlite3.connect(db) as con:
        con.execute("UPDATE meta SET value='99' WHERE key='schema'")
    con.close()
    with pytest.raises(JobStoreError, match="schema 99"):
        JobStore(db)
    (tmp_path / "junk.sqlite3").write_bytes(b"not a database at all" * 100)
    with pytest.raises(JobStoreError, match="cannot open the job database"):
        JobStore(tmp_path / "junk.sqlite3")
