"""Dashboard Server (port 29999) of the simulator: PolyScope 5.x commands and replies.

One request line, one reply line. In Local control the commands that act on the robot
or its program are refused with :data:`LOCAL_REFUSAL`; queries always work.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, ClassVar

from fxcell.protocol import RobotMode, SafetyMode
from fxcell.sim.constants import (
    POLYSCOPE_BUILD_DATE,
    POLYSCOPE_VERSION,
    ROBOT_MODEL,
    SERIAL_NUMBER,
)
from fxcell.sim.controller import program_name

if TYPE_CHECKING:
    from fxcell.sim.controller import Controller

log = logging.getLogger(__name__)

BANNER = "Connected: Universal Robots Dashboard Server"
LOCAL_REFUSAL = (
    "Command is not allowed due to safety reasons, please switch robot to Remote Control "
    "mode and reconnect to port 29999"
)
VERSION_TEXT = ".".join(str(v) for v in POLYSCOPE_VERSION)
POLYSCOPE_TEXT = f"URSoftware {VERSION_TEXT} ({POLYSCOPE_BUILD_DATE:%b %d %Y})"
# Commands refused in Local control (the robot or its program would change).
REMOTE_ONLY = (
    "power on",
    "power off",
    "brake release",
    "load",
    "play",
    "stop",
    "pause",
    "unlock protective stop",
    "restart safety",
    "shutdown",
    "set operational mode",
    "clear operational mode",
)


def _mode_name(mode: RobotMode | SafetyMode) -> str:
    return mode.name


class Dashboard:
    """Dashboard command interpreter bound to one controller."""

    def __init__(self, controller: Controller) -> None:
        self.c = controller

    def reply(self, line: str, peer_host: str = "127.0.0.1") -> tuple[str, bool]:
        """The reply to one request line and whether to close the connection after it."""
        text = line.strip()
        lower = text.lower()
        c = self.c
        if not c.remote_control and any(
            lower == cmd or lower.startswith(cmd + " ") for cmd in REMOTE_ONLY
        ):
            return LOCAL_REFUSAL, False
        if lower == "quit":
            return "Disconnected", True
        if lower == "shutdown":
            return "Shutting down", True
        handler = self._simple.get(lower)
        if handler is not None:
            return handler(self), False
        if lower.startswith("load installation"):
            path = text[len("load installation") :].strip()
            outcome = c.load_installation(path)
            if outcome == "loaded":
                return f"Loading installation: {path}", False
            if outcome == "missing":
                return f"File not found: {path}", False
            return f"Failed to load installation: {path}", False
        if lower.startswith("load "):
            outcome, full = c.load_program(text[5:].strip())
            if outcome == "loaded":
                return f"Loading program: {full}", False
            if outcome == "missing":
                return f"File not found: {full}", False
            return f"Error while loading program: {full}", False
        if lower == "play":
            c.client_host = peer_host
            return ("Starting program" if c.play() else "Failed to execute: play"), False
        if lower.startswith("popup "):
            return "showing popup", False
        if lower.startswith("addtolog"):
            message = text[len("addToLog") :].strip()
            if not message:
                return "No log message to add", False
            c.log_messages.append(message)
            return "Added log message", False
        if lower.startswith("set operational mode "):
            mode = text[len("set operational mode ") :].strip().lower()
            if mode not in ("manual", "automatic"):
                return f"Failed setting operational mode: '{mode}'", False
            c.operational_mode = mode.upper()
            return f"Operational mode '{mode}' is set", False
        if lower.startswith("generate support file"):
            return "Completed successfully: ur_simulated_support_file.zip", False
        return f"could not understand: '{text}'", False

    # ------------------------------------------------------------------ simple commands

    def _power_on(self) -> str:
        self.c.power_on()
        return "Powering on"

    def _power_off(self) -> str:
        self.c.power_off()
        return "Powering off"

    def _brake_release(self) -> str:
        self.c.brake_release()
        return "Brake releasing"

    def _stop(self) -> str:
        # "Stopped" also when nothing runs: ur_rtde's reuploadScript() sends stopScript and
        # then "stop", and raises unless the reply is exactly "Stopped".
        self.c.stop("stopped by the dashboard")
        return "Stopped"

    def _pause(self) -> str:
        return "Pausing program" if self.c.pause() else "Failed to execute: pause"

    def _unlock(self) -> str:
        why = self.c.unlock_protective_stop()
        return why if why is not None else "Protective stop releasing"

    def _restart_safety(self) -> str:
        self.c.restart_safety()
        return "Restarting safety"

    def _program_state(self) -> str:
        return f"{self.c.program_state_name} {program_name(self.c.loaded_program)}"

    def _running(self) -> str:
        return f"Program running: {'true' if self.c.program_state_name == 'PLAYING' else 'false'}"

    def _loaded(self) -> str:
        p = self.c.loaded_program
        return f"Loaded program: {p}" if p else "No program loaded"

    def _saved(self) -> str:
        flag = "true" if self.c.program_saved else "false"
        return f"{flag} {program_name(self.c.loaded_program)}"

    def _clear_operational_mode(self) -> str:
        mode = self.c.operational_mode.lower()
        self.c.operational_mode = "NONE"
        return (
            "No longer controlling the operational mode. "
            f"Current operational mode: '{mode if mode != 'none' else 'automatic'}'."
        )

    _simple: ClassVar[dict[str, Callable[[Dashboard], str]]] = {
        "power on": _power_on,
        "power off": _power_off,
        "brake release": _brake_release,
        "stop": _stop,
        "pause": _pause,
        "unlock protective stop": _unlock,
        "restart safety": _restart_safety,
        "close safety popup": lambda self: "closing safety popup",
        "close popup": lambda self: "closing popup",
        "robotmode": lambda self: f"Robotmode: {_mode_name(self.c.robot_mode)}",
        "safetymode": lambda self: f"Safetymode: {_mode_name(self.c.safety_mode)}",
        "safetystatus": lambda self: f"Safetystatus: {_mode_name(self.c.safety_mode)}",
        "programstate": _program_state,
        "running": _running,
        "get loaded program": _loaded,
        "isprogramsaved": _saved,
        "polyscopeversion": lambda self: POLYSCOPE_TEXT,
        "version": lambda self: f"Version: {VERSION_TEXT}",
        "get serial number": lambda self: SERIAL_NUMBER,
        "get robot model": lambda self: ROBOT_MODEL,
        "is in remote control": lambda self: "true" if self.c.remote_control else "false",
        "get operational mode": lambda self: self.c.operational_mode,
        "savelog": lambda self: "Log saved to disk",
        "clear operational mode": _clear_operational_mode,
    }


class DashboardConnection(asyncio.Protocol):
    """One Dashboard client: banner, then one reply per line."""

    def __init__(self, dashboard: Dashboard, on_shutdown: Callable[[], None]) -> None:
        self.dashboard = dashboard
        self.on_shutdown = on_shutdown
        self.transport: asyncio.Transport | None = None
        self.buffer = b""
        self.peer_host = "127.0.0.1"

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        peer = transport.get_extra_info("peername")
        if peer:
            self.peer_host = peer[0]
        transport.write((BANNER + "\n").encode())

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        while self.transport is not None and b"\n" in self.buffer:
            raw, self.buffer = self.buffer.split(b"\n", 1)
            line = raw.decode("utf-8", "replace").rstrip("\r")
            if not line.strip():
                continue
            answer, close = self.dashboard.reply(line, self.peer_host)
            log.debug("dashboard %r -> %r", line, answer)
            self.transport.write((answer + "\n").encode())
            if close:
                self.transport.close()
                self.transport = None
                if line.strip().lower() == "shutdown":
                    self.on_shutdown()

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None
