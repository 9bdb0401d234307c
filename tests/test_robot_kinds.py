"""A second robot kind plugs in as one registry entry: the Cell drives it unchanged.

``toy`` is a made-up kind registered here: the in-process fake link as its link, a
kinematic model factory of its own (the UR3e's geometry, counted), no simulator, and
freedrive among the commands it cannot do. ``toy5`` shares nothing with the UR3e but the
link contract (:mod:`fxcell.testing.toy`): five joints, a trajectory sample every 4 ms, its
own kinematic model, calibration and collision model. The Cell is not touched to drive
either.
"""

from __future__ import annotations

import asyncio
import math
import subprocess
import sys
from collections.abc import Iterator
from typing import get_args

import numpy as np
import pytest

from fxcell import Cell, CellState
from fxcell.calibration import Calibration
from fxcell.commands import COMMANDS, Feature
from fxcell.config import CONFIG_DIR, CellConfig, RobotKindName
from fxcell.errors import (
    CalibrationError,
    ConfigError,
    InvalidArgumentError,
    MoveStoppedError,
    UnsupportedCommandError,
)
from fxcell.events import Event, MotionEvent
from fxcell.geometry import Pose
from fxcell.link.capabilities import UR3E, RobotCapabilities
from fxcell.link.contract import StopReason
from fxcell.motion.kinematics import Kinematics
from fxcell.motion.moves import ur3e_kinematics
from fxcell.protocol import CONTROL_PERIOD
from fxcell.robot_specs import SPECS
from fxcell.robots import NED2_KIND, RobotKind, kind_names, register, robot_kind, unregister
from fxcell.testing import FakeRobot
from fxcell.testing.toy import ToyCalibration, ToyRobot, toy_kind

HOME = [0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0]
QUARTER_TURN = [math.pi / 2, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0]


@pytest.fixture
def toy(fake_robot: FakeRobot) -> Iterator[list[Calibration | None]]:
    """Register the ``toy`` kind on ``fake_robot``; the calibrations its kinematic
    model factory was called with."""
    built: list[Calibration | None] = []

    def kinematics(config: CellConfig, calibration: Calibration | None) -> Kinematics:
        built.append(calibration)
        return ur3e_kinematics(config, calibration)

    no_freedrive = frozenset(Feature) - {Feature.FREEDRIVE}
    capabilities = RobotCapabilities(
        "toy", joints=6, sample_period=CONTROL_PERIOD, features=no_freedrive
    )
    ur3e = robot_kind("ur3e")
    register(
        RobotKind(
            capabilities,
            fake_robot.link_factory,
            kinematics,
            collision=ur3e.collision,
            calibration=ur3e.calibration,
        )
    )
    try:
        yield built
    finally:
        unregister("toy")


def _toy_config() -> CellConfig:
    # robot.kind accepts the kinds fxcell ships; a test's own kind is set past validation
    config = CellConfig.load()
    return config.model_copy(update={"robot": config.robot.model_copy(update={"kind": "toy"})})


async def test_a_registered_second_kind_inits_moves_and_stops_through_the_cell(
    toy: list[Calibration | None], fake_robot: FakeRobot
) -> None:
    async with Cell(config=_toy_config(), record=None) as cell:
        assert cell.kind.name == "toy"
        assert cell.host is None  # no simulator started: the kind has none
        await cell.init()
        assert cell.state is CellState.EXTERNAL_CONTROL_READY
        result = await cell.move_joint(HOME)
        assert result.joint_error < 1e-5
        move = asyncio.create_task(cell.move_joint(QUARTER_TURN))
        async with asyncio.timeout(5.0):
            with cell.robot_states(maxsize=8) as states:
                async for sample in states:
                    if abs(sample.actual_qd[0]) > 0.2:
                        break
        assert await cell.stop() is True
        with pytest.raises(MoveStoppedError):
            await move
        assert float(fake_robot.arm.q[0]) < QUARTER_TURN[0] - 0.1  # braked short of it
        # the kind's own kinematic model: built with the calibration its link read
        assert toy
        assert isinstance(toy[-1], Calibration)


