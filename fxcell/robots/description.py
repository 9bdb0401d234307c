"""A robot-neutral description of an arm: its frames as a tree of joints, for the views.

What draws or animates the arm (the page's arm view, the recorder's ``/tf`` and robot
description for Foxglove) takes an :class:`ArmDescription` from the robot kind
(:attr:`fxcell.robots.RobotKind.description`) and never a kind's own parameters. Each
joint is a fixed transform from its parent link's frame (``origin``) followed, for a
revolute joint, by a rotation about ``axis`` (in the joint's frame) by the joint
position; fixed joints carry the flange, the tool and the TCP. A DH arm (the UR3e) and a
URDF arm (the Ned2) are both written so: DH row ``i`` becomes the origin of joint
``i + 1``. The description also holds the URDF text that names the same links (for
Foxglove), and which frame the configured TCP is given in.

The joint positions ``q`` map to the revolute joints in their order here.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

import numpy as np
from numpy.typing import NDArray

from fxcell.errors import InvalidArgumentError
from fxcell.geometry import Pose

__all__ = ["TCP_FRAME", "ArmDescription", "ArmJoint", "from_urdf", "tcp_joint"]

TCP_FRAME = "tcp"
"""The TCP's frame in every description (a fixed joint on the tool frame)."""


@dataclass(frozen=True)
class ArmJoint:
    """One joint: ``child``'s frame is ``parent``'s · ``origin`` · rotation about ``axis``
    by the joint position (``axis`` None: a fixed joint)."""

    name: str
    parent: str
    child: str
    origin: Pose
    axis: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.axis is not None:
            norm = math.sqrt(sum(v * v for v in self.axis))
            if not math.isclose(norm, 1.0, abs_tol=1e-9):
                raise InvalidArgumentError(f"joint {self.name}: the axis must be a unit vector")

    @property
    def revolute(self) -> bool:
        return self.axis is not None


def tcp_joint(tool: str, tcp: Pose) -> ArmJoint:
    """The fixed joint of the TCP frame on the tool frame ``tool``."""
    return ArmJoint(f"{TCP_FRAME}_joint", tool, TCP_FRAME, tcp)


@dataclass(frozen=True)
class ArmDescription:
    """An arm as a tree of frames (see the module's doc)."""

    kind: str
    """The robot kind's name (``ur3e``, ``ned2``): the URDF attachment is named for it."""
    name: str
    """For people: ``UR3e``, ``Ned2``."""
    base: str
    """The root frame: the robot's base frame in which poses are given."""
    joints: tuple[ArmJoint, ...]
    """Every joint, each after its parent's (revolute ones in joint order)."""
    tool: str
    """The frame the configured TCP is given in (the UR's flange, the Ned2's ``tool_link``)."""
    urdf: str
    """The arm as URDF with the same link names and the TCP frame."""

    def __post_init__(self) -> None:
        known = {self.base}
        for joint in self.joints:
            if joint.parent not in known:
                raise InvalidArgumentError(
                    f"joint {joint.name}: its parent {joint.parent!r} comes later or not at all"
                )
            if joint.child in known:
                raise InvalidArgumentError(f"joint {joint.name}: {joint.child!r} twice")
            known.add(joint.child)
        if self.tool not in known:
            raise InvalidArgumentError(f"the tool frame {self.tool!r} is no frame of the arm")

    @property
    def revolute(self) -> tuple[ArmJoint, ...]:
        """The revolute joints, in the order of the joint positions."""
        return tuple(j for j in self.joints if j.revolute)

    @property
    def frames(self) -> tuple[str, ...]:
        """Every frame: the base, then each joint's child."""
        return (self.base, *(j.child for j in self.joints))

    def local(self, q: Sequence[float]) -> list[tuple[ArmJoint, Pose]]:
        """Each joint with its child's pose in its parent's frame at joint positions ``q``."""
        revolute = self.revolute
        if len(q) != len(revolute):
            raise InvalidArgumentError(
                f"the {self.name} has {len(revolute)} joints, got {len(q)} positions"
            )
        angles = dict(zip((j.name for j in revolute), q, strict=True))
        out = []
        for joint in self.joints:
            if joint.axis is None:
                out.append((joint, joint.origin))
            else:
                turn = Pose.from_rotvec((0.0, 0.0, 0.0), np.array(joint.axis) * angles[joint.name])
                out.append((joint, joint.origin @ turn))
        return out

    def poses(self, q: Sequence[float]) -> dict[str, Pose]:
        """Every frame's pose in the base frame at joint positions ``q``."""
        world = {self.base: Pose.identity()}
        for joint, pose in self.local(q):
            world[joint.child] = world[joint.parent] @ pose
        return world

    def tool_chain(self) -> tuple[tuple[ArmJoint, ...], Pose]:
        """The revolute joints from the base to the tool frame, and the fixed transform from
        the last one's child to the tool frame (what draws the arm as a chain needs)."""
        by_child = {j.child: j for j in self.joints}
        path: list[ArmJoint] = []
        frame = self.tool
        while frame != self.base:
            joint = by_child[frame]
            path.append(joint)
            frame = joint.parent
        path.reverse()
        moving = [i for i, j in enumerate(path) if j.revolute]
        last = moving[-1] if moving else -1
        tail = Pose.identity()
        for joint in path[last + 1 :]:
            tail = tail @ joint.origin
        chain: list[ArmJoint] = []
        before = Pose.identity()  # fixed joints between two revolute ones fold into the next
        for joint in path[: last + 1]:
            if joint.revolute:
                origin = before @ joint.origin
                chain.append(ArmJoint(joint.name, joint.parent, joint.child, origin, joint.axis))
                before = Pose.identity()
            else:
                before = before @ joint.origin
        return tuple(chain), tail

    def chain_json(self) -> dict[str, object]:
        """The arm as the page draws it: the revolute joints from the base to the tool
        frame, each an origin (4x4 row-major, in the previous joint's frame) and an axis,
        then the tool frame's transform from the last joint (the page adds the TCP)."""
        chain, tail = self.tool_chain()
        return {
            "robot": self.name,
            "kind": self.kind,
            "base": self.base,
            "tool_frame": self.tool,
            "joints": [
                {"name": j.name, "origin": _rows(j.origin.matrix), "axis": list(j.axis or ())}
                for j in chain
            ],
            "tool": _rows(tail.matrix),
        }


