"""The simulated camera: renders what a camera sees of the fusion machine's crucible holder.

A small painter's renderer on OpenCV primitives, enough to make the placement check work for
its living: the holder plate (dark anodised aluminium with a pocket per position and four
ArUco markers on white labels, warped in as one planar texture), the machine's deck around
it, and the objects standing on it as solids (tapered platinum crucibles with a bright rim
and white flux inside, bead carrier rings, boxes, flat lumps) drawn far to near. Imaging
conditions vary per frame: exposure (gain), an illumination gradient, sensor noise, defocus
blur, JPEG compression and small shifts of the camera.

Coordinates are those of :mod:`fxcell.vision.model` (the station frame, metres). The
simulator process serves these frames over HTTP (:mod:`fxcell.sim.server`); tests and
benches call :func:`render` directly (``fxcell.testing.vision``).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import math
import os
import random
from collections.abc import Awaitable, Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from fxcell.config import CameraConfig
from fxcell.geometry import Pose
from fxcell.link.realtime import LINK_PRIORITY, name_thread
from fxcell.vision.model import Deck, FloatArray, Intrinsics, camera_pose, plane_homography

log = logging.getLogger(__name__)

RENDER_PRIORITY = LINK_PRIORITY - 10
"""The renderer thread's SCHED_FIFO priority in a real-time simulator: below the robot link's
(and the link client's beat thread's), above every normal process. A frame takes ~150 ms
of a CPU; at the control cycle's priority, two simulators rendering at once held both
CPUs above the links of the cells beside them, and those links fell silent."""

RENDER_THREAD = "sim-camera"
"""The renderer thread's name as the system shows it (``/proc/PID/task/TID/comm``)."""


def _render_thread_setup() -> None:
    """The renderer thread's start: named, and in a real-time simulator moved below the
    robot link's priority (see :data:`RENDER_PRIORITY`); otherwise as it was started."""
    name_thread(RENDER_THREAD)
    with contextlib.suppress(OSError, AttributeError):
        realtime = os.sched_getscheduler(0) == os.SCHED_FIFO
        if realtime and os.sched_getparam(0).sched_priority > RENDER_PRIORITY:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RENDER_PRIORITY))


TEXTURE_SCALE = 0.00025  # m per texture pixel of the holder plate
PLATE_BGR = (58.0, 60.0, 62.0)
POCKET_BGR = (40.0, 41.0, 42.0)
CHAMFER_BGR = (74.0, 76.0, 78.0)
DECK_BGR = (150.0, 152.0, 150.0)
RIM_BGR = (228.0, 228.0, 232.0)  # polished platinum lip
WALL_BGR = (120.0, 121.0, 126.0)  # the crucible's outer wall, lit from above at a grazing angle
FLUX_BGR = (206.0, 208.0, 210.0)  # lithium borate flux with the sample
GLASS_BGR = (120.0, 168.0, 130.0)  # a glass bead in its carrier ring
SEGMENTS = 72  # polygon vertices per circle


@dataclass(frozen=True)
class Thing:
    """A solid on the holder, in the station frame: ``crucible``, ``bead`` (a carrier ring),
    ``box`` or ``lump`` (a flat irregular blob: spilt flux, a glove's fingertip)."""

    kind: str
    position: tuple[float, float, float]
    """The centre of its bottom (m)."""
    width: float = 0.030
    """Diameter (crucible: at the rim; box: along its x)."""
    height: float = 0.035
    depth: float = 0.030
    """A box's size along its y."""
    tilt: float = 0.0
    """Angle of its axis from the vertical (rad)."""
    azimuth: float = 0.0
    """Direction (in the xy plane, rad from +x) its top leans to."""
    yaw: float = 0.0
    colour: tuple[float, float, float] = (60.0, 90.0, 200.0)
    seed: int = 0
    """Shapes a lump's outline."""


