"""The robot-link contract: every request has a handler on each side, unknown messages and
another wire version are refused with a typed error, and each stop reason has its error."""

from __future__ import annotations

import argparse
import asyncio
import logging
import socket
from collections.abc import Iterator
from typing import Any

import pytest

from fxcell.cell.statemachine import CellState
from fxcell.errors import (
    ConnectionLostError,
    EmergencyStopError,
    FxcellError,
    LinkBrakeError,
    LinkContractError,
    MoveError,
    MoveStoppedError,
    ProgramStoppedError,
    ProtectiveStopError,
    RobotFaultError,
    SafeguardStopError,
    SafetyStopError,
)
from fxcell.link import process, wire
from fxcell.link.client import LinkClient
from fxcell.link.contract import (
    LINK_BRAKES,
    REQUESTS,
    STATE_STOPS,
    STOP_ERRORS,
    WIRE_VERSION,
    Dashboard,
    Guard,
    Ping,
    ReplaceTrajectory,
    SetOutput,
    StartTrajectory,
    StopReason,
    StopTrajectory,
    TrajectoryResult,
    reply_error,
    stop_reason,
)
from fxcell.protocol import SAFETY_STOPS, RuntimeState, SafetyMode
from fxcell.testing import fake

pytestmark = pytest.mark.timeout(30)


# ----------------------------------------------------------------- requests


@pytest.mark.parametrize("request_type", REQUESTS, ids=lambda t: t.__name__)
def test_the_link_process_has_a_handler_for_every_request(request_type: type) -> None:
    assert request_type in process.HANDLERS, f"link process: no handler for {request_type}"


@pytest.mark.parametrize("request_type", REQUESTS, ids=lambda t: t.__name__)
def test_the_fake_link_has_a_handler_for_every_request(request_type: type) -> None:
    assert request_type in fake.HANDLERS, f"fake link: no handler for {request_type}"


def test_the_handler_tables_hold_nothing_but_requests() -> None:
    assert set(process.HANDLERS) == set(REQUESTS)
    assert set(fake.HANDLERS) == set(REQUESTS)


def test_requests_are_frozen_values_that_survive_the_wire() -> None:
    request = SetOutput("tool", 1, 1.0)
    message = wire.decode(wire.encode((wire.CALL, 7, request))[wire.HEADER.size :])
    assert message == (wire.CALL, 7, request)
    with pytest.raises(AttributeError):
        request.index = 2  # type: ignore[misc]


class _Sent(process.Link):
    """The link process's request side, its messages kept instead of sent."""

    def __init__(self, sock: socket.socket) -> None:
        super().__init__(sock, argparse.Namespace(host="127.0.0.1", beat_fd=None))
        self.sent: list[tuple[Any, ...]] = []

    def send(self, *message: Any) -> None:
        self.sent.append(message)


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    mine, theirs = socket.socketpair()
    with mine, theirs:
        yield mine, theirs


@pytest.fixture
def link(pair: tuple[socket.socket, socket.socket]) -> Iterator[_Sent]:
    link = _Sent(pair[0])
    yield link
    link.outbox.close(1.0)


def test_the_link_process_answers_a_request_by_its_type(link: _Sent) -> None:
    link.answer(3, Ping())
    assert link.sent == [(wire.REPLY, 3, True, "pong")]


def test_the_link_process_refuses_an_unknown_request_with_a_contract_error(
    link: _Sent,
) -> None:
    link.answer(4, ("set_output", {"group": "tool"}))  # the old, untyped call
    [(kind, request_id, ok, (error_kind, text))] = link.sent
    assert (kind, request_id, ok, error_kind) == (wire.REPLY, 4, False, "contract")
    assert isinstance(reply_error(error_kind, text), LinkContractError)
    assert "tuple" in text


def test_the_link_process_refuses_an_unknown_message_and_says_so(link: _Sent) -> None:
    link._dispatch(("call_by_name", 1, "teach_mode"))
    assert [m[0] for m in link.sent] == [wire.LOG]
    assert "unknown message 'call_by_name'" in link.sent[0][2]
    assert link._calls.empty()


async def test_the_fake_link_refuses_an_unknown_request_with_a_contract_error() -> None:
    link = fake.FakeLink(fake.FakeRobot())
    with pytest.raises(LinkContractError):
        await link.request(object())  # type: ignore[arg-type]


