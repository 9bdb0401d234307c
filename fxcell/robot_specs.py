"""What each robot kind's maker publishes, written once: the joints' range, the planning
velocity and acceleration limits, the home joints, the TCP of its usual gripper, its
payload. The configuration (:mod:`fxcell.config`) takes its defaults from the kind's spec
and checks what the user gives against it; the kinematic models (:mod:`fxcell.motion`)
read the same numbers. Plain Python (no numpy): every configuration load reads it.

Units: radians, rad/s, rad/s², metres, kilograms.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

__all__ = ["NED2_SPEC", "SPECS", "UR3E_SPEC", "RobotSpec", "Vector3", "Vector6"]

Vector6 = tuple[float, float, float, float, float, float]
"""Six numbers: a joint vector (rad) or a pose as UR writes it (x y z m, rotation vector rad).
The one definition: ``fxcell.config`` and ``fxcell.geometry`` use it, and this module needs
no numpy, as the light client does not."""
Vector3 = tuple[float, float, float]


def _six(*values: float) -> Vector6:
    a, b, c, d, e, f = values
    return (a, b, c, d, e, f)


def _degrees(*values: float) -> Vector6:
    return _six(*(math.radians(v) for v in values))


@dataclass(frozen=True)
class RobotSpec:
    """One kind's published figures and what its configuration may say."""

    kind: str
    """``robot.kind``."""
    title: str
    """The robot's name as its maker writes it (for messages)."""
    position_min: Vector6
    position_max: Vector6
    """The joints' range (rad): configured position limits must lie inside it."""
    velocity_max: Vector6
    """The fastest each joint may be planned to move (rad/s)."""
    limits: Mapping[str, Vector6]
    """Defaults of ``limits`` (the keys of :class:`fxcell.config.JointLimits`' vectors)."""
    home: Vector6
    """Default ``home`` joints."""
    tcp: Vector6
    """Default ``tool.tcp``: its usual gripper's grip point in the flange frame (x, y, z in
    m, rotation vector in rad; z along the fingers' approach)."""
    payload: float
    """Default ``tool.payload`` (kg)."""
    payload_max: float
    """The rated payload (kg): ``tool.payload`` may not exceed it."""
    shipped_config: str
    """The shipped configuration of a cell with this robot (a file in ``config/``): what a
    user's file leaves out comes from it."""
    robot_options: Mapping[str, tuple[object, ...]] = field(default_factory=dict)
    """``robot.*`` options the kind takes only some values of (absent: any value)."""
    link_process: bool = True
    """Its robot link runs in a process of its own that asks for real-time scheduling
    (``robot.realtime_priority``; the UR's 500 Hz servo stream); False: in the cell process
    (the Ned2's, which hands the robot whole trajectories)."""


UR3E_SPEC = RobotSpec(
    kind="ur3e",
    title="Universal Robots UR3e",
    position_min=(-2 * math.pi,) * 6,
    position_max=(2 * math.pi,) * 6,
    # UR3e data sheet: 180°/s for base, shoulder and elbow, 360°/s for the wrists
    velocity_max=_six(math.pi, math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi),
    limits={
        "position_min": (-2 * math.pi,) * 6,
        "position_max": (2 * math.pi,) * 6,
        "velocity": _six(math.pi, math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi),
        "acceleration": (0.7, 0.7, 0.7, 1.4, 1.4, 1.4),  # the seed's joint_limits.yaml
        "jerk": (10.0,) * 6,
        "braking_acceleration": (4.0, 4.0, 4.0, 8.0, 8.0, 8.0),
        "braking_jerk": (40.0,) * 6,
    },
    home=(0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0),
    # the seed's TCP: the Robotiq Hand-E's fingertip centre
    tcp=(-0.00025, 0.00245, 0.14789, 0.0, 0.0, -1.5708),
    payload=1.0,  # Hand-E with fingers
    payload_max=3.0,
    shipped_config="cell.yaml",
)

_NED2_LOWER = _degrees(-171.88, -105.0, -76.78, -119.75, -110.01, -144.96)
_NED2_UPPER = _degrees(171.88, 34.96, 89.96, 119.75, 110.17, 144.96)
# niryo_moveit_config_standalone joint_limits.yaml
_NED2_VELOCITY = _six(1.57, 1.047, 1.57, 3.14, 3.14, 3.14)
_NED2_ACCELERATION = _six(2.0, 0.8, 2.0, 3.0, 3.0, 3.0)

NED2_SPEC = RobotSpec(
    kind="ned2",
    title="Niryo Ned2",
    # niryo_robot_description/urdf/ned2 (ned_ros v5.6.x); they changed between releases
    position_min=_NED2_LOWER,
    position_max=_NED2_UPPER,
    velocity_max=_NED2_VELOCITY,
    limits={
        "position_min": _NED2_LOWER,
        "position_max": _NED2_UPPER,
        "velocity": _NED2_VELOCITY,
        "acceleration": _NED2_ACCELERATION,
        "jerk": (10.0,) * 6,
        # a stop brakes at the robot's planning accelerations: from full speed within 1.5 s
        "braking_acceleration": _NED2_ACCELERATION,
        "braking_jerk": (40.0,) * 6,
    },
    home=(0.0, 0.3, -1.3, 0.0, 0.0, 0.0),  # Niryo's home: forearm resting on the shoulder
    # Gripper 1: the fingers close 75 mm along tool_link's x, the direction they approach
    # along; the TCP's z is tool_link's x
    tcp=(0.075, 0.0, 0.0, 0.0, math.pi / 2, 0.0),
    payload=0.0,  # the Ned2 takes no payload over its interfaces
    payload_max=0.3,
    shipped_config="ned2-cell.yaml",
    robot_options={
        "external_control": ("script",),  # no URCap: the robot's own servers take the plan
        "receiver": ("stream",),  # the rosbridge's joint states; ur_rtde is a UR's
        # the robot calibrates its encoders itself: no calibration file
        "calibration": ("controller", "nominal", None),
    },
    link_process=False,
)

SPECS: Mapping[str, RobotSpec] = {spec.kind: spec for spec in (UR3E_SPEC, NED2_SPEC)}
"""The specs of the kinds fxcell ships, by ``robot.kind``."""