@dataclass(frozen=True)
class Imaging:
    """How one frame is taken: exposure, light, noise, blur, compression, camera shift."""

    gain: float = 1.0
    gradient: tuple[float, float] = (0.0, 0.0)
    """Relative brightness change across the image's width and height."""
    noise: float = 2.0
    """Sensor noise, standard deviation in grey levels."""
    blur: float = 0.0
    """Defocus, Gaussian sigma in pixels."""
    jpeg_quality: int | None = 92
    shift: tuple[float, float, float, float, float, float] = (0.0,) * 6
    """Camera displaced from its nominal pose: x, y, z (m), rotation vector (rad), camera frame."""
    seed: int = 0


@dataclass
class Renderer:
    """Renders frames of ``deck`` through ``intrinsics``; the plate texture is made once."""

    deck: Deck
    intrinsics: Intrinsics
    _texture: np.ndarray | None = field(default=None, repr=False)
    _origin: FloatArray | None = field(default=None, repr=False)

    def texture(self) -> tuple[np.ndarray, FloatArray]:
        """The holder plate's top as a metric image and the station (x, y) of its pixel (0, 0)."""
        if self._texture is None:
            self._texture, self._origin = _plate_texture(self.deck)
        assert self._origin is not None
        return self._texture, self._origin

    def render(
        self, camera_in_station: Pose, things: Iterable[Thing], imaging: Imaging | None = None
    ) -> np.ndarray:
        """The BGR frame (uint8) the camera at ``camera_in_station`` takes of ``things``."""
        intr = self.intrinsics
        imaging = imaging or Imaging()
        if any(imaging.shift):
            shift = Pose.from_rotvec(imaging.shift[:3], imaging.shift[3:])
            camera_in_station = camera_in_station @ shift
        station_in_cam = camera_in_station.inverse()
        img = np.empty((intr.height, intr.width, 3), np.float32)
        img[:] = DECK_BGR
        texture, origin = self.texture()
        H = plane_homography(intr.matrix, station_in_cam, 0.0, origin, TEXTURE_SCALE)
        cv2.warpPerspective(
            texture,
            H,
            (intr.width, intr.height),
            dst=img,
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_TRANSPARENT,
        )
        rvec, _ = cv2.Rodrigues(station_in_cam.rotation)
        tvec = station_in_cam.position.reshape(3, 1)
        cam = camera_in_station.position

        def project(points: FloatArray) -> np.ndarray:
            uv, _ = cv2.projectPoints(
                points.reshape(-1, 1, 3), rvec, tvec, intr.matrix, intr.distortion
            )
            return np.asarray(uv).reshape(-1, 2)

        order = sorted(things, key=lambda t: -float(np.linalg.norm(np.asarray(t.position) - cam)))
        for thing in order:
            _draw(img, thing, project)
        return _expose(img, imaging)


def _fill(img: np.ndarray, points: np.ndarray, colour: Sequence[float]) -> None:
    pts = np.round(points * 16).astype(np.int32).reshape(-1, 1, 2)
    cv2.fillPoly(img, [pts], tuple(float(c) for c in colour), cv2.LINE_AA, shift=4)


def _hull(points: np.ndarray) -> np.ndarray:
    return np.asarray(cv2.convexHull(points.astype(np.float32))).reshape(-1, 2)


def _axes(thing: Thing) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The thing's own x, y and z (up) axes in the station frame."""
    tilt = Pose.from_rotvec(
        (0, 0, 0),
        np.array([-math.sin(thing.azimuth), math.cos(thing.azimuth), 0.0]) * thing.tilt,
    )
    yaw = Pose.from_rotvec((0, 0, 0), (0.0, 0.0, thing.yaw))
    R = (tilt @ yaw).rotation
    return R[:, 0], R[:, 1], R[:, 2]


def _circle(centre: FloatArray, x: FloatArray, y: FloatArray, r: float) -> FloatArray:
    phi = np.linspace(0, 2 * math.pi, SEGMENTS, endpoint=False)
    return centre + r * (np.cos(phi)[:, None] * x + np.sin(phi)[:, None] * y)


