"""The fusion-machine job in the daemon: one :class:`~fxcell.job.Job` on the daemon's Cell.

The job is created when the Cell is attached and recovers at once whatever run a previous
daemon left unfinished (it then waits, paused, for the operator's ``resume``, with questions
where a sample's place is ambiguous). Its events go onto the Cell's event bus as
``DeviceEvent("job", ...)``: the recorder writes them to ``/job`` and the stream sends them to
the page. HTTP: ``GET /api/job`` and ``POST /api/job/{start,pause,resume,abort,confirm,discard}``
(token and control of the cell, like commands).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Collection, Mapping
from typing import TYPE_CHECKING, Any

from fxcell.errors import ConnectionLostError, FxcellError, InvalidArgumentError
from fxcell.events import DeviceEvent
from fxcell.job import Job, JobStore
from fxcell.layout import Layout

if TYPE_CHECKING:
    from fxcell.cell import Cell
    from fxcell.cell.gripper import Gripper
    from fxcell.config import CellConfig
    from fxcell.protocol import RobotState
    from fxcell.vision.placement import PlacementReport

log = logging.getLogger(__name__)


class _CellIO:
    """The Cell's IO as the job uses it (digital signals by configured name)."""

    def __init__(self, cell: Cell) -> None:
        self._cell = cell

    async def set(self, signal: str, value: bool) -> None:
        await self._cell.io_set(signal, value)

    def get(self, signal: str) -> bool:
        return bool(self._cell.io.get(signal))

    async def wait_for(self, signal: str, value: bool, timeout: float) -> None:  # noqa: ASYNC109
        await self._cell.io_wait_for(signal, value, timeout)


class CellForJob:
    """A :class:`~fxcell.cell.Cell` as the job's ``JobCell``."""

    def __init__(self, cell: Cell) -> None:
        self._cell = cell
        self._io = _CellIO(cell)

    @property
    def layout(self) -> Layout:
        return self._cell.layout

    @property
    def io(self) -> _CellIO:
        return self._io

    @property
    def gripper(self) -> Gripper:
        return self._cell.gripper

    @property
    def held(self) -> str | None:
        return self._cell.held

    @property
    def robot_state(self) -> RobotState | None:
        return self._cell.robot_state

    async def declare_held(self, kind: str | None = None) -> None:
        await self._cell.declare_held(kind)

    async def restore_control(self) -> None:
        await self._cell.restore_control()

    async def pick(self, station: str, slot: str) -> None:
        await self._cell.pick(station, slot)

    async def place(self, station: str, slot: str) -> None:
        await self._cell.place(station, slot)

    async def go_home(self) -> None:
        await self._cell.go_home()

    async def inspect_placement(self, expected: Collection[str]) -> PlacementReport | None:
        return await self._cell.inspect_placement(expected)


class JobService:
    """The daemon's job: created on the attached Cell, recovered from its database."""

    def __init__(self, config: CellConfig) -> None:
        self.config = config
        self.job: Job | None = None
        self.error: str | None = None
        self._ready = asyncio.Event()
        self._cell: Cell | None = None

    async def attach(self, cell: Cell) -> None:
        """Create the job on ``cell`` and recover an unfinished run, if any."""
        await self.detach()
        self._cell = cell

        def publish(event: Mapping[str, Any]) -> None:
            cell.bus.publish(DeviceEvent(time.time(), "job", dict(event)))

        try:
            store = await asyncio.to_thread(JobStore, self.config.job.database)
            job = Job(CellForJob(cell), store, self.config.job, on_event=publish)
            recovered = await job.recover()
        except FxcellError as exc:
            self.error = str(exc)
            log.error("job: %s", exc)
            return
        self.job = job
        self.error = None
        self._ready.set()
        if recovered.get("run") is not None:
            log.warning("job: run %s was interrupted; it waits for resume", recovered.get("run"))

    async def detach(self) -> None:
        """Stop the job's work (the cell brakes a running step); the run stays resumable."""
        job, self.job = self.job, None
        self._ready.clear()
        if job is not None:
            with contextlib.suppress(Exception):
                await job.close()

    async def require(self) -> Job:
        if self.job is None:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.config.robot.command_timeout):
                    await self._ready.wait()
        if self.job is None:
            why = f": {self.error}" if self.error else ": the cell is not connected"
            raise ConnectionLostError(f"the job is not available{why}")
        return self.job

    def status(self) -> dict[str, Any]:
        if self.job is None:
            return {"state": "unavailable", "message": self.error or "the cell is not connected"}
        return self.job.status()

    async def command(self, name: str, body: Mapping[str, Any]) -> dict[str, Any]:
        """Run job command ``name`` with its JSON body; the job's status afterwards."""
        job = await self.require()
        if name == "start":
            run = body.get("run")
            if not isinstance(run, Mapping):
                raise InvalidArgumentError("start needs {'run': {...}}: the run as JSON")
            await job.start(run)
        elif name == "resume":
            answers = body.get("answers") or {}
            if not isinstance(answers, Mapping) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in answers.items()
            ):
                raise InvalidArgumentError("answers: a mapping of question id to a place")
            await job.resume(answers)
        elif name == "confirm":
            prompt = body.get("prompt")
            await job.confirm(prompt if isinstance(prompt, str) else None)
        elif name in ("pause", "abort", "discard"):
            await getattr(job, name)()
        else:
            raise InvalidArgumentError(f"unknown job command {name!r}")
        return job.status()


JOB_COMMANDS = ("start", "pause", "resume", "abort", "confirm", "discard")
