"""``cell.camera``: the cell's camera and the placement check of the fusion machine's positions.

The camera (``vision.camera`` in the configuration: an OpenCV capture, a snapshot URL or the
simulator's rendered camera) is opened on first use. :meth:`CellCamera.check` takes a frame,
judges it off the event loop (:class:`fxcell.vision.placement.PlacementChecker`), keeps the
result as :attr:`CellCamera.last` and publishes it (image and verdict) on the event bus, so
the recorder writes it to MCAP and the daemon's page shows it.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Collection
from typing import TYPE_CHECKING

import cv2
import numpy as np

from fxcell.errors import CameraError
from fxcell.events import PlacementEvent
from fxcell.layout import Layout
from fxcell.vision.camera import Camera, open_camera
from fxcell.vision.placement import PlacementChecker, PlacementReport

if TYPE_CHECKING:
    from fxcell.cell.cell import Cell


class CellCamera:
    """The camera of a :class:`~fxcell.cell.Cell` (``cell.camera``)."""

    def __init__(self, cell: Cell) -> None:
        self._cell = cell
        self._camera: Camera | None = None
        self._checker: tuple[Layout, PlacementChecker] | None = None
        self._lock = asyncio.Lock()
        self.last: PlacementReport | None = None
        """The newest placement check (its annotated image in ``.image``)."""

    @property
    def configured(self) -> bool:
        """Whether a camera is configured (``vision.camera.source`` is not null)."""
        return self._cell.config.vision.camera.source is not None

    def checker(self) -> PlacementChecker:
        """The check for the layout as taught now (re-made when a frame is re-taught)."""
        layout = self._cell.layout
        if self._checker is None or self._checker[0] is not layout:
            self._checker = (layout, PlacementChecker(self._cell.config.vision, layout))
        return self._checker[1]

    async def capture(self) -> np.ndarray:
        """A fresh frame (BGR); :class:`~fxcell.errors.CameraError` when none comes."""
        if self._camera is None:
            self._camera = open_camera(self._cell.config.vision.camera, self._cell.host)
        return await self._camera.capture()

    async def check(self, expected: Collection[str] | None = None) -> PlacementReport:
        """Take a frame and judge every position of ``vision.station``: ``expected`` are the
        slots that must hold a seated crucible (the rest must be empty); ``None``: each must
        be seated or empty. Recorded and kept as :attr:`last`."""
        async with self._lock:
            checker = self.checker()
            if expected is not None:
                for slot in expected:  # a bad name raises SlotError before the camera is used
                    checker.deck.station.index(slot)
                expected = set(expected)
            frame = await self.capture()
            try:
                report = await asyncio.to_thread(checker.check, frame, expected)
            except cv2.error as exc:  # a frame OpenCV cannot work on (size, type)
                raise CameraError(f"the frame could not be judged: {exc.msg}") from None
            self.last = report
            self._cell.bus.publish(PlacementEvent(time.time(), report.image, report.as_dict()))
            return report

    async def close(self) -> None:
        camera, self._camera = self._camera, None
        if camera is not None:
            await camera.close()
