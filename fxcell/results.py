"""What commands return, as plain data (no numpy): a move's result, the program status.

Defined in the base layer so that the network client decodes the daemon's answers into
the same types the in-process :class:`~fxcell.cell.Cell` returns, without the motion
stack installed.
"""

from __future__ import annotations

from dataclasses import dataclass

from fxcell.protocol import ProgramState


@dataclass(frozen=True, slots=True)
class ProgramStatus:
    """The dashboard's program state: ``PLAYING``/``STOPPED``/``PAUSED`` and the program."""

    state: ProgramState
    program: str


@dataclass(frozen=True, slots=True)
class GripResult:
    """Where the gripper's fingers stopped (opening in m) and whether they hold an object."""

    width: float
    holding: bool


@dataclass(frozen=True)
class MoveResult:
    """What a move did."""

    target_joints: tuple[float, ...]
    target_pose: tuple[float, ...]
    """Target TCP pose ``(x, y, z, qx, qy, qz, qw)``, the form ``get_current_pose`` returns
    and ``move_pose`` accepts (a six-number list would be read as roll, pitch, yaw)."""
    reached_joints: tuple[float, ...]
    reached_pose: tuple[float, ...]
    """Reached TCP pose ``(x, y, z, qx, qy, qz, qw)``: can be passed back to ``move_pose``."""
    joint_error: float
    """Largest |reached - target| over the joints (rad)."""
    position_error: float
    """TCP position error (m)."""
    orientation_error: float
    """TCP orientation error (rad)."""
    planned_duration: float
    executed_duration: float
    """From the first streamed sample to the robot at rest (s)."""
    planner: str
    stopped: bool = False
    max_tracking_error: float = 0.0
    """Largest |actual - planned| joint difference seen while streaming (rad)."""
