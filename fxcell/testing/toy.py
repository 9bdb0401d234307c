"""A made-up robot kind for tests of the robot seam: its own joints, sample period and arm.

Nothing here is a UR: :func:`toy_kind` is a :class:`~fxcell.robots.RobotKind` of five
joints whose link takes a trajectory sample every ``period`` (4 ms by default, where a
UR3e's servo takes 2 ms), with a kinematic model, a calibration form and a collision model
of its own, so that a test shows the unchanged Cell driving a robot that shares nothing
with the UR3e but the link contract::

    robot = ToyRobot(joints=5, period=0.004)
    register(toy_kind(robot))

:class:`ToyRobot` is the controller, in the test's event loop: power, brakes and an
external-control program as modes of :class:`~fxcell.protocol.RobotState`, a clock that
runs ``speed`` times faster than the wall clock, one state sample per period. Its arm
tracks perfectly: each period it is where the next trajectory sample puts it (so the
samples a test reads back are the motion). It records every trajectory it was given
(:attr:`ToyRobot.received`). A link stop (``TrajectoryRun.stop``) holds the arm where it is;
the Cell's own stop splices its braking profile in before that.

Test support: the runtime never imports it.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import struct
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fxcell.config import CellConfig, RobotConfig
from fxcell.errors import (
    CalibrationError,
    ConnectionLostError,
    InvalidArgumentError,
    RobotCommandError,
    UnreachableError,
)
from fxcell.geometry import Pose
from fxcell.link.backend import ArmCalibration, TrajectoryRun
from fxcell.link.capabilities import RobotCapabilities
from fxcell.link.contract import (
    ControllerInfo,
    Guard,
    LinkStatus,
    OutputGroup,
    StopReason,
    TrajectoryProgress,
    TrajectoryResult,
    TrajectoryStatus,
)
from fxcell.link.subscription import StateSubscription
from fxcell.motion.moves import ExecutionOptions
from fxcell.protocol import ProgramState, RobotMode, RobotState, RuntimeState
from fxcell.results import ProgramStatus
from fxcell.robots import CalibrationFormat, RobotKind

Array = NDArray[np.float64]

__all__ = [
    "ToyCalibration",
    "ToyCollisions",
    "ToyKinematics",
    "ToyLink",
    "ToyRobot",
    "toy_kind",
]

IDLE_PERIOD = 0.005
"""Wall seconds between two wake-ups of the controller's clock."""
MAX_CATCH_UP = 200
"""Periods run at most per wake-up (a starved loop slows the robot's clock)."""


# ----------------------------------------------------------------- the arm's model


@dataclass(frozen=True)
class ToyCalibration:
    """The toy arm's calibration: a zero offset per joint (rad), not a UR's DH deltas."""

    offsets: tuple[float, ...] = (0.0,) * 5

    @property
    def checksum(self) -> str:
        packed = struct.pack(f">{len(self.offsets)}d", *self.offsets)
        return f"{zlib.crc32(packed):08x}"

    @property
    def is_nominal(self) -> bool:
        return not any(self.offsets)

    def summary(self) -> dict[str, object]:
        return {"offsets": list(self.offsets), "checksum": self.checksum}

    @classmethod
    def load(cls, path: str) -> ToyCalibration:
        """A file of comma-separated offsets (rad)."""
        try:
            with open(path, encoding="utf-8") as file:
                return cls(tuple(float(v) for v in file.read().split(",")))
        except (OSError, ValueError) as exc:
            raise CalibrationError(f"{path}: {exc}") from None


