"""The UR link's typed controller operations over Dashboard lines
(``fxcell.link.dashboard.DashboardOperations``, used by LinkClient and FakeLink).

A scripted Dashboard stands in for the controller: each test gives the replies a real
Dashboard server gives (the simulator's texts, ``fxcell.sim.dashboard``) and checks what
the typed operation sends and how it reads the reply.
"""

from __future__ import annotations

import pytest

from fxcell.errors import (
    ConnectionLostError,
    NotInRemoteControlError,
    RobotCommandError,
    RobotTimeoutError,
)
from fxcell.link.contract import ControllerInfo, ControlMode
from fxcell.link.dashboard import DashboardOperations
from fxcell.protocol import ProgramState
from fxcell.results import ProgramStatus
from fxcell.sim.dashboard import LOCAL_REFUSAL


class ScriptedDashboard(DashboardOperations):
    """Answers each Dashboard line from ``replies`` (an exception: raised, after the line
    counts as sent unless ``unsent``)."""

    def __init__(
        self, replies: dict[str, str | Exception], *, unsent: bool = False, **config: str
    ) -> None:
        self.replies = replies
        self.unsent = unsent
        self.sent: list[str] = []
        self.controls: list[tuple[str, ControlMode, str]] = []
        if "control_mode" in config:
            self.control_mode = "urcap" if config["control_mode"] == "urcap" else "script"
        if "urcap_program" in config:
            self.urcap_program = config["urcap_program"]

    def _requests_sent(self) -> int:
        return len(self.sent)

    async def dashboard(self, command: str, within: float = 5.0) -> str:
        reply = self.replies[command]
        if not (isinstance(reply, Exception) and self.unsent):
            self.sent.append(command)
        if isinstance(reply, Exception):
            raise reply
        return reply

    async def start_control(self, mode: ControlMode, program: str, within: float) -> None:
        self.controls.append(("start", mode, program))

    async def stop_control(self, mode: ControlMode, within: float = 5.0) -> None:
        self.controls.append(("stop", mode, ""))


@pytest.mark.parametrize(
    ("call", "line", "confirmation"),
    [
        ("power on", "power on", "Powering on"),
        ("power off", "power off", "Powering off"),
        ("release", "brake release", "Brake releasing"),
    ],
)
async def test_power_and_brakes_send_the_dashboards_words_and_check_its_confirmation(
    call: str, line: str, confirmation: str
) -> None:
    async def run(link: ScriptedDashboard) -> None:
        if call == "release":
            await link.release_brakes()
        else:
            await link.power(call == "power on")

    link = ScriptedDashboard({line: confirmation})
    await run(link)
    assert link.sent == [line]
    with pytest.raises(NotInRemoteControlError, match="Remote Control"):
        await run(ScriptedDashboard({line: LOCAL_REFUSAL}))
    with pytest.raises(RobotCommandError, match="controller replied"):
        await run(ScriptedDashboard({line: "Failed to execute: " + line}))


@pytest.mark.parametrize(("reply", "remote"), [("true", True), ("false", False), ("", False)])
async def test_remote_control_reads_the_pendants_switch(reply: str, remote: bool) -> None:
    link = ScriptedDashboard({"is in remote control": reply + "\n"})
    assert await link.remote_control() is remote


@pytest.mark.parametrize(
    ("reply", "released"),
    [
        ("Protective stop releasing", True),
        ("Cannot unlock protective stop until 5s after occurrence. Always inspect cause", False),
        ("Cannot unlock protective stop, safetymode is not PROTECTIVE_STOP", False),
    ],
)
async def test_unlock_says_released_or_held_by_the_five_second_rule(
    reply: str, released: bool
) -> None:
    link = ScriptedDashboard({"unlock protective stop": reply})
    assert await link.unlock_protective_stop() is released


async def test_unlock_refused_otherwise_is_a_command_error() -> None:
    link = ScriptedDashboard({"unlock protective stop": LOCAL_REFUSAL})
    with pytest.raises(RobotCommandError, match="unlock protective stop failed"):
        await link.unlock_protective_stop()


async def test_program_status_is_typed_from_the_program_state_reply() -> None:
    link = ScriptedDashboard({"programState": "PLAYING external_control.urp\n"})
    assert await link.program_status() == ProgramStatus(
        ProgramState.PLAYING, "external_control.urp"
    )
    with pytest.raises(RobotCommandError, match="unexpected programState"):
        await ScriptedDashboard({"programState": "RUNNING x"}).program_status()


async def test_shutdown_whose_reply_is_lost_with_the_controller_counts_as_done() -> None:
    await ScriptedDashboard({"shutdown": "Shutting down"}).shutdown()
    # the line left, then the controller went down before replying: the effect asked
    await ScriptedDashboard({"shutdown": ConnectionLostError("gone")}).shutdown()
    with pytest.raises(ConnectionLostError):  # never sent: the link was down already
        await ScriptedDashboard({"shutdown": ConnectionLostError("down")}, unsent=True).shutdown()
    with pytest.raises(RobotCommandError):
        await ScriptedDashboard({"shutdown": LOCAL_REFUSAL}).shutdown()


async def test_controller_info_leaves_out_what_it_cannot_read(
    caplog: pytest.LogCaptureFixture,
) -> None:
    link = ScriptedDashboard(
        {
            "PolyscopeVersion": "URSoftware 5.11.1",
            "get serial number": RobotTimeoutError("no reply"),
            "get robot model": "UR3",
        }
    )
    info = await link.controller_info()
    assert info == ControllerInfo("URSoftware 5.11.1", None, "UR3")
    assert info.as_dict() == {"controller_version": "URSoftware 5.11.1", "robot_model": "UR3"}
    assert "serial" in caplog.text


async def test_enable_and_disable_control_use_the_configured_ur_mode() -> None:
    default = ScriptedDashboard({})
    await default.enable_control(10.0)
    await default.disable_control()
    assert default.controls == [
        ("start", "script", "external_control.urp"),
        ("stop", "script", ""),
    ]
    urcap = ScriptedDashboard({}, control_mode="urcap", urcap_program="cell.urp")
    await urcap.enable_control(10.0)
    assert urcap.controls == [("start", "urcap", "cell.urp")]
