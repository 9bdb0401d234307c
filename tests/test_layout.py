"""The cell layout: taught frames, slot grids, and the collision scene derived from them."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fxcell.config import CellConfig
from fxcell.errors import ConfigError, LayoutError, SlotError, UnknownStationError
from fxcell.geometry import Pose
from fxcell.layout import Layout, LayoutConfig, frame_from_points, parse_slot, slot_name
from fxcell.motion.collision import CollisionChecker

CONFIG = CellConfig.load()
LAYOUT = Layout(CONFIG.layout)

unit = st.floats(-1.0, 1.0, allow_nan=False)
angles = st.tuples(*(st.floats(-np.pi, np.pi) for _ in range(3)))


@given(st.tuples(unit, unit, unit), angles, st.floats(0.01, 0.5), st.floats(0.01, 0.5), unit)
def test_three_taught_points_give_back_the_frame_they_were_taken_from(
    origin: tuple[float, float, float],
    rpy: tuple[float, float, float],
    along_x: float,
    off_axis: float,
    skew: float,
) -> None:
    frame = Pose.from_rpy(origin, rpy)
    taught = frame_from_points(
        frame.transform_point([0, 0, 0]),
        frame.transform_point([along_x, 0, 0]),
        frame.transform_point([skew * 0.3, off_axis, 0]),
    )
    assert taught.isclose(frame, position_tol=1e-9, angle_tol=1e-7)


@pytest.mark.parametrize(
    ("x_point", "xy_point"),
    [([0.001, 0, 0], [0, 0.1, 0]), ([0.1, 0, 0], [0.2, 0.001, 0]), ([np.nan, 0, 0], [0, 1, 0])],
)
def test_degenerate_taught_points_are_refused(x_point: list[float], xy_point: list[float]) -> None:
    with pytest.raises(LayoutError):
        frame_from_points([0, 0, 0], x_point, xy_point)


@given(st.integers(0, 25), st.integers(0, 98))
def test_slot_names_round_trip(row: int, column: int) -> None:
    assert parse_slot(slot_name(row, column)) == (row, column)
    assert parse_slot(slot_name(row, column).lower()) == (row, column)


@given(
    st.text(max_size=5).filter(lambda s: not s.strip()[:1].isalpha() or not s.strip()[1:].isdigit())
)
def test_malformed_slot_names_are_refused(name: str) -> None:
    with pytest.raises(SlotError):
        parse_slot(name)


def test_slots_outside_the_grid_are_refused_with_the_valid_range() -> None:
    with pytest.raises(SlotError, match=r"A1\.\.D4"):
        LAYOUT.slot("rack", "E1")
    with pytest.raises(SlotError, match=r"A1\.\.A4"):
        LAYOUT.slot("machine", "A5")
    with pytest.raises(SlotError):
        LAYOUT.slot("rack", "A0")


def test_an_unknown_station_lists_the_known_ones() -> None:
    with pytest.raises(UnknownStationError, match="machine, moulds, rack, tray"):
        LAYOUT.station("oven")


def test_the_grip_pose_points_down_at_the_grip_height_above_the_seat() -> None:
    rack = LAYOUT.station("rack")
    grip = rack.grip_pose("B3")
    seat = rack.seat("B3")
    assert np.allclose(grip.position - seat, [0, 0, rack.kind.grip_height])
    assert np.allclose(grip.rotation[:, 2], [0, 0, -1])
    assert np.allclose(rack.seat("B3") - rack.seat("A1"), [2 * 0.045, 0.045, 0])
    approach = rack.approach_pose("B3")
    assert np.allclose(approach.position - grip.position, [0, 0, rack.config.approach])


def _moved(layout: LayoutConfig, station: str, shift: np.ndarray, yaw: float) -> LayoutConfig:
    data = layout.model_dump()
    frame = data["stations"][station]["frame"]
    turn = Pose.from_rpy([0, 0, 0], [0, 0, yaw])
    for key in ("origin", "x_point", "xy_point"):
        frame[key] = tuple(turn.transform_point(frame[key]) + shift)
    return LayoutConfig.model_validate(data)


def test_re_teaching_a_station_frame_moves_every_slot_and_its_obstacle() -> None:
    shift, yaw = np.array([0.01, -0.02, 0.005]), 0.1
    moved = Layout(_moved(CONFIG.layout, "rack", shift, yaw))
    turn = Pose.from_rpy([0, 0, 0], [0, 0, yaw])
    before, after = LAYOUT.station("rack"), moved.station("rack")
    for slot in before.slots:
        assert np.allclose(after.seat(slot), turn.transform_point(before.seat(slot)) + shift)
    body_before, body_after = before.body_pose(), after.body_pose()
    assert body_before is not None
    assert body_after is not None
    assert np.allclose(
        body_after[0].position, turn.transform_point(body_before[0].position) + shift
    )
    # The other stations stay where they were.
    assert np.allclose(moved.station("tray").seat("A1"), LAYOUT.station("tray").seat("A1"))


def test_the_collision_scene_is_built_from_the_layout() -> None:
    checker = CollisionChecker.for_config(CONFIG)
    assert {"table", "rack", "tray", "machine", "moulds"} <= set(checker.names)


def test_every_slot_of_the_shipped_layout_is_reachable_without_collision() -> None:
    from fxcell.motion.kinematics import Kinematics

    checker = CollisionChecker.for_config(CONFIG)
    kin = Kinematics.ur3e().with_tcp(CONFIG.tool.tcp)
    for station in LAYOUT:
        for slot in station.slots:
            for pose in (station.grip_pose(slot), station.approach_pose(slot)):
                free = [q for q in kin.inverse_all(pose) if not checker.in_collision(q)]
                assert free, f"{station.name} {slot}: no collision-free solution"


def test_a_station_holding_an_unknown_object_kind_is_a_config_error() -> None:
    data = CONFIG.model_dump()
    data["layout"]["stations"]["rack"]["holds"] = "beaker"
    with pytest.raises(ConfigError, match="unknown object kind 'beaker'"):
        CellConfig.from_dict(data)


def test_a_held_crucible_collides_where_the_bare_gripper_passes() -> None:
    from fxcell.motion.kinematics import Kinematics

    checker = CollisionChecker.for_config(CONFIG)
    kin = Kinematics.ur3e().with_tcp(CONFIG.tool.tcp)
    rack = LAYOUT.station("rack")
    # The TCP 15 mm below the grip point: the fingers clear the rack's body, a crucible
    # hanging 25 mm below them would not.
    low = rack.grip_pose("B2") @ Pose([0, 0, 0.015])
    free = [q for q in kin.inverse_all(low) if not checker.in_collision(q)]
    assert free
    checker.attach("crucible")
    assert checker.held == "crucible"
    assert all(checker.in_collision(q) for q in free)
    assert any("held_crucible" in pair for pair in checker.colliding_pairs(free[0]))
    checker.detach()
    assert not checker.in_collision(free[0])


def test_the_walls_of_the_free_space_do_not_depend_on_what_is_held() -> None:
    bare = CollisionChecker.for_config(CONFIG)
    holding = CollisionChecker.for_config(CONFIG)
    holding.attach("crucible")
    assert holding.walls() == bare.walls()
    holding.detach()
    assert holding.walls() == bare.walls()