def _rows(matrix: NDArray[np.float64]) -> list[float]:
    return [float(v) for v in matrix.reshape(-1)]


def from_urdf(kind: str, name: str, urdf: str, tool: str, tcp: Pose) -> ArmDescription:
    """The arm a URDF describes (its revolute and fixed joints; a continuous joint counts
    as revolute), with the TCP frame added on ``tool`` (to the URDF text too)."""
    try:
        root = ET.fromstring(urdf)
    except ET.ParseError as exc:
        raise InvalidArgumentError(f"the {name}'s URDF does not parse: {exc}") from None
    children: set[str] = set()
    links = [link.get("name", "") for link in root.iter("link")]
    pending: list[ArmJoint] = []
    for element in root.iter("joint"):
        joint_name = element.get("name", "")
        kind_of = element.get("type", "")
        parent, child = element.find("parent"), element.find("child")
        if parent is None or child is None or kind_of not in ("revolute", "continuous", "fixed"):
            raise InvalidArgumentError(
                f"the {name}'s URDF: joint {joint_name!r} is no revolute or fixed joint "
                "between two links"
            )
        origin = element.find("origin")
        xyz = _floats(origin.get("xyz") if origin is not None else None, joint_name)
        rpy = _floats(origin.get("rpy") if origin is not None else None, joint_name)
        axis_element = element.find("axis")
        axis: tuple[float, float, float] | None = None
        if kind_of != "fixed":
            axis = _floats(axis_element.get("xyz") if axis_element is not None else "1 0 0", "")
        pose = Pose.from_rpy(xyz, rpy)
        pending.append(
            ArmJoint(joint_name, parent.get("link", ""), child.get("link", ""), pose, axis)
        )
        children.add(child.get("link", ""))
    roots = [link for link in links if link not in children]
    if len(roots) != 1:
        raise InvalidArgumentError(f"the {name}'s URDF has {len(roots)} root links, not one")
    ordered: list[ArmJoint] = []  # parents first: a serial arm's joints base to tool
    known = {roots[0]}
    while pending:
        ready = [j for j in pending if j.parent in known]
        if not ready:
            raise InvalidArgumentError(f"the {name}'s URDF: joints hang off no link")
        ordered.extend(ready)
        pending = [j for j in pending if j.parent not in known]
        known.update(j.child for j in ready)
    if tool not in known:
        raise InvalidArgumentError(f"the tool frame {tool!r} is no frame of the {name}")
    ordered.append(tcp_joint(tool, tcp))
    return ArmDescription(kind, name, roots[0], tuple(ordered), tool, _with_tcp(urdf, tool, tcp))


def _floats(text: str | None, joint: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in (text or "0 0 0").split())
    except ValueError:
        values = ()
    if len(values) != 3:
        raise InvalidArgumentError(f"URDF joint {joint!r}: expected 3 numbers, got {text!r}")
    return (values[0], values[1], values[2])


def _with_tcp(urdf: str, tool: str, tcp: Pose) -> str:
    """``urdf`` with the TCP frame as a link on a fixed joint to ``tool``."""
    xyz = " ".join(repr(float(v)) for v in tcp.position)
    rpy = " ".join(repr(float(v)) for v in tcp.rpy)
    added = (
        f"  <link name={quoteattr(TCP_FRAME)}/>\n"
        f'  <joint name={quoteattr(TCP_FRAME + "_joint")} type="fixed">'
        f"<parent link={quoteattr(tool)}/><child link={quoteattr(TCP_FRAME)}/>"
        f'<origin xyz="{xyz}" rpy="{rpy}"/></joint>\n'
    )
    end = urdf.rindex("</robot>")
    return urdf[:end] + added + urdf[end:]
