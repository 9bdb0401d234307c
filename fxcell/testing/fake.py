"""An in-process robot: the simulator's controller model behind a fake robot link.

:class:`FakeRobot` runs the simulator's pure model classes (:class:`fxcell.sim.controller.
Controller`, :class:`fxcell.sim.motion.Arm`, :class:`fxcell.sim.dashboard.Dashboard`) in
the test's event loop, ticked by an asyncio task, and :class:`FakeLink` is the
:class:`fxcell.link.backend.LinkBackend` a Cell talks to instead of the ur_rtde process::

    robot = FakeRobot()
    async with Cell(link_factory=robot.link_factory) as cell:
        await cell.init()
        robot.inject("protective_stop")

Dashboard commands get the simulator's replies and effects (power on, brake release,
play/stop, Local control); robot and safety modes, protective stops (including the 5 s
unlock rule and the arm entering the table) and program stops are the simulator's.
External control runs the simulator's control-script program; trajectories are streamed
with its servoJ tracker one setpoint per control cycle by the link process's own
trajectory follower (:mod:`fxcell.link.follower`): they advance, splice, brake along the
path and end as the link process's do (``completed``, ``stopped``, ``failed`` with the
reason).

Differences from the simulator process: no sockets and no ur_rtde (so no GIL stalls and
no link process to kill); controller time runs ``speed`` times faster than the wall clock
(default 5) and the controller's own delays are scaled by ``time_scale`` as in the
simulator; the gripper (Robotiq URCap socket) is not simulated, so ``cell.gripper``
commands fail with a connection error; the arm is nominal and its link reports all-zero
calibration deltas (``read_calibration``) instead of serving the primary interface;
``drop_rtde`` drops the link for 50 ms, as a restarted link process would.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections.abc import Awaitable, Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from fxcell.calibration import Calibration
from fxcell.config import CellConfig, RobotConfig
from fxcell.errors import (
    ConnectionLostError,
    InvalidArgumentError,
    LinkContractError,
    NotInRemoteControlError,
    RobotCommandError,
    RobotTimeoutError,
)
from fxcell.link.contract import (
    REQUESTS,
    ControlMode,
    Dashboard,
    Guard,
    LeaveServo,
    LinkStatus,
    OutputGroup,
    Ping,
    Request,
    ServoStop,
    SetOutput,
    SetTool,
    StartControl,
    StopControl,
    StopReason,
    TeachMode,
    TrajectoryProgress,
    TrajectoryResult,
    TrajectoryStatus,
    counts_as_sent,
)
from fxcell.link.dashboard import DashboardOperations
from fxcell.link.embedded import SimulatorState
from fxcell.link.follower import Follower
from fxcell.link.subscription import StateSubscription
from fxcell.protocol import CONTROL_PERIOD, RobotState, RuntimeState
from fxcell.sim.controller import Controller
from fxcell.sim.dashboard import Dashboard as DashboardServer
from fxcell.sim.motion import Arm, SafetyLimitError, ServoTrack, TableGuard
from fxcell.sim.script import SCRIPT_MARKER

log = logging.getLogger("fxcell.testing.fake")

CONTROL_SCRIPT = f"def rtde_control():\n  {SCRIPT_MARKER}\n  end\nend\n"
"""What the fake uploads: the simulator runs it as ur_rtde's control script."""
IDLE_PERIOD = 0.01
"""Wall seconds between two wake-ups while nothing moves (one sample each)."""
MAX_CATCH_UP = 250
"""Control cycles run at most per wake-up (a starved loop slows the robot's clock)."""
STALE_AFTER = 0.1
"""Controller seconds without a state sample after which the link counts as down."""
RECONNECT_AFTER = 0.05
"""Wall seconds a dropped link stays down (a restarted link process's first backoff)."""
SERVO_STOP_DECELERATION = 10.0  # rad/s², ur_rtde's servoStop() default


