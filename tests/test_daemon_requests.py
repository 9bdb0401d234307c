"""The daemon's bad-input suite on a cell: a request is refused before its operation exists.

Everything that can be known before a command starts (arguments, finite values, factors,
reach, the state machine's guard, Local control, a running move, the lease) is the request's
answer, 409 or 422, the same whether the client waits or not; no operation is created and the
arm does not move. The daemon's app runs in process (``httpx.ASGITransport``) on a Cell on
the in-process fake robot.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import httpx
import pytest
from fastapi import FastAPI

from fxcell.cell import Cell
from fxcell.client import RemoteCell
from fxcell.config import CellConfig
from fxcell.daemon.app import create_app
from fxcell.daemon.service import CellService
from fxcell.errors import InvalidFactorError, UnreachableError
from fxcell.events import CommandEvent
from fxcell.testing import FakeRobot

TOKEN = "s3cret-token-for-tests-0123456789"
HOME = [0.0, -1.5708, 0.0, -1.5708, 0.0, 0.0]
WORK = [0.4, -1.4, 1.6, -1.8, -1.57, 0.0]


@dataclass
class Api:
    cell: Cell
    robot: FakeRobot
    service: CellService
    app: FastAPI
    http: httpx.AsyncClient
    headers: dict[str, str]

    async def post(self, name: str, body: Any = None, *, wait: bool) -> httpx.Response:
        r = await self.http.post(
            f"/api/cell/{name}",
            json=body,
            headers=self.headers,
            params={"wait": "true" if wait else "false"},
        )
        if lease := r.headers.get("X-Fxcell-Lease"):
            self.headers["X-Fxcell-Lease"] = lease
        return r


@pytest.fixture(scope="module")
def served() -> tuple[CellService, FastAPI]:
    """The daemon's app, built once for the file (its ~70 routes take ~0.2 s to build),
    and the service it serves: each test makes that service new (:func:`api`)."""
    service = CellService(CellConfig.load(), TOKEN)
    return service, create_app(service)


@pytest.fixture
async def api(fake_robot: FakeRobot, served: tuple[CellService, FastAPI]) -> AsyncIterator[Api]:
    service, app = served
    async with Cell(link_factory=fake_robot.link_factory, record=None) as cell:
        await cell.init()
        # The app reads everything of its service when a request comes (its closures hold
        # the object): initialised again, the service is as new as a new CellService
        # would be, for this test's cell.
        CellService.__init__(service, cell.config, TOKEN)
        service.attach(cell)
        transport = httpx.ASGITransport(app=app)
        headers = {"Authorization": f"Bearer {TOKEN}", "X-Fxcell-Client": "tester"}
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as http:
            yield Api(cell, fake_robot, service, app, http, headers)
        await service.operations.cancel_all()
        service.detach()


REFUSED = [
    # factors the pydantic model admits but the cell's minimum factor does not
    ("move_joint", {"target": WORK, "velocity_factor": 1e-5}, 422, "InvalidFactorError"),
    ("move_joint", {"target": WORK, "acceleration_factor": 1e-300}, 422, "InvalidFactorError"),
    ("go_home", {"velocity_factor": 0.001}, 422, "InvalidFactorError"),
    # finite but absurd numbers: never an overflow, a typed refusal
    ("move_distance", {"distance": [1e300, 0, 0]}, 422, "UnreachableError"),
    ("move_distance", {"distance": [0, -1e30, 0]}, 422, "UnreachableError"),
    ("move_distance", {"distance": [5, 0, 0]}, 422, "UnreachableError"),
    ("move_joint", {"target": [1e300, 0, 0, 0, 0, 0]}, 422, "InvalidTargetError"),
    ("move_pose", {"target": [1e300, 0, 0.3, 0, 0, 0]}, 422, "UnreachableError"),
    ("move_pose", {"target": [1e300, 0, 0.3, 0, 0, 0], "linear": True}, 422, "UnreachableError"),
    ("move_pose", {"target": [0.3, 0, 0.3, 1e300, 0, 0]}, 422, "InvalidTargetError"),
    (
        "move_relative",
        {"start_pose": [1e300, 0, 0, 0, 0, 0], "target_pose": [0.3, 0, 0.3, 0, 0, 0]},
        422,
        "UnreachableError",
    ),
    # bad quaternions, unreachable and colliding poses
    ("move_pose", {"target": [0.3, 0, 0.3, 0, 0, 0, 0]}, 422, "InvalidTargetError"),
    ("move_pose", {"target": [0.3, 0, 0.3, 1e-300, 0, 0, 0]}, 422, "InvalidTargetError"),
    ("move_pose", {"target": [3.0, 0, 0.3, 0, 0, 0]}, 422, "UnreachableError"),
    ("move_pose", {"target": [0.6, 0, 0.3, 3.1416, 0, 0]}, 422, "UnreachableError"),
    ("move_pose", {"target": [0.3, 0, 0.3, 0, 0, 0]}, 422, "CollisionError"),
    # names the configuration does not know
    ("move_to", {"name": "nowhere"}, 422, "UnknownPositionError"),
    ("pick", {"station": "rack", "slot": "Z99"}, 422, "SlotError"),
    ("pick", {"station": "attic", "slot": "A1"}, 422, "UnknownStationError"),
    ("place", {"station": "rack", "slot": "A1"}, 409, "HoldingError"),  # holds nothing
    ("io_set", {"signal": "nope", "value": True}, 422, "UnknownSignalError"),
    ("io_wait_for", {"signal": "nope", "timeout": 1}, 422, "UnknownSignalError"),
    ("teach", {"name": "9 lives"}, 422, "InvalidArgumentError"),
    ("teach_frame_point", {"station": "rack", "point": "corner"}, 422, "InvalidArgumentError"),
    # ranges of the table's argument types
    ("gripper_move", {"width": 0.2}, 422, "InvalidArgumentError"),
    ("gripper_move", {"width": 0.02, "speed": 1e300}, 422, "InvalidArgumentError"),
    ("gripper_close", {"grip_force": 5}, 422, "InvalidArgumentError"),
    # guard refusals
    ("power_on", None, 409, "InvalidStateError"),
    ("unlock_protective_stop", None, 409, "InvalidStateError"),
]


@pytest.mark.parametrize("wait", [False, True])
@pytest.mark.parametrize(("name", "body", "status", "kind"), REFUSED)
async def test_what_is_known_before_a_command_starts_is_its_answer(
    api: Api, name: str, body: Any, status: int, kind: str, wait: bool
) -> None:
    q = api.robot.state()["q"]
    r = await api.post(name, body, wait=wait)
    assert r.status_code == status, r.text
    error = r.json()["error"]
    assert error["type"] == kind, error
    assert error["status"] == status
    assert error["message"]
    assert api.service.operations.all() == []  # no operation was started
    assert api.robot.state()["q"] == pytest.approx(q, abs=1e-9)


async def test_a_move_while_the_control_program_is_stopped_is_refused_at_once(api: Api) -> None:
    await api.cell.stop_external_control()
    for wait in (False, True):
        r = await api.post("move_joint", {"target": WORK}, wait=wait)
        assert r.status_code == 409
        assert r.json()["error"]["type"] == "InvalidStateError"
        assert "move_joint" in r.json()["error"]["message"]
    assert api.service.operations.all() == []


async def test_a_move_in_local_control_is_refused_at_once(api: Api) -> None:
    api.robot.inject("local_control")
    async with asyncio.timeout(5):
        with api.cell.robot_states() as states:
            async for _ in states:  # the cell polls the pendant's switch
                if api.cell.local_control:
                    break
    r = await api.post("move_joint", {"target": WORK}, wait=False)
    assert r.status_code == 409
    assert r.json()["error"]["type"] == "NotInRemoteControlError"
    assert api.service.operations.all() == []


async def test_a_second_move_is_refused_unless_queued(api: Api) -> None:
    first = await api.post("move_joint", {"target": WORK}, wait=False)
    assert first.status_code == 202
    r = await api.post("move_joint", {"target": HOME}, wait=False)
    assert r.status_code == 409
    assert r.json()["error"]["type"] == "MoveInProgressError"
    queued = await api.post("move_joint", {"target": HOME, "queue": True}, wait=False)
    assert queued.status_code == 202
    # a queued move's target is checked when it is queued, not when its turn comes
    bad = await api.post("move_joint", {"target": [9, 0, 0, 0, 0, 0], "queue": True}, wait=False)
    assert bad.status_code == 422
    r = await api.http.post(f"/api/operations/{queued.json()['id']}/wait", params={"timeout": 30})
    assert r.json()["status"] == "succeeded", r.text
    assert api.robot.state()["q"] == pytest.approx(HOME, abs=1e-3)


async def test_a_refusal_is_recorded_with_the_client_and_keeps_the_lease(api: Api) -> None:
    events: list[CommandEvent] = []
    unsubscribe = api.cell.bus.subscribe(
        lambda e: events.append(e) if isinstance(e, CommandEvent) else None
    )
    try:
        r = await api.post("move_distance", {"distance": [1e300, 0, 0]}, wait=False)
    finally:
        unsubscribe()
    assert r.status_code == 422
    assert r.headers["X-Fxcell-Lease"]  # control was taken with this request
    ended = [e for e in events if e.name == "move_distance" and e.outcome == "error"]
    assert len(ended) == 1
    assert ended[0].origin == "tester"
    assert ended[0].error_type == "UnreachableError"


async def test_the_library_refuses_the_same_before_a_move_exists(api: Api) -> None:
    cell = api.cell
    with pytest.raises(UnreachableError, match="reaches"):
        await cell.move_distance([1e300, 0, 0])
    with pytest.raises(UnreachableError):
        await cell.move_pose([1e300, 0, 0.3, 0, 0, 0], linear=True)
    with pytest.raises(InvalidFactorError):
        await cell.check_command("move_joint", target=WORK, velocity_factor=1e-5)
    assert cell._runner is None  # no move was ever started
    await cell.check_command("move_joint", target=WORK)  # a good one passes


async def test_commands_with_an_argument_called_name_work_over_the_daemon(api: Api) -> None:
    transport = httpx.ASGITransport(app=api.app)
    async with RemoteCell("http://127.0.0.1", TOKEN, transport=transport) as remote:
        taught = await remote.teach("p1")
        assert taught["joints"] == pytest.approx(api.robot.state()["q"])
        result = await remote.move_to("p1")
        assert result.reached_joints == pytest.approx(taught["joints"], abs=1e-3)