class ToyKinematics:
    """A Cartesian toy arm of five joints: joints 1-3 move the TCP along x, y, z
    (:attr:`SCALE` m per rad, from :attr:`ORIGIN`), joint 4 turns it about z and joint 5
    about x (rotation ``Rz(q4)·Rx(q5)``). The inverse is exact; a pose whose rotation is
    not of that form is unreachable. ``calibration`` offsets the joints' zeros."""

    SCALE = 0.1
    ORIGIN = (0.2, 0.0, 0.3)

    def __init__(
        self, lower: Sequence[float], upper: Sequence[float], calibration: ToyCalibration
    ) -> None:
        self.lower = np.asarray(lower, float)
        self.upper = np.asarray(upper, float)
        self.offsets = np.asarray(calibration.offsets, float)

    @property
    def reach(self) -> float:
        corner = np.maximum(np.abs(self.lower[:3]), np.abs(self.upper[:3])) * self.SCALE
        return float(np.linalg.norm(np.asarray(self.ORIGIN) + corner)) + 0.01

    def forward(self, q: ArrayLike) -> Pose:
        a = np.asarray(q, float) + self.offsets
        cz, sz, cx, sx = math.cos(a[3]), math.sin(a[3]), math.cos(a[4]), math.sin(a[4])
        rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
        rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
        return Pose(np.asarray(self.ORIGIN) + self.SCALE * a[:3], rz @ rx)

    def inverse(self, pose: Pose, seed: ArrayLike | None = None) -> Array:
        solutions = self.inverse_all(pose, seed)
        if not solutions:
            raise UnreachableError(f"the toy arm cannot reach {pose!r}")
        return solutions[0]

    def inverse_near(self, pose: Pose, seed: ArrayLike) -> Array:
        return self.inverse(pose, seed)

    def inverse_all(self, pose: Pose, seed: ArrayLike | None = None) -> list[Array]:
        r = pose.rotation
        qz = math.atan2(r[1, 0], r[0, 0])
        qx = math.atan2(r[2, 1], r[2, 2])
        a = np.array([*((pose.position - np.asarray(self.ORIGIN)) / self.SCALE), qz, qx])
        q = a - self.offsets
        if np.any(q < self.lower) or np.any(q > self.upper):
            return []
        if not self.forward(q).isclose(pose, position_tol=1e-9, angle_tol=1e-9):
            return []  # an orientation that is not Rz·Rx: this arm has none such
        return [q]


class ToyCollisions:
    """The toy arm's collision model: it touches nothing (a test of the seam, not of
    collision checking); it keeps what the gripper holds."""

    def __init__(self) -> None:
        self.held: str | None = None

    def in_collision(self, q: ArrayLike) -> bool:
        return False

    def colliding_pairs(self, q: ArrayLike) -> list[tuple[str, str]]:
        return []

    def check(self, q: ArrayLike, what: str = "target") -> None:
        return None

    def first_collision(self, samples: ArrayLike) -> int | None:
        return None

    def motion_free(self, start: ArrayLike, end: ArrayLike) -> bool:
        return True

    def separating_wall(self, start: ArrayLike, end: ArrayLike) -> tuple[int, float] | None:
        return None

    def attach(self, kind: str) -> None:
        self.held = kind

    def detach(self) -> None:
        self.held = None


# ----------------------------------------------------------------- the controller


