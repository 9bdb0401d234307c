"""Configuration loading: defaults, referenced files, and errors that name the bad key."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from fxcell.config import CONFIG_DIR, HOME_JOINTS, SEED_TCP, CellConfig, default_state_dir
from fxcell.errors import ConfigError, FxcellError
from fxcell.robot_specs import NED2_SPEC


def test_shipped_config_loads_with_the_seed_defaults() -> None:
    config = CellConfig.load()
    assert config.robot.host is None
    assert config.tool.tcp == SEED_TCP
    assert config.home == pytest.approx(HOME_JOINTS)
    assert config.limits.acceleration == (0.7, 0.7, 0.7, 1.4, 1.4, 1.4)
    table = next(o for o in config.scene.objects if o.name == "table")
    assert table.size == (1.15, 0.73, 0.04)
    assert table.position == (-0.075, -0.065, -0.02)


def test_unknown_key_is_named_in_the_error(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text("tool:\n  tpc: [0, 0, 0, 0, 0, 0]\n")
    with pytest.raises(ConfigError, match=r"tool\.tpc"):
        CellConfig.load(path)


def test_config_errors_are_fxcell_errors_and_value_errors(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text("robot: [not, a, mapping]\n")
    with pytest.raises(FxcellError):
        CellConfig.load(path)
    with pytest.raises(ValueError, match="robot"):
        CellConfig.load(path)


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        CellConfig.load(tmp_path / "absent.yaml")


def test_invalid_yaml_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text("robot: {host: [\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        CellConfig.load(path)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, math.nan])
def test_non_positive_or_non_finite_limits_are_rejected(bad: float) -> None:
    with pytest.raises(ConfigError, match=r"limits\.acceleration"):
        CellConfig.from_dict({"limits": {"acceleration": [bad, 1, 1, 1, 1, 1]}})


def test_limits_file_is_read_relative_to_the_cell_file(tmp_path: Path) -> None:
    (tmp_path / "lim.yaml").write_text("jerk: [5, 5, 5, 5, 5, 5]\n")
    (tmp_path / "cell.yaml").write_text("limits_file: lim.yaml\n")
    assert CellConfig.load(tmp_path / "cell.yaml").limits.jerk == (5.0,) * 6


def test_a_cell_without_a_config_plans_in_the_shipped_scene() -> None:
    from fxcell.cell import Cell

    cell = Cell(host="192.0.2.1")  # not opened: nothing connects
    shipped = CellConfig.load()
    assert cell.config.scene.objects  # never an empty scene
    assert cell.config.scene == shipped.scene
    assert cell.config.tool == shipped.tool
    assert cell.config.limits == shipped.limits
    assert cell.host == "192.0.2.1"


def test_a_user_config_overrides_the_shipped_one_and_inherits_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text("robot:\n  host: 10.0.0.5\nio:\n  signals:\n    lamp: DO4\n")
    config = CellConfig.load(path)
    assert config.robot.host == "10.0.0.5"
    assert config.robot.external_control == "script"  # shipped default, merged key by key
    assert [o.name for o in config.scene.objects] == ["table"]
    assert set(config.layout.stations) == {"rack", "tray", "machine", "moulds"}
    assert config.io.signals["lamp"] == "DO4"
    assert config.io.signals["machine_done"] == "DI2"
    assert config.positions_file == tmp_path / "positions.yaml"
    assert config.job.database == tmp_path / "job.sqlite3"


def test_the_job_section_has_defaults_and_rejects_typos(tmp_path: Path) -> None:
    cfg = CellConfig.load()
    assert (cfg.job.manual, cfg.job.start_timeout, cfg.job.database) == (
        False,
        10.0,
        default_state_dir() / "job.sqlite3",
    )
    (tmp_path / "cell.yaml").write_text("job: {database: runs/job.db}\n")
    assert CellConfig.load(tmp_path / "cell.yaml").job.database == tmp_path / "runs" / "job.db"
    with pytest.raises(ConfigError, match=r"job\.done_timout"):
        CellConfig.from_dict({"job": {"done_timout": 5}})
    with pytest.raises(ConfigError, match=r"job\.start_timeout"):
        CellConfig.from_dict({"job": {"start_timeout": 0}})


def test_yaml_is_parsed_as_safe_load_parses_it() -> None:
    import yaml

    from fxcell.config import CONFIG_DIR, parse_yaml

    for path in sorted(CONFIG_DIR.glob("*.yaml")):
        text = path.read_text()
        assert parse_yaml(text) == yaml.safe_load(text), path.name
    with pytest.raises(yaml.YAMLError):  # no Python objects from a file
        parse_yaml("!!python/object/apply:os.system ['true']")


def test_a_text_parsed_again_gives_objects_of_its_own() -> None:
    # parse_yaml keeps the parses of the texts it has seen: what a caller changes in its
    # result never reaches the next caller of the same text
    import yaml

    from fxcell.config import parse_yaml

    text = "a: {b: [1, 2]}\nc: &x [3]\nd: *x\n"
    first = parse_yaml(text)
    first["a"]["b"].append(99)
    first["c"].append(4)
    del first["d"]
    second = parse_yaml(text)
    assert second == {"a": {"b": [1, 2]}, "c": [3], "d": [3]}
    assert second["c"] is second["d"]  # an alias is still one object, as a parse makes it
    with pytest.raises(yaml.YAMLError):  # a bad text fails every time, nothing is kept
        parse_yaml("a: [")
    with pytest.raises(yaml.YAMLError):
        parse_yaml("a: [")


# ----------------------------------------------------------------- robot kinds


def test_a_ned2_config_takes_the_ned2s_limits_home_and_gripper_tcp() -> None:
    config = CellConfig.from_dict({"robot": {"kind": "ned2"}})
    assert config.limits.position_min == NED2_SPEC.position_min
    assert config.limits.position_max == NED2_SPEC.position_max
    assert config.limits.velocity == (1.57, 1.047, 1.57, 3.14, 3.14, 3.14)
    assert config.limits.acceleration == (2.0, 0.8, 2.0, 3.0, 3.0, 3.0)
    assert config.home == (0.0, 0.3, -1.3, 0.0, 0.0, 0.0)
    assert config.tool.tcp == pytest.approx((0.075, 0.0, 0.0, 0.0, math.pi / 2, 0.0))
    # what the user gives is kept, the rest is the kind's
    config = CellConfig.from_dict(
        {"robot": {"kind": "ned2"}, "limits": {"velocity": [1.0] * 6}, "tool": {"payload": 0.1}}
    )
    assert config.limits.velocity == (1.0,) * 6
    assert config.limits.acceleration == NED2_SPEC.limits["acceleration"]
    assert (config.tool.payload, config.tool.tcp) == (0.1, NED2_SPEC.tcp)
    # the UR3e's stay the default kind's
    assert CellConfig().limits.velocity[0] == pytest.approx(math.pi)
    assert CellConfig().home == pytest.approx(HOME_JOINTS)


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"limits": {"position_max": [2 * math.pi] * 6}}, r"limits\.position_max: joint 1 .*ned2"),
        ({"limits": {"velocity": [math.pi] * 6}}, r"limits\.velocity: joint 1 .*ned2's 1\.57"),
        ({"home": [0.0, 1.0, 0.0, 0.0, 0.0, 0.0]}, r"home: joint 2 at 1 rad .*ned2"),
        ({"tool": {"payload": 1.0}}, r"tool\.payload: .*ned2's rated 0\.3 kg"),
        ({"robot": {"external_control": "urcap"}}, r"robot\.external_control: .*ned2.*'urcap'"),
        ({"robot": {"receiver": "ur_rtde"}}, r"robot\.receiver: .*ned2"),
        ({"robot": {"calibration": "calibration.conf"}}, r"robot\.calibration: .*ned2"),
    ],
)
def test_what_a_ned2_cannot_take_is_a_config_error_naming_the_kind(
    section: dict[str, Any], message: str
) -> None:
    data: dict[str, Any] = {"robot": {"kind": "ned2"}}
    for key, value in section.items():
        data[key] = {**data.get(key, {}), **value} if isinstance(value, dict) else value
    with pytest.raises(ConfigError, match=message):
        CellConfig.from_dict(data)
    # the same on a UR3e is fine
    data["robot"]["kind"] = "ur3e"
    CellConfig.from_dict(data)


def test_the_ur3es_shipped_limits_on_a_ned2_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(f"robot:\n  kind: ned2\nlimits_file: {CONFIG_DIR / 'ur3e_limits.yaml'}\n")
    with pytest.raises(ConfigError, match=r"limits\.position_min: joint 1 .*ned2's range"):
        CellConfig.load(path)


def test_a_ned2_user_config_inherits_the_shipped_ned2_cell(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text("robot:\n  kind: ned2\n  host: 10.10.10.10\n")
    config = CellConfig.load(path)
    shipped = CellConfig.load(CONFIG_DIR / "ned2-cell.yaml")
    assert config.robot.host == "10.10.10.10"
    assert (config.limits, config.scene, config.layout) == (
        shipped.limits,
        shipped.scene,
        shipped.layout,
    )
    # its own small stations, not the UR3e cell's (whose crucibles Gripper 1 could not take)
    assert config.layout != CellConfig.load().layout
    assert all(obj.width < 0.027 for obj in config.layout.objects.values())
    assert config.vision.camera.source is None
    # the shipped Ned2 cell keeps its taught positions and job apart from the UR3e cell's
    assert shipped.positions_file.parent == default_state_dir()
    assert shipped.positions_file != CellConfig.load().positions_file
    assert shipped.job.database != CellConfig.load().job.database
