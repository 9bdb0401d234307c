"""``fxcell replay``: summary, timeline, plot and Foxglove serving of recorded sessions."""

from __future__ import annotations

import itertools
import json
import shutil
import struct
import threading
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from fxcell.cli import main
from fxcell.errors import InvalidArgumentError
from fxcell.recorder import Recorder, is_finished, topics
from fxcell.recorder.protobuf import decode_robot_state
from fxcell.recorder.reading import LogMessage, LogReader
from fxcell.recorder.synthetic import SyntheticSession
from fxcell.replay import _declutter, format_summary, summarize, timeline


@pytest.fixture(scope="module")
def log_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("logs")
    t0 = 1_790_000_000_000_000_000
    now = [t0]  # a simulated clock: log times exactly as planned, however loaded the machine
    rec = Recorder(
        directory, chunk_duration=0.1, metadata={"serial": "20235500042"}, clock=lambda: now[0]
    )
    session = SyntheticSession(1.5, move_every=0.4, protective_stop_at=0.95, t0=t0 / 1e9)
    for planned in session.events():
        now[0] = t0 + round(planned.at * 1e9)
        rec.submit(planned.event)
    rec.close()
    (path,) = rec.stats.files
    return path


def test_summary_lists_commands_transitions_errors_and_stops(log_file: Path) -> None:
    s = summarize(log_file)
    assert s.finished
    assert s.duration == pytest.approx(1.5, abs=0.01)
    assert s.counts[topics.ROBOT_STATE] == 750
    assert s.rate(topics.ROBOT_STATE) == pytest.approx(500, rel=0.01)
    names = [c.name for c in s.commands]
    assert names[:2] == ["power_on", "brake_release"]
    assert "unlock_protective_stop" in names
    failed = [c for c in s.commands if c.outcome == "error"]
    assert [c.error_type for c in failed] == ["ProtectiveStopError"]
    assert all(c.ended is not None and c.ended >= c.started for c in s.commands)
    assert [t["dest"] for t in s.transitions] == ["idle", "ready", "protective_stop", "ready"]
    assert len(s.protective_stops) == 1
    assert any("ProtectiveStopError" in text for _, text in s.errors)
    assert any("protective stop" in text for _, text in s.errors)  # the ERROR log record
    text = format_summary(s)
    assert "serial: 20235500042" in text
    assert "protective stops: 1" in text
    assert "move_joint" in text


def test_timeline_is_chronological_and_filters_by_topic_and_time(log_file: Path) -> None:
    lines = timeline(log_file)
    stamps = [float(line.split("s", 1)[0]) for line in lines]
    assert stamps == sorted(stamps)
    assert any("power_off → idle" in line for line in lines)
    assert any("✗" in line and "ProtectiveStopError" in line for line in lines)
    only = timeline(log_file, topic_names=[topics.TRANSITIONS])
    assert len(only) == 4
    assert all(topics.TRANSITIONS in line for line in only)
    late = timeline(log_file, topic_names=[topics.TRANSITIONS], start=0.5)
    assert [line.split("→")[1].split()[0] for line in late] == ["protective_stop", "ready"]
    with pytest.raises(InvalidArgumentError):
        timeline(log_file, topic_names=["/nope"])


