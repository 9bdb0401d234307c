"""Moves on a calibrated arm: the simulator runs a factory calibration (by default its shipped
one; here also deltas up to 2 mm and 0.002 rad); a Cell reads it at connect by default and
reaches targets as the controller reports them, one told to use the nominal model misses by
millimetres.

fxcell sets its TCP on the controller when external control starts, so the controller's
``actual_TCP_pose`` is the tool centre point itself.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Awaitable, Iterator
from pathlib import Path

import numpy as np
import pytest

from fxcell.calibration import Calibration
from fxcell.cell import Cell
from fxcell.config import CellConfig
from fxcell.errors import UncalibratedError
from fxcell.geometry import Pose
from fxcell.protocol import RobotState
from fxcell.testing import SimulatorHandle, simulator

pytestmark = pytest.mark.timeout(120)

CALIBRATION = Calibration(
    delta_theta=(0.0012, -0.002, 0.0017, -0.0009, 0.0015, -0.002),
    delta_a=(0.0006, 0.002, -0.0015, 0.0011, -0.0008, 0.0),
    delta_d=(-0.0015, 0.0009, 0.0012, 0.002, -0.0017, 0.0011),
    delta_alpha=(0.002, -0.0011, 0.0008, -0.0016, 0.0013, -0.0007),
)
DEFAULT = CellConfig.load()  # robot.calibration: controller, by default
NOMINAL = DEFAULT.model_copy(
    update={"robot": DEFAULT.robot.model_copy(update={"calibration": "nominal"})}
)
WORK = [0.4, -1.4, 1.6, -1.8, -1.57, 0.0]  # gripper down over the table
POSITION_TOL = 1e-5
ANGLE_TOL = 1e-4
LINE_TOL = 1e-4


@pytest.fixture(scope="module")
def calibration_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("calibration") / "calibration.conf"
    path.write_text(CALIBRATION.to_conf())
    return path


@pytest.fixture(scope="module")
def calibrated_sim(calibration_file: Path) -> Iterator[SimulatorHandle]:
    with simulator(extra_args=["--calibration", str(calibration_file)]) as handle:
        yield handle


@contextlib.asynccontextmanager
async def ready_cell(sim: SimulatorHandle, config: CellConfig) -> AsyncIterator[Cell]:
    sim.set_joints(WORK)
    async with Cell(sim.host, config=config) as cell:
        await cell.init()
        await cell.set_velocity_factor(0.3)
        yield cell


def calibrated_config(source: Path | str, **robot: object) -> CellConfig:
    settings = NOMINAL.robot.model_copy(update={"calibration": str(source), **robot})
    return NOMINAL.model_copy(update={"robot": settings})


def reported_tcp(sample: RobotState) -> Pose:
    """The controller's actual_TCP_pose (fxcell set the TCP on it)."""
    return Pose.from_ur(sample.actual_tcp_pose)


async def settled_tcp(cell: Cell) -> Pose:
    with cell.robot_states() as states:
        async for s in states:
            if max(map(abs, s.actual_qd)) < 1e-9:
                return reported_tcp(s)
    raise AssertionError("no state")


def errors(actual: Pose, target: Pose) -> tuple[float, float]:
    return float(np.linalg.norm(actual.position - target.position)), actual.angle_to(target)


async def pose_target(cell: Cell, offset: tuple[float, float, float]) -> Pose:
    here = await settled_tcp(cell)
    return Pose(here.position + np.array(offset), here.rotation)


async def traced(cell: Cell, move: Awaitable[object]) -> list[Pose]:
    """The reported TCP at every sample while ``move`` runs (converted afterwards: the loop
    stays free for the move's heartbeat)."""
    samples: list[tuple[float, ...]] = []
    with cell.robot_states() as states:

        async def collect() -> None:
            async for s in states:
                samples.append(s.actual_tcp_pose)

        collector = asyncio.create_task(collect())
        try:
            await move
        finally:
            collector.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await collector
    return [Pose.from_ur(p) for p in samples]


def line_deviation(trace: list[Pose], start: Pose, end: Pose) -> float:
    a, b = start.position, end.position
    u = (b - a) / np.linalg.norm(b - a)
    worst = 0.0
    for p in trace:
        d = p.position - a
        worst = max(worst, float(np.linalg.norm(d - np.dot(d, u) * u)))
    return worst


async def test_a_calibrated_cell_reaches_targets_as_the_controller_reports_them(
    calibrated_sim: SimulatorHandle, calibration_file: Path
) -> None:
    async with ready_cell(calibrated_sim, calibrated_config(calibration_file)) as cell:
        assert cell.controller_info["calibration_checksum"] == CALIBRATION.checksum
        assert cell.controller_info["calibration_source"] == str(calibration_file)
        target = await pose_target(cell, (0.03, -0.02, 0.04))
        await cell.move_pose(target)
        dp, da = errors(await settled_tcp(cell), target)
        assert dp < POSITION_TOL, dp
        assert da < ANGLE_TOL, da
        # fxcell's own view of the pose agrees with the controller's
        x, y, z, qx, qy, qz, qw = await cell.get_current_pose()
        dp, _ = errors(await settled_tcp(cell), Pose.from_quaternion([x, y, z], [qx, qy, qz, qw]))
        assert dp < 1e-9

        start = await settled_tcp(cell)
        await cell.move_distance([-0.04, 0.03, -0.03])
        end = Pose(start.position + np.array([-0.04, 0.03, -0.03]), start.rotation)
        dp, da = errors(await settled_tcp(cell), end)
        assert dp < POSITION_TOL, dp
        assert da < ANGLE_TOL, da

        start = await settled_tcp(cell)
        target = Pose(start.position + np.array([0.05, 0.02, 0.02]), start.rotation)
        trace = await traced(cell, cell.move_pose(target, linear=True))
        dp, da = errors(await settled_tcp(cell), target)
        assert dp < POSITION_TOL, dp
        assert da < ANGLE_TOL, da
        assert len(trace) > 50
        assert line_deviation(trace, start, target) < LINE_TOL


