"""Render the fusion machine's holder and run the placement check without a robot.

>>> from fxcell.testing.vision import VisionBench
>>> bench = VisionBench()                                   # the shipped configuration
>>> frame = bench.render({"A1": "seated", "A2": Fault.offset(0.004)})
>>> report = bench.check(frame, expected={"A1", "A2"})
>>> report.verdicts()["A2"]
'offset'

:class:`Fault` describes what stands in a position (a seated, offset or tilted crucible, a
foreign object, nothing); :func:`random_imaging` draws imaging conditions (exposure, light
gradient, noise, blur, JPEG quality, a small camera shift). The renderer is the simulator's
(:mod:`fxcell.sim.camera`).
"""

from __future__ import annotations

import math
import random
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fxcell.config import CellConfig
from fxcell.layout import Layout
from fxcell.sim.camera import Imaging, Renderer, Thing
from fxcell.vision.model import Deck, Intrinsics, camera_pose
from fxcell.vision.placement import PlacementChecker, PlacementReport

__all__ = ["Fault", "Imaging", "Thing", "VisionBench", "random_fault", "random_imaging"]


@dataclass(frozen=True)
class Fault:
    """What stands in one position: ``seated``, ``offset`` (by ``dx``, ``dy`` m), ``tilted``
    (by ``tilt`` rad towards ``azimuth``), ``foreign`` (a ``thing`` kind: box, bead, lump),
    ``empty``."""

    kind: str
    dx: float = 0.0
    dy: float = 0.0
    tilt: float = 0.0
    azimuth: float = 0.0
    thing: str = "box"
    size: float = 0.03
    colour: tuple[float, float, float] = (60.0, 90.0, 200.0)
    seed: int = 0

    @classmethod
    def seated(cls, dx: float = 0.0, dy: float = 0.0) -> Fault:
        return cls("seated", dx, dy)

    @classmethod
    def offset(cls, distance: float, direction: float = 0.0) -> Fault:
        """A crucible ``distance`` m off its position towards ``direction`` (rad from +x)."""
        return cls("offset", distance * math.cos(direction), distance * math.sin(direction))

    @classmethod
    def tilted(cls, tilt: float, azimuth: float = 0.0) -> Fault:
        return cls("tilted", tilt=tilt, azimuth=azimuth)

    @classmethod
    def foreign(
        cls,
        thing: str = "box",
        size: float = 0.03,
        colour: tuple[float, float, float] = (60.0, 90.0, 200.0),
        seed: int = 0,
    ) -> Fault:
        return cls("foreign", thing=thing, size=size, colour=colour, seed=seed)

    @classmethod
    def empty(cls) -> Fault:
        return cls("empty")

    @property
    def misplaced(self) -> bool:
        """A crucible that must not go into the machine like this (or something else)."""
        return self.kind in ("offset", "tilted", "foreign")

    def things(self, seat: np.ndarray, deck: Deck) -> list[Thing]:
        x, y = float(seat[0]), float(seat[1])
        kind = deck.kind
        if self.kind == "empty":
            return []
        if self.kind in ("seated", "offset"):
            return [Thing("crucible", (x + self.dx, y + self.dy, 0.0), kind.width, kind.height)]
        if self.kind == "tilted":
            # resting on the pocket's edge: the crucible turns about its bottom's far edge
            r = kind.width / 2 * 0.78
            c, s = math.cos(self.azimuth), math.sin(self.azimuth)
            lift = r * math.sin(self.tilt)
            shift = r * (1 - math.cos(self.tilt))
            return [
                Thing(
                    "crucible",
                    (x + c * shift, y + s * shift, lift),
                    kind.width,
                    kind.height,
                    tilt=self.tilt,
                    azimuth=self.azimuth,
                )
            ]
        if self.thing == "bead":
            return [Thing("bead", (x + self.dx, y + self.dy, 0.0), 0.034, 0.012)]
        if self.thing == "lump":
            return [
                Thing("lump", (x, y, 0.0), self.size, 0.004, colour=self.colour, seed=self.seed)
            ]
        return [
            Thing(
                "box", (x, y, 0.0), self.size, 0.02, self.size * 0.7, yaw=self.seed * 0.37,
                colour=self.colour,
            )
        ]  # fmt: skip