async def test_a_command_the_kind_cannot_do_is_refused_naming_the_kind(
    toy: list[Calibration | None], fake_robot: FakeRobot
) -> None:
    async with Cell(config=_toy_config(), record=None) as cell:
        await cell.init()
        sent = cell._link().messages_sent
        with pytest.raises(UnsupportedCommandError, match="toy") as info:
            await cell.freedrive_start()
        assert (info.value.command, info.value.kind) == ("freedrive_start", "toy")
        for refused in ("freedrive_start", "freedrive_stop"):  # both need the feature
            with pytest.raises(UnsupportedCommandError):
                await cell.check_command(refused)
        assert cell._link().messages_sent == sent  # nothing sent
        assert not fake_robot.controller.teach_mode
        assert cell.state is CellState.EXTERNAL_CONTROL_READY


def test_the_ur3e_is_the_default_kind_and_does_every_command() -> None:
    assert CellConfig.load().robot.kind == "ur3e"
    assert robot_kind("ur3e").capabilities is UR3E
    assert UR3E.unsupported == frozenset()
    assert (UR3E.joints, UR3E.sample_period) == (6, 0.002)
    assert "ur3e" in kind_names()


def test_the_ned2_is_a_registered_kind_that_refuses_remote_power() -> None:
    ned2 = robot_kind("ned2")
    assert ned2 is NED2_KIND
    assert set(kind_names()) >= {"ur3e", "ned2"}
    assert ned2.capabilities.unsupported == frozenset({"power_on", "power_off", "shutdown"})
    assert ned2.simulator is not None  # no host configured: its embedded simulator


def test_the_configurable_kinds_are_the_registered_ones_with_a_spec() -> None:
    # robot.kind's values, the makers' figures and the registry name the same kinds
    assert set(get_args(RobotKindName)) == set(SPECS) == set(kind_names())
    for name, spec in SPECS.items():
        assert robot_kind(name).capabilities.joints == len(spec.home)
        assert (CONFIG_DIR / spec.shipped_config).is_file()
        assert CellConfig.load(CONFIG_DIR / spec.shipped_config).robot.kind == name


def test_the_registry_loads_no_motion_stack() -> None:
    code = (
        "import sys, fxcell.robots\n"
        "print(sorted(m for m in sys.modules if m.startswith(('fxcell.motion.moves',"
        " 'fxcell.motion.planning', 'pinocchio', 'ompl', 'ruckig', 'coal'))))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "[]"


def test_a_kind_fxcell_does_not_drive_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"robot\.kind"):
        CellConfig.from_dict({"robot": {"kind": "abb"}})
    with pytest.raises(ConfigError, match="'abb' is not a robot kind"):
        robot_kind("abb")
    config = CellConfig.load()
    unknown = config.model_copy(update={"robot": config.robot.model_copy(update={"kind": "x"})})
    with pytest.raises(ConfigError, match=r"known: .*ned2.*ur3e"):
        Cell(config=unknown, record=None)


def test_capabilities_name_only_features_of_the_table() -> None:
    with pytest.raises(InvalidArgumentError, match="fly"):
        RobotCapabilities("toy", 6, 0.002, frozenset({"fly"}))  # type: ignore[arg-type]
    with pytest.raises(InvalidArgumentError):
        RobotCapabilities("toy", 0, 0.002)
    no_power = RobotCapabilities("toy", 6, 0.002, frozenset(Feature) - {Feature.REMOTE_POWER})
    assert not no_power.supports("power_on")
    assert no_power.supports("brake_release")


def test_the_command_table_says_which_features_each_command_needs() -> None:
    needing = {f: sorted(n for n, c in COMMANDS.items() if f in c.requires) for f in Feature}
    assert needing[Feature.REMOTE_POWER] == ["power_off", "power_on"]
    assert needing[Feature.REMOTE_SHUTDOWN] == ["shutdown"]
    assert needing[Feature.FREEDRIVE] == ["freedrive_start", "freedrive_stop"]
    assert {"pick", "place", "gripper_close"} <= set(needing[Feature.GRIPPER])
    assert needing[Feature.IO] == ["get_io", "io_set", "io_wait_for"]
    # a kind refuses exactly the commands needing a feature it lacks; moves need none
    assert NED2_KIND.capabilities.unsupported == {"power_on", "power_off", "shutdown"}
    assert not COMMANDS["move_joint"].requires
    assert not COMMANDS["stop"].requires


