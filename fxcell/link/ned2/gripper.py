"""The Ned2's gripper (Niryo's Gripper 1) as ``cell.gripper`` drives it: a
:class:`~fxcell.link.gripper.GripperDriver` over the robot's TCP server (port 40001, the
protocol pyniryo speaks), one short connection per command.

- **Commands**: ``OPEN_GRIPPER`` / ``CLOSE_GRIPPER`` (speed, max torque %, hold torque %:
  pyniryo's defaults; a Ned2 ignores the speed). The robot answers once the fingers have
  stopped. The gripper has two positions only, fully open and closed, and no setting in
  m/s or N: the spec (:data:`GRIPPER_1`) says so and the Cell refuses anything else.
- **Grasp detection**: Gripper 1 tells nothing about an object itself (its close answers
  "Successfully closed gripper" either way); what it does tell is where its motor stopped
  (``GET_CURRENT_TOOL_POSITION``, in motor steps). Fingers that stop clearly short of the
  closed position (:data:`HOLD_MARGIN` of the stroke) are holding something; an object
  thinner than that margin (about a millimetre) reads as nothing.
- **Activation**: there is none: ``activate`` scans the tool port (``UPDATE_TOOL``) and
  checks that a Gripper 1 is mounted; a missing tool reads as not active.

Why the TCP server and one connection per command: it has the tool commands and the tool
position (the rosbridge's tools action has the commands only), and it serves one client at
a time, so fxcell holds it only for the few milliseconds of a command (the link's stop and
state go through the rosbridge). An operator's pyniryo session holding it makes the
gripper's commands wait and time out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from fxcell.errors import GripperError, RobotCommandError
from fxcell.link.gripper import GripperReading, GripperSpec
from fxcell.link.ned2.tcp import NiryoTcpClient
from fxcell.results import GripResult

__all__ = ["GRIPPER_1", "GRIPPER_1_STEPS", "Ned2Gripper", "ned2_gripper"]

GRIPPER_1 = GripperSpec(
    name="Gripper 1",
    stroke=0.027,
    speed_range=None,
    force_range=None,
    default_speed=None,
    default_force=None,
    continuous=False,
    detects_objects=True,
)
"""Niryo's Gripper 1: about 27 mm between closed and open fingers, two positions, no speed
or force in SI units; an object is told by where the fingers stop."""
GRIPPER_1_STEPS = (900, 2200)
"""Gripper 1's motor positions (closed, open) in steps, as Niryo's ``tools_definition.yaml``
(ned2) gives them; used when the robot does not answer ``GET_GRIPPER_SPECS``."""
HOLD_MARGIN = 0.04
"""Fraction of the stroke short of either end at which stopped fingers count as holding."""
OPEN_ARGS = (500, 100, 30)  # speed, max torque %, hold torque %: pyniryo's defaults
CLOSE_ARGS = (500, 100, 20)
TOOL = "GRIPPER_1"
COMMAND_TIMEOUT = 5.0  # s for a command that does not move the fingers


@dataclass(frozen=True)
class _Steps:
    closed: int
    opened: int

    def width(self, position: float) -> float:
        span = self.opened - self.closed
        fraction = (position - self.closed) / span if span else 0.0
        return GRIPPER_1.stroke * min(1.0, max(0.0, fraction))

    def holding(self, position: float) -> bool:
        margin = HOLD_MARGIN * abs(self.opened - self.closed)
        lo, hi = sorted((self.closed, self.opened))
        return lo + margin < position < hi - margin


class Ned2Gripper:
    """Gripper 1 on the Ned2 at ``host`` (see the module's docstring)."""

    def __init__(self, host: str, port: int | None = None) -> None:
        self.host = host
        self.port = port
        self._steps: _Steps | None = None

    @property
    def spec(self) -> GripperSpec:
        return GRIPPER_1

    async def _session(self, within: float) -> NiryoTcpClient:
        tcp = (
            NiryoTcpClient(self.host) if self.port is None else NiryoTcpClient(self.host, self.port)
        )
        await tcp.connect(within)
        return tcp

    async def _tool(self, tcp: NiryoTcpClient) -> str:
        values = (await tcp.command("GET_CURRENT_TOOL_ID", within=COMMAND_TIMEOUT)).values
        return str(values[0]) if values else "NONE"

    async def _position(self, tcp: NiryoTcpClient) -> float:
        values = (await tcp.command("GET_CURRENT_TOOL_POSITION", within=COMMAND_TIMEOUT)).values
        if len(values) != 1 or not isinstance(values[0], int | float):
            raise GripperError(f"the Ned2 answered {values!r} for the tool's position")
        return float(values[0])

    async def _read_steps(self, tcp: NiryoTcpClient) -> _Steps:
        if self._steps is None:
            try:
                answer = (
                    await tcp.command("GET_GRIPPER_SPECS", TOOL, within=COMMAND_TIMEOUT)
                ).values
                closed, opened = (int(v) for v in answer[0])
                self._steps = _Steps(closed, opened)
            except (RobotCommandError, TypeError, ValueError, IndexError):
                self._steps = _Steps(*GRIPPER_1_STEPS)  # an older robot: Niryo's values
        return self._steps

    async def read(self) -> GripperReading:
        tcp = await self._session(COMMAND_TIMEOUT)
        try:
            tool = await self._tool(tcp)
            if tool != TOOL:
                return GripperReading(False, 0, 0.0, False)
            steps = await self._read_steps(tcp)
            position = await self._position(tcp)
        finally:
            await tcp.close()
        return GripperReading(True, 0, steps.width(position), steps.holding(position))

    async def activate(self, within: float, guard: Callable[[], None]) -> None:
        tcp = await self._session(within)
        try:
            await tcp.command("UPDATE_TOOL", within=within)
            tool = await self._tool(tcp)
        finally:
            await tcp.close()
        if tool != TOOL:
            raise GripperError(
                f"the Ned2 carries {tool.replace('_', ' ').lower()}, not a Gripper 1 "
                "(mount it on the tool port, then activate again)"
            )

    async def move(
        self,
        width: float,
        speed: float | None,
        force: float | None,
        *,
        within: float,
        guard: Callable[[], None],
    ) -> GripResult:
        close = width < GRIPPER_1.stroke / 2
        tcp = await self._session(within)
        try:
            steps = await self._read_steps(tcp)
            command, args = ("CLOSE_GRIPPER", CLOSE_ARGS) if close else ("OPEN_GRIPPER", OPEN_ARGS)
            try:
                await tcp.command(command, *args, within=within)
            except RobotCommandError as exc:
                raise GripperError(f"the Ned2 refused {command}: {exc}") from None
            position = await self._position(tcp)
        finally:
            await tcp.close()
        return GripResult(steps.width(position), close and steps.holding(position))

    async def halt(self) -> None:
        """Gripper 1 has no stop: a cancelled command's fingers finish their stroke."""

    async def close(self) -> None:
        """Nothing held open between commands."""


def ned2_gripper(host: str) -> Ned2Gripper:
    """The Ned2 kind's gripper factory."""
    return Ned2Gripper(host)
