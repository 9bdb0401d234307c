"""The daemon's parts that need no robot: token, control lease, binding, sd_notify, stream
decimation, and the HTTP layer's refusals (which happen before any robot is involved)."""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import socket
import stat
import subprocess
import sys
import time
import urllib.parse
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi import FastAPI

from fxcell import errors
from fxcell.client import decode_client_name, encode_client_name
from fxcell.config import CellConfig
from fxcell.daemon.app import create_app
from fxcell.daemon.auth import TOKEN_ENV, check_bearer, load_or_create_token, read_token
from fxcell.daemon.control import ControlLock
from fxcell.daemon.encoding import http_status
from fxcell.daemon.guard import same_origin
from fxcell.daemon.notify import Notifier
from fxcell.daemon.process import free_port
from fxcell.daemon.server import check_bind, is_loopback
from fxcell.daemon.service import CellService
from fxcell.daemon.stream import Watcher, parse_rate, parse_topics
from fxcell.errors import ConfigError, ControlHeldError
from fxcell.geometry import Pose
from fxcell.motion import ned2
from fxcell.motion.kinematics import Kinematics
from fxcell.robots import UR3E_KIND, kind_names, register, unregister
from fxcell.robots.ned2 import NED2_KIND

TOKEN = "s3cret-token-for-tests-0123456789"


# ----------------------------------------------------------------- token


def test_first_start_creates_an_owner_only_token(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    path = tmp_path / "conf" / "token"
    token = load_or_create_token(path)
    assert len(token) >= 32
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    assert load_or_create_token(path) == token  # reused at the next start
    assert read_token(path) == token


def test_environment_token_overrides_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(TOKEN_ENV, "from-env")
    assert load_or_create_token(tmp_path / "token") == "from-env"
    assert not (tmp_path / "token").exists()
    assert read_token(tmp_path / "token") == "from-env"


def test_token_file_readable_by_others_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    path = tmp_path / "token"
    path.write_text("abc\n")
    os.chmod(path, 0o644)
    with pytest.raises(ConfigError, match="chmod 600"):
        load_or_create_token(path)


@pytest.mark.parametrize(
    ("header", "ok"),
    [
        (f"Bearer {TOKEN}", True),
        (f"bearer {TOKEN}", True),
        (None, False),
        ("", False),
        (TOKEN, False),
        (f"Basic {TOKEN}", False),
        (f"Bearer {TOKEN}x", False),
        ("Bearer ", False),
    ],
)
def test_bearer_header_must_carry_the_token(header: str | None, ok: bool) -> None:
    assert check_bearer(header, TOKEN) is ok


# ----------------------------------------------------------------- binding


def test_non_loopback_address_needs_the_explicit_option() -> None:
    assert is_loopback("127.0.0.1")
    assert is_loopback("::1")
    assert is_loopback("localhost")
    assert not is_loopback("0.0.0.0")
    assert not is_loopback("192.168.1.20")
    check_bind("127.0.0.1", False, "x")
    with pytest.raises(ConfigError, match="--allow-remote"):
        check_bind("0.0.0.0", False, TOKEN)
    check_bind("0.0.0.0", True, TOKEN)
    with pytest.raises(ConfigError, match="token"):
        check_bind("0.0.0.0", True, "short")


# ----------------------------------------------------------------- control


def test_second_client_is_refused_with_the_holder_named() -> None:
    lock = ControlLock(lease=30)
    alice = lock.acquire("alice@lab").lease
    assert lock.acquire("alice@lab", alice).lease == alice  # renewed with her lease
    with pytest.raises(ControlHeldError, match="controlled by 'alice@lab'"):
        lock.acquire("bob@pc")
    assert not lock.release(None)
    assert not lock.release("not-her-lease")
    assert lock.release(alice)
    assert lock.acquire("bob@pc").client == "bob@pc"


def test_a_client_giving_the_holders_name_is_not_the_holder() -> None:
    lock = ControlLock(lease=30)
    lock.acquire("alice@lab")
    with pytest.raises(ControlHeldError):
        lock.acquire("alice@lab")  # the name is a label, the lease is the key
    assert lock.describe() is not None
    assert "lease" not in lock.describe()  # type: ignore[operator]


def test_force_takes_control_over() -> None:
    changes: list[str | None] = []
    lock = ControlLock(on_change=lambda h: changes.append(h.client if h else None))
    first = lock.acquire("alice").lease
    taken = lock.acquire("bob", force=True)
    assert taken.client == "bob"
    assert taken.lease != first
    assert changes == ["alice", "bob"]
    assert not lock.is_holder(first)


def test_lease_runs_out_unless_the_holder_keeps_it_alive() -> None:
    alive = {"alice": True}
    lock = ControlLock(lease=0.0, keeps_alive=lambda h: alive.get(h.client, False))
    lock.acquire("alice")
    with pytest.raises(ControlHeldError):
        lock.acquire("bob")  # alice watches: her lease holds
    alive["alice"] = False
    deadline = time.monotonic() + 1.0
    while lock.holder is not None and time.monotonic() < deadline:
        pass
    assert lock.holder is None
    assert lock.acquire("bob").client == "bob"


def test_only_a_watcher_that_answers_pings_keeps_a_lease_alive() -> None:
    from fxcell.daemon.stream import PONG_TIMEOUT, StreamHub

    hub = StreamHub(lambda: None)
    watcher = hub.add(frozenset({"state"}), 10.0, "alice", "lease-1")
    hub.add(frozenset({"state"}), 10.0, "alice", None)  # names itself alice, no lease
    assert hub.watches("lease-1")
    assert not hub.watches("lease-2")
    watcher.last_pong -= PONG_TIMEOUT + 1  # frozen: stopped answering pings
    assert not hub.watches("lease-1")


# ----------------------------------------------------------------- sd_notify


def test_notifier_speaks_the_systemd_datagram_protocol(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(path)
        server.settimeout(2)
        notifier = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "4000000"})
        assert notifier.enabled
        assert notifier.watchdog_interval == pytest.approx(2.0)
        assert notifier.ready("serving")
        assert server.recv(1024) == b"READY=1\nSTATUS=serving"
        assert notifier.watchdog()
        assert server.recv(1024) == b"WATCHDOG=1"
        assert notifier.stopping()
        assert server.recv(1024) == b"STOPPING=1"


