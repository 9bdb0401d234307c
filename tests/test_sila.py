"""The cell as a SiLA 2 server, driven by the reference package's generic client.

Nothing of fxcell runs on the client side: ``sila2.client.SilaClient`` builds its calls from
the feature definitions the server sends (SiLAService), discovery is the package's
``SilaClient.discover`` / ``SilaDiscoveryBrowser``. The daemons run on simulators in processes
of their own; where crucibles end up is read from the simulator's own object poses.

Discovery runs on loopback only: the test set-up binds zeroconf to 127.0.0.1 (the daemons
announce on the interface of their address, here loopback), so no packet leaves the machine.
Loopback's mDNS is machine-wide, though: a suite running beside this one (another worker,
another checkout) announces its own test cells there, with certificates of their own. The
reference client's browser connects to every server it hears of with the certificates it
was given, and warns (an error here) when one does not verify; so the browser listens only
to the servers this run started (by their SiLA Server UUID, unique to each daemon's state),
as a lab's scheduler would to the cells it was told about.
"""

from __future__ import annotations

import contextlib
import functools
import queue
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import yaml
from sila2.client import SilaClient
from sila2.discovery.browser import SilaDiscoveryBrowser
from sila2.discovery.listener import SilaServiceListener
from sila2.framework import SilaError
from zeroconf import IPVersion, Zeroconf

from fxcell.config import CellConfig
from fxcell.daemon.process import DaemonProcess, free_port
from fxcell.job.plan import location
from fxcell.layout import Layout
from fxcell.testing import SimulatorHandle, brisk_limits, simulator

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]
RUN_LOCK = 600
"""s: a lock held through a whole run (SiLA's lock timeout restarts only with a call under
the lock, and Run Job is one call; 120 s ran out on a busy machine)."""

TOKEN = "sila-test-token-0123456789abcdef"
LAYOUT = Layout(CellConfig.load().layout)
CRUCIBLES = "A1,A2,A3,A4,B1,B2,B3"


class Cell:
    """A simulator and a daemon serving SiLA on it."""

    def __init__(self, sim: SimulatorHandle, daemon: DaemonProcess, name: str, state: Path):
        self.sim = sim
        self.daemon = daemon
        self.name = name
        self.port = int(yaml.safe_load((state / "cell.yaml").read_text())["daemon"]["sila"]["port"])
        self.certificate = (state / "sila-cert.pem").read_bytes()
        self.server_uuid = uuid.UUID((state / "sila-server-uuid").read_text().strip())
        OWN_SERVERS.add(self.server_uuid)

    def client(self) -> SilaClient:
        return SilaClient("127.0.0.1", self.port, root_certs=self.certificate)


OWN_SERVERS: set[uuid.UUID] = set()
"""The SiLA Server UUIDs of the daemons this test process started."""
RUN = uuid.uuid4().hex[:8]
"""Part of this run's server names: two suites at once on one machine never share one."""


def _own_server(name: str) -> bool:
    """Whether a ``<uuid>._sila._tcp.local.`` service is one of this run's daemons."""
    try:
        return uuid.UUID(name.split(".")[0]) in OWN_SERVERS
    except ValueError:
        return False


class _OwnServersListener(SilaServiceListener):
    """The reference client's listener, deaf to SiLA servers this run did not start."""

    def add_service(self, zc: Zeroconf, type_: str, name: str) -> None:
        if _own_server(name):
            super().add_service(zc, type_, name)

    def update_service(self, zc: Zeroconf, type_: str, name: str) -> None:
        if _own_server(name):
            super().update_service(zc, type_, name)


@functools.cache
def _loopback_zeroconf() -> None:
    """The reference client's discovery on loopback only (its default is every interface),
    hearing only this run's servers (see the module's docstring)."""
    import sila2.discovery.browser as browser

    browser.Zeroconf = functools.partial(  # type: ignore[misc]
        Zeroconf, interfaces=["127.0.0.1"], ip_version=IPVersion.V4Only
    )
    browser.SilaServiceListener = _OwnServersListener  # type: ignore[misc]


