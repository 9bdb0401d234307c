"""The placement check: is every crucible seated in its position of the fusion machine?

Classical computer vision on one camera frame (OpenCV):

1. **Holder**: the ArUco markers on the holder plate give its pose in the camera frame
   (``solvePnP`` on every detected marker corner; at least two markers, reprojection error
   checked), so the check needs the camera's intrinsics but not where the camera is.
2. **Plate**: the plate's top is rectified to a metric image (0.5 mm per pixel); its grey level
   (the median away from positions and markers) is the background. Anything that differs
   from it in brightness or colour outside the positions is an *obstruction* (something left
   in the gripper's path).
3. **Positions**: each position is rectified at rim height (0.2 mm per pixel), where a seated
   crucible's rim is a circle of its width around the position's centre. The brightest part
   of what stands there (the polished rim and the flux inside) is segmented and an ellipse
   fitted to its outline. Verdicts: ``empty`` (too little foreground), ``foreign`` (colourful,
   boxy, irregular, dark, or not the crucible's width), ``tilted`` (minor/major axis ratio
   low), ``offset`` (centre farther from the position than the tolerance), else ``seated``,
   each with a confidence (how far the deciding measure is from its threshold, 0.5-1) and the
   measured offset in millimetres.

Thresholds come from the configuration (``vision.thresholds``), chosen from the measured
distributions of ``bench/placement.py``.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Collection
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Final, Literal

import cv2
import numpy as np

from fxcell.config import PlacementThresholds, VisionConfig
from fxcell.errors import InvalidArgumentError
from fxcell.geometry import Pose
from fxcell.layout import Layout
from fxcell.vision.model import Deck, FloatArray, Intrinsics, plane_homography

Verdict = Literal["empty", "seated", "offset", "tilted", "foreign"]
VERDICTS: Final = ("empty", "seated", "offset", "tilted", "foreign")
PLATE_SCALE: Final = 0.0005  # m per pixel of the rectified plate
PATCH_SCALE: Final = 0.0002  # m per pixel of a rectified position
PATCH_HALF: Final = 0.032  # m: half the side of a position's window
EXCLUSION: Final = 0.011  # m beyond an object's radius that belongs to its position
MAX_REPROJECTION: Final = 3.0  # px: markers farther from the fitted holder are inconsistent
CHROMA: Final = 22.0  # Lab chroma above which a pixel is colourful (not metal, not plate)


@dataclass(frozen=True)
class PositionCheck:
    """The verdict on one position, with what was measured."""

    slot: str
    verdict: Verdict
    confidence: float
    offset_mm: float | None = None
    """Distance of the rim's centre from the position's centre (mm)."""
    offset_xy_mm: tuple[float, float] | None = None
    """The same along the station's x and y (mm)."""
    diameter_mm: float | None = None
    """The rim's minor axis (mm)."""
    axis_ratio: float | None = None
    """The rim's minor/major axis ratio (1: flat)."""
    coverage: float = 0.0
    """Fraction of a crucible's disc covered by something."""
    expected: bool | None = None
    """Whether a crucible belongs here (``None``: no expectation given)."""
    ok: bool = True
    note: str = ""
    pixel: tuple[float, float] | None = None
    """Where the position's rim centre is in the image (px; for annotations)."""
    pixel_radius: float | None = None
    """A crucible rim's radius there (px)."""


@dataclass(frozen=True)
class Obstruction:
    """Something on the holder outside the positions."""

    x_mm: float
    y_mm: float
    """Its centre in the station frame (mm)."""
    area_mm2: float


