"""The cell layout: stations as taught frames, each with a grid of slots holding one kind of object.

A station's frame is taught with three points in the robot base frame (as on the teach
pendant's "Point" plane feature): ``origin``, a point on its x axis and a point in its xy plane.
Its slots form a grid: rows along the frame's y axis (named ``A``, ``B``, ...), columns along x
(numbered from 1), so ``B3`` is the second row, third column; slot ``A1`` sits at the origin.
A slot's *seat* is where the bottom of the object stands; the gripper grasps it ``grip_height``
above the seat, pointing down the station's z axis. ``approach``/``retreat`` are heights above the
grip point from which the gripper descends and to which it rises, straight.

The layout is also the collision scene's source: each station's ``body`` (a box in the
station frame) is an obstacle, so re-teaching a station moves its slots and its obstacle
together. Units: metres, radians.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from fxcell.errors import LayoutError, SlotError, UnknownStationError

if TYPE_CHECKING:
    from fxcell.geometry import FloatArray, Pose

# numpy (and fxcell.geometry) are imported where the geometry is computed: the light network
# client reads the configuration, and with it these models, without them.

Vector3 = tuple[float, float, float]

_SLOT = re.compile(r"^([A-Za-z])([1-9][0-9]*)$")
_FRAME_MIN_SPAN = 0.005  # m: taught points closer than this give no usable axis


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ObjectKind(_Model):
    """A kind of graspable object (an upright cylinder for the gripper)."""

    width: float = Field(gt=0, lt=0.05)
    """Across the fingers (m); below the Hand-E's 50 mm stroke."""
    height: float = Field(gt=0)
    grip_height: float = Field(ge=0)
    """Height of the grip point above the object's bottom (m)."""
    mass: float = Field(gt=0, le=3.0)

    @model_validator(mode="after")
    def _grip_inside(self) -> ObjectKind:
        if self.grip_height > self.height:
            raise ValueError("grip_height must not exceed height")
        return self


class TaughtFrame(_Model):
    """Three taught points (base frame): the origin, one on +x, one in the xy plane (+y side)."""

    origin: Vector3
    x_point: Vector3
    xy_point: Vector3

    def pose(self) -> Pose:
        """The frame as a pose in the base frame (raises :class:`LayoutError` if degenerate)."""
        return frame_from_points(self.origin, self.x_point, self.xy_point)


class Box(_Model):
    """A box in a station's frame: centre and size (m)."""

    size: Vector3
    position: Vector3 = (0.0, 0.0, 0.0)

    @field_validator("size")
    @classmethod
    def _positive(cls, v: Vector3) -> Vector3:
        if not all(math.isfinite(x) and x > 0 for x in v):
            raise ValueError("every size must be a finite number > 0")
        return v


class StationConfig(_Model):
    """A station: where it is (taught frame), its slot grid and what it holds."""

    holds: str
    """The object kind its slots hold (a key of ``layout.objects``)."""
    frame: TaughtFrame
    rows: int = Field(1, ge=1, le=26)
    columns: int = Field(1, ge=1, le=99)
    pitch: tuple[float, float] = (0.0, 0.0)
    """Distance between neighbouring columns (along x) and rows (along y), m."""
    approach: float = Field(0.08, gt=0, le=0.3)
    retreat: float = Field(0.08, gt=0, le=0.3)
    body: Box | None = None
    """The station's obstacle for collision checking, in its frame."""
    zone: str | None = None
    """A named zone (e.g. ``machine``) whose interlocks guard moves into this station."""

    @model_validator(mode="after")
    def _pitch_given(self) -> StationConfig:
        if self.columns > 1 and self.pitch[0] <= 0:
            raise ValueError("pitch[0] (between columns) must be > 0 with several columns")
        if self.rows > 1 and self.pitch[1] <= 0:
            raise ValueError("pitch[1] (between rows) must be > 0 with several rows")
        return self


class LayoutConfig(_Model):
    """Object kinds and stations of the cell."""

    objects: dict[str, ObjectKind] = {}
    stations: dict[str, StationConfig] = {}

    @model_validator(mode="after")
    def _kinds_known(self) -> LayoutConfig:
        for name, st in self.stations.items():
            if st.holds not in self.objects:
                known = ", ".join(sorted(self.objects)) or "none"
                raise ValueError(
                    f"station {name!r} holds unknown object kind {st.holds!r} (known: {known})"
                )
        return self


def frame_from_points(origin: Any, x_point: Any, xy_point: Any) -> Pose:
    """The frame through three points: x towards ``x_point``, y towards ``xy_point``'s side."""
    import numpy as np

    from fxcell.geometry import Pose

    o, px, pxy = (np.asarray(p, dtype=float).reshape(3) for p in (origin, x_point, xy_point))
    if not all(np.all(np.isfinite(p)) for p in (o, px, pxy)):
        raise LayoutError("taught points must be finite")
    x = px - o
    if np.linalg.norm(x) < _FRAME_MIN_SPAN:
        raise LayoutError(
            f"the x point must be at least {_FRAME_MIN_SPAN * 1e3:.0f} mm from the origin"
        )
    x /= np.linalg.norm(x)
    v = pxy - o
    y = v - x * float(v @ x)
    if np.linalg.norm(y) < _FRAME_MIN_SPAN:
        raise LayoutError(
            f"the xy-plane point must lie at least {_FRAME_MIN_SPAN * 1e3:.0f} mm off the x axis"
        )
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    return Pose(o, np.column_stack((x, y, z)))


