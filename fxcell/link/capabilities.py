"""What a robot kind can do: :class:`RobotCapabilities`, data beside the link contract.

A robot kind (``robot.kind`` in the configuration) names its joint count, the period of
the trajectory samples its link streams, and the commands of the command table
(:data:`fxcell.commands.COMMANDS`) it cannot do. The Cell refuses such a command before
anything is sent, with :class:`~fxcell.errors.UnsupportedCommandError` naming the kind.
The registry of kinds (link, kinematic model, simulator) is :mod:`fxcell.robots`.
"""

from __future__ import annotations

from dataclasses import dataclass

from fxcell.commands import COMMANDS
from fxcell.errors import InvalidArgumentError, UnsupportedCommandError
from fxcell.protocol import CONTROL_PERIOD

__all__ = ["UR3E", "RobotCapabilities"]


@dataclass(frozen=True)
class RobotCapabilities:
    """A robot kind's shape and the commands it cannot do."""

    kind: str
    """The kind's name, as ``robot.kind`` says it (``ur3e``)."""
    joints: int
    """Joints of the arm: the width of every joint vector and trajectory sample."""
    sample_period: float
    """Seconds between two samples of a streamed trajectory (the link's servo cycle)."""
    unsupported: frozenset[str] = frozenset()
    """Commands of the command table this kind refuses."""

    def __post_init__(self) -> None:
        unknown = sorted(self.unsupported - COMMANDS.keys())
        if unknown:
            raise InvalidArgumentError(f"{self.kind}: no such commands {unknown}")
        if self.joints < 1 or not self.sample_period > 0:
            raise InvalidArgumentError(f"{self.kind}: joints and sample_period must be > 0")

    def supports(self, command: str) -> bool:
        """Whether this kind can do ``command`` (a name of the command table)."""
        return command not in self.unsupported

    def check(self, command: str) -> None:
        """Raise :class:`UnsupportedCommandError` unless this kind can do ``command``."""
        if command in self.unsupported:
            raise UnsupportedCommandError(command, self.kind)


UR3E = RobotCapabilities(kind="ur3e", joints=6, sample_period=CONTROL_PERIOD)
"""The UR3e does every command of the table; servoJ at the e-Series' 500 Hz."""
