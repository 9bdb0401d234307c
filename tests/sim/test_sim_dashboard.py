"""The simulator's process, CLI and Dashboard server, seen by the real ur_rtde DashboardClient."""

from __future__ import annotations

import asyncio
import signal
import socket
import subprocess
import sys
import threading

import pytest
from dashboard_client import DashboardClient
from waiting import until, wait_until

from fxcell.cli import main
from fxcell.errors import InvalidArgumentError, SimulatorError
from fxcell.link.embedded import EmbeddedSimulator, address_is_free, free_loopback_host
from fxcell.testing import SimulatorHandle, simulator


class RawDashboard:
    """A plain-socket Dashboard client, to check the exact reply strings."""

    def __init__(self, host: str) -> None:
        self.sock = socket.create_connection((host, 29999), timeout=5)
        self.file = self.sock.makefile("rwb")
        self.banner = self.file.readline().decode().rstrip("\n")

    def ask(self, line: str) -> str:
        self.file.write(line.encode() + b"\n")
        self.file.flush()
        return self.file.readline().decode().rstrip("\n")

    def close(self) -> None:
        self.file.close()
        self.sock.close()


def test_life_cycle_power_on_brake_release_load_play_pause_stop(sim: SimulatorHandle) -> None:
    d = DashboardClient(sim.host)
    d.connect()
    try:
        assert d.robotmode() == "Robotmode: POWER_OFF"
        d.powerOn()
        wait_until(lambda: d.robotmode() == "Robotmode: IDLE", what="IDLE")
        d.brakeRelease()
        wait_until(lambda: d.robotmode() == "Robotmode: RUNNING", what="RUNNING")
        d.loadURP("fxcell.urp")
        assert d.getLoadedProgram() == "Loaded program: /programs/fxcell.urp"
        assert d.programState() == "STOPPED fxcell.urp"
        assert not d.running()
        d.play()
        assert d.running()
        assert d.programState() == "PLAYING fxcell.urp"
        d.pause()
        assert d.programState() == "PAUSED fxcell.urp"
        d.play()  # resumes
        assert d.programState() == "PLAYING fxcell.urp"
        d.stop()
        assert d.programState() == "STOPPED fxcell.urp"
        d.powerOff()
        assert d.robotmode() == "Robotmode: POWER_OFF"
        assert d.isInRemoteControl()
        assert d.polyscopeVersion().startswith("5.25.1")
        assert d.getSerialNumber() == "20235500001"
        assert d.getRobotModel() == "UR3"
    finally:
        d.disconnect()


def test_every_reply_form_is_the_polyscope_5_string(sim: SimulatorHandle) -> None:
    d = RawDashboard(sim.host)
    try:
        assert d.banner == "Connected: Universal Robots Dashboard Server"
        expected = {
            "robotmode": "Robotmode: POWER_OFF",
            "safetymode": "Safetymode: NORMAL",
            "safetystatus": "Safetystatus: NORMAL",
            "programState": "STOPPED null",
            "running": "Program running: false",
            "get loaded program": "No program loaded",
            "PolyscopeVersion": "URSoftware 5.25.1.1 (Sep 03 2025)",
            "get serial number": "20235500001",
            "get robot model": "UR3",
            "is in remote control": "true",
            "play": "Failed to execute: play",
            "stop": "Stopped",
            "pause": "Failed to execute: pause",
            "load missing.urp": "File not found: /programs/missing.urp",
            "load notes.txt": "Error while loading program: /programs/notes.txt",
            "load /programs/external_control.urp": (
                "Loading program: /programs/external_control.urp"
            ),
            "isProgramSaved": "true external_control.urp",
            "popup hello": "showing popup",
            "close popup": "closing popup",
            "close safety popup": "closing safety popup",
            "addToLog hello": "Added log message",
            "unlock protective stop": (
                "Cannot unlock protective stop, safetymode is not PROTECTIVE_STOP"
            ),
            "get operational mode": "NONE",
            "set operational mode manual": "Operational mode 'manual' is set",
            "clear operational mode": (
                "No longer controlling the operational mode. Current operational mode: 'manual'."
            ),
            "load installation default.installation": (
                "Loading installation: default.installation"
            ),
            "load installation missing.installation": "File not found: missing.installation",
            "load installation notes.txt": "Failed to load installation: notes.txt",
            "saveLog": "Log saved to disk",
            "version": "Version: 5.25.1.1",
            "addToLog": "No log message to add",
            "power on": "Powering on",
            "brake release": "Brake releasing",
            "power off": "Powering off",
            "restart safety": "Restarting safety",
            "no such command": "could not understand: 'no such command'",
        }
        for request, reply in expected.items():
            assert d.ask(request) == reply, request
        assert d.ask("quit") == "Disconnected"
        assert d.file.readline() == b""  # the server closed the connection
    finally:
        d.close()