async def test_the_fake_link_answers_a_request_by_its_type_once_up() -> None:
    robot = fake.FakeRobot()
    link = fake.FakeLink(robot)
    with pytest.raises(ConnectionLostError):
        await link.request(Dashboard("robotmode"))  # not started: no link
    await link.start()
    try:
        assert await link.request(Ping()) == "pong"
        assert (await link.dashboard("robotmode")).startswith("Robotmode")
    finally:
        await link.close()


# ----------------------------------------------------------------- wire version


async def test_the_client_refuses_a_link_process_of_another_wire_version() -> None:
    client = LinkClient("127.0.0.1")
    client._handle((wire.HELLO, {"pid": 1, "wire": WIRE_VERSION + 1}))
    assert isinstance(client.contract_error, LinkContractError)
    assert f"wire version {WIRE_VERSION + 1}" in str(client.contract_error)
    with pytest.raises(LinkContractError):
        await client.wait_up(5.0)


async def test_the_client_refuses_a_link_process_that_names_no_wire_version() -> None:
    client = LinkClient("127.0.0.1")
    client._handle((wire.HELLO, {"pid": 1}))  # the untyped protocol's HELLO
    with pytest.raises(LinkContractError):
        await client.wait_up(5.0)


async def test_the_client_accepts_a_link_process_of_its_own_wire_version() -> None:
    client = LinkClient("127.0.0.1")
    client._handle((wire.HELLO, {"pid": 1, "wire": WIRE_VERSION}))
    assert client.contract_error is None


async def test_a_contract_reply_reaches_the_caller_as_a_contract_error() -> None:
    client = LinkClient("127.0.0.1")
    future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
    client._pending[9] = future
    client._handle((wire.REPLY, 9, False, ("contract", "no request Foo")))
    with pytest.raises(LinkContractError, match="no request Foo"):
        await future


async def test_the_client_ignores_an_unknown_message_with_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    client = LinkClient("127.0.0.1")
    client._handle(("gossip", 1))
    assert "unknown message 'gossip'" in caplog.text


# ----------------------------------------------------------------- stop reasons

EXPECTED_ERRORS: dict[StopReason, type[FxcellError]] = {
    StopReason.PROTECTIVE_STOP: ProtectiveStopError,
    StopReason.SAFEGUARD_STOP: SafeguardStopError,
    StopReason.EMERGENCY_STOP: EmergencyStopError,
    StopReason.FAULT: RobotFaultError,
    StopReason.VIOLATION: RobotFaultError,
    StopReason.PROGRAM_STOPPED: ProgramStoppedError,
    StopReason.LINK_LOST: ConnectionLostError,
    StopReason.CELL_SILENT: LinkBrakeError,
    StopReason.STATE_STALLED: LinkBrakeError,
    StopReason.LINK_DOWN: LinkBrakeError,
    StopReason.STOP_REQUESTED: MoveStoppedError,
    StopReason.MOVE_ABORTED: MoveStoppedError,
    StopReason.SERVOJ_REFUSED: MoveError,
    StopReason.NO_EXTERNAL_CONTROL: MoveError,
    StopReason.LINK_ERROR: MoveError,
}


@pytest.mark.parametrize("reason", list(StopReason), ids=lambda r: r.name)
def test_each_stop_reason_maps_to_its_error(reason: StopReason) -> None:
    error = STOP_ERRORS[reason]
    assert issubclass(error, FxcellError)
    if reason in EXPECTED_ERRORS:
        assert error is EXPECTED_ERRORS[reason]
    result = TrajectoryResult("failed", reason, 3, 10, None, 0.1)
    assert result.error() is error


def test_the_link_brakes_are_the_reasons_of_link_brake_errors() -> None:
    assert {StopReason.CELL_SILENT, StopReason.STATE_STALLED, StopReason.LINK_DOWN} == LINK_BRAKES


@pytest.mark.parametrize("mode", sorted(SAFETY_STOPS), ids=lambda m: SafetyMode(m).name)
def test_every_safety_stop_is_a_stop_reason_and_a_cell_state(mode: int) -> None:
    reason = stop_reason(mode, RuntimeState.PLAYING)
    assert reason is not None
    assert reason in STATE_STOPS
    assert CellState(reason.value).value == reason.value  # the cell names its state the same
    assert issubclass(STOP_ERRORS[reason], SafetyStopError)