@pytest.mark.system  # matplotlib runs fc-list to build its font cache on first use
def test_plot_writes_a_png(log_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "session.png"
    assert main(["replay", str(log_file), "--plot", str(out)]) == 0
    header = out.read_bytes()[:24]
    assert header[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", header[16:24])
    assert width > 800
    assert height > 600


def test_cli_prints_the_summary_and_timeline(
    log_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["replay", str(log_file)]) == 0
    out = capsys.readouterr().out
    assert "commands:" in out
    assert topics.ROBOT_STATE in out
    assert main(["replay", str(log_file), "--timeline", "--topic", topics.COMMANDS]) == 0
    out = capsys.readouterr().out
    assert "▶ #1 power_on" in out
    assert "transitions" not in out


def test_reader_reads_an_unfinished_file_to_its_last_chunk(log_file: Path, tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    data = log_file.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    assert not is_finished(cut)
    reader = LogReader(cut)
    full = LogReader(log_file)
    assert 0 < reader.counts[topics.ROBOT_STATE] < full.counts[topics.ROBOT_STATE]
    states = [s for _m, s in reader.decoded([topics.ROBOT_STATE])]
    assert len(states) == reader.counts[topics.ROBOT_STATE]
    assert "unfinished" in format_summary(summarize(cut))


def test_indexed_and_linear_reads_agree(log_file: Path, tmp_path: Path) -> None:
    linear = tmp_path / "linear.mcap"
    data = log_file.read_bytes()
    linear.write_bytes(data[: data.rindex(b"\x89MCAP0\r\n")])  # drop the footer magic
    wanted = [topics.COMMANDS, topics.TRANSITIONS, topics.LOG]
    a = [(m.topic, m.log_time, m.data) for m in LogReader(log_file).messages(wanted)]
    b = [(m.topic, m.log_time, m.data) for m in LogReader(linear).messages(wanted)]
    assert a == b
    assert len(a) > 10
    reader = LogReader(log_file)
    start = next(reader.messages([topics.ROBOT_STATE])).log_time
    window = list(reader.messages([topics.ROBOT_STATE], start=start, end=start + 100_000_000))
    assert len(window) == 50  # 100 ms at 500 Hz


def fields(m: LogMessage) -> tuple[str, int, int, bytes]:
    return m.topic, m.log_time, m.publish_time, m.data


@settings(max_examples=40, deadline=None)
@given(
    records=st.lists(
        st.tuples(st.sampled_from([topics.ROBOT_STATE, topics.COMMANDS, topics.TF]), st.binary()),
        max_size=60,
    ),
    chunk_size=st.integers(1, 2000),
    compression=st.sampled_from(CompressionType),
    window=st.tuples(st.integers(0, 70), st.integers(0, 70)),
)
def test_reader_returns_what_mcap_reads_whatever_the_chunking(
    tmp_path_factory: pytest.TempPathFactory,
    records: list[tuple[str, bytes]],
    chunk_size: int,
    compression: CompressionType,
    window: tuple[int, int],
) -> None:
    path = tmp_path_factory.mktemp("chunks") / "log.mcap"
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size, compression=compression)
        w.start()
        sid = w.register_schema("s", "jsonschema", b"{}")
        cids = {t: w.register_channel(t, "json", sid) for t in sorted({t for t, _ in records})}
        for i, (topic, data) in enumerate(records):
            w.add_message(cids[topic], 1000 + i, data, 2000 + i, sequence=i)
        w.finish()
    with open(path, "rb") as f:
        expected = [
            (ch.topic, m.log_time, m.publish_time, m.data)
            for _s, ch, m in make_reader(f).iter_messages(log_time_order=False)
        ]
    unfinished = path.with_suffix(".cut.mcap")
    raw = path.read_bytes()
    unfinished.write_bytes(raw[: raw.rindex(b"\x89MCAP0\r\n")])  # read linearly
    lo, hi = 1000 + min(window), 1000 + max(window)
    for p in (path, unfinished):
        reader = LogReader(p)
        assert [fields(m) for m in reader.messages()] == expected
        for wanted in ([topics.ROBOT_STATE], [topics.COMMANDS]):  # dense and sparse paths
            got = [fields(m) for m in reader.messages(wanted, start=lo, end=hi)]
            assert got == [e for e in expected if e[0] in wanted and lo <= e[1] < hi]
            assert all(type(m.data) is bytes for m in reader.messages(wanted))


def test_serve_streams_the_file_over_the_foxglove_websocket_protocol(
    log_file: Path, tmp_path: Path
) -> None:
    from websockets.sync.client import connect

    from fxcell.recorder.serve import Player

    player = Player(shutil.copy(log_file, tmp_path / "x.mcap"), port=0, autoplay=False)
    runner = threading.Thread(target=player.run, kwargs={"until": 30})
    runner.start()
    try:
        with connect(f"ws://127.0.0.1:{player.port}", subprotocols=["foxglove.sdk.v1"]) as ws:
            info = json.loads(ws.recv(timeout=5))
            assert info["op"] == "serverInfo"
            assert "playbackControl" in info["capabilities"]
            channels: dict[str, dict[str, object]] = {}
            while topics.ROBOT_STATE not in channels:
                msg = ws.recv(timeout=5)
                if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
                    channels.update({c["topic"]: c for c in json.loads(msg)["channels"]})
            assert channels[topics.TF]["schemaName"] == "foxglove.FrameTransforms"
            assert channels[topics.ROBOT_STATE]["schemaName"] == topics.SCHEMA_ROBOT_STATE
            sub = {"id": 3, "channelId": channels[topics.ROBOT_STATE]["id"]}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [sub]}))
            # seek to 1 s into the file and play (0.5 s of data left)
            reader = LogReader(log_file)
            assert reader.start_time is not None
            player.control(seek=reader.start_time + 1_000_000_000, play=True, speed=1.0)
            received = []
            while len(received) < 20:
                msg = ws.recv(timeout=5)
                if isinstance(msg, bytes) and msg[0] == 0x01:
                    sub_id, log_time = struct.unpack_from("<IQ", msg, 1)
                    assert sub_id == 3
                    received.append((log_time, decode_robot_state(msg[13:])))
            assert received[0][0] >= reader.start_time + 1_000_000_000
            assert all(b[0] > a[0] for a, b in itertools.pairwise(received))
            player.control(play=False)
            assert not player.playing
    finally:
        player.stop()
        runner.join(10)
    assert not runner.is_alive()


