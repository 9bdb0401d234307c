"""A Robotiq Hand-E behind the Robotiq URCap's socket server (port 63352), and the objects it grips.

The URCap on a real controller serves ASCII lines: ``SET VAR value [VAR value ...]`` (reply
``ack``) and ``GET VAR`` (reply ``VAR value``). The variables mirror the gripper's registers:
``ACT`` activate, ``GTO`` go to the requested position, ``POS`` requested (SET) or actual (GET)
position 0 (open) .. 255 (closed), ``SPE``/``FOR`` speed and force 0..255, ``PRE`` echo of the
requested position, ``STA`` 0 reset / 1 activating / 3 active, ``OBJ`` 0 moving / 1 stopped on
an object while opening / 2 while closing / 3 at the requested position, ``FLT`` fault code.

Hand-E: 50 mm stroke, 20..150 mm/s, 20..185 N. Finger motion and activation take time, both
multiplied by the simulator's time scale. The gripper is powered from the tool flange: with the
arm off it loses its activation and does not move.

Objects (crucibles, glass beads) are upright cylinders with a grip width, height and mass.
Closing with the TCP at an object's grip point stops the fingers at its width (``OBJ`` 2) and
the object then moves with the TCP until the fingers open past it; it stays where released.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fxcell.geometry import Pose

log = logging.getLogger(__name__)

URCAP_GRIPPER_PORT = 63352
STROKE = 0.050  # m, fully open width
SPEED_RANGE = (0.020, 0.150)  # m/s at SPE 0 and 255
FORCE_RANGE = (20.0, 185.0)  # N at FOR 0 and 255
ACTIVATION_TIME = 1.0  # s before time scaling (the gripper opens and closes to find its stroke)
GRASP_TOLERANCE = 0.005  # m: an object's grip point this close to the TCP is between the fingers
DEFAULT_FAULT = 0x0E  # overcurrent (Robotiq's major fault codes are 0x0A and above)

VARIABLES = ("ACT", "GTO", "ATR", "ARD", "POS", "SPE", "FOR", "STA", "OBJ", "FLT", "PRE")


def width_of(position: int) -> float:
    """Finger opening in m for a position register value (0 open, 255 closed)."""
    return STROKE * (1.0 - max(0, min(255, position)) / 255.0)


def position_of(width: float) -> int:
    """Position register value (0..255) of a finger opening in m."""
    return max(0, min(255, round(255.0 * (1.0 - width / STROKE))))


@dataclass
class SimObject:
    """A graspable object of the simulated world (pose of its grip point, base frame)."""

    name: str
    kind: str
    width: float  # m across the fingers
    height: float  # m
    mass: float  # kg
    pose: Pose
    held_from: Pose | None = None  # the object in the TCP frame while held
    contents: str | None = None  # what it carries (a crucible's sample), None when empty

    def as_json(self) -> dict[str, object]:
        return {
            "kind": self.kind,
            "width": self.width,
            "height": self.height,
            "mass": self.mass,
            "pose": list(self.pose.as_ur()),
            "held": self.held_from is not None,
            "contents": self.contents,
        }


class HandE:
    """The gripper's registers and finger motion, advanced by :meth:`tick` (controller time)."""

    def __init__(
        self,
        *,
        time_scale: float,
        tcp_pose: Callable[[], Pose],
        powered: Callable[[], bool],
    ) -> None:
        self.time_scale = time_scale
        self.tcp_pose = tcp_pose
        self.powered = powered
        self.act = 0
        self.gto = 0
        self.atr = 0
        self.ard = 0
        self.pre = 0
        self.requested = 0
        self.spe = 255
        self.force = 150
        self.sta = 0
        self.obj = 0
        self.flt = 0
        self.width = STROKE
        self.moving = False
        self.activation_done_at: float | None = None
        self.objects: dict[str, SimObject] = {}
        self.held: SimObject | None = None
        self.slipped: str | None = None  # out of the fingers' reach until they next open
        self.release_offset: tuple[float, float] | None = None
        """``inject place_offset DX DY``: the next object released lands this far (m, base x
        and y) from where the fingers let it go (a crucible that slid on the pocket's edge)."""
        self._time: float | None = None

    # ------------------------------------------------------------------ protocol

    def handle(self, line: str) -> str:
        """The URCap server's reply to one request line."""
        words = line.split()
        if not words:
            return "?"
        cmd = words[0].upper()
        if cmd == "GET" and len(words) == 2:
            name = words[1].upper()
            value = self.get(name)
            return "?" if value is None else f"{name} {value}"
        if cmd == "SET" and len(words) >= 3 and len(words) % 2 == 1:
            pairs: list[tuple[str, int]] = []
            for name, text in zip(words[1::2], words[2::2], strict=True):
                try:
                    value = int(text)
                except ValueError:
                    return "?"
                if name.upper() not in VARIABLES:
                    return "?"
                pairs.append((name.upper(), max(0, min(255, value))))
            for name, value in pairs:
                self.set(name, value)
            return "ack"
        return "?"

    def get(self, name: str) -> int | None:
        values = {
            "ACT": self.act,
            "GTO": self.gto,
            "ATR": self.atr,
            "ARD": self.ard,
            "POS": position_of(self.width),
            "SPE": self.spe,
            "FOR": self.force,
            "STA": self.sta,
            "OBJ": self.obj,
            "FLT": self.flt,
            "PRE": self.pre,
        }
        return values.get(name)

    def set(self, name: str, value: int) -> None:
        if name == "ACT":
            if value == 0:
                self._reset()
            elif self.act == 0:
                self.act = 1
                self.flt = 0
                if self.powered():
                    self._start_activation()
        elif name == "GTO":
            self.gto = 1 if value else 0
            if self.gto:
                self._go()
            else:
                self.moving = False
        elif name == "POS":
            self.requested = value
            self.pre = value
            if self.gto:
                self._go()
        elif name == "SPE":
            self.spe = value
        elif name == "FOR":
            self.force = value
        elif name == "ATR":
            self.atr = value
        elif name == "ARD":
            self.ard = value

    def _reset(self) -> None:
        self.act = self.gto = 0
        self.sta = 0
        self.obj = 0
        self.flt = 0
        self.moving = False
        self.activation_done_at = None

    def _start_activation(self) -> None:
        self.sta = 1
        self.activation_done_at = (self._time or 0.0) + ACTIVATION_TIME * self.time_scale

    def _go(self) -> None:
        if self.sta != 3 or self.flt or not self.powered():
            return
        self.obj = 0
        self.moving = True

    # ------------------------------------------------------------------ motion

    @property
    def speed(self) -> float:
        lo, hi = SPEED_RANGE
        return lo + (hi - lo) * self.spe / 255.0

    @property
    def grip_force(self) -> float:
        lo, hi = FORCE_RANGE
        return lo + (hi - lo) * self.force / 255.0

    def tick(self, now: float) -> None:
        """Advance to controller time ``now`` (s)."""
        dt = 0.0 if self._time is None else max(0.0, now - self._time)
        self._time = now
        if not (self.act or self.sta or self.moving or self.held is not None):
            return  # never activated and holding nothing: no state to advance
        if not self.powered():
            if self.act or self.sta:
                log.info("gripper: tool power lost, activation cleared")
                self._reset()
        elif (
            self.sta == 1 and self.activation_done_at is not None and now >= self.activation_done_at
        ):
            self.sta = 3
            self.activation_done_at = None
            self.width = STROKE
            if self.gto:
                self._go()
        if self.moving and not self.flt:
            self._move(dt)
        if self.held is not None and self.held.held_from is not None:
            self.held.pose = self.tcp_pose() @ self.held.held_from

    def _move(self, dt: float) -> None:
        target = width_of(self.requested)
        step = self.speed * dt / self.time_scale
        closing = target < self.width
        if closing:
            new = max(target, self.width - step)
            if self.held is None:
                grasped = self._object_between_fingers()
                if grasped is not None and new <= grasped.width < self.width + 1e-12:
                    self.width = grasped.width
                    self.moving = False
                    self.obj = 2
                    grasped.held_from = self.tcp_pose().inverse() @ grasped.pose
                    self.held = grasped
                    log.info("gripper: holding %s", grasped.name)
                    return
            elif new <= self.held.width:
                self.width = self.held.width
                self.moving = False
                self.obj = 2
                return
        else:
            new = min(target, self.width + step)
            self.slipped = None
            if self.held is not None and new > self.held.width + 0.0005:
                self._release()
        self.width = new
        if abs(new - target) < 1e-9:
            self.moving = False
            self.obj = 3

    def _object_between_fingers(self) -> SimObject | None:
        tcp = self.tcp_pose().position
        best: tuple[float, SimObject] | None = None
        for o in self.objects.values():
            if o.name == self.slipped:
                continue
            d = float(np.linalg.norm(o.pose.position - tcp))
            if d <= GRASP_TOLERANCE and (best is None or d < best[0]):
                best = (d, o)
        return None if best is None else best[1]

    def _release(self) -> None:
        if self.held is not None:
            log.info("gripper: released %s", self.held.name)
            self.held.held_from = None
            if self.release_offset is not None:
                dx, dy = self.release_offset
                self.release_offset = None
                pose = self.held.pose
                self.held.pose = type(pose)(pose.position + np.array([dx, dy, 0.0]), pose.rotation)
                log.info("gripper: %s landed %.1f mm off", self.held.name, 1000 * np.hypot(dx, dy))
            self.held = None

    # ------------------------------------------------------------------ faults, world

    def inject_fault(self, code: int = DEFAULT_FAULT) -> str:
        """A gripper fault: the fingers stop and ``FLT`` reports ``code`` until reactivated."""
        self.flt = code
        self.moving = False
        return f"gripper fault 0x{code:02X}"

    def drop(self) -> str:
        """The held object slips out: it stays where it is, the fingers go on closing."""
        if self.held is None:
            return "nothing held"
        name = self.held.name
        self._release()
        self.slipped = name
        if self.sta == 3 and self.gto and not self.flt:
            self.obj = 0
            self.moving = True
        return f"{name} dropped"

    def add_object(self, obj: SimObject) -> None:
        if self.held is not None and self.held.name == obj.name:
            self._release()
        self.objects[obj.name] = obj

    def state(self) -> dict[str, object]:
        return {
            "act": self.act,
            "sta": self.sta,
            "gto": self.gto,
            "obj": self.obj,
            "flt": self.flt,
            "pre": self.pre,
            "width": self.width,
            "speed": self.speed,
            "force": self.grip_force,
            "held": None if self.held is None else self.held.name,
            "tcp_pose": list(self.tcp_pose().as_ur()),
        }


class GripperConnection(asyncio.Protocol):
    """One client of the URCap gripper socket: one reply line per request line."""

    def __init__(self, gripper: HandE) -> None:
        self.gripper = gripper
        self.transport: asyncio.Transport | None = None
        self.buffer = b""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        while self.transport is not None and b"\n" in self.buffer:
            raw, self.buffer = self.buffer.split(b"\n", 1)
            line = raw.decode("ascii", "replace").strip()
            if line:
                self.transport.write((self.gripper.handle(line) + "\n").encode())
