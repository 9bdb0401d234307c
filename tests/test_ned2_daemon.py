"""``fxcell daemon --robot ned2`` (``./dev run --robot ned2``): the daemon on the embedded
Ned2 simulator with a Ned2 cell's configuration, driven over HTTP as an operator's client:
its state names the kind, init calibrates the arm, a command a Ned2 cannot do is refused
naming it, the CLI's status says the kind, and Ctrl-C stops it cleanly."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from fxcell.daemon.process import DaemonProcess
from fxcell.robot_specs import NED2_SPEC

TOKEN = "ned2-daemon-token-0123456789abcdef"
HEADERS = {"X-Fxcell-Client": "tester", "Authorization": f"Bearer {TOKEN}"}

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]


def _config(tmp: Path) -> Path:
    # a user's Ned2 cell: the rest comes from the shipped config/ned2-cell.yaml
    path = tmp / "cell.yaml"
    path.write_text(f"robot:\n  kind: ned2\ndaemon:\n  token_file: {tmp / 'token'}\n")
    return path


def _first_robot_state(url: str, within: float = 20.0) -> dict[str, Any]:
    """The robot part of the daemon's state once a robot state has arrived."""
    deadline = time.monotonic() + within
    while (robot := httpx.get(f"{url}/api/state", timeout=10).json()["robot"]) is None:
        assert time.monotonic() < deadline, "no robot state"
        time.sleep(0.05)
    result: dict[str, Any] = robot
    return result


def test_the_daemon_runs_a_ned2_cell_on_its_simulator(tmp_path: Path) -> None:
    args = ("--robot", "ned2", "--sim-time-scale", "0.1")
    with DaemonProcess.start(_config(tmp_path), token=TOKEN, extra_args=args) as daemon:
        assert daemon.wait_connected()["kind"] == "ned2"
        robot = _first_robot_state(daemon.url)
        assert robot["q"] == pytest.approx(NED2_SPEC.home, abs=1e-9)  # it boots at home
        info = httpx.get(f"{daemon.url}/api/info", headers=HEADERS, timeout=10).json()
        assert (info["kind"], info["simulated"]) == ("ned2", True)
        assert info["limits"]["velocity"] == list(NED2_SPEC.limits["velocity"])

        r = httpx.post(f"{daemon.url}/api/cell/init", headers=HEADERS, timeout=60)
        assert r.status_code == 200, r.text
        lease = {"X-Fxcell-Lease": r.headers["X-Fxcell-Lease"]}
        state = httpx.get(f"{daemon.url}/api/state", timeout=10).json()
        assert state["state"] == "running.external_control_ready"
        r = httpx.post(f"{daemon.url}/api/cell/power_off", headers={**HEADERS, **lease}, timeout=10)
        assert r.status_code == 409, r.text
        error = r.json()["error"]
        assert (error["type"], error["detail"]["kind"]) == ("UnsupportedCommandError", "ned2")

        status = subprocess.run(
            [sys.executable, "-m", "fxcell", "status", "--url", daemon.url],
            capture_output=True,
            text=True,
            timeout=60,
            env={**os.environ, "FXCELL_TOKEN": TOKEN},
        )
        assert status.returncode == 0, status.stderr
        assert status.stdout.splitlines()[0].split() == ["robot:", "ned2"]

        # Ctrl-C in the terminal: the daemon brakes, closes the cell and its simulator
        os.killpg(os.getpgid(daemon.proc.pid), signal.SIGINT)
        assert daemon.proc.wait(20) == 0
    output = "\n".join(daemon.output)
    assert "Traceback" not in output, output[-3000:]


def test_a_robot_kind_the_configuration_does_not_name_is_refused(tmp_path: Path) -> None:
    config = str(_config(tmp_path))
    out = subprocess.run(
        [sys.executable, "-m", "fxcell", "daemon", "--config", config, "--robot", "ur3e"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode != 0
    assert "--robot ur3e" in out.stderr, out.stderr
    assert "configures a ned2" in out.stderr
