"""Log retention keeps the log directory within its size and age limits, oldest first."""

from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.cli import main as cli_main
from fxcell.errors import InvalidArgumentError
from fxcell.events import LogEvent
from fxcell.recorder import Recorder, Retention
from fxcell.recorder.retention import enforce

NOW = 1_800_000_000.0


def _log(directory: Path, name: str, size: int, age: float, now: float = NOW) -> Path:
    path = directory / f"fxcell_{name}.mcap"
    path.write_bytes(b"x" * size)
    os.utime(path, (now - age, now - age))
    return path


def test_the_oldest_logs_go_first_until_the_rest_fit(tmp_path: Path) -> None:
    old = _log(tmp_path, "a", 400, age=300)
    middle = _log(tmp_path, "b", 400, age=200)
    new = _log(tmp_path, "c", 400, age=100)
    report = enforce(tmp_path, Retention(max_total_size=900), now=NOW)
    assert report.removed == [old]
    assert not old.exists()
    assert middle.exists()
    assert new.exists()
    assert report.freed == 400
    assert report.kept_bytes == 800


def test_logs_older_than_the_age_limit_go_whatever_the_size(tmp_path: Path) -> None:
    stale = _log(tmp_path, "a", 10, age=8 * 86400)
    fresh = _log(tmp_path, "b", 10, age=86400)
    enforce(tmp_path, Retention(max_age=7 * 86400), now=NOW)
    assert not stale.exists()
    assert fresh.exists()


def test_the_running_file_and_files_of_other_recorders_are_never_removed(tmp_path: Path) -> None:
    running = _log(tmp_path, "a", 500, age=500)
    locked = _log(tmp_path, "b", 500, age=400)
    finished = _log(tmp_path, "c", 500, age=300)
    with open(locked, "rb") as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX)
        report = enforce(tmp_path, Retention(max_total_size=1), keep=[running], now=NOW)
    assert report.removed == [finished]
    assert running.exists()
    assert locked.exists()


def test_files_that_are_not_fxcell_logs_are_left_alone(tmp_path: Path) -> None:
    other = tmp_path / "notes.mcap"
    other.write_bytes(b"y" * 1000)
    foreign = tmp_path / "fxcell_a.txt"
    foreign.write_bytes(b"y" * 1000)
    enforce(tmp_path, Retention(max_total_size=1, max_age=1), now=NOW)
    assert other.exists()
    assert foreign.exists()


def test_a_dry_run_removes_nothing(tmp_path: Path) -> None:
    old = _log(tmp_path, "a", 400, age=300)
    report = enforce(tmp_path, Retention(max_total_size=1), now=NOW, dry_run=True)
    assert report.removed == [old]
    assert old.exists()


def test_limits_must_be_positive() -> None:
    with pytest.raises(InvalidArgumentError):
        Retention(max_total_size=0)
    with pytest.raises(InvalidArgumentError):
        Retention(max_age=-1.0)


@settings(max_examples=60, deadline=None)
@given(
    files=st.lists(
        st.tuples(st.integers(1, 1000), st.integers(0, 10_000)), min_size=0, max_size=12
    ),
    limit=st.integers(1, 6000),
)
def test_what_is_kept_fits_and_is_newer_than_what_was_removed(
    tmp_path_factory: pytest.TempPathFactory, files: list[tuple[int, int]], limit: int
) -> None:
    directory = tmp_path_factory.mktemp("logs")
    for i, (size, age) in enumerate(files):
        _log(directory, f"{i:03d}", size, age=float(age))
    report = enforce(directory, Retention(max_total_size=limit), now=NOW)
    kept = list(directory.glob("*.mcap"))
    assert sum(p.stat().st_size for p in kept) == report.kept_bytes <= limit
    if report.removed and kept:
        newest_removed = max(NOW - files[int(p.stem[-3:])][1] for p in report.removed)
        oldest_kept = min(p.stat().st_mtime for p in kept)
        assert newest_removed <= oldest_kept


def test_a_rotating_recorder_keeps_its_directory_within_the_limit(tmp_path: Path) -> None:
    old = _log(tmp_path, "20000101T000000.000Z", 300_000, age=86400, now=time.time())
    recorder = Recorder(
        tmp_path,
        chunk_duration=0.05,
        rotate_size=20_000,
        tf_rate=0,
        fsync=False,
        compression="none",
        recover=False,
        retention=Retention(max_total_size=150_000),
    )
    try:
        deadline = time.monotonic() + 20
        while len(recorder.stats.files) < 4 and time.monotonic() < deadline:
            for i in range(200):
                recorder.submit(LogEvent(time.time(), 20, "test", f"message {i} " + "z" * 200))
            time.sleep(0.06)
        assert len(recorder.stats.files) >= 4, "the recorder did not rotate"
        assert not old.exists()
        total = sum(p.stat().st_size for p in tmp_path.glob("*.mcap"))
        assert total <= 150_000 + 2 * 20_000 + 100_000  # the open file may overrun its chunk
        assert recorder.current_file is not None
        assert recorder.current_file.exists()
    finally:
        recorder.close()


def test_logs_prune_command_applies_the_limits(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    old = _log(tmp_path, "a", 2_000_000, age=3 * 86400, now=time.time())
    fresh = _log(tmp_path, "b", 10, age=0, now=time.time())
    assert cli_main(["logs", "prune", str(tmp_path), "--max-age", "2", "--dry-run"]) == 0
    assert "would remove" in capsys.readouterr().out
    assert old.exists()
    assert cli_main(["logs", "prune", str(tmp_path), "--max-age", "2"]) == 0
    out = capsys.readouterr().out
    assert f"removed {old}" in out
    assert not old.exists()
    assert fresh.exists()