def _draw(img: np.ndarray, thing: Thing, project: object) -> None:
    proj = project  # Callable[[FloatArray], ndarray]
    assert callable(proj)
    x, y, z = _axes(thing)
    base = np.asarray(thing.position, dtype=np.float64)
    top = base + z * thing.height
    if thing.kind in ("crucible", "bead"):
        r_top = thing.width / 2
        r_bottom = r_top * (0.78 if thing.kind == "crucible" else 1.0)
        bottom_pts = proj(_circle(base, x, y, r_bottom))
        top_pts = proj(_circle(top, x, y, r_top))
        _fill(img, _hull(np.vstack([bottom_pts, top_pts])), WALL_BGR)
        lip = 0.0015 if thing.kind == "crucible" else 0.004
        inside = FLUX_BGR if thing.kind == "crucible" else GLASS_BGR
        _fill(img, top_pts, RIM_BGR if thing.kind == "crucible" else (196.0, 198.0, 200.0))
        _fill(img, proj(_circle(top, x, y, r_top - lip)), inside)
        return
    if thing.kind == "box":
        w, d = thing.width / 2, thing.depth / 2
        corners = [
            base + sx * w * x + sy * d * y for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))
        ]
        bottom = np.array(corners)
        upper = bottom + z * thing.height
        _fill(img, _hull(np.vstack([proj(bottom), proj(upper)])), [c * 0.6 for c in thing.colour])
        _fill(img, proj(upper), thing.colour)
        return
    if thing.kind == "lump":
        rng = np.random.default_rng(thing.seed)
        phi = np.linspace(0, 2 * math.pi, 24, endpoint=False)
        radii = thing.width / 2 * rng.uniform(0.55, 1.0, phi.size)
        radii = np.convolve(np.concatenate([radii[-2:], radii, radii[:2]]), np.ones(5) / 5, "valid")
        outline = top + (radii * np.cos(phi))[:, None] * x + (radii * np.sin(phi))[:, None] * y
        _fill(img, proj(outline), thing.colour)
        return
    raise ValueError(f"cannot render a {thing.kind!r}")


def _expose(img: np.ndarray, imaging: Imaging) -> np.ndarray:
    h, w = img.shape[:2]
    gx, gy = imaging.gradient
    if gx or gy:
        ramp = (
            1.0
            + gx * (np.arange(w, dtype=np.float32)[None, :] / w - 0.5)
            + gy * (np.arange(h, dtype=np.float32)[:, None] / h - 0.5)
        )
        img *= (ramp * imaging.gain)[:, :, None]
    else:
        img *= imaging.gain
    if imaging.blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), imaging.blur)
    if imaging.noise > 0:
        rng = np.random.default_rng(imaging.seed)
        img += rng.standard_normal(img.shape[:2], dtype=np.float32)[:, :, None] * imaging.noise
    out: np.ndarray = np.clip(img, 0, 255).astype(np.uint8)
    if imaging.jpeg_quality is not None:
        ok, data = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, imaging.jpeg_quality])
        assert ok
        out = np.asarray(cv2.imdecode(data, cv2.IMREAD_COLOR))
    return out


