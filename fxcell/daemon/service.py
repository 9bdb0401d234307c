"""What the daemon's API serves: the Cell (when up), control, operations and the stream.

:class:`CellService` is the seam between the HTTP layer and the Cell: the HTTP app
only talks to it, and the supervisor (:mod:`fxcell.daemon.server`) plugs in a new
Cell whenever it (re)connects. It keeps its own event bus subscription so that the
state snapshot and the stream survive a Cell restart.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Awaitable, Callable, Mapping
from typing import Any

from fxcell._version import __version__
from fxcell.cell.statemachine import CellState, Statechart, load_statechart
from fxcell.commands import COMMANDS, get_command
from fxcell.config import CellConfig
from fxcell.daemon.auth import check_bearer
from fxcell.daemon.control import ControlLock, Holder
from fxcell.daemon.encoding import jsonable
from fxcell.daemon.jobs import JobService
from fxcell.daemon.operations import Operation, OperationRegistry
from fxcell.daemon.stream import StreamHub
from fxcell.errors import ConnectionLostError, MoveInProgressError, UnsupportedCommandError
from fxcell.events import COMMAND_ORIGIN, Event, EventBus, StateEvent, TransitionEvent
from fxcell.geometry import Pose
from fxcell.protocol import RobotState
from fxcell.robots import robot_kind


class CellService:
    """The daemon's view of the cell, shared by every request and watcher."""

    def __init__(
        self,
        config: CellConfig,
        token: str,
        *,
        control_lease: float = 30.0,
        statechart: Statechart | None = None,
    ) -> None:
        self.config = config
        self._token = token
        self.cell: Any = None
        self.bus: EventBus | None = None
        self._unsubscribe: Callable[[], None] | None = None
        self.latest: RobotState | None = None
        self._state: str = CellState.DISCONNECTED.value
        self.robot_description = config.robot.host or "embedded simulator"
        self.cell_error: str | None = None
        self._attached = asyncio.Event()
        self.started = time.time()
        self.statechart = statechart or load_statechart()
        self._allowed_in: dict[str, list[str]] = {}
        self.hub = StreamHub(self.machine_state)
        self.operations = OperationRegistry(on_change=self._operation_changed)
        self.control = ControlLock(
            control_lease, keeps_alive=self._keeps_alive, on_change=self._control_changed
        )
        self.jobs = JobService(config)
        """The fusion-machine job on the attached Cell (the supervisor attaches it)."""
        self.lease_keepers: list[Callable[[Holder], bool]] = []
        """More reasons a control lease stays alive (the SiLA server's lock)."""

    # ------------------------------------------------------------- the cell

    def attach(self, cell: Any) -> None:
        """Serve ``cell`` (its event bus feeds the snapshot and the stream)."""
        self.detach()
        self.cell = cell
        self.cell_error = None
        self.bus = cell.bus
        self._unsubscribe = cell.bus.subscribe(self._on_event)
        self._state = str(cell.state)
        self._attached.set()

    def detach(self, reason: str | None = None) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
        self._unsubscribe = None
        self.cell = None
        self.bus = None
        self.latest = None
        self._attached.clear()
        self._state = CellState.DISCONNECTED.value
        if reason:
            self.cell_error = reason

    async def wait_cell(self) -> Any:
        """The cell, waiting up to ``robot.command_timeout`` while the daemon is still
        connecting it for the first time (so a command sent right after start does not
        fail); once connecting has failed, at once."""
        if self.cell is None and self.cell_error is None:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.config.robot.command_timeout):
                    await self._attached.wait()
        return self.require_cell()

    def require_cell(self) -> Any:
        if self.cell is None:
            why = f": {self.cell_error}" if self.cell_error else ""
            raise ConnectionLostError(f"the cell is not connected{why}")
        return self.cell

    def _on_event(self, event: Event) -> None:
        if isinstance(event, StateEvent):
            self.latest = event.sample
        elif isinstance(event, TransitionEvent):
            self._state = event.dest
        self.hub.on_event(event)

    def machine_state(self) -> str:
        return self._state

    # ------------------------------------------------------------- commands

    def authorized(self, header: str | None) -> bool:
        return check_bearer(header, self._token)

    def start_operation(
        self,
        name: str,
        args: Mapping[str, Any],
        client: str,
        call: Callable[[], Awaitable[Any]],
        *,
        lease: str | None = None,
    ) -> Operation:
        """Run ``call`` as an operation (control, if needed, was taken by the caller).

        Its commands are recorded as sent by ``client`` (the operation's task keeps the
        context it was created in)."""
        self.require_cell()
        token = COMMAND_ORIGIN.set(client)
        try:
            return self.operations.start(
                name, args, client, call(), move=get_command(name).kind == "move", lease=lease
            )
        finally:
            COMMAND_ORIGIN.reset(token)

    async def check(self, command: str, args: Mapping[str, Any], client: str) -> None:
        """Raise what ``command`` would be refused with before it starts (the Cell's
        :meth:`~fxcell.cell.Cell.check_command`; a refusal is recorded as ``client``'s)."""
        cell = await self.wait_cell()
        token = COMMAND_ORIGIN.set(client)
        try:
            if (
                get_command(command).kind == "move"
                and not args.get("queue")
                and any(op.move for op in self.operations.running())
            ):  # one that has not reached the Cell yet counts too
                raise MoveInProgressError(f"{command}(): another move is running")
            await cell.check_command(command, **args)
        finally:
            COMMAND_ORIGIN.reset(token)

    async def call(self, command: str, /, **kwargs: Any) -> Any:
        cell = await self.wait_cell()
        return await cell.run_command(command, **kwargs)

    async def query(self, name: str) -> Any:
        cell = await self.wait_cell()
        return await cell.run_command(name)

    async def cancel_operation(self, op: Operation) -> None:
        await self.operations.cancel(op)

    def allowed_commands(self, state: str | None = None) -> list[str]:
        """Commands the statechart admits in ``state`` (default: the current one)."""
        state = state or self._state
        cached = self._allowed_in.get(state)
        if cached is None:
            cached = [c for c in self.statechart.commands if state in self._allowed_states(c)]
            self._allowed_in[state] = cached
        return cached

    def _allowed_states(self, command: str) -> list[str]:
        """States admitting ``command``: a statechart guard or a command of the table
        (none for a command the robot kind cannot do)."""
        if not robot_kind(self.config.robot.kind).capabilities.supports(command):
            return []
        entry = COMMANDS.get(command)
        guard = entry.guard if entry is not None else command
        if guard is None:
            return [s.value for s in CellState]
        return [s.value for s in self.statechart.allowed(guard)]

    # ------------------------------------------------------------- views

    def snapshot(self) -> dict[str, Any]:
        sample = self.latest
        robot: dict[str, Any] | None = None
        if sample is not None:
            robot = {
                "t": sample.timestamp,
                "robot_mode": sample.robot_mode.name,
                "safety_mode": sample.safety_mode.name,
                "runtime_state": sample.runtime_state.name,
                "q": list(sample.actual_q),
                "qd": list(sample.actual_qd),
                "tcp": list(sample.actual_tcp_pose),
                "speed_scaling": sample.speed_scaling,
            }
        return {
            "state": self._state,
            "kind": self.config.robot.kind,
            "connected": self.cell is not None,
            "cell_error": self.cell_error,
            "remote_control": (None if self.cell is None else not self.cell.local_control),
            "calibration": None if self.cell is None else self.cell.calibration_status,
            "robot": robot,
            "gripper": None
            if self.cell is None
            else {**self.cell.gripper.last, "held": self.cell.held},
            "allowed": list(self.allowed_commands()),
            "control": self.control.describe(),
            "operations": [op.describe() for op in self.operations.running()],
            "watchers": self.hub.watchers,
            "time": time.time(),
        }

    def info(self) -> dict[str, Any]:
        cfg = self.config
        return {
            "version": __version__,
            "kind": cfg.robot.kind,
            "robot": self.robot_description,
            "simulated": cfg.robot.host is None,
            "started": self.started,
            "home": list(cfg.home),
            "tcp": list(cfg.tool.tcp),
            "limits": jsonable(cfg.limits),
            "scene": jsonable(cfg.scene.objects),
            "io": dict(cfg.io.signals),
            "recorder": jsonable(cfg.recorder),
        }

    def arm_model(self) -> dict[str, object]:
        """The configured robot's arm as the page draws it (its kind's description: the
        joints from the base to the tool frame, each an origin and an axis);
        UnsupportedCommandError for a kind without one."""
        describe = robot_kind(self.config.robot.kind).description
        if describe is None:
            raise UnsupportedCommandError("robot_model", self.config.robot.kind)
        return describe(Pose.from_ur(self.config.tool.tcp)).chain_json()

    def commands_data(self) -> dict[str, Any]:
        """The command table as data (for clients and the operator page)."""
        return {
            name: {
                "kind": c.kind,
                "summary": c.summary,
                "doc": c.doc,
                "args": [
                    {
                        "name": a.name,
                        "type": a.type.name,
                        "unit": a.type.unit,
                        "length": list(a.type.length) if a.type.length else None,
                        "required": a.required,
                        "default": jsonable(a.default),
                        "keyword_only": a.keyword_only,
                        "doc": a.doc,
                    }
                    for a in c.args
                ],
                "result": c.result.annotation,
                "guard": c.guard,
                "allowed": self._allowed_states(name),
                "supported": robot_kind(self.config.robot.kind).capabilities.supports(name),
                "requires": sorted(c.requires),
                "changes_robot": c.changes_robot,
                "needs_control": c.needs_control,
            }
            for name, c in COMMANDS.items()
        }

    def statechart_data(self) -> dict[str, Any]:
        chart = self.statechart
        return {
            "name": chart.name,
            "title": chart.title,
            "initial": chart.initial,
            "states": chart.states,
            "transitions": chart.transitions,
            "commands": {c: self._allowed_states(c) for c in chart.commands},
            "current": self._state,
        }

    # ------------------------------------------------------------- notifications

    def _keeps_alive(self, holder: Holder) -> bool:
        return (
            self.hub.watches(holder.lease)
            or bool(self.operations.running(holder.lease))
            or any(keeps(holder) for keeps in self.lease_keepers)
        )

    def _operation_changed(self, op: Operation) -> None:
        if self.hub.watchers:  # no description (nor its JSON) when nobody watches
            self.hub.broadcast({"type": "operation", **op.describe()})

    def _control_changed(self, holder: Holder | None) -> None:
        self.hub.broadcast({"type": "control", "holder": self.control.describe()})