class FakeRobot:
    """A simulated UR3e controller in this process (see the module docstring).

    ``time_scale`` multiplies the controller's delays (power on, brake release, program
    start); ``speed`` makes controller time (motion, the 5 s protective-stop rule) run
    faster than the wall clock. ``joints`` is the arm's start (default: the config's home).
    """

    def __init__(
        self,
        config: CellConfig | None = None,
        *,
        time_scale: float = 0.05,
        speed: float = 5.0,
        joints: Sequence[float] | None = None,
    ) -> None:
        from fxcell.motion.kinematics import Kinematics

        if speed <= 0:
            raise InvalidArgumentError("speed must be > 0")
        self.config = config or CellConfig.load()
        self.speed = speed
        limits = (self.config.limits.position_min, self.config.limits.position_max)

        def make_kinematics(tcp: Any) -> Kinematics:
            return Kinematics.ur3e(tcp, limits)

        table = next((o for o in self.config.scene.objects if o.name == "table"), None)
        guard = TableGuard(table.position, table.size) if table is not None else None
        start = joints if joints is not None else self.config.home
        self.arm = Arm(make_kinematics(None), start, table=guard, make_kinematics=make_kinematics)
        self.calibration = Calibration.nominal()
        """What the fake controller reports as the arm's calibration (its arm is nominal)."""
        self.controller = Controller(self.arm, time_scale=time_scale)
        self.dashboard = DashboardServer(self.controller)
        self.controller.on_drop_rtde = self._drop_rtde
        self.controller.on_shutdown = self._shut_down
        self.controller.request_urcap_program = self._urcap_program
        self.digital_input_bits = 0
        """Digital inputs as the state stream reports them (standard 0-7, configurable 8-15,
        tool 16-17); see :meth:`set_input`."""
        self.links: list[FakeLink] = []
        self.cycles = 0
        self.last_published = 0.0
        """Controller time of the newest state sample (RTDE stalls pause them)."""
        self.off = False
        """The controller was shut down (Dashboard ``shutdown``): no more state."""
        self._task: asyncio.Task[None] | None = None
        self._fk: tuple[int, tuple[float, ...]] = (-1, (0.0,) * 6)
        self._servo: ServoTrack | None = None

    # ------------------------------------------------------------- for tests

    def link_factory(
        self,
        host: str | None,
        robot: RobotConfig,
        *,
        on_state: Callable[[RobotState], None],
        on_status: Callable[[LinkStatus, str], None],
        on_control: Callable[[bool, str], None],
    ) -> FakeLink:
        """A :class:`fxcell.link.backend.LinkFactory`: ``Cell(link_factory=robot.link_factory)``."""
        return FakeLink(
            self,
            control_mode=robot.external_control,
            urcap_program=robot.urcap_program,
            on_state=on_state,
            on_status=on_status,
            on_control=on_control,
        )

    def inject(self, fault: str, *args: object) -> str:
        """A fault, as ``fxcell sim inject`` (``protective_stop``, ``emergency_stop``,
        ``safeguard_stop``, their ``_release``, ``local_control``, ``remote_control``,
        ``stop_program``, ``power_loss``, ``drop_rtde``, ``stall_rtde SECONDS``)."""
        return self.controller.inject(fault, [str(a) for a in args])

    def state(self) -> SimulatorState:
        """Modes by name, joints and program, as the simulator's control port's ``state``."""
        return self.controller.state()

    def set_joints(self, q: Sequence[float]) -> None:
        """Place the resting arm."""
        self.arm.set_state(np.asarray(q, dtype=float), None, None)

    def set_input(self, index: int, value: bool) -> None:
        """Set digital input ``index`` (standard 0-7, configurable 8-15, tool 16-17)."""
        if not 0 <= index < 18:
            raise InvalidArgumentError(f"no digital input {index}")
        bit = 1 << index
        self.digital_input_bits = (
            (self.digital_input_bits | bit) if value else (self.digital_input_bits & ~bit)
        )

    # ------------------------------------------------------------- the model

    def _drop_rtde(self) -> None:
        for link in self.links:
            link._lose("RTDE connection dropped", RECONNECT_AFTER)

    def _shut_down(self) -> None:
        self.off = True
        for link in self.links:
            link._lose("the controller shut down", None)

    def _urcap_program(self) -> None:
        c = self.controller
        if c.runtime_state == RuntimeState.PLAYING and c.script is None:
            c.run_script(CONTROL_SCRIPT, via_urcap=True)

    @property
    def control_running(self) -> bool:
        """The control script plays and accepts commands."""
        c = self.controller
        return c.script is not None and c.runtime_state == RuntimeState.PLAYING

    def servo(self, q: Sequence[float], lookahead: float, gain: float) -> bool:
        """One servoJ setpoint, as the control script takes it (False: not running)."""
        if not self.control_running:
            return False
        arm = self.arm
        if self._servo is None or arm.generator is not self._servo:
            self._servo = ServoTrack(arm)
            arm.run(self._servo)
        try:
            self._servo.command(arm, q, CONTROL_PERIOD, lookahead, gain, self.controller.time)
        except SafetyLimitError as exc:
            self.controller.protective_stop(str(exc))
        return True

    def servo_stop(self) -> None:
        if self._servo is not None and self.arm.generator is self._servo:
            self.arm.stop_motion(SERVO_STOP_DECELERATION)
        self._servo = None

    def servo_state(self) -> RobotState:
        """What a trajectory reads of this cycle: modes and joints (cheaper than
        :meth:`sample`, no forward kinematics)."""
        c, arm = self.controller, self.arm
        q, qd, _ = arm.lists()
        return RobotState(
            timestamp=c.time,
            robot_mode=c.robot_mode,
            safety_mode=c.safety_mode,
            runtime_state=c.runtime_state,
            target_q=tuple(q),
            target_qd=tuple(qd),
            actual_q=tuple(q),
            actual_qd=tuple(qd),
        )

    def sample(self) -> RobotState:
        """The state stream's sample of this control cycle."""
        c, arm = self.controller, self.arm
        version, tcp = self._fk
        if version != arm.version:
            tcp = arm.kinematics.forward(arm.q).as_ur()
            self._fk = (arm.version, tcp)
        q = tuple(arm.q.tolist())
        qd = tuple(arm.qd.tolist())
        io = c.io
        return RobotState(
            timestamp=c.time,
            robot_mode=c.robot_mode,
            safety_mode=c.safety_mode,
            runtime_state=c.runtime_state,
            robot_status_bits=c.robot_status_bits,
            safety_status_bits=c.safety_status_bits,
            target_q=q,
            target_qd=qd,
            target_qdd=tuple(arm.qdd.tolist()),
            actual_q=q,
            actual_qd=qd,
            target_tcp_pose=tcp,
            actual_tcp_pose=tcp,
            output_int_registers=tuple(c.registers.out_int[:3]),
            digital_input_bits=self.digital_input_bits,
            digital_output_bits=io.output_bits,
            standard_analog_output0=io.analog_out[0],
            standard_analog_output1=io.analog_out[1],
            received_at=time.monotonic(),
        )

    def _busy(self) -> bool:
        return not self.controller.idle or any(link._trajectory for link in self.links)

    def _cycle(self) -> bool:
        """One control cycle; False once the controller is off."""
        for link in self.links:
            link._before_cycle()
        self.controller.tick(1)
        self.cycles += 1
        self._publish()
        return not self.off

    def _idle(self, steps: int) -> None:
        """``steps`` cycles of an idle controller: only the clock and the timers move, so
        they go at once, but the cycle before each timer that fires is published and so
        is the timer's own, as a real controller publishes every cycle (a mode that
        lasts a few cycles is never skipped by a late event loop); cycle by cycle once
        the controller has work."""
        c = self.controller
        while steps > 0:
            if self._busy():
                for _ in range(steps):
                    if not self._cycle():
                        return
                return
            due = c.cycles_to_next_timer()
            n = max(1, min(steps, due - 1 if due is not None else steps))
            c.tick(n)
            self.cycles += n
            steps -= n
            self._publish()

    def _publish(self) -> None:
        c = self.controller
        if c.time < c.rtde_stalled_until:
            return
        self.last_published = c.time
        state = self.sample()
        for link in self.links:
            link._after_cycle(state)

    def _start(self) -> None:
        if self._task is None or self._task.done():
            self._task = asyncio.get_running_loop().create_task(self._run(), name="fake robot")

    async def _stop(self) -> None:
        if self._task is not None and not self.links:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    async def _run(self) -> None:
        last = time.monotonic()
        carry = 0.0
        while not self.off:
            busy = self._busy()
            await asyncio.sleep(CONTROL_PERIOD / self.speed if busy else IDLE_PERIOD)
            now = time.monotonic()
            due = (now - last) * self.speed / CONTROL_PERIOD + carry
            last = now
            steps = int(due)
            carry = due - steps
            steps = min(steps, MAX_CATCH_UP)
            if steps == 0:
                continue
            if busy or self._busy():
                for _ in range(steps):
                    if not self._cycle():
                        break
            else:
                self._idle(steps)
            for link in self.links:
                link._watch()