def test_notifier_is_silent_outside_systemd() -> None:
    notifier = Notifier({})
    assert not notifier.enabled
    assert notifier.watchdog_interval is None
    assert not notifier.ready()


def test_watchdog_for_another_process_is_ignored() -> None:
    notifier = Notifier({"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": str(os.getpid() + 1)})
    assert notifier.watchdog_interval is None


# ----------------------------------------------------------------- stream


@pytest.mark.parametrize("rate", [50.0, 100.0, 125.0, 250.0, 500.0])
def test_state_samples_are_decimated_to_the_chosen_rate(rate: float) -> None:
    watcher = Watcher(frozenset({"state"}), rate, None)
    sent = 0
    for i in range(5000):  # 10 s of 500 Hz samples
        before = watcher._state
        watcher._state = None
        watcher.offer_state(i * 0.002, lambda: "s")
        sent += watcher._state is not None
        watcher._state = before
    assert sent == pytest.approx(rate * 10, abs=2)


def test_slow_watcher_keeps_every_event_but_only_the_newest_state() -> None:
    watcher = Watcher(frozenset({"state", "transition"}), 500.0, None)
    watcher.offer("transition", "t1")
    for i in range(10):
        watcher.offer_state(i * 0.002, lambda i=i: f"s{i}")  # type: ignore[misc]
    watcher.offer("transition", "t2")
    watcher.offer("command", "not subscribed")
    assert list(watcher._backlog) == ["t1", "t2"]
    assert watcher._state == "s9"


