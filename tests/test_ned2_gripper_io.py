"""The unchanged Cell's gripper, IO and pick/place on a Ned2 (its simulator): Gripper 1
through the robot's tool commands, judged by the simulator's own state (what it grips,
where its objects are, its pins); what Gripper 1 cannot do is refused naming the kind
before anything is sent."""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator, Iterator

import numpy as np
import pytest

from fxcell import Cell
from fxcell.config import CellConfig, IOConfig, JointLimits, SceneConfig, SceneObject
from fxcell.errors import (
    GripperError,
    GripperNotActivatedError,
    NothingGraspedError,
    ObjectLostError,
    UnknownSignalError,
    UnsupportedGripError,
)
from fxcell.layout import Layout, LayoutConfig, ObjectKind, StationConfig, TaughtFrame
from fxcell.link.ned2.gripper import GRIPPER_1
from fxcell.motion import ned2
from fxcell.sim.ned2.robot import GRIPPER_TCP
from fxcell.testing import injected_faults
from fxcell.testing.ned2 import Ned2SimulatorHandle, ned2_simulator

pytestmark = [pytest.mark.system, pytest.mark.timeout(180)]

TABLE = SceneObject(name="table", size=(1.0, 1.0, 0.05), position=(0.0, 0.0, -0.025))
# The TCP where Gripper 1's fingers close, its z along them (tool_link's x) and its x along
# tool_link's z: pointing down, the fingers close across the stations' y axis.
_HALF_TURN = math.pi / math.sqrt(2.0)
TCP = (GRIPPER_TCP, 0.0, 0.0, _HALF_TURN, 0.0, _HALF_TURN)
VIAL = ObjectKind(width=0.02, height=0.04, grip_height=0.02, mass=0.02)
SEAT_Z = 0.01  # the stations stand 1 cm above the table


def _station(x: float, y: float, columns: int) -> StationConfig:
    frame = TaughtFrame(
        origin=(x, y, SEAT_Z), x_point=(x + 0.1, y, SEAT_Z), xy_point=(x, y + 0.1, SEAT_Z)
    )
    return StationConfig(holds="vial", frame=frame, columns=columns, pitch=(0.04, 0.0))


LAYOUT = LayoutConfig(
    objects={"vial": VIAL},
    stations={"rack": _station(0.22, -0.12, 2), "tray": _station(0.22, 0.12, 2)},
)


def _config() -> CellConfig:
    limits = JointLimits(
        position_min=tuple(ned2.LOWER),
        position_max=tuple(ned2.UPPER),
        velocity=tuple(ned2.VELOCITY_LIMITS),
        acceleration=tuple(ned2.ACCELERATION_LIMITS),
    )
    config = CellConfig()
    robot = config.robot.model_copy(update={"kind": "ned2"})  # past validation
    tool = config.tool.model_copy(update={"tcp": TCP, "payload": 0.1})
    io = IOConfig(signals={"lamp": "DO2", "door": "DI3", "valve": "DO7"})
    return config.model_copy(
        update={
            "robot": robot,
            "tool": tool,
            "limits": limits,
            "scene": SceneConfig(objects=(TABLE,)),
            "layout": LAYOUT,
            "io": io,
        }
    )


@pytest.fixture(scope="module")
def sim() -> Iterator[Ned2SimulatorHandle]:
    with ned2_simulator(time_scale=1.0, calibrated=True) as handle:
        yield handle


@pytest.fixture
async def cell(sim: Ned2SimulatorHandle) -> AsyncIterator[Cell]:
    async with Cell(config=_config(), host=sim.host, record=None) as c:
        await c.init()
        yield c
        if c.held is not None:
            await c.gripper_open()


def _fingers(sim: Ned2SimulatorHandle) -> list[float]:
    t = ned2.forward(sim.state()["joints"])
    return [float(v) for v in t[:3, 3] + GRIPPER_TCP * t[:3, 0]]


async def test_gripper_1_opens_and_closes_on_nothing(cell: Cell, sim: Ned2SimulatorHandle) -> None:
    await cell.gripper_activate()
    opened = await cell.gripper_open()
    assert opened.width == pytest.approx(GRIPPER_1.stroke)
    assert not opened.holding
    assert sim.state()["gripper_open"] is True
    closed = await cell.gripper_close()
    assert closed.width == pytest.approx(0.0)
    assert not closed.holding
    assert sim.state()["gripper_open"] is False
    assert cell.gripper.state == "empty"
    with pytest.raises(NothingGraspedError):
        await cell.gripper_close(expect_object=True)


