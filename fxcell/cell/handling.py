"""Pick and place at the layout's slots: approach, descend straight, grip or release, rise.

A step that fails because the robot link dropped or restarted under it is done again once
the link, the arm at rest and external control are back (:mod:`fxcell.cell.healing`):
each is a move to a fixed target or a gripper command, so it goes on from wherever the arm
braked. Everything that can be checked is checked before the arm moves: the station and slot names,
the zone's interlock, the gripper's readiness and what it holds, and that the approach, grip
and retreat poses have collision-free IK solutions on one arm configuration. Each step is a
recorded command of its own (``move_pose``, ``gripper_close``, ...) inside the recorded
``pick``/``place``.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Protocol

import numpy as np

from fxcell.cell.healing import Recoverable, resilient
from fxcell.errors import (
    FxcellError,
    GripperError,
    HoldingError,
    InterlockError,
    NothingGraspedError,
    UnreachableError,
)
from fxcell.geometry import Pose
from fxcell.layout import Layout, Station
from fxcell.results import GripResult

if TYPE_CHECKING:
    from fxcell.cell.context import CellContext
    from fxcell.cell.gripper import Gripper
    from fxcell.cell.io import CellIO
    from fxcell.motion.moves import MotionController
    from fxcell.results import MoveResult

CLEARANCE = 0.012
"""Finger opening beyond an object's width when approaching or releasing it (m)."""
SAME_BRANCH = 0.6
"""Largest joint change (rad) between the approach and grip solutions: a straight descent
must not need a different arm configuration."""


class SlotCell(Recoverable, Protocol):
    """The commands and parts of a :class:`~fxcell.cell.Cell` that pick and place are made
    of (each step is a recorded command of its own); the rest comes through the
    :class:`~fxcell.cell.context.CellContext`."""

    @property
    def layout(self) -> Layout: ...

    @property
    def held(self) -> str | None: ...

    @property
    def io(self) -> CellIO: ...

    @property
    def gripper(self) -> Gripper: ...

    @property
    def motion(self) -> MotionController: ...

    async def move_pose(
        self,
        target: Pose,
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        linear: bool = False,
    ) -> MoveResult: ...

    async def gripper_move(self, width: float) -> GripResult: ...

    async def gripper_close(self, *, expect_object: bool = False) -> GripResult: ...


def check_interlock(cell: SlotCell, station: Station) -> None:
    """Refuse a move into ``station`` while its zone's interlock signal is on."""
    zone = station.config.zone
    signal = cell.config.io.interlocks.get(zone) if zone else None
    if signal is None:
        return
    if cell.io.get(signal):
        raise InterlockError(
            f"{station.name}: the {zone} zone is interlocked ({signal} is on); wait until it clears"
        )


def admit_pick(cell: SlotCell, station_name: str, slot_name: str) -> tuple[Station, str]:
    """The station and slot of a pick, or the error that refuses it (names, interlock,
    a held object, an object wider than the gripper opens): no IK yet (see
    :func:`reach_slot`)."""
    station, slot = cell.layout.slot(station_name, slot_name)
    check_interlock(cell, station)
    if cell.held is not None:
        raise HoldingError(
            f"pick refused: the gripper holds a {cell.held}; place or release it first"
        )
    cell.gripper.check_fits(station.kind.width, station.config.holds)
    return station, slot


def admit_place(cell: SlotCell, station_name: str, slot_name: str) -> tuple[Station, str]:
    """The station and slot of a place, or the error that refuses it (names, interlock,
    nothing or the wrong kind held)."""
    station, slot = cell.layout.slot(station_name, slot_name)
    check_interlock(cell, station)
    if cell.held is None:
        raise HoldingError("place refused: the gripper holds nothing; pick an object first")
    if cell.held != station.config.holds:
        raise HoldingError(
            f"place refused: {station.name} takes {station.config.holds}s, "
            f"the gripper holds a {cell.held}"
        )
    return station, slot


async def check(
    cell: SlotCell,
    context: CellContext,
    name: str,
    station_name: str,
    slot_name: str,
    velocity_factor: float | None,
    acceleration_factor: float | None,
) -> None:
    """Raise what refuses ``pick`` or ``place`` (``name``) before anything moves: names,
    interlock, what the gripper holds, factors, reach of the slot's three poses."""
    station, slot = ADMIT[name](cell, station_name, slot_name)
    cell.motion.factors(velocity_factor, acceleration_factor)
    await reach_slot(cell, context, station, slot)


