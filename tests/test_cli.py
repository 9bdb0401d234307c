"""The ``fxcell`` command line: version, help, info, error handling."""

from __future__ import annotations

import subprocess
import sys

import pytest

import fxcell
from fxcell.cli import main
from fxcell.config import CONFIG_DIR


def test_version_flag_prints_the_package_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"fxcell {fxcell.__version__}"


def test_package_version_comes_from_the_installed_metadata() -> None:
    import importlib.metadata

    assert fxcell.__version__ == importlib.metadata.version("fxcell")


def test_help_lists_the_subcommands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "usage: fxcell" in out
    assert "info" in out


def test_no_subcommand_prints_help_and_succeeds(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 0
    assert "usage: fxcell" in capsys.readouterr().out


def test_unknown_subcommand_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["no-such-command"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_info_reports_the_robotics_stack(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    for dist in ("ur_rtde", "pin", "ompl", "ruckig", "mcap", "transitions"):
        line = next(line for line in out.splitlines() if line.strip().startswith(dist))
        assert "missing" not in line
    assert "embedded simulator" in out
    assert "arm model: calibrated, read from the controller at connect" in out
    assert "robot link scheduling: " in out  # the UR's link process asks for real time


def test_info_on_a_ned2_cell_names_the_kind_and_where_its_link_runs(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["info", "--config", str(CONFIG_DIR / "ned2-cell.yaml")]) == 0
    out = capsys.readouterr().out
    assert "robot: ned2 (Niryo Ned2), embedded simulator" in out
    assert "arm model: nominal" in out
    assert "robot link: in the cell process" in out
    assert "scheduling" not in out  # no link process to ask real time for


def test_info_names_the_arm_model_and_a_calibration_files_checksum(
    tmp_path: pytest.TempPathFactory, capsys: pytest.CaptureFixture[str]
) -> None:
    from fxcell.calibration import Calibration
    from fxcell.sim.server import default_calibration

    shipped = default_calibration()
    conf = tmp_path / "calibration.conf"  # type: ignore[operator]
    conf.write_text(shipped.to_conf())
    for setting, expected in (
        (str(conf), f"checksum {shipped.checksum}"),
        ("nominal", "arm model: nominal"),
    ):
        cfg = tmp_path / "cell.yaml"  # type: ignore[operator]
        cfg.write_text(f"robot:\n  calibration: {setting}\n")
        assert main(["info", "--config", str(cfg)]) == 0
        assert expected in capsys.readouterr().out
    assert Calibration.nominal().checksum != shipped.checksum


def test_config_error_is_reported_without_a_traceback(
    tmp_path: pytest.TempPathFactory, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "cell.yaml"  # type: ignore[operator]
    bad.write_text("robot:\n  hots: 10.0.0.1\n")
    assert main(["info", "--config", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "robot.hots" in err
    assert "Traceback" not in err


def test_console_script_runs_as_a_module() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "fxcell", "--version"],
        capture_output=True,
        text=True,
        check=True,
        timeout=30,
    )
    assert out.stdout.strip() == f"fxcell {fxcell.__version__}"


def test_the_daemon_logs_at_info_by_default_and_other_commands_at_warning() -> None:
    import logging

    from fxcell.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["daemon"]).default_log_level == logging.INFO
    assert getattr(parser.parse_args(["info"]), "default_log_level", logging.WARNING) == (
        logging.WARNING
    )


def test_a_client_command_on_a_daemon_at_any_free_port_needs_its_url(
    tmp_path: pytest.TempPathFactory,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("FXCELL_URL", raising=False)
    config = tmp_path / "cell.yaml"  # type: ignore[operator]
    config.write_text("daemon:\n  port: 0\n")
    assert main(["status", "--config", str(config)]) == 1
    err = capsys.readouterr().err
    assert "daemon.port is 0" in err
    assert "--url" in err
