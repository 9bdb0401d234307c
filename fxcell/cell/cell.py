"""``Cell``: the await-style API over one UR3e, guarded by the robot-mode state machine.

Every public command checks the state machine's guard first (refusing with
:class:`~fxcell.errors.InvalidStateError` before anything is sent), talks to the robot
through the robot-link process, and returns once the robot confirms the effect, as
the 500 Hz state stream shows it. Commands, transitions and state samples are
published on :attr:`Cell.bus`. Moves are tasks the Cell owns: a safety stop, a
program stop or a lost link observed while one runs cancels it, and its caller gets
the matching error.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import time
from collections.abc import (
    AsyncIterator,
    Awaitable,
    Callable,
    Collection,
    Coroutine,
    Mapping,
    Sequence,
)
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

from fxcell.cell import handling, healing
from fxcell.cell.camera import CellCamera
from fxcell.cell.context import CellContext
from fxcell.cell.gripper import Gripper
from fxcell.cell.io import CellIO
from fxcell.cell.statemachine import CellState, RobotStateMachine, observed_state
from fxcell.cell.teach import TaughtStore, check_frame_point
from fxcell.cell.teach import check_name as check_position_name
from fxcell.commands import COMMANDS, CellCommands, get_command
from fxcell.config import CellConfig
from fxcell.errors import (
    CalibrationError,
    ConnectionLostError,
    FxcellError,
    InvalidArgumentError,
    InvalidStateError,
    MoveInProgressError,
    MoveStoppedError,
    NotInRemoteControlError,
    ProtectiveStopUnlockTooSoonError,
    RobotTimeoutError,
)
from fxcell.events import (
    COMMAND_ORIGIN,
    CommandEvent,
    DeviceEvent,
    EventBus,
    EventStream,
    Origin,
    StateEvent,
    TransitionEvent,
)
from fxcell.geometry import Pose
from fxcell.jsonable import to_jsonable
from fxcell.layout import Layout, LayoutConfig, layout_data
from fxcell.link import LinkStatus, StateSubscription
from fxcell.link.backend import LinkBackend, LinkFactory
from fxcell.link.client import LinkClient
from fxcell.link.contract import STOP_ERRORS, StopReason
from fxcell.motion.runner import (
    DistanceTarget,
    JointTarget,
    MoveRunner,
    MoveTarget,
    PoseTarget,
    RelativeTarget,
)
from fxcell.protocol import RobotMode, RobotState, RuntimeState, SafetyMode
from fxcell.results import GripResult, MoveResult, ProgramStatus
from fxcell.robots import RobotKind, Simulator, robot_kind
from fxcell.settling import REST_TIME, REST_VELOCITY

if TYPE_CHECKING:
    from fxcell.link.backend import ArmCalibration
    from fxcell.motion.moves import MotionController
    from fxcell.vision.placement import PlacementReport

log = logging.getLogger(__name__)

T = TypeVar("T")

PROTECTIVE_STOP_HOLD = 5.0
"""Seconds the controller keeps a protective stop locked (its wording says 5 s)."""

# States in which a command waiting for an effect gives up, as the stop reason each is: the
# error it raises comes from the link contract's one table of stop reasons (STOP_ERRORS).
_STATE_STOPS: dict[CellState, StopReason] = {
    CellState.DISCONNECTED: StopReason.LINK_LOST,
    CellState.PROTECTIVE_STOP: StopReason.PROTECTIVE_STOP,
    CellState.SAFEGUARD_STOP: StopReason.SAFEGUARD_STOP,
    CellState.EMERGENCY_STOP: StopReason.EMERGENCY_STOP,
    CellState.FAULT: StopReason.FAULT,
}
_FAILURE_STATES: dict[CellState, type[FxcellError]] = {
    state: STOP_ERRORS[reason] for state, reason in _STATE_STOPS.items()
}
EXPLAIN_SAMPLES = 25
"""State samples a failed move waits for the one that shows why (a safety or program stop)..."""
EXPLAIN_WITHIN = 0.25
"""...and seconds at most (the state stream may have stopped)."""
REMOTE_POLL = 0.25
"""Seconds between two queries of the pendant's Local/Remote switch while no move runs."""
REMOTE_POLL_MOVING = 0.02
"""... and while a move runs: a switch to Local brakes it within this plus a dashboard
round trip (neither RTDE nor the primary interface streams the switch)."""
_MOVE_ABORT_STATES: dict[CellState, type[FxcellError]] = {
    **_FAILURE_STATES,
    CellState.PROGRAM_STOPPED: STOP_ERRORS[StopReason.PROGRAM_STOPPED],
    CellState.IDLE: MoveStoppedError,
    CellState.POWER_OFF: MoveStoppedError,
    CellState.SHUTTING_DOWN: MoveStoppedError,
}


