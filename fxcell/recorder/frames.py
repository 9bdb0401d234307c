"""The arm's link frames for Foxglove's 3D panel: its URDF and its /tf, for any robot kind.

The frames come from the robot kind's :class:`~fxcell.robots.description.ArmDescription`
(the UR3e's from UR's DH table, the Ned2's from its URDF): each joint is a fixed origin
and, for a revolute joint, a rotation about its axis. The transform of a revolute joint at
``q_i`` is ``origin · R(axis, q_i)``: its quaternion is the origin's quaternion times
``(axis·sin(q_i/2), cos(q_i/2))``, four products of constants with two half-angle terms,
cheap enough for the writer thread at tens of Hz.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from typing import Any

from fxcell.geometry import Pose
from fxcell.recorder import topics
from fxcell.robots.description import ArmDescription
from fxcell.robots.ur3e import ur3e_description

_Quat = tuple[float, float, float, float]


class LinkFrames:
    """Per-link transforms and the URDF of an arm: ``arm`` (default the UR3e with ``tcp``,
    UR ``x, y, z, rx, ry, rz`` in the flange frame; None: the flange)."""

    def __init__(
        self, tcp: Sequence[float] | None = None, arm: ArmDescription | None = None
    ) -> None:
        if arm is None:
            arm = ur3e_description(Pose.from_ur(tcp) if tcp is not None else Pose.identity())
        self.arm = arm
        self.joint_count = len(arm.revolute)
        # per joint: parent, child, translation, and for a fixed joint its quaternion, for a
        # revolute one the constants (o, k) of its quaternion o·cos(q/2) + k·sin(q/2)
        self._joints: list[tuple[str, str, tuple[float, float, float], _Quat, _Quat | None]] = []
        for joint in arm.joints:
            x, y, z = (float(v) for v in joint.origin.position)
            o = joint.origin.quaternion
            k: _Quat | None = None
            if joint.axis is not None:
                ox, oy, oz, ow = o
                ax, ay, az = joint.axis
                k = (
                    ow * ax + oy * az - oz * ay,
                    ow * ay + oz * ax - ox * az,
                    ow * az + ox * ay - oy * ax,
                    -(ox * ax + oy * ay + oz * az),
                )
            self._joints.append((joint.parent, joint.child, (x, y, z), o, k))

    def transforms(self, q: Sequence[float], stamp: dict[str, int]) -> list[dict[str, Any]] | None:
        """``foxglove.FrameTransform`` dicts for joint positions ``q`` (None if ``q`` is not
        as long as the arm has joints)."""
        if len(q) != self.joint_count:
            return None
        out = []
        angles = iter(q)
        for parent, child, xyz, o, k in self._joints:
            if k is None:
                rot = {"x": o[0], "y": o[1], "z": o[2], "w": o[3]}
            else:
                qi = next(angles)
                s, c = math.sin(qi / 2), math.cos(qi / 2)
                rot = {
                    "x": o[0] * c + k[0] * s,
                    "y": o[1] * c + k[1] * s,
                    "z": o[2] * c + k[2] * s,
                    "w": o[3] * c + k[3] * s,
                }
            out.append(_transform(stamp, parent, child, xyz, rot))
        return out

    def transforms_json(self, q: Sequence[float], sec: int, nsec: int) -> bytes | None:
        """The ``foxglove.FrameTransforms`` message of :meth:`transforms` as JSON, fast.

        One ``%`` formatting of a template made once: about ten times cheaper than
        building dicts and ``json.dumps`` (the writer thread does this tens of times a second).
        """
        if len(q) != self.joint_count:
            return None
        args: list[float] = []
        angles = iter(q)
        for *_, o, k in self._joints:
            if k is None:
                args += (sec, nsec)
            else:
                qi = next(angles)
                s, c = math.sin(qi / 2), math.cos(qi / 2)
                args += (
                    sec,
                    nsec,
                    o[0] * c + k[0] * s,
                    o[1] * c + k[1] * s,
                    o[2] * c + k[2] * s,
                    o[3] * c + k[3] * s,
                )
        return (self._template % tuple(args)).encode()

    @functools.cached_property
    def _template(self) -> str:
        # placeholders no number or frame name in the JSON can contain
        stamp: dict[str, Any] = {"sec": "@d@", "nsec": "@d@"}
        marker = {"x": "@r@", "y": "@r@", "z": "@r@", "w": "@r@"}
        parts = []
        for parent, child, xyz, o, k in self._joints:
            fixed = {"x": o[0], "y": o[1], "z": o[2], "w": o[3]}
            parts.append(_transform(stamp, parent, child, xyz, fixed if k is None else marker))
        text = json.dumps({"transforms": parts}, separators=(",", ":")).replace("%", "%%")
        return text.replace('"@d@"', "%d").replace('"@r@"', "%r")

    def urdf(self) -> str:
        """The arm as URDF, with the same link names and the TCP frame."""
        return self.arm.urdf

    @property
    def attachment(self) -> str:
        """The name of the URDF attachment in a file (``<kind>.urdf``)."""
        return f"{self.arm.kind}{topics.URDF_SUFFIX}"


def _transform(
    stamp: dict[str, Any],
    parent: str,
    child: str,
    xyz: Sequence[float],
    rotation: dict[str, Any],
) -> dict[str, Any]:
    return {
        "timestamp": stamp,
        "parent_frame_id": parent,
        "child_frame_id": child,
        "translation": {"x": xyz[0], "y": xyz[1], "z": xyz[2]},
        "rotation": rotation,
    }