def _plate_texture(deck: Deck) -> tuple[np.ndarray, FloatArray]:
    """The plate's top face, ``TEXTURE_SCALE`` m per pixel, x right and y up."""
    x0, y0, x1, y1 = deck.holder
    s = TEXTURE_SCALE
    w, h = round((x1 - x0) / s), round((y1 - y0) / s)
    tex = np.empty((h, w, 3), np.float32)
    tex[:] = PLATE_BGR

    def px(x: float, y: float) -> tuple[float, float]:
        return (x - x0) / s, (y1 - y) / s

    for seat in deck.positions.values():
        u, v = px(float(seat[0]), float(seat[1]))
        centre = (round(u * 16), round(v * 16))
        r = deck.radius
        cv2.circle(tex, centre, round((r + 0.002) / s * 16), CHAMFER_BGR, -1, cv2.LINE_AA, 4)
        cv2.circle(tex, centre, round((r + 0.0012) / s * 16), PLATE_BGR, -1, cv2.LINE_AA, 4)
        cv2.circle(tex, centre, round(r * 0.8 / s * 16), POCKET_BGR, -1, cv2.LINE_AA, 4)
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, deck.dictionary))
    for marker_id, corners in deck.markers.items():
        side = round(deck.marker_size / s)
        label = round(side * 1.4)
        cx, cy = corners[:, :2].mean(axis=0)
        u, v = px(float(cx), float(cy))
        u0, v0 = round(u - label / 2), round(v - label / 2)
        tex[v0 : v0 + label, u0 : u0 + label] = (236.0, 238.0, 238.0)
        marker = cv2.aruco.generateImageMarker(dictionary, marker_id, side)
        m0u, m0v = round(u - side / 2), round(v - side / 2)
        mbgr = np.repeat(marker[:, :, None], 3, axis=2).astype(np.float32) * (226 / 255) + 12
        tex[m0v : m0v + side, m0u : m0u + side] = mbgr
    return tex, np.array([x0, y1])


# ---------------------------------------------------------------- the simulator's camera


def world_things(
    objects: Iterable[SimObjectLike], deck: Deck, grip_heights: dict[str, float]
) -> list[Thing]:
    """The simulator's objects (grip-point poses in the base frame) as solids in the station
    frame. Crucibles and beads are drawn as such; anything else as a box of its size."""
    to_station = deck.station.frame.inverse()
    out = []
    for obj in objects:
        pose = to_station @ obj.pose
        # a layout grip pose points down the object's axis; add_object's pose is upright
        z = pose.rotation[:, 2]
        up = -z if z[2] < 0 else z
        grip = grip_heights.get(obj.kind, obj.height / 2)
        bottom = pose.position - up * grip
        if np.linalg.norm(bottom[:2] - deck.station.frame.inverse().position[:2]) > 1.0:
            continue  # far from the holder: out of view
        tilt = math.acos(max(-1.0, min(1.0, float(up[2]))))
        azimuth = math.atan2(float(up[1]), float(up[0])) if tilt > 1e-6 else 0.0
        position = (float(bottom[0]), float(bottom[1]), float(bottom[2]))
        if obj.kind in ("crucible", "bead"):
            out.append(Thing(obj.kind, position, obj.width, obj.height, tilt=tilt, azimuth=azimuth))
        else:
            out.append(
                Thing("box", position, obj.width, obj.height, obj.width, tilt=tilt, azimuth=azimuth)
            )
    return out


class SimObjectLike(Protocol):
    kind: str
    width: float
    height: float
    pose: Pose


class CameraConnection(asyncio.Protocol):
    """``GET /snapshot.jpg`` over HTTP/1.1: one rendered JPEG per request, as the still-image
    URL of a network camera; anything else is 404. Rendering runs in a worker thread so the
    controller's cycle keeps its time."""

    def __init__(self, snapshot: Callable[[], Awaitable[bytes]]) -> None:
        self.snapshot = snapshot
        self.transport: asyncio.Transport | None = None
        self.buffer = b""
        self.task: asyncio.Task[None] | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        if len(self.buffer) > 16384:
            self._answer(431, b"request too large", "text/plain", close=True)
            return
        if b"\r\n\r\n" not in self.buffer or self.task is not None:
            return
        head, self.buffer = self.buffer.split(b"\r\n\r\n", 1)
        request = head.split(b"\r\n", 1)[0].decode("latin-1").split()
        if len(request) < 2 or request[0] not in ("GET", "HEAD"):
            self._answer(405, b"only GET", "text/plain", close=True)  # its body is not read
            return
        if request[1].split("?", 1)[0] != SNAPSHOT_PATH:
            self._answer(404, b"the camera is at " + SNAPSHOT_PATH.encode(), "text/plain")
            return
        self.task = asyncio.get_running_loop().create_task(self._serve(request[0] == "HEAD"))

    async def _serve(self, head_only: bool) -> None:
        try:
            data = await self.snapshot()
        except Exception as exc:  # a rendering bug must not take the controller down
            log.exception("camera: rendering failed")
            self._answer(500, str(exc).encode(), "text/plain")
        else:
            self._answer(200, b"" if head_only else data, "image/jpeg", length=len(data))
        finally:
            self.task = None

    def _answer(
        self, status: int, body: bytes, kind: str, *, length: int | None = None, close: bool = False
    ) -> None:
        if self.transport is None:
            return
        reason = {200: "OK", 404: "Not Found", 405: "Method Not Allowed", 431: "Too Large"}
        size = length if length is not None else len(body)
        connection = "close" if close else "keep-alive"
        head = (
            f"HTTP/1.1 {status} {reason.get(status, 'Error')}\r\n"
            f"Content-Type: {kind}\r\nContent-Length: {size}\r\n"
            f"Cache-Control: no-store\r\nConnection: {connection}\r\n\r\n"
        )
        self.transport.write(head.encode() + body)
        if close:
            self.transport.close()