class Cell(CellCommands):
    """One UR3e cell.

    ``host=None`` starts the robot kind's simulator (the UR3e's: the embedded controller
    simulator, ``fxcell.link.embedded``); a kind without one gets no address.
    Without ``config`` the shipped configuration is used (its tool, limits and scene).
    Use ``async with Cell(...) as cell:`` (or :meth:`open` / :meth:`close`).
    ``record`` names a directory for an MCAP flight record of the session (default:
    the configuration's ``recorder.directory`` when ``recorder.enabled``).
    ``robot.kind`` in the configuration chooses the robot (:mod:`fxcell.robots`: its
    link, kinematic model and simulator; commands it cannot do are refused with
    :class:`~fxcell.errors.UnsupportedCommandError`). ``link_factory`` makes the robot
    link instead of the kind's (the UR3e's: the supervised ur_rtde process,
    :func:`fxcell.link.client.process_link`); with one, no simulator is started
    (``fxcell.testing.FakeRobot`` gives an in-process one).

    The commands (``init``, ``move_joint``, ``stop``, ...) are those of
    :class:`fxcell.commands.CellCommands`, where each is documented once.
    """

    def __init__(
        self,
        host: str | None = None,
        *,
        config: CellConfig | None = None,
        record: str | Path | None = None,
        external_control: Literal["script", "urcap"] | None = None,
        command_timeout: float | None = None,
        origin: Origin = Origin.LIBRARY,
        simulator_options: Mapping[str, Any] | None = None,
        link_factory: LinkFactory | None = None,
    ) -> None:
        # Without a config, the shipped one: its scene, tool and limits (never an empty scene).
        config = config if config is not None else CellConfig.load()
        self.taught = TaughtStore(config.positions_file)
        """Taught positions and re-taught station frames (``positions_file``)."""
        self.config = config.model_copy(update={"layout": self.taught.apply_frames(config.layout)})
        self.layout = Layout(self.config.layout)
        """The stations and their slots, as taught."""
        robot = self.config.robot
        self.kind: RobotKind = robot_kind(robot.kind)
        """The robot kind: capabilities, link, kinematic model and simulator."""
        self._host = host if host is not None else robot.host
        self.external_control = external_control or robot.external_control
        self.command_timeout = command_timeout or robot.command_timeout
        if record is None and self.config.recorder.enabled:
            record = self.config.recorder.directory
        self._record = record
        self._origin = origin
        self._simulator_options = dict(simulator_options or {})
        self.bus = EventBus()
        self.machine = RobotStateMachine(on_transition=self._on_transition)
        self._link_factory = link_factory
        self.link: LinkBackend | None = None
        self._simulator: Simulator | None = None
        self._recorder: Any = None
        self.controller_info: dict[str, str] = {}
        """Controller version, serial number and robot model, read when the link is up."""
        self._machine_task: asyncio.Task[None] | None = None
        self._observed: CellState = CellState.DISCONNECTED
        self._shutting_down = False
        self._control_wanted = False
        self._protective_since: float | None = None
        self._runner: MoveRunner | None = None
        """The move running, or the last one (its status object)."""
        self._motion: MotionController | None = None
        self._move_queue = asyncio.Lock()
        self._stops = 0
        """Counts stop() calls: a queued move that sees it change while waiting ends."""
        self.calibration: ArmCalibration | None = None
        """The arm's calibration the planner uses, in its kind's form (None: not read, or
        unreadable)."""
        self._restore: asyncio.Task[None] | None = None
        self._remote_watch: asyncio.Task[None] | None = None
        self._move_started = asyncio.Event()
        """Set when a move starts: the remote watch polls fast from then on."""
        self.local_control = False
        """The teach pendant is in Local control (polled every 0.25 s, every 0.02 s while a
        move runs): moves are refused and a running move brakes."""
        self._opened = False
        self._gripper: Gripper | None = None
        self._io: CellIO | None = None
        self._camera: CellCamera | None = None
        self._freedrive = False
        self.held: str | None = None
        """The kind of object the gripper holds after a pick (None: nothing)."""
        self.link_losses = 0
        """Times the robot link went down after being up (a dropped or restarted link
        process, a paused state stream): each one is a warning in the log."""
        self._link_was_up = False
        self._context = CellContext(
            bus=self.bus,
            command=self._command,
            record=self._recorded,
            link=self._link,
            sample=self._sample,
            latest=lambda: self.robot_state,
            states=self.robot_states,
            hold=self._hold,
            config=lambda: self.config,
            layout=lambda: self.layout,
            host=lambda: self.host,
            timeout=lambda: self.command_timeout,
        )
        """What the parts (gripper, IO, camera, pick and place) use of the Cell."""

    @classmethod
    def from_config(cls, config: str | Path | CellConfig | None = None, **kwargs: Any) -> Cell:
        """A Cell configured from ``cell.yaml`` (a path) or a :class:`CellConfig`."""
        if not isinstance(config, CellConfig):
            config = CellConfig.load(config)
        return cls(config=config, **kwargs)

    # ------------------------------------------------------------- life cycle

    @property
    def gripper(self) -> Gripper:
        """The robot kind's gripper (the UR3e's Robotiq Hand-E through the URCap's socket,
        the Ned2's Gripper 1 through its TCP server), in SI units."""
        if self._gripper is None:
            self._gripper = Gripper(self._context, self.kind.gripper, self.kind.name)
        return self._gripper

    @property
    def io(self) -> CellIO:
        """The configured IO signals by name (``cell.io.get("machine_done")``)."""
        if self._io is None:
            self._io = CellIO(self._context, self.kind.signals, self.kind.name)
        return self._io

    @property
    def camera(self) -> CellCamera:
        """The cell's camera and the placement check (``vision`` in the configuration)."""
        if self._camera is None:
            self._camera = CellCamera(self._context)
        return self._camera

    @property
    def host(self) -> str | None:
        """The controller address (that of the embedded simulator once it runs)."""
        return self._host

    async def open(self) -> None:
        """Start the recorder, the simulator if no host is set, and the robot link."""
        if self._opened:
            return
        self._opened = True
        try:
            if self._record is not None:
                self._recorder = _start_recorder(Path(self._record), self)
            launch = self.kind.simulator
            if self._host is None and self._link_factory is None and launch is not None:
                simulator = launch(self._simulator_options)
                self._host = str(await asyncio.to_thread(simulator.start))
                self._simulator = simulator
            # Load the motion planner before the link streams: its imports hold the GIL
            # long enough to starve the loop (and trip the link watchdog) mid-move.
            await asyncio.to_thread(self._moves().warm_up)
            self._machine_task = asyncio.create_task(self.machine.run(), name="cell machine")
            factory = self._link_factory or self.kind.link
            self.link = factory(
                self._host,
                self.config.robot.model_copy(update={"external_control": self.external_control}),
                on_state=self._on_sample,
                on_status=self._on_link_status,
                on_control=self._on_control,
            )
            await self.link.start(wait=True)
            await self.wait_for_state(*[s for s in CellState if s is not CellState.DISCONNECTED])
            self.controller_info = (await self.link.controller_info()).as_dict()
            if isinstance(self.link, LinkClient) and self.link.scheduling is not None:
                self.controller_info["link_scheduling"] = self.link.scheduling.describe()
            self.controller_info.update(await self._use_calibration())
            if self._recorder is not None:
                self._recorder.update_metadata(self.controller_info)
            self._remote_watch = asyncio.create_task(self._watch_remote(), name="remote watch")
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        """Cancel any move, stop the link (and the embedded simulator), finish the record."""
        await self._cancel_move(MoveStoppedError("the cell is closing"))
        if self._remote_watch is not None:
            self._remote_watch.cancel()
            with contextlib.suppress(BaseException):
                await self._remote_watch
            self._remote_watch = None
        if self._restore is not None:
            self._restore.cancel()
            with contextlib.suppress(BaseException):
                await self._restore
            self._restore = None
        if self._gripper is not None:
            await self._gripper.close_connection()
        if self._camera is not None:
            await self._camera.close()
        if self.link is not None:
            await self.link.close()
        if self._machine_task is not None:
            self._machine_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._machine_task
            self._machine_task = None
        if self._simulator is not None:
            simulator, self._simulator = self._simulator, None
            await asyncio.to_thread(simulator.stop)
            self._host = None
        if self._recorder is not None:
            recorder, self._recorder = self._recorder, None
            await asyncio.to_thread(recorder.close)
        self._opened = False

    async def __aenter__(self) -> Cell:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ------------------------------------------------------------- state

    @property
    def state(self) -> CellState:
        """The state machine's current state."""
        return self.machine.state

    @property
    def robot_state(self) -> RobotState | None:
        """The latest 500 Hz sample (``None`` while disconnected)."""
        return self.link.latest if self.link is not None else None

    def transitions(self, maxsize: int = 256) -> EventStream:
        """Async iterator over :class:`TransitionEvent` (use ``with``)."""
        return self.bus.stream(TransitionEvent, maxsize=maxsize)

    def events(self, *types: type, maxsize: int = 4096) -> EventStream:
        """Async iterator over bus events of the given types (all if none)."""
        return self.bus.stream(*types, maxsize=maxsize)

    def robot_states(self, maxsize: int = 1024) -> StateSubscription:
        """Async iterator over every 500 Hz :class:`RobotState` sample (use ``with``)."""
        return self._link().subscribe(maxsize)

    async def wait_for_state(
        self,
        *states: CellState,
        timeout: float | None = None,  # noqa: ASYNC109
    ) -> CellState:
        """Wait until the machine is in one of ``states``; returns it."""
        wanted = set(states)
        try:
            async with asyncio.timeout(timeout if timeout is not None else self.command_timeout):
                while self.state not in wanted:
                    await self.machine.wait_changed()
        except TimeoutError:
            raise RobotTimeoutError(
                f"state {self.state.value!r} did not become one of "
                f"{sorted(s.value for s in wanted)}"
            ) from None
        return self.state

    @property
    def calibration_status(self) -> dict[str, str] | None:
        """Which arm model pose moves are planned on (``model``: ``calibrated``, ``nominal``,
        ``nominal (fallback)`` or ``uncalibrated``), its ``source`` and the calibration's
        ``checksum``; None before the cell has connected."""
        info = self.controller_info
        if "calibration_model" not in info:
            return None
        return {
            "model": info["calibration_model"],
            "source": info.get("calibration_source", ""),
            "checksum": info.get("calibration_checksum", ""),
        }

    async def _use_calibration(self) -> dict[str, str]:
        """Take the arm's calibration (``robot.calibration``: the controller's, by default, a
        file, or ``nominal``) into the planner; which model is in use, its source, deltas and
        checksum for the log metadata, ``fxcell info`` and the daemon's state.

        A controller whose calibration cannot be read is not an error at connect: pose moves
        are refused (UncalibratedError) unless ``robot.accept_nominal_kinematics``, and the
        model says ``uncalibrated`` (or ``nominal (fallback)``), so nothing moves on a model
        millimetres off without it being visible."""
        from fxcell.motion.calibration import CONTROLLER, NOMINAL

        source = self.config.robot.calibration
        formats = self.kind.calibration
        calibration: ArmCalibration | None = None
        if source == NOMINAL:
            calibration = formats.nominal()
            source = "nominal (robot.calibration: nominal)"
        elif source is None or source == CONTROLLER:
            try:
                calibration = await self._link().read_calibration()
            except CalibrationError as exc:
                log.warning("the arm's calibration: %s", exc)
                self._moves().planner.use_calibration(None, str(exc))
                fallback = self.config.robot.accept_nominal_kinematics
                return {
                    "calibration_model": "nominal (fallback)" if fallback else "uncalibrated",
                    "calibration_source": f"unreadable: {exc}",
                    "calibration_checksum": formats.nominal().checksum if fallback else "",
                }
            source = f"controller {self._host}"
            self._moves().planner.use_calibration(calibration)
        else:
            calibration = formats.load(source)  # the planner read it already
        self.calibration = calibration
        return {
            "calibration_model": "nominal" if calibration.is_nominal else "calibrated",
            "calibration_source": source,
            "calibration_checksum": calibration.checksum,
            "calibration": json.dumps(calibration.summary()),
        }

    # ------------------------------------------------------------- observation

    def _on_sample(self, sample: RobotState) -> None:
        self.bus.publish(StateEvent(sample))
        self._observe(sample)

    def _on_link_status(self, status: LinkStatus, reason: str) -> None:
        if status is not LinkStatus.UP:
            if self._link_was_up and status is LinkStatus.DOWN:
                self.link_losses += 1
            self._link_was_up = False
            self._shutting_down = False
            self._observe(None, reason)
            return
        self._link_was_up = True
        if self._control_wanted and (self._restore is None or self._restore.done()):
            self._restore = asyncio.create_task(self._restore_control(), name="restore control")

    async def _restore_control(self) -> None:
        """After the link came back: take over the control script it left playing.

        A new link process has no control interface, but the script of the old one may
        still be PLAYING on the controller (a crashed link does not stop it). If external
        control was on and that program still plays, start it again (the link replaces
        the orphan); a program stopped meanwhile (pendant, safety) stays stopped.
        """
        try:
            await self.wait_for_state(*[s for s in CellState if s is not CellState.DISCONNECTED])
            if self._control_wanted and self.state is CellState.PROGRAM_STOPPED:
                # the arm may still be braking after the old link's last setpoint: a new
                # control script is started only once it is seen at rest
                await self._wait_at_rest(self.command_timeout, "restore_external_control")
            sample = self.robot_state
            if (
                self._control_wanted
                and self.state is CellState.PROGRAM_STOPPED
                and sample is not None
                and sample.runtime_state == RuntimeState.PLAYING
            ):
                async with self._command("restore_external_control"):
                    await self._link().enable_control(self.command_timeout)
                    await self._await_effect(
                        "restore_external_control", {CellState.EXTERNAL_CONTROL_READY}, None
                    )
                    await self._send_tool()
        except FxcellError as exc:
            log.warning("could not restore external control after reconnecting: %s", exc)

    @property
    def link_recovering(self) -> bool:
        """The link is down, or back but external control not restored yet."""
        return self.state is CellState.DISCONNECTED or (
            self._restore is not None and not self._restore.done()
        )

    async def _wait_at_rest(self, within: float, command: str) -> None:
        """Return once the state samples of :data:`REST_TIME` s of controller time in a
        row show every joint slower than ``REST_VELOCITY`` (the controller's own joint
        speeds)."""
        quiet_since: float | None = None  # controller time of the first quiet sample
        try:
            async with asyncio.timeout(within):
                with self._link().subscribe(256) as samples:
                    latest = self.robot_state
                    if latest is not None and _at_rest(latest):
                        quiet_since = latest.timestamp
                    async for sample in samples:
                        if not _at_rest(sample):
                            quiet_since = None
                            continue
                        if quiet_since is None:
                            quiet_since = sample.timestamp
                        if sample.timestamp - quiet_since >= REST_TIME - 1e-9:
                            return
        except TimeoutError:
            raise RobotTimeoutError(
                f"{command}(): the arm was not seen at rest within {within:g} s"
            ) from None

    async def restore_control(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        async with self._command("restore_control"):
            limit = timeout if timeout is not None else self.config.robot.heal_timeout
            loop = asyncio.get_running_loop()
            deadline = loop.time() + limit

            def left() -> float:
                return max(0.0, deadline - loop.time())

            connected = [s for s in CellState if s is not CellState.DISCONNECTED]
            await self.wait_for_state(*connected, timeout=left())
            restore = self._restore
            if restore is not None and not restore.done():
                # the automatic take-over after the reconnect finishes first
                with contextlib.suppress(Exception):
                    async with asyncio.timeout(left()):
                        await asyncio.shield(restore)
            await self._move_landed()
            state = self.state
            error = _FAILURE_STATES.get(state)
            if error is not None:
                raise error(f"restore_control(): the robot is in {state.value}")
            if not state.is_running or state is CellState.FREEDRIVE:
                raise InvalidStateError(
                    "restore_control",
                    state.value,
                    sorted(s.value for s in _running_states() if s is not CellState.FREEDRIVE),
                    "init the robot (power on, brake release) first",
                )
            await self._wait_at_rest(left(), "restore_control")
            if self.state is CellState.PROGRAM_STOPPED:
                await self._require_remote()
                self._control_wanted = True
                await self._link().enable_control(left())
            await self._await_effect("restore_control", {CellState.EXTERNAL_CONTROL_READY}, left())
            await self._send_tool()

    def _on_control(self, ready: bool, reason: str) -> None:
        if self.link is not None:
            self._observe(self.link.latest, reason)

    def _observe(self, sample: RobotState | None, detail: str = "") -> None:
        moving = self._moving()
        target = observed_state(
            sample,
            control_ready=self.link is not None and self.link.control_ready,
            moving=moving,
            stopping=moving and self._runner is not None and self._runner.stopping,
            shutting_down=self._shutting_down,
            freedrive=self._freedrive,
        )
        if target is self._observed:
            return
        self._observed = target
        if target is CellState.PROTECTIVE_STOP:
            self._protective_since = time.monotonic()
        if moving and target in _MOVE_ABORT_STATES:
            error = _MOVE_ABORT_STATES[target](f"move aborted: robot went to {target.value}")
            if self._runner is not None:
                self._runner.abort(error)
        self.machine.sync(target, "observed", detail)

    def _on_transition(self, event: TransitionEvent) -> None:
        self.bus.publish(event)

    # ------------------------------------------------------------- commands

    async def run_command(self, command: str, /, **args: Any) -> Any:
        """Run ``command`` of :data:`fxcell.commands.COMMANDS` with keyword arguments
        (how the daemon and replay call the Cell)."""
        entry = get_command(command)
        entry.check_args(args)
        method = getattr(type(self), command)
        if method is getattr(CellCommands, command):
            raise NotImplementedError(f"Cell does not implement {command}()")
        return await getattr(self, command)(**args)

    async def check_command(self, command: str, /, **args: Any) -> None:
        """Raise now what ``command`` with ``args`` would be refused with before it starts,
        without starting it (nothing is sent to the robot).

        The checks are those the command itself makes before it acts: the arguments
        against the table (names, finite numbers, bounds, lengths), the state machine's
        guard, for moves a running move (unless ``queue``), Local control, the factors
        and the target (within the joint limits, a pose, within reach, a collision-free
        IK solution; for ``pick``/``place`` names, interlock, what the gripper holds and
        the slot's poses). The daemon calls it before an operation exists, so a refusal
        is the request's answer whether or not the client waits. A refusal is recorded
        as the command's error.
        """
        entry = get_command(command)
        try:
            entry.check_args(args)
            entry.check_values(args)
            if entry.kind != "move":
                await self._admit(command, args)
                return
            await self._move_landed()
            await self._admit_move(command, args, queue=bool(args.get("queue")))
        except FxcellError as exc:
            self._record_refusal(command, args, exc)
            raise

    def _check_arguments(self, command: str, args: Mapping[str, Any]) -> None:
        """The checks of arguments against the cell's configuration that commands other
        than moves make before they act (moves: :meth:`_admit_move`)."""
        checks: dict[str, Callable[[], object]] = {
            "io_set": lambda: self.io.check_set(args["signal"], args["value"]),
            "io_wait_for": lambda: self.io.check_wait(args["signal"], args.get("value", True)),
            "teach": lambda: check_position_name(args["name"]),
            "teach_frame_point": lambda: check_frame_point(
                self.layout.station(args["station"]).name, args["point"]
            ),
        }
        check = checks.get(command)
        if check is not None:
            check()

    async def _admit(self, name: str, args: Mapping[str, Any]) -> None:
        """Raise what refuses command ``name`` of the table (not a move: :meth:`_admit_move`)
        before it acts: its arguments against the configuration, then the guard the table
        names (a move that has just ended is let land in the state machine first); any
        command the robot kind cannot do (UnsupportedCommandError)."""
        self.kind.capabilities.check(name)
        entry = COMMANDS.get(name)
        if entry is None or entry.kind == "move":
            return
        self._check_arguments(name, args)
        if entry.guard is not None and self.state not in self.machine.allowed(entry.guard):
            await self._move_landed()
            self._check_guard(name)

    def _check_guard(self, name: str) -> CellState:
        """Raise :class:`InvalidStateError` unless the guard the command table names for
        ``name`` admits the current state (a name outside the table is a move of
        :meth:`run_move`: the moves' guard); the state."""
        guard = (COMMANDS.get(name) or COMMANDS["move_joint"]).guard
        return self.machine.check(guard, name) if guard is not None else self.state

    def _record_refusal(self, name: str, args: Mapping[str, Any], exc: FxcellError) -> None:
        """Record a command refused before it started, as one that failed at once."""
        self._failed(self._started(name, {k: to_jsonable(v) for k, v in args.items()}), exc)

    async def _admit_move(self, name: str, args: Mapping[str, Any], *, queue: bool) -> None:
        """Raise what refuses move ``name`` before it exists: another move running
        (unless ``queue``: it waits its turn), the guard, Local control, then the factors
        and the target, or for ``pick``/``place`` the slot; first a move the robot kind
        cannot do (UnsupportedCommandError)."""
        self.kind.capabilities.check(name)
        if not (queue and self._moving()):
            if self._moving():
                raise MoveInProgressError(f"{name}(): another move is running")
            self._check_guard(name)
        self._check_remote(name)
        vf, af = args.get("velocity_factor"), args.get("acceleration_factor")
        if name in handling.ADMIT:
            await handling.check(self, self._context, name, args["station"], args["slot"], vf, af)
            return
        target = self._move_target(name, args)
        await self._moves().check(target, self._sample().actual_q, vf, af)

    def _move_target(self, name: str, args: Mapping[str, Any]) -> MoveTarget:
        """The target of move command ``name`` (the move methods and :meth:`check_command`
        build it here, so both check the same thing)."""
        targets: dict[str, Callable[[], MoveTarget]] = {
            "move_joint": lambda: JointTarget(args["target"]),
            "go_home": lambda: JointTarget(self.config.home),
            "move_pose": lambda: PoseTarget(args["target"], bool(args.get("linear", False))),
            "move_distance": lambda: DistanceTarget(args["distance"]),
            "move_relative": lambda: RelativeTarget(args["start_pose"], args["target_pose"]),
            "move_to": lambda: JointTarget(self._position_joints(args["name"])),
        }
        return targets[name]()

    def _position_joints(self, name: str) -> Sequence[float]:
        """The joints of taught position ``name`` (``home``: the configured home);
        UnknownPositionError for an unknown name."""
        if name == "home":
            return self.config.home
        joints: Sequence[float] = self.taught.position(name)["joints"]
        return joints

    def _check_remote(self, name: str) -> None:
        if self.local_control:
            raise NotInRemoteControlError(
                f"{name}() refused: the teach pendant is in Local control; "
                "switch it to Remote Control"
            )

    @contextlib.asynccontextmanager
    async def _command(self, name: str, /, **args: Any) -> AsyncIterator[dict[str, Any]]:
        """Run command ``name`` as a recorded one (see :meth:`_recorded`), refused first if
        the table's checks refuse it (:meth:`_admit`: the refusal is recorded as its error)."""
        async with self._recorded(name, **args) as outcome:
            await self._admit(name, args)
            yield outcome

    @contextlib.asynccontextmanager
    async def _recorded(self, name: str, /, **args: Any) -> AsyncIterator[dict[str, Any]]:
        """Publish command ``name``'s start, then its end: ``outcome["result"]`` or the
        error that ended it."""
        start = self._started(name, args)
        outcome: dict[str, Any] = {"result": None}
        try:
            yield outcome
        except BaseException as exc:
            self._failed(start, exc)
            raise
        result = to_jsonable(outcome["result"])
        self.bus.publish(dataclasses.replace(start, ended=time.time(), outcome="ok", result=result))

    def _started(self, name: str, args: Mapping[str, Any]) -> CommandEvent:
        origin = COMMAND_ORIGIN.get() or self._origin
        event = CommandEvent(self.bus.next_command_id(), name, args, origin, time.time())
        self.bus.publish(event)
        return event

    def _failed(self, start: CommandEvent, exc: BaseException) -> None:
        kind, message = type(exc).__name__, str(exc)
        self.bus.publish(
            dataclasses.replace(
                start, ended=time.time(), outcome="error", error_type=kind, error_message=message
            )
        )

    def _link(self) -> LinkBackend:
        if self.link is None:
            raise ConnectionLostError("the cell is not open (use `async with Cell(...)`)")
        return self.link

    def _sample(self) -> RobotState:
        sample = self.robot_state
        if sample is None:
            raise ConnectionLostError("no robot state: the link is down")
        return sample

    async def _watch_remote(self) -> None:
        """Follow the pendant's Local/Remote switch: Local brakes a running move."""
        while True:
            period = REMOTE_POLL_MOVING if self._moving() else REMOTE_POLL
            with contextlib.suppress(TimeoutError):  # a move starting ends the wait
                async with asyncio.timeout(period):
                    await self._move_started.wait()
            self._move_started.clear()
            link = self.link
            if link is None or not link.up:
                continue
            try:
                local = not await link.remote_control(within=2.0)
            except FxcellError:
                continue
            if local and not self.local_control:
                log.warning("the teach pendant switched to Local control")
                if self._runner is not None:
                    self._runner.abort(
                        NotInRemoteControlError(
                            "move aborted: the teach pendant switched to Local control"
                        )
                    )
            self.local_control = local

    async def _require_remote(self) -> None:
        if not await self._link().remote_control():
            raise NotInRemoteControlError(
                "the teach pendant is in Local control: switch it to Remote Control"
            )

    async def _await_effect(
        self,
        command: str,
        wanted: set[CellState],
        within: float | None,
        ignore: CellState | None = None,
    ) -> CellState:
        """Wait until the state is in ``wanted``; typed errors on safety stops or timeout."""
        limit = within if within is not None else self.command_timeout
        try:
            async with asyncio.timeout(limit):
                while True:
                    state = self.state
                    if state in wanted:
                        return state
                    error = _FAILURE_STATES.get(state) if state is not ignore else None
                    if error is not None:
                        raise error(f"{command}(): the robot went to {state.value}")
                    await self.machine.wait_changed()
        except TimeoutError:
            raise RobotTimeoutError(
                f"{command}(): the robot did not reach "
                f"{' or '.join(sorted(s.value for s in wanted))} within {limit:g} s "
                f"(state {self.state.value})"
            ) from None

    async def power_on(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        async with self._command("power_on"):
            state = self.state
            if state is CellState.POWER_OFF:
                await self._require_remote()
                await self._link().power(True)
            await self._await_effect("power_on", {CellState.IDLE}, timeout)

    async def brake_release(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        async with self._command("brake_release"):
            state = self.state
            if state is CellState.IDLE:
                await self._require_remote()
                await self._link().release_brakes()
            await self._await_effect("brake_release", _running_states(), timeout)

    async def power_off(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        async with self._command("power_off"):
            state = self.state
            if state is not CellState.POWER_OFF:
                self._control_wanted = False
                await self._require_remote()
                await self._link().power(False)
            await self._await_effect("power_off", {CellState.POWER_OFF}, timeout)

    async def init(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        async with self._command("init"):
            if self.state in (CellState.POWER_OFF, CellState.POWERING_ON):
                await self.power_on(timeout=timeout)
            if self.state is CellState.IDLE:
                await self.brake_release(timeout=timeout)
            if self.state is not CellState.EXTERNAL_CONTROL_READY:
                await self.start_external_control(timeout=timeout)

    async def start_external_control(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        async with self._command("start_external_control", mode=self.external_control):
            state = self.state
            if state is CellState.EXTERNAL_CONTROL_READY:
                return
            await self._require_remote()
            limit = timeout if timeout is not None else self.command_timeout
            self._control_wanted = True
            await self._link().enable_control(limit)
            await self._await_effect(
                "start_external_control", {CellState.EXTERNAL_CONTROL_READY}, timeout
            )
            await self._send_tool()

    async def stop_external_control(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        async with self._command("stop_external_control"):
            self._control_wanted = False
            link = self._link()
            if link.control_ready or self.state is CellState.EXTERNAL_CONTROL_READY:
                await link.disable_control()
            await self._await_effect("stop_external_control", {CellState.PROGRAM_STOPPED}, timeout)

    async def unlock_protective_stop(
        self,
        wait: bool = False,
        *,
        timeout: float | None = None,  # noqa: ASYNC109
    ) -> None:
        async with self._command("unlock_protective_stop", wait=wait):
            await self._require_remote()
            limit = timeout if timeout is not None else self.command_timeout
            deadline = time.monotonic() + limit + (PROTECTIVE_STOP_HOLD if wait else 0.0)
            link = self._link()
            while True:
                if await link.unlock_protective_stop():
                    break
                since = self._protective_since or time.monotonic()
                remaining = max(0.0, PROTECTIVE_STOP_HOLD - (time.monotonic() - since))
                if not wait:
                    raise ProtectiveStopUnlockTooSoonError(remaining)
                if time.monotonic() > deadline:
                    raise RobotTimeoutError("the controller kept refusing to unlock")
                await asyncio.sleep(min(max(remaining, 0.05), 0.25))
            await self._await_effect(
                "unlock_protective_stop",
                {CellState.IDLE, CellState.POWER_OFF, *_running_states()},
                timeout,
                ignore=CellState.PROTECTIVE_STOP,
            )
            if self._control_wanted and self.state is CellState.PROGRAM_STOPPED:
                await link.enable_control(limit)
                await self._await_effect(
                    "unlock_protective_stop", {CellState.EXTERNAL_CONTROL_READY}, timeout
                )

    async def shutdown(self, *, timeout: float | None = None) -> None:  # noqa: ASYNC109
        async with self._command("shutdown"):
            await self._require_remote()
            link = self._link()
            self._control_wanted = False
            await link.shutdown()
            self._shutting_down = True
            self._observe(self.robot_state, "shutdown sent")
            await self.wait_for_state(
                CellState.DISCONNECTED, CellState.SHUTTING_DOWN, timeout=timeout
            )
            if self.state is CellState.SHUTTING_DOWN:
                await self.wait_for_state(CellState.DISCONNECTED, timeout=timeout)

    # ------------------------------------------------------------- queries

    async def get_robot_mode(self) -> RobotMode:
        async with self._command("get_robot_mode") as out:
            out["result"] = mode = RobotMode(self._sample().robot_mode)
            return mode

    async def get_safety_status(self) -> SafetyMode:
        async with self._command("get_safety_status") as out:
            out["result"] = mode = SafetyMode(self._sample().safety_mode)
            return mode

    async def get_program_state(self) -> ProgramStatus:
        async with self._command("get_program_state") as out:
            out["result"] = status = await self._link().program_status()
            return status

    async def is_in_remote_control(self) -> bool:
        async with self._command("is_in_remote_control") as out:
            out["result"] = remote = await self._link().remote_control()
            return remote

    async def get_current_joint_values(self) -> tuple[float, ...]:
        async with self._command("get_current_joint_values") as out:
            out["result"] = q = tuple(self._sample().actual_q)
            return q

    def _tcp_pose(self) -> Pose:
        pose: Pose = self._moves().planner.kinematics.forward(self._sample().actual_q)
        return pose

    async def get_current_pose(self) -> tuple[float, ...]:
        async with self._command("get_current_pose") as out:
            pose = self._tcp_pose()
            out["result"] = result = (*map(float, pose.position), *pose.quaternion)
            return result

    async def get_current_rpy(self) -> tuple[float, float, float]:
        async with self._command("get_current_rpy") as out:
            out["result"] = rpy = self._tcp_pose().rpy
            return rpy

    async def get_current_pose_rpy(self) -> tuple[float, ...]:
        async with self._command("get_current_pose_rpy") as out:
            pose = self._tcp_pose()
            out["result"] = result = (*map(float, pose.position), *pose.rpy)
            return result

    async def get_velocity(self) -> tuple[float, ...]:
        async with self._command("get_velocity") as out:
            out["result"] = qd = tuple(self._sample().actual_qd)
            return qd

    # ------------------------------------------------------------- moves

    async def run_move(
        self, name: str, args: Mapping[str, Any], body: Callable[[], Coroutine[Any, Any, T]]
    ) -> T:
        """Run ``body`` as the Cell's move, guarded and cancellable (see :meth:`_run_move`)."""
        result: T = await self._run_move(name, args, lambda: MoveRunner(lambda _: body(), name))
        return result

    async def _run_move(
        self, name: str, args: Mapping[str, Any], make: Callable[[], MoveRunner]
    ) -> Any:
        """Run the move ``make()`` returns, as the Cell's one move.

        Only in ``running.external_control_ready``; one move at a time; an observed
        safety stop, program stop or lost link aborts it and the caller gets the
        matching error; :meth:`stop` brakes it, ending it with :class:`MoveStoppedError`.
        """
        async with self._command(name, **args) as out:
            if self._runner is not None and self._runner.running:
                raise MoveInProgressError(f"{name}(): another move is running")
            self._check_guard(name)
            self._check_remote(name)
            runner = make()
            self._runner = runner
            task = runner.start()
            self._move_started.set()
            self._observe(self.robot_state, name)
            try:
                out["result"] = result = await asyncio.shield(task)
                return result
            except asyncio.CancelledError:
                if not task.done():  # our caller was cancelled: stop the move too
                    runner.stopping = True
                    self._observe(self.robot_state, f"{name} cancelled")
                    task.cancel()
                    with contextlib.suppress(BaseException):
                        await task
                    raise
                if runner.error is not None:
                    raise runner.error from None
                raise MoveStoppedError(f"{name}() was stopped") from None
            except MoveStoppedError:
                if runner.error is not None:
                    raise runner.error from None
                raise
            except FxcellError as exc:
                if runner.error is not None:
                    raise runner.error from None
                # the body may have heard of a stop (the link's end report) before the
                # state sample that shows it: that sample names the error
                explained = await self._stop_behind(name)
                if explained is not None:
                    raise explained from exc
                raise
            finally:
                self._observe(self.robot_state, f"{name} ended")

    async def _stop_behind(self, name: str) -> FxcellError | None:
        """The stop that ended a failed move, once the state shows it (within
        :data:`EXPLAIN_SAMPLES` samples or :data:`EXPLAIN_WITHIN` s); None if none shows."""

        def seen() -> FxcellError | None:
            error = _MOVE_ABORT_STATES.get(self._observed)
            if error is None:
                return None
            return error(f"move aborted: robot went to {self._observed.value}")

        found = seen()
        link = self.link
        if found is not None or link is None:
            return found
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(EXPLAIN_WITHIN):
                with link.subscribe(EXPLAIN_SAMPLES + 1) as samples:
                    count = 0
                    async for _ in samples:  # each was observed before it got here
                        found = seen()
                        count += 1
                        if found is not None or count >= EXPLAIN_SAMPLES:
                            break
        return found

    def _moving(self) -> bool:
        return self._runner is not None and self._runner.running

    async def _cancel_move(self, error: FxcellError, graceful: bool = False) -> None:
        runner = self._runner
        if runner is None or not runner.running:
            return
        runner.stopping = True
        self._observe(self.robot_state, "stop")
        await runner.stop(error, graceful=graceful)

    async def stop(self) -> bool:
        async with self._command("stop") as out:
            self._stops += 1  # ends the moves waiting with queue=True too
            running = self._moving()
            await self._cancel_move(MoveStoppedError("stopped by stop()"), graceful=True)
            out["result"] = running
            return running

    # ------------------------------------------------------------- move methods
    # The logic lives in fxcell.motion.moves (MotionController): validate, IK, collision
    # check, plan, time, stream, brake. Here: guards, the move task, events.

    def _moves(self) -> MotionController:
        if self._motion is None:
            from fxcell.motion.moves import MotionController

            self._motion = MotionController(
                self.config,
                publish=self.bus.publish,
                kinematics=self.kind.kinematics,
                collision=self.kind.collision,
                capabilities=self.kind.capabilities,
                options=self.kind.execution,
            )
        return self._motion

    @property
    def motion(self) -> MotionController:
        """The move logic: default factors, the OMPL planner (``use_planner``), the
        running execution."""
        return self._moves()

    async def _move(self, name: str, args: dict[str, Any], *, queue: bool = False) -> MoveResult:
        """Run move command ``name``: its target checked before the move exists (a
        refusal is recorded), then planned and executed as the Cell's one move."""
        try:
            await self._move_landed()
            await self._admit_move(name, args, queue=queue)
        except FxcellError as exc:
            self._record_refusal(name, {**args, "queue": queue}, exc)
            raise
        return await self._run_checked(name, args, self._move_target(name, args), queue=queue)

    async def _run_checked(
        self, name: str, args: dict[str, Any], target: MoveTarget, *, queue: bool = False
    ) -> MoveResult:
        if queue:
            # Queued moves start in call order, each once the running move has ended
            # (however it ended); a stop() meanwhile ends them without moving.
            stops = self._stops
            async with self._move_queue:
                while (running := self._runner) is not None and running.task is not None:
                    if running.task.done():
                        break
                    await asyncio.wait({running.task})
                if self._stops != stops:
                    recorded = {k: to_jsonable(v) for k, v in args.items()}
                    async with self._command(name, **recorded, queue=True):
                        raise MoveStoppedError(f"{name}() was waiting in the queue: stopped")
                return await self._run_checked(name, {**args, "queue": True}, target)
        await self._move_landed()

        def make() -> MoveRunner:
            return self._moves().runner(
                target,
                self._link(),
                lambda: self._sample().actual_q,
                args.get("velocity_factor"),
                args.get("acceleration_factor"),
                name=name,
            )

        result: MoveResult = await self._run_move(
            name, {k: to_jsonable(v) for k, v in args.items()}, make
        )
        return result

    async def _move_landed(self) -> None:
        """Let the end of the previous move land in the state machine (it is queued there
        when the move's caller resumes), so that a command right after a move sees ready."""
        if not self._moving() and self.state in (CellState.MOVING, CellState.STOPPING):
            others = [st for st in CellState if st not in (CellState.MOVING, CellState.STOPPING)]
            with contextlib.suppress(RobotTimeoutError):
                await self.wait_for_state(*others, timeout=1.0)

    async def move_joint(
        self,
        target: Sequence[float],
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        queue: bool = False,
    ) -> MoveResult:
        args = {"target": target, "velocity_factor": velocity_factor,
                "acceleration_factor": acceleration_factor}  # fmt: skip
        return await self._move("move_joint", args, queue=queue)

    async def go_home(
        self,
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        queue: bool = False,
    ) -> MoveResult:
        args = {"velocity_factor": velocity_factor, "acceleration_factor": acceleration_factor}
        return await self._move("go_home", args, queue=queue)

    async def move_pose(
        self,
        target: Pose | Sequence[float],
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        linear: bool = False,
        queue: bool = False,
    ) -> MoveResult:
        args = {"target": target, "velocity_factor": velocity_factor,
                "acceleration_factor": acceleration_factor, "linear": linear}  # fmt: skip
        return await self._move("move_pose", args, queue=queue)

    async def move_distance(
        self,
        distance: Sequence[float],
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        queue: bool = False,
    ) -> MoveResult:
        args = {"distance": distance, "velocity_factor": velocity_factor,
                "acceleration_factor": acceleration_factor}  # fmt: skip
        return await self._move("move_distance", args, queue=queue)

    async def move_relative(
        self,
        start_pose: Pose | Sequence[float],
        target_pose: Pose | Sequence[float],
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        queue: bool = False,
    ) -> MoveResult:
        args = {"start_pose": start_pose, "target_pose": target_pose,
                "velocity_factor": velocity_factor,
                "acceleration_factor": acceleration_factor}  # fmt: skip
        return await self._move("move_relative", args, queue=queue)

    async def set_velocity_factor(self, value: float) -> None:
        async with self._command("set_velocity_factor", value=to_jsonable(value)):
            self._moves().set_velocity_factor(value)

    async def set_acceleration_factor(self, value: float) -> None:
        async with self._command("set_acceleration_factor", value=to_jsonable(value)):
            self._moves().set_acceleration_factor(value)

    async def get_velocity_factor(self) -> float:
        async with self._command("get_velocity_factor") as out:
            out["result"] = factor = self._moves().velocity_factor
            return factor

    async def get_acceleration_factor(self) -> float:
        async with self._command("get_acceleration_factor") as out:
            out["result"] = factor = self._moves().acceleration_factor
            return factor

    # ------------------------------------------------------------- gripper
    # The gripper records its commands itself (``cell.gripper.open()`` is one too), refused by
    # its own check of the flange's power; these check the table's guard before it runs.

    async def gripper_activate(self) -> None:
        self._check_guard("gripper_activate")
        await self.gripper.activate()

    async def gripper_open(self, *, speed: float | None = None) -> GripResult:
        self._check_guard("gripper_open")
        result = await self.gripper.open(speed=speed)
        if not result.holding and self.held is not None:
            await self._hold(None)
        return result

    async def gripper_close(
        self,
        *,
        speed: float | None = None,
        grip_force: float | None = None,
        expect_object: bool = False,
    ) -> GripResult:
        self._check_guard("gripper_close")
        return await self.gripper.close(speed=speed, force=grip_force, expect_object=expect_object)

    async def gripper_move(
        self,
        width: float,
        *,
        speed: float | None = None,
        grip_force: float | None = None,
        expect_object: bool = False,
    ) -> GripResult:
        self._check_guard("gripper_move")
        result = await self.gripper.move(
            width, speed=speed, force=grip_force, expect_object=expect_object
        )
        if not result.holding and self.held is not None:
            await self._hold(None)
        return result

    async def get_gripper_width(self) -> float:
        async with self._command("get_gripper_width") as outcome:
            outcome["result"] = await self.gripper.get_width()
            return float(outcome["result"])

    # ------------------------------------------------------------- tool and payload

    async def _send_tool(self) -> None:
        """Set the TCP and the payload (gripper plus what it holds) on the controller, so
        that its ``actual_TCP_pose`` is the TCP fxcell plans for."""
        tool = self.config.tool
        held = self.config.layout.objects.get(self.held) if self.held else None
        mass = tool.payload + (held.mass if held is not None else 0.0)
        async with self._command("set_tool", tcp=list(tool.tcp), payload=mass):
            await self._link().set_tool(
                tuple(tool.tcp), mass, tool.payload_cog, within=self.command_timeout
            )

    async def declare_held(self, kind: str | None = None) -> None:
        async with self._command("declare_held", kind=kind):
            if kind is not None and kind not in self.config.layout.objects:
                known = ", ".join(sorted(self.config.layout.objects))
                raise InvalidArgumentError(f"no object kind {kind!r} (known: {known})")
            await self._hold(kind)

    async def _hold(self, kind: str | None) -> None:
        """The gripper now holds an object of ``kind`` (None: nothing): collision checking
        carries it and the controller's payload includes it."""
        if kind == self.held:
            return
        self.held = kind
        checker = self._moves().planner.checker
        if kind is None:
            checker.detach()
        else:
            checker.attach(kind)
        self.bus.publish(DeviceEvent(time.time(), "gripper", {"event": "held", "held": kind}))
        if self.link is not None and self.link.control_ready:
            await self._send_tool()

    # ------------------------------------------------------------- IO

    async def get_io(self) -> dict[str, Any]:
        async with self._command("get_io") as out:
            out["result"] = values = self.io.snapshot()
            return values

    async def io_set(self, signal: str, value: bool | float) -> None:
        await self.io.set(signal, value)

    async def io_wait_for(
        self,
        signal: str,
        value: bool | float = True,
        timeout: float = 60.0,  # noqa: ASYNC109
    ) -> float:
        return await self.io.wait_for(signal, value, timeout)

    # ------------------------------------------------------------- teach-in

    async def freedrive_start(self) -> None:
        async with self._command("freedrive_start"):
            await self._require_remote()
            await self._link().teach_mode(True, within=self.command_timeout)
            self._freedrive = True
            self._observe(self.robot_state, "freedrive")
            await self.wait_for_state(CellState.FREEDRIVE)

    async def freedrive_stop(self) -> None:
        async with self._command("freedrive_stop"):
            if not self._freedrive:
                return
            try:
                await self._link().teach_mode(False, within=self.command_timeout)
            finally:
                self._freedrive = False
                self._observe(self.robot_state, "freedrive ended")
            await self.wait_for_state(*[st for st in CellState if st is not CellState.FREEDRIVE])

    async def teach(self, name: str) -> dict[str, Any]:
        async with self._command("teach", name=name) as out:
            q = self._sample().actual_q
            pose = self._moves().planner.tcp_pose(q).as_ur()
            self.taught.teach_position(name, q, pose)
            out["result"] = entry = {"joints": list(q), "pose": list(pose)}
            return entry

    async def get_positions(self) -> dict[str, Any]:
        async with self._command("get_positions") as out:
            out["result"] = positions = {
                name: {k: entry[k] for k in ("joints", "pose", "taught")}
                for name, entry in sorted(self.taught.positions.items())
            }
            return positions

    async def move_to(
        self,
        name: str,
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
        *,
        queue: bool = False,
    ) -> MoveResult:
        args = {"name": name, "velocity_factor": velocity_factor,
                "acceleration_factor": acceleration_factor}  # fmt: skip
        return await self._move("move_to", args, queue=queue)

    # ------------------------------------------------------------- layout, pick and place

    async def get_layout(self) -> dict[str, Any]:
        async with self._command("get_layout") as out:
            out["result"] = data = layout_data(self.layout)
            return data

    async def teach_frame_point(self, station: str, point: str) -> dict[str, Any]:
        async with self._command("teach_frame_point", station=station, point=point) as out:
            st = self.layout.station(station)
            if self._moving():
                raise MoveInProgressError("teach_frame_point(): a move is running")
            position = self._moves().planner.tcp_pose(self._sample().actual_q).position.tolist()
            current = st.config.frame.model_dump()
            frame = self.taught.teach_frame_point(station, point, position, current)
            self._use_layout(self.taught.apply_frames(self.config.layout))
            out["result"] = frame
            return frame

    def _use_layout(self, layout: LayoutConfig) -> None:
        """Plan around a changed layout from now on (a re-taught station frame)."""
        self.config = self.config.model_copy(update={"layout": layout})
        self.layout = Layout(layout)
        old = self._motion
        if old is not None:
            self._motion = None
            fresh = self._moves()
            fresh.set_velocity_factor(old.velocity_factor)
            fresh.set_acceleration_factor(old.acceleration_factor)
            if self.calibration is not None:
                fresh.planner.use_calibration(self.calibration)
            elif old.planner.uncalibrated is not None:
                fresh.planner.use_calibration(None, old.planner.uncalibrated)
            if self.held is not None:
                fresh.planner.checker.attach(self.held)

    async def pick(
        self,
        station: str,
        slot: str,
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
    ) -> GripResult:
        return await self._at_slot(
            handling.pick, station, slot, velocity_factor, acceleration_factor
        )

    async def place(
        self,
        station: str,
        slot: str,
        velocity_factor: float | None = None,
        acceleration_factor: float | None = None,
    ) -> GripResult:
        return await self._at_slot(
            handling.place, station, slot, velocity_factor, acceleration_factor
        )

    async def _at_slot(
        self,
        action: Callable[
            [Cell, CellContext, str, str, float | None, float | None], Awaitable[GripResult]
        ],
        station: str,
        slot: str,
        velocity_factor: float | None,
        acceleration_factor: float | None,
    ) -> GripResult:
        """Run ``handling.pick`` or ``handling.place`` as the recorded command of its name."""
        name = action.__name__

        async def admitted() -> None:
            await self._move_landed()
            self._check_guard(name)

        async with self._command(name, station=station, slot=slot) as out:
            # a link that dropped just before is waited for, as within the steps
            await healing.resilient(self, f"start {name}", admitted)
            out["result"] = result = await action(
                self, self._context, station, slot, velocity_factor, acceleration_factor
            )
            return result

    async def check_placement(self, expected: str = "") -> dict[str, Any]:
        async with self._command("check_placement", expected=expected) as out:
            text = expected.strip()
            slots: set[str] | None
            if not text:
                slots = None
            elif text == "-":
                slots = set()
            else:
                slots = {s.strip().upper() for s in text.split(",") if s.strip()}
            report = await self.camera.check(slots)
            out["result"] = result = report.as_dict()
            return result

    async def inspect_placement(self, expected: Collection[str]) -> PlacementReport | None:
        """The job's check before it starts the machine: ``expected`` must hold seated
        crucibles, the other positions be empty (recorded as ``check_placement``). ``None``
        when no camera is configured or ``vision.check_before_start`` is off."""
        if not (self.camera.configured and self.config.vision.check_before_start):
            return None
        await self.check_placement(",".join(sorted(expected)) or "-")
        return self.camera.last

    async def get_max_acceleration(self) -> tuple[float, ...]:
        async with self._command("get_max_acceleration") as out:
            out["result"] = limits = self._moves().max_acceleration
            return limits


def _at_rest(sample: RobotState) -> bool:
    return max(map(abs, sample.actual_qd)) < REST_VELOCITY


def _running_states() -> set[CellState]:
    return {s for s in CellState if s.is_running}


def _start_recorder(directory: Path, cell: Cell) -> Any:
    from fxcell.recorder import Recorder, Retention
    from fxcell.recorder.recorder import TF_RATE

    rec = cell.config.recorder
    describe = cell.kind.description
    arm = describe(Pose.from_ur(cell.config.tool.tcp)) if describe is not None else None
    recorder = Recorder(
        directory,
        chunk_duration=rec.chunk_duration,
        rotate_size=rec.rotate_size,
        rotate_duration=rec.rotate_duration,
        metadata={
            "host": str(cell.host) if cell.host is not None else "embedded simulator",
            "external_control": cell.external_control,
            "config": cell.config.model_dump(mode="json"),
        },
        arm=arm,
        tf_rate=TF_RATE if arm is not None else 0.0,  # no description: no frames, no URDF
        retention=Retention(rec.max_total_size, rec.max_age),
    )
    recorder.attach(cell.bus)
    return recorder