def start_cell(tmp: Path, name: str) -> Iterator[Cell]:
    args = ["--fusion-time", "20", "--cooling-time", "10", "--crucibles", CRUCIBLES]
    with simulator(time_scale=0.05, extra_args=args) as sim:
        config = {
            "robot": {"host": sim.host},
            "daemon": {
                "token_file": str(tmp / "token"),
                "sila": {"port": free_port(), "server_name": name},
            },
            "limits": brisk_limits(),
            "job": {"database": str(tmp / "job.sqlite3"), "ready_timeout": 30.0},
            "positions_file": str(tmp / "positions.yaml"),
        }
        (tmp / "cell.yaml").write_text(yaml.safe_dump(config))
        with DaemonProcess.start(tmp / "cell.yaml", token=TOKEN, extra_args=["--sila"]) as daemon:
            daemon.wait_connected()
            yield Cell(sim, daemon, name, tmp)


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cell]:
    """The cell most tests share (they use disjoint crucibles)."""
    yield from start_cell(tmp_path_factory.mktemp("cell-1"), f"fxcell test cell 1 {RUN}")


@pytest.fixture
def job_cell(tmp_path: Path) -> Iterator[Cell]:
    """A cell of its own for a run: whatever a run leaves (a fault on an overloaded machine
    stops the arm where it was) stays out of the other tests."""
    yield from start_cell(tmp_path, f"fxcell test job cell {RUN}")


def token(client: SilaClient) -> list[Any]:
    return [client.AuthorizationService.AccessToken(TOKEN)]


def place_of(obj: dict[str, Any]) -> str | None:
    """Where an object of the simulated world is (within 1 mm of a slot), as the job names it."""
    if obj["held"]:
        return "gripper"
    position = np.array(obj["pose"][:3])
    for station in LAYOUT:
        for slot in station.slots:
            if np.linalg.norm(station.grip_pose(slot).position - position) < 1e-3:
                return location(station.name, slot)
    return None


class Locked:
    """``with Locked(client) as metadata:`` the server locked by ``client``."""

    def __init__(self, client: SilaClient, timeout: int = 120) -> None:
        self.client = client
        self.identifier = str(uuid.uuid4())
        self.timeout = timeout

    def __enter__(self) -> list[Any]:
        md = token(self.client)
        self.client.LockController.LockServer(self.identifier, self.timeout, metadata=md)
        return [*md, self.client.LockController.LockIdentifier(self.identifier)]

    def __exit__(self, *exc: object) -> None:
        self.client.LockController.UnlockServer(self.identifier, metadata=token(self.client))


class Watched:
    """``with Watched(feature.Property, metadata) as values:`` a live subscription to an
    observable property: entered once the server sent its current value, so every change
    after that shows (a change made just before may come as the next value: the daemon
    refreshes its properties every few tens of milliseconds)."""

    def __init__(self, prop: Any, metadata: list[Any], within: float = 30.0) -> None:
        self.prop = prop
        self.metadata = metadata
        self.within = within
        self.values: queue.Queue[Any] = queue.Queue()

    def __enter__(self) -> Watched:
        self.subscription = self.prop.subscribe(metadata=self.metadata, callbacks=[self.values.put])
        self.first = self.values.get(timeout=self.within)
        return self

    def __exit__(self, *exc: object) -> None:
        self.subscription.cancel()

    def until(self, value: Any) -> list[Any]:
        """The values shown (the current one first) up to ``value``, or for ``within``
        seconds if it never comes."""
        shown = [self.first]
        with contextlib.suppress(queue.Empty):
            while value not in shown:
                shown.append(self.values.get(timeout=self.within))
        return shown


def run_to_end(cell: Cell, instance: Any, steps: Any = None) -> tuple[list[Any], Any]:
    """Every intermediate response of a Run Job execution, then its responses; fails at
    once when the run faults (a recoverable error nobody here answers), saying why."""
    seen = []
    for step in steps if steps is not None else instance.subscribe_to_intermediate_responses():
        seen.append(step)
        if step.JobState == "fault":
            job = httpx.get(f"{cell.daemon.url}/api/job", timeout=10).json()
            log = "\n".join(cell.daemon.output[-30:])
            pytest.fail(f"the run faulted at {step.Step!r}: {job['message']}\n{log}")
    return seen, instance.get_responses()


def until(cell: Cell, stream: Any, condition: Callable[[Any], bool]) -> list[Any]:
    """Intermediate responses up to the first one that meets ``condition`` (fails on a
    fault, or when the run ends first)."""
    seen = []
    for step in stream:
        seen.append(step)
        if step.JobState == "fault":
            job = httpx.get(f"{cell.daemon.url}/api/job", timeout=10).json()
            pytest.fail(f"the run faulted at {step.Step!r}: {job['message']}")
        if condition(step):
            return seen
    pytest.fail(f"the run's responses ended first: {[s.Step for s in seen[-3:]]}")