def test_a_stopped_program_is_a_stop_reason_and_a_playing_one_none() -> None:
    assert stop_reason(SafetyMode.NORMAL, RuntimeState.STOPPED) is StopReason.PROGRAM_STOPPED
    assert stop_reason(SafetyMode.NORMAL, RuntimeState.PLAYING) is None


def test_a_stop_reason_travels_as_its_string() -> None:
    for reason in StopReason:
        sent = wire.decode(wire.encode((wire.TRAJ_STOP, 1, reason.value))[wire.HEADER.size :])
        assert type(sent[2]) is str
        assert StopReason(sent[2]) is reason


def test_a_failed_results_reason_shows_its_detail() -> None:
    result = TrajectoryResult("failed", StopReason.LINK_ERROR, 0, 5, None, 0.0, "boom")
    assert result.why == "link_error: boom"
    assert TrajectoryResult("stopped", StopReason.SETTLED, 5, 5, None, 0.0).why == "settled"


# ----------------------------------------------------------------- trajectory messages


class _Traj:
    id = 5

    def __init__(self) -> None:
        self.stops: list[StopReason] = []

    def stop(self, reason: StopReason) -> None:
        self.stops.append(reason)


def test_a_stop_message_brakes_the_trajectory_for_its_reason(link: _Sent) -> None:
    traj = _Traj()
    link._traj = traj  # type: ignore[assignment]
    link._dispatch((wire.TRAJ_STOP, StopTrajectory(5, StopReason.LINK_DOWN.value)))
    link._dispatch((wire.TRAJ_STOP, StopTrajectory(4, StopReason.LINK_DOWN.value)))  # not it
    assert traj.stops == [StopReason.LINK_DOWN]


def test_a_stop_for_a_reason_the_contract_does_not_name_still_brakes(link: _Sent) -> None:
    traj = _Traj()
    link._traj = traj  # type: ignore[assignment]
    link._dispatch((wire.TRAJ_STOP, StopTrajectory(5, "because")))
    assert traj.stops == [StopReason.STOP_REQUESTED]
    assert [m[0] for m in link.sent] == [wire.LOG]


def test_a_trajectory_message_of_the_untyped_protocol_is_refused(link: _Sent) -> None:
    traj = _Traj()
    link._traj = traj  # type: ignore[assignment]
    link._dispatch((wire.TRAJ_STOP, 5, "stop requested"))  # positional, told apart by length
    assert traj.stops == []
    assert "unknown message 'traj_stop'" in link.sent[0][2]


def test_a_replacement_for_another_trajectory_is_answered_not_ok(link: _Sent) -> None:
    link._dispatch((wire.TRAJ_REPLACE, ReplaceTrajectory(8, (1, bytes(48)), None)))
    assert link.sent == [(wire.TRAJ, 8, "replaced", {"ok": False})]


def test_trajectory_messages_survive_the_wire() -> None:
    start = StartTrajectory(1, (1, bytes(48)), 0.1, 300.0, Guard(cell_timeout=None))
    for message in ((wire.TRAJ_START, start), (wire.TRAJ_STOP, StopTrajectory(1, "settled"))):
        assert wire.decode(wire.encode(message)[wire.HEADER.size :]) == message


def test_a_call_of_the_untyped_protocol_is_answered_with_a_contract_error(link: _Sent) -> None:
    link._dispatch((wire.CALL, 6, "set_output", {"group": "tool"}))  # (CALL, id, method, kwargs)
    [(kind, request_id, ok, (error_kind, text))] = link.sent
    assert (kind, request_id, ok) == (wire.REPLY, 6, False)
    assert isinstance(reply_error(error_kind, text), LinkContractError)
    assert link._calls.empty()


def test_an_undecodable_message_is_refused_and_the_next_one_read(
    link: _Sent, pair: tuple[socket.socket, socket.socket]
) -> None:
    theirs = pair[1]
    garbage = b"\x80\x05not a pickle"
    theirs.sendall(wire.HEADER.pack(len(garbage)) + garbage)
    theirs.sendall(wire.encode((wire.CALL, 2, Ping())))
    theirs.shutdown(socket.SHUT_WR)  # the reader ends after these two
    link._reader()
    assert link.sent[0][:2] == (wire.LOG, logging.ERROR)
    assert "undecodable message refused" in link.sent[0][2]
    assert link._calls.get_nowait() == (2, Ping())