def test_reexecute_compares_where_the_robot_went_not_when() -> None:
    import numpy as np

    from fxcell.replay import _numeric_deviation, _path_deviation

    t = np.arange(0, 1.0, 0.002)
    q = np.column_stack([np.sin(2 * t + j) for j in range(6)])
    slower = np.column_stack([np.sin(2 * t[::2] * 0.5 + j) for j in range(6)])  # half speed
    late = np.vstack([np.repeat(q[:1], 40, axis=0), q])  # started 80 ms later
    assert _path_deviation(q, late) == pytest.approx(0, abs=1e-12)
    assert _path_deviation(q[: len(q) // 2], slower) == pytest.approx(0, abs=2e-3)
    offset = q + np.array([0, 0, 0.05, 0, 0, 0])  # another path
    assert _path_deviation(q, offset) == pytest.approx(0.05, abs=2e-3)
    # a controller running late streams one sample for 15 cycles (60 mrad apart here):
    # the same path, measured to the line between the samples
    gappy = np.vstack([q[::15], q[-1:]])
    assert _path_deviation(q, gappy) == pytest.approx(0, abs=1e-3)
    assert _path_deviation(gappy, offset) == pytest.approx(0.05, abs=2e-3)
    assert _path_deviation(q, q[: len(q) // 2]) > 0.5  # stopped half way
    assert _numeric_deviation([0.1, [0.2, 0.3]], [0.1, [0.2, 0.35]]) == pytest.approx(0.05)
    assert _numeric_deviation("a", "a") is None
    assert _numeric_deviation("a", "b") == float("inf")
    assert _numeric_deviation([1, 2], [1]) == float("inf")


def test_reexecute_reissues_only_the_commands_a_user_issued() -> None:
    from fxcell.replay import CommandRecord, top_level_commands

    def cmd(i: int, name: str, start: float, end: float) -> CommandRecord:
        return CommandRecord(i, name, {}, "library", start, end, "ok")

    commands = [
        cmd(1, "init", 0.0, 1.0),
        cmd(2, "power_on", 0.1, 0.4),  # issued by init
        cmd(3, "brake_release", 0.4, 0.8),  # issued by init
        cmd(4, "move_joint", 2.0, 5.0),
        cmd(5, "stop", 3.0, 3.1),  # a user's stop during the move: kept
        cmd(6, "power_off", 6.0, 6.1),
    ]
    assert [c.name for c in top_level_commands(commands)] == [
        "init",
        "move_joint",
        "stop",
        "power_off",
    ]


@given(
    times=st.lists(st.floats(0, 100, allow_nan=False), max_size=40),
    gap=st.floats(0.01, 10),
)
def test_plot_labels_are_merged_so_that_no_two_stand_closer_than_the_gap(
    times: list[float], gap: float
) -> None:
    marks = sorted((t, f"c{i}") for i, t in enumerate(times))
    labels = _declutter(marks, gap)
    xs = [x for x, _ in labels]
    assert all(b - a >= gap for a, b in itertools.pairwise(xs))
    merged = sum(int(text.split("+")[1]) if "+" in text else 0 for _, text in labels)
    assert len(labels) + merged == len(marks)  # every mark is labelled or counted


def test_summary_tells_each_job_samples_story(tmp_path: Path) -> None:
    from fxcell.events import DeviceEvent

    t0 = 1_790_000_000.0
    rec = Recorder(tmp_path, chunk_duration=0.1)
    moves = [
        ("S01", "crucible", "rack:A1", "gripper"),
        ("S01", "crucible", "gripper", "machine:A1"),
        ("S02", "crucible", "rack:A2", "gripper"),
    ]
    for n, (sample, obj, src, dst) in enumerate(moves):
        end = {"event": "step", "phase": "end", "seq": n, "kind": "pick", "outcome": "done",
               "moved": [{"sample": sample, "object": obj, "from": src, "to": dst}]}  # fmt: skip
        rec.submit(DeviceEvent(t0 + n, "job", {"t": t0 + n, "run": 1, **end}))
    rec.close()
    (path,) = rec.stats.files
    s = summarize(path)
    assert list(s.samples) == ["S01", "S02"]
    assert ["rack:A1 → gripper" in s.samples["S01"][0], "→ machine:A1" in s.samples["S01"][1]] == [
        True,
        True,
    ]
    text = format_summary(s)
    assert "job samples: 2" in text
    assert "crucible rack:A2 → gripper" in text