# ----------------------------------------------------------------- one cell


def test_discovered_by_name_with_its_certificate(cell: Cell) -> None:
    _loopback_zeroconf()
    client = SilaClient.discover(server_name=cell.name, root_certs=cell.certificate, timeout=30)
    with client:
        assert client.SiLAService.ServerName.get() == cell.name
        assert client.SiLAService.ServerType.get() == "RobotCell"
        implemented = set(client.SiLAService.ImplementedFeatures.get())
        for feature in (
            "org.silastandard/core/LockController/v1",
            "org.silastandard/core/ErrorRecoveryService/v1",
            "org.silastandard/core/SimulationController/v1",
            "org.fxcell/robot/CellController/v1",
            "org.fxcell/robot/JobController/v1",
            "org.fxcell/robot/LabwareTransferManipulatorController/v1",
        ):
            assert any(f.lower() == feature.lower() for f in implemented), (feature, implemented)
        assert client.SimulationController.SimulationModeActive.get(metadata=token(client)) is False


def test_calls_without_the_token_are_refused(cell: Cell) -> None:
    with cell.client() as client:
        with pytest.raises(SilaError, match="AccessToken"):
            client.CellController.Init()
        wrong = [client.AuthorizationService.AccessToken("not-the-token")]
        with pytest.raises(SilaError, match="InvalidAccessToken"):
            client.CellController.Init(metadata=wrong)


def test_locked_cell_refuses_other_clients_and_the_page_shows_the_lock(cell: Cell) -> None:
    with cell.client() as owner, cell.client() as other, Locked(owner) as md:
        assert other.LockController.IsLocked.get(metadata=token(other)) is True
        with pytest.raises(SilaError, match="LockIdentifier"):
            other.CellController.Init(metadata=token(other))
        wrong = [*token(other), other.LockController.LockIdentifier("guess")]
        with pytest.raises(SilaError, match="InvalidLockIdentifier"):
            other.CellController.Init(metadata=wrong)
        # One control lease: an HTTP client is refused too, and the page shows the holder.
        state = httpx.get(f"{cell.daemon.url}/api/state", timeout=10).json()
        assert state["control"]["client"] == "SiLA client (LockController)"
        refused = httpx.post(
            f"{cell.daemon.url}/api/cell/init",
            headers={"Authorization": f"Bearer {TOKEN}"},
            timeout=10,
        )
        assert refused.status_code == 409, refused.text
        assert refused.json()["error"]["type"] == "ControlHeldError"
        with Watched(owner.CellController.ControlHolder, token(owner)) as holders:
            shown = holders.until("SiLA client (LockController)")
            assert shown[-1] == "SiLA client (LockController)", shown
        owner.CellController.Init(metadata=md)
        owner.CellController.MoveToPosition("home", metadata=md)
        with pytest.raises(SilaError, match="InvalidArgument: UnknownPositionError"):
            owner.CellController.MoveToPosition("nowhere", metadata=md)
        assert owner.CellController.CellState.get(metadata=token(owner)).startswith("running")
        # Stop needs the token, not the lock.
        assert other.CellController.Stop(metadata=token(other)).Stopped is False
    with cell.client() as client:
        assert client.LockController.IsLocked.get(metadata=token(client)) is False


def test_stop_over_sila_stops_a_move_started_over_http(cell: Cell) -> None:
    headers = {"Authorization": f"Bearer {TOKEN}", "X-Fxcell-Client": "engineer"}
    with (
        httpx.Client(base_url=cell.daemon.url, headers=headers, timeout=30) as http,
        cell.client() as client,
    ):
        r = http.post("/api/cell/init")
        assert r.status_code == 200, r.text
        http.headers["X-Fxcell-Lease"] = r.headers["X-Fxcell-Lease"]
        http.post("/api/cell/go_home", params={"wait": True}).raise_for_status()
        home = http.get("/api/info").json()["home"]
        with Watched(client.CellController.CellState, token(client)) as states:
            op = http.post("/api/cell/move_joint", json={"target": [home[0] + 2.5, *home[1:]]})
            assert op.status_code == 202, op.text
            op_id = op.json()["id"]
            shown = states.until("running.moving")
        assert shown[-1] == "running.moving", (
            f"the move never showed in CellState (it showed {shown}); the move: "
            f"{http.get(f'/api/operations/{op_id}').json()}\n" + "\n".join(cell.daemon.output[-30:])
        )
        assert client.CellController.Stop(metadata=token(client)).Stopped is True
        ended = http.post(f"/api/operations/{op_id}/wait", params={"timeout": 10}).json()
        assert ended["error"]["type"] == "MoveStoppedError", ended
        http.post("/api/cell/go_home", params={"wait": True}).raise_for_status()
        http.delete("/api/control").raise_for_status()


