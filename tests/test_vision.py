"""The placement check on rendered frames: each fault gets its verdict, a correct holder passes.

Frames come from the simulator's renderer (``fxcell.testing.vision``) with imaging conditions
that are not ideal (exposure, light gradient, noise, defocus, JPEG, a camera knocked a little).
"""

from __future__ import annotations

import asyncio
import math
import random
import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fxcell.config import CellConfig
from fxcell.errors import (
    CameraError,
    CameraNotConfiguredError,
    ConfigError,
    InvalidArgumentError,
)
from fxcell.job.store import SCHEMA_VERSION, JobStore
from fxcell.testing.vision import Fault, Imaging, Thing, VisionBench, random_imaging
from fxcell.vision.camera import OpenCVCamera, SnapshotCamera, open_camera

ALL = ("A1", "A2", "A3", "A4")
# a realistic, not ideal, frame: dimmer, uneven light, noisy, a little soft, compressed,
# the camera knocked by a few millimetres and a fraction of a degree
LAB_DAY = Imaging(
    gain=0.8,
    gradient=(0.2, -0.15),
    noise=5.0,
    blur=0.8,
    jpeg_quality=80,
    shift=(0.004, -0.003, 0.006, 0.008, -0.006, 0.015),
    seed=7,
)


@pytest.fixture(scope="module")
def bench() -> VisionBench:
    return VisionBench()


def test_four_seated_crucibles_pass(bench: VisionBench) -> None:
    report = bench.check(bench.render(dict.fromkeys(ALL, "seated"), LAB_DAY), set(ALL))
    assert report.ok, report.reason
    assert report.verdicts() == dict.fromkeys(ALL, "seated")
    assert report.holder_found
    assert report.markers == 4
    for p in report.positions:
        assert p.offset_mm is not None
        assert p.offset_mm < 1.0
        assert p.confidence >= 0.5
    assert report.image[:2] == b"\xff\xd8"  # the annotated frame, JPEG


@pytest.mark.parametrize("distance_mm", [2.0, 4.0, 6.0, 10.0])
@pytest.mark.parametrize("direction", [0.0, 2.0, 4.2])
def test_an_offset_crucible_is_offset_by_the_measured_distance(
    bench: VisionBench, distance_mm: float, direction: float
) -> None:
    positions: dict[str, Fault | str] = dict.fromkeys(ALL, "seated")
    positions["A3"] = Fault.offset(distance_mm / 1000, direction)
    report = bench.check(bench.render(positions, LAB_DAY), set(ALL))
    assert not report.ok
    a3 = report.position("A3")
    assert a3.verdict == "offset", a3
    assert a3.offset_mm == pytest.approx(distance_mm, abs=0.5)
    assert "A3" in report.reason
    assert "off its position" in report.reason
    assert {p.slot for p in report.positions if not p.ok} == {"A3"}


@pytest.mark.parametrize("tilt_deg", [15.0, 20.0, 25.0])
def test_a_crucible_resting_on_the_pocket_edge_is_tilted(
    bench: VisionBench, tilt_deg: float
) -> None:
    positions: dict[str, Fault | str] = dict.fromkeys(ALL, "seated")
    positions["A2"] = Fault.tilted(math.radians(tilt_deg), azimuth=2.5)
    report = bench.check(bench.render(positions, LAB_DAY), set(ALL))
    assert report.position("A2").verdict == "tilted"
    assert not report.ok


def test_a_missing_crucible_is_an_empty_position_that_fails(bench: VisionBench) -> None:
    positions: dict[str, Fault | str] = {"A1": "seated", "A2": "seated", "A4": "seated"}
    report = bench.check(bench.render(positions, LAB_DAY), set(ALL))
    assert report.position("A3").verdict == "empty"
    assert not report.ok
    assert "A3: no crucible" in report.reason


