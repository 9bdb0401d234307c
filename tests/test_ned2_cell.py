"""The unchanged Cell drives a Ned2 (its simulator) through the Ned2 kind: init leaves
learning mode, move_joint lands on its target by the simulator's own joints, a stop ends a
move short of its target with the arm at rest, and the commands a Ned2 cannot do over
the network are refused naming it."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

import numpy as np
import pytest

from fxcell import Cell, CellState
from fxcell.config import CellConfig, JointLimits, SceneConfig, SceneObject
from fxcell.errors import MoveStoppedError, UnsupportedCommandError
from fxcell.motion import ned2
from fxcell.robots import register, unregister
from fxcell.robots.ned2 import NED2_KIND
from fxcell.testing.ned2 import Ned2SimulatorHandle, ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

TABLE = SceneObject(name="table", size=(1.0, 1.0, 0.05), position=(0.0, 0.0, -0.025))
TARGET = [0.6, -0.3, 0.2, 0.4, -0.5, 0.3]
FAR = [-1.5, -0.4, 0.3, 1.0, 1.0, 1.0]


@pytest.fixture
def sim() -> Iterator[Ned2SimulatorHandle]:
    with ned2_simulator(time_scale=1.0, calibrated=True) as handle:
        yield handle


@pytest.fixture
def kind() -> Iterator[None]:
    register(NED2_KIND)
    try:
        yield
    finally:
        unregister("ned2")


def _config() -> CellConfig:
    limits = JointLimits(
        position_min=tuple(ned2.LOWER),
        position_max=tuple(ned2.UPPER),
        velocity=tuple(ned2.VELOCITY_LIMITS),
        acceleration=tuple(ned2.ACCELERATION_LIMITS),
    )
    config = CellConfig()
    robot = config.robot.model_copy(update={"kind": "ned2"})  # past validation: not shipped yet
    tool = config.tool.model_copy(update={"tcp": (0.0,) * 6})
    return config.model_copy(
        update={
            "robot": robot,
            "tool": tool,
            "limits": limits,
            "scene": SceneConfig(objects=(TABLE,)),
        }
    )


async def test_the_cell_inits_moves_and_stops_a_ned2(kind: None, sim: Ned2SimulatorHandle) -> None:
    async with Cell(config=_config(), host=sim.host, record=None) as cell:
        assert cell.kind.name == "ned2"
        await cell.init()
        assert cell.state is CellState.EXTERNAL_CONTROL_READY
        assert sim.state()["learning_mode"] is False
        await cell.move_joint(TARGET)
        assert sim.state()["joints"] == pytest.approx(TARGET, abs=1e-6)
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
