"""Crash safety: a recording cut off by SIGKILL or a torn write loses at most one chunk."""

from __future__ import annotations

import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from fxcell.cli import main
from fxcell.errors import RecorderError
from fxcell.recorder import Recorder, is_finished, recover, topics
from fxcell.recorder.protobuf import decode_robot_state
from fxcell.recorder.recovery import is_locked
from fxcell.recorder.synthetic import SyntheticSession, play

CHUNK = 0.5
# the writer thread waiting for a CPU on a loaded 2-core machine (measured loss: 0.07-0.45 s)
SLACK = 0.35
# The child says, every 20 ms, the wall time just after it published an event: the last such
# line left in the pipe bounds what it had published when it was killed, so a child starved
# of CPU (publishing late) is not counted as the recorder's loss.
CHILD = textwrap.dedent(
    """
    import sys, time
    from fxcell.events import EventBus
    from fxcell.recorder import Recorder
    from fxcell.recorder.synthetic import SyntheticSession

    rec = Recorder(sys.argv[1], chunk_duration=float(sys.argv[2]), metadata={"serial": "S1"})
    bus = EventBus()
    rec.attach(bus)
    start = time.monotonic()
    announced = False
    said = 0
    for p in SyntheticSession(60.0).events():
        delay = p.at - (time.monotonic() - start)
        if delay > 0:
            time.sleep(delay)
        bus.publish(p.event)
        if not announced and p.at >= 2.0:
            print("recording", flush=True)
            announced = True
        if announced and time.time_ns() - said > 20_000_000:
            said = time.time_ns()
            print(said, flush=True)
    """
)


def messages(path: Path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as f:
        return [
            (ch.topic, m.log_time, m.data)
            for _s, ch, m in make_reader(f).iter_messages(log_time_order=False)
        ]


def test_sigkill_mid_session_loses_at_most_one_chunk(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(logs), str(CHUNK)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "recording"
        published = [int(child.stdout.readline())]  # it publishes on
        (path,) = logs.glob("*.mcap")
        assert is_locked(path)  # recovery at another start must leave it alone
        os.kill(child.pid, signal.SIGKILL)
        child.wait(10)
        published += [int(line) for line in child.stdout.read().split()]
    finally:
        child.kill()
        child.wait(10)
        if child.stdout is not None:
            child.stdout.close()
    assert not is_finished(path)
    assert not is_locked(path)
    copy = tmp_path / "copy.mcap"
    shutil.copy(path, copy)

    # automatic recovery when the next recorder starts in the same directory
    with Recorder(logs) as rec:
        pass
    assert is_finished(path)
    assert len(rec.stats.files) == 1
    assert rec.stats.files[0] != path
    recovered = messages(path)
    states = [decode_robot_state(d) for t, _, d in recovered if t == topics.ROBOT_STATE]
    assert len(states) > 500
    steps = {round(b.timestamp - a.timestamp, 6) for a, b in itertools.pairwise(states)}
    assert steps == {0.002}  # a gap-free prefix of the session
    loss = (published[-1] - max(t for _, t, _ in recovered)) / 1e9
    assert loss <= CHUNK + SLACK, f"lost {loss:.3f} s with {CHUNK} s chunks"
    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = [a.name for a in reader.iter_attachments()]
    assert meta[topics.METADATA_NAME]["serial"] == "S1"
    assert int(meta[topics.RECOVERY_METADATA_NAME]["kept_bytes"]) <= copy.stat().st_size
    assert attachments == [topics.URDF_ATTACHMENT]

    # and by hand: fxcell logs recover FILE
    assert main(["logs", "recover", str(copy)]) == 0
    assert is_finished(copy)
    assert messages(copy) == recovered


@pytest.fixture(scope="module")
def finished_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("logs")
    rec = Recorder(directory, chunk_duration=0.05)
    play(SyntheticSession(0.8, move_every=0.3), rec.submit, realtime=True)
    rec.close()
    (path,) = rec.stats.files
    return path


@settings(max_examples=15, deadline=None)
@given(cut=st.floats(0.0, 1.0))
def test_a_torn_write_keeps_every_complete_chunk(
    finished_log: Path, tmp_path_factory: pytest.TempPathFactory, cut: float
) -> None:
    with open(finished_log, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    data_end = max(c.chunk_start_offset + c.chunk_length for c in summary.chunk_indexes)
    offset = int(cut * data_end)
    torn = tmp_path_factory.mktemp("torn") / "torn.mcap"
    torn.write_bytes(finished_log.read_bytes()[:offset])
    report = recover(torn)
    complete = [c for c in summary.chunk_indexes if c.chunk_start_offset + c.chunk_length <= offset]
    expected = messages(finished_log)[: report.messages]
    assert messages(torn) == expected  # a prefix of the original, nothing altered
    last = complete[-1].message_end_time if complete else -1
    assert report.messages >= sum(1 for _, t, _ in messages(finished_log) if t <= last)
    assert report.chunks == len(complete)


def test_recover_refuses_what_is_not_a_log_or_still_recording(tmp_path: Path) -> None:
    bogus = tmp_path / "notes.mcap"
    bogus.write_text("hello, this is not MCAP at all")
    with pytest.raises(RecorderError):
        recover(bogus)
    with pytest.raises(RecorderError):
        recover(tmp_path / "missing.mcap")
    empty = tmp_path / "empty.mcap"  # power lost right after the file was created
    empty.write_bytes(b"")
    assert recover(empty).messages == 0
    assert is_finished(empty)
    with Recorder(tmp_path / "live") as rec:
        live = rec.current_file
        assert live is not None
        with pytest.raises(RecorderError, match="being recorded"):
            recover(live)
    assert main(["logs", "recover", str(live)]) == 0  # finished: nothing to do


def test_recovered_file_says_it_was_recovered(finished_log: Path, tmp_path: Path) -> None:
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(finished_log.read_bytes()[: finished_log.stat().st_size // 2])
    out = tmp_path / "out.mcap"
    assert main(["logs", "recover", str(torn), "-o", str(out)]) == 0
    with open(out, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    rec = meta[topics.RECOVERY_METADATA_NAME]
    assert rec["source"] == "torn.mcap"
    assert json.loads(rec["was_finished"]) is False
    assert int(rec["messages"]) == len(messages(out))


def test_logs_recover_on_a_directory_repairs_every_unfinished_log(
    finished_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = finished_log.read_bytes()
    (tmp_path / "a.mcap").write_bytes(data[: len(data) // 3])
    (tmp_path / "b.mcap").write_bytes(data)  # finished: left alone
    assert main(["logs", "recover", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "a.mcap" in out
    assert "b.mcap" not in out
    assert is_finished(tmp_path / "a.mcap")
    assert (tmp_path / "b.mcap").read_bytes() == data