@pytest.mark.parametrize(
    "fault",
    [
        Fault.foreign("box", 0.03, (60.0, 90.0, 200.0)),
        Fault.foreign("box", 0.025, (225.0, 225.0, 225.0), seed=3),
        Fault.foreign("bead"),
        Fault.foreign("lump", 0.03, (225.0, 225.0, 225.0), seed=11),
        Fault.foreign("box", 0.035, (25.0, 25.0, 28.0)),
    ],
    ids=["blue box", "white box", "bead ring", "flux lump", "black box"],
)
def test_something_that_is_not_a_crucible_is_foreign(bench: VisionBench, fault: Fault) -> None:
    positions: dict[str, Fault | str] = dict.fromkeys(ALL, "seated")
    positions["A1"] = fault
    report = bench.check(bench.render(positions, LAB_DAY), set(ALL))
    assert report.position("A1").verdict == "foreign", report.position("A1")
    assert not report.ok


def test_a_crucible_left_between_positions_is_an_obstruction(bench: VisionBench) -> None:
    deck = bench.deck
    stray = Thing("crucible", (0.09, 0.04, 0.0), deck.kind.width, deck.kind.height)
    report = bench.check(
        bench.render({"A1": "seated", "A2": "seated"}, LAB_DAY, [stray]), {"A1", "A2"}
    )
    assert not report.ok
    assert report.obstructions, report.reason
    found = report.obstructions[0]
    assert math.hypot(found.x_mm - 90, found.y_mm - 40) < 12
    assert "gripper's path" in report.reason
    assert report.verdicts() == {"A1": "seated", "A2": "seated", "A3": "empty", "A4": "empty"}


def test_a_crucible_in_a_position_this_cycle_does_not_use_fails(bench: VisionBench) -> None:
    report = bench.check(bench.render(dict.fromkeys(ALL, "seated"), LAB_DAY), {"A1", "A2"})
    assert not report.ok
    assert {p.slot for p in report.positions if not p.ok} == {"A3", "A4"}
    assert "none belongs" in report.reason


def test_without_expectations_seated_and_empty_positions_pass(bench: VisionBench) -> None:
    report = bench.check(bench.render({"A2": "seated"}, LAB_DAY))
    assert report.ok, report.reason
    assert report.position("A2").expected is None


def test_a_frame_without_the_holder_says_so(bench: VisionBench) -> None:
    frame = np.full((960, 1280, 3), 120, np.uint8)
    report = bench.check(frame, {"A1"})
    assert not report.ok
    assert not report.holder_found
    assert "holder was not found: 0 of 4 markers" in report.reason
    assert report.positions == ()


def test_a_frame_of_another_size_than_the_calibration_is_refused(bench: VisionBench) -> None:
    with pytest.raises(InvalidArgumentError, match=r"640x480 pixels.*1280x960"):
        bench.check(np.zeros((480, 640, 3), np.uint8), {"A1"})


def test_an_unknown_position_is_refused_before_the_frame_is_judged(bench: VisionBench) -> None:
    with pytest.raises(InvalidArgumentError, match="no position B7"):
        bench.check(np.zeros((960, 1280, 3), np.uint8), {"A1", "B7"})


def test_random_lab_conditions_keep_seated_crucibles_seated(bench: VisionBench) -> None:
    rng = random.Random(5)
    for _ in range(6):
        report = bench.check(
            bench.render(dict.fromkeys(ALL, "seated"), random_imaging(rng)), set(ALL)
        )
        assert report.ok, report.reason


def test_the_check_works_through_a_distorting_lens() -> None:
    config = CellConfig.load()
    camera = config.vision.camera.model_copy(update={"distortion": (-0.12, 0.05, 0.0, 0.0)})
    vision = config.vision.model_copy(update={"camera": camera})
    distorted = VisionBench(config.model_copy(update={"vision": vision}))
    frame = VisionBench(config).render(dict.fromkeys(ALL, "seated"))
    # distort the ideal frame with the lens model: each output pixel looks up where the
    # lens would have taken it from
    intr = distorted.checker.intrinsics
    h, w = frame.shape[:2]
    grid = (
        np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 1, 2).astype(np.float32)
    )
    ideal = cv2.undistortPoints(grid, intr.matrix, intr.distortion, P=intr.matrix).reshape(h, w, 2)
    bent = cv2.remap(frame, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR)
    report = distorted.check(bent, set(ALL))
    assert report.ok, report.reason