class FakeLink(DashboardOperations):
    """The :class:`fxcell.link.backend.LinkBackend` of a :class:`FakeRobot` (made by
    :meth:`FakeRobot.link_factory`): a UR link, its controller operations the Dashboard's
    (:class:`~fxcell.link.dashboard.DashboardOperations`), ``control_mode`` and
    ``urcap_program`` from the robot configuration."""

    def __init__(
        self,
        robot: FakeRobot,
        *,
        control_mode: ControlMode = "script",
        urcap_program: str = "external_control.urp",
        on_state: Callable[[RobotState], None] | None = None,
        on_status: Callable[[LinkStatus, str], None] | None = None,
        on_control: Callable[[bool, str], None] | None = None,
    ) -> None:
        self.robot = robot
        self.control_mode = control_mode
        self.urcap_program = urcap_program
        self._on_state = on_state
        self._on_status = on_status
        self._on_control = on_control
        self.status = LinkStatus.STARTING
        self._latest: RobotState | None = None
        self._control = False
        self._sent = 0
        self._subscriptions: set[StateSubscription] = set()
        self._trajectory: FakeTrajectory | None = None
        self._ids = itertools.count(1)
        self._changed = asyncio.Event()
        self._last_sample = time.monotonic()
        self._down_until: float | None = None  # wall time it comes back (None: never)
        self.restarts = 0

    # -- LinkBackend

    @property
    def latest(self) -> RobotState | None:
        return self._latest

    @property
    def control_ready(self) -> bool:
        return self._control

    @property
    def up(self) -> bool:
        return self.status is LinkStatus.UP

    @property
    def messages_sent(self) -> int:
        return self._sent

    async def start(self, wait: bool = True) -> None:
        if self not in self.robot.links:
            self.robot.links.append(self)
        self._last_sample = time.monotonic()
        self.robot._start()
        if wait:
            await self._until(lambda: self.up, 10.0, "the link to come up")

    async def close(self) -> None:
        if self._trajectory is not None:
            self._trajectory.finish("failed", StopReason.LINK_LOST)
        if self in self.robot.links:
            self.robot.links.remove(self)
        await self.robot._stop()
        self._set_status(LinkStatus.CLOSED, "closed")

    async def request(self, request: Request) -> object:
        """Answer one request of the link contract as the link process would (its handler
        from :data:`HANDLERS`, by its type)."""
        handler = HANDLERS.get(type(request))
        if handler is None:
            raise LinkContractError(f"the fake link has no request {type(request).__name__}")
        self._check_up()
        self._sent += counts_as_sent(request)
        return await handler(self, request)

    async def _do_dashboard(self, request: Dashboard) -> str:
        return self._dashboard(request.command)

    async def _do_ping(self, request: Ping) -> str:
        return "pong"

    async def _do_leave_servo(self, request: LeaveServo) -> bool:
        return True

    async def _do_start_control(self, request: StartControl) -> bool:
        await self._start_control(request.mode, request.program, request.timeout)
        return True

    async def _do_stop_control(self, request: StopControl) -> bool:
        robot, c = self.robot, self.robot.controller
        await self._stop_trajectory(StopReason.EXTERNAL_CONTROL_STOPPED)
        robot.servo_stop()
        if c.script is not None or request.mode == "urcap":
            c.stop("external control stopped")
        self._set_control(False, "external control stopped")
        return True

    async def _do_servo_stop(self, request: ServoStop) -> bool:
        await self._stop_trajectory(StopReason.SERVO_STOP)
        self.robot.servo_stop()
        return self._control

    async def _do_set_output(self, request: SetOutput) -> bool:
        return self._set_output(request.group, int(request.index), float(request.value))

    async def _do_set_tool(self, request: SetTool) -> bool:
        robot, c = self.robot, self.robot.controller
        self._require_control("setting the tool")
        robot.arm.set_tcp(list(request.tcp))
        c.tcp = tuple(float(v) for v in request.tcp)
        cog = tuple(float(v) for v in request.cog)
        c.set_payload(float(request.mass), (cog[0], cog[1], cog[2]))
        return True

    async def _do_teach_mode(self, request: TeachMode) -> bool:
        robot, c = self.robot, self.robot.controller
        await self._stop_trajectory(StopReason.TEACH_MODE)
        self._require_control("freedrive")
        robot.servo_stop()
        if request.on:
            c.enter_freedrive()
        else:
            c.end_freedrive()
        return True

    def _requests_sent(self) -> int:
        return self._sent

    async def dashboard(self, command: str, within: float = 5.0) -> str:
        """One raw Dashboard request line (UR only: outside the link contract)."""
        return str(await self.request(Dashboard(command)))

    async def read_calibration(self) -> Calibration:
        """The fake arm's calibration: all-zero deltas (it moves on the nominal model), as
        the kinematics info of an uncalibrated controller would say."""
        return self.robot.calibration

    async def start_control(self, mode: ControlMode, program: str, within: float) -> None:
        await self.request(StartControl(mode, program, within))

    async def stop_control(self, mode: ControlMode, within: float = 5.0) -> None:
        await self.request(StopControl(mode))

    async def servo_stop(self, within: float = 5.0) -> bool:
        return bool(await self.request(ServoStop()))

    async def set_output(
        self, group: OutputGroup, index: int, value: float, within: float = 5.0
    ) -> bool:
        return bool(await self.request(SetOutput(group, index, value)))

    async def set_tool(
        self,
        tcp: tuple[float, ...],
        mass: float,
        cog: tuple[float, float, float],
        within: float = 5.0,
    ) -> bool:
        return bool(await self.request(SetTool(tuple(tcp), mass, cog)))

    async def teach_mode(self, on: bool, within: float = 5.0) -> bool:
        return bool(await self.request(TeachMode(on)))

    async def execute_trajectory(
        self,
        samples: ArrayLike,
        *,
        lookahead_time: float = 0.1,
        gain: float = 300.0,
        guard: Guard | None = None,
    ) -> FakeTrajectory:
        array = np.asarray(samples, dtype=float)
        if array.ndim != 2 or array.shape[1] != 6 or len(array) == 0:
            raise InvalidArgumentError(f"trajectory samples must be (N, 6), got {array.shape}")
        if not np.all(np.isfinite(array)):
            raise InvalidArgumentError("trajectory samples must be finite")
        if not 0.03 <= lookahead_time <= 0.2:
            raise InvalidArgumentError("lookahead_time must be within [0.03, 0.2] s")
        if not 100 <= gain <= 2000:
            raise InvalidArgumentError("gain must be within [100, 2000]")
        self._check_up()
        self._sent += 1
        if self._trajectory is not None:
            self._trajectory._request_stop(StopReason.SUPERSEDED)
        run = FakeTrajectory(self, next(self._ids), array, lookahead_time, gain, guard or Guard())
        self._trajectory = run
        return run

    def subscribe(self, maxsize: int = 1024) -> StateSubscription:
        return StateSubscription(self._subscriptions, maxsize)

    # -- helpers

    def _check_up(self) -> None:
        if self.status is not LinkStatus.UP:
            raise ConnectionLostError(f"no robot link (fake, {self.status.value})")

    def _require_control(self, what: str) -> None:
        if not self.robot.control_running:
            raise RobotCommandError(
                f"{what} needs external control (the control script is not running)"
            )

    def _dashboard(self, command: str) -> str:
        reply, _ = self.robot.dashboard.reply(command)
        if command.strip().lower() == "shutdown":
            self.robot.controller.shutdown()
        return reply

    async def _until(self, predicate: Callable[[], bool], within: float, what: str) -> None:
        try:
            async with asyncio.timeout(within):
                while not predicate():
                    if self.status is LinkStatus.CLOSED:
                        raise ConnectionLostError("the robot link is closed")
                    self._changed.clear()
                    await self._changed.wait()
        except TimeoutError:
            raise RobotTimeoutError(f"timed out waiting for {what}") from None

    async def _start_control(self, mode: ControlMode, program: str, within: float) -> None:
        robot, c = self.robot, self.robot.controller
        if self._control and robot.control_running:
            self._set_control(True, "already running")
            return
        if mode == "urcap":
            reply = self._dashboard(f"load {program}")
            if "Loading program" not in reply:
                raise RobotCommandError(f"load {program}: {reply}")
            reply = self._dashboard("play")
            if reply != "Starting program":
                raise RobotCommandError(f"play: {reply}")
        else:
            if c.runtime_state != RuntimeState.STOPPED:  # a leftover program: stop it first
                self._dashboard("stop")
            if not c.remote_control:
                raise NotInRemoteControlError(
                    "cannot start external control: the robot is in Local control"
                )
            if not c.run_script(CONTROL_SCRIPT):
                raise RobotCommandError(
                    "cannot start external control: the controller refused the script "
                    f"(robot mode {c.robot_mode.name}, safety {c.safety_mode.name})"
                )
        await self._until(lambda: robot.control_running, within, "the control script to play")
        self._set_control(True, f"external control ({mode})")

    def _set_output(self, group: str, index: int, value: float) -> bool:
        io = self.robot.controller.io
        bit = 1 << index
        if group == "standard":
            io.standard_digital = (
                (io.standard_digital | bit) if value else (io.standard_digital & ~bit)
            )
        elif group == "configurable":
            io.configurable_digital = (
                (io.configurable_digital | bit) if value else (io.configurable_digital & ~bit)
            )
        elif group == "tool":
            io.tool_digital = (io.tool_digital | bit) if value else (io.tool_digital & ~bit)
        elif group == "analog":
            io.analog_out[index] = value
        else:
            raise InvalidArgumentError(f"no output group {group!r}")
        return True

    async def _stop_trajectory(self, reason: StopReason) -> None:
        """Brake a running trajectory to rest along its path and wait for its end (as the
        link process does before these calls)."""
        run = self._trajectory
        if run is not None:
            run._request_stop(reason)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(3.0):
                    await run.wait()

    def _set_control(self, ready: bool, reason: str) -> None:
        if ready == self._control:
            if ready and self._on_control is not None:
                self._on_control(True, reason)
            return
        self._control = ready
        self._changed.set()
        if self._on_control is not None:
            self._on_control(ready, reason)

    def _set_status(self, status: LinkStatus, reason: str) -> None:
        if status is self.status:
            return
        self.status = status
        if status is not LinkStatus.UP:
            self._latest = None
            if self._control:
                self._set_control(False, reason)
        self._changed.set()
        if self._on_status is not None:
            self._on_status(status, reason)

    def _lose(self, reason: str, back_after: float | None) -> None:
        """The link goes down (a restarted link process comes back after ``back_after``)."""
        if self.status is LinkStatus.CLOSED:
            return
        if self._trajectory is not None:
            self._trajectory._request_stop(StopReason.LINK_DOWN)
            self._trajectory.finish("failed", StopReason.LINK_LOST, keep_braking=True)
        self._down_until = None if back_after is None else time.monotonic() + back_after
        self._set_status(LinkStatus.DOWN, reason)
        self.restarts += 1

    def _watch(self) -> None:
        """Down when the controller's state stream pauses for longer than STALE_AFTER (its
        own clock: a late event loop is not a dead link)."""
        robot = self.robot
        silent = robot.controller.time - robot.last_published
        if self.status is LinkStatus.UP and silent > STALE_AFTER:
            self._lose(f"no robot state for {silent * 1000:.0f} ms", 0.0)

    # -- the robot's cycle

    def _before_cycle(self) -> None:
        if self._trajectory is not None:
            self._trajectory.step()

    def _after_cycle(self, state: RobotState) -> None:
        now = time.monotonic()
        if self.status is LinkStatus.DOWN:
            if self._down_until is None or now < self._down_until:
                return
        elif self.status is not LinkStatus.UP and self.status is not LinkStatus.STARTING:
            return
        self._last_sample = now
        self._latest = state
        self._changed.set()
        if self._control and state.runtime_state != RuntimeState.PLAYING:
            self._control = False  # the program ended (pendant, safety stop, power off)
            if self._on_control is not None:
                self._on_control(False, "control program stopped")
        if self.status is not LinkStatus.UP:
            self._set_status(LinkStatus.UP, "state stream live")
        if self._on_state is not None:
            self._on_state(state)
        for sub in tuple(self._subscriptions):
            sub.offer(state)


