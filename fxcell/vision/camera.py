"""Where frames come from: a camera behind OpenCV's capture, a network camera's snapshot URL,
or the simulator's rendered camera (which serves snapshots as a network camera does).

Every backend is opened and read off the event loop (a thread of its own for an OpenCV
capture; an async HTTP request for snapshots), so a slow or dead camera never blocks the
cell. :func:`open_camera` picks the backend from ``vision.camera.source``.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from typing import Protocol

import cv2
import httpx
import numpy as np

from fxcell.config import SIMULATOR_CAMERA_PORT, CameraConfig
from fxcell.errors import CameraError, CameraNotConfiguredError

SNAPSHOT_PATH = "/snapshot.jpg"
"""Where the simulator serves its camera (``http://<controller address>:<port>/snapshot.jpg``)."""


class Camera(Protocol):
    """A source of frames (BGR, uint8)."""

    @property
    def description(self) -> str:
        """Where the frames come from, for messages."""
        ...

    async def capture(self) -> np.ndarray:
        """A frame taken after the call (never an old buffered one); :class:`CameraError`
        when none comes within the configured timeout."""
        ...

    async def close(self) -> None: ...


def decode_jpeg(data: bytes, where: str) -> np.ndarray:
    frame = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if frame is None:
        raise CameraError(f"{where}: the answer is not an image ({len(data)} bytes)")
    return np.asarray(frame)


class SnapshotCamera:
    """A network camera's still-image URL: one JPEG per HTTP GET."""

    def __init__(self, url: str, timeout: float = 5.0) -> None:
        self.url = url
        self.timeout = timeout
        self._client: httpx.AsyncClient | None = None

    @property
    def description(self) -> str:
        return f"snapshot camera {self.url}"

    async def capture(self) -> np.ndarray:
        if self._client is None:
            self._client = httpx.AsyncClient(timeout=self.timeout)
        try:
            answer = await self._client.get(self.url)
        except httpx.HTTPError as exc:
            raise CameraError(f"{self.description}: {str(exc) or type(exc).__name__}") from None
        if answer.status_code != 200:
            raise CameraError(f"{self.description}: HTTP {answer.status_code}")
        return await asyncio.to_thread(decode_jpeg, answer.content, self.description)

    async def close(self) -> None:
        if self._client is not None:
            client, self._client = self._client, None
            await client.aclose()


class OpenCVCamera:
    """A USB/V4L2 camera (an index) or a stream URL, read by ``cv2.VideoCapture`` in a thread.

    The thread opens the capture (which can take seconds, or hang on a dead stream) and reads
    frames continuously, so the newest frame is always the one returned and a capture's
    internal buffer never hands out a stale one.
    """

    def __init__(self, source: int | str, width: int, height: int, timeout: float = 5.0) -> None:
        self.source = source
        self.width = width
        self.height = height
        self.timeout = timeout
        self._lock = threading.Lock()
        self._waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[np.ndarray]]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: str | None = None

    @property
    def description(self) -> str:
        return f"camera {self.source!r}"

    def _run(self) -> None:
        cap = cv2.VideoCapture(self.source)
        try:
            if not cap.isOpened():
                self._fail("cannot be opened")
                return
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
            while not self._stop.is_set():
                ok, frame = cap.read()
                if not ok:
                    self._fail("stopped delivering frames")
                    return
                self._error = None
                with self._lock:
                    waiters, self._waiters = self._waiters, []
                for loop, fut in waiters:
                    with contextlib.suppress(RuntimeError):  # its loop has closed
                        loop.call_soon_threadsafe(_resolve, fut, frame)
        finally:
            cap.release()

    def _fail(self, why: str) -> None:
        self._error = why
        with self._lock:
            waiters, self._waiters = self._waiters, []
        for loop, fut in waiters:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(_reject, fut, CameraError(f"{self.description}: {why}"))

    async def capture(self) -> np.ndarray:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[np.ndarray] = loop.create_future()
        with self._lock:
            self._waiters.append((loop, fut))
        if self._thread is None or not self._thread.is_alive():
            # (re)open: a camera unplugged and plugged back in is found again
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="fxcell-camera", daemon=True)
            self._thread.start()
        try:
            async with asyncio.timeout(self.timeout):
                frame = await fut
        except TimeoutError:
            why = self._error or f"no frame within {self.timeout:g} s"
            raise CameraError(f"{self.description}: {why}") from None
        finally:
            with self._lock:
                self._waiters = [w for w in self._waiters if w[1] is not fut]
        if frame.shape[1] != self.width or frame.shape[0] != self.height:
            raise CameraError(
                f"{self.description}: frames are {frame.shape[1]}x{frame.shape[0]}, the "
                f"calibration is for {self.width}x{self.height}"
            )
        return frame

    async def close(self) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            # a capture blocked in read() ends within its own timeout; don't wait for ever
            await asyncio.to_thread(thread.join, 2.0)


def _resolve(fut: asyncio.Future[np.ndarray], frame: np.ndarray) -> None:
    if not fut.done():
        fut.set_result(frame)


def _reject(fut: asyncio.Future[np.ndarray], exc: BaseException) -> None:
    if not fut.done():
        fut.set_exception(exc)


def open_camera(camera: CameraConfig, controller_host: str | None) -> Camera:
    """The backend ``camera.source`` names (``simulator``: the simulator at
    ``controller_host``); :class:`CameraNotConfiguredError` when it is null."""
    source = camera.source
    if source is None:
        raise CameraNotConfiguredError(
            "no camera is configured (vision.camera.source in the cell configuration; "
            "see docs/guides/vision.md)"
        )
    if source == "simulator":
        if controller_host is None:
            raise CameraError("the simulator's camera needs the simulator running (open the cell)")
        url = f"http://{controller_host}:{SIMULATOR_CAMERA_PORT}{SNAPSHOT_PATH}"
        return SnapshotCamera(url, camera.timeout)
    if isinstance(source, str) and source.startswith("snapshot:"):
        return SnapshotCamera(source.removeprefix("snapshot:"), camera.timeout)
    if isinstance(source, str) and source.isdigit():
        source = int(source)
    return OpenCVCamera(source, camera.width, camera.height, camera.timeout)


__all__ = ["Camera", "OpenCVCamera", "SnapshotCamera", "decode_jpeg", "open_camera"]
