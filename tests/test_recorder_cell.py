"""A scripted cell session against the simulator, recorded with Cell(record=...), read back and
re-executed (``fxcell replay --re-execute``)."""

from __future__ import annotations

import asyncio
import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import jsonschema
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

import fxcell
from fxcell import Cell, CellState
from fxcell.config import CellConfig
from fxcell.events import CommandEvent, Event, StateEvent, TransitionEvent
from fxcell.protocol import CONTROL_PERIOD
from fxcell.recorder import topics
from fxcell.recorder.protobuf import decode_robot_state
from fxcell.replay import ReexecuteReport, reexecute
from fxcell.testing import simulator

TIME_SCALE = 0.05
A = (0.3, -1.4, 0.4, -1.6, -0.2, 0.1)


@dataclass
class Session:
    path: Path
    published: list[Event]
    late_cycles: int
    """Controller cycles the simulator ran late (it then streams one sample for several)."""


async def _script(cell: Cell) -> None:
    await cell.init()
    await cell.get_current_pose()
    await cell.move_joint(A, velocity_factor=0.3)
    await cell.get_current_pose()
    await cell.get_current_joint_values()
    await cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY)  # the move's end has landed
    # A standalone start of external control is recorded with its mode: re-execution
    # passes only the command's own arguments (it failed with TypeError before).
    await cell.stop_external_control()
    await cell.start_external_control()
    await cell.power_off()


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Session:
    directory = tmp_path_factory.mktemp("logs")
    published: list[Event] = []

    async def record() -> int:
        with simulator(time_scale=TIME_SCALE) as sim:
            late = sim.state()["late_cycles"]
            cell = Cell(host=sim.host, record=directory)
            cell.bus.subscribe(published.append)
            async with cell:
                await _script(cell)
            return int(sim.state()["late_cycles"] - late)

    late = asyncio.run(record())
    (path,) = directory.glob("*.mcap")
    return Session(path, published, late)


def test_a_scripted_cell_session_is_recorded_completely(session: Session) -> None:
    with open(session.path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
        recorded = [
            (ch.topic, msg.data) for _s, ch, msg in reader.iter_messages(log_time_order=False)
        ]
    published = session.published

    # every command and transition, in order, with its outcome
    commands = [json.loads(d) for t, d in recorded if t == topics.COMMANDS]
    sent = [e for e in published if isinstance(e, CommandEvent)]
    assert [(c["command_id"], c["name"], c["outcome"]) for c in commands] == [
        (e.command_id, e.name, e.outcome) for e in sent
    ]
    names = [c["name"] for c in commands if c["phase"] == "start"]
    assert names[0] == "init"
    assert {"move_joint", "get_current_pose", "power_off"} <= set(names)
    assert all(c["outcome"] != "error" for c in commands)
    transitions = [json.loads(d) for t, d in recorded if t == topics.TRANSITIONS]
    assert [(t["source"], t["dest"], t["trigger"]) for t in transitions] == [
        (e.source, e.dest, e.trigger) for e in published if isinstance(e, TransitionEvent)
    ]
    assert len(transitions) >= 6
    assert any(json.loads(d)["kind"] == "trajectory" for t, d in recorded if t == topics.MOTION)

    # every state sample the cell published, bit for bit, and at the full rate
    states = [decode_robot_state(d) for t, d in recorded if t == topics.ROBOT_STATE]
    # IO is recorded on /robot/io whenever a digital bit changes, not in every state sample.
    io_free = dict.fromkeys(("digital_input_bits", "digital_output_bits"), 0) | {
        f"standard_analog_{d}{i}": 0.0 for d in ("input", "output") for i in (0, 1)
    }
    published_states = [e.sample for e in published if isinstance(e, StateEvent)]
    assert states == [dataclasses.replace(s, **io_free) for s in published_states]
    io = [json.loads(d) for t, d in recorded if t == topics.IO]
    changes = {(s.digital_input_bits, s.digital_output_bits) for s in published_states}
    assert {(m["digital_input_bits"], m["digital_output_bits"]) for m in io} == changes
    span = states[-1].timestamp - states[0].timestamp
    expected = span / CONTROL_PERIOD + 1
    # A simulator starved of CPU runs late cycles without streaming them (a real controller
    # never does): those samples never existed, so they do not count against the recording.
    streamed = expected - session.late_cycles
    assert len(states) >= 0.999 * streamed, (
        f"{len(states)} state samples over {span:.3f} s of controller time: "
        f"{len(states) / expected:.2%} of 500 Hz, {session.late_cycles} cycles the simulator "
        "ran late"
    )

    # metadata: fxcell version, config snapshot, and the controller's version and serial
    with open(session.path, "rb") as f:
        records = [dict(m.metadata) for m in make_reader(f).iter_metadata() if m.name == "fxcell"]
    meta = records[-1]  # readers take the last record: everything known by then
    assert meta["fxcell_version"] == fxcell.__version__
    assert json.loads(meta["config"])["tool"]["tcp"] == list(CellConfig.load().tool.tcp)
    assert meta["controller_version"].startswith("URSoftware 5.")
    assert meta["serial"].isdigit()

    # schemas Foxglove understands
    assert schemas[topics.TF].name == "foxglove.FrameTransforms"
    assert schemas[topics.LOG].name == "foxglove.Log"
    for topic, schema in schemas.items():
        if schema.encoding == topics.JSONSCHEMA:
            jsonschema.Draft202012Validator.check_schema(json.loads(schema.data))
        else:
            assert topic == topics.ROBOT_STATE
            fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
            pool = descriptor_pool.DescriptorPool()
            for file in fds.file:
                pool.Add(file)
            message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))


async def _reexecute(path: Path, config: CellConfig) -> ReexecuteReport:
    return await reexecute(path, config=config, time_scale=TIME_SCALE)


async def test_reexecuting_a_session_reproduces_it(session: Session) -> None:
    report = await _reexecute(session.path, CellConfig())
    assert report.unexpected == [], report.format()
    moves = [c for c in report.comparisons if c.name == "move_joint"]
    assert len(moves) == 1
    assert all(c.joint_deviation is not None for c in moves)
    assert report.comparisons[0].name == "init"  # power_on etc. came from init
    (start,) = [c for c in report.comparisons if c.name == "start_external_control"]
    assert start.args["mode"] == "script"  # recorded context, not an argument
    assert start.outcome == "ok"


async def test_reexecuting_with_another_tcp_reports_the_deviation(session: Session) -> None:
    other = CellConfig.from_dict({"tool": {"tcp": [0.0, 0.0, 0.2, 0.0, 0.0, 0.0]}})
    report = await _reexecute(session.path, other)
    flagged = {problem.split(":")[0] for problem in report.unexpected}
    assert flagged == {"get_current_pose"}, report.format()  # joint moves ignore the TCP