@pytest.mark.long  # a 4-sample run: minutes of robot time (./dev test -m long)
def test_four_sample_run_paused_and_resumed_to_its_end_with_a_response_per_step(
    job_cell: Cell,
) -> None:
    cell = job_cell
    samples = [
        {"SampleId": f"S{i}", "RackSlot": f"A{i}", "MachineSlot": f"A{i}", "TraySlot": f"A{i}"}
        for i in range(1, 5)
    ]
    with cell.client() as client, Locked(client, timeout=RUN_LOCK) as md:
        client.CellController.Init(metadata=md)
        client.CellController.GripperActivate(metadata=md)
        instance = client.JobController.RunJob("four samples", samples, metadata=md)
        stream = instance.subscribe_to_intermediate_responses()
        steps = until(cell, stream, lambda s: s.Step.startswith("place the crucible of sample S2"))
        # paused by the scheduler: the step under way ends first, then the run holds
        client.JobController.Pause(metadata=md)
        steps += until(cell, stream, lambda s: s.JobState == "paused")
        assert httpx.get(f"{cell.daemon.url}/api/job", timeout=10).json()["state"] == "paused"
        assert max(map(abs, cell.sim.state()["qd"])) < 1e-3  # the arm at rest
        client.JobController.Resume(metadata=md)
        rest, result = run_to_end(cell, instance, stream)
        steps += rest
        locations = client.JobController.SampleLocations.get(metadata=token(client))
    assert result.StepsDone == steps[-1].StepsTotal
    assert steps[-1].JobState == "done"
    done = [s.StepsDone for s in steps]
    assert done == sorted(done)
    # every step was reported (each step's text, in order, at least once)
    texts = [s.Step for s in steps]
    assert any(t.startswith("pick the crucible of sample S4 from rack slot A4") for t in texts)
    assert any(t.startswith("place the bead of sample S1 on tray slot A1") for t in texts)
    assert set(range(done[0], result.StepsDone + 1)) <= set(done)  # no step left out
    world = cell.sim.objects()
    for i in range(1, 5):
        assert place_of(world[f"crucible-A{i}"]) == f"rack:A{i}"
        assert place_of(world[f"crucible-A{i}.bead"]) == f"tray:A{i}"
    assert {(s.SampleId, s.Crucible, s.Bead) for s in locations} == {
        (f"S{i}", f"rack:A{i}", f"tray:A{i}") for i in range(1, 5)
    }


def test_paused_run_recovered_through_error_recovery(job_cell: Cell) -> None:
    cell = job_cell
    samples = [{"SampleId": "R1", "RackSlot": "B1", "MachineSlot": "A1", "TraySlot": "B1"}]
    with cell.client() as client, Locked(client, timeout=RUN_LOCK) as md:
        client.CellController.Init(metadata=md)
        client.CellController.GripperActivate(metadata=md)
        instance = client.JobController.RunJob("recovery", samples, metadata=md)
        steps = instance.subscribe_to_intermediate_responses()
        # abort in the middle of carrying the crucible
        until(cell, steps, lambda s: s.Step.startswith("place the crucible of sample R1"))
        client.JobController.Abort(metadata=md)
        errors = client.ErrorRecoveryService.RecoverableErrors.subscribe(metadata=token(client))
        pending = next(e for e in errors if e)
        errors.cancel()
        (error,) = pending
        assert error.CommandExecutionUUID == str(instance.execution_uuid)
        assert error.ErrorIdentifier == "ObjectLocationUnknown"
        assert "sample R1" in error.ErrorMessage
        options = {o.Identifier for o in error.ContinuationOptions}
        truth = place_of(cell.sim.objects()["crucible-B1"])
        assert truth in options, (truth, options)
        with pytest.raises(SilaError, match="UnknownContinuationOption"):
            client.ErrorRecoveryService.ExecuteContinuationOption(
                error.CommandExecutionUUID, "nowhere", "", metadata=md
            )
        client.ErrorRecoveryService.ExecuteContinuationOption(
            error.CommandExecutionUUID, truth, "", metadata=md
        )
        rest, result = run_to_end(cell, instance, steps)
        assert rest[-1].JobState == "done"
        assert result.StepsDone == rest[-1].StepsTotal
        assert client.ErrorRecoveryService.RecoverableErrors.get(metadata=token(client)) == []
    world = cell.sim.objects()
    assert place_of(world["crucible-B1"]) == "rack:B1"
    assert place_of(world["crucible-B1.bead"]) == "tray:B1"