def parse_slot(name: str) -> tuple[int, int]:
    """``"B3"`` → ``(1, 2)`` (row and column index from 0)."""
    m = _SLOT.match(name.strip()) if isinstance(name, str) else None
    if m is None:
        raise SlotError(f"not a slot name: {name!r} (a row letter and a column number, e.g. 'B3')")
    return ord(m.group(1).upper()) - ord("A"), int(m.group(2)) - 1


def slot_name(row: int, column: int) -> str:
    return f"{chr(ord('A') + row)}{column + 1}"


_DOWN = ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))
"""The gripper pointing down the station's z axis, fingers closing along its y axis."""


@dataclass(frozen=True)
class Station:
    """A station of the layout, resolved into the base frame."""

    name: str
    config: StationConfig
    kind: ObjectKind
    frame: Pose

    @property
    def slots(self) -> list[str]:
        """Slot names, row by row (``A1``, ``A2``, ..., ``B1``, ...)."""
        return [
            slot_name(r, c) for r in range(self.config.rows) for c in range(self.config.columns)
        ]

    def index(self, slot: str) -> tuple[int, int]:
        """Row and column of a slot of this station, or :class:`SlotError`."""
        row, col = parse_slot(slot)
        if row >= self.config.rows or col >= self.config.columns:
            last = slot_name(self.config.rows - 1, self.config.columns - 1)
            raise SlotError(
                f"station {self.name!r} has slots A1..{last}; {slot!r} is not one of them"
            )
        return row, col

    def seat(self, slot: str) -> FloatArray:
        """Where the bottom of the slot's object stands (base frame, m)."""
        row, col = self.index(slot)
        local = (col * self.config.pitch[0], row * self.config.pitch[1], 0.0)
        return self.frame.transform_point(local)

    def grip_pose(self, slot: str) -> Pose:
        """TCP pose grasping the slot's object: at its grip point, pointing down the station z."""
        from fxcell.geometry import Pose

        row, col = self.index(slot)
        local = (col * self.config.pitch[0], row * self.config.pitch[1], self.kind.grip_height)
        return self.frame @ Pose(local, _DOWN)

    def above(self, slot: str, height: float) -> Pose:
        """The grip pose raised ``height`` along the station's z axis."""
        from fxcell.geometry import Pose

        grip = self.grip_pose(slot)
        return Pose(grip.position + self.frame.rotation[:, 2] * height, grip.rotation)

    def approach_pose(self, slot: str) -> Pose:
        return self.above(slot, self.config.approach)

    def retreat_pose(self, slot: str) -> Pose:
        return self.above(slot, self.config.retreat)

    def body_pose(self) -> tuple[Pose, Vector3] | None:
        """The station's obstacle: its centre pose in the base frame and its size."""
        from fxcell.geometry import Pose

        if self.config.body is None:
            return None
        return self.frame @ Pose(self.config.body.position), self.config.body.size


class Layout:
    """All stations, resolved; the single source of slot poses and station obstacles."""

    def __init__(self, config: LayoutConfig) -> None:
        self.config = config
        self.stations: dict[str, Station] = {
            name: Station(name, st, config.objects[st.holds], st.frame.pose())
            for name, st in config.stations.items()
        }

    def __iter__(self) -> Iterator[Station]:
        return iter(self.stations.values())

    def station(self, name: str) -> Station:
        """The station called ``name`` or a :class:`LayoutError` listing the known ones."""
        try:
            return self.stations[name]
        except KeyError:
            known = ", ".join(sorted(self.stations)) or "none"
            raise UnknownStationError(f"no station {name!r} (known: {known})") from None

    def slot(self, station: str, slot: str) -> tuple[Station, str]:
        """Validate ``station``/``slot`` and return the station and the slot's canonical name."""
        st = self.station(station)
        row, col = st.index(slot)
        return st, slot_name(row, col)


def layout_data(layout: Layout) -> dict[str, Any]:
    """The layout as JSON-ready data (for the page and the API): per station its frame,
    grid, object kind, zone, body and every slot's seat and grip pose (UR vectors)."""
    stations: dict[str, Any] = {}
    for st in layout:
        body = st.body_pose()
        stations[st.name] = {
            "holds": st.config.holds,
            "zone": st.config.zone,
            "rows": st.config.rows,
            "columns": st.config.columns,
            "pitch": list(st.config.pitch),
            "frame": st.config.frame.model_dump(),
            "frame_pose": list(st.frame.as_ur()),
            "body": None
            if body is None
            else {"pose": list(body[0].as_ur()), "size": list(body[1])},
            "slots": {
                slot: {"seat": st.seat(slot).tolist(), "grip": list(st.grip_pose(slot).as_ur())}
                for slot in st.slots
            },
        }
    objects = {name: kind.model_dump() for name, kind in layout.config.objects.items()}
    return {"objects": objects, "stations": stations}