def test_rate_and_topics_are_validated() -> None:
    assert parse_rate(None) == 50.0
    assert parse_rate("200") == 200.0
    for bad in ("0", "-5", "nan", "inf", "501", "fast"):
        with pytest.raises(ValueError):  # noqa: PT011 - message checked elsewhere
            parse_rate(bad)
    assert parse_topics("state,transition") == {"state", "transition"}
    with pytest.raises(ValueError, match="unknown topics"):
        parse_topics("state,secrets")


# ----------------------------------------------------------------- HTTP refusals


UNATTACHED = CellConfig.from_dict({"robot": {"command_timeout": 0.3}})


@pytest.fixture(scope="module")
def unattached() -> tuple[CellService, FastAPI]:
    """The daemon's app, built once for the file (its ~70 routes take ~0.2 s to build),
    and the service it serves: :func:`http` makes that service new for each test."""
    service = CellService(UNATTACHED, TOKEN)
    return service, create_app(service)


@pytest.fixture
async def http(unattached: tuple[CellService, FastAPI]) -> AsyncIterator[httpx.AsyncClient]:
    """The API with no cell attached: refusals must come before the robot is needed
    (commands wait 0.3 s for a cell before they say it is not connected)."""
    service, app = unattached
    # The app reads everything of its service when a request comes (its closures hold the
    # object): initialised again, the service is as new as a new CellService would be.
    CellService.__init__(service, UNATTACHED, TOKEN)
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as client:
        yield client


def auth(client: str = "alice") -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKEN}", "X-Fxcell-Client": client}


async def test_commands_without_the_token_are_refused(http: httpx.AsyncClient) -> None:
    for path in ("/api/cell/power_on", "/api/cell/stop", "/api/control"):
        r = await http.post(path, headers={"X-Fxcell-Client": "eve"})
        assert r.status_code == 401, path
        assert r.json()["error"]["type"] == "NotAuthorizedError"
        assert r.headers["WWW-Authenticate"] == "Bearer"
    r = await http.post(
        "/api/cell/move_joint", json={"target": [0] * 6}, headers={"Authorization": "Bearer no"}
    )
    assert r.status_code == 401


@pytest.mark.parametrize(
    ("path", "body", "fragment"),
    [
        ("/api/cell/move_joint", {"target": [0, 0, 0]}, "target"),
        ("/api/cell/move_joint", {"target": [0, 0, 0, 0, 0, "x"]}, "target.5"),
        ("/api/cell/move_joint", {"target": [0] * 6, "velocity_factor": 2}, "velocity_factor"),
        ("/api/cell/move_joint", {"target": [0] * 6, "velocity_factor": 0}, "velocity_factor"),
        ("/api/cell/move_joint", {"target": [0] * 6, "speed": 1}, "speed"),
        ("/api/cell/move_joint", None, "body"),
        ("/api/cell/move_pose", {"target": [0.1] * 5}, "target"),
        ("/api/cell/move_distance", {"distance": [0, 0]}, "distance"),
        ("/api/cell/set_velocity_factor", {"value": -1.4}, "value"),
        ("/api/cell/set_acceleration_factor", {"value": 10}, "value"),
        ("/api/cell/unlock_protective_stop", {"wait": "maybe"}, "wait"),
    ],
)
async def test_malformed_requests_get_422_with_a_message(
    http: httpx.AsyncClient, path: str, body: object, fragment: str
) -> None:
    r = await http.post(path, json=body, headers=auth())
    assert r.status_code == 422
    error = r.json()["error"]
    assert error["type"] == "InvalidArgumentError"
    assert fragment in error["message"]


async def test_nan_in_a_target_is_refused(http: httpx.AsyncClient) -> None:
    r = await http.post(
        "/api/cell/move_joint",
        content=b'{"target": [0, 0, NaN, 0, 0, 0]}',
        headers={**auth(), "Content-Type": "application/json"},
    )
    assert r.status_code == 422


