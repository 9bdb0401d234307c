"""The UR link's controller operations, as UR's Dashboard server does them.

The link contract (:class:`~fxcell.link.backend.LinkBackend`) names typed operations
(``power``, ``release_brakes``, ``remote_control``, ...); a UR does them with Dashboard
request lines. :class:`DashboardOperations` is that mapping, written once for the UR link
client (:class:`fxcell.link.client.LinkClient`) and the in-process fake
(``fxcell.testing.FakeLink``): the Dashboard's words and replies live here and nowhere
above the link. The class using it provides ``dashboard`` (one raw request line, a
UR-only method outside the contract), ``start_control``/``stop_control`` (UR's script or
URCap external control), ``_requests_sent`` and sets the configured ``control_mode`` and
``urcap_program``.
"""

from __future__ import annotations

import logging

from fxcell.errors import (
    ConnectionLostError,
    FxcellError,
    NotInRemoteControlError,
    RobotCommandError,
)
from fxcell.link.contract import REMOTE_QUERY, ControllerInfo, ControlMode
from fxcell.protocol import ProgramState
from fxcell.results import ProgramStatus

__all__ = ["DashboardOperations"]

log = logging.getLogger(__name__)

_LOCAL_CONTROL_MARKERS = ("remote control", "not allowed due to safety")
"""Words of a Dashboard reply refusing a command because the pendant is in Local."""

_INFO_QUERIES = (
    ("controller_version", "PolyscopeVersion"),
    ("serial", "get serial number"),
    ("robot_model", "get robot model"),
)


class DashboardOperations:
    """The contract's controller operations over UR's Dashboard (a mixin)."""

    control_mode: ControlMode = "script"
    """How external control runs: ``script`` (ur_rtde uploads its control script) or
    ``urcap`` (play :attr:`urcap_program`); the UR driver's configuration."""
    urcap_program: str = "external_control.urp"

    async def dashboard(self, command: str, within: float = 5.0) -> str:
        """Send one Dashboard request line; returns the reply line."""
        raise NotImplementedError

    async def start_control(self, mode: ControlMode, program: str, within: float) -> None:
        """Start external control: ``script`` upload or ``urcap`` program."""
        raise NotImplementedError

    async def stop_control(self, mode: ControlMode, within: float = 5.0) -> None:
        """Stop external control."""
        raise NotImplementedError

    def _requests_sent(self) -> int:
        """Requests sent to the robot so far (the contract's ``messages_sent``)."""
        raise NotImplementedError

    async def _checked(self, command: str, expect: str, within: float) -> str:
        """Send ``command``; NotInRemoteControlError if the pendant refused it, else
        RobotCommandError unless the reply holds ``expect``."""
        reply = await self.dashboard(command, within)
        if any(marker in reply.lower() for marker in _LOCAL_CONTROL_MARKERS):
            raise NotInRemoteControlError(f"{command!r} refused: {reply}")
        if expect not in reply:
            raise RobotCommandError(f"{command!r} failed: controller replied {reply!r}")
        return reply

    async def power(self, on: bool, within: float = 5.0) -> None:
        """Power the arm on (to idle, brakes engaged) or off."""
        if on:
            await self._checked("power on", "Powering on", within)
        else:
            await self._checked("power off", "Powering off", within)

    async def release_brakes(self, within: float = 5.0) -> None:
        """Release the brakes of a powered arm (it becomes ready to run)."""
        await self._checked("brake release", "Brake releasing", within)

    async def remote_control(self, within: float = 5.0) -> bool:
        """Whether the teach pendant lets the network command the robot (Remote)."""
        reply = await self.dashboard(REMOTE_QUERY, within)
        return reply.strip().lower() == "true"

    async def unlock_protective_stop(self, within: float = 5.0) -> bool:
        """Unlock a protective stop: True once released, False while the controller still
        holds it (its 5 s rule); RobotCommandError for any other refusal."""
        reply = await self.dashboard("unlock protective stop", within)
        if "releasing" in reply.lower():
            return True
        if "5s" not in reply and "cannot unlock" not in reply.lower():
            raise RobotCommandError(f"unlock protective stop failed: {reply!r}")
        return False

    async def program_status(self, within: float = 5.0) -> ProgramStatus:
        """The controller's program state and loaded program."""
        reply = await self.dashboard("programState", within)
        word, _, program = reply.strip().partition(" ")
        try:
            state = ProgramState(word)
        except ValueError:
            raise RobotCommandError(f"unexpected programState reply {reply!r}") from None
        return ProgramStatus(state, program)

    async def shutdown(self, within: float = 5.0) -> None:
        """Shut the controller down (the link goes down with it)."""
        sent = self._requests_sent()
        try:
            reply = await self.dashboard("shutdown", within)
        except ConnectionLostError:
            if self._requests_sent() == sent:  # never left: the link was already down
                raise
            # The controller went down before its reply reached us: the effect asked.
            reply = "Shutting down"
        if "shutting down" not in reply.lower():
            raise RobotCommandError(f"'shutdown' failed: controller replied {reply!r}")

    async def controller_info(self, within: float = 5.0) -> ControllerInfo:
        """Controller version, serial number and model; a field that cannot be read is
        None (logged: informational only)."""
        values: dict[str, str] = {}
        for key, command in _INFO_QUERIES:
            try:
                values[key] = await self.dashboard(command, within)
            except FxcellError as exc:
                log.warning("could not read %s from the controller: %s", key, exc)
        return ControllerInfo(**values)

    async def enable_control(self, within: float) -> None:
        """Start external control as configured (:attr:`control_mode`); return once it
        accepts commands."""
        await self.start_control(self.control_mode, self.urcap_program, within)

    async def disable_control(self, within: float = 5.0) -> None:
        """Stop external control (braking a running trajectory first)."""
        await self.stop_control(self.control_mode, within)
