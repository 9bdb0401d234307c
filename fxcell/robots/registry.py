"""The registry of robot kinds: :class:`RobotKind` by name (``robot.kind``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from fxcell.errors import ConfigError, InvalidArgumentError

if TYPE_CHECKING:
    from fxcell.calibration import Calibration
    from fxcell.config import CellConfig
    from fxcell.link.backend import LinkFactory
    from fxcell.link.capabilities import RobotCapabilities
    from fxcell.motion.kinematics import Kinematics

__all__ = [
    "KinematicsFactory",
    "RobotKind",
    "Simulator",
    "SimulatorLauncher",
    "kind_names",
    "register",
    "robot_kind",
    "unregister",
]

KinematicsFactory = Callable[["CellConfig", "Calibration | None"], "Kinematics"]
"""The arm the planner plans on: ``factory(config, calibration)`` with the configuration's
TCP and limits, and the calibration the link read (None: none read, the nominal model)."""


class Simulator(Protocol):
    """A kind's simulator as the Cell runs it: started in the background, stopped at close."""

    def start(self) -> str:
        """Start it; the controller address the link connects to."""

    def stop(self, timeout: float = 10.0) -> None:
        """Stop it for good."""


SimulatorLauncher = Callable[[Mapping[str, Any]], Simulator]
"""Makes a kind's simulator from the Cell's ``simulator_options`` (not started yet)."""


@dataclass(frozen=True)
class RobotKind:
    """One robot kind: what the Cell needs to drive it, chosen by ``robot.kind``."""

    capabilities: RobotCapabilities
    link: LinkFactory
    kinematics: KinematicsFactory
    simulator: SimulatorLauncher | None = None
    """None: the kind has no simulator (a controller address must be configured)."""

    @property
    def name(self) -> str:
        return self.capabilities.kind


_KINDS: dict[str, RobotKind] = {}


def register(kind: RobotKind) -> None:
    """Add ``kind`` (InvalidArgumentError if its name is taken)."""
    if kind.name in _KINDS:
        raise InvalidArgumentError(f"robot kind {kind.name!r} is registered already")
    _KINDS[kind.name] = kind


def unregister(name: str) -> None:
    """Remove the kind ``name`` (tests that registered one)."""
    _KINDS.pop(name, None)


def kind_names() -> tuple[str, ...]:
    """The names of the registered kinds."""
    return tuple(_KINDS)


def robot_kind(name: str) -> RobotKind:
    """The kind ``robot.kind`` names; ConfigError for a kind fxcell does not drive."""
    kind = _KINDS.get(name)
    if kind is None:
        raise ConfigError(
            f"robot.kind: {name!r} is not a robot kind fxcell drives "
            f"(known: {', '.join(sorted(_KINDS))})"
        )
    return kind