class FakeTrajectory:
    """A trajectory streamed by a :class:`FakeLink`, as the link process streams one
    (a :class:`fxcell.link.backend.TrajectoryRun`): one servoJ setpoint per control cycle,
    braking along the path when stopped, holding the last sample until the arm settles."""

    def __init__(
        self,
        link: FakeLink,
        traj_id: int,
        samples: np.ndarray,
        lookahead: float,
        gain: float,
        guard: Guard,
    ) -> None:
        self.link = link
        self.id = traj_id
        self.samples: list[tuple[float, ...]] = [tuple(row) for row in samples.tolist()]
        self.total = len(self.samples)
        self.lookahead = lookahead
        self.gain = gain
        self.guard = guard
        self.progress: TrajectoryProgress | None = None
        loop = asyncio.get_running_loop()
        self._done: asyncio.Future[TrajectoryResult] = loop.create_future()
        self._progress_event = asyncio.Event()
        self._replaced: asyncio.Future[bool] | None = None
        robot = link.robot
        now = robot.controller.time
        self._follower = Follower(self.samples, guard, lookahead, gain=gain, now=now, clock=now)
        self._started = time.monotonic()
        self._detached = False  # the client was told it ended; the arm still brakes

    @property
    def _u(self) -> float:
        return self._follower.u

    @property
    def done(self) -> bool:
        return self._done.done()

    async def replace_remaining(self, samples: ArrayLike, at_index: int | None = None) -> bool:
        array = np.asarray(samples, dtype=float)
        if array.ndim != 2 or array.shape[1] != 6 or len(array) == 0:
            raise InvalidArgumentError(f"trajectory samples must be (N, 6), got {array.shape}")
        if self.done:
            return False
        self.link._sent += 1
        self._follower.replace([tuple(r) for r in array.tolist()], at_index)
        self._replaced = asyncio.get_running_loop().create_future()
        waitables: set[asyncio.Future[Any]] = {self._replaced, self._done}
        finished, _ = await asyncio.wait(waitables, timeout=1.0, return_when="FIRST_COMPLETED")
        if self._replaced in finished:
            return self._replaced.result()
        return False

    async def stop(self, reason: StopReason = StopReason.STOP_REQUESTED) -> TrajectoryResult:
        if not self.done:
            self.link._sent += 1
            self._request_stop(reason)
        return await self.wait()

    async def wait(self) -> TrajectoryResult:
        return await asyncio.shield(self._done)

    async def next_progress(self) -> TrajectoryProgress | None:
        self._progress_event.clear()
        waiter = asyncio.ensure_future(self._progress_event.wait())
        try:
            waitables: set[asyncio.Future[Any]] = {waiter, self._done}
            await asyncio.wait(waitables, return_when=asyncio.FIRST_COMPLETED)
        finally:
            waiter.cancel()
        return None if self.done else self.progress

    # -- the link's side

    def _request_stop(self, reason: StopReason) -> None:
        self._follower.stop(reason)

    def finish(
        self,
        status: TrajectoryStatus,
        reason: StopReason,
        *,
        keep_braking: bool = False,
    ) -> None:
        """Report the end to the client (``keep_braking``: the arm still brakes along the
        path, as the link process does once its client is gone)."""
        if not self._done.done():
            state = self.link.robot.sample()
            self._done.set_result(
                TrajectoryResult(
                    status,
                    reason,
                    self._follower.index,
                    len(self._follower.samples),
                    state.actual_q,
                    time.monotonic() - self._started,
                )
            )
        if self._replaced is not None and not self._replaced.done():
            self._replaced.set_result(False)
        if keep_braking:
            self._detached = True
        else:
            self._end()

    def _end(self) -> None:
        self.link.robot.servo_stop()
        if self.link._trajectory is self:
            self.link._trajectory = None

    def step(self) -> None:
        """Send this cycle's setpoint (before the controller's cycle)."""
        robot = self.link.robot
        c = robot.controller
        now = c.time
        follower = self._follower
        out = follower.cycle(now, robot.servo_state(), state_at=robot.last_published)
        for notice in follower.notices:
            replaced = self._replaced
            if notice.kind == "log":
                log.log(notice.level, "link: %s", notice.text)  # as the link client logs it
            elif replaced is not None and not replaced.done():
                replaced.set_result(bool(notice.data["ok"]))
        follower.notices.clear()
        if out.target is None:
            self._finish_here(out.status or "completed", out.reason)
            return
        if not robot.servo(out.target, self.lookahead, self.gain):
            first = follower.u == 0
            self._finish_here(
                "failed",
                StopReason.NO_EXTERNAL_CONTROL if first else StopReason.SERVOJ_REFUSED,
            )
            return
        if out.progress is not None:
            self._report_progress(out.progress, len(follower.samples), out.target)
        follower.advance(now, now + CONTROL_PERIOD)

    def _finish_here(self, status: TrajectoryStatus, reason: StopReason) -> None:
        if self._detached:
            self._end()
        else:
            self.finish(status, reason)

    def _report_progress(self, index: int, total: int, commanded: tuple[float, ...]) -> None:
        if self._detached:
            return
        robot = self.link.robot
        actual = tuple(robot.arm.q.tolist())
        error = max(abs(a - b) for a, b in zip(commanded, actual, strict=True))
        # as the link process: the setpoint answers the newest state sample
        self.progress = TrajectoryProgress(
            index, total, actual, error, time.time(), robot.last_published
        )
        self._progress_event.set()


HANDLERS: dict[type[Request], Callable[[FakeLink, Any], Awaitable[object]]] = {
    Dashboard: FakeLink._do_dashboard,
    Ping: FakeLink._do_ping,
    LeaveServo: FakeLink._do_leave_servo,
    StartControl: FakeLink._do_start_control,
    StopControl: FakeLink._do_stop_control,
    ServoStop: FakeLink._do_servo_stop,
    SetOutput: FakeLink._do_set_output,
    SetTool: FakeLink._do_set_tool,
    TeachMode: FakeLink._do_teach_mode,
}
"""Each request type's handler in the fake (the same table as the link process's)."""
if set(HANDLERS) != set(REQUESTS):  # pragma: no cover - caught by the unit tests too
    raise ImportError(f"fake link requests without a handler: {set(REQUESTS) - set(HANDLERS)}")

if TYPE_CHECKING:
    from fxcell.link.backend import LinkFactory

    def _is_a_link_factory(robot: FakeRobot) -> LinkFactory:
        return robot.link_factory  # mypy checks FakeLink against LinkBackend here
