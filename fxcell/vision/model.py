"""What the camera looks at: the crucible holder (its plate, fiducials and positions) and the
camera's pinhole model, in one place for the placement check and the simulator's renderer.

Coordinates: the *station frame* of the layout station the check judges (``vision.station``,
the fusion machine's loading deck): slot A1's seat at the origin, slots along +x, the seat
plane at z = 0, z up. Distances in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fxcell.config import CameraConfig, VisionConfig
from fxcell.errors import ConfigError
from fxcell.geometry import Pose
from fxcell.layout import Layout, ObjectKind, Station

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera with OpenCV distortion: image size, camera matrix, coefficients."""

    width: int
    height: int
    matrix: FloatArray
    distortion: FloatArray

    @classmethod
    def from_config(cls, camera: CameraConfig) -> Intrinsics:
        matrix = np.array(
            [[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]]
        )
        dist = np.array(camera.distortion or (0.0, 0.0, 0.0, 0.0), dtype=np.float64)
        return cls(camera.width, camera.height, matrix, dist)


@dataclass(frozen=True)
class Deck:
    """The holder as the camera sees it: positions, fiducials, plate, the object's size."""

    station: Station
    kind: ObjectKind
    positions: dict[str, FloatArray]
    """Slot name → seat centre (x, y) in the station frame."""
    markers: dict[int, FloatArray]
    """Marker id → its four corners (4, 3) in the station frame, in ArUco's order
    (top-left, top-right, bottom-right, bottom-left as seen from above, x right, y up)."""
    marker_size: float
    holder: tuple[float, float, float, float]
    dictionary: str

    @classmethod
    def from_config(cls, vision: VisionConfig, layout: Layout) -> Deck:
        try:
            station = layout.station(vision.station)
        except Exception as exc:
            raise ConfigError(f"vision.station: {exc}") from None
        kind = layout.config.objects[station.config.holds]
        positions = {}
        for slot in station.slots:
            row, col = station.index(slot)
            positions[slot] = np.array(
                [col * station.config.pitch[0], row * station.config.pitch[1]]
            )
        h = vision.marker_size / 2
        markers = {
            m.id: np.array(
                [
                    [m.position[0] - h, m.position[1] + h, 0.0],
                    [m.position[0] + h, m.position[1] + h, 0.0],
                    [m.position[0] + h, m.position[1] - h, 0.0],
                    [m.position[0] - h, m.position[1] - h, 0.0],
                ]
            )
            for m in vision.markers
        }
        return cls(
            station, kind, positions, markers, vision.marker_size, vision.holder, vision.dictionary
        )

    @property
    def radius(self) -> float:
        """The object's outer radius (m)."""
        return self.kind.width / 2

    @property
    def rim_height(self) -> float:
        """Height of the object's rim above its seat (m)."""
        return self.kind.height


def camera_pose(camera: CameraConfig, flange: Pose | None = None) -> Pose:
    """The camera frame in the robot base frame (``flange``: the flange pose, for a camera
    mounted on it)."""
    mount = Pose.from_ur(camera.pose)
    if camera.mount == "flange":
        if flange is None:
            raise ConfigError("camera.mount is flange: its pose needs the flange's pose")
        return flange @ mount
    return mount


def station_in_camera(station: Station, camera_in_base: Pose) -> Pose:
    """The station frame in the camera frame (what ``solvePnP`` estimates from the markers)."""
    return camera_in_base.inverse() @ station.frame


def plane_homography(
    matrix: FloatArray, station_in_cam: Pose, height: float, origin: FloatArray, scale: float
) -> FloatArray:
    """Image ← rectified plane: pixel (u, v) of a metric image of the station plane at
    ``height`` whose pixel (0, 0) is at ``origin`` (x, y) and whose pixels are ``scale`` m wide
    (u along x, v along -y: the image looks down on the plane)."""
    R = station_in_cam.rotation
    t = station_in_cam.position + R[:, 2] * height
    plane = np.column_stack([R[:, 0], R[:, 1], t])
    metric = np.array([[scale, 0.0, origin[0]], [0.0, -scale, origin[1]], [0.0, 0.0, 1.0]])
    H: FloatArray = matrix @ plane @ metric
    out: FloatArray = H / H[2, 2]
    return out