class ToyRobot:
    """The toy controller and its perfectly tracking arm (see the module docstring)."""

    def __init__(
        self,
        *,
        joints: int = 5,
        period: float = 0.004,
        start: Sequence[float] | None = None,
        speed: float = 5.0,
    ) -> None:
        if joints < 1 or not period > 0 or not speed > 0:
            raise InvalidArgumentError("joints, period and speed must be > 0")
        self.joints = joints
        self.period = period
        self.speed = speed
        self.q = np.asarray(start if start is not None else np.zeros(joints), float)
        self.qd = np.zeros(joints)
        self.calibration = ToyCalibration((0.0,) * joints)
        """What the toy controller reports as its arm's calibration."""
        self.time = 0.0
        """Controller time (s): ``period`` per cycle."""
        self.cycles = 0
        self.robot_mode = RobotMode.POWER_OFF
        self.program = False
        """The external-control program plays."""
        self.received: list[ToyTrajectory] = []
        """Every trajectory the link was given, in order."""
        self.links: list[ToyLink] = []
        self._run: ToyTrajectory | None = None
        self._task: asyncio.Task[None] | None = None

    def link_factory(
        self,
        host: str | None,
        robot: RobotConfig,
        *,
        on_state: Callable[[RobotState], None],
        on_status: Callable[[LinkStatus, str], None],
        on_control: Callable[[bool, str], None],
    ) -> ToyLink:
        """A :class:`~fxcell.link.backend.LinkFactory`."""
        return ToyLink(self, on_state=on_state, on_status=on_status, on_control=on_control)

    def sample(self) -> RobotState:
        q, qd = tuple(self.q.tolist()), tuple(self.qd.tolist())
        return RobotState(
            timestamp=self.time,
            robot_mode=self.robot_mode,
            runtime_state=RuntimeState.PLAYING if self.program else RuntimeState.STOPPED,
            target_q=q,
            target_qd=qd,
            target_qdd=(0.0,) * self.joints,
            actual_q=q,
            actual_qd=qd,
            actual_current=(0.0,) * self.joints,
            received_at=time.monotonic(),
        )

    def _cycle(self) -> None:
        self.time += self.period
        self.cycles += 1
        run = self._run
        if run is not None and not run.done:
            q = run.step(self.time)
            if q is not None:
                self.qd = (q - self.q) / self.period
                self.q = q
            else:
                self.qd = np.zeros(self.joints)
        else:
            self.qd = np.zeros(self.joints)
        state = self.sample()
        for link in self.links:
            link._publish(state)

    async def _clock(self) -> None:
        last = time.monotonic()
        carry = 0.0
        while True:
            await asyncio.sleep(min(IDLE_PERIOD, self.period / self.speed))
            now = time.monotonic()
            due = (now - last) * self.speed / self.period + carry
            last = now
            steps = int(due)
            carry = due - steps
            for _ in range(min(steps, MAX_CATCH_UP)):
                self._cycle()

    def _start(self) -> None:
        if self._task is None or self._task.done():
            self._task = asyncio.get_running_loop().create_task(self._clock(), name="toy robot")

    async def _stop(self) -> None:
        if self._task is not None and not self.links:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None


class ToyTrajectory:
    """A trajectory the toy arm plays one sample per period (a
    :class:`~fxcell.link.backend.TrajectoryRun`)."""

    def __init__(self, robot: ToyRobot, samples: Array, guard: Guard | None) -> None:
        self._robot = robot
        self.given = samples.copy()
        """The samples as the link was given them."""
        self.guard = guard
        self.splices: list[tuple[int, int, int]] = []
        """Each :meth:`replace_remaining`: the index it was asked to replace from, the
        index it joined at (the next sample to play, when that was later) and how many
        samples it brought."""
        self._samples = samples
        self._index = -1
        self._progress: TrajectoryProgress | None = None
        self._result: TrajectoryResult | None = None
        self._stop: StopReason | None = None
        self._ended = asyncio.Event()
        self._reported = asyncio.Event()
        self._started_at = robot.time

    @property
    def done(self) -> bool:
        return self._result is not None

    @property
    def progress(self) -> TrajectoryProgress | None:
        return self._progress

    @property
    def played(self) -> Array:
        """The samples the arm has been put at, one per period, in order."""
        return self._samples[: self._index + 1]

    def step(self, now: float) -> Array | None:
        """The sample of this cycle (None: it ended)."""
        if self._stop is not None:
            self._end("stopped", self._stop)
            return None
        self._index += 1
        if self._index >= len(self._samples):
            self._index = len(self._samples) - 1
            self._end("completed", StopReason.NONE)
            return None
        q = self._samples[self._index]
        self._progress = TrajectoryProgress(
            self._index, len(self._samples), tuple(q.tolist()), 0.0, time.time(), now
        )
        self._reported.set()
        return np.array(q, float)

    def _end(self, status: TrajectoryStatus, reason: StopReason) -> None:
        self._result = TrajectoryResult(
            status,
            reason,
            self._index,
            len(self._samples),
            tuple(self._robot.q.tolist()),
            self._robot.time - self._started_at,
        )
        self._ended.set()
        self._reported.set()

    async def replace_remaining(self, samples: ArrayLike, at_index: int | None = None) -> bool:
        if self.done:
            return False
        array = np.asarray(samples, float)
        if array.ndim != 2 or array.shape[1] != self._robot.joints or len(array) == 0:
            raise InvalidArgumentError(f"samples must be (N, {self._robot.joints})")
        following = self._index + 1
        at = following if at_index is None else at_index
        joined = max(at, following)
        self.splices.append((at, joined, len(array)))
        # a replacement from a sample already played joins in where the arm is now
        late = min(joined - at, len(array) - 1)
        self._samples = np.concatenate([self._samples[:joined], array[late:]])
        return True

    async def stop(self, reason: StopReason = StopReason.STOP_REQUESTED) -> TrajectoryResult:
        if not self.done:
            self._stop = reason
        return await self.wait()

    async def wait(self) -> TrajectoryResult:
        await self._ended.wait()
        assert self._result is not None
        return self._result

    async def next_progress(self) -> TrajectoryProgress | None:
        if self.done:
            return None
        self._reported.clear()
        await self._reported.wait()
        return None if self.done else self._progress