async def test_a_kind_whose_joints_the_configured_limits_do_not_fit_is_refused_at_open(
    fake_robot: FakeRobot,
) -> None:
    capabilities = RobotCapabilities("toy", 7, 0.002)
    ur3e = robot_kind("ur3e")
    register(
        RobotKind(
            capabilities,
            fake_robot.link_factory,
            ur3e.kinematics,
            collision=ur3e.collision,
            calibration=ur3e.calibration,
        )
    )
    try:
        with pytest.raises(ConfigError, match="7 joints"):
            async with Cell(config=_toy_config(), record=None):
                pass
    finally:
        unregister("toy")


def test_a_kind_name_is_registered_once() -> None:
    with pytest.raises(InvalidArgumentError, match="already"):
        register(robot_kind("ur3e"))
    assert np.isclose(robot_kind("ur3e").capabilities.sample_period, CONTROL_PERIOD)


async def test_the_daemons_command_table_marks_what_the_kind_cannot_do(
    toy: list[Calibration | None],
) -> None:
    from fxcell.daemon.service import CellService

    table = CellService(_toy_config(), "token").commands_data()
    assert table["freedrive_start"]["supported"] is False
    assert table["freedrive_start"]["allowed"] == []  # the page's button stays disabled
    assert table["move_joint"]["supported"] is True
    assert table["move_joint"]["allowed"]


def test_a_remote_client_gets_the_refusal_back_with_command_and_kind() -> None:
    from fxcell.client import build_error
    from fxcell.daemon.encoding import error_info, http_status

    refusal = UnsupportedCommandError("freedrive_start", "toy")
    assert http_status(refusal) == 409
    again = build_error(error_info(refusal), 409)
    assert isinstance(again, UnsupportedCommandError)
    assert (again.command, again.kind, str(again)) == ("freedrive_start", "toy", str(refusal))


# ----------------------------------------------------------------- toy5: no UR in it

TOY5_PERIOD = 0.004
TOY5_VELOCITY = (1.0, 1.0, 1.5, 2.0, 2.0)
TOY5_BRAKING = (3.0, 3.0, 3.0, 6.0, 6.0)


@pytest.fixture
def toy5() -> Iterator[ToyRobot]:
    """Register ``toy5``: the toy arm of five joints sampled every 4 ms."""
    robot = ToyRobot(joints=5, period=TOY5_PERIOD)
    register(toy_kind(robot, "toy5"))
    try:
        yield robot
    finally:
        unregister("toy5")


def _toy5_config() -> CellConfig:
    config = CellConfig.load()
    # five joints' limits: past validation too (the configuration's vectors are the UR's six)
    limits = config.limits.model_copy(
        update={
            "position_min": (-3.0,) * 5,
            "position_max": (3.0,) * 5,
            "velocity": TOY5_VELOCITY,
            "acceleration": (2.0, 2.0, 2.0, 4.0, 4.0),
            "jerk": (20.0,) * 5,
            "braking_acceleration": TOY5_BRAKING,
            "braking_jerk": (60.0,) * 5,
        }
    )
    robot = config.robot.model_copy(update={"kind": "toy5"})
    return config.model_copy(update={"robot": robot, "limits": limits})


