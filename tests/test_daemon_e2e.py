"""The daemon on the embedded simulator, driven over HTTP and WebSocket like an operator's
client: life cycle, moves as operations, refusals, and a clean SIGTERM mid-move."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import signal
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import websockets

from fxcell.daemon.process import DaemonProcess
from fxcell.settling import REST_VELOCITY
from fxcell.testing import simulator

TOKEN = "e2e-test-token-0123456789abcdef"
CONFIG = "robot:\n  host: null\ndaemon:\n  token_file: {token_file}\n"
SIM_ARGS = ("--sim-time-scale", "0.2")

pytestmark = pytest.mark.slow


def write_config(tmp: Path) -> Path:
    config = tmp / "cell.yaml"
    config.write_text(CONFIG.format(token_file=tmp / "token"))
    return config


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    tmp = tmp_path_factory.mktemp("daemon")
    with DaemonProcess.start(write_config(tmp), token=TOKEN, extra_args=SIM_ARGS) as process:
        process.wait_connected()
        yield process
    assert process.proc.returncode == 0, "\n".join(process.output[-30:])


def headers(client: str = "tester", token: str | None = TOKEN) -> dict[str, str]:
    out = {"X-Fxcell-Client": client}
    if token:
        out["Authorization"] = f"Bearer {token}"
    return out


@pytest.fixture
async def http(daemon: DaemonProcess) -> AsyncIterator[httpx.AsyncClient]:
    """An HTTP client that, as "tester", keeps the control lease the daemon hands it
    and shows it with its commands (as RemoteCell and the page do)."""
    lease: dict[str, str] = {}

    async def show_lease(request: httpx.Request) -> None:
        if request.headers.get("X-Fxcell-Client") == "tester" and "lease" in lease:
            request.headers.setdefault("X-Fxcell-Lease", lease["lease"])

    async def keep_lease(response: httpx.Response) -> None:
        value = response.headers.get("X-Fxcell-Lease")
        if value and response.request.headers.get("X-Fxcell-Client") == "tester":
            lease["lease"] = value

    hooks = {"request": [show_lease], "response": [keep_lease]}
    async with httpx.AsyncClient(base_url=daemon.url, timeout=30, event_hooks=hooks) as client:
        yield client
        # leave the cell free for the next test
        await client.delete("/api/control", headers=headers())


class Watcher:
    """Collects stream messages in the background of a test."""

    def __init__(self, url: str, rate: float = 50) -> None:
        self.url = url.replace("http://", "ws://") + f"/api/stream?rate={rate}"
        self.messages: list[dict[str, Any]] = []
        self._task: asyncio.Task[None] | None = None
        self._ready = asyncio.Event()

    async def _run(self) -> None:
        async with websockets.connect(self.url, max_size=None) as ws:
            async for text in ws:
                self.messages.append(json.loads(text))
                self._ready.set()

    async def __aenter__(self) -> Watcher:
        self._task = asyncio.create_task(self._run())
        await asyncio.wait_for(self._ready.wait(), 10)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._task is not None
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)

    def of(self, kind: str) -> list[dict[str, Any]]:
        return [m for m in self.messages if m["type"] == kind]

    async def wait_for(self, test: Any, within: float = 20, after: int = 0) -> dict[str, Any]:
        """The first message (from index ``after`` on) that passes ``test``."""
        deadline = time.monotonic() + within
        seen = after
        while time.monotonic() < deadline:
            for message in self.messages[seen:]:
                if test(message):
                    return message
            seen = len(self.messages)
            await asyncio.sleep(0.01)
        raise AssertionError(f"no matching stream message in {within} s")


async def state(http: httpx.AsyncClient) -> dict[str, Any]:
    r = await http.get("/api/state")
    r.raise_for_status()
    return r.json()  # type: ignore[no-any-return]


async def ensure_ready(http: httpx.AsyncClient) -> None:
    r = await http.post("/api/cell/init", headers=headers())
    assert r.status_code == 200, r.text
    assert (await state(http))["state"] == "running.external_control_ready"


async def test_full_life_cycle_over_http_and_websocket(
    daemon: DaemonProcess, http: httpx.AsyncClient
) -> None:
    async with Watcher(daemon.url) as watcher:
        hello = watcher.of("hello")[0]
        assert hello["snapshot"]["connected"] is True
        # the embedded simulator's factory calibration, read at connect (the page shows it)
        from fxcell.sim.server import default_calibration

        calibration = hello["snapshot"]["calibration"]
        assert calibration["model"] == "calibrated"
        assert calibration["checksum"] == default_calibration().checksum
        steps = [
            ("power_off", "power_off"),
            ("power_on", "idle"),
            ("brake_release", "running.program_stopped"),
            ("start_external_control", "running.external_control_ready"),
            ("stop_external_control", "running.program_stopped"),
            ("power_off", "power_off"),
            ("init", "running.external_control_ready"),
        ]
        for command, expected in steps:
            r = await http.post(f"/api/cell/{command}", headers=headers())
            assert r.status_code == 200, f"{command}: {r.text}"
            op = r.json()
            assert op["status"] == "succeeded"
            assert op["name"] == command
            assert (await state(http))["state"] == expected, command
        r = await http.get("/api/cell/get_robot_mode")
        assert r.json() == {"result": "RUNNING"}
        r = await http.get("/api/cell/get_current_joint_values")
        assert len(r.json()["result"]) == 6
        r = await http.get("/api/cell/get_current_pose")
        pose = r.json()["result"]
        assert len(pose) == 7
        assert math.isclose(sum(v * v for v in pose[3:]), 1.0, rel_tol=1e-6)
        await watcher.wait_for(
            lambda m: m["type"] == "transition" and m["dest"] == "running.external_control_ready"
        )
        await watcher.wait_for(lambda m: m["type"] == "state")
    dests = [m["dest"] for m in watcher.of("transition")]
    for expected in ("power_off", "idle", "running.program_stopped"):
        assert expected in dests
    commands = [(m["name"], m["outcome"]) for m in watcher.of("command")]
    assert ("power_on", "ok") in commands
    # commands carry the client that sent them; queries (GET) the daemon
    assert {m["origin"] for m in watcher.of("command")} == {"daemon", "tester"}
    assert all(m["origin"] == "tester" for m in watcher.of("command") if m["name"] == "power_on")
    ops = [m for m in watcher.of("operation") if m["status"] == "succeeded"]
    assert [m["name"] for m in ops][-1] == "init"


async def test_move_runs_as_an_operation_and_cancel_stops_it(
    daemon: DaemonProcess, http: httpx.AsyncClient
) -> None:
    await ensure_ready(http)
    start_q = (await state(http))["robot"]["q"]
    target = [start_q[0] + 1.5, *start_q[1:]]
    async with Watcher(daemon.url, rate=100) as watcher:
        r = await http.post(
            "/api/cell/move_joint",
            json={"target": target, "velocity_factor": 0.3, "acceleration_factor": 0.5},
            headers=headers(),
        )
        assert r.status_code == 202, r.text
        op = r.json()
        assert op["status"] == "running"
        listed = (await http.get("/api/operations", params={"running": "true"})).json()
        assert [o["id"] for o in listed] == [op["id"]], listed
        await watcher.wait_for(  # well under way: 0.05 rad travelled
            lambda m: m["type"] == "state" and m["q"][0] > start_q[0] + 0.05, within=20
        )
        r = await http.post(f"/api/operations/{op['id']}/cancel", headers=headers())
        assert r.status_code == 200
        cancelled = r.json()
        assert cancelled["status"] == "cancelled"
        assert cancelled["error"]["type"] == "MoveStoppedError"
        rest = await watcher.wait_for(
            lambda m: m["type"] == "state" and max(abs(v) for v in m["qd"]) < 1e-4,
            after=len(watcher.messages),
        )
        assert start_q[0] + 0.05 < rest["q"][0] < target[0] - 0.01
        r = await http.post(f"/api/operations/{op['id']}/wait", params={"timeout": 1})
        assert r.status_code == 409  # a move that did not reach its goal is never a 200
        assert r.json()["operation"]["status"] == "cancelled"
        assert r.json()["error"]["type"] == "MoveStoppedError"
    assert (await state(http))["state"] == "running.external_control_ready"
    dests = [m["dest"] for m in watcher.of("transition")]
    assert "running.moving" in dests


async def test_move_completes_and_can_be_awaited(
    daemon: DaemonProcess, http: httpx.AsyncClient
) -> None:
    await ensure_ready(http)
    start_q = (await state(http))["robot"]["q"]
    target = [start_q[0] - 0.1, *start_q[1:]]
    r = await http.post(
        "/api/cell/move_joint", json={"target": target}, params={"wait": "true"}, headers=headers()
    )
    assert r.status_code == 200, r.text
    assert r.json()["status"] == "succeeded"
    q = (await state(http))["robot"]["q"]
    assert max(abs(a - b) for a, b in zip(q, target, strict=True)) < 1e-4


async def test_unauthorised_commands_are_refused_and_nothing_changes(
    daemon: DaemonProcess, http: httpx.AsyncClient
) -> None:
    await ensure_ready(http)
    before = await state(http)
    for token in (None, "wrong-token"):
        for path, body in (
            ("/api/cell/power_off", None),
            ("/api/cell/move_joint", {"target": [0.5, -1.5, 0, -1.5, 0, 0]}),
        ):
            r = await http.post(path, json=body, headers=headers("intruder", token))
            assert r.status_code == 401, r.text
            assert "Bearer" in r.json()["error"]["message"]
    after = await state(http)
    assert after["state"] == before["state"] == "running.external_control_ready"
    assert after["robot"]["q"] == pytest.approx(before["robot"]["q"], abs=1e-6)
    assert after["control"] is None or after["control"]["client"] != "intruder"


async def test_a_second_controller_is_refused(
    daemon: DaemonProcess, http: httpx.AsyncClient
) -> None:
    await ensure_ready(http)  # "tester" holds control now
    before = await state(http)
    r = await http.post(
        "/api/cell/move_joint",
        json={"target": [0.3, -1.5, 0, -1.5, 0, 0]},
        headers=headers("second@other-pc"),
    )
    assert r.status_code == 409
    error = r.json()["error"]
    assert error["type"] == "ControlHeldError"
    assert "controlled by 'tester'" in error["message"]
    r = await http.post("/api/cell/power_off", headers=headers("second@other-pc"))
    assert r.status_code == 409
    assert (await state(http))["state"] == before["state"]
    assert (await http.get("/api/control")).json()["client"] == "tester"


@pytest.mark.parametrize("wait", ["1", "0"])
@pytest.mark.parametrize(
    ("path", "body", "status", "kind"),
    [
        ("move_joint", {"target": [10.0, 0, 0, 0, 0, 0]}, 422, "InvalidTargetError"),
        ("move_joint", {"target": [0, 0, 0, 0, 0]}, 422, "InvalidArgumentError"),
        ("move_joint", {"target": [0] * 6, "velocity_factor": 1.4}, 422, "InvalidArgumentError"),
        ("move_joint", {"target": "home"}, 422, "InvalidArgumentError"),
        ("move_joint", {"targets": [0, 0, 0, 0, 0, 0]}, 422, "InvalidArgumentError"),
        # the same answer whatever wait is (issue 27): known before the operation exists
        ("move_joint", {"target": [0] * 6, "velocity_factor": 1e-5}, 422, "InvalidFactorError"),
        ("move_pose", {"target": [0.3, 0, 0.3, 0, 0, 0, 0]}, 422, "InvalidTargetError"),
        ("move_pose", {"target": [2.0, 0, 0.3, 0, 0, 0]}, 422, "UnreachableError"),
        ("move_distance", {"distance": [1e300, 0, 0]}, 422, "UnreachableError"),
        (
            "move_pose",
            {"target": [1e300, 0, 0.3, 0, 0, 0], "linear": True},
            422,
            "UnreachableError",
        ),
        ("move_pose", {"target": [0.3, 0, 0.3, 1e300, 0, 0]}, 422, "InvalidTargetError"),
        ("move_to", {"name": "nowhere"}, 422, "UnknownPositionError"),
    ],
)
async def test_malformed_requests_are_refused_without_motion(
    daemon: DaemonProcess,
    http: httpx.AsyncClient,
    path: str,
    body: dict[str, Any],
    status: int,
    kind: str,
    wait: str,
) -> None:
    await ensure_ready(http)
    before = await state(http)
    r = await http.post(f"/api/cell/{path}", json=body, headers=headers(), params={"wait": wait})
    assert r.status_code == status, r.text
    assert r.json()["error"]["type"] == kind
    assert r.json()["error"]["message"]
    after = await state(http)
    assert after["state"] == "running.external_control_ready"
    assert after["robot"]["q"] == pytest.approx(before["robot"]["q"], abs=1e-6)
    assert after["operations"] == []


async def test_a_move_while_idle_is_refused_at_once(
    daemon: DaemonProcess, http: httpx.AsyncClient
) -> None:
    await ensure_ready(http)
    r = await http.post("/api/cell/stop_external_control", headers=headers())
    assert r.status_code == 200, r.text
    try:
        r = await http.post(
            "/api/cell/move_joint",
            json={"target": [0] * 6},
            headers=headers(),
            params={"wait": "0"},
        )
        assert r.status_code == 409, r.text
        assert r.json()["error"]["type"] == "InvalidStateError"
    finally:
        await ensure_ready(http)


async def test_framework_errors_are_typed(daemon: DaemonProcess, http: httpx.AsyncClient) -> None:
    for body in (b'{"target": "\xff"}', b"[" * 100_000 + b"]" * 100_000, b"9" * 5000):
        r = await http.post(
            "/api/cell/move_joint",
            content=body,
            headers={**headers(), "Content-Type": "application/json"},
        )
        assert r.status_code == 422, r.text
        assert r.json()["error"]["type"] == "InvalidArgumentError"
    r = await http.get("/api/nothing")
    assert (r.status_code, r.json()["error"]["type"]) == (404, "RemoteError")
    r = await http.put("/api/state")
    assert (r.status_code, r.json()["error"]["type"]) == (405, "RemoteError")


async def test_a_utf8_client_name_is_stored_and_broadcast(daemon: DaemonProcess) -> None:
    name = "bétà-☺"
    async with Watcher(daemon.url) as watcher, httpx.AsyncClient(base_url=daemon.url) as client:
        r = await client.post(
            "/api/control",
            json={"force": True},
            headers={"Authorization": f"Bearer {TOKEN}", "X-Fxcell-Client": name.encode()},  # type: ignore[dict-item]
        )
        assert r.json()["client"] == name
        message = await watcher.wait_for(
            lambda m: m["type"] == "control" and m["holder"] is not None
        )
        assert message["holder"]["client"] == name
        assert (await client.get("/api/control")).json()["client"] == name
        await client.delete(
            "/api/control",
            headers={"Authorization": f"Bearer {TOKEN}", "X-Fxcell-Lease": r.json()["lease"]},
        )


async def test_half_open_connections_are_closed(daemon: DaemonProcess) -> None:
    host, port = daemon.url.removeprefix("http://").rstrip("/").rsplit(":", 1)
    streams = []
    for _ in range(400):
        reader, writer = await asyncio.open_connection(host, int(port))
        writer.write(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Fx")
        streams.append((reader, writer))

    async def closed(reader: asyncio.StreamReader) -> None:
        while await reader.read(4096):
            pass

    # daemon.header_timeout is 3 s: all closed within a few seconds (bounded)
    async with asyncio.timeout(8):
        await asyncio.gather(*(closed(r) for r, _ in streams))
    for _, writer in streams:
        writer.close()
    async with httpx.AsyncClient() as client:  # and the daemon serves on
        assert (await client.get(daemon.url + "/api/info")).status_code == 200


async def test_command_in_the_wrong_state_is_refused_with_the_state_named(
    daemon: DaemonProcess, http: httpx.AsyncClient
) -> None:
    await ensure_ready(http)
    r = await http.post("/api/cell/power_on", headers=headers())
    assert r.status_code == 409
    error = r.json()["error"]
    assert error["type"] == "InvalidStateError"
    assert error["detail"]["state"] == "running.external_control_ready"
    assert "idle" in error["detail"]["allowed"]


async def test_stream_rate_is_selectable_and_can_change(daemon: DaemonProcess) -> None:
    url = daemon.url.replace("http://", "ws://") + "/api/stream?rate=50&topics=state"

    async def rate_over(ws: Any, seconds: float) -> float:
        count, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < seconds:
            if json.loads(await ws.recv())["type"] == "state":
                count += 1
        return count / (time.monotonic() - t0)

    async with websockets.connect(url) as ws:
        assert json.loads(await ws.recv())["type"] == "hello"
        assert 40 < await rate_over(ws, 1.0) < 60
        await ws.send(json.dumps({"rate": 200}))
        await rate_over(ws, 0.1)  # what was already queued at the old rate
        # well above the old 50 Hz even when a loaded machine cannot keep up all 200
        assert 120 < await rate_over(ws, 1.0) < 230
    with pytest.raises(websockets.InvalidStatus):  # refused before the upgrade: HTTP 403
        async with websockets.connect(url.replace("rate=50", "rate=5000")) as ws:
            await ws.recv()


async def test_stream_refuses_pages_of_other_sites(daemon: DaemonProcess) -> None:
    url = daemon.url.replace("http://", "ws://") + "/api/stream?topics=control"
    with pytest.raises(websockets.InvalidStatus):
        async with websockets.connect(url, origin="http://evil.example") as ws:  # type: ignore[arg-type]
            await ws.recv()
    same_host_other_scheme = daemon.url.replace("http://", "https://")
    with pytest.raises(websockets.InvalidStatus):
        async with websockets.connect(url, origin=same_host_other_scheme) as ws:  # type: ignore[arg-type]
            await ws.recv()
    async with websockets.connect(url, origin=daemon.url) as ws:  # type: ignore[arg-type]
        assert json.loads(await ws.recv())["type"] == "hello"


def _descendants(pid: int) -> list[tuple[int, str]]:
    """(pid, command line) of every process below ``pid`` (Linux /proc)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                children.setdefault(ppid, []).append(int(entry.name))
    out, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            with contextlib.suppress(OSError):
                cmd = (Path("/proc") / str(child) / "cmdline").read_bytes().replace(b"\0", b" ")
                out.append((child, cmd.decode()))
                todo.append(child)
    return out


