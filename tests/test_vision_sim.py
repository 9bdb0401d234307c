"""The placement check through the simulator's camera: each fault made in the simulated world
(objects moved over the control port) and judged from the frames it serves, as a network
camera's snapshots; and ``cell.check_placement`` on a Cell, recorded."""

from __future__ import annotations

import asyncio
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest
from mcap.reader import make_reader

from fxcell import Cell
from fxcell.config import SIMULATOR_CAMERA_PORT, CellConfig
from fxcell.layout import Layout
from fxcell.link import embedded
from fxcell.link.realtime import LINK_PRIORITY
from fxcell.recorder import topics
from fxcell.sim.camera import RENDER_THREAD
from fxcell.testing import SimulatorHandle, simulator, thread_scheduling
from fxcell.vision.camera import open_camera
from fxcell.vision.placement import PlacementChecker, PlacementReport

CONFIG = CellConfig.load()
CHECKER = PlacementChecker(CONFIG.vision, Layout(CONFIG.layout))
ALL = {"A1", "A2", "A3", "A4"}


@pytest.fixture(scope="module")
def sim() -> Iterator[SimulatorHandle]:
    with simulator(time_scale=0.2) as s:
        yield s


@pytest.fixture
def seated(sim: SimulatorHandle) -> Iterator[SimulatorHandle]:
    """Four crucibles seated in the machine; afterwards put back (and strays removed)."""
    for slot in sorted(ALL):
        embedded.place_object(sim.host, f"c{slot}", "crucible", "machine", slot)
    yield sim
    for slot in sorted(ALL):
        embedded.place_object(sim.host, f"c{slot}", "crucible", "machine", slot)


AWAY = (1.0, 1.0, 0.5)  # out of the camera's view (the simulator has no "remove")


def put(host: str, name: str, kind: str, size: tuple[float, float], at: Sequence[float]) -> None:
    """An upright object of (width, height) with its middle at ``at`` (base frame)."""
    position = [float(v) for v in at]
    embedded.add_object(
        host, name, kind, width=size[0], height=size[1], mass=0.05, position=position
    )


def recorded_topics(path: Path) -> set[str]:
    with open(path, "rb") as f:
        return {ch.topic for _s, ch, _m in make_reader(f).iter_messages()}


async def look(sim: SimulatorHandle, expected: set[str] = ALL) -> PlacementReport:
    camera = open_camera(CONFIG.vision.camera, sim.host)
    try:
        frame = await camera.capture()
    finally:
        await camera.close()
    return await asyncio.to_thread(CHECKER.check, frame, expected)


async def test_the_camera_renders_below_the_robot_links_priority(seated: SimulatorHandle) -> None:
    # the control cycle runs on the main thread (its id: the process's)
    main = os.sched_getscheduler(seated.pid), os.sched_getparam(seated.pid).sched_priority
    if main[0] != os.SCHED_FIFO:
        pytest.skip("the simulator did not get real-time scheduling here")
    await look(seated)  # the renderer thread starts with the first frame
    (renderer,) = thread_scheduling(seated.pid, RENDER_THREAD)
    policy, priority = renderer
    assert policy == os.SCHED_FIFO  # still above every normal process
    assert priority < LINK_PRIORITY < main[1]


async def test_four_seated_crucibles_in_the_simulator_pass(seated: SimulatorHandle) -> None:
    report = await look(seated)
    assert report.ok, report.reason
    assert report.verdicts() == dict.fromkeys(sorted(ALL), "seated")


@pytest.mark.parametrize("mm", [2.5, 4.0, 10.0])
async def test_a_crucible_moved_off_its_position_is_offset(
    seated: SimulatorHandle, mm: float
) -> None:
    await asyncio.to_thread(embedded.offset_object, seated.host, "cA2", 0.0, mm / 1000)
    report = await look(seated)
    a2 = report.position("A2")
    assert a2.verdict == "offset"
    assert a2.offset_mm == pytest.approx(mm, abs=0.5)
    assert not report.ok