async def test_the_default_cell_on_the_default_simulator_is_calibrated_and_accurate() -> None:
    # no calibration anywhere in the configuration, none given to the simulator: the
    # simulator presents its shipped factory calibration and the cell reads it at connect
    from fxcell.sim.server import default_calibration

    shipped = default_calibration()
    assert not shipped.is_nominal
    assert DEFAULT.robot.calibration == "controller"
    with simulator() as sim:
        async with ready_cell(sim, DEFAULT) as cell:
            assert cell.calibration_status == {
                "model": "calibrated",
                "source": f"controller {cell.host}",
                "checksum": shipped.checksum,
            }
            for offset in ((0.03, -0.02, 0.04), (-0.05, 0.03, -0.02)):
                target = await pose_target(cell, offset)
                await cell.move_pose(target)
                dp, da = errors(await settled_tcp(cell), target)
                assert dp < POSITION_TOL, dp
                assert da < ANGLE_TOL, da
            start = await settled_tcp(cell)
            await cell.move_distance([0.0, 0.03, 0.0])
            dp, _ = errors(
                await settled_tcp(cell),
                Pose(start.position + np.array([0.0, 0.03, 0.0]), start.rotation),
            )
            assert dp < POSITION_TOL, dp


async def test_a_simulator_told_nominal_presents_the_nominal_arm() -> None:
    from fxcell.link.primary import read_calibration

    with simulator(extra_args=["--calibration", "nominal"]) as sim:
        calibration = await asyncio.to_thread(read_calibration, sim.host)
        assert calibration.is_nominal
        async with ready_cell(sim, DEFAULT) as cell:
            assert cell.calibration_status is not None
            assert cell.calibration_status["model"] == "nominal"
            assert cell.calibration_status["checksum"] == Calibration.nominal().checksum


async def test_the_nominal_model_misses_a_calibrated_arms_targets_by_millimetres(
    calibrated_sim: SimulatorHandle,
) -> None:
    # only by explicit choice (robot.calibration: nominal)
    async with ready_cell(calibrated_sim, NOMINAL) as cell:
        assert cell.calibration_status is not None
        assert cell.calibration_status["model"] == "nominal"
        target = await pose_target(cell, (0.03, -0.02, 0.04))
        await cell.move_pose(target)
        dp, _ = errors(await settled_tcp(cell), target)
        assert dp > 1e-3, dp

        start = await settled_tcp(cell)
        target = Pose(start.position + np.array([0.05, 0.02, 0.02]), start.rotation)
        trace = await traced(cell, cell.move_pose(target, linear=True))
        dp, _ = errors(await settled_tcp(cell), target)
        assert dp > 1e-3, dp
        assert line_deviation(trace, start, target) > LINE_TOL


async def test_the_cell_reads_the_calibration_from_the_controller(
    calibrated_sim: SimulatorHandle,
) -> None:
    # the calibrated simulator reports its deltas in the primary interface's kinematics info
    async with ready_cell(calibrated_sim, calibrated_config("controller")) as cell:
        assert cell.controller_info["calibration_source"] == f"controller {cell.host}"
        assert cell.controller_info["calibration_checksum"] == CALIBRATION.checksum
        target = await pose_target(cell, (0.02, 0.02, 0.03))
        await cell.move_pose(target)
        dp, da = errors(await settled_tcp(cell), target)
        assert dp < POSITION_TOL, dp
        assert da < ANGLE_TOL, da


async def test_pose_moves_are_refused_when_the_calibration_cannot_be_read(
    calibrated_sim: SimulatorHandle,
) -> None:
    # a controller whose primary interface sends no kinematics info: the calibration is unreadable
    calibrated_sim.inject("hide_kinematics_info")
    try:
        async with ready_cell(calibrated_sim, calibrated_config("controller")) as cell:
            assert cell.controller_info["calibration_source"].startswith("unreadable")
            assert cell.calibration_status is not None
            assert cell.calibration_status["model"] == "uncalibrated"  # visible, and safe
            start = cell.robot_state.actual_q
            target = await pose_target(cell, (0.02, 0.0, 0.0))
            with pytest.raises(UncalibratedError, match="accept_nominal_kinematics"):
                await cell.move_pose(target)
            with pytest.raises(UncalibratedError):
                await cell.move_distance([0.0, 0.0, 0.01])
            assert cell.robot_state.actual_q == pytest.approx(start, abs=1e-9)
        accepting = calibrated_config("controller", accept_nominal_kinematics=True)
        async with ready_cell(calibrated_sim, accepting) as cell:
            assert cell.calibration_status is not None
            assert cell.calibration_status["model"] == "nominal (fallback)"
            await cell.move_distance([0.0, 0.0, 0.01])  # nominal, as configured
    finally:
        calibrated_sim.inject("show_kinematics_info")