@pytest.mark.injects_faults("the link process killed")
async def test_daemon_survives_a_crashed_robot_link(
    daemon: DaemonProcess, http: httpx.AsyncClient
) -> None:
    links = [p for p, cmd in _descendants(daemon.proc.pid) if "fxcell.link.process" in cmd]
    assert len(links) == 1, _descendants(daemon.proc.pid)
    async with Watcher(daemon.url) as watcher:
        os.kill(links[0], signal.SIGKILL)
        await watcher.wait_for(lambda m: m["type"] == "transition" and m["dest"] == "disconnected")
        await watcher.wait_for(
            lambda m: m["type"] == "transition" and m["source"] == "disconnected", within=30
        )
    snapshot = await state(http)
    assert snapshot["connected"] is True
    assert snapshot["state"] != "disconnected"
    await ensure_ready(http)  # and it takes commands again


def test_sigterm_during_a_move_stops_the_robot_finishes_the_log_and_exits_0(
    tmp_path: Path,
) -> None:
    import socket

    from mcap.reader import make_reader

    logs = tmp_path / "logs"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)  # plays systemd's part
    notify.bind(str(tmp_path / "notify"))
    notify.settimeout(10)
    systemd = {"NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "1000000"}
    systemd["FXCELL_DAEMON_VERBOSE"] = "1"  # the shutdown steps' timings, if this fails
    with notify, DaemonProcess.start(
        write_config(tmp_path), token=TOKEN, log_dir=logs, extra_args=SIM_ARGS, env=systemd
    ) as daemon, httpx.Client(base_url=daemon.url, timeout=30) as http:  # fmt: skip
        notices: list[str] = []
        while not any(n.startswith("READY=1") for n in notices):  # READY once connected
            notices.append(notify.recv(4096).decode())
            assert len(notices) < 50, notices
        assert "cell connected" in next(n for n in notices if n.startswith("READY=1"))
        assert "WATCHDOG=1" in notices
        assert daemon.wait_connected()["state"] != "disconnected"
        r = http.post("/api/cell/init", headers=headers())
        assert r.status_code == 200
        lease = {"X-Fxcell-Lease": r.headers["X-Fxcell-Lease"]}
        q = http.get("/api/state").json()["robot"]["q"]
        target = [q[0] + 1.5, *q[1:]]
        r = http.post(
            "/api/cell/move_joint",
            # full speed: stops brake with the braking limits, well within the 3 s
            json={"target": target, "velocity_factor": 1.0},
            headers={**headers(), **lease},
        )
        assert r.status_code == 202, r.text
        op = r.json()["id"]
        deadline = time.monotonic() + 20
        while abs(http.get("/api/state").json()["robot"]["qd"][0]) < 0.8:
            record = http.get(f"/api/operations/{op}").json()
            # it ended before reaching speed: the daemon's log says why (a link brake?)
            assert record["status"] == "running", (record, daemon.output[-15:])
            assert time.monotonic() < deadline, "the move did not reach speed"
            time.sleep(0.01)
        notify.settimeout(0)
        with contextlib.suppress(BlockingIOError):  # the watchdog notices so far
            while True:
                notify.recv(4096)
        t0 = time.monotonic()
        code = daemon.stop(signal.SIGTERM, timeout=10)
        elapsed = time.monotonic() - t0
        notices = []
        with contextlib.suppress(BlockingIOError):
            while True:
                notices.append(notify.recv(4096).decode())
        assert "STOPPING=1" in notices
    assert code == 0, "\n".join(daemon.output[-30:])
    assert elapsed < 3.0
    files = sorted(logs.glob("*.mcap"))
    assert files, f"no MCAP file in {logs}"
    with files[-1].open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()  # a finished file has its summary section
        assert summary is not None
        transitions = [
            json.loads(msg.data)
            for _, _, msg in reader.iter_messages(topics=["/fxcell/transitions"])
        ]
    dests = [t.get("dest") or t.get("to") for t in transitions]
    assert "running.moving" in dests
    after_move = dests[dests.index("running.moving") + 1 :]
    assert after_move, "the log ends while moving"
    assert after_move[0] in ("running.stopping", "running.external_control_ready")


# ----------------------------------------------------------------- RemoteCell and the CLI


async def test_remote_cell_has_the_cells_await_style_api(daemon: DaemonProcess) -> None:
    from fxcell.client import RemoteCell
    from fxcell.errors import InvalidStateError
    from fxcell.protocol import RobotMode, SafetyMode
    from fxcell.results import MoveResult

    async with RemoteCell(daemon.url, TOKEN, name="remote tester") as cell:
        await cell.init()
        assert await cell.get_state() == "running.external_control_ready"
        ready = await cell.wait_for_state("idle", "running.external_control_ready", timeout=5)
        assert ready == "running.external_control_ready"
        assert await cell.get_robot_mode() is RobotMode.RUNNING
        assert await cell.get_safety_status() is SafetyMode.NORMAL
        assert await cell.is_in_remote_control() is True
        q = await cell.get_current_joint_values()
        result = await cell.move_joint([q[0] + 0.05, *q[1:]], velocity_factor=0.5)
        assert isinstance(result, MoveResult)
        assert result.joint_error < 1e-4
        assert not result.stopped
        reached = await cell.get_current_joint_values()
        assert reached[0] == pytest.approx(q[0] + 0.05, abs=1e-4)
        with pytest.raises(InvalidStateError) as refused:
            await cell.power_on()
        assert refused.value.state == "running.external_control_ready"
        assert "idle" in refused.value.allowed
        assert (await cell.control())["client"] == "remote tester"  # type: ignore[index]
    async with RemoteCell(daemon.url) as watcher:
        assert await watcher.control() is None  # released on exit


async def test_cancelling_a_remote_move_stops_the_robot(daemon: DaemonProcess) -> None:
    from fxcell.client import RemoteCell

    async with RemoteCell(daemon.url, TOKEN, name="remote canceller") as cell:
        await cell.init()
        q = await cell.get_current_joint_values()
        move = asyncio.create_task(cell.move_joint([q[0] - 1.5, *q[1:]], velocity_factor=0.3))
        deadline = time.monotonic() + 20
        while abs((await cell.get_velocity())[0]) < 0.05:
            assert time.monotonic() < deadline, "the move did not start"
        move.cancel()
        with pytest.raises(asyncio.CancelledError):
            await move
        ops = await cell.operations()
        assert ops[-1]["name"] == "move_joint"
        assert ops[-1]["status"] == "cancelled"
        assert await cell.get_state() == "running.external_control_ready"
        # the cancelled move returned with the arm at rest, as fxcell defines it (a servo's
        # tracking lag decays for a while below that: 1e-4 rad/s was stricter than promised)
        assert max(abs(v) for v in await cell.get_velocity()) < REST_VELOCITY


async def test_remote_refusals_are_typed(daemon: DaemonProcess) -> None:
    from fxcell.client import RemoteCell
    from fxcell.errors import ControlHeldError, NotAuthorizedError

    async with (
        RemoteCell(daemon.url, TOKEN, name="first") as first,
        RemoteCell(daemon.url, TOKEN, name="second") as second,
        RemoteCell(daemon.url, "wrong", name="intruder") as intruder,
    ):
        await first.take_control()
        with pytest.raises(ControlHeldError, match="controlled by 'first'"):
            await second.power_off()
        with pytest.raises(NotAuthorizedError):
            await intruder.power_off()
        assert await first.release_control() is True


def test_operator_cli_talks_to_the_daemon(daemon: DaemonProcess) -> None:
    import subprocess
    import sys

    def fxcell(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "fxcell", *args, "--url", daemon.url, "--token", TOKEN],
            capture_output=True,
            text=True,
            timeout=60,
        )

    out = fxcell("status")
    assert out.returncode == 0, out.stderr
    assert "state:" in out.stdout
    assert "robot mode:" in out.stdout
    out = fxcell("init")
    assert out.returncode == 0, out.stderr
    assert "running.external_control_ready" in out.stdout
    out = fxcell("power-on")  # refused in the current state: a clear error, exit 1
    assert out.returncode == 1
    assert "power_on() is refused: the robot is running.external_control_ready" in out.stderr
    q = httpx.get(f"{daemon.url}/api/state").json()["robot"]["q"]
    out = fxcell("move-joint", *(str(v) for v in [q[0] + 0.02, *q[1:]]))
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["joint_error"] < 1e-4
    out = fxcell("go-home", "-v", "0.5")  # no body needed (it failed with 422 before)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["joint_error"] < 1e-4