async def test_a_second_client_is_refused_control(http: httpx.AsyncClient) -> None:
    r = await http.post("/api/control", headers=auth("alice@lab"))
    assert r.status_code == 200
    assert r.json()["client"] == "alice@lab"
    lease = r.json()["lease"]
    r = await http.post("/api/cell/power_on", headers=auth("bob@pc"))
    assert r.status_code == 409
    assert "controlled by 'alice@lab'" in r.json()["error"]["message"]
    r = await http.post("/api/cell/power_on", headers=auth("alice@lab"))  # her name, no lease
    assert r.status_code == 409
    assert (await http.get("/api/control")).json() == {
        "client": "alice@lab",
        "since": pytest.approx(time.time(), abs=60),
    }
    r = await http.post("/api/control", json={"force": True}, headers=auth("bob@pc"))
    assert r.json()["client"] == "bob@pc"
    assert r.json()["lease"] != lease
    r = await http.request("DELETE", "/api/control", headers={**auth(), "X-Fxcell-Lease": lease})
    assert r.json() == {"released": False}  # alice's old lease no longer holds


async def test_commands_without_a_cell_say_it_is_not_connected(http: httpx.AsyncClient) -> None:
    r = await http.post("/api/cell/power_on", headers=auth())
    assert r.status_code == 503
    assert "not connected" in r.json()["error"]["message"]
    r = await http.get("/api/cell/get_robot_mode")
    assert r.status_code == 503


async def test_openapi_documents_every_cell_function(http: httpx.AsyncClient) -> None:
    doc = (await http.get("/api/openapi.json")).json()
    paths = doc["paths"]
    for name in (
        "power_on", "brake_release", "power_off", "init", "shutdown", "start_external_control",
        "stop_external_control", "unlock_protective_stop", "move_joint", "go_home", "move_pose",
        "move_distance", "move_relative", "stop", "set_velocity_factor",
        "set_acceleration_factor",
    ):  # fmt: skip
        assert "post" in paths[f"/api/cell/{name}"], name
    for name in (
        "get_robot_mode", "get_safety_status", "get_program_state", "is_in_remote_control",
        "get_current_joint_values", "get_current_pose", "get_current_rpy",
        "get_current_pose_rpy", "get_velocity", "get_velocity_factor",
        "get_acceleration_factor", "get_max_acceleration", "state",
    ):  # fmt: skip
        assert "get" in paths[f"/api/cell/{name}"], name
    assert "/api/operations/{op_id}/cancel" in paths
    schema = doc["components"]["schemas"]["MoveJointRequest"]["properties"]["target"]
    assert schema["minItems"] == schema["maxItems"] == 6


def _page_chain(model: dict[str, Any], q: list[float], tcp: list[float]) -> np.ndarray:
    """The page's arm chain (app.js armPoints): each joint's origin, a turn about its axis
    by q, then the tool frame and the TCP (UR x, y, z, rx, ry, rz)."""
    frame = np.eye(4)
    for joint, angle in zip(model["joints"], q, strict=True):
        frame = frame @ np.array(joint["origin"]).reshape(4, 4)
        frame = frame @ Pose.from_rotvec((0, 0, 0), np.array(joint["axis"]) * angle).matrix
    frame = frame @ np.array(model["tool"]).reshape(4, 4)
    return frame @ Pose.from_ur(tcp).matrix


async def test_the_page_draws_the_arm_with_the_runtimes_kinematics(
    http: httpx.AsyncClient,
) -> None:
    model = (await http.get("/api/robot/model")).json()
    assert model["robot"] == "UR3e"
    assert model["tool_frame"] == "flange"
    tcp = (await http.get("/api/info")).json()["tcp"]
    kinematics = Kinematics.ur3e(tcp)
    for q in ([0.0] * 6, [0.3, -1.2, 1.1, -0.4, 1.3, 0.7], [-2.0, -0.5, -1.9, 2.2, -0.8, 3.0]):
        frame = _page_chain(model, q, tcp)
        assert np.allclose(frame, kinematics.forward(np.array(q)).matrix, atol=1e-12)


