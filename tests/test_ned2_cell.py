"""The unchanged Cell drives a Ned2 (its simulator) through the Ned2 kind, chosen by
``robot.kind: ned2`` in the configuration: with no host the Cell starts the embedded Ned2
simulator, which boots needing calibration (init calibrates it); init leaves
learning mode, move_joint lands on its target by the simulator's own joints, a stop ends a
move short of its target with the arm at rest, and the commands a Ned2 cannot do over
the network are refused naming it."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator

import numpy as np
import pytest

from fxcell import Cell, CellState
from fxcell.config import CONFIG_DIR, CellConfig, SceneObject
from fxcell.errors import (
    InvalidArgumentError,
    MoveStoppedError,
    SimulatorError,
    UnsupportedCommandError,
)
from fxcell.geometry import Pose
from fxcell.link.ned2.embedded import request
from fxcell.motion import ned2
from fxcell.robots import robot_kind
from fxcell.testing.ned2 import Ned2SimulatorHandle, ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

# rad: where a Ned2 move ends by the simulator's own joints. The cell ends a Ned2 move with a
# stop once its joint states show the arm settled (SETTLE_POSITION, SETTLE_VELOCITY); the
# arm goes on until the stop arrives (1.2e-6 rad past the target seen on 3 busy workers).
ARRIVED = 1e-5
TABLE = SceneObject(name="table", size=(1.0, 1.0, 0.05), position=(0.0, 0.0, -0.025))
TARGET = [0.6, -0.3, 0.2, 0.4, -0.5, 0.3]
FAR = [-1.5, -0.4, 0.3, 1.0, 1.0, 1.0]


@pytest.fixture
def sim() -> Iterator[Ned2SimulatorHandle]:
    with ned2_simulator(time_scale=1.0, calibrated=True) as handle:
        yield handle


def _config() -> CellConfig:
    # the Ned2's limits, home and TCP are the kind's defaults; the tool_link as TCP here
    return CellConfig.from_dict(
        {
            "robot": {"kind": "ned2"},
            "tool": {"tcp": [0.0] * 6},
            "scene": {"objects": [TABLE.model_dump()]},
        }
    )


async def test_the_cell_inits_moves_and_stops_a_ned2(sim: Ned2SimulatorHandle) -> None:
    async with Cell(config=_config(), host=sim.host, record=None) as cell:
        assert cell.kind.name == "ned2"
        await cell.init()
        assert cell.state is CellState.EXTERNAL_CONTROL_READY
        assert sim.state()["learning_mode"] is False
        await cell.move_joint(TARGET)
        assert sim.state()["joints"] == pytest.approx(TARGET, abs=ARRIVED)
        move = asyncio.create_task(cell.move_joint(FAR))
        async with asyncio.timeout(10.0):
            with cell.robot_states(maxsize=8) as states:
                async for sample in states:
                    if abs(sample.actual_qd[0]) > 0.2:
                        break
        assert await cell.stop() is True
        with pytest.raises(MoveStoppedError):
            await move
        state = sim.state()
        assert state["moving"] is False
        assert np.max(np.abs(np.array(state["joints"]) - FAR)) > 0.1  # stopped short
        with pytest.raises(UnsupportedCommandError, match="ned2"):
            await cell.power_off()


async def test_a_ned2_cell_without_a_host_starts_its_simulator_which_init_calibrates() -> None:
    config = _config()
    assert config.robot.host is None
    async with Cell(config=config, record=None, simulator_options={"time_scale": 0.1}) as cell:
        host = cell.host
        assert host is not None
        state = json.loads(request(host, "state"))
        # it boots as a real Ned2 does: needing calibration, in learning mode
        assert (state["calibrated"], state["learning_mode"]) == (False, True)
        assert cell.state is not CellState.EXTERNAL_CONTROL_READY
        await cell.init()
        assert cell.state is CellState.EXTERNAL_CONTROL_READY
        state = json.loads(request(host, "state"))
        assert (state["calibrated"], state["learning_mode"]) == (True, False)
        await cell.move_joint(TARGET)
        assert json.loads(request(host, "state"))["joints"] == pytest.approx(TARGET, abs=ARRIVED)
    with pytest.raises(SimulatorError):  # closing the cell ended its simulator
        request(host, "state", timeout=1.0)


def test_the_ned2_simulator_refuses_options_it_does_not_take() -> None:
    launch = robot_kind("ned2").simulator
    assert launch is not None
    with pytest.raises(InvalidArgumentError, match="fusion_time"):
        launch({"time_scale": 0.5, "fusion_time": 60})


async def test_the_example_cells_slots_are_reached_to_within_a_millimetre() -> None:
    # the shipped Ned2 cell as ./dev run --robot ned2 starts it: its TCP (Gripper 1's
    # fingers), its layout; the simulator's own joints say where the fingers are
    config = CellConfig.load(CONFIG_DIR / "ned2-cell.yaml")
    tcp = Pose.from_ur(config.tool.tcp).matrix
    async with Cell(config=config, record=None, simulator_options={"time_scale": 0.1}) as cell:
        assert cell.host is not None
        await cell.init()
        rack, tray = cell.layout.station("rack"), cell.layout.station("tray")
        # a straight descent is planned on Cartesian knots (each an IK solve): one here
        moves = (
            (rack.approach_pose("A1"), False),
            (rack.grip_pose("A1"), True),
            (tray.approach_pose("C3"), False),
        )
        for target, linear in moves:
            await cell.move_pose(target.as_ur(), linear=linear)
            joints = json.loads(request(cell.host, "state"))["joints"]
            fingers = ned2.forward(np.array(joints)) @ tcp
            assert np.linalg.norm(fingers[:3, 3] - target.position) < 1e-3
            assert np.allclose(fingers[:3, :3], target.rotation, atol=1e-3)
        await cell.go_home()
        joints = json.loads(request(cell.host, "state"))["joints"]
        assert joints == pytest.approx(config.home, abs=ARRIVED)