def test_daemon_serves_while_the_robot_is_unreachable(tmp_path: Path) -> None:
    config = tmp_path / "cell.yaml"
    config.write_text(
        f"robot:\n  host: 127.0.0.254\n  connect_timeout: 0.5\n"
        f"daemon:\n  token_file: {tmp_path / 'token'}\n"
    )
    with DaemonProcess.start(config, token=TOKEN) as daemon:
        deadline = time.monotonic() + 30
        while True:
            snapshot = httpx.get(f"{daemon.url}/api/state", timeout=10).json()
            if snapshot["cell_error"]:
                break
            assert time.monotonic() < deadline, snapshot
            time.sleep(0.05)
        assert snapshot["state"] == "disconnected"
        r = httpx.post(f"{daemon.url}/api/cell/power_on", headers=headers(), timeout=10)
        assert r.status_code == 503
        assert "not connected" in r.json()["error"]["message"]
        code = daemon.stop(signal.SIGTERM, timeout=10)
    assert code == 0
    assert any("reopening in" in line for line in daemon.output)


def test_a_command_sent_as_soon_as_the_daemon_serves_waits_for_the_cell(tmp_path: Path) -> None:
    with DaemonProcess.start(write_config(tmp_path), token=TOKEN, extra_args=SIM_ARGS) as daemon:
        # no wait_connected(): the cell is typically still connecting at this point
        r = httpx.post(f"{daemon.url}/api/cell/init", headers=headers(), timeout=30)
        assert r.status_code == 200, r.text
        assert daemon.stop(signal.SIGTERM, timeout=10) == 0


