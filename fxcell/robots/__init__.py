"""Robot kinds: what ``robot.kind`` in the configuration chooses.

A kind is one :class:`RobotKind`: its capabilities (joints, trajectory sample period,
commands it refuses: :mod:`fxcell.link.capabilities`), its link factory (an
implementation of :class:`~fxcell.link.backend.LinkBackend`), its kinematic model factory
(a :class:`KinematicModel`, what the motion planner plans on), its collision model (a
:class:`CollisionModel` of the arm in the configured scene), its calibration forms
(:class:`CalibrationFormat`: nominal, from a file; the link reads the arm's own), how its
link takes a streamed plan (``execution``), its simulator launcher (started when no
controller address is configured) and its description for the views
(:class:`~fxcell.robots.description.ArmDescription`: frames as a tree of joints, URDF).
Adding a robot is one package holding those and one :func:`register` call; the Cell and
the motion layer never name a kind.
"""

from __future__ import annotations

from fxcell.robots.ned2 import NED2_KIND
from fxcell.robots.registry import (
    CalibrationFormat,
    CollisionFactory,
    CollisionModel,
    DescriptionFactory,
    KinematicModel,
    KinematicsFactory,
    RobotKind,
    Simulator,
    SimulatorLauncher,
    kind_names,
    register,
    robot_kind,
    unregister,
)
from fxcell.robots.ur3e import UR3E_KIND

register(UR3E_KIND)
register(NED2_KIND)

__all__ = [
    "NED2_KIND",
    "UR3E_KIND",
    "CalibrationFormat",
    "CollisionFactory",
    "CollisionModel",
    "DescriptionFactory",
    "KinematicModel",
    "KinematicsFactory",
    "RobotKind",
    "Simulator",
    "SimulatorLauncher",
    "kind_names",
    "register",
    "robot_kind",
    "unregister",
]
