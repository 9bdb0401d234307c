"""``cell.camera``: the cell's camera and the placement check of the fusion machine's positions.

The camera (``vision.camera`` in the configuration: an OpenCV capture, a snapshot URL or the
simulator's rendered camera) is opened on first use. :meth:`CellCamera.check` takes a frame,
judges it off the event loop (:class:`fxcell.vision.placement.PlacementChecker`), keeps the
result as :attr:`CellCamera.last` and publishes it (image and verdict) on the event bus, so
the recorder writes it to MCAP and the daemon's page shows it.

OpenCV is a large library (its import maps tens of megabytes and takes seconds on a busy
machine): :mod:`fxcell.vision` is imported on first use, in a worker thread, never on the
event loop (the daemon imports the Cell on its loop while it serves).
"""

from __future__ import annotations

import asyncio
import importlib
import time
from collections.abc import Collection
from typing import TYPE_CHECKING

from fxcell.errors import CameraError
from fxcell.events import PlacementEvent
from fxcell.layout import Layout

if TYPE_CHECKING:
    import numpy as np

    from fxcell.cell.cell import Cell
    from fxcell.vision.camera import Camera
    from fxcell.vision.placement import PlacementChecker, PlacementReport

_VISION = ("cv2", "fxcell.vision.camera", "fxcell.vision.placement")


def _import_vision() -> None:
    for name in _VISION:
        importlib.import_module(name)


class CellCamera:
    """The camera of a :class:`~fxcell.cell.Cell` (``cell.camera``)."""

    def __init__(self, cell: Cell) -> None:
        self._cell = cell
        self._camera: Camera | None = None
        self._checker: tuple[Layout, PlacementChecker] | None = None
        self._lock = asyncio.Lock()
        self._imported = False
        self.last: PlacementReport | None = None
        """The newest placement check (its annotated image in ``.image``)."""

    @property
    def configured(self) -> bool:
        """Whether a camera is configured (``vision.camera.source`` is not null)."""
        return self._cell.config.vision.camera.source is not None

    async def _ready(self) -> None:
        """OpenCV and the vision modules imported (in a worker thread, once)."""
        if not self._imported:
            await asyncio.to_thread(_import_vision)
            self._imported = True

    def checker(self) -> PlacementChecker:
        """The check for the layout as taught now (re-made when a frame is re-taught)."""
        from fxcell.vision.placement import PlacementChecker

        layout = self._cell.layout
        if self._checker is None or self._checker[0] is not layout:
            self._checker = (layout, PlacementChecker(self._cell.config.vision, layout))
        return self._checker[1]

    async def capture(self) -> np.ndarray:
        """A fresh frame (BGR); :class:`~fxcell.errors.CameraError` when none comes."""
        await self._ready()
        from fxcell.vision.camera import open_camera

        if self._camera is None:
            self._camera = open_camera(self._cell.config.vision.camera, self._cell.host)
        return await self._camera.capture()

    async def check(self, expected: Collection[str] | None = None) -> PlacementReport:
        """Take a frame and judge every position of ``vision.station``: ``expected`` are the
        slots that must hold a seated crucible (the rest must be empty); ``None``: each must
        be seated or empty. Recorded and kept as :attr:`last`."""
        async with self._lock:
            await self._ready()
            import cv2

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