@pytest.mark.injects_faults("the program stopped, the power lost")
@pytest.mark.parametrize("fault", ["stop_program", "power_loss"])
async def test_a_move_the_controller_aborts_answers_with_an_error_status(
    tmp_path: Path, fault: str
) -> None:
    from fxcell.testing import simulator

    with simulator(time_scale=0.2) as sim:
        config = tmp_path / "cell.yaml"
        config.write_text(
            f"robot:\n  host: {sim.host}\ndaemon:\n  token_file: {tmp_path / 'token'}\n"
        )
        with DaemonProcess.start(config, token=TOKEN) as daemon:
            await asyncio.to_thread(daemon.wait_connected)
            async with httpx.AsyncClient(base_url=daemon.url, timeout=30) as http:
                r = await http.post("/api/cell/init", headers=headers())
                assert r.status_code == 200, r.text
                lease = {"X-Fxcell-Lease": r.headers["X-Fxcell-Lease"]}
                q = (await state(http))["robot"]["q"]
                move = asyncio.create_task(
                    http.post(
                        "/api/cell/move_joint",
                        params={"wait": "true"},
                        json={"target": [q[0] + 1.0, *q[1:]], "velocity_factor": 0.3},
                        headers={**headers(), **lease},
                    )
                )
                deadline = time.monotonic() + 20
                while abs((await state(http))["robot"]["qd"][0]) < 0.1:
                    assert time.monotonic() < deadline, "the move did not start"
                    await asyncio.sleep(0.02)
                await asyncio.to_thread(sim.inject, fault)
                r = await move
            assert r.status_code in (409, 503), r.text
            assert r.json()["error"]["type"] in (
                "ProgramStoppedError",
                "MoveStoppedError",
                "ConnectionLostError",
            )
            assert daemon.stop(signal.SIGTERM, timeout=10) == 0


