"""The UR3e kind: the supervised ur_rtde link, the UR3e's (calibrated) kinematics, its
collision bodies, UR's calibration files, the embedded UR controller simulator, the
Robotiq Hand-E (through the URCap's socket) and its description for the views (frames from
UR's nominal DH table, a primitive-geometry URDF)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any
from xml.sax.saxutils import quoteattr

from fxcell.calibration import (
    UR3E_NOMINAL_A,
    UR3E_NOMINAL_ALPHA,
    UR3E_NOMINAL_D,
    Calibration,
)
from fxcell.geometry import Pose
from fxcell.link.capabilities import UR3E
from fxcell.link.client import process_link
from fxcell.link.embedded import EmbeddedSimulator
from fxcell.link.gripper import hand_e
from fxcell.robots.description import TCP_FRAME, ArmDescription, ArmJoint, tcp_joint
from fxcell.robots.registry import CalibrationFormat, RobotKind

if TYPE_CHECKING:
    from fxcell.config import CellConfig
    from fxcell.link.backend import ArmCalibration
    from fxcell.motion.kinematics import Kinematics
    from fxcell.robots.registry import CollisionModel

__all__ = ["UR3E_KIND", "ur3e_description"]


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


BASE = "base"
"""Root frame: the controller's base frame, as on the teach pendant (not ROS base_link)."""
FLANGE = "flange"

_RADIUS = 0.045
_HOUSING = 0.11


def ur3e_description(tcp: Pose) -> ArmDescription:
    """The UR3e from UR's nominal DH table: link ``i`` is DH frame ``i-1`` turned by
    ``q_i`` about its z axis, so joint ``i`` has the fixed origin ``Tz(d)·Tx(a)·Rx(α)``
    of the previous DH row; the flange is DH frame 6; ``tcp`` in the flange frame."""
    from fxcell.motion.kinematics import JOINT_NAMES as JOINTS
    from fxcell.motion.kinematics import LINK_NAMES as LINKS

    d, a, alpha = UR3E_NOMINAL_D, UR3E_NOMINAL_A, UR3E_NOMINAL_ALPHA
    parents = (BASE, *LINKS[:-1])
    joints = [
        ArmJoint(
            JOINTS[i],
            parents[i],
            LINKS[i],
            _dh_origin(d[i - 1], a[i - 1], alpha[i - 1]) if i else Pose.identity(),
            (0.0, 0.0, 1.0),
        )
        for i in range(6)
    ]
    joints.append(ArmJoint("flange_joint", LINKS[-1], FLANGE, _dh_origin(d[5], a[5], alpha[5])))
    joints.append(tcp_joint(FLANGE, tcp))
    urdf = _urdf(tcp, JOINTS, LINKS)
    return ArmDescription("ur3e", "UR3e", BASE, tuple(joints), FLANGE, urdf)


def _dh_origin(d: float, a: float, alpha: float) -> Pose:
    return Pose.from_rpy((a, 0.0, d), (alpha, 0.0, 0.0))


def _urdf(tcp: Pose, joint_names: Sequence[str], link_names: Sequence[str]) -> str:
    """The arm as URDF: links named as in UR's ROS description, cylinders as geometry."""
    d, a_, alpha = UR3E_NOMINAL_D, UR3E_NOMINAL_A, UR3E_NOMINAL_ALPHA
    tcp_xyz = tuple(float(v) for v in tcp.position)
    lines = ['<?xml version="1.0"?>', '<robot name="ur3e">']
    lines.append('  <material name="ur_blue"><color rgba="0.35 0.55 0.85 1"/></material>')
    lines.append('  <material name="ur_grey"><color rgba="0.75 0.75 0.75 1"/></material>')
    lines.append('  <material name="tool"><color rgba="0.25 0.25 0.25 1"/></material>')
    lines.append(_link(BASE, [_cylinder((0, 0, 0.03), (0, 0, 0), 0.06, 0.075, "ur_grey")]))
    for i, link in enumerate(link_names):
        visuals = [_cylinder((0, 0, 0), (0, 0, 0), _HOUSING, _RADIUS, "ur_blue")]
        a, di = a_[i], d[i]
        length = math.hypot(a, di)
        if length > 1e-6:  # the segment to the next joint: (a, 0, d) in this frame
            pitch = math.atan2(a, di)
            visuals.append(
                _cylinder((a / 2, 0, di / 2), (0, pitch, 0), length, _RADIUS * 0.8, "ur_grey")
            )
        lines.append(_link(link, visuals))
    tool_len = math.dist((0.0, 0.0, 0.0), tcp_xyz)
    tool = []
    if tool_len > 1e-6:  # the gripper as a cylinder along the flange z axis
        tool.append(_cylinder((0, 0, tool_len / 2), (0, 0, 0), tool_len, 0.035, "tool"))
    lines.append(_link(FLANGE, tool))
    lines.append(_link(TCP_FRAME, []))
    parents = (BASE, *link_names[:-1])
    for i, name in enumerate(joint_names):
        xyz, rot = ((a_[i - 1], 0.0, d[i - 1]), alpha[i - 1]) if i else ((0.0, 0.0, 0.0), 0.0)
        lines.append(
            f'  <joint name="{name}" type="revolute">'
            f'<parent link="{parents[i]}"/><child link="{link_names[i]}"/>'
            f'<origin xyz="{_v(xyz)}" rpy="{_v((rot, 0.0, 0.0))}"/>'
            '<axis xyz="0 0 1"/>'
            '<limit lower="-6.283185" upper="6.283185" effort="56" velocity="3.14"/>'
            "</joint>"
        )
    lines.append(
        f'  <joint name="flange_joint" type="fixed"><parent link="{link_names[-1]}"/>'
        f'<child link="{FLANGE}"/><origin xyz="{_v((a_[5], 0.0, d[5]))}" '
        f'rpy="{_v((alpha[5], 0.0, 0.0))}"/></joint>'
    )
    lines.append(
        f'  <joint name="{TCP_FRAME}_joint" type="fixed"><parent link="{FLANGE}"/>'
        f'<child link="{TCP_FRAME}"/><origin xyz="{_v(tcp_xyz)}" '
        f'rpy="{_v(tcp.rpy)}"/></joint>'
    )
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


def _v(values: Sequence[float]) -> str:
    return " ".join(f"{v:.6g}" for v in values)


def _cylinder(
    xyz: Sequence[float], rpy: Sequence[float], length: float, radius: float, material: str
) -> str:
    return (
        f'<visual><origin xyz="{_v(xyz)}" rpy="{_v(rpy)}"/>'
        f'<geometry><cylinder radius="{radius:.6g}" length="{length:.6g}"/></geometry>'
        f'<material name="{material}"/></visual>'
    )


def _link(name: str, visuals: list[str]) -> str:
    return f"  <link name={quoteattr(name)}>{''.join(visuals)}</link>"


UR3E_KIND = RobotKind(
    capabilities=UR3E,
    link=process_link,
    kinematics=ur3e_kinematics,
    collision=ur3e_collision,
    calibration=CalibrationFormat(nominal=Calibration.nominal, load=Calibration.load),
    simulator=ur3e_simulator,
    description=ur3e_description,
    gripper=hand_e,
)