@pytest.mark.injects_faults("the pendant switched to Local control")
def test_local_control_refuses_robot_commands_but_answers_queries(sim: SimulatorHandle) -> None:
    sim.inject("local_control")
    refusal = sim.dashboard("power on")
    assert refusal.startswith("Command is not allowed due to safety reasons")
    for command in ("brake release", "load fxcell.urp", "play", "stop", "unlock protective stop"):
        assert sim.dashboard(command) == refusal, command
    assert sim.dashboard("is in remote control") == "false"
    assert sim.dashboard("robotmode") == "Robotmode: POWER_OFF"
    d = DashboardClient(sim.host)
    d.connect()
    try:
        assert not d.isInRemoteControl()
        d.powerOn()  # the client does not check this reply: the robot must stay off
        assert d.robotmode() == "Robotmode: POWER_OFF"
        sim.inject("remote_control")
        assert d.isInRemoteControl()
        d.powerOn()
        wait_until(lambda: d.robotmode() == "Robotmode: IDLE", what="IDLE")
    finally:
        d.disconnect()


def test_restart_safety_goes_through_recovery_to_power_off(sim: SimulatorHandle) -> None:
    sim.bring_up()
    assert sim.dashboard("restart safety") == "Restarting safety"
    assert sim.dashboard("robotmode") == "Robotmode: POWER_OFF"
    wait_until(lambda: sim.dashboard("safetymode") == "Safetymode: NORMAL", what="NORMAL")


def test_shutdown_ends_the_simulator_process() -> None:
    with simulator() as sim:
        assert sim.dashboard("shutdown") == "Shutting down"
        wait_until(lambda: not sim.running, timeout=10, what="process exit")