def test_camera_config_rejects_a_wrong_number_of_distortion_coefficients() -> None:
    with pytest.raises(ConfigError, match="distortion"):
        CellConfig.from_dict({"vision": {"camera": {"distortion": [0.1, 0.2]}}})


def test_no_camera_configured_is_a_typed_error() -> None:
    camera = CellConfig.load().vision.camera.model_copy(update={"source": None})
    with pytest.raises(CameraNotConfiguredError, match=r"vision\.camera\.source"):
        open_camera(camera, "127.0.0.2")


def test_the_simulator_camera_is_its_snapshot_url() -> None:
    camera = open_camera(CellConfig.load().vision.camera, "127.0.0.9")
    assert isinstance(camera, SnapshotCamera)
    assert camera.url == "http://127.0.0.9:8089/snapshot.jpg"


async def test_an_opencv_capture_reads_a_stream_in_its_thread(
    tmp_path: Path, bench: VisionBench
) -> None:
    """A video file stands in for a stream: frames come from the capture thread."""
    frame = bench.render(dict.fromkeys(ALL, "seated"))
    path = tmp_path / "stream.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 10, (1280, 960))
    for _ in range(30):
        writer.write(frame)
    writer.release()
    camera = OpenCVCamera(str(path), 1280, 960, timeout=10.0)
    try:
        got = await camera.capture()
        assert got.shape == (960, 1280, 3)
        assert bench.check(got, set(ALL)).ok
    finally:
        await camera.close()


async def test_an_opencv_capture_that_cannot_open_raises_camera_error(tmp_path: Path) -> None:
    camera = OpenCVCamera(str(tmp_path / "no-such-stream.avi"), 1280, 960, timeout=5.0)
    try:
        with pytest.raises(CameraError, match="cannot be opened"):
            await camera.capture()
    finally:
        await camera.close()


def test_the_job_database_of_schema_1_gains_the_placement_checks(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite3"
    JobStore(path).close()
    with sqlite3.connect(path) as db:  # as fxcell before the camera left it
        db.execute("DROP TABLE placement_checks")
        db.execute("UPDATE meta SET value='1' WHERE key='schema'")
    store = JobStore(path)
    try:
        assert store.placement_checks(1) == []
    finally:
        store.close()
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT value FROM meta WHERE key='schema'").fetchone() == (
            str(SCHEMA_VERSION),
        )


