"""A Ned2 cell records itself as a UR3e cell does: its MCAP holds the Ned2's URDF and
``/tf`` frames that compose to the Ned2's kinematics (Foxglove shows a Ned2), and ``fxcell
replay`` summarises, lists, plots and re-executes it against a Ned2 simulator."""

from __future__ import annotations

import asyncio
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from fxcell import Cell
from fxcell.cli import main
from fxcell.config import CellConfig, JointLimits, SceneConfig, SceneObject
from fxcell.errors import InvalidArgumentError
from fxcell.geometry import Pose
from fxcell.motion import ned2
from fxcell.recorder import topics
from fxcell.recorder.protobuf import decode_robot_state
from fxcell.replay import reexecute, summarize, timeline, top_level_commands
from fxcell.testing.ned2 import Ned2SimulatorHandle, ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(240)]

TCP = (0.05, 0.0, 0.01, 0.0, 0.2, 0.0)
TABLE = SceneObject(name="table", size=(1.0, 1.0, 0.05), position=(0.0, 0.0, -0.025))
TARGET = [0.6, -0.3, 0.2, 0.4, -0.5, 0.3]


def _config() -> CellConfig:
    limits = JointLimits(
        position_min=tuple(ned2.LOWER),
        position_max=tuple(ned2.UPPER),
        velocity=tuple(ned2.VELOCITY_LIMITS),
        acceleration=tuple(ned2.ACCELERATION_LIMITS),
    )
    config = CellConfig()
    return config.model_copy(
        update={
            "robot": config.robot.model_copy(update={"kind": "ned2"}),
            "tool": config.tool.model_copy(update={"tcp": TCP}),
            "limits": limits,
            "scene": SceneConfig(objects=(TABLE,)),
        }
    )


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("ned2_logs")

    async def record(sim: Ned2SimulatorHandle) -> None:
        async with Cell(config=_config(), host=sim.host, record=directory) as cell:
            await cell.init()
            await cell.move_joint(TARGET)
            await cell.get_current_joint_values()

    with ned2_simulator(time_scale=1.0, calibrated=True) as sim:
        asyncio.run(record(sim))
    (path,) = directory.glob("*.mcap")
    return path


def _read(path: Path) -> tuple[dict[str, bytes], list[tuple[str, int, bytes]]]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        attachments = {a.name: a.data for a in reader.iter_attachments()}
        messages = [
            (ch.topic, msg.log_time, msg.data)
            for _s, ch, msg in reader.iter_messages(log_time_order=False)
        ]
    return attachments, messages


def test_a_ned2_recording_holds_the_ned2s_urdf(recording: Path) -> None:
    attachments, messages = _read(recording)
    assert set(attachments) == {"ned2.urdf"}
    urdf = attachments["ned2.urdf"].decode()
    root = ET.fromstring(urdf)
    assert root.get("name") == "niryo_ned2"
    revolute = [j.get("name") for j in root.iter("joint") if j.get("type") == "revolute"]
    assert revolute == list(ned2.JOINT_NAMES)
    links = {link.get("name") for link in root.iter("link")}
    assert {"base_link", "hand_link", "tool_link", "gripper_link", "tcp"} <= links
    description = [json.loads(d) for t, _, d in messages if t == topics.ROBOT_DESCRIPTION]
    assert description == [{"data": urdf}]


def test_a_ned2_recordings_frames_compose_to_the_ned2s_kinematics(recording: Path) -> None:
    _, messages = _read(recording)
    states = {t: decode_robot_state(d) for topic, t, d in messages if topic == topics.ROBOT_STATE}
    frames = [(t, json.loads(d)) for topic, t, d in messages if topic == topics.TF]
    assert len(frames) > 30  # 30 Hz over the session
    bare, tooled = ned2.Ned2Kinematics(), ned2.Ned2Kinematics(Pose.from_ur(TCP))
    seen = []
    for t, message in frames:
        q = states[t].actual_q  # the sample the frames were made from
        world = {"base_link": np.eye(4)}
        for tf in message["transforms"]:
            tr, rot = tf["translation"], tf["rotation"]
            local = Pose.from_quaternion(
                [tr["x"], tr["y"], tr["z"]], [rot["x"], rot["y"], rot["z"], rot["w"]]
            ).matrix
            world[tf["child_frame_id"]] = world[tf["parent_frame_id"]] @ local
        for frame, kinematics in (("tool_link", bare), ("tcp", tooled)):
            expected = kinematics.forward(q).matrix
            assert np.max(np.abs(world[frame][:3, 3] - expected[:3, 3])) < 1e-6, frame
            assert np.max(np.abs(world[frame][:3, :3] - expected[:3, :3])) < 1e-6, frame
        seen.append(q)
    assert np.max(np.ptp(np.array(seen), axis=0)) > 0.3  # the frames follow the move
    assert np.allclose(seen[-1], TARGET, atol=1e-3)


def test_replay_summarises_lists_and_plots_a_ned2_recording(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    summary = summarize(recording)
    assert summary.robot_kind == "ned2"
    issued = top_level_commands(summary.commands)
    assert [c.name for c in issued] == ["init", "move_joint", "get_current_joint_values"]
    assert all(c.outcome == "ok" for c in summary.commands)
    assert any("move_joint" in line for line in timeline(recording))
    plot = tmp_path / "ned2.png"
    assert main(["replay", str(recording), "--plot", str(plot)]) == 0
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["replay", str(recording)]) == 0
    assert "robot kind: ned2" in capsys.readouterr().out


async def test_a_ned2_recording_re_executes_on_a_ned2_cell_only(recording: Path) -> None:
    with pytest.raises(InvalidArgumentError, match="recorded on a ned2 cell"):
        await reexecute(recording, config=CellConfig())
    report = await reexecute(recording, config=_config())
    assert [c.name for c in report.comparisons] == [
        "init",
        "move_joint",
        "get_current_joint_values",
    ]
    assert report.unexpected == [], report.format()