@dataclass
class PlacementReport:
    """The outcome of one check: per position verdicts, obstructions, the annotated image."""

    ok: bool
    reason: str
    positions: tuple[PositionCheck, ...] = ()
    obstructions: tuple[Obstruction, ...] = ()
    holder_found: bool = False
    markers: int = 0
    reprojection_px: float | None = None
    time: float = field(default_factory=time.time)
    duration: float = 0.0
    """Seconds the analysis took (not the capture)."""
    image: bytes = b""
    """The annotated frame, JPEG."""

    def position(self, slot: str) -> PositionCheck:
        return next(p for p in self.positions if p.slot == slot)

    def verdicts(self) -> dict[str, str]:
        """Slot → verdict."""
        return {p.slot: p.verdict for p in self.positions}

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready, without the image."""
        out = asdict(self)
        out.pop("image")
        return out


class PlacementChecker:
    """Judges frames of the holder of ``vision.station`` (one per configuration and layout)."""

    def __init__(self, vision: VisionConfig, layout: Layout) -> None:
        self.config = vision
        self.deck = Deck.from_config(vision, layout)
        self.intrinsics = Intrinsics.from_config(vision.camera)
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, vision.dictionary))
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._detector = cv2.aruco.ArucoDetector(dictionary, params)
        self._undistort: tuple[np.ndarray, np.ndarray] | None = None
        if np.any(self.intrinsics.distortion):
            i = self.intrinsics
            self._undistort = cv2.initUndistortRectifyMap(
                i.matrix, i.distortion, None, i.matrix, (i.width, i.height), cv2.CV_16SC2
            )

    @functools.cached_property
    def _plate_mask(self) -> np.ndarray:
        """The plate's pixels (rectified at ``PLATE_SCALE``) away from positions and markers."""
        x0, y0, x1, y1 = self.deck.holder
        s = PLATE_SCALE
        w, h = round((x1 - x0) / s), round((y1 - y0) / s)
        X, Y = np.meshgrid(x0 + s * np.arange(w), y1 - s * np.arange(h))
        margin = 0.003
        mask = (x0 + margin < X) & (x1 - margin > X) & (y0 + margin < Y) & (y1 - margin > Y)
        for seat in self.deck.positions.values():
            mask &= np.hypot(X - seat[0], Y - seat[1]) > self.deck.radius + EXCLUSION
        half = self.deck.marker_size * 0.7 + 0.003
        for corners in self.deck.markers.values():
            cx, cy = corners[:, :2].mean(axis=0)
            mask &= (np.abs(X - cx) > half) | (np.abs(Y - cy) > half)
        out: np.ndarray = mask
        return out

    @functools.cached_property
    def _patch_radius(self) -> np.ndarray:
        """Distance (m) of each pixel of a rectified position from the position's centre."""
        n = round(2 * PATCH_HALF / PATCH_SCALE)
        yy, xx = np.mgrid[0:n, 0:n]
        c = PATCH_HALF / PATCH_SCALE
        r: np.ndarray = np.hypot(xx - c, yy - c) * PATCH_SCALE
        return r

    @property
    def thresholds(self) -> PlacementThresholds:
        return self.config.thresholds

    # ------------------------------------------------------------- the check

    def check(self, frame: np.ndarray, expected: Collection[str] | None = None) -> PlacementReport:
        """Judge ``frame`` (BGR); ``expected``: the slots that must hold a seated crucible
        (the others must be empty); ``None``: each position must be seated or empty."""
        started = time.perf_counter()
        if expected is not None:
            unknown = set(expected) - set(self.deck.positions)
            if unknown:
                names = ", ".join(sorted(unknown))
                raise InvalidArgumentError(
                    f"station {self.deck.station.name!r} has no position {names}"
                )
        i = self.intrinsics
        if frame.ndim != 3 or frame.shape[:2] != (i.height, i.width):
            raise InvalidArgumentError(
                f"the frame is {'x'.join(str(n) for n in frame.shape[1::-1])} pixels; the "
                f"camera's calibration (vision.camera) is for {i.width}x{i.height} colour frames"
            )
        if self._undistort is not None:
            frame = cv2.remap(frame, *self._undistort, cv2.INTER_LINEAR)
        report, pose = self._analyse(frame, expected)
        report.duration = time.perf_counter() - started
        report.image = annotate(frame, report, self, pose)
        return report

    def locate_holder(self, gray: np.ndarray) -> tuple[Pose | None, int, float | None]:
        """The station frame in the camera frame from the markers, their count, the RMS
        reprojection error (px)."""
        corners, found_ids, _ = self._detector.detectMarkers(gray)
        ids: np.ndarray | None = found_ids  # None when no marker is seen (the stub says not)
        if ids is None:
            return None, 0, None
        obj, img = [], []
        for c, marker_id in zip(corners, ids.ravel(), strict=True):
            model = self.deck.markers.get(int(marker_id))
            if model is not None:
                obj.append(model)
                img.append(np.asarray(c, dtype=np.float64).reshape(4, 2))
        if len(obj) < 2:
            return None, len(obj), None
        object_points = np.vstack(obj)
        image_points = np.vstack(img)
        K = self.intrinsics.matrix
        zero = np.zeros(4)
        ok, rvec, tvec = cv2.solvePnP(object_points, image_points, K, zero, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            return None, len(obj), None
        rvec, tvec = cv2.solvePnPRefineLM(object_points, image_points, K, zero, rvec, tvec)
        projected, _ = cv2.projectPoints(object_points, rvec, tvec, K, zero)
        error = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - image_points) ** 2, 1))))
        R, _ = cv2.Rodrigues(rvec)
        pose = Pose(np.asarray(tvec, dtype=np.float64).ravel(), R)
        if error > MAX_REPROJECTION:
            return None, len(obj), error
        return pose, len(obj), error

    def _analyse(
        self, frame: np.ndarray, expected: Collection[str] | None
    ) -> tuple[PlacementReport, Pose | None]:
        """The report and the holder's pose in the camera frame (``None``: not found)."""
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        pose, n, error = self.locate_holder(gray)
        if pose is None:
            why = (
                f"the holder's markers are inconsistent (reprojection {error:.1f} px)"
                if error is not None
                else f"the holder was not found: {n} of {len(self.deck.markers)} markers seen "
                "(at least 2 needed)"
            )
            return PlacementReport(False, why, markers=n, reprojection_px=error), None
        level, obstructions = self._plate(frame, pose)
        checks = []
        rvec, _ = cv2.Rodrigues(pose.rotation)
        tvec = pose.position.reshape(3, 1)
        for slot, seat in self.deck.positions.items():
            want = None if expected is None else slot in expected
            check = self._position(frame, pose, slot, seat, level, want)
            z = self.deck.rim_height
            ring = np.array([[seat[0], seat[1], z], [seat[0] + self.deck.radius, seat[1], z]])
            uv, _ = cv2.projectPoints(ring, rvec, tvec, self.intrinsics.matrix, np.zeros(4))
            uv = np.asarray(uv).reshape(2, 2)
            pixel = (round(float(uv[0, 0]), 1), round(float(uv[0, 1]), 1))
            radius = round(float(np.linalg.norm(uv[1] - uv[0])), 1)
            checks.append(replace(check, pixel=pixel, pixel_radius=radius))
        reasons = [f"{c.slot}: {c.note}" for c in checks if not c.ok]
        reasons += [
            f"something on the holder at x {o.x_mm:.0f} mm, y {o.y_mm:.0f} mm "
            f"({o.area_mm2:.0f} mm², in the gripper's path)"
            for o in obstructions
        ]
        ok = not reasons
        report = PlacementReport(
            ok,
            "every position as expected" if ok else "; ".join(reasons),
            tuple(checks),
            tuple(obstructions),
            True,
            n,
            error,
        )
        return report, pose

    def _warp(
        self, frame: np.ndarray, pose: Pose, height: float, origin: FloatArray, scale: float,
        size: tuple[int, int],
    ) -> np.ndarray:  # fmt: skip
        H = plane_homography(self.intrinsics.matrix, pose, height, origin, scale)
        return cv2.warpPerspective(
            frame, H, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )  # fmt: skip

    def _foreground(
        self, patch: np.ndarray, level: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Grey image, foreground mask (differs from the plate's level, or colourful) and the
        raw Lab chroma."""
        g = np.asarray(
            cv2.GaussianBlur(
                cv2.cvtColor(patch, cv2.COLOR_BGR2GRAY).astype(np.float32), (0, 0), 1.0
            )
        )
        lab = cv2.cvtColor(patch, cv2.COLOR_BGR2LAB).astype(np.float32)
        raw = np.hypot(lab[:, :, 1] - 128, lab[:, :, 2] - 128)
        chroma = cv2.GaussianBlur(raw, (0, 0), 1.5)
        fg = (np.abs(g - level) > max(14.0, 0.45 * level)) | (chroma > CHROMA)
        fg8 = cv2.morphologyEx(fg.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        return g, fg8, raw

    def _plate(self, frame: np.ndarray, pose: Pose) -> tuple[float, list[Obstruction]]:
        """The plate's grey level and what lies on it outside the positions."""
        x0, y0, x1, y1 = self.deck.holder
        s = PLATE_SCALE
        w, h = round((x1 - x0) / s), round((y1 - y0) / s)
        origin = np.array([x0, y1])
        plate = self._warp(frame, pose, 0.0, origin, s, (w, h))
        mask = self._plate_mask
        gray = cv2.cvtColor(plate, cv2.COLOR_BGR2GRAY)
        level = float(np.median(gray[mask]))
        _, fg, _ = self._foreground(plate, level)
        fg &= mask.astype(np.uint8)
        count, _, stats, centroids = cv2.connectedComponentsWithStats(fg)
        found = []
        for i in range(1, count):
            area = stats[i, cv2.CC_STAT_AREA] * s * s
            if area > self.thresholds.obstruction:
                cu, cv_ = centroids[i]
                found.append(
                    Obstruction(
                        round((x0 + s * cu) * 1000, 1), round((y1 - s * cv_) * 1000, 1),
                        round(area * 1e6, 1),
                    )
                )  # fmt: skip
        return level, found

    def _position(
        self, frame: np.ndarray, pose: Pose, slot: str, seat: FloatArray, level: float,
        expected: bool | None,
    ) -> PositionCheck:  # fmt: skip
        t = self.thresholds
        s = PATCH_SCALE
        n = round(2 * PATCH_HALF / s)
        origin = np.array([seat[0] - PATCH_HALF, seat[1] + PATCH_HALF])
        patch = self._warp(frame, pose, self.deck.rim_height, origin, s, (n, n))
        g, fg, raw_chroma = self._foreground(patch, level)
        c = PATCH_HALF / s  # the seat's pixel
        r = self._patch_radius
        disc = r <= self.deck.radius
        fg &= (r <= PATCH_HALF).astype(np.uint8)
        coverage = float(fg[disc].mean())
        if coverage < t.presence:
            return self._judge(
                slot, "empty", _confidence(t.presence - coverage, t.presence), expected,
                coverage=coverage,
            )  # fmt: skip
        _, labels, stats, _ = cv2.connectedComponentsWithStats(fg)
        # the object: the largest component touching the position's disc
        touching = np.unique(labels[disc & (fg > 0)])
        touching = touching[touching > 0]
        best = int(touching[np.argmax(stats[touching, cv2.CC_STAT_AREA])])
        obj = labels == best
        values = g[obj]
        top_level = float(np.percentile(values, 98))
        chroma = float(raw_chroma[obj].mean())
        note = ""
        if top_level < level * 2.0:
            note = "dark or dull (not a platinum rim)"
        top = (g > level + 0.78 * (top_level - level)) & obj
        top8 = cv2.morphologyEx(top.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
        contours, _ = cv2.findContours(top8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        contour = max(contours, key=cv2.contourArea) if contours else None
        if contour is None or len(contour) < 8:
            return self._judge(
                slot, "foreign", 0.6, expected, coverage=coverage, note="no rim found"
            )
        (eu, ev), (a1, a2), angle = cv2.fitEllipse(contour)
        major, minor = max(a1, a2) * s, min(a1, a2) * s
        dx = (eu - c) * s
        dy = -(ev - c) * s
        offset = math.hypot(dx, dy)
        ratio = minor / major if major > 0 else 0.0
        area = cv2.contourArea(contour)
        (_, _), (rw, rh), _ = cv2.minAreaRect(contour)
        rectangularity = area / max(rw * rh, 1e-9)
        residual = _ellipse_residual(contour.reshape(-1, 2), (eu, ev), (a1, a2), angle) * s
        width = self.deck.kind.width
        measured: dict[str, Any] = {
            "offset_mm": round(offset * 1000, 2),
            "offset_xy_mm": (round(dx * 1000, 2), round(dy * 1000, 2)),
            "diameter_mm": round(minor * 1000, 2),
            "axis_ratio": round(ratio, 4),
            "coverage": round(coverage, 3),
        }
        if not note and chroma > t.saturation / 2.55:
            note = f"coloured (chroma {chroma:.0f})"
        if not note and rectangularity > t.rectangularity:
            note = f"boxy (fills {rectangularity:.0%} of its rectangle)"
        # a tilted crucible: its rim an ellipse no wider than the crucible, its minor axis
        # shortened by perspective and by the part of the rim the wall hides
        leaning = (
            ratio < t.tilt_ratio and 0.8 * width < minor < width + t.diameter and residual < 0.0025
        )
        if not note and not leaning and residual > 0.0006:
            note = f"irregular outline ({residual * 1000:.1f} mm from an ellipse)"
        if not note and not leaning and abs(minor - width) > t.diameter:
            note = f"{minor * 1000:.1f} mm across, a crucible is {width * 1000:.0f} mm"
        if note:
            return self._judge(slot, "foreign", 0.9, expected, note=note, **measured)
        if leaning:
            conf = _confidence(t.tilt_ratio - ratio, 1 - t.tilt_ratio)
            return self._judge(slot, "tilted", conf, expected, **measured)
        if offset > t.offset:
            return self._judge(
                slot, "offset", _confidence(offset - t.offset, t.offset), expected, **measured
            )
        conf = min(
            _confidence(t.offset - offset, t.offset),
            _confidence(ratio - t.tilt_ratio, 1 - t.tilt_ratio),
        )
        return self._judge(slot, "seated", conf, expected, **measured)

    def _judge(
        self, slot: str, verdict: Verdict, confidence: float, expected: bool | None,
        *, note: str = "", **measured: Any,
    ) -> PositionCheck:  # fmt: skip
        if expected is None:
            ok = verdict in ("seated", "empty")
        else:
            ok = verdict == ("seated" if expected else "empty")
        if not ok:
            off = measured.get("offset_mm")
            what = {
                "empty": "no crucible",
                "seated": "a crucible where none belongs (in the gripper's path)",
                "offset": f"crucible {off:.1f} mm off its position" if off is not None else "",
                # (a crucible leaning towards the camera looks like one shifted: its rim stays
                # round; far off its pocket it cannot stand flat, so say so)
                "tilted": "crucible not seated flat (tilted)",
                "foreign": f"not a crucible: {note}" if note else "not a crucible",
            }[verdict]
            if verdict == "offset" and off is not None and off > 6.0:
                what += " (or leaning towards the camera)"
            if verdict in ("offset", "tilted") and expected is False:
                what += " where none belongs"
            note = what
        return PositionCheck(
            slot, verdict, round(confidence, 3), expected=expected, ok=ok, note=note, **measured
        )


def _confidence(margin: float, scale: float) -> float:
    """0.5 at the threshold, 1.0 a ``scale`` beyond it."""
    return 0.5 + 0.5 * min(1.0, max(0.0, margin) / max(scale, 1e-12))


def _ellipse_residual(
    points: np.ndarray, centre: tuple[float, float], axes: tuple[float, float], angle: float
) -> float:
    """Mean distance (px) of ``points`` from the ellipse (approximately, radially)."""
    a, b = axes[0] / 2, axes[1] / 2
    if a <= 0 or b <= 0:
        return math.inf
    th = math.radians(angle)
    d = points.astype(np.float64) - np.array(centre)
    x = d[:, 0] * math.cos(th) + d[:, 1] * math.sin(th)
    y = -d[:, 0] * math.sin(th) + d[:, 1] * math.cos(th)
    k = np.sqrt((x / a) ** 2 + (y / b) ** 2)
    return float(np.mean(np.abs(k - 1.0)) * math.sqrt(a * b))


ANNOTATED_WIDTH: Final = 960  # px: the annotated image, cropped to the holder


def annotate(
    frame: np.ndarray, report: PlacementReport, checker: PlacementChecker, pose: Pose | None
) -> bytes:
    """The frame around the holder (the whole frame when it was not found), ``ANNOTATED_WIDTH``
    pixels wide, with each position's ring and verdict, obstructions and the outcome (JPEG)."""
    deck = checker.deck
    K = checker.intrinsics.matrix
    h, w = frame.shape[:2]
    red, green, amber = (40, 40, 230), (60, 190, 60), (0, 170, 240)
    rvec: np.ndarray | None = None
    tvec: np.ndarray | None = None
    left, top, right, bottom = 0, 0, w, h
    x0, y0, x1, y1 = deck.holder
    outline = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
    if pose is not None:
        rvec, _ = cv2.Rodrigues(pose.rotation)
        tvec = pose.position.reshape(3, 1)
        uv, _ = cv2.projectPoints(outline.reshape(-1, 1, 3), rvec, tvec, K, np.zeros(4))
        uv = np.asarray(uv).reshape(-1, 2)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        margin = 0.12 * (hi - lo)
        left, top = (int(max(0, v)) for v in lo - margin)
        right, bottom = (int(min(m, v)) for v, m in zip(hi + margin, (w, h), strict=True))
        top = max(0, top - int(0.10 * (bottom - top)))  # room for the banner
    crop = frame[top:bottom, left:right]
    zoom = ANNOTATED_WIDTH / max(1, crop.shape[1])
    img = cv2.resize(crop, (ANNOTATED_WIDTH, max(1, round(crop.shape[0] * zoom))))

    def project(points: FloatArray) -> np.ndarray:
        assert rvec is not None
        assert tvec is not None
        uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, tvec, K, np.zeros(4))
        px = (np.asarray(uv).reshape(-1, 2) - (left, top)) * zoom
        out: np.ndarray = np.round(px * 16).astype(np.int32)
        return out

    if pose is not None:
        cv2.polylines(img, [project(outline)], True, (220, 220, 220), 1, cv2.LINE_AA, 4)
        phi = np.linspace(0, 2 * math.pi, 60, endpoint=False)
        for check in report.positions:
            seat = deck.positions[check.slot]
            ring = np.column_stack(
                [
                    seat[0] + deck.radius * np.cos(phi),
                    seat[1] + deck.radius * np.sin(phi),
                    np.full(phi.size, deck.rim_height),
                ]
            )
            colour = green if check.ok else red
            cv2.polylines(img, [project(ring)], True, colour, 3, cv2.LINE_AA, 4)
            if check.offset_xy_mm is not None and check.verdict in ("offset", "tilted"):
                centre = np.array(
                    [
                        [seat[0], seat[1], deck.rim_height],
                        [
                            seat[0] + check.offset_xy_mm[0] / 1000,
                            seat[1] + check.offset_xy_mm[1] / 1000,
                            deck.rim_height,
                        ],
                    ]
                )
                p = project(centre)
                cv2.arrowedLine(img, tuple(p[0]), tuple(p[1]), amber, 2, cv2.LINE_AA, 4, 0.3)
            label: str = check.verdict
            if check.offset_mm is not None and check.verdict in ("offset", "tilted"):
                label += f" {check.offset_mm:.0f}mm"
            box = project(ring) / 16
            mid_x = int(box[:, 0].mean())
            _text(img, check.slot, (mid_x, int(box[:, 1].min()) - 6), colour, 0.6, centre=True)
            _text(img, label, (mid_x, int(box[:, 1].max()) + 22), colour, 0.6, centre=True)
        for o in report.obstructions:
            q = project(np.array([[o.x_mm / 1000, o.y_mm / 1000, 0.0]]))
            mid = (int(q[0, 0] // 16), int(q[0, 1] // 16))
            cv2.circle(img, mid, 34, red, 3, cv2.LINE_AA)
            _text(img, "in the path", (mid[0], mid[1] - 40), red, 0.6, centre=True)
    banner = ("OK: " if report.ok else "STOP: ") + report.reason
    cv2.rectangle(img, (0, 0), (img.shape[1], 36), (25, 25, 25), -1)
    _text(img, banner[:64], (8, 26), green if report.ok else red, 0.7)
    ok, data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return bytes(data) if ok else b""


def _text(
    img: np.ndarray,
    text: str,
    org: tuple[int, int],
    colour: tuple[int, int, int],
    size: float,
    *,
    centre: bool = False,
) -> None:
    """Text on a dark box (legible on any background); ``org`` its baseline's left end (or
    its middle with ``centre``)."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    thick = max(1, round(1.6 * size))
    (tw, th), base = cv2.getTextSize(text, font, size, thick)
    x, y = (org[0] - tw // 2 if centre else org[0]), org[1]
    cv2.rectangle(img, (x - 3, y - th - 3), (x + tw + 3, y + base), (25, 25, 25), -1)
    cv2.putText(img, text, (x, y), font, size, colour, thick, cv2.LINE_AA)