def test_a_check_is_recorded_as_a_foxglove_image_with_annotations_and_a_verdict(
    tmp_path: Path, bench: VisionBench
) -> None:
    import base64
    import json
    import time

    import foxglove.messages as fox
    import jsonschema
    from google.protobuf import descriptor_pb2
    from mcap.reader import make_reader

    from fxcell.events import PlacementEvent
    from fxcell.recorder import Recorder, topics

    positions: dict[str, Fault | str] = {"A1": "seated", "A2": Fault.offset(0.005)}
    report = bench.check(bench.render(positions, LAB_DAY), {"A1", "A2"})
    rec = Recorder(tmp_path)
    rec.submit(PlacementEvent(time.time(), report.image, report.as_dict()))
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
        messages = {
            ch.topic: json.loads(msg.data)
            for _s, ch, msg in reader.iter_messages()
            if ch.topic.startswith("/camera")
        }
    image = messages[topics.CAMERA_PLACEMENT]
    assert image["format"] == "jpeg"
    assert base64.b64decode(image["data"]) == report.image
    annotations = messages[topics.CAMERA_PLACEMENT_ANNOTATIONS]
    assert len(annotations["circles"]) == 4
    assert annotations["texts"][0]["text"].startswith("A1 seated")
    assert annotations["texts"][1]["text"].startswith("A2 offset")
    verdict = messages[topics.CAMERA_PLACEMENT_VERDICT]
    assert verdict["ok"] is False
    assert verdict["positions"][1]["verdict"] == "offset"
    for topic, sdk, name in (
        (topics.CAMERA_PLACEMENT, fox.CompressedImage, "CompressedImage"),
        (topics.CAMERA_PLACEMENT_ANNOTATIONS, fox.ImageAnnotations, "ImageAnnotations"),
    ):
        definition = json.loads(schemas[topic].data)
        assert schemas[topic].name == f"foxglove.{name}"
        jsonschema.validate(messages[topic], definition)
        fds = descriptor_pb2.FileDescriptorSet.FromString(sdk.get_schema().data)
        fields = {m.name: {f.name for f in m.field} for f in fds.file for m in f.message_type}
        assert set(definition["properties"]) == fields[name]
    circle = json.loads(schemas[topics.CAMERA_PLACEMENT_ANNOTATIONS].data)["properties"]
    fds = descriptor_pb2.FileDescriptorSet.FromString(fox.ImageAnnotations.get_schema().data)
    fields = {m.name: {f.name for f in m.field} for f in fds.file for m in f.message_type}
    assert set(circle["circles"]["items"]["properties"]) == fields["CircleAnnotation"]
    assert set(circle["texts"]["items"]["properties"]) == fields["TextAnnotation"]


@given(
    position=st.tuples(*[st.floats(-0.3, 0.3)] * 2, st.floats(0.3, 0.8)),
    tilt=st.tuples(*[st.floats(-0.3, 0.3)] * 3),
    height=st.floats(0.0, 0.05),
    point=st.tuples(st.floats(-0.1, 0.3), st.floats(-0.08, 0.08)),
)
@settings(max_examples=60, deadline=None)
def test_the_plane_homography_maps_rectified_pixels_where_the_camera_sees_them(
    position: tuple[float, float, float],
    tilt: tuple[float, float, float],
    height: float,
    point: tuple[float, float],
) -> None:
    from fxcell.geometry import Pose
    from fxcell.vision.model import plane_homography

    # a camera above the plane, looking down (turned by up to ~17° about each axis)
    looking_down = Pose.from_rotvec((0, 0, 0), (math.pi, 0, 0))
    camera = Pose(position, (looking_down @ Pose.from_rotvec((0, 0, 0), tilt)).rotation)
    station_in_cam = camera.inverse()
    K = np.array([[1100.0, 0, 640], [0, 1100.0, 480], [0, 0, 1]])
    origin, scale = np.array([-0.05, 0.07]), 0.0005
    # the rectified pixel of the plane point (x, y) at that height
    u, v = (point[0] - origin[0]) / scale, (origin[1] - point[1]) / scale
    H = plane_homography(K, station_in_cam, height, origin, scale)
    mapped = H @ np.array([u, v, 1.0])
    # the pinhole projection of that point, computed directly
    in_camera = station_in_cam.rotation @ np.array([point[0], point[1], height])
    in_camera += station_in_cam.position
    expected = (K @ in_camera)[:2] / in_camera[2]
    assert mapped[:2] / mapped[2] == pytest.approx(expected, abs=1e-6)


async def test_a_snapshot_camera_that_never_answers_says_why_it_failed() -> None:
    async def silent(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read()  # reads the request, never answers
        writer.close()

    server = await asyncio.start_server(silent, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    camera = SnapshotCamera(f"http://127.0.0.1:{port}/snapshot.jpg", timeout=0.2)
    try:
        with pytest.raises(CameraError, match=r"snapshot\.jpg: ReadTimeout$|snapshot\.jpg: \S"):
            await camera.capture()
    finally:
        await camera.close()
        server.close()
        await server.wait_closed()