async def test_what_gripper_1_cannot_do_is_refused_naming_the_kind_before_it_moves(
    cell: Cell, sim: Ned2SimulatorHandle
) -> None:
    await cell.gripper_open()
    before = sim.state()["log"]
    for call in (
        lambda: cell.gripper_move(0.01),  # between open and closed
        lambda: cell.gripper_close(speed=0.05),  # no speed setting
        lambda: cell.gripper_close(grip_force=50.0),  # no force in N
    ):
        with pytest.raises(UnsupportedGripError, match="ned2") as refused:
            await call()
        assert refused.value.kind == "ned2"
    state = sim.state()
    assert state["gripper_open"] is True
    assert state["log"] == before


async def test_an_object_between_the_fingers_is_gripped_and_its_loss_detected(
    cell: Cell, sim: Ned2SimulatorHandle
) -> None:
    await cell.gripper_open()
    await asyncio.to_thread(sim.add_object, "probe", _fingers(sim), 0.02)
    result = await cell.gripper_close(expect_object=True)
    assert result.holding
    assert result.width == pytest.approx(0.02, abs=1e-3)  # where the motor stopped
    assert sim.state()["held"] == "probe"
    assert cell.gripper.state == "holding"
    with injected_faults("the held object slips"):
        await asyncio.to_thread(sim.inject, "gripper_drop")
    with pytest.raises(ObjectLostError):
        await cell.gripper.check_holding()
    assert cell.gripper.state == "empty"
    await cell.gripper_open()


async def test_without_a_gripper_on_the_tool_port_its_commands_are_refused(
    cell: Cell, sim: Ned2SimulatorHandle
) -> None:
    with injected_faults("the tool taken off"):
        await asyncio.to_thread(sim.inject, "tool_disconnect")
    try:
        with pytest.raises(GripperNotActivatedError):
            await cell.gripper_close()
        assert cell.gripper.state == "inactive"
        with pytest.raises(GripperError, match="not a Gripper 1"):
            await cell.gripper_activate()
    finally:
        await asyncio.to_thread(sim.inject, "tool_connect")
    await cell.gripper_activate()
    assert (await cell.gripper_open()).width == pytest.approx(GRIPPER_1.stroke)


async def test_io_by_configured_names_sets_and_reads_the_ned2s_pins(
    cell: Cell, sim: Ned2SimulatorHandle
) -> None:
    await cell.io_set("lamp", True)
    assert sim.state()["digital_out"]["DO2"] is True
    assert cell.io.get("lamp") is True
    await cell.io_set("lamp", False)
    assert sim.state()["digital_out"]["DO2"] is False
    assert cell.io.get("door") is False
    await asyncio.to_thread(sim.set_input, "DI3", 1)
    assert await cell.io_wait_for("door", True, 5.0) >= 0.0
    assert cell.io.get("door") is True
    with pytest.raises(UnknownSignalError, match="ned2"):
        await cell.io_set("valve", True)  # DO7: a UR output, not a Ned2 pin
    assert "valve" not in cell.io.snapshot()


async def test_a_vial_picked_from_the_rack_lands_on_the_tray_within_1_mm(
    cell: Cell, sim: Ned2SimulatorHandle
) -> None:
    layout = Layout(LAYOUT)
    source = layout.stations["rack"].grip_pose("A2").position
    target = layout.stations["tray"].grip_pose("A1").position
    await cell.gripper_activate()
    await asyncio.to_thread(sim.add_object, "vial1", [float(v) for v in source], VIAL.width)
    picked = await cell.pick("rack", "A2")
    assert picked.holding
    assert cell.held == "vial"
    assert sim.state()["held"] == "vial1"
    released = await cell.place("tray", "A1")
    assert not released.holding
    assert cell.held is None
    state = sim.state()
    assert state["held"] is None
    landed = np.array(state["objects"]["vial1"])
    assert np.linalg.norm(landed - target) < 1e-3


async def test_a_pick_of_an_object_wider_than_gripper_1_opens_is_refused_before_it_moves(
    sim: Ned2SimulatorHandle,
) -> None:
    wide = LAYOUT.model_copy(update={"objects": {"vial": VIAL.model_copy(update={"width": 0.03})}})
    config = _config().model_copy(update={"layout": wide})
    async with Cell(config=config, host=sim.host, record=None) as c:
        await c.init()
        before = sim.state()["joints"]
        with pytest.raises(UnsupportedGripError, match="ned2") as refused:
            await c.pick("rack", "A1")
        assert refused.value.argument == "width"
        assert sim.state()["joints"] == before