class ToyLink:
    """The toy robot's :class:`~fxcell.link.backend.LinkBackend`."""

    def __init__(
        self,
        robot: ToyRobot,
        *,
        on_state: Callable[[RobotState], None],
        on_status: Callable[[LinkStatus, str], None],
        on_control: Callable[[bool, str], None],
    ) -> None:
        self.robot = robot
        self._on_state = on_state
        self._on_status = on_status
        self._on_control = on_control
        self._latest: RobotState | None = None
        self._subscriptions: set[StateSubscription] = set()
        self._sent = 0
        self._status = LinkStatus.STARTING
        self._up = asyncio.Event()

    @property
    def latest(self) -> RobotState | None:
        return self._latest

    @property
    def control_ready(self) -> bool:
        return self.robot.program and self._status is LinkStatus.UP

    @property
    def up(self) -> bool:
        return self._status is LinkStatus.UP

    @property
    def messages_sent(self) -> int:
        return self._sent

    async def start(self, wait: bool = True) -> None:
        self.robot.links.append(self)
        self.robot._start()
        if wait:
            async with asyncio.timeout(10.0):
                await self._up.wait()

    async def close(self) -> None:
        run = self.robot._run
        if run is not None and not run.done:
            run._end("failed", StopReason.LINK_CLOSING)
        if self in self.robot.links:
            self.robot.links.remove(self)
        await self.robot._stop()
        self._status = LinkStatus.CLOSED
        self._on_status(LinkStatus.CLOSED, "closed")

    def _publish(self, state: RobotState) -> None:
        self._latest = state
        if self._status is not LinkStatus.UP:
            self._status = LinkStatus.UP
            self._up.set()
            self._on_status(LinkStatus.UP, "state stream live")
        self._on_state(state)
        for subscription in tuple(self._subscriptions):
            subscription.offer(state)

    def _request(self, counted: bool = True) -> None:
        if self._status is not LinkStatus.UP:
            raise ConnectionLostError("the toy link is not up")
        self._sent += counted

    async def power(self, on: bool, within: float = 5.0) -> None:
        self._request()
        self.robot.robot_mode = RobotMode.IDLE if on else RobotMode.POWER_OFF
        self.robot.program = self.robot.program and on

    async def release_brakes(self, within: float = 5.0) -> None:
        self._request()
        if self.robot.robot_mode != RobotMode.IDLE:
            raise RobotCommandError("the toy arm's brakes release only when it is idle")
        self.robot.robot_mode = RobotMode.RUNNING

    async def remote_control(self, within: float = 5.0) -> bool:
        self._request(counted=False)  # the cell's background poll (see counts_as_sent)
        return True

    async def unlock_protective_stop(self, within: float = 5.0) -> bool:
        self._request()
        return True

    async def program_status(self, within: float = 5.0) -> ProgramStatus:
        self._request()
        state = ProgramState.PLAYING if self.robot.program else ProgramState.STOPPED
        return ProgramStatus(state, "toy control")

    async def shutdown(self, within: float = 5.0) -> None:
        raise RobotCommandError("the toy robot does not shut down")

    async def controller_info(self, within: float = 5.0) -> ControllerInfo:
        self._request()
        return ControllerInfo("toy 1.0", "T-0001", "toy")

    async def read_calibration(self) -> ArmCalibration:
        self._request()
        return self.robot.calibration

    async def enable_control(self, within: float) -> None:
        self._request()
        if self.robot.robot_mode != RobotMode.RUNNING:
            raise RobotCommandError("the toy arm must run (brakes released) for control")
        self.robot.program = True
        self._on_control(True, "toy control program playing")

    async def disable_control(self, within: float = 5.0) -> None:
        self._request()
        await self.servo_stop(within)
        self.robot.program = False
        self._on_control(False, "toy control program stopped")

    async def servo_stop(self, within: float = 5.0) -> bool:
        self._request()
        run = self.robot._run
        if run is None or run.done:
            return False
        await run.stop(StopReason.SERVO_STOP)
        return True

    async def set_output(
        self, group: OutputGroup, index: int, value: float, within: float = 5.0
    ) -> bool:
        self._request()
        return False  # the toy robot has no outputs

    async def set_tool(
        self,
        tcp: tuple[float, ...],
        mass: float,
        cog: tuple[float, float, float],
        within: float = 5.0,
    ) -> bool:
        self._request()
        return True

    async def teach_mode(self, on: bool, within: float = 5.0) -> bool:
        self._request()
        return False

    async def execute_trajectory(
        self,
        samples: ArrayLike,
        *,
        lookahead_time: float = 0.1,
        gain: float = 300.0,
        guard: Guard | None = None,
    ) -> TrajectoryRun:
        self._request()
        array = np.array(samples, dtype=float)
        if array.ndim != 2 or array.shape[1] != self.robot.joints or len(array) == 0:
            raise InvalidArgumentError(
                f"trajectory samples must be (N, {self.robot.joints}), got {array.shape}"
            )
        if not self.control_ready:
            raise RobotCommandError("the toy control program does not play")
        previous = self.robot._run
        if previous is not None and not previous.done:
            await previous.stop(StopReason.SUPERSEDED)
        run = ToyTrajectory(self.robot, array, guard)
        self.robot.received.append(run)
        self.robot._run = run
        return run

    def subscribe(self, maxsize: int = 1024) -> StateSubscription:
        return StateSubscription(self._subscriptions, maxsize)


# ----------------------------------------------------------------- the kind


def toy_kind(robot: ToyRobot, name: str = "toy5") -> RobotKind:
    """The toy kind of ``robot`` (five joints: :class:`ToyKinematics`), registered by
    the caller under ``name``; its link streams without lag compensation (the arm tracks
    perfectly)."""
    if robot.joints != 5:
        raise InvalidArgumentError("the toy arm's kinematic model has five joints")

    def kinematics(config: CellConfig, calibration: ArmCalibration | None) -> ToyKinematics:
        if calibration is not None and not isinstance(calibration, ToyCalibration):
            raise CalibrationError(f"not a toy calibration: {type(calibration).__name__}")
        limits = config.limits
        return ToyKinematics(
            limits.position_min, limits.position_max, calibration or ToyCalibration()
        )

    return RobotKind(
        capabilities=RobotCapabilities(name, joints=robot.joints, sample_period=robot.period),
        link=robot.link_factory,
        kinematics=kinematics,
        collision=lambda config: ToyCollisions(),
        calibration=CalibrationFormat(nominal=ToyCalibration, load=ToyCalibration.load),
        execution=ExecutionOptions(compensate_lag=False),
    )
