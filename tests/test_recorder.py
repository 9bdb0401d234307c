"""The MCAP flight recorder, fed with synthetic event streams and read back with ``mcap``."""

from __future__ import annotations

import errno
import json
import math
import threading
import time
import xml.etree.ElementTree as ET
from dataclasses import fields
from pathlib import Path
from typing import IO, Any

import jsonschema
import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from waiting import wait_until

from fxcell.errors import InvalidArgumentError, RecorderError
from fxcell.events import CommandEvent, EventBus, LogEvent, Origin, StateEvent, TransitionEvent
from fxcell.motion.kinematics import JOINT_NAMES as JOINTS
from fxcell.motion.kinematics import Kinematics
from fxcell.protocol import RobotMode, RobotState, RuntimeState, SafetyMode
from fxcell.recorder import Recorder, is_finished, recover, topics
from fxcell.recorder.frames import LinkFrames
from fxcell.recorder.protobuf import (
    _decode_robot_state_general,
    decode_robot_state,
    encode_robot_state,
    robot_state_schema,
)
from fxcell.recorder.synthetic import SyntheticSession, play

TCP = (-0.00025, 0.00245, 0.14789, 0.0, 0.0, -1.5708)


def read_all(path: Path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as f:
        return [
            (ch.topic, msg.log_time, msg.data)
            for _s, ch, msg in make_reader(f).iter_messages(log_time_order=False)
        ]


@pytest.fixture
def session_file(tmp_path: Path) -> tuple[Path, SyntheticSession, int]:
    session = SyntheticSession(6.0, protective_stop_at=2.7)
    rec = Recorder(tmp_path, metadata={"serial": "20235500001", "config": {"tcp": TCP}}, tcp=TCP)
    bus = EventBus()
    rec.attach(bus)
    n = play(session, bus.publish)
    rec.close()
    assert rec.stats.messages_dropped == 0
    (path,) = rec.stats.files
    return path, session, n


def test_every_command_transition_and_state_is_written_in_order(
    session_file: tuple[Path, SyntheticSession, int],
) -> None:
    path, session, _ = session_file
    expected = [p.event for p in session.events()]
    messages = read_all(path)
    commands = [json.loads(d) for t, _, d in messages if t == topics.COMMANDS]
    sent_commands = [e for e in expected if isinstance(e, CommandEvent)]
    assert [(c["command_id"], c["outcome"]) for c in commands] == [
        (e.command_id, e.outcome) for e in sent_commands
    ]
    failed = [c for c in commands if c["outcome"] == "error"]
    assert failed
    assert failed[0]["error_type"] == "ProtectiveStopError"
    transitions = [json.loads(d) for t, _, d in messages if t == topics.TRANSITIONS]
    assert [(t["source"], t["dest"]) for t in transitions] == [
        (e.source, e.dest) for e in expected if isinstance(e, TransitionEvent)
    ]
    states = [decode_robot_state(d) for t, _, d in messages if t == topics.ROBOT_STATE]
    sent_states = [e.sample for e in expected if isinstance(e, StateEvent)]
    assert states == sent_states  # every sample, bit for bit, in order
    log_times = [t for _, t, _ in messages]
    assert log_times == sorted(log_times)
    modes = [json.loads(d) for t, _, d in messages if t == topics.ROBOT_MODES]
    assert [m["safety_mode"] for m in modes] == ["NORMAL", "PROTECTIVE_STOP", "NORMAL"]


def test_file_carries_metadata_and_the_urdf(
    session_file: tuple[Path, SyntheticSession, int],
) -> None:
    path, _, _ = session_file
    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = {a.name: a for a in reader.iter_attachments()}
    assert meta[topics.METADATA_NAME]["serial"] == "20235500001"
    assert json.loads(meta[topics.METADATA_NAME]["config"]) == {"tcp": list(TCP)}
    assert meta[topics.METADATA_NAME]["fxcell_version"]
    urdf = ET.fromstring(attachments[topics.URDF_ATTACHMENT].data)
    revolute = [j.get("name") for j in urdf.iter("joint") if j.get("type") == "revolute"]
    assert revolute == list(JOINTS)
    description = [json.loads(d) for t, _, d in read_all(path) if t == topics.ROBOT_DESCRIPTION]
    assert description == [{"data": attachments[topics.URDF_ATTACHMENT].data.decode()}]


def test_schemas_are_valid_and_use_the_foxglove_names(
    session_file: tuple[Path, SyntheticSession, int],
) -> None:
    import foxglove.messages as fox

    path, _, _ = session_file
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        by_topic = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
        samples: dict[str, bytes] = {}
        for _s, ch, msg in reader.iter_messages(log_time_order=False):
            samples.setdefault(ch.topic, msg.data)
    assert set(by_topic) == set(topics.ALL_TOPICS)
    assert by_topic[topics.TF].name == "foxglove.FrameTransforms"
    assert by_topic[topics.LOG].name == "foxglove.Log"
    for topic, schema in by_topic.items():
        if schema.encoding == topics.JSONSCHEMA:
            definition = json.loads(schema.data)
            jsonschema.Draft202012Validator.check_schema(definition)
            assert definition["title"] == schema.name
            if topic in samples:
                jsonschema.validate(json.loads(samples[topic]), definition)
        else:
            assert schema.encoding == topics.PROTOBUF
            fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
            pool = descriptor_pool.DescriptorPool()
            for file in fds.file:
                pool.Add(file)
            cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
            msg = cls.FromString(samples[topic])
            state = decode_robot_state(samples[topic])
            assert list(msg.actual_q) == list(state.actual_q)
            assert msg.robot_mode == state.robot_mode
    # the JSON field names are Foxglove's own (checked against the foxglove SDK's schemas)
    for topic, sdk in ((topics.TF, fox.FrameTransforms), (topics.LOG, fox.Log)):
        fds = descriptor_pb2.FileDescriptorSet.FromString(sdk.get_schema().data)
        fields = {m.name: {f.name for f in m.field} for f in fds.file for m in f.message_type}
        ours = json.loads(by_topic[topic].data)
        props = ours["properties"]
        if topic == topics.TF:
            assert set(props) == fields["FrameTransforms"]
            assert set(props["transforms"]["items"]["properties"]) == fields["FrameTransform"]
        else:
            assert set(props) == fields["Log"]


def test_link_frames_compose_to_the_forward_kinematics() -> None:
    from fxcell.geometry import Pose

    frames = LinkFrames(TCP)
    kin = Kinematics.ur3e(TCP)
    rng = np.random.default_rng(7)
    for _ in range(20):
        q = rng.uniform(-math.pi, math.pi, 6)
        world = {"base": np.eye(4)}
        transforms = frames.transforms(list(q), {"sec": 0, "nsec": 0})
        assert transforms is not None
        for t in transforms:
            tr, rot = t["translation"], t["rotation"]
            T = Pose.from_quaternion(
                [tr["x"], tr["y"], tr["z"]], [rot["x"], rot["y"], rot["z"], rot["w"]]
            ).matrix
            world[t["child_frame_id"]] = world[t["parent_frame_id"]] @ T
        encoded = frames.transforms_json(list(q), 0, 0)
        assert encoded is not None
        assert json.loads(encoded) == {"transforms": transforms}  # the fast path agrees
        fk = kin.joint_frames(q)
        np.testing.assert_allclose(world["flange"], fk[6], atol=1e-12)
        np.testing.assert_allclose(world["tcp"], fk[7], atol=1e-12)


states = st.builds(
    RobotState,
    timestamp=st.floats(allow_nan=False),
    robot_mode=st.sampled_from(RobotMode),
    safety_mode=st.sampled_from(SafetyMode),
    runtime_state=st.sampled_from(RuntimeState),
    robot_status_bits=st.integers(0, 2**32 - 1),
    safety_status_bits=st.integers(0, 2**32 - 1),
    actual_q=st.lists(st.floats(allow_nan=False), min_size=0, max_size=8).map(tuple),
    actual_tcp_pose=st.tuples(*[st.floats(-10, 10)] * 6),
    output_int_registers=st.tuples(*[st.integers(-(2**31), 2**31 - 1)] * 3),
    speed_scaling=st.floats(0, 1),
)


@settings(max_examples=150, deadline=None)
@given(states)
def test_robot_state_protobuf_round_trips(state: RobotState) -> None:
    assert decode_robot_state(encode_robot_state(state)) == state


mode_values = st.one_of(
    st.sampled_from([*RobotMode, *SafetyMode, *RuntimeState]).map(int),
    st.integers(-(2**31), 2**31 - 1),  # values no enum knows stay plain ints
)


@settings(max_examples=150, deadline=None)
@given(states, st.tuples(mode_values, mode_values, mode_values))
def test_robot_state_fast_decode_matches_the_general_one(
    state: RobotState, modes: tuple[int, int, int]
) -> None:
    state.robot_mode, state.safety_mode, state.runtime_state = modes  # type: ignore[assignment]
    data = encode_robot_state(state)
    general = _decode_robot_state_general(data)
    assert general == state
    for _ in range(2):  # the second time from the cache of enum prefixes
        for payload in (data, memoryview(data), bytearray(data)):
            fast = decode_robot_state(payload)  # type: ignore[arg-type]
            assert fast == general
            for f in fields(RobotState):  # an enum stays an enum, an int an int
                assert type(getattr(fast, f.name)) is type(getattr(general, f.name)), f.name


def test_robot_state_schema_parses_with_protobuf() -> None:
    fds = descriptor_pb2.FileDescriptorSet.FromString(robot_state_schema())
    pool = descriptor_pool.DescriptorPool()
    for file in fds.file:
        pool.Add(file)
    desc = pool.FindMessageTypeByName(topics.SCHEMA_ROBOT_STATE)
    names = {f.name for f in desc.fields}
    assert {"actual_q", "target_q", "actual_current", "actual_tcp_pose", "safety_mode"} <= names
    state = RobotState(safety_mode=SafetyMode.PROTECTIVE_STOP, actual_q=(1, 2, 3, 4, 5, 6))
    msg = message_factory.GetMessageClass(desc).FromString(encode_robot_state(state))
    safety = desc.fields_by_name["safety_mode"].enum_type
    assert safety.full_name == "fxcell.SafetyMode"
    assert safety.values_by_number[msg.safety_mode].name == "SAFETY_MODE_PROTECTIVE_STOP"


def test_chunks_close_every_chunk_duration(tmp_path: Path) -> None:
    rec = Recorder(tmp_path, chunk_duration=0.2, tf_rate=0)
    play(SyntheticSession(1.2), rec.submit, realtime=True)
    rec.close()
    with open(rec.stats.files[0], "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    spans = [(c.message_end_time - c.message_start_time) / 1e9 for c in summary.chunk_indexes]
    assert len(spans) >= 5
    assert max(spans) <= 0.2
    assert rec.stats.chunks_written == len(spans)


def test_rotation_by_size_and_time_keeps_every_message(tmp_path: Path) -> None:
    rec = Recorder(tmp_path, chunk_duration=0.05, rotate_size=25_000, rotate_duration=0.3)
    n = play(SyntheticSession(1.0), rec.submit, realtime=True)
    rec.close()
    files = rec.stats.files
    assert len(files) >= 3
    assert list(files) == sorted(files)  # names sort by start time
    assert sorted(tmp_path.glob("*.mcap")) == sorted(files)
    total = 0
    for path in files:
        assert is_finished(path)
        with open(path, "rb") as f:
            reader = make_reader(f)
            assert topics.METADATA_NAME in {m.name for m in reader.iter_metadata()}
        total += sum(1 for t, _, _ in read_all(path) if t == topics.ROBOT_STATE)
    assert total == 500
    assert rec.stats.messages_written == sum(rec.stats.per_topic.values())
    assert n > 500


class _Disk:
    """A disk with a byte budget: writes past it fail with ENOSPC, as a full disk does."""

    def __init__(self, budget: int) -> None:
        self.budget = budget
        self.lock = threading.Lock()

    def open(self, path: Path) -> IO[bytes]:
        disk = self
        raw = open(path, "xb")  # noqa: SIM115

        class Stream:
            def write(self, data: bytes) -> int:
                with disk.lock:
                    if len(data) > disk.budget:
                        raise OSError(errno.ENOSPC, "No space left on device")
                    disk.budget -= len(data)
                return raw.write(data)

            def __getattr__(self, name: str) -> Any:
                return getattr(raw, name)

        return Stream()  # type: ignore[return-value]


def test_full_disk_is_reported_counted_and_survived(tmp_path: Path) -> None:
    disk = _Disk(budget=20_000)
    errors: list[str] = []

    class OnDisk(Recorder):
        def _open_stream(self, path: Path) -> IO[bytes]:
            return disk.open(path)

    rec = OnDisk(tmp_path, chunk_duration=0.05, retry_interval=0.1, on_error=errors.append)
    session = SyntheticSession(1.0)
    sent = play(session, rec.submit, realtime=True)
    wait_until(lambda: rec.stats.messages_dropped > 0, 10.0, "a dropped message")
    assert any("No space left" in e for e in errors)
    assert any("dropped" in e for e in errors)
    with disk.lock:
        disk.budget = 10**9  # space freed: the recorder starts a new file
    wait_until(
        lambda: rec.stats.messages_written > 0 and rec.current_file is not None,
        10.0,
        "a written message in an open file",
    )
    more = play(SyntheticSession(0.3), rec.submit)
    rec.close()
    stats = rec.stats
    assert stats.errors >= 2
    unfinished = [p for p in tmp_path.glob("*.mcap") if not is_finished(p)]
    assert unfinished  # the file the disk filled up is recoverable up to its last chunk
    for p in unfinished:
        recover(p)
    messages = [m for p in sorted(tmp_path.glob("*.mcap")) for m in read_all(p)]
    assert stats.messages_written <= len(messages)
    sent_states = 500 + 150
    recorded_states = sum(1 for t, _, _ in messages if t == topics.ROBOT_STATE)
    assert recorded_states < sent_states
    # every sample is in a file or counted as dropped
    assert recorded_states + stats.messages_dropped >= sent_states
    assert sent + more > sent_states


def test_slow_disk_drops_and_counts_instead_of_blocking_the_caller(tmp_path: Path) -> None:
    stall, release = threading.Event(), threading.Event()

    class Stalled(Recorder):
        def _open_stream(self, path: Path) -> IO[bytes]:
            raw = open(path, "xb")  # noqa: SIM115

            class Stream:
                def write(self, data: bytes) -> int:
                    if stall.is_set():
                        release.wait(20)
                    return raw.write(data)

                def __getattr__(self, name: str) -> Any:
                    return getattr(raw, name)

            return Stream()  # type: ignore[return-value]

    rec = Stalled(tmp_path, chunk_duration=0.05, max_queue=200, tf_rate=0)
    try:
        stall.set()  # the disk hangs from now on (for 20 s unless released)
        bus = EventBus()
        rec.attach(bus)
        worst = 0.0
        for i in range(2000):
            t = time.perf_counter()
            bus.publish(StateEvent(RobotState(timestamp=i * 0.002)))
            worst = max(worst, time.perf_counter() - t)
            if i % 100 == 0:
                time.sleep(0.005)
        # the publisher never waits for the disk (that would be the 20 s hang); a busy
        # machine may still deschedule it for a few hundred milliseconds
        assert worst < 2.0
        wait_until(lambda: rec.stats.messages_dropped > 0, 10.0, "a dropped message")
    finally:
        release.set()
        rec.close()
    stats = rec.stats
    assert stats.queue_high_water >= 190
    states = stats.per_topic[topics.ROBOT_STATE]
    assert states + stats.messages_dropped == 2000
    written = sum(1 for t, _, _ in read_all(stats.files[0]) if t == topics.ROBOT_STATE)
    assert written == states


def test_bad_arguments_raise_typed_errors(tmp_path: Path) -> None:
    with pytest.raises(InvalidArgumentError):
        Recorder(tmp_path, chunk_duration=0)
    with pytest.raises(InvalidArgumentError):
        Recorder(tmp_path, compression="gzip")
    with pytest.raises(InvalidArgumentError):
        Recorder(tmp_path, max_queue=0)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(RecorderError):
        Recorder(blocker / "logs")
    assert not list(tmp_path.glob("*.mcap"))


def test_attach_twice_is_refused_and_close_stops_recording(tmp_path: Path) -> None:
    bus = EventBus()
    with Recorder(tmp_path) as rec:
        rec.attach(bus)
        with pytest.raises(RecorderError):
            rec.attach(bus)
        bus.publish(LogEvent(time.time(), 30, "test", "before close"))
    bus.publish(LogEvent(time.time(), 30, "test", "after close"))
    logs = [json.loads(d) for t, _, d in read_all(rec.stats.files[0]) if t == topics.LOG]
    assert [m["message"] for m in logs] == ["before close"]
    assert logs[0]["level"] == 3  # foxglove WARNING


def test_command_arguments_of_any_type_are_recorded(tmp_path: Path) -> None:
    from fxcell.geometry import Pose

    with Recorder(tmp_path) as rec:
        args = {
            "q": np.array([0.1, 0.2]),
            "pose": Pose.from_ur([0.1, 0.2, 0.3, 0, 0, 0]),
            "mode": SafetyMode.NORMAL,
            "path": tmp_path,
            "nan": float("nan"),
        }
        rec.submit(CommandEvent(1, "move_pose", args, Origin.DAEMON, time.time()))
    (cmd,) = [json.loads(d) for t, _, d in read_all(rec.stats.files[0]) if t == topics.COMMANDS]
    assert cmd["args"]["q"] == [0.1, 0.2]
    assert cmd["args"]["pose"]["position"] == [0.1, 0.2, 0.3]
    assert cmd["args"]["mode"] == 1
    assert cmd["args"]["nan"] == "nan"
    assert cmd["origin"] == "daemon"


def test_fxcell_warnings_are_recorded_as_foxglove_logs(tmp_path: Path) -> None:
    import logging

    with Recorder(tmp_path) as rec:
        logging.getLogger("fxcell.cell.cell").warning("gripper %s did not open", "hand-e")
        logging.getLogger("elsewhere").warning("not ours")
    (entry,) = [json.loads(d) for t, _, d in read_all(rec.stats.files[0]) if t == topics.LOG]
    assert entry["message"] == "gripper hand-e did not open"
    assert entry["name"] == "fxcell.cell.cell"
    assert entry["level"] == 3
    assert entry["file"].endswith("test_recorder.py")
    assert entry["line"] > 0
    capture = [h for h in logging.getLogger("fxcell").handlers if type(h).__name__ == "_LogCapture"]
    assert capture == []  # removed on close


def test_metadata_learned_later_reaches_the_current_and_next_files(tmp_path: Path) -> None:
    from fxcell.recorder.reading import LogReader

    rec = Recorder(tmp_path, metadata={"serial": "unknown"}, chunk_duration=0.05, rotate_size=1)
    rec.update_metadata({"serial": "20235500001", "controller_version": "5.15.0"})
    play(SyntheticSession(0.3), rec.submit, realtime=True)
    rec.close()
    first, *later = rec.stats.files
    assert later  # rotated (every chunk is over 1 byte)
    for path in (first, later[-1]):
        meta = LogReader(path).metadata[topics.METADATA_NAME]
        assert meta["serial"] == "20235500001"
        assert meta["controller_version"] == "5.15.0"
