"""The logic of a move, kept apart from the Cell: check, IK, collision, plan, time, execute, stop.

:class:`MotionPlanner` turns a target into a :class:`MovePlan` — validated factors and
target, IK nearest the current joints and free of collision, a collision-free path
(straight joint line, else OMPL; or a Cartesian straight line) and a jerk-limited
trajectory sampled at the robot kind's period (its capabilities' ``sample_period``: a
UR3e's 2 ms) — or raises before anything moves. :class:`MoveExecution` streams a plan
through the robot link (a UR3e's: servoJ at 500 Hz in the link process) and, when
stopped or cancelled, replaces the samples not yet sent by a jerk-limited braking
profile computed with Ruckig from the planned state where the replacement takes over.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fxcell.calibration import Calibration
from fxcell.config import CellConfig
from fxcell.errors import (
    CalibrationError,
    CollisionError,
    ConfigError,
    ConnectionLostError,
    InvalidArgumentError,
    InvalidTargetError,
    LinkBrakeError,
    MoveStoppedError,
    PlanningError,
    TrackingError,
    UncalibratedError,
    UnreachableError,
)
from fxcell.events import MotionEvent, now
from fxcell.geometry import Pose
from fxcell.link.capabilities import UR3E, RobotCapabilities
from fxcell.link.contract import LINK_BRAKES, Guard, StopReason
from fxcell.motion.calibration import calibrated_kinematics, kinematics_for
from fxcell.motion.execution import ExecutionOptions
from fxcell.motion.planning import DEFAULT_PLANNER, PLANNERS, JointPlanner, cartesian_line
from fxcell.motion.runner import (
    DistanceTarget,
    JointTarget,
    MoveRunner,
    MoveTarget,
    PoseTarget,
    RelativeTarget,
)
from fxcell.motion.trajectory import (
    Limits,
    Trajectory,
    along_path,
    braking,
    rest_to_rest,
    through_waypoints,
    validate_factor,
)
from fxcell.protocol import RobotState
from fxcell.results import MoveResult

if TYPE_CHECKING:
    from fxcell.link import StateSubscription, TrajectoryResult
    from fxcell.link.backend import ArmCalibration, LinkBackend, TrajectoryRun
    from fxcell.motion.kinematics import Kinematics
    from fxcell.robots.registry import (
        CollisionFactory,
        CollisionModel,
        KinematicModel,
        KinematicsFactory,
    )

Array = NDArray[np.float64]
MoveKind = Literal["joint", "pose", "linear", "distance"]

__all__ = [
    "ExecutionOptions",
    "MotionController",
    "MotionPlanner",
    "MoveExecution",
    "MovePlan",
    "MoveResult",
    "execute",
    "validate_factor",
]


@dataclass(frozen=True)
class MovePlan:
    """A checked, timed move, ready to stream."""

    kind: MoveKind
    start_joints: Array
    target_joints: Array
    target_pose: Pose
    """TCP pose at ``target_joints``."""
    waypoints: Array
    """The geometric path: joint waypoints (a Cartesian line's IK knots)."""
    trajectory: Trajectory
    planner: str
    """``direct``, the OMPL planner's name, or ``cartesian``."""
    planning_time: float
    velocity_factor: float
    acceleration_factor: float

    @property
    def duration(self) -> float:
        return self.trajectory.duration


T = TypeVar("T")

MAX_ANGLE = 2 * math.pi
"""Largest roll, pitch or yaw (rad) a pose's 6-list may give."""


def _vector(value: object, n: int, what: str) -> Array:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InvalidTargetError(f"{what} must be {n} numbers, got {value!r}") from None
    if arr.shape != (n,) or isinstance(value, str | bytes):
        raise InvalidTargetError(f"{what} must be {n} numbers, got {value!r}")
    if not np.all(np.isfinite(arr)):
        raise InvalidTargetError(f"{what} must be finite, got {value!r}")
    return arr


def ur3e_kinematics(config: CellConfig, calibration: ArmCalibration | None) -> Kinematics:
    """The UR3e with the configuration's TCP and limits: calibrated with ``calibration``,
    else as ``robot.calibration`` says (a file, or the nominal model until one is read);
    CalibrationError for a calibration that is not a UR's DH deltas."""
    if calibration is None:
        return kinematics_for(config)
    if not isinstance(calibration, Calibration):
        raise CalibrationError(
            f"the UR3e's model takes UR DH deltas, not a {type(calibration).__name__}"
        )
    return calibrated_kinematics(config, calibration)


def ur3e_collision(config: CellConfig) -> CollisionModel:
    """The UR3e's and its gripper's collision bodies in the configured scene (Pinocchio and
    coal, loaded on first use)."""
    from fxcell.motion.collision import CollisionChecker

    return CollisionChecker.for_config(config)


def _check_joints(capabilities: RobotCapabilities, config: CellConfig) -> None:
    """ConfigError unless the configured limits are as wide as the kind's joint vectors."""
    joints = len(config.limits.velocity)
    if capabilities.joints != joints:
        raise ConfigError(
            f"robot.kind {capabilities.kind!r}: {capabilities.joints} joints, but the "
            f"configured limits are for {joints}"
        )


class MotionPlanner:
    """Plans moves in the configured cell: the robot kind's arm (default: the UR3e) with
    its TCP, limits and scene; trajectories sampled at the kind's period."""

    def __init__(
        self,
        config: CellConfig,
        *,
        planner: str = DEFAULT_PLANNER,
        planning_timeout: float = 1.0,
        checker: CollisionModel | None = None,
        seed: int | None = None,
        kinematics: KinematicsFactory | None = None,
        collision: CollisionFactory | None = None,
        capabilities: RobotCapabilities = UR3E,
    ) -> None:
        _check_joints(capabilities, config)
        self.config = config
        self.capabilities = capabilities
        self.period = capabilities.sample_period
        """Seconds between two trajectory samples (the kind's servo cycle)."""
        self.joints = capabilities.joints
        """The width of every joint vector."""
        self.limits = config.limits
        self._kinematics_of: KinematicsFactory = kinematics or ur3e_kinematics
        """The robot kind's kinematic model factory (default: the UR3e's)."""
        self.kinematics: KinematicModel = self._kinematics_of(config, None)
        self.uncalibrated: str | None = None
        """Why pose moves are refused (the calibration could not be read), or None."""
        if checker is None:
            checker = (collision or ur3e_collision)(config)
        self.checker: CollisionModel = checker
        self.joint_planner = JointPlanner(
            self.checker,
            config.limits.position_min,
            config.limits.position_max,
            planner=planner,
            timeout=planning_timeout,
            seed=seed,
        )
        self._lower = np.asarray(config.limits.position_min, float)
        self._upper = np.asarray(config.limits.position_max, float)
        self.reach = self.kinematics.reach
        """No TCP position farther than this from the base origin is reachable (m)."""

    @property
    def max_acceleration(self) -> tuple[float, ...]:
        """The configured joint acceleration limits (rad/s², factor 1)."""
        return tuple(self.limits.acceleration)

    def scaled_limits(self, velocity_factor: float, acceleration_factor: float) -> Limits:
        """Joint limits scaled by validated factors (InvalidFactorError otherwise)."""
        return Limits.from_config(
            self.limits, velocity_factor, acceleration_factor, period=self.period
        )

    def braking_limits(self) -> Limits:
        """Limits for stopping: the configured braking limits, whatever the move's factors."""
        return Limits.for_braking(self.limits, period=self.period)

    def use_calibration(self, calibration: ArmCalibration | None, why: str = "") -> None:
        """Plan on ``calibration`` (the controller's, read at connect); None: it could not
        be read (``why``), so pose moves raise UncalibratedError unless the configuration
        accepts the nominal model."""
        self.uncalibrated = None
        self.kinematics = self._kinematics_of(self.config, calibration)
        if calibration is not None:
            return
        if not self.config.robot.accept_nominal_kinematics:
            self.uncalibrated = why or "the arm's calibration could not be read"

    def tcp_pose(self, joints: ArrayLike) -> Pose:
        return self.kinematics.forward(np.asarray(joints, float))

    # ------------------------------------------------------------ checks

    def check_joints(self, target: object, what: str = "joint target") -> Array:
        """The kind's number of finite joint values within the position limits, or
        InvalidTargetError."""
        q = _vector(target, self.joints, what)
        outside = np.flatnonzero((q < self._lower) | (q > self._upper))
        if len(outside):
            j = int(outside[0])
            raise InvalidTargetError(
                f"{what}: joint {j + 1} = {q[j]:.6g} rad is outside "
                f"[{self._lower[j]:.4f}, {self._upper[j]:.4f}]"
            )
        return q

    def parse_pose(self, target: object) -> Pose:
        """A Pose, 7-list (quaternion) or 6-list (RPY) as :meth:`Pose.parse`; InvalidTargetError.

        Roll, pitch and yaw must lie in [-2π, 2π]: a larger angle is a mistake (a unit or a
        typo), not a rotation anybody means."""
        try:
            pose = target if isinstance(target, Pose) else Pose.parse(target)
        except InvalidTargetError:
            raise
        except (TypeError, ValueError, OverflowError) as exc:
            raise InvalidTargetError(f"not a pose: {target!r} ({exc})") from None
        if not isinstance(target, Pose) and len(target) == 6:  # type: ignore[arg-type]
            for axis, angle in zip(("roll", "pitch", "yaw"), list(target)[3:], strict=True):  # type: ignore[call-overload]
                if not abs(float(angle)) <= MAX_ANGLE:
                    raise InvalidTargetError(
                        f"{axis} {float(angle):.6g} rad is not an angle in [-2π, 2π]"
                    )
        return pose

    def check_reach(self, pose: Pose, what: str = "target") -> None:
        """UnreachableError for a TCP position beyond the arm's reach, before IK or a
        straight line is computed (a huge target would overflow them)."""
        distance = math.hypot(*(float(v) for v in pose.position))
        if not distance <= self.reach:  # also inf and nan
            raise UnreachableError(
                f"the {what} is {distance:.4g} m from the base; the arm reaches "
                f"{self.reach:.3f} m at most"
            )

    def distance_target(self, start: ArrayLike, distance: object) -> Pose:
        """The TCP pose ``distance`` (x, y, z, m, base axes; finite) away from the pose at
        ``start`` joints, orientation kept; InvalidArgumentError for a bad vector."""
        try:
            d = _vector(distance, 3, "distance vector")
        except InvalidTargetError as exc:
            raise InvalidArgumentError(str(exc)) from None
        here = self.tcp_pose(_vector(start, self.joints, "start joints"))
        return Pose(here.position + d, here.rotation)

    def check(self, target: MoveTarget, start: ArrayLike) -> None:
        """Raise what can be known of a move before it is planned: a target that is not
        finite, outside the joint limits, no pose, beyond reach, or with no collision-free
        IK solution (each leg of a relative move). No path is searched."""
        self._check_calibrated(target)
        q0 = _vector(start, self.joints, "start joints")
        match target:
            case JointTarget(joints):
                self.check_joints(joints)
            case PoseTarget(pose, _):
                self.solve(self.parse_pose(pose), q0)
            case DistanceTarget(distance):
                self.solve(self.distance_target(q0, distance), q0)
            case RelativeTarget(start_pose, target_pose):
                q1 = self.solve(self.parse_pose(start_pose), q0)
                self.solve(self.parse_pose(target_pose), q1)

    def solve(self, pose: Pose, seed: Array) -> Array:
        """IK nearest ``seed`` among the collision-free solutions.

        UnreachableError when no solution is within the limits, CollisionError when
        every solution collides.
        """
        self.check_reach(pose)
        solutions = self.kinematics.inverse_all(pose, seed=seed)
        if not solutions:
            raise UnreachableError(f"no inverse-kinematics solution within the limits for {pose!r}")
        for q in solutions:  # sorted nearest first
            if not self.checker.in_collision(q):
                return q
        pairs = ", ".join(f"{a}–{b}" for a, b in self.checker.colliding_pairs(solutions[0]))
        raise CollisionError(
            f"every one of the {len(solutions)} IK solutions for {pose!r} is in collision "
            f"(nearest: {pairs})"
        )

    # ------------------------------------------------------------ plans

    def plan(
        self,
        target: MoveTarget,
        start: ArrayLike,
        velocity_factor: float = 1.0,
        acceleration_factor: float = 1.0,
    ) -> list[MovePlan]:
        """The plans (legs) of a move from ``start`` joints to ``target``."""
        vf, af = velocity_factor, acceleration_factor
        self._check_calibrated(target)
        match target:
            case JointTarget(joints):
                return [self.plan_joint(start, joints, vf, af)]
            case PoseTarget(pose, linear):
                return [self.plan_pose(start, pose, vf, af, linear=linear)]
            case DistanceTarget(distance):
                return [self.plan_distance(start, distance, vf, af)]
            case RelativeTarget(start_pose, target_pose):
                return self.plan_relative(start, start_pose, target_pose, vf, af)
        raise InvalidArgumentError(f"not a move target: {target!r}")

    def _check_calibrated(self, target: MoveTarget) -> None:
        if self.uncalibrated is not None and not isinstance(target, JointTarget):
            raise UncalibratedError(
                f"pose moves are refused: {self.uncalibrated}; the nominal model would put the "
                "TCP millimetres off (set robot.accept_nominal_kinematics to allow it, or give "
                "robot.calibration a calibration.conf)"
            )

    def plan_joint(
        self,
        start: ArrayLike,
        target: object,
        velocity_factor: float = 1.0,
        acceleration_factor: float = 1.0,
        *,
        kind: MoveKind = "joint",
        search: bool = True,
    ) -> MovePlan:
        """Plan a joint-space move: the straight line if free, else OMPL (``search=False``:
        PlanningError instead), then Ruckig."""
        t0 = time.perf_counter()
        limits = self.scaled_limits(velocity_factor, acceleration_factor)
        q1 = self.check_joints(target)
        q0 = _vector(start, self.joints, "start joints")
        for attempt in range(3):
            path = self.joint_planner.plan(q0, q1, search=search)
            if len(path.waypoints) == 2:
                traj = rest_to_rest(q0, q1, limits)  # exactly on the checked straight line
                break
            try:
                traj = through_waypoints(
                    path.waypoints, limits, validate=self.checker.first_collision
                )
                break
            except PlanningError:
                # Even at rest a segment failed the sample check: it grazes an obstacle
                # between the points its line check looked at. Plan another path.
                if attempt == 2:
                    raise
        return MovePlan(
            kind,
            q0,
            q1,
            self.tcp_pose(q1),
            path.waypoints,
            traj,
            path.planner,
            time.perf_counter() - t0,
            float(velocity_factor),
            float(acceleration_factor),
        )

    def plan_pose(
        self,
        start: ArrayLike,
        target: object,
        velocity_factor: float = 1.0,
        acceleration_factor: float = 1.0,
        *,
        linear: bool = False,
    ) -> MovePlan:
        """Plan a move of the TCP to a pose: joint-space (default) or a straight line."""
        t0 = time.perf_counter()
        limits = self.scaled_limits(velocity_factor, acceleration_factor)
        pose = self.parse_pose(target)
        q0 = _vector(start, self.joints, "start joints")
        if linear:
            return self._plan_line(
                q0, pose, limits, t0, "linear", velocity_factor, acceleration_factor
            )
        q1 = self.solve(pose, q0)
        plan = self.plan_joint(q0, q1, velocity_factor, acceleration_factor, kind="pose")
        return MovePlan(
            "pose",
            q0,
            q1,
            self.tcp_pose(q1),
            plan.waypoints,
            plan.trajectory,
            plan.planner,
            time.perf_counter() - t0,
            plan.velocity_factor,
            plan.acceleration_factor,
        )

    def plan_distance(
        self,
        start: ArrayLike,
        distance: object,
        velocity_factor: float = 1.0,
        acceleration_factor: float = 1.0,
    ) -> MovePlan:
        """Plan a straight TCP line by ``distance`` (x, y, z in the base frame, metres),
        keeping the orientation."""
        t0 = time.perf_counter()
        limits = self.scaled_limits(velocity_factor, acceleration_factor)
        target = self.distance_target(start, distance)
        q0 = _vector(start, self.joints, "start joints")
        return self._plan_line(
            q0, target, limits, t0, "distance", velocity_factor, acceleration_factor
        )

    def plan_relative(
        self,
        start: ArrayLike,
        start_pose: object,
        target_pose: object,
        velocity_factor: float = 1.0,
        acceleration_factor: float = 1.0,
        *,
        linear: bool = False,
    ) -> list[MovePlan]:
        """The seed's ``move_relative``: to ``start_pose``, then to ``target_pose``.

        Both legs are planned (and so checked) before anything moves.
        """
        first = self.plan_pose(start, start_pose, velocity_factor, acceleration_factor)
        second = self.plan_pose(
            first.target_joints, target_pose, velocity_factor, acceleration_factor, linear=linear
        )
        return [first, second]

    def _plan_line(
        self,
        q0: Array,
        target: Pose,
        limits: Limits,
        t0: float,
        kind: MoveKind,
        vf: float,
        af: float,
    ) -> MovePlan:
        self.checker.check(q0, "start configuration")
        self.check_reach(target, "line's end")
        line = cartesian_line(self.kinematics, self.checker, q0, target)
        traj = along_path(line.joints, line.knots, limits)
        bad = self.checker.first_collision(traj.positions)
        if bad is not None:  # between two checked knots: rare, but the samples are what moves
            raise CollisionError(f"the straight line collides after {bad * traj.period:.3f} s")
        q1 = line.target_joints
        return MovePlan(
            kind,
            q0,
            q1,
            self.tcp_pose(q1),
            line.knots,
            traj,
            "cartesian",
            time.perf_counter() - t0,
            float(vf),
            float(af),
        )


# ----------------------------------------------------------------- execution


INLINE_SPAN = 0.25
"""rad: joint moves at most this long on every joint are planned on the event loop (a free
straight line then costs ~0.5-1.2 ms: collision checks along it and Ruckig)."""
TRACKING_EVERY = 0.05
"""Seconds of controller time between two tracking reports of a running move (25 state
samples of a UR)."""


def lead_setpoints(traj: Trajectory, lag: float) -> Array:
    """Setpoints that make servoJ's tracker follow ``traj`` sample for sample.

    servoJ behaves like a critically damped second-order tracker with lag = 2/ω; fed
    ``q + lag·q̇ + (lag²/4)·q̈`` it follows q without the lag. The derivatives are the
    samples' own differences (backward velocity, central acceleration), which is what a
    tracker stepping once per sample period needs to land on the next sample exactly.
    Samples at rest are unchanged (the last one is the target).
    """
    q = traj.positions
    if len(q) < 2 or lag <= 0:
        return q.copy()
    dt = traj.period
    prev = np.concatenate([q[:1], q[:-1]])
    nxt = np.concatenate([q[1:], q[-1:]])
    qd = (q - prev) / dt
    qdd = (nxt - 2 * q + prev) / (dt * dt)
    out: Array = q + lag * qd + (lag * lag / 4.0) * qdd
    out[-1] = q[-1]
    return out


class MoveExecution:
    """One plan being streamed through the link; :meth:`stop` brakes it to rest.

    ``run()`` returns a :class:`MoveResult` when the target is reached, raises
    :class:`MoveStoppedError` (with ``.result``) after :meth:`stop`, a safety-stop or
    connection error when the robot or the link fails the move, and brakes before
    re-raising when its task is cancelled.
    """

    def __init__(
        self,
        plan: MovePlan,
        link: LinkBackend,
        planner: MotionPlanner,
        options: ExecutionOptions | None = None,
        on_tracking: Callable[[dict[str, Any]], None] | None = None,
    ) -> None:
        self.plan = plan
        self.link = link
        self.planner = planner
        self.options = options or ExecutionOptions()
        self.on_tracking = on_tracking
        """Called about every 50 ms while the plan streams with where the robot is
        against the plan (for MotionEvent(kind="tracking"))."""
        self.max_tracking_error = 0.0
        self._stop = asyncio.Event()
        self._handle: TrajectoryRun | None = None
        self._sent_at = 0.0
        self._braked = False
        self.brake_duration = 0.0
        """Duration of the braking profile that was used (0 if none)."""
        self.brake_requested_at: float | None = None
        self._finished = asyncio.Event()
        self._settled = False
        self._settled_at: float | None = None
        self._brake_task: asyncio.Task[None] | None = None
        self._spliced = False  # the braking profile replaced the remaining samples

    @property
    def handle(self) -> TrajectoryRun | None:
        return self._handle

    def request_stop(self) -> None:
        """Ask the running move to brake to rest (returns at once; the braking profile is
        computed and sent right away, not at the next state sample)."""
        if self.brake_requested_at is None:
            self.brake_requested_at = time.monotonic()
        self._stop.set()
        handle = self._handle
        if handle is not None and not handle.done and self._brake_task is None:
            self._brake_task = asyncio.get_running_loop().create_task(self._brake(handle))

    async def _braking(self, handle: TrajectoryRun) -> None:
        """Brake now, or wait for the braking already under way."""
        if self._brake_task is None:
            self._brake_task = asyncio.get_running_loop().create_task(self._brake(handle))
        await asyncio.shield(self._brake_task)

    async def stop(self) -> None:
        """Brake to rest and wait until the move has ended."""
        self.request_stop()
        await self._finished.wait()

    async def run(self) -> MoveResult:
        try:
            return await self._run()
        finally:
            if self._brake_task is not None and not self._brake_task.done():
                with contextlib.suppress(BaseException):
                    await self._brake_task
            self._finished.set()

    async def _run(self) -> MoveResult:
        opts = self.options
        traj = self.plan.trajectory
        samples = lead_setpoints(traj, opts.lag) if opts.compensate_lag else traj.positions
        samples[-1] = traj.positions[-1]
        # Hold the target after the last sample: servoJ converges onto it, and the
        # stream is ended as soon as the robot has settled there.
        hold = np.repeat(samples[-1:], max(round(opts.settle_timeout / traj.period), 1), axis=0)
        with self.link.subscribe(maxsize=4096) as states:
            self._sent_at = time.monotonic()
            handle = await self.link.execute_trajectory(
                np.concatenate([samples, hold]),
                lookahead_time=opts.lookahead_time,
                gain=opts.gain,
                guard=self._guard(),
            )
            self._handle = handle
            try:
                state = await self._watch(handle, states)
                end = await handle.wait()
            except TimeoutError:
                with contextlib.suppress(Exception):
                    await handle.stop()
                p = handle.progress
                where = f"; last progress: sample {p.index} of {p.total}" if p else ""
                raise TrackingError(
                    f"the move did not end within {self.plan.duration:.2f} s planned + margins"
                    f" after its last progress{where}"
                ) from None
            except (asyncio.CancelledError, ConnectionLostError):
                # Our task was cancelled (stop(), a safety event, a lost link, the
                # caller), or the robot's state stopped coming: brake to rest before
                # letting the cancellation or the error through. When the braking profile
                # cannot be spliced in (the link is down), the link process brakes along
                # the path by itself; either way it goes through only once the trajectory
                # has ended (a robot whose controller holds the whole trajectory, as the
                # Ned2's, would otherwise run on, and refuse the retry's trajectory).
                self.request_stop()
                with contextlib.suppress(Exception):
                    if not handle.done:
                        await self._braking(handle)
                if not handle.done and not self._spliced:
                    with contextlib.suppress(Exception):
                        await handle.stop(StopReason.MOVE_ABORTED)
                with contextlib.suppress(Exception):
                    async with asyncio.timeout(self.brake_duration + 3.0):
                        await handle.wait()
                with contextlib.suppress(Exception):
                    await self._wait_rest(states)
                raise
            return self._finish(end, state)

    async def _watch(self, handle: TrajectoryRun, states: StateSubscription) -> RobotState:
        """Follow the robot sample by sample until it has settled at the target (then end
        the stream), the stream ends, or a stop request brakes it to rest."""
        opts = self.options
        target = self.plan.trajectory.positions[-1].tolist()
        period = self.plan.trajectory.period
        # The link process sends one sample per controller cycle it sees; starved of CPU it
        # sees fewer, and the trajectory stretches (slower, never faster). So the patience
        # runs from the latest progress report: the samples still to send, plus margins.
        margin = 2 * opts.settle_timeout + 1.0
        loop = asyncio.get_running_loop()
        reported = -1
        state = self.link.latest
        patience_for_state = self.planner.capabilities.state_patience
        tracked: float | None = None  # controller time of the last tracking report
        async with asyncio.timeout(self.plan.duration + margin) as patience:
            while True:
                progress = handle.progress
                if progress is not None and progress.index > reported:
                    reported = progress.index
                    left = (progress.total - progress.index) * period + margin
                    patience.reschedule(max(patience.when() or 0.0, loop.time() + left))
                if self._stop.is_set() and not handle.done:
                    await self._braking(handle)
                if state is not None:
                    # plain floats: this runs for every state sample (500 Hz on a UR)
                    moving = max(map(abs, state.actual_qd))
                    if tracked is None:
                        tracked = state.timestamp
                    elif not self._braked and state.timestamp - tracked >= TRACKING_EVERY - 1e-9:
                        tracked = state.timestamp
                        self._track(handle, state)
                    if self._braked:
                        if handle.done and moving < opts.rest_velocity:
                            self._settled_at = state.received_at
                            return state
                    elif (
                        moving < opts.settle_velocity
                        and max(abs(a - b) for a, b in zip(state.actual_q, target, strict=True))
                        <= opts.settle_position
                        and self._arrived(handle, state)
                    ):
                        self._settled_at = state.received_at
                        self._settled = True
                        if not handle.done:
                            await handle.stop(StopReason.SETTLED)
                        return state
                    elif handle.done:
                        if (
                            max(abs(a - b) for a, b in zip(state.actual_q, target, strict=True))
                            <= opts.arrive_tolerance
                        ):
                            self._settled_at = state.received_at
                            self._settled = True
                        return state
                waiting_since = time.monotonic()
                try:
                    state = await states.next_within(patience_for_state)
                except TimeoutError:
                    if handle.done:
                        return state if state is not None else RobotState()
                    if time.monotonic() - waiting_since > patience_for_state + 0.05:
                        continue  # this loop was held up, not the robot: read what came
                    raise ConnectionLostError(
                        f"no robot state for {patience_for_state:g} s during a move"
                    ) from None

    def _track(self, handle: TrajectoryRun, state: RobotState) -> None:
        """Compare the robot with the planned sample for now (index from the link's
        progress and the clock, so ±1 sample of timing is part of the figure)."""
        traj = self.plan.trajectory
        index = min(round(self._current_index(handle)), len(traj) - 1)
        planned = traj.positions[index]
        error = max(abs(a - b) for a, b in zip(state.actual_q, planned.tolist(), strict=True))
        self.max_tracking_error = max(self.max_tracking_error, error)
        if self.on_tracking is not None:
            self.on_tracking(
                {"index": index, "planned": planned.tolist(),
                 "actual": list(state.actual_q), "error": error}
            )  # fmt: skip

    def _arrived(self, handle: TrajectoryRun, state: RobotState) -> bool:
        """Whether the stream has passed the planned samples (into the hold) at ``state``."""
        return self._index_at(handle, state) >= len(self.plan.trajectory) - 1

    def _index_at(self, handle: TrajectoryRun, state: RobotState) -> float:
        """The link's sample index when it had ``state``: counted in controller cycles from
        its last progress report when that names the controller time it answered (exact,
        whatever the delays of the report and of this loop), else :meth:`_current_index`."""
        p = handle.progress
        if p is None or p.timestamp is None:
            return self._current_index(handle)
        return p.index + round((state.timestamp - p.timestamp) / self.plan.trajectory.period)

    def _current_index(self, handle: TrajectoryRun) -> float:
        """The link's sample index now, from its last progress report and the clock."""
        p = handle.progress
        period = self.plan.trajectory.period
        if p is None:
            return (time.monotonic() - self._sent_at) / period
        return p.index + max(time.time() - p.time, 0.0) / period

    async def _brake(self, handle: TrajectoryRun) -> None:
        """Replace the samples not yet sent by the jerk-limited stop."""
        if self._braked:
            return
        self._braked = True
        traj = self.plan.trajectory
        at = math.floor(self._current_index(handle)) + self.options.brake_lead
        if at >= len(traj) - 1:
            return  # it ends within the lead anyway
        p, v, a = traj.state(at)
        stop = braking(p, v, a, self.planner.braking_limits())
        self.brake_duration = stop.duration
        samples = stop.positions
        if self.options.compensate_lag:
            # Lead the braking samples with the planned ones before them as history, so
            # the setpoints continue exactly where the replaced ones leave off.
            history = traj.positions[max(at - 1, 0) : at]
            shape = (len(history) + len(stop), traj.positions.shape[1])
            joined = Trajectory(
                np.concatenate([history, stop.positions]),
                np.zeros(shape),
                np.zeros(shape),
                stop.duration,
                stop.period,
            )
            samples = lead_setpoints(joined, self.options.lag)[len(history) :]
        samples[-1] = stop.positions[-1]
        self._spliced = await handle.replace_remaining(samples, at_index=at)

    def _guard(self) -> Guard:
        """How the link process brakes this move by itself (see fxcell.link.process)."""
        limits = self.planner.limits
        robot = self.planner.config.robot
        return Guard(
            brake_acceleration=tuple(limits.braking_acceleration),
            brake_jerk=min(limits.braking_jerk),
            cell_timeout=robot.heartbeat_timeout,
            stall_timeout=robot.stall_timeout,
            velocity=tuple(limits.velocity),
            path_acceleration=tuple(limits.acceleration),
        )

    async def _wait_rest(self, states: StateSubscription) -> None:
        """Wait (bounded) until the robot's joints are at rest."""
        async with asyncio.timeout(self.options.settle_timeout):
            state = self.link.latest
            while state is None or max(map(abs, state.actual_qd)) >= self.options.rest_velocity:
                state = await states.__anext__()

    def _finish(self, end: TrajectoryResult, state: RobotState) -> MoveResult:
        if end.status == "failed":
            # the reason's error from the contract's one table (fxcell.link.contract)
            raise end.error()(f"the move failed: {end.why} (at sample {end.index} of {end.total})")
        reached = np.asarray(state.actual_q, float)
        result = self._result(reached, self._settled_at, end)
        if self._braked or (end.status == "stopped" and not self._settled):
            # braked by the link process's own guard (not asked by the cell): LinkBrakeError
            guarded = not self._braked and end.reason in LINK_BRAKES
            raise (LinkBrakeError if guarded else MoveStoppedError)(
                f"the move was stopped at {reached.round(4).tolist()} "
                f"({result.executed_duration:.3f} s after it started)",
                result,
            )
        if not self._settled:
            raise TrackingError(
                f"the robot did not settle at the target (joint error {result.joint_error:.2e} "
                f"rad, speed {max(map(abs, state.actual_qd)):.2e} rad/s)"
            )
        return result

    def _result(
        self, reached: Array, settled_at: float | None, end: TrajectoryResult
    ) -> MoveResult:
        plan = self.plan
        kin = self.planner.kinematics
        reached_pose = kin.forward(reached)
        target_pose = plan.target_pose
        finished = settled_at if settled_at is not None else time.monotonic()
        return MoveResult(
            target_joints=tuple(plan.target_joints.tolist()),
            target_pose=tuple(target_pose.as_quaternion_list()),
            reached_joints=tuple(reached.tolist()),
            reached_pose=tuple(reached_pose.as_quaternion_list()),
            joint_error=float(np.max(np.abs(reached - plan.target_joints))),
            position_error=float(np.linalg.norm(reached_pose.position - target_pose.position)),
            orientation_error=float(reached_pose.angle_to(target_pose)),
            planned_duration=plan.duration,
            executed_duration=max(finished - self._sent_at, 0.0),
            planner=plan.planner,
            stopped=not self._settled,
            max_tracking_error=self.max_tracking_error,
        )


async def execute(
    plan: MovePlan,
    link: LinkBackend,
    planner: MotionPlanner,
    options: ExecutionOptions | None = None,
) -> MoveResult:
    """Stream ``plan`` and wait for the robot to arrive (see :class:`MoveExecution`)."""
    return await MoveExecution(plan, link, planner, options).run()


# ----------------------------------------------------------------- the Cell's move logic

Publish = Callable[[MotionEvent], None]


class MotionController:
    """What the Cell's move methods do, apart from guards and task ownership.

    Holds the default velocity and acceleration factors (a move's own factor, when
    given, is used for that move only), plans in a worker thread so the event loop keeps
    serving the 500 Hz state stream, publishes the path, trajectory and result as
    :class:`~fxcell.events.MotionEvent`, and executes. The planner (Pinocchio, coal,
    OMPL) is built on first use.
    """

    def __init__(
        self,
        config: CellConfig,
        *,
        publish: Publish | None = None,
        options: ExecutionOptions | None = None,
        planner: str = DEFAULT_PLANNER,
        kinematics: KinematicsFactory | None = None,
        collision: CollisionFactory | None = None,
        capabilities: RobotCapabilities = UR3E,
    ) -> None:
        _check_joints(capabilities, config)
        self.config = config
        self._kinematics = kinematics
        self._collision = collision
        self.capabilities = capabilities
        """The robot kind's joints and trajectory sample period."""
        self.options = options or ExecutionOptions()
        self._min_factor = config.limits.min_factor
        self._publish = publish
        self._planner_name = planner
        self._planner: MotionPlanner | None = None
        self.velocity_factor = 1.0
        self.acceleration_factor = 1.0
        self.execution: MoveExecution | None = None
        self._move_ids = 0
        self._plan_lock = threading.Lock()

    @property
    def planner(self) -> MotionPlanner:
        if self._planner is None:
            self._planner = MotionPlanner(
                self.config,
                planner=self._planner_name,
                kinematics=self._kinematics,
                collision=self._collision,
                capabilities=self.capabilities,
            )
        return self._planner

    def use_planner(self, name: str) -> None:
        """Plan blocked joint moves with another OMPL geometric planner (see
        :data:`fxcell.motion.planning.PLANNERS`; default RRTConnect)."""
        if name not in PLANNERS:
            raise InvalidArgumentError(
                f"unknown planner {name!r}; choose one of {', '.join(PLANNERS)}"
            )
        self._planner_name = name  # taken up by the next plan (under the plan lock)

    def warm_up(self) -> None:
        """Build the planner now (imports Pinocchio, coal, OMPL: ~0.3 s, much of it in
        C extension initialisation that holds the GIL). Call it off the event loop before
        the robot link streams, so the first move does not stall the loop."""
        _ = self.planner

    def set_velocity_factor(self, value: object) -> None:
        self.velocity_factor = validate_factor("velocity_factor", value, self._min_factor)

    def set_acceleration_factor(self, value: object) -> None:
        self.acceleration_factor = validate_factor("acceleration_factor", value, self._min_factor)

    @property
    def max_acceleration(self) -> tuple[float, ...]:
        return tuple(self.config.limits.acceleration)

    def factors(self, velocity: object | None, acceleration: object | None) -> tuple[float, float]:
        """The move's factors: given ones validated, else the defaults."""
        vf = (
            self.velocity_factor
            if velocity is None
            else validate_factor("velocity_factor", velocity, self._min_factor)
        )
        af = (
            self.acceleration_factor
            if acceleration is None
            else validate_factor("acceleration_factor", acceleration, self._min_factor)
        )
        return vf, af

    async def plan(
        self,
        target: MoveTarget,
        start: ArrayLike,
        velocity_factor: float = 1.0,
        acceleration_factor: float = 1.0,
    ) -> list[MovePlan]:
        """Plan ``target`` from ``start`` joints in a worker thread (see
        :meth:`MotionPlanner.plan`).

        One plan at a time: a move cancelled while planning leaves its thread running to
        the end, and the planner's Pinocchio data must not be shared with the next one.
        """

        def locked() -> list[MovePlan]:
            with self._plan_lock:
                joint = self.planner.joint_planner
                if joint.planner_name != self._planner_name:
                    self.planner.joint_planner = JointPlanner(
                        self.planner.checker,
                        self.config.limits.position_min,
                        self.config.limits.position_max,
                        planner=self._planner_name,
                        timeout=joint.timeout,
                    )
                return self.planner.plan(target, start, velocity_factor, acceleration_factor)

        # A short joint move on a free straight line plans in ~0.5-1.2 ms: here, not
        # through a worker thread, whose hand-offs cost more than the planning; a blocked
        # line goes to the thread for the search.
        if (
            isinstance(target, JointTarget)
            and _within(start, target.joints, INLINE_SPAN)
            and self._plan_lock.acquire(blocking=False)
        ):
            try:
                vf, af = velocity_factor, acceleration_factor
                return [self.planner.plan_joint(start, target.joints, vf, af, search=False)]
            except PlanningError:
                pass
            finally:
                self._plan_lock.release()
        return await asyncio.to_thread(locked)

    async def check(
        self,
        target: MoveTarget,
        start: ArrayLike,
        velocity_factor: object | None = None,
        acceleration_factor: object | None = None,
    ) -> None:
        """Raise now what a move to ``target`` would be refused with before it plans:
        bad factors, then :meth:`MotionPlanner.check` (IK and collision checks in a worker
        thread, under the plan lock like a plan; a joint target on the loop)."""
        self.factors(velocity_factor, acceleration_factor)
        if isinstance(target, JointTarget):
            self.planner.check(target, start)
            return
        await self.locked(lambda: self.planner.check(target, start))

    async def locked(self, work: Callable[[], T]) -> T:
        """Run ``work`` (which uses the planner's Pinocchio and collision data) in a worker
        thread, one at a time with plans."""

        def run() -> T:
            with self._plan_lock:
                return work()

        return await asyncio.to_thread(run)

    def runner(
        self,
        target: MoveTarget,
        link: LinkBackend,
        start: Callable[[], ArrayLike],
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        name: str = "move",
    ) -> MoveRunner:
        """A :class:`MoveRunner` for ``target``: factors checked (else the defaults),
        planned from the joints ``start()`` reads when it runs, executed through ``link``."""

        async def work(runner: MoveRunner) -> MoveResult:
            factors = self.factors(velocity_factor, acceleration_factor)
            plans = await self.plan(target, start(), *factors)
            return await self.execute(plans, link, runner=runner)

        return MoveRunner(work, name)

    async def execute(
        self,
        plans: MovePlan | Sequence[MovePlan],
        link: LinkBackend,
        *,
        runner: MoveRunner | None = None,
    ) -> MoveResult:
        """Stream each plan in turn; the result of the last (see :class:`MoveExecution`).

        ``runner`` is told the execution of each leg (so that its stop brakes it)."""
        seq = [plans] if isinstance(plans, MovePlan) else list(plans)
        result: MoveResult | None = None
        for plan in seq:
            self._move_ids += 1
            move_id = self._move_ids
            self._event(move_id, "path", _path_data(plan))
            self._event(move_id, "trajectory", _trajectory_data(plan))
            execution = MoveExecution(
                plan,
                link,
                self.planner,
                self.options,
                on_tracking=functools.partial(self._event, move_id, "tracking"),
            )
            self.execution = execution
            if runner is not None:
                runner.execution = execution
            try:
                result = await execution.run()
            except MoveStoppedError as exc:
                stopped = getattr(exc, "result", None)
                if stopped is not None:
                    self._event(move_id, "result", _result_data(stopped))
                raise
            finally:
                self.execution = None
                if runner is not None:
                    runner.execution = None
            self._event(move_id, "result", _result_data(result))
        assert result is not None
        return result

    def _event(
        self,
        move_id: int,
        kind: Literal["path", "trajectory", "tracking", "result"],
        data: dict[str, Any],
    ) -> None:
        if self._publish is not None:
            self._publish(MotionEvent(now(), move_id, kind, data))


def _path_data(plan: MovePlan) -> dict[str, Any]:
    return {
        "kind": plan.kind,
        "planner": plan.planner,
        "planning_time": plan.planning_time,
        "start_joints": plan.start_joints.tolist(),
        "target_joints": plan.target_joints.tolist(),
        "target_pose": list(plan.target_pose.as_ur()),
        "waypoints": plan.waypoints.tolist() if len(plan.waypoints) <= 64 else len(plan.waypoints),
        "velocity_factor": plan.velocity_factor,
        "acceleration_factor": plan.acceleration_factor,
    }


def _result_data(result: MoveResult) -> dict[str, Any]:
    """The result's fields (``dataclasses.asdict`` without its deep copy: they are
    immutable numbers, strings and tuples of numbers)."""
    return {f.name: getattr(result, f.name) for f in fields(result)}


def _trajectory_data(plan: MovePlan) -> dict[str, Any]:
    traj = plan.trajectory
    step = max(len(traj) // 200, 1)  # at most ~200 points: a preview, not the stream
    return {
        "duration": traj.duration,
        "samples": len(traj),
        "dt": traj.period,
        "stops": traj.stops,
        "preview": traj.positions[::step].tolist(),
    }


def _within(start: ArrayLike, joints: object, span: float) -> bool:
    """Whether ``joints`` (finite numbers, as many as ``start``) is within ``span`` rad of
    ``start`` on every joint (False for anything malformed: the thread's planning reports
    it)."""
    try:
        a = np.asarray(start, dtype=float)
        b = np.asarray(joints, dtype=float)
    except (TypeError, ValueError):
        return False
    if a.ndim != 1 or b.shape != a.shape or not np.all(np.isfinite(b)):
        return False
    return float(np.max(np.abs(b - a))) <= span