async def test_a_ned2_cells_page_draws_the_ned2_from_its_own_model() -> None:
    added = "ned2" not in kind_names()  # registered here until the Ned2 ships
    if added:
        register(NED2_KIND)
    try:
        config = CellConfig()
        tcp = (0.05, 0.0, 0.01, 0.0, 0.2, 0.0)
        config = config.model_copy(
            update={
                "robot": config.robot.model_copy(update={"kind": "ned2"}),
                "tool": config.tool.model_copy(update={"tcp": tcp}),
            }
        )
        transport = httpx.ASGITransport(app=create_app(CellService(config, TOKEN)))
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as client:
            model = (await client.get("/api/robot/model")).json()
    finally:
        if added:
            unregister("ned2")
    assert (model["robot"], model["tool_frame"]) == ("Ned2", "tool_link")
    assert [j["name"] for j in model["joints"]] == list(ned2.JOINT_NAMES)
    kinematics = ned2.Ned2Kinematics(Pose.from_ur(tcp))
    for q in ([0.0] * 6, list(ned2.HOME), [0.6, -0.3, 0.2, 0.4, -0.5, 0.3]):
        frame = _page_chain(model, q, list(tcp))
        assert np.allclose(frame, kinematics.forward(np.array(q)).matrix, atol=1e-12)


async def test_a_kind_without_a_description_has_no_arm_model_to_draw() -> None:
    plain = dataclasses.replace(
        UR3E_KIND, capabilities=dataclasses.replace(UR3E_KIND.capabilities, kind="plain"),
        description=None,
    )  # fmt: skip
    register(plain)
    try:
        config = CellConfig()
        config = config.model_copy(
            update={"robot": config.robot.model_copy(update={"kind": "plain"})}
        )
        transport = httpx.ASGITransport(app=create_app(CellService(config, TOKEN)))
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as client:
            r = await client.get("/api/robot/model")
    finally:
        unregister("plain")
    assert r.status_code == 409
    assert r.json()["error"]["type"] == "UnsupportedCommandError"
    assert "plain" in r.json()["error"]["message"]


async def test_page_and_its_assets_are_served_without_external_resources(
    http: httpx.AsyncClient,
) -> None:
    page = await http.get("/")
    assert page.status_code == 200
    assert "<canvas" in page.text
    for asset in ("/static/app.js", "/static/style.css"):
        r = await http.get(asset)
        assert r.status_code == 200
        assert "http://" not in r.text.replace("http://www.w3.org/2000/svg", "")
        assert "https://" not in r.text
    assert "https://" not in page.text
    assert "http://" not in page.text


# ----------------------------------------------------------------- start-up checks


