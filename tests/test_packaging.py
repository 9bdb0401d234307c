"""The light client for the lab PC: ``pip install "fxcell[client]"`` without the motion stack.

A fresh virtual environment gets fxcell from this checkout (a real, non-editable install of
the wheel built from it),
with nothing but the base dependencies; the CLI and RemoteCell then drive a daemon that
runs from the development environment, and the cell-only commands say what to install.
"""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
from collections.abc import Iterator
from pathlib import Path

import pytest

from fxcell.daemon.process import DaemonProcess

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "packaging-token-0123456789abcdef"

# installing into fresh virtual environments takes 30-90 s on a busy machine
pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """fxcell's wheel built once from this checkout (the build compiles the native
    kinematics), installed by both environments below as pip would install the checkout."""
    where = tmp_path_factory.mktemp("wheel")
    out = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--disable-pip-version-check",
         "-w", str(where), str(ROOT)],
        capture_output=True, text=True, timeout=900, check=False,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    (built,) = where.glob("fxcell-*.whl")
    return built


@pytest.fixture(scope="module")
def light_venv(tmp_path_factory: pytest.TempPathFactory, wheel: Path) -> Path:
    venv = tmp_path_factory.mktemp("light") / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    pip = [
        str(venv / "bin" / "python"),
        "-m",
        "pip",
        "install",
        "-q",
        "--disable-pip-version-check",
    ]
    out = subprocess.run(
        [*pip, f"{wheel}[client]"], capture_output=True, text=True, timeout=600, check=False
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return venv


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    tmp = tmp_path_factory.mktemp("daemon")
    config = tmp / "cell.yaml"
    config.write_text(f"robot:\n  host: null\ndaemon:\n  token_file: {tmp / 'token'}\n")
    with DaemonProcess.start(config, token=TOKEN, extra_args=("--sim-time-scale", "0.2")) as d:
        d.wait_connected()
        yield d


def _run(venv: Path, *args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["FXCELL_TOKEN"] = TOKEN
    return subprocess.run(
        [str(venv / "bin" / args[0]), *args[1:]],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd,
        env=env,
        check=False,
    )


def test_the_light_client_has_no_motion_stack(light_venv: Path, tmp_path: Path) -> None:
    probe = (
        "import importlib.util as u; import fxcell.client, fxcell.cli;"
        "print(sorted(m for m in ('numpy', 'pinocchio', 'ompl', 'ruckig', 'rtde_control',"
        " 'fastapi', 'mcap') if u.find_spec(m)))"
    )
    out = _run(light_venv, "python", "-c", probe, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_the_light_cli_drives_a_running_daemon(
    light_venv: Path, daemon: DaemonProcess, tmp_path: Path
) -> None:
    out = _run(light_venv, "fxcell", "status", "--url", daemon.url, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "state:" in out.stdout
    out = _run(light_venv, "fxcell", "init", "--url", daemon.url, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    code = (
        "import asyncio, os\n"
        "from fxcell.client import RemoteCell\n"
        "async def main():\n"
        f"    async with RemoteCell({daemon.url!r}, os.environ['FXCELL_TOKEN']) as cell:\n"
        "        print((await cell.get_robot_mode()).name)\n"
        "asyncio.run(main())\n"
    )
    out = _run(light_venv, "python", "-c", code, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "RUNNING" in out.stdout


def test_cell_commands_of_the_light_client_say_what_to_install(
    light_venv: Path, tmp_path: Path
) -> None:
    for command in (["daemon"], ["sim"], ["replay", "x.mcap"]):
        out = _run(light_venv, "fxcell", *command, cwd=tmp_path)
        assert out.returncode == 1, (command, out.stdout, out.stderr)
        assert "pip install 'fxcell[cell]'" in out.stderr, out.stderr
        assert "Traceback" not in out.stderr


def test_a_full_install_runs_info_and_a_daemon_from_any_directory(
    tmp_path_factory: pytest.TempPathFactory, wheel: Path
) -> None:
    # config/ and statecharts/ ship inside the wheel: nothing is read from this checkout.
    # fxcell itself is a real (non-editable) install; its dependencies are this environment's,
    # reached through a .pth file (copying pinocchio and the rest again took 1-2 min).
    venv = tmp_path_factory.mktemp("full") / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    python = str(venv / "bin" / "python")
    site = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True, text=True, check=True, timeout=60,
    ).stdout.strip()  # fmt: skip
    deps = sorted({sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]})
    # addsitedir, so that their own .pth files (cmeel's prefix for pinocchio and coal) count
    (Path(site) / "fxcell-test-deps.pth").write_text(
        "".join(f"import site; site.addsitedir({d!r})\n" for d in deps)
    )
    out = subprocess.run(
        [python, "-m", "pip", "install", "-q", "--no-deps", "--disable-pip-version-check",
         str(wheel)],
        capture_output=True, text=True, timeout=900, check=False,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    where = _run(venv, "python", "-c", "import fxcell; print(fxcell.__file__)", cwd=venv)
    assert where.stdout.startswith(site), where.stdout  # the wheel's copy, not this checkout
    # hatch_build.py put the mypyc-compiled inverse kinematics in the wheel
    kin = _run(venv, "python", "-c", "import fxcell.motion.kinematics as k; print(k.__file__)")
    assert kin.stdout.strip().endswith(sysconfig.get_config_var("EXT_SUFFIX")), kin
    elsewhere = tmp_path_factory.mktemp("elsewhere")
    out = _run(venv, "fxcell", "info", cwd=elsewhere)
    assert out.returncode == 0, out.stderr
    assert "scene: table" in out.stdout
    assert "stations: rack (4x4 crucible), tray (4x4 bead)" in out.stdout
    token_file = elsewhere / "token"
    config = elsewhere / "cell.yaml"
    config.write_text(f"daemon:\n  token_file: {token_file}\n")  # everything else: defaults
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    proc = subprocess.Popen(
        [str(venv / "bin" / "fxcell"), "daemon", "--config", str(config),
         "--port", "0", "--no-record", "--sim-time-scale", "0.2"],
        cwd=elsewhere, env={**env, "FXCELL_TOKEN": TOKEN},
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if "ready (" in line:
                break
        assert any("ready (cell connected" in line for line in lines), "".join(lines)
    finally:
        proc.terminate()
        proc.communicate(timeout=15)
