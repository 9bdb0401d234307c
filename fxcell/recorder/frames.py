"""Link frames of the UR3e for Foxglove's 3D panel: a primitive-geometry URDF and its /tf.

UR publishes no meshes fxcell could ship, so the URDF is generated from the DH
parameters of :mod:`fxcell.motion.kinematics` with cylinders for the joint housings and the
links. Each URDF link frame sits at its joint: link *i* is DH frame *i−1* turned by
``q_i`` about its z axis, so joint *i* has the fixed origin ``Tz(d)·Tx(a)·Rx(α)`` of the
previous DH row and a z axis — a plain URDF any tool animates. The transform of joint
*i* at ``q_i`` is ``origin · Rz(q_i)``: its quaternion is a closed form of two half
angles, cheap enough for the writer thread at tens of Hz.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from typing import Any, Final
from xml.sax.saxutils import quoteattr

from fxcell.motion.kinematics import DH, JOINT_NAMES, LINK_NAMES, UR3E_DH

BASE: Final = "base"
"""Root frame: the controller's base frame, as on the teach pendant (not ROS base_link)."""
LINKS: Final = LINK_NAMES
JOINTS: Final = JOINT_NAMES
FLANGE: Final = "flange"
TCP: Final = "tcp"

_RADIUS = 0.045
_HOUSING = 0.11