def _config(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cell.yaml"
    path.write_text(text + f"\ndaemon:\n  token_file: {tmp_path / 'token'}\n")
    return path


def test_daemon_refuses_a_non_loopback_address_without_the_option(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from fxcell.cli import main

    monkeypatch.setenv(TOKEN_ENV, TOKEN)
    config = _config(tmp_path, "robot:\n  host: null")
    assert main(["daemon", "--config", str(config), "--host", "0.0.0.0", "--no-record"]) == 1
    err = capsys.readouterr().err
    assert "--allow-remote" in err
    assert "Traceback" not in err


def test_daemon_names_the_bad_key_of_its_config(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from fxcell.cli import main

    config = tmp_path / "cell.yaml"
    config.write_text("daemon:\n  prot: 8040\n")
    assert main(["daemon", "--config", str(config)]) == 1
    assert "daemon.prot" in capsys.readouterr().err
    assert main(["daemon", "--config", str(config.parent / "missing.yaml")]) == 1
    assert main(["daemon", "--port", "70000", "--no-record"]) == 1
    assert "daemon.port" in capsys.readouterr().err


def test_notifier_never_blocks_on_a_reader_that_fell_behind(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(path)  # never read: its queue fills up
        notifier = Notifier({"NOTIFY_SOCKET": path})
        t0 = time.monotonic()
        sent = [notifier.watchdog() for _ in range(2000)]
        assert time.monotonic() - t0 < 5
        assert sent[0]
        assert not sent[-1]  # dropped, not blocked


# ----------------------------------------------------------------- request hygiene


async def test_a_body_with_a_wrong_token_is_refused_before_it_is_read(
    http: httpx.AsyncClient,
) -> None:
    r = await http.post(
        "/api/cell/move_joint",
        content=b"x" * 2_000_000,
        headers={"Authorization": "Bearer wrong", "Content-Type": "application/json"},
    )
    assert r.status_code == 401
    assert r.json()["error"]["type"] == "NotAuthorizedError"


async def test_a_body_over_the_limit_is_refused_with_413(http: httpx.AsyncClient) -> None:
    r = await http.post(
        "/api/cell/move_joint",
        content=b" " * (1024 * 1024 + 1),
        headers={**auth(), "Content-Type": "application/json"},
    )
    assert r.status_code == 413
    assert "exceeds" in r.json()["error"]["message"]


async def test_a_body_of_undeclared_length_is_cut_off_at_the_limit(
    http: httpx.AsyncClient,
) -> None:
    async def chunks() -> AsyncIterator[bytes]:
        for _ in range(40):
            yield b" " * 65536  # 2.5 MiB in all, no Content-Length

    r = await http.post(
        "/api/cell/move_joint",
        content=chunks(),
        headers={**auth(), "Content-Type": "application/json"},
    )
    assert r.status_code == 413


@pytest.mark.parametrize(
    "host", ["127.0.0.1:8040", "localhost:8040", "[::1]:8040", "10.1.2.3", "cell.localhost"]
)
async def test_requests_to_addresses_and_localhost_are_served(
    http: httpx.AsyncClient, host: str
) -> None:
    r = await http.get("/api/info", headers={"Host": host})
    assert r.status_code == 200


async def test_a_request_under_a_foreign_host_name_is_refused(http: httpx.AsyncClient) -> None:
    # what a DNS-rebinding page would send
    r = await http.get("/api/state", headers={"Host": "attacker.example:8040"})
    assert r.status_code == 421
    assert "allowed_hosts" in r.json()["error"]["message"]


async def test_configured_host_names_are_served() -> None:
    config = CellConfig.from_dict({"daemon": {"allowed_hosts": ["cell-pc.lab"]}})
    transport = httpx.ASGITransport(app=create_app(CellService(config, TOKEN)))
    async with httpx.AsyncClient(transport=transport, base_url="http://cell-pc.lab") as client:
        assert (await client.get("/api/info")).status_code == 200


@pytest.mark.parametrize(
    ("path", "body"),
    [
        ("/api/cell/move_joint", {"target": [True, 0, 0, 0, 0, 0]}),
        ("/api/cell/move_joint", {"target": ["0.1", 0, 0, 0, 0, 0]}),
        ("/api/cell/move_joint", {"target": [0, 0, 0, 0, 0, 0], "velocity_factor": "0.5"}),
        ("/api/cell/move_pose", {"target": [0.1, 0.2, 0.3, 0, 0, 0], "linear": "yes"}),
        ("/api/cell/move_pose", {"target": [0.1, 0.2, 0.3, 0, 0, 0], "linear": 1}),
        ("/api/cell/set_velocity_factor", {"value": True}),
        ("/api/cell/unlock_protective_stop", {"wait": "true"}),
    ],
)
async def test_booleans_and_strings_are_not_numbers_nor_flags(
    http: httpx.AsyncClient, path: str, body: dict[str, object]
) -> None:
    r = await http.post(path, json=body, headers=auth())
    assert r.status_code == 422, r.text


async def test_an_unknown_operation_is_404(http: httpx.AsyncClient) -> None:
    assert (await http.get("/api/operations/op-999")).status_code == 404
    r = await http.post("/api/operations/op-999/wait")
    assert r.status_code == 404
    assert r.json()["error"]["type"] == "RemoteError"


@pytest.mark.parametrize(
    ("error", "status"),
    [
        (errors.JobAnswerError("answer first"), 422),
        (errors.JobStateError("resume", "running", ("paused", "fault")), 409),
        (errors.JobSpecError("no such slot"), 422),
        (errors.JobError("run 3 is unfinished"), 409),
        (errors.MachineError("the fusion machine reports an error"), 502),
        (errors.JobStoreError("unreadable"), 500),
    ],
)
def test_job_errors_answer_with_their_own_http_status(error: Exception, status: int) -> None:
    # a wrong answer or a refused job command is the client's doing: never a 500
    assert http_status(error) == status


@pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only"
)
def test_after_fixing_the_mmap_threshold_freeing_a_big_block_no_longer_raises_it() -> None:
    """serve() calls fix_mmap_threshold() first. Its effect, in a fresh interpreter (the
    threshold is process state): by glibc's own rule, freeing a mapped block raises the
    threshold to its size, so a block the heap cannot hold is then added to the heap; once
    the threshold is fixed, such a block is mapped of its own (and given back when freed)."""
    script = """
import ctypes
from fxcell.daemon.server import fix_mmap_threshold

class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd",
        "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL(None)
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.restype, libc.free.argtypes = None, [ctypes.c_void_p]
libc.mallinfo2.restype, libc.mallinfo2.argtypes = MallInfo2, []

def mapped_after_a_bigger_free():
    size = libc.mallinfo2().fordblks + (1 << 20)  # more than the heap has free
    libc.free(libc.malloc(2 * size))  # mapped, then freed
    before = libc.mallinfo2().hblks  # blocks mapped of their own
    block = libc.malloc(size)
    mapped = libc.mallinfo2().hblks > before
    libc.free(block)
    return mapped

print(mapped_after_a_bigger_free(), fix_mmap_threshold(), mapped_after_a_bigger_free())
"""
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True
    ).stdout.split()
    assert out == ["False", "True", "True"], out


# ----------------------------------------------------------------- the framework's own errors


@pytest.mark.parametrize(
    ("body", "fragment"),
    [
        (b'{"target": [0, 0, 0, 0, 0, "\xff\xfe"]}', "not UTF-8"),
        (b'{"value": ' + b"9" * 5000 + b"}", "too many digits"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (b'{"target": [0, 0, 0', "json"),
    ],
    ids=["invalid-utf8", "5000-digit-integer", "100000-deep-nesting", "truncated"],
)
async def test_bodies_that_do_not_parse_get_a_typed_422(
    http: httpx.AsyncClient, body: bytes, fragment: str
) -> None:
    r = await http.post(
        "/api/cell/move_joint",
        content=body,
        headers={**auth(), "Content-Type": "application/json"},
    )
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["type"] == "InvalidArgumentError"
    assert error["status"] == 422
    assert fragment.lower() in error["message"].lower()


async def test_unknown_paths_and_wrong_methods_get_typed_errors(http: httpx.AsyncClient) -> None:
    r = await http.get("/api/no/such/thing")
    assert r.status_code == 404
    assert r.json()["error"] == {
        "type": "RemoteError",
        "message": "no such path: GET /api/no/such/thing",
        "status": 404,
        "detail": {},
    }
    r = await http.delete("/api/state")
    assert r.status_code == 405
    assert r.json()["error"]["type"] == "RemoteError"
    assert r.json()["error"]["status"] == 405
    assert "GET" in r.headers["Allow"]


@pytest.mark.parametrize(
    ("path", "body"),
    [
        ("/api/cell/move_distance", {"distance": [1e400, 0, 0]}),  # inf once parsed
        ("/api/cell/move_joint", {"target": [0, 0, 0, 0, 0, 10**400]}),
        ("/api/cell/gripper_move", {"width": 0.2}),
        ("/api/cell/gripper_move", {"width": 0.02, "grip_force": -1e300}),
        ("/api/cell/io_wait_for", {"signal": "x", "timeout": 1e300}),
    ],
)
async def test_numbers_out_of_their_range_are_refused_before_a_cell_is_needed(
    http: httpx.AsyncClient, path: str, body: dict[str, object]
) -> None:
    content = json.dumps(body).replace("Infinity", "1e400").encode()
    r = await http.post(
        path, content=content, headers={**auth(), "Content-Type": "application/json"}
    )
    assert r.status_code == 422, r.text
    assert r.json()["error"]["type"] == "InvalidArgumentError"


# ----------------------------------------------------------------- client names, origins


NAME = "bétà-☺"


@pytest.mark.parametrize(
    "header",
    [NAME.encode(), b"UTF-8''" + urllib.parse.quote(NAME).encode(), encode_client_name(NAME)],
    ids=["raw-utf8", "rfc8187", "as-remotecell-sends-it"],
)
async def test_client_names_are_utf8_end_to_end(http: httpx.AsyncClient, header: object) -> None:
    r = await http.post(
        "/api/control",
        headers={"Authorization": f"Bearer {TOKEN}", "X-Fxcell-Client": header},  # type: ignore[arg-type]
    )
    assert r.status_code == 200, r.text
    assert r.json()["client"] == NAME
    assert (await http.get("/api/control")).json()["client"] == NAME


def test_client_names_round_trip_through_the_header() -> None:
    for name in (NAME, "plain@host (RemoteCell, pid 7)", "utf-8''x", "tab\there", "日本語"):
        value = encode_client_name(name)
        assert value.isascii()
        assert decode_client_name(value.encode()) == name.replace("\t", "")
    assert decode_client_name(b"caf\xe9") == "café"  # not UTF-8: read as Latin-1


@pytest.mark.parametrize(
    ("origin", "scheme", "host", "same"),
    [
        ("http://127.0.0.1:8040", "ws", "127.0.0.1:8040", True),
        ("https://127.0.0.1:8040", "ws", "127.0.0.1:8040", False),  # another scheme
        ("http://127.0.0.1:8040", "wss", "127.0.0.1:8040", False),
        ("https://cell.lab", "wss", "cell.lab", True),
        ("https://cell.lab:443", "wss", "cell.lab", True),
        ("http://cell.lab", "ws", "cell.lab:80", True),
        ("http://CELL.lab", "ws", "cell.LAB", True),
        ("http://127.0.0.1:8041", "ws", "127.0.0.1:8040", False),
        ("http://evil.example", "ws", "127.0.0.1:8040", False),
        ("null", "ws", "127.0.0.1:8040", False),
        ("http://127.0.0.1:99999", "ws", "127.0.0.1:8040", False),
        ("http://127.0.0.1:8040", "ws", None, False),
    ],
)
def test_the_stream_is_open_only_to_pages_of_the_same_origin(
    origin: str, scheme: str, host: str | None, same: bool
) -> None:
    assert same_origin(origin, scheme, host) is same


def test_free_ports_are_bindable_below_the_ephemeral_range_and_never_given_twice() -> None:
    lowest_ephemeral = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    ports = [free_port() for _ in range(20)]
    assert len(set(ports)) == len(ports)
    for port in ports:
        assert port < lowest_ephemeral  # no outgoing connection can take it
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            sock.bind(("127.0.0.1", port))
