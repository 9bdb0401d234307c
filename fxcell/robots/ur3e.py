"""The UR3e kind: the supervised ur_rtde link, the UR3e's (calibrated) kinematics, its
collision bodies, UR's calibration files, the embedded UR controller simulator and the
Robotiq Hand-E (through the URCap's socket)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from fxcell.calibration import Calibration
from fxcell.link.capabilities import UR3E
from fxcell.link.client import process_link
from fxcell.link.embedded import EmbeddedSimulator
from fxcell.link.gripper import hand_e
from fxcell.robots.registry import CalibrationFormat, RobotKind

if TYPE_CHECKING:
    from fxcell.config import CellConfig
    from fxcell.link.backend import ArmCalibration
    from fxcell.motion.kinematics import Kinematics
    from fxcell.robots.registry import CollisionModel

__all__ = ["UR3E_KIND"]


def ur3e_kinematics(config: CellConfig, calibration: ArmCalibration | None) -> Kinematics:
    """The UR3e's kinematic model (:func:`fxcell.motion.moves.ur3e_kinematics`, imported
    when the planner is built: the motion stack loads on first use)."""
    from fxcell.motion.moves import ur3e_kinematics as model

    return model(config, calibration)


def ur3e_collision(config: CellConfig) -> CollisionModel:
    """The UR3e's collision bodies (:func:`fxcell.motion.moves.ur3e_collision`, imported on
    first use)."""
    from fxcell.motion.moves import ur3e_collision as model

    return model(config)


def ur3e_simulator(options: Mapping[str, Any]) -> EmbeddedSimulator:
    """The embedded UR controller simulator (a process on a free loopback address)."""
    return EmbeddedSimulator(**options)


UR3E_KIND = RobotKind(
    capabilities=UR3E,
    link=process_link,
    kinematics=ur3e_kinematics,
    collision=ur3e_collision,
    calibration=CalibrationFormat(nominal=Calibration.nominal, load=Calibration.load),
    simulator=ur3e_simulator,
    gripper=hand_e,
)