async def reach_slot(cell: SlotCell, context: CellContext, station: Station, slot: str) -> None:
    """IK for approach, grip and retreat on one configuration, free of collision (in the
    planner's worker thread, one at a time with plans)."""
    q0 = np.asarray(context.sample().actual_q, float)
    await cell.motion.locked(lambda: _reach_slot(cell, station, slot, q0))


def _reach_slot(cell: SlotCell, station: Station, slot: str, q0: np.ndarray) -> None:
    planner = cell.motion.planner
    what = f"{station.name} {slot}"
    try:
        q_above = planner.solve(station.approach_pose(slot), q0)
        q_grip = planner.solve(station.grip_pose(slot), q_above)
        q_retreat = planner.solve(station.retreat_pose(slot), q_grip)
    except FxcellError as exc:
        raise type(exc)(f"{what} cannot be reached: {exc}") from None
    if max(np.abs(q_grip - q_above).max(), np.abs(q_retreat - q_grip).max()) > SAME_BRANCH:
        raise UnreachableError(f"{what}: no straight descent on one arm configuration")


async def pick(
    cell: SlotCell,
    context: CellContext,
    station_name: str,
    slot_name: str,
    velocity_factor: float | None,
    acceleration_factor: float | None,
) -> GripResult:
    station, slot = admit_pick(cell, station_name, slot_name)
    cell.motion.factors(velocity_factor, acceleration_factor)
    where = f"{station.name} {slot}"
    await resilient(cell, f"check {where}", _checked(cell, context, station, slot))
    kind = station.kind
    vf, af = velocity_factor, acceleration_factor
    open_width = cell.gripper.opening(kind.width + CLEARANCE)
    await resilient(cell, "open the gripper", lambda: cell.gripper_move(open_width))
    await resilient(
        cell, f"approach {where}", lambda: cell.move_pose(station.approach_pose(slot), vf, af)
    )
    check_interlock(cell, station)
    await resilient(
        cell,
        f"descend to {where}",
        lambda: cell.move_pose(station.grip_pose(slot), vf, af, linear=True),
    )
    try:
        grip = await resilient(
            cell, f"grip at {where}", lambda: cell.gripper_close(expect_object=True)
        )
    except NothingGraspedError:
        await resilient(cell, "open the gripper", lambda: cell.gripper_move(open_width))
        await resilient(
            cell,
            f"rise from {where}",
            lambda: cell.move_pose(station.retreat_pose(slot), vf, af, linear=True),
        )
        raise NothingGraspedError(
            f"no {station.config.holds} detected in {station.name} slot {slot}"
        ) from None
    await resilient(cell, "hold", lambda: context.hold(station.config.holds))
    await resilient(
        cell,
        f"rise from {where}",
        lambda: cell.move_pose(station.retreat_pose(slot), vf, af, linear=True),
    )
    try:
        await cell.gripper.check_holding()
    except GripperError:
        await context.hold(None)
        raise
    return grip


async def place(
    cell: SlotCell,
    context: CellContext,
    station_name: str,
    slot_name: str,
    velocity_factor: float | None,
    acceleration_factor: float | None,
) -> GripResult:
    station, slot = admit_place(cell, station_name, slot_name)
    cell.motion.factors(velocity_factor, acceleration_factor)
    where = f"{station.name} {slot}"
    await resilient(cell, f"check {where}", _checked(cell, context, station, slot))
    vf, af = velocity_factor, acceleration_factor
    await resilient(
        cell, f"approach {where}", lambda: cell.move_pose(station.approach_pose(slot), vf, af)
    )
    check_interlock(cell, station)
    await cell.gripper.check_holding()
    await resilient(
        cell,
        f"descend to {where}",
        lambda: cell.move_pose(station.grip_pose(slot), vf, af, linear=True),
    )
    width = cell.gripper.opening(station.kind.width + CLEARANCE)
    released = await resilient(cell, f"release at {where}", lambda: cell.gripper_move(width))
    await resilient(cell, "let go", lambda: context.hold(None))
    await resilient(
        cell,
        f"rise from {where}",
        lambda: cell.move_pose(station.retreat_pose(slot), vf, af, linear=True),
    )
    return released


def _checked(
    cell: SlotCell, context: CellContext, station: Station, slot: str
) -> Callable[[], Awaitable[None]]:
    """The checks before a pick or place moves (they need the robot's state), repeated
    when a lost link interrupts them."""

    async def check() -> None:
        check_interlock(cell, station)
        await reach_slot(cell, context, station, slot)

    return check


ADMIT = {"pick": admit_pick, "place": admit_place}
"""The admission check of each slot command (see :func:`check`)."""