def test_transfer_between_two_slots_lands_within_1_mm(cell: Cell) -> None:
    with cell.client() as client, Locked(client) as md:
        client.CellController.Init(metadata=md)
        client.CellController.GripperActivate(metadata=md)
        sites = client.LabwareTransferManipulatorController.Sites.get(metadata=token(client))
        assert {"rack/B2", "rack/D4"} <= set(sites)
        with pytest.raises(SilaError, match="HandoverPositionUnknown"):
            client.LabwareTransferManipulatorController.GetLabware(
                {"Position": "rack", "SubPosition": "Z9"}, metadata=md
            )
        client.LabwareTransferManipulatorController.TransferLabware(
            {"Position": "rack", "SubPosition": "B2"},
            {"Position": "rack", "SubPosition": "D4"},
            metadata=md,
        )
        obj = cell.sim.objects()["crucible-B2"]
        target = LAYOUT.station("rack").grip_pose("D4").position
        assert not obj["held"]
        assert np.linalg.norm(np.array(obj["pose"][:3]) - target) < 1e-3
        client.LabwareTransferManipulatorController.TransferLabware(
            {"Position": "rack", "SubPosition": "D4"},
            {"Position": "rack", "SubPosition": "B2"},
            metadata=md,
        )
    assert place_of(cell.sim.objects()["crucible-B2"]) == "rack:B2"


# ----------------------------------------------------------------- two cells


def test_two_cells_discovered_and_driven_at_once(
    cell: Cell, tmp_path_factory: pytest.TempPathFactory
) -> None:
    _loopback_zeroconf()
    second = start_cell(tmp_path_factory.mktemp("cell-2"), f"fxcell test cell 2 {RUN}")
    other = next(second)
    try:
        names = {cell.name: cell, other.name: other}
        with SilaDiscoveryBrowser(root_certs=cell.certificate + other.certificate) as browser:
            found: dict[str, SilaClient] = {}
            deadline = time.monotonic() + 60
            while set(found) != set(names):
                assert time.monotonic() < deadline, f"discovered only {sorted(found)}"
                for client in browser.clients:
                    found.setdefault(client.SiLAService.ServerName.get(), client)
                time.sleep(0.1)
            uuids = {c.SiLAService.ServerUUID.get() for c in found.values()}
            assert len(uuids) == 2
            failures: list[BaseException] = []

            def drive(client: SilaClient, source: str, dest: str) -> None:
                try:
                    with Locked(client) as md:
                        client.CellController.Init(metadata=md)
                        client.CellController.GripperActivate(metadata=md)
                        client.LabwareTransferManipulatorController.TransferLabware(
                            {"Position": "rack", "SubPosition": source},
                            {"Position": "rack", "SubPosition": dest},
                            metadata=md,
                        )
                except BaseException as exc:
                    failures.append(exc)

            threads = [
                threading.Thread(target=drive, args=(found[cell.name], "B3", "D3")),
                threading.Thread(target=drive, args=(found[other.name], "A4", "D2")),
            ]
            for t in threads:
                t.start()
            for t in threads:
                t.join(300)
            assert not failures, failures
        assert place_of(cell.sim.objects()["crucible-B3"]) == "rack:D3"
        assert place_of(other.sim.objects()["crucible-A4"]) == "rack:D2"
        assert place_of(cell.sim.objects()["crucible-A4"]) == "rack:A4"  # each its own
        assert place_of(other.sim.objects()["crucible-B3"]) == "rack:B3"
    finally:
        second.close()