class VisionBench:
    """The holder, camera and checker of a configuration (default: the shipped one)."""

    def __init__(self, config: CellConfig | str | Path | None = None) -> None:
        if not isinstance(config, CellConfig):
            config = CellConfig.load(config)
        self.config = config
        self.layout = Layout(config.layout)
        self.deck = Deck.from_config(config.vision, self.layout)
        self.renderer = Renderer(self.deck, Intrinsics.from_config(config.vision.camera))
        self.checker = PlacementChecker(config.vision, self.layout)
        self.camera_in_station = self.deck.station.frame.inverse() @ camera_pose(
            config.vision.camera
        )

    @property
    def slots(self) -> list[str]:
        return list(self.deck.positions)

    def render(
        self,
        positions: Mapping[str, Fault | str],
        imaging: Imaging | None = None,
        extra: Sequence[Thing] = (),
    ) -> np.ndarray:
        """A frame with each named position as described (``"seated"``, ``"empty"`` or a
        :class:`Fault`; unnamed ones empty) and ``extra`` things anywhere on the holder."""
        things: list[Thing] = list(extra)
        for slot, fault in positions.items():
            f = Fault(fault) if isinstance(fault, str) else fault
            things += f.things(self.deck.positions[slot], self.deck)
        return self.renderer.render(self.camera_in_station, things, imaging or Imaging())

    def check(self, frame: np.ndarray, expected: Collection[str] | None = None) -> PlacementReport:
        return self.checker.check(frame, expected)


def random_imaging(rng: random.Random) -> Imaging:
    """Imaging conditions of a lab day: exposure, uneven light, noise, defocus, a camera
    knocked by a few millimetres and a fraction of a degree."""
    return Imaging(
        gain=rng.uniform(0.6, 1.35),
        gradient=(rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)),
        noise=rng.uniform(1.0, 7.0),
        blur=rng.choice([0.0, rng.uniform(0.3, 1.6)]),
        jpeg_quality=rng.choice([None, rng.randint(70, 95)]),
        shift=(
            rng.uniform(-0.006, 0.006),
            rng.uniform(-0.006, 0.006),
            rng.uniform(-0.01, 0.01),
            rng.uniform(-0.012, 0.012),
            rng.uniform(-0.012, 0.012),
            rng.uniform(-0.02, 0.02),
        ),
        seed=rng.randrange(2**31),
    )


FOREIGN_COLOURS = (
    (60.0, 90.0, 200.0),
    (200.0, 120.0, 40.0),
    (40.0, 170.0, 60.0),
    (225.0, 225.0, 225.0),
    (25.0, 25.0, 28.0),
)


def random_fault(rng: random.Random, kind: str) -> Fault:
    """A fault of ``kind`` with random parameters: offsets 2-10 mm in any direction, tilts
    15-25°, foreign boxes, bead rings and lumps of several sizes and colours."""
    if kind == "seated":
        # placement repeatability of the arm: a few tenths of a millimetre
        return Fault.seated(rng.gauss(0, 0.0002), rng.gauss(0, 0.0002))
    if kind == "offset":
        return Fault.offset(rng.uniform(0.002, 0.010), rng.uniform(0, 2 * math.pi))
    if kind == "tilted":
        return Fault.tilted(math.radians(rng.uniform(15, 25)), rng.uniform(0, 2 * math.pi))
    if kind == "foreign":
        thing = rng.choice(["box", "bead", "lump"])
        return Fault.foreign(
            thing, rng.uniform(0.018, 0.04), rng.choice(FOREIGN_COLOURS), rng.randrange(1000)
        )
    if kind == "empty":
        return Fault.empty()
    raise ValueError(f"unknown fault kind {kind!r}")