def test_ctrl_c_in_the_terminal_stops_the_daemon_cleanly(tmp_path: Path) -> None:
    # Ctrl-C sends SIGINT to the terminal's whole foreground process group; the link and
    # the simulator have groups of their own, so only the daemon sees it and stops them.
    with DaemonProcess.start(write_config(tmp_path), token=TOKEN, extra_args=SIM_ARGS) as daemon:
        daemon.wait_connected()
        os.killpg(os.getpgid(daemon.proc.pid), signal.SIGINT)
        assert daemon.proc.wait(10) == 0
    output = "\n".join(daemon.output)
    assert "Traceback" not in output, output[-3000:]


async def test_commands_are_recorded_with_the_client_that_sent_them(
    daemon: DaemonProcess, http: httpx.AsyncClient
) -> None:
    async with Watcher(daemon.url) as watcher:
        await ensure_ready(http)
        done = await watcher.wait_for(
            lambda m: m["type"] == "command" and m["name"] == "init" and m["outcome"] == "ok"
        )
    assert done["origin"] == "tester"  # the X-Fxcell-Client name, not just "daemon"
    assert isinstance(done["result"], type(None) | dict | list | int | float | str)


def test_no_simulator_refuses_to_start_without_a_robot_host(tmp_path: Path) -> None:
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "fxcell", "daemon", "--config", str(write_config(tmp_path)),
         "--no-simulator", "--no-record"],
        capture_output=True, text=True, timeout=60, check=False,
        env={**os.environ, "FXCELL_TOKEN": TOKEN},
    )  # fmt: skip
    assert out.returncode == 1
    assert "no robot host configured" in out.stderr


