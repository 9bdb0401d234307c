"""The shipped example Ned2 cell (``config/ned2-cell.yaml``): it loads as a Ned2 cell with
the Ned2's own limits, home and gripper TCP, it has what the fusion job needs (a crucible
rack, the machine's four positions and moulds, a bead tray, the machine's signals on the
Ned2's pins), and every slot of every station can be reached:
grip, approach and retreat poses have joint solutions within the limits, free of the
scene, and so has every point of the straight descent between them, with and without an
object in the gripper."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from fxcell.config import CONFIG_DIR, CellConfig
from fxcell.geometry import Pose
from fxcell.layout import Layout
from fxcell.robot_specs import NED2_SPEC
from fxcell.robots import CollisionModel, KinematicModel, robot_kind

CONFIG = CellConfig.load(CONFIG_DIR / "ned2-cell.yaml")
LAYOUT = Layout(CONFIG.layout)
SLOTS = [(station.name, slot) for station in LAYOUT for slot in station.slots]
STEPS = 10  # points checked along each descent
Models = tuple[KinematicModel, CollisionModel]


@pytest.fixture(scope="module")
def models() -> Models:
    kind = robot_kind("ned2")
    return kind.kinematics(CONFIG, None), kind.collision(CONFIG)


def test_the_example_is_a_ned2_cell_with_the_ned2s_own_figures() -> None:
    assert CONFIG.robot.kind == "ned2"
    assert CONFIG.robot.host is None  # the embedded Ned2 simulator
    assert CONFIG.home == NED2_SPEC.home
    assert CONFIG.tool.tcp == pytest.approx(NED2_SPEC.tcp)
    for key, values in NED2_SPEC.limits.items():
        assert getattr(CONFIG.limits, key) == pytest.approx(values), key
    assert {s.name for s in LAYOUT} == {"rack", "tray", "machine", "moulds"}
    assert len(SLOTS) == 9 + 9 + 4 + 4
    assert CONFIG.vision.camera.source is None  # the Ned2's simulator has no camera
    # objects the Ned2's Gripper 1 can take (27 mm stroke, 0.3 kg payload)
    for kind in CONFIG.layout.objects.values():
        assert kind.width < 0.027
        assert kind.mass <= NED2_SPEC.payload_max


def test_the_example_has_what_the_fusion_job_needs() -> None:
    from fxcell.job.runner import BUSY, DONE, ERROR, READY, START_SIGNAL
    from fxcell.link.ned2.link import NED2_SIGNALS

    holds = {s.name: s.config.holds for s in LAYOUT}
    assert holds == {"rack": "crucible", "machine": "crucible", "moulds": "bead", "tray": "bead"}
    assert len(LAYOUT.station("machine").slots) == len(LAYOUT.station("moulds").slots) == 4
    signals = CONFIG.io.signals
    assert signals[START_SIGNAL] in NED2_SIGNALS
    assert signals[START_SIGNAL].startswith("DO")
    inputs = [signals[name] for name in (READY, BUSY, DONE, ERROR)]
    assert set(inputs) <= NED2_SIGNALS
    assert all(pin.startswith("DI") for pin in inputs)
    assert len(set(inputs)) == 4
    assert CONFIG.io.interlocks == {"machine": "machine_busy"}
    assert {s.config.zone for s in LAYOUT if s.name in ("machine", "moulds")} == {"machine"}


def test_home_is_free(models: Models) -> None:
    _, collision = models
    assert not collision.in_collision(np.array(CONFIG.home))


@pytest.mark.parametrize(("station", "slot"), SLOTS, ids=[f"{s}-{n}" for s, n in SLOTS])
def test_every_slot_is_reachable_and_free_along_its_descent(
    models: Models, station: str, slot: str
) -> None:
    kinematics, collision = models
    st = LAYOUT.station(station)
    reach = kinematics.reach
    grip = st.grip_pose(slot)
    assert float(np.linalg.norm(grip.position)) < reach
    for top in (st.approach_pose(slot), st.retreat_pose(slot)):
        q = kinematics.inverse(top, np.array(CONFIG.home))
        assert collision.colliding_pairs(q) == []
        # down the straight line to the grip pose, each point from the one before, solved
        # as the planner solves a straight line's knots (on the previous point's branch)
        for t in np.linspace(0.0, 1.0, STEPS + 1)[1:]:
            pose = Pose(top.position + t * (grip.position - top.position), grip.rotation)
            nxt = kinematics.inverse_near(pose, q)
            assert np.max(np.abs(nxt - q)) < 0.3, "the descent jumps to another branch"
            q = nxt
            assert np.all(q >= np.array(CONFIG.limits.position_min) - 1e-9)
            assert np.all(q <= np.array(CONFIG.limits.position_max) + 1e-9)
            assert collision.colliding_pairs(q) == [], (station, slot, t)
        np.testing.assert_allclose(kinematics.forward(q).position, grip.position, atol=1e-6)
    # with the object in the gripper, the approach pose is free too
    collision.attach(st.config.holds)
    try:
        q = kinematics.inverse(st.approach_pose(slot), np.array(CONFIG.home))
        assert collision.colliding_pairs(q) == []
    finally:
        collision.detach()


def _daemon_args(**given: object) -> argparse.Namespace:
    args = {"sim_time_scale": None, "sim_crucibles": None, "sim_fusion_time": None}
    args |= {"sim_cooling_time": None, "config": None}
    return argparse.Namespace(**(args | given))


def test_the_daemon_starts_the_ned2_simulator_with_the_machine_and_a_full_rack() -> None:
    from fxcell.daemon.cli import SIM_COOLING_TIME, SIM_FUSION_TIME, _simulator_options

    extra = _simulator_options(_daemon_args(), CONFIG)["extra_args"]
    assert extra[0] == "--machine"
    assert extra[extra.index("--crucibles") + 1] == "9"  # the example's 3 x 3 rack
    assert float(extra[extra.index("--fusion-time") + 1]) == SIM_FUSION_TIME
    assert float(extra[extra.index("--cooling-time") + 1]) == SIM_COOLING_TIME
    # a user's file: the simulator takes its layout from it
    options = _simulator_options(_daemon_args(config="my-ned2.yaml", sim_crucibles="A1"), CONFIG)
    extra = options["extra_args"]
    assert Path(extra[extra.index("--config") + 1]).name == "my-ned2.yaml"
    assert extra[extra.index("--crucibles") + 1] == "A1"


def test_a_ned2_cell_without_the_machines_stations_refuses_the_machines_options() -> None:
    from fxcell.daemon.cli import _simulator_options
    from fxcell.errors import FxcellError

    stations = {k: v for k, v in CONFIG.layout.stations.items() if k in ("rack", "tray")}
    layout = CONFIG.layout.model_copy(update={"stations": stations})
    bare = CONFIG.model_copy(update={"layout": layout})
    assert "extra_args" not in _simulator_options(_daemon_args(), bare)  # a bare Ned2
    with pytest.raises(FxcellError, match="--sim-crucibles: the layout has no"):
        _simulator_options(_daemon_args(sim_crucibles="2"), bare)