class LinkFrames:
    """Per-link transforms and the URDF of a UR arm with a TCP (flange frame, UR x,y,z,rx,ry,rz)."""

    def __init__(self, tcp: Sequence[float] | None = None, dh: DH = UR3E_DH) -> None:
        from fxcell.geometry import Pose  # keep the module import light

        self.dh = dh
        tcp_pose = Pose.from_ur(tcp) if tcp is not None else Pose.identity()
        self._tcp_xyz = tuple(float(v) for v in tcp_pose.position)
        self._tcp_quat = tuple(float(v) for v in tcp_pose.quaternion)
        self._tcp_rpy = tuple(float(v) for v in tcp_pose.rpy)
        parents = (BASE, *LINKS[:-1])
        # joint i: origin = previous DH row (none for the first joint)
        self._joints: list[tuple[str, str, tuple[float, float, float], float]] = []
        for i in range(6):
            if i == 0:
                xyz, alpha = (0.0, 0.0, 0.0), 0.0
            else:
                xyz, alpha = (dh.a[i - 1], 0.0, dh.d[i - 1]), dh.alpha[i - 1]
            self._joints.append((parents[i], LINKS[i], xyz, alpha))
        self._half_alpha = [(math.sin(a / 2), math.cos(a / 2)) for *_, a in self._joints]
        self._flange_xyz = (dh.a[5], 0.0, dh.d[5])
        self._flange_quat = (math.sin(dh.alpha[5] / 2), 0.0, 0.0, math.cos(dh.alpha[5] / 2))

    def transforms(self, q: Sequence[float], stamp: dict[str, int]) -> list[dict[str, Any]] | None:
        """``foxglove.FrameTransform`` dicts for joint positions ``q`` (None if ``q`` is not 6)."""
        if len(q) != 6:
            return None
        out = []
        for (parent, child, (x, y, z), _), (sa, ca), qi in zip(
            self._joints, self._half_alpha, q, strict=True
        ):
            sz, cz = math.sin(qi / 2), math.cos(qi / 2)
            # Rx(α) ⊗ Rz(q) as a quaternion (x, y, z, w)
            rot = {"x": sa * cz, "y": -sa * sz, "z": ca * sz, "w": ca * cz}
            out.append(_transform(stamp, parent, child, (x, y, z), rot))
        fx, fy, fz, fw = self._flange_quat
        out.append(
            _transform(
                stamp, LINKS[-1], FLANGE, self._flange_xyz, {"x": fx, "y": fy, "z": fz, "w": fw}
            )
        )
        tx, ty, tz, tw = self._tcp_quat
        out.append(
            _transform(stamp, FLANGE, TCP, self._tcp_xyz, {"x": tx, "y": ty, "z": tz, "w": tw})
        )
        return out

    def transforms_json(self, q: Sequence[float], sec: int, nsec: int) -> bytes | None:
        """The ``foxglove.FrameTransforms`` message of :meth:`transforms` as JSON, fast.

        One ``%`` formatting of a template made once: about ten times cheaper than
        building dicts and ``json.dumps`` (the writer thread does this tens of times a second).
        """
        if len(q) != 6:
            return None
        args: list[float] = []
        for (sa, ca), qi in zip(self._half_alpha, q, strict=True):
            sz, cz = math.sin(qi / 2), math.cos(qi / 2)
            args += (sec, nsec, sa * cz, -sa * sz, ca * sz, ca * cz)
        args += (sec, nsec, sec, nsec)
        return (self._template % tuple(args)).encode()

    @functools.cached_property
    def _template(self) -> str:
        stamp = {"sec": 111111, "nsec": 222222}
        rot = {"x": 333333.5, "y": 444444.5, "z": 555555.5, "w": 666666.5}
        parts = [
            _transform(stamp, parent, child, xyz, rot) for parent, child, xyz, _ in self._joints
        ]
        fixed = self.transforms([0.0] * 6, stamp)
        assert fixed is not None
        parts += fixed[6:]
        text = json.dumps({"transforms": parts}, separators=(",", ":")).replace("%", "%%")
        for marker, code in (
            ("111111", "%d"),
            ("222222", "%d"),
            ("333333.5", "%r"),
            ("444444.5", "%r"),
            ("555555.5", "%r"),
            ("666666.5", "%r"),
        ):
            text = text.replace(marker, code)
        return text

    def urdf(self) -> str:
        """The arm as URDF: links named as in UR's ROS description, cylinders as geometry."""
        lines = ['<?xml version="1.0"?>', '<robot name="ur3e">']
        lines.append('  <material name="ur_blue"><color rgba="0.35 0.55 0.85 1"/></material>')
        lines.append('  <material name="ur_grey"><color rgba="0.75 0.75 0.75 1"/></material>')
        lines.append('  <material name="tool"><color rgba="0.25 0.25 0.25 1"/></material>')
        lines.append(_link(BASE, [_cylinder((0, 0, 0.03), (0, 0, 0), 0.06, 0.075, "ur_grey")]))
        for i, link in enumerate(LINKS):
            visuals = [_cylinder((0, 0, 0), (0, 0, 0), _HOUSING, _RADIUS, "ur_blue")]
            a, d = self.dh.a[i], self.dh.d[i]
            length = math.hypot(a, d)
            if length > 1e-6:  # the segment to the next joint: (a, 0, d) in this frame
                pitch = math.atan2(a, d)
                visuals.append(
                    _cylinder((a / 2, 0, d / 2), (0, pitch, 0), length, _RADIUS * 0.8, "ur_grey")
                )
            lines.append(_link(link, visuals))
        lines.append(_link(FLANGE, []))
        tool_len = math.dist((0.0, 0.0, 0.0), self._tcp_xyz)
        tool = []
        if tool_len > 1e-6:  # the gripper as a cylinder along the flange z axis
            tool.append(_cylinder((0, 0, tool_len / 2), (0, 0, 0), tool_len, 0.035, "tool"))
        lines[-1] = _link(FLANGE, tool)
        lines.append(_link(TCP, []))
        for (parent, child, xyz, alpha), name in zip(self._joints, JOINTS, strict=True):
            lines.append(
                f'  <joint name="{name}" type="revolute">'
                f'<parent link="{parent}"/><child link="{child}"/>'
                f'<origin xyz="{_v(xyz)}" rpy="{_v((alpha, 0.0, 0.0))}"/>'
                '<axis xyz="0 0 1"/>'
                '<limit lower="-6.283185" upper="6.283185" effort="56" velocity="3.14"/>'
                "</joint>"
            )
        lines.append(
            f'  <joint name="flange_joint" type="fixed"><parent link="{LINKS[-1]}"/>'
            f'<child link="{FLANGE}"/><origin xyz="{_v(self._flange_xyz)}" '
            f'rpy="{_v((self.dh.alpha[5], 0.0, 0.0))}"/></joint>'
        )
        lines.append(
            f'  <joint name="tcp_joint" type="fixed"><parent link="{FLANGE}"/>'
            f'<child link="{TCP}"/><origin xyz="{_v(self._tcp_xyz)}" '
            f'rpy="{_v(self._tcp_rpy)}"/></joint>'
        )
        lines.append("</robot>")
        return "\n".join(lines) + "\n"


def _transform(
    stamp: dict[str, int],
    parent: str,
    child: str,
    xyz: Sequence[float],
    rotation: dict[str, float],
) -> dict[str, Any]:
    return {
        "timestamp": stamp,
        "parent_frame_id": parent,
        "child_frame_id": child,
        "translation": {"x": xyz[0], "y": xyz[1], "z": xyz[2]},
        "rotation": rotation,
    }


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