async def test_a_kind_of_five_joints_sampled_every_4_ms_is_driven_by_the_unchanged_cell(
    toy5: ToyRobot,
) -> None:
    target = [1.5, -0.5, 0.3, 1.0, -0.4]
    async with Cell(config=_toy5_config(), record=None) as cell:
        events: list[MotionEvent] = []

        def collect(event: Event) -> None:
            if isinstance(event, MotionEvent):
                events.append(event)

        unsubscribe = cell.bus.subscribe(collect)
        await cell.init()
        assert cell.state is CellState.EXTERNAL_CONTROL_READY
        # the kind's own calibration, read from its link, shown as the UR's is
        status = cell.calibration_status
        assert status is not None
        assert (status["model"], status["checksum"]) == ("nominal", toy5.calibration.checksum)
        assert isinstance(cell.calibration, ToyCalibration)

        result = await cell.move_joint(target)
        assert result.joint_error < 1e-9  # the toy arm tracks perfectly
        np.testing.assert_allclose(toy5.q, target, atol=1e-12)
        assert result.reached_pose == tuple(
            cell.motion.planner.tcp_pose(target).as_quaternion_list()
        )

        # planned and streamed at the kind's period: 4 ms between samples, not the UR's 2
        (trajectory,) = [e.data for e in events if e.kind == "trajectory"]
        assert trajectory["dt"] == TOY5_PERIOD
        assert trajectory["samples"] == math.ceil(result.planned_duration / TOY5_PERIOD - 1e-9) + 1
        run = toy5.received[-1]
        samples = run.given
        hold = round(0.5 / TOY5_PERIOD)  # the target held 0.5 s for the arm to settle
        assert len(samples) == trajectory["samples"] + hold
        assert samples.shape[1] == 5
        np.testing.assert_array_equal(samples[-hold:], np.tile(target, (hold, 1)))
        # the joint that limits the move cruises at its velocity limit, samples 4 ms apart
        speed = np.max(np.abs(np.diff(samples, axis=0)) / TOY5_PERIOD / TOY5_VELOCITY)
        assert speed == pytest.approx(1.0, rel=1e-3)
        # the move ended once the arm had played the plan and settled, early in the hold
        end = await run.wait()
        assert (end.status, end.reason) == ("stopped", StopReason.SETTLED)
        assert trajectory["samples"] <= len(run.played) < trajectory["samples"] + hold

        back = [-1.5, 0.5, -0.3, -1.0, 0.4]
        move = asyncio.create_task(cell.move_joint(back))
        async with asyncio.timeout(5.0):
            with cell.robot_states(maxsize=8) as states:
                async for sample in states:
                    if abs(sample.actual_qd[0]) > 0.5:
                        break
        assert await cell.stop() is True
        with pytest.raises(MoveStoppedError):
            await move
        unsubscribe()
        assert float(toy5.q[0]) > back[0] + 0.5  # braked well short of it
        assert not toy5.qd.any()
        await cell.wait_for_state(CellState.EXTERNAL_CONTROL_READY, timeout=5.0)
        # the Cell's braking profile was spliced into the stream and played to rest; timed
        # at the kind's period, it brakes the limiting joint at its braking limit, 4 ms apart
        braked = toy5.received[-1]
        (splice,) = braked.splices
        braking = braked.played[splice[1] :]
        assert len(braking) > 10
        decel = np.abs(np.diff(braking, n=2, axis=0)) / TOY5_PERIOD**2 / TOY5_BRAKING
        assert float(np.max(decel)) == pytest.approx(1.0, rel=0.02)
        assert float(np.max(decel)) <= 1.0 + 1e-6


def test_the_toy_kinds_model_is_its_own() -> None:
    kind = toy_kind(ToyRobot(joints=5, period=TOY5_PERIOD), "toy5")
    config = _toy5_config()
    model = kind.kinematics(config, ToyCalibration((0.01, 0.0, 0.0, 0.0, 0.0)))
    q = np.array([0.5, -0.2, 0.1, 0.7, -0.3])
    pose = model.forward(q)
    (solution,) = model.inverse_all(pose)
    np.testing.assert_allclose(solution, q, atol=1e-12)
    assert model.inverse_all(Pose.from_rpy(pose.position, (0.0, 0.4, 0.0))) == []  # no pitch
    with pytest.raises(CalibrationError):
        kind.kinematics(config, Calibration.nominal())  # a UR's calibration is not its form
    with pytest.raises(CalibrationError):
        robot_kind("ur3e").kinematics(CellConfig.load(), ToyCalibration())
    assert kind.calibration.nominal().is_nominal
