"""The Ned2 kind: its rosbridge link (:class:`~fxcell.link.ned2.link.Ned2Link`), its
kinematic model (:class:`~fxcell.motion.ned2.Ned2Kinematics`), its collision bodies (its
URDF's shapes), its calibration (the nominal model: the robot calibrates its encoders
itself). No power or shutdown over the network: those commands are refused for it. With
no host configured the Cell starts the embedded Ned2 simulator
(:func:`~fxcell.link.ned2.embedded.ned2_simulator`), which boots needing calibration as
the robot does."""

from __future__ import annotations

from typing import TYPE_CHECKING

from fxcell.commands import Feature
from fxcell.geometry import Pose
from fxcell.link.capabilities import RobotCapabilities
from fxcell.link.ned2.embedded import ned2_simulator
from fxcell.link.ned2.gripper import ned2_gripper
from fxcell.link.ned2.link import NED2_SIGNALS, Ned2Calibration, Ned2Link
from fxcell.motion.execution import ExecutionOptions
from fxcell.robots.description import ArmDescription, from_urdf
from fxcell.robots.registry import CalibrationFormat, RobotKind

if TYPE_CHECKING:
    from collections.abc import Callable

    from fxcell.config import CellConfig, RobotConfig
    from fxcell.link.backend import ArmCalibration
    from fxcell.link.contract import LinkStatus
    from fxcell.motion.ned2 import Ned2Kinematics
    from fxcell.protocol import RobotState
    from fxcell.robots.registry import CollisionModel

__all__ = ["NED2", "NED2_KIND"]

NED2 = RobotCapabilities(
    kind="ned2",
    joints=6,
    sample_period=0.01,
    features=frozenset(Feature) - {Feature.REMOTE_POWER, Feature.REMOTE_SHUTDOWN},
    state_patience=1.0,
)
"""Six joints, trajectories planned every 10 ms (handed to the robot a point every
50 ms); no remote power or shutdown. Its state comes at 50 Hz over a WebSocket, and its
link counts it lost after 1 s (``fxcell.link.ned2.link.STALE_AFTER``), so a move waits as
long for it (the controller runs the whole trajectory by itself meanwhile); at the UR's
0.25 s a busy machine once interrupted a healthy Ned2 move."""


def ned2_kinematics(config: CellConfig, calibration: ArmCalibration | None) -> Ned2Kinematics:
    from fxcell.errors import CalibrationError
    from fxcell.motion.ned2 import Ned2Kinematics

    if calibration is not None and not isinstance(calibration, Ned2Calibration):
        raise CalibrationError(
            f"the Ned2's model takes its own calibration, not a {type(calibration).__name__}"
        )
    limits = config.limits
    return Ned2Kinematics(Pose.from_ur(config.tool.tcp), limits.position_min, limits.position_max)


def ned2_collision(config: CellConfig) -> CollisionModel:
    import pinocchio as pin

    from fxcell.layout import Layout
    from fxcell.motion import ned2
    from fxcell.motion.collision import CollisionChecker

    tcp = Pose.from_ur(config.tool.tcp)
    return CollisionChecker.from_urdf(
        ned2.urdf(),
        config.scene,
        tool_frame="tool_link",
        never=ned2.NEVER_IN_CONTACT,
        layout=Layout(config.layout),
        tcp=pin.SE3(tcp.rotation, tcp.position),
    )


def ned2_link(
    host: str | None,
    robot: RobotConfig,
    *,
    on_state: Callable[[RobotState], None],
    on_status: Callable[[LinkStatus, str], None],
    on_control: Callable[[bool, str], None],
) -> Ned2Link:
    from fxcell.motion.ned2 import Ned2Kinematics

    return Ned2Link(
        host,
        robot,
        on_state=on_state,
        on_status=on_status,
        on_control=on_control,
        sample_period=NED2.sample_period,
        forward=Ned2Kinematics().forward,
    )


def ned2_description(tcp: Pose) -> ArmDescription:
    """The Ned2 for the views: its URDF's frames (:func:`fxcell.motion.ned2.urdf`), the
    TCP on ``tool_link``."""
    from fxcell.motion import ned2

    return from_urdf("ned2", "Ned2", ned2.urdf(), "tool_link", tcp)


NED2_KIND = RobotKind(
    capabilities=NED2,
    link=ned2_link,
    kinematics=ned2_kinematics,
    collision=ned2_collision,
    calibration=CalibrationFormat(nominal=Ned2Calibration.nominal, load=Ned2Calibration.load),
    simulator=ned2_simulator,
    execution=ExecutionOptions(compensate_lag=False),
    description=ned2_description,
    gripper=ned2_gripper,
    signals=NED2_SIGNALS,
)
