"""What a robot kind can do: :class:`RobotCapabilities`, data beside the link contract.

A robot kind (``robot.kind`` in the configuration) names its joint count, the period of
the trajectory samples its link streams, and the robot features it has
(:class:`fxcell.commands.Feature`). Each entry of the command table
(:data:`fxcell.commands.COMMANDS`) says which features it needs; the Cell refuses a
command whose features the kind lacks before anything is sent, with
:class:`~fxcell.errors.UnsupportedCommandError` naming the kind.
The registry of kinds (link, kinematic model, simulator) is :mod:`fxcell.robots`.
"""

from __future__ import annotations

from dataclasses import dataclass

from fxcell.commands import COMMANDS, Feature
from fxcell.errors import InvalidArgumentError, UnsupportedCommandError
from fxcell.protocol import CONTROL_PERIOD

__all__ = ["UR3E", "RobotCapabilities"]


@dataclass(frozen=True)
class RobotCapabilities:
    """A robot kind's shape and the features it has."""

    kind: str
    """The kind's name, as ``robot.kind`` says it (``ur3e``)."""
    joints: int
    """Joints of the arm: the width of every joint vector and trajectory sample."""
    sample_period: float
    """Seconds between two samples of a streamed trajectory (the link's servo cycle)."""
    features: frozenset[Feature] = frozenset(Feature)
    """The robot features this kind has (default: every one)."""
    state_patience: float = 0.25
    """Seconds a running move waits for the robot's next state sample before it counts the
    robot lost (a UR streams 500 samples a second; a slower stream needs more)."""

    def __post_init__(self) -> None:
        unknown = sorted(str(f) for f in self.features if f not in set(Feature))
        if unknown:
            raise InvalidArgumentError(f"{self.kind}: no such features {unknown}")
        if self.joints < 1 or not self.sample_period > 0 or not self.state_patience > 0:
            raise InvalidArgumentError(
                f"{self.kind}: joints, sample_period and state_patience must be > 0"
            )

    @property
    def unsupported(self) -> frozenset[str]:
        """The commands of the table this kind refuses (they need a feature it lacks)."""
        return frozenset(n for n, c in COMMANDS.items() if not c.requires <= self.features)

    def supports(self, command: str) -> bool:
        """Whether this kind can do ``command`` (a name of the command table; a name the
        table lacks needs no feature)."""
        entry = COMMANDS.get(command)
        return entry is None or entry.requires <= self.features

    def check(self, command: str) -> None:
        """Raise :class:`UnsupportedCommandError` unless this kind can do ``command``."""
        if not self.supports(command):
            raise UnsupportedCommandError(command, self.kind)


UR3E = RobotCapabilities(kind="ur3e", joints=6, sample_period=CONTROL_PERIOD)
"""The UR3e has every feature of the table; servoJ at the e-Series' 500 Hz."""
