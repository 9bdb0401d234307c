"""The registry of robot kinds: :class:`RobotKind` by name (``robot.kind``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from fxcell.errors import ConfigError, InvalidArgumentError

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import ArrayLike, NDArray

    from fxcell.config import CellConfig
    from fxcell.geometry import Pose
    from fxcell.link.backend import ArmCalibration, LinkFactory
    from fxcell.link.capabilities import RobotCapabilities
    from fxcell.link.gripper import GripperFactory
    from fxcell.motion.execution import ExecutionOptions
    from fxcell.robots.description import ArmDescription

__all__ = [
    "CalibrationFormat",
    "CollisionFactory",
    "CollisionModel",
    "DescriptionFactory",
    "KinematicModel",
    "KinematicsFactory",
    "RobotKind",
    "Simulator",
    "SimulatorLauncher",
    "kind_names",
    "register",
    "robot_kind",
    "unregister",
]


class KinematicModel(Protocol):
    """The arm as the planner plans on it: joint vectors as wide as the kind's
    capabilities say, poses of the TCP in the robot's base frame (the UR3e's:
    :class:`fxcell.motion.kinematics.Kinematics`)."""

    @property
    def reach(self) -> float:
        """No TCP position farther than this from the base origin is reachable (m)."""

    def forward(self, q: ArrayLike) -> Pose:
        """The TCP pose at joints ``q``."""

    def inverse(self, pose: Pose, seed: ArrayLike | None = None) -> NDArray[np.float64]:
        """The joints within the limits reaching ``pose`` nearest ``seed``
        (UnreachableError when there are none)."""

    def inverse_near(self, pose: Pose, seed: ArrayLike) -> NDArray[np.float64]:
        """The solution continuous with ``seed``, for a path's next point (a straight
        line's knots and samples): the nearest where the seed is close, found as fast as
        the model can (UnreachableError when there is none)."""

    def inverse_all(self, pose: Pose, seed: ArrayLike | None = None) -> list[NDArray[np.float64]]:
        """Every solution within the limits (one per branch), nearest ``seed`` first."""


class CollisionModel(Protocol):
    """The arm and the cell's scene as the planner checks them (the UR3e's:
    :class:`fxcell.motion.collision.CollisionChecker`)."""

    def in_collision(self, q: ArrayLike) -> bool:
        """Whether the arm at joints ``q`` touches the scene or itself."""

    def colliding_pairs(self, q: ArrayLike) -> list[tuple[str, str]]:
        """The bodies in contact at ``q`` (for error messages)."""

    def check(self, q: ArrayLike, what: str = "target") -> None:
        """CollisionError naming ``what`` when ``q`` collides."""

    def first_collision(self, samples: ArrayLike) -> int | None:
        """Index of the first colliding state among consecutive ``samples``, or None."""

    def motion_free(self, start: ArrayLike, end: ArrayLike) -> bool:
        """Whether the straight joint line from ``start`` to ``end`` is free."""

    def separating_wall(self, start: ArrayLike, end: ArrayLike) -> tuple[int, float] | None:
        """A joint value every configuration collides at which lies between ``start`` and
        ``end`` (``(joint, value)``; None: none known): no path can exist."""

    def attach(self, kind: str) -> None:
        """The gripper now holds an object of ``kind`` (of the layout's objects)."""

    def detach(self) -> None:
        """The gripper holds nothing."""


KinematicsFactory = Callable[["CellConfig", "ArmCalibration | None"], KinematicModel]
"""The arm the planner plans on: ``factory(config, calibration)`` with the configuration's
TCP and limits, and the calibration the link read or :class:`CalibrationFormat` made (None:
none, the model as ``robot.calibration`` says; a kind's factory refuses a calibration of
another kind with CalibrationError)."""

CollisionFactory = Callable[["CellConfig"], CollisionModel]
"""The arm's collision bodies in the configured scene (``config.scene``, the layout's
objects for :meth:`CollisionModel.attach`)."""


@dataclass(frozen=True)
class CalibrationFormat:
    """A kind's calibrations apart from the one its link reads
    (:meth:`~fxcell.link.backend.LinkBackend.read_calibration`)."""

    nominal: Callable[[], ArmCalibration]
    """The arm as its maker publishes it (``robot.calibration: nominal``, the fallback)."""
    load: Callable[[str], ArmCalibration]
    """Read a calibration file (``robot.calibration: <path>``); CalibrationError when it
    cannot be read."""


class Simulator(Protocol):
    """A kind's simulator as the Cell runs it: started in the background, stopped at close."""

    def start(self) -> str:
        """Start it; the controller address the link connects to."""

    def stop(self, timeout: float = 10.0) -> None:
        """Stop it for good."""


SimulatorLauncher = Callable[[Mapping[str, Any]], Simulator]
"""Makes a kind's simulator from the Cell's ``simulator_options`` (not started yet)."""

DescriptionFactory = Callable[["Pose"], "ArmDescription"]
"""The arm for the views (the page's arm view, the recorder's frames and URDF):
``factory(tcp)`` with the configured TCP in the kind's tool frame."""


@dataclass(frozen=True)
class RobotKind:
    """One robot kind: what the Cell needs to drive it, chosen by ``robot.kind``."""

    capabilities: RobotCapabilities
    link: LinkFactory
    kinematics: KinematicsFactory
    collision: CollisionFactory
    calibration: CalibrationFormat
    simulator: SimulatorLauncher | None = None
    """None: the kind has no simulator (a controller address must be configured)."""
    execution: ExecutionOptions | None = None
    """How its link takes a streamed plan: servo lookahead and gain, whether setpoints lead
    the servo's lag, settling (None: the defaults, made for a UR's servoJ)."""
    description: DescriptionFactory | None = None
    """The arm's frames and URDF for the page and the recorder (None: they draw no arm)."""
    gripper: GripperFactory | None = None
    """Its gripper's driver for a controller address (:mod:`fxcell.link.gripper`; the
    UR3e's: the Robotiq Hand-E through the URCap's socket). None: ``cell.gripper``'s
    commands are refused with UnsupportedCommandError naming the kind."""
    signals: frozenset[str] | None = None
    """The IO addresses (:mod:`fxcell.signals`: ``DI2``, ``DO1``) its controller has and its
    link reads and sets; None: every address :func:`fxcell.signals.parse_signal` takes
    (the UR's). ``cell.io`` refuses a configured signal at another address, naming the
    kind, before anything is sent."""

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
