"""The UR3e kind: the supervised ur_rtde link, the UR3e's (calibrated) kinematics and the
embedded UR controller simulator."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from fxcell.link.capabilities import UR3E
from fxcell.link.client import process_link
from fxcell.link.embedded import EmbeddedSimulator
from fxcell.robots.registry import RobotKind

if TYPE_CHECKING:
    from fxcell.calibration import Calibration
    from fxcell.config import CellConfig
    from fxcell.motion.kinematics import Kinematics

__all__ = ["UR3E_KIND"]


def ur3e_kinematics(config: CellConfig, calibration: Calibration | None) -> Kinematics:
    """The UR3e's kinematic model (:func:`fxcell.motion.moves.ur3e_kinematics`, imported
    when the planner is built: the motion stack loads on first use)."""
    from fxcell.motion.moves import ur3e_kinematics as model

    return model(config, calibration)


def ur3e_simulator(options: Mapping[str, Any]) -> EmbeddedSimulator:
    """The embedded UR controller simulator (a process on a free loopback address)."""
    return EmbeddedSimulator(**options)


UR3E_KIND = RobotKind(
    capabilities=UR3E,
    link=process_link,
    kinematics=ur3e_kinematics,
    simulator=ur3e_simulator,
)
