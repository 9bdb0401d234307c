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
from fxcell.config import CellConfig, SceneObject
from fxcell.errors import MoveStoppedError, UnsupportedCommandError
from fxcell.testing.ned2 import Ned2SimulatorHandle, ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

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