@pytest.mark.injects_faults("the daemon frozen (SIGSTOP) mid-move")
def test_a_frozen_daemon_leaves_no_arm_moving(tmp_path: Path) -> None:
    # SIGSTOP freezes the cell process, the thread that beats to the link included; the
    # link process (its own process group) brakes by itself within the beat timeout.
    with simulator() as sim:
        config = tmp_path / "cell.yaml"
        config.write_text(
            f"robot:\n  host: {sim.host}\ndaemon:\n  token_file: {tmp_path / 'token'}\n"
        )
        with DaemonProcess.start(config, token=TOKEN, extra_args=("--no-record",)) as daemon:
            daemon.wait_connected()
            with httpx.Client(base_url=daemon.url, timeout=30) as http:
                r = http.post("/api/cell/init", headers=headers())
                assert r.status_code == 200, r.text
                lease = {"X-Fxcell-Lease": r.headers["X-Fxcell-Lease"]}
                q = sim.state()["q"]
                target = [q[0] + 2.0, *q[1:]]
                r = http.post(
                    "/api/cell/move_joint",
                    json={"target": target, "velocity_factor": 0.5},
                    headers={**headers(), **lease},
                )
                assert r.status_code == 202, r.text
            deadline = time.monotonic() + 10
            while abs(sim.state()["qd"][0]) < 0.3:
                assert time.monotonic() < deadline, "the move did not reach speed"
                time.sleep(0.01)
            daemon.proc.send_signal(signal.SIGSTOP)
            try:
                deadline = time.monotonic() + 2.0
                while max(map(abs, sim.state()["qd"])) > 1e-6:  # the daemon is still frozen
                    assert time.monotonic() < deadline, "the arm went on moving"
                    time.sleep(0.01)
                assert abs(sim.state()["q"][0] - target[0]) > 0.3  # braked, not arrived
            finally:
                daemon.proc.send_signal(signal.SIGCONT)
