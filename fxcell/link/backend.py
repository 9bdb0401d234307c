"""What the Cell and the move runner need from a robot link: :class:`LinkBackend`.

The contract is robot-neutral and typed: one method per operation (never an operation
named by a string), the value types and the stop reasons of :mod:`fxcell.link.contract`.

:class:`fxcell.link.client.LinkClient` (the supervised ur_rtde process) is the production
backend; ``fxcell.testing.FakeRobot`` provides an in-process one for fast unit tests. A
:class:`fxcell.cell.Cell` takes a :class:`LinkFactory` (``Cell(link_factory=...)``) to use
another backend.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from fxcell.link.contract import (
    ControlMode,
    Guard,
    LinkStatus,
    OutputGroup,
    StopReason,
    TrajectoryProgress,
    TrajectoryResult,
)

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from fxcell.calibration import Calibration
    from fxcell.config import RobotConfig
    from fxcell.link.subscription import StateSubscription
    from fxcell.protocol import RobotState

__all__ = [
    "Guard",
    "LinkBackend",
    "LinkFactory",
    "LinkStatus",
    "StopReason",
    "TrajectoryProgress",
    "TrajectoryResult",
    "TrajectoryRun",
]


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
        """Requests sent to the robot so far (calls and trajectory messages)."""

    async def start(self, wait: bool = True) -> None:
        """Connect; with ``wait`` return once the link is up (or raise)."""

    async def close(self) -> None:
        """Disconnect for good."""

    # Each request below fails with a typed fxcell error (RobotCommandError,
    # RobotTimeoutError after ``within`` s, ConnectionLostError, ...).

    async def dashboard(self, command: str, within: float = 5.0) -> str:
        """Send one Dashboard request line; returns the reply line."""

    async def read_calibration(self) -> Calibration:
        """The arm's factory calibration as the controller reports it (the primary
        interface's kinematics info); CalibrationError when it cannot be read."""

    async def start_control(self, mode: ControlMode, program: str, within: float) -> None:
        """Start external control: ``script`` upload or ``urcap`` program."""

    async def stop_control(self, mode: ControlMode, within: float = 5.0) -> None:
        """Stop external control."""

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
        """Stream (N, 6) joint positions spaced 2 ms apart with servoJ."""

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