SNAPSHOT_PATH = "/snapshot.jpg"


class SimCamera:
    """The cell's configured camera in the simulated world: renders the simulator's objects
    with mild, varying imaging conditions (each frame a little different, as a real one)."""

    def __init__(
        self,
        renderer: Renderer,
        camera: CameraConfig,
        objects: Callable[[], list[SimObjectLike]],
        grip_heights: dict[str, float],
        flange: Callable[[], Pose],
    ) -> None:
        self.renderer = renderer
        self.camera = camera
        self.objects = objects
        self.grip_heights = grip_heights
        self.flange = flange
        self.frames = 0
        # The renderer stays real time where the simulator is: a worker at normal priority
        # would be descheduled on a busy machine while it holds the GIL, and the control
        # cycle waiting for the GIL would stall behind it (and the snapshot would take
        # seconds). But it runs below the robot links (RENDER_PRIORITY): a real camera
        # takes no CPU from the cell computer.
        self._executor = concurrent.futures.ThreadPoolExecutor(
            1, "fxcell-sim-camera", initializer=_render_thread_setup
        )
        # OpenCV's own workers inherit that scheduling too: with one per core, a frame's
        # parallel regions would take every CPU from the control cycle (a real-time thread
        # waits behind running ones of its priority). One thread renders a frame in time.
        # Process-wide, and only the camera uses OpenCV in the simulator.
        cv2.setNumThreads(1)

    async def snapshot(self) -> bytes:
        """Take a frame (the world as it is now), rendered in the worker thread."""
        deck = self.renderer.deck
        flange = self.flange() if self.camera.mount == "flange" else None
        camera_in_station = deck.station.frame.inverse() @ camera_pose(self.camera, flange)
        things = world_things(self.objects(), deck, self.grip_heights)
        self.frames += 1
        rng = random.Random(self.frames)
        imaging = Imaging(
            gain=rng.uniform(0.9, 1.1),
            gradient=(rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)),
            noise=rng.uniform(1.5, 3.0),
            blur=rng.uniform(0.0, 0.6),
            jpeg_quality=None,
            # a mount that is not perfectly rigid: a millimetre, a tenth of a degree
            shift=(
                rng.gauss(0, 0.001),
                rng.gauss(0, 0.001),
                rng.gauss(0, 0.001),
                rng.gauss(0, 0.002),
                rng.gauss(0, 0.002),
                rng.gauss(0, 0.002),
            ),
            seed=self.frames,
        )
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(
            self._executor, self._encode, camera_in_station, things, imaging
        )

    def _encode(self, camera_in_station: Pose, things: list[Thing], imaging: Imaging) -> bytes:
        frame = self.renderer.render(camera_in_station, things, imaging)
        ok, data = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, 92])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        return bytes(data)

    def close(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)