@pytest.mark.injects_faults("faults injected through the CLI")
def test_cli_inject_reaches_the_simulator_and_rejects_unknown_faults(
    sim: SimulatorHandle, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["sim", "inject", "--host", sim.host, "safeguard_stop"]) == 0
    assert "safeguard stop" in capsys.readouterr().out
    assert sim.dashboard("safetymode") == "Safetymode: SAFEGUARD_STOP"
    with pytest.raises(SystemExit) as exc:
        main(["sim", "inject", "--host", sim.host, "meteor_strike"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err
    with pytest.raises(InvalidArgumentError, match="stall_rtde needs SECONDS"):
        sim.inject("stall_rtde")


def test_help_lists_the_sim_subcommand(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["sim", "--help"])
    out = capsys.readouterr().out
    assert "--time-scale" in out
    assert "inject" in out


def test_simulators_run_side_by_side_on_their_own_addresses() -> None:
    sims = [simulator() for _ in range(3)]
    try:
        for s in sims:
            s.start()
        hosts = {s.host for s in sims}
        assert len(hosts) == 3
        for i, s in enumerate(sims):
            s.set_joints([0.1 * (i + 1), -1.5, 0.5, -1.0, -1.5, 0.0])
        for i, s in enumerate(sims):
            assert s.state()["q"][0] == pytest.approx(0.1 * (i + 1))
        sims[0].dashboard("power on")
        assert sims[1].dashboard("robotmode") == "Robotmode: POWER_OFF"
    finally:
        for s in sims:
            s.stop()


def test_a_taken_address_is_reported_not_hung() -> None:
    with simulator() as first:
        assert not address_is_free(first.host)
        second = EmbeddedSimulator(first.host, time_scale=0.05, startup_timeout=20)
        with pytest.raises(SimulatorError, match="exit code 2"):
            second.start()
        assert first.dashboard("robotmode") == "Robotmode: POWER_OFF"


def test_fxcell_sim_serves_until_sigint() -> None:
    host = free_loopback_host()
    proc = subprocess.Popen(
        [sys.executable, "-m", "fxcell", "sim", "--host", host, "--time-scale", "0.05"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "listening" in line
        assert host in line
        d = RawDashboard(host)
        assert d.banner.startswith("Connected: Universal Robots")
        d.close()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(10) == 0
    finally:
        proc.kill()
        proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


async def test_simulator_context_manager_also_works_with_async_with() -> None:
    async with simulator() as sim:
        assert sim.running
        assert await asyncio.to_thread(sim.dashboard, "robotmode") == "Robotmode: POWER_OFF"
    assert not sim.running


def _listening_on_a_free_address(sock: socket.socket, port: int) -> str:
    """Bind ``sock`` to ``port`` on a free loopback address and listen: the address is chosen
    and taken in one step, so another test cannot take it in between. SO_REUSEADDR as the
    simulator's own bind has it: a connection in TIME_WAIT left there by an earlier test does
    not refuse the bind (a listening socket still refuses the simulator's)."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    for _ in range(50):
        host = free_loopback_host()
        try:
            sock.bind((host, port))
        except OSError:  # taken since free_loopback_host looked: pick another address
            continue
        sock.listen()
        return host
    raise AssertionError(f"no loopback address with port {port} free in 50 tries")


@pytest.mark.parametrize("ending", ["stopped", "port taken"])
async def test_the_simulator_stops_only_once_its_dynamic_model_is_built(
    ending: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a daemon thread still building the model (inside Pinocchio's C++) when the interpreter
    # exits aborts the process: `fxcell sim` stopped at once after listening exited -6, and
    # so did one that found its address taken (4 workers beside a CPU burner)
    import fxcell.sim.dynamics
    from fxcell.protocol import DASHBOARD_PORT
    from fxcell.sim.server import SimServer

    building = threading.Event()
    release = threading.Event()

    class SlowModel:
        def __init__(self) -> None:
            building.set()
            release.wait(30)

    monkeypatch.setattr(fxcell.sim.dynamics, "ArmDynamics", SlowModel)
    with socket.socket() as taken:
        if ending == "port taken":
            host = _listening_on_a_free_address(taken, DASHBOARD_PORT)
        else:
            host = free_loopback_host()
        server = SimServer(host, time_scale=0.05)
        failed = threading.Event()  # the port was found taken (the hub closed on the way out)
        close_hub = server.hub.close

        def closing_hub() -> None:
            failed.set()
            close_hub()

        monkeypatch.setattr(server.hub, "close", closing_hub)
        serving = asyncio.create_task(
            server.serve(announce=False, handle_signals=False, on_listening=server.request_stop)
        )
        assert await asyncio.to_thread(building.wait, 30)

        def ports_closed() -> bool:
            return bool(server._servers) and not any(s.is_serving() for s in server._servers)

        # stopped, or failed: without the wait serve would have ended in that same step
        await until(failed.is_set if ending == "port taken" else ports_closed, "serving to end")
        assert not serving.done()  # waiting for the model
        release.set()
        if ending == "port taken":
            with pytest.raises(OSError, match=r"(?i)in use"):
                await asyncio.wait_for(serving, 30)
        else:
            await asyncio.wait_for(serving, 30)
    loader = server._dynamics_loader
    assert loader is not None
    assert not loader.is_alive()
