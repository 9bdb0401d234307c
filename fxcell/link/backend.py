"""What the Cell and the move runner need from a robot link: :class:`LinkBackend`.

The contract is robot-neutral and typed: one method per operation (never an operation
named by a string, no vendor protocol's words), the value types and the stop reasons of
:mod:`fxcell.link.contract`. What a robot kind can do (its joints, its trajectory sample
period, the commands it refuses) is :mod:`fxcell.link.capabilities`; a kind's link
factory, kinematic model and simulator are registered in :mod:`fxcell.robots`.

:class:`fxcell.link.client.LinkClient` (the supervised ur_rtde process) is the production
backend; ``fxcell.testing.FakeRobot`` provides an in-process one for fast unit tests. A
:class:`fxcell.cell.Cell` takes a :class:`LinkFactory` (``Cell(link_factory=...)``) to use
another backend.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from fxcell.link.contract import (
    ControllerInfo,
    Guard,
    LinkStatus,
    OutputGroup,
    StopReason,
    TrajectoryProgress,
    TrajectoryResult,
)

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from fxcell.config import RobotConfig
    from fxcell.link.subscription import StateSubscription
    from fxcell.protocol import RobotState
    from fxcell.results import ProgramStatus

__all__ = [
    "ArmCalibration",
    "ControllerInfo",
    "Guard",
    "LinkBackend",
    "LinkFactory",
    "LinkStatus",
    "StopReason",
    "TrajectoryProgress",
    "TrajectoryResult",
    "TrajectoryRun",
]


class ArmCalibration(Protocol):
    """An arm's calibration, of whatever form its kind's kinematic model factory takes
    (:mod:`fxcell.robots`; a UR's: :class:`fxcell.calibration.Calibration`, DH deltas).
    The Cell shows which one it plans on by these."""

    @property
    def checksum(self) -> str:
        """Equal for equal calibrations (``fxcell info``, the status, the page)."""

    @property
    def is_nominal(self) -> bool:
        """The arm as its maker publishes it (no corrections)."""

    def summary(self) -> dict[str, object]:
        """The calibration as plain data (MCAP metadata, JSON, the CLI)."""


class TrajectoryRun(Protocol):
    """A trajectory being streamed (see :class:`fxcell.link.client.TrajectoryHandle`)."""

    @property
    def done(self) -> bool: ...

    @property
    def progress(self) -> TrajectoryProgress | None:
        """The newest progress report (sample index, actual joints, tracking error)."""

    async def replace_remaining(self, samples: ArrayLike, at_index: int | None = None) -> bool:
        """Replace the samples not yet sent (from ``at_index``); False once it has ended."""

    async def stop(self, reason: StopReason = StopReason.STOP_REQUESTED) -> TrajectoryResult:
        """Brake to rest along the path and wait for the end report."""

    async def wait(self) -> TrajectoryResult:
        """Wait for the end: completed, stopped or failed."""

    async def next_progress(self) -> TrajectoryProgress | None:
        """Wait for the next progress report (``None`` once ended)."""


class LinkBackend(Protocol):
    """A robot link as the Cell and the move runner use it.

    State samples, link status and external-control changes are reported through the
    ``on_state``/``on_status``/``on_control`` callbacks given to the :class:`LinkFactory`.
    """

    @property
    def latest(self) -> RobotState | None:
        """The newest state sample (``None`` while the link is down)."""

    @property
    def control_ready(self) -> bool:
        """External control runs and accepts commands."""

    @property
    def up(self) -> bool:
        """State samples arrive."""

    @property
    def messages_sent(self) -> int:
        """Requests sent to the robot so far (calls and trajectory messages; not the
        Local/Remote query of the cell's background poll, see ``contract.counts_as_sent``)."""

    async def start(self, wait: bool = True) -> None:
        """Connect; with ``wait`` return once the link is up (or raise)."""

    async def close(self) -> None:
        """Disconnect for good."""

    # Each request below fails with a typed fxcell error (RobotCommandError,
    # RobotTimeoutError after ``within`` s, ConnectionLostError, ...).

    # The controller's operations. A kind does them with its own protocol (the UR with
    # Dashboard lines, fxcell.link.dashboard); a kind that lacks one says so in its
    # capabilities (fxcell.link.capabilities) and the Cell never calls it.

    async def power(self, on: bool, within: float = 5.0) -> None:
        """Power the arm on (to idle, brakes engaged) or off; NotInRemoteControlError
        when the pendant refuses it."""

    async def release_brakes(self, within: float = 5.0) -> None:
        """Release the brakes of a powered arm."""

    async def remote_control(self, within: float = 5.0) -> bool:
        """Whether the robot takes commands from the network (a UR pendant in Remote)."""

    async def unlock_protective_stop(self, within: float = 5.0) -> bool:
        """Unlock a protective stop: True once released, False while the controller still
        holds it (too soon); RobotCommandError for another refusal."""

    async def program_status(self, within: float = 5.0) -> ProgramStatus:
        """The controller's program state and the program loaded."""

    async def shutdown(self, within: float = 5.0) -> None:
        """Shut the controller down (the link goes down with it)."""

    async def controller_info(self, within: float = 5.0) -> ControllerInfo:
        """Controller version, serial number and model (a field it cannot read: None)."""

    async def read_calibration(self) -> ArmCalibration:
        """The arm's factory calibration as the controller reports it, in the form the
        kind's kinematic model factory takes (:mod:`fxcell.robots`; a UR: the primary
        interface's DH deltas); CalibrationError when it cannot be read."""

    async def enable_control(self, within: float) -> None:
        """Start external control (how: the driver's configuration, e.g. the UR's script
        upload or URCap program); return once it accepts commands."""

    async def disable_control(self, within: float = 5.0) -> None:
        """Stop external control (braking a running trajectory first)."""

    async def servo_stop(self, within: float = 5.0) -> bool:
        """Brake any streamed trajectory and leave servo mode."""

    async def set_output(
        self, group: OutputGroup, index: int, value: float, within: float = 5.0
    ) -> bool:
        """Set a digital (0/1) or analog (fraction of its range) output; False if refused."""

    async def set_tool(
        self,
        tcp: tuple[float, ...],
        mass: float,
        cog: tuple[float, float, float],
        within: float = 5.0,
    ) -> bool:
        """Set the TCP (flange frame, UR pose) and the payload (kg, centre of gravity m)."""

    async def teach_mode(self, on: bool, within: float = 5.0) -> bool:
        """Enter (``on``) or leave teach mode (freedrive: the arm moved by hand)."""

    async def execute_trajectory(
        self,
        samples: ArrayLike,
        *,
        lookahead_time: float = 0.1,
        gain: float = 300.0,
        guard: Guard | None = None,
    ) -> TrajectoryRun:
        """Stream ``samples``, (N, joints) joint positions ``sample_period`` apart, both
        from the kind's :class:`~fxcell.link.capabilities.RobotCapabilities` (a UR3e:
        6 joints, 2 ms, sent with servoJ); ``lookahead_time`` and ``gain`` tune a
        servo that takes them (others ignore them)."""

    def subscribe(self, maxsize: int = 1024) -> StateSubscription:
        """An async iterator over every state sample (use as a context manager)."""


class LinkFactory(Protocol):
    """Makes the Cell's link: ``factory(host, robot, on_state=, on_status=, on_control=)``.

    ``host`` is ``None`` only for backends that need no controller address.
    """

    def __call__(
        self,
        host: str | None,
        robot: RobotConfig,
        *,
        on_state: Callable[[RobotState], None],
        on_status: Callable[[LinkStatus, str], None],
        on_control: Callable[[bool, str], None],
    ) -> LinkBackend: ...