async def test_a_crucible_on_the_pocket_edge_is_tilted(seated: SimulatorHandle) -> None:
    await asyncio.to_thread(embedded.offset_object, seated.host, "cA3", 0.0, 0.0, 20.0, 90.0)
    report = await look(seated)
    assert report.position("A3").verdict == "tilted"


async def test_a_missing_crucible_and_a_foreign_object(seated: SimulatorHandle) -> None:
    # the crucible of A1 goes back to the rack; a tool box sits in A4
    await asyncio.to_thread(embedded.place_object, seated.host, "cA1", "crucible", "rack", "D4")
    await asyncio.to_thread(embedded.place_object, seated.host, "cA4", "crucible", "rack", "D3")
    seat = Layout(CONFIG.layout).station("machine").grip_pose("A4").position
    put(seated.host, "spanner", "tool", (0.03, 0.02), (seat[0], seat[1], seat[2] - 0.015))
    try:
        report = await look(seated)
        assert report.position("A1").verdict == "empty"
        assert report.position("A4").verdict == "foreign"
        assert not report.ok
    finally:
        put(seated.host, "spanner", "tool", (0.03, 0.02), AWAY)


async def test_a_crucible_left_in_the_gripper_s_path(seated: SimulatorHandle) -> None:
    station = Layout(CONFIG.layout).station("machine")
    grip = station.grip_pose("A2").position
    put(seated.host, "stray", "crucible", (0.03, 0.035), (grip[0] + 0.03, grip[1] + 0.04, grip[2]))
    try:
        report = await look(seated)
        assert report.obstructions, report.reason
        assert "gripper's path" in report.reason
    finally:
        put(seated.host, "stray", "crucible", (0.03, 0.035), AWAY)


async def test_check_placement_on_a_cell_is_recorded(
    seated: SimulatorHandle, tmp_path: Path
) -> None:
    await asyncio.to_thread(embedded.offset_object, seated.host, "cA1", 0.004, 0.0)
    config = CONFIG.model_copy(update={"positions_file": tmp_path / "p.yaml"})
    async with Cell(host=seated.host, config=config, record=tmp_path / "logs") as cell:
        result = await cell.check_placement("A1,A2,A3,A4")
        assert result["ok"] is False
        assert result["positions"][0]["verdict"] == "offset"
        assert cell.camera.last is not None
        assert cell.camera.last.image[:2] == b"\xff\xd8"
    (path,) = (tmp_path / "logs").glob("*.mcap")
    seen = await asyncio.to_thread(recorded_topics, path)
    assert {
        topics.CAMERA_PLACEMENT,
        topics.CAMERA_PLACEMENT_ANNOTATIONS,
        topics.CAMERA_PLACEMENT_VERDICT,
        topics.COMMANDS,
    } <= seen


async def test_the_simulator_camera_answers_like_a_snapshot_url(sim: SimulatorHandle) -> None:
    import httpx

    base = f"http://{sim.host}:{SIMULATOR_CAMERA_PORT}"
    async with httpx.AsyncClient(timeout=20) as http:
        one = await http.get(f"{base}/snapshot.jpg")
        two = await http.get(f"{base}/snapshot.jpg?t=2")  # the same connection, kept alive
        missing = await http.get(f"{base}/video")
        refused = await http.post(f"{base}/snapshot.jpg", content=b"x")
    assert one.status_code == two.status_code == 200
    assert one.headers["content-type"] == "image/jpeg"
    assert one.content[:2] == b"\xff\xd8"
    assert one.content != two.content  # each frame is taken anew (noise, light)
    assert missing.status_code == 404
    assert refused.status_code == 405


async def test_a_camera_that_does_not_answer_is_a_camera_error() -> None:
    from fxcell.errors import CameraError
    from fxcell.vision.camera import SnapshotCamera

    camera = SnapshotCamera("http://127.0.0.254:9/snapshot.jpg", timeout=2.0)
    try:
        with pytest.raises(CameraError, match="snapshot camera"):
            await camera.capture()
    finally:
        await camera.close()
