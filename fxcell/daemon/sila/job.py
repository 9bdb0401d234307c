"""The job over SiLA: JobController (Run Job and its control) and ErrorRecoveryService.

``RunJob`` starts a run on the daemon's job (the same :class:`~fxcell.job.Job` the page and
the HTTP API drive) and follows it, woken by the job's events on the cell's event bus, until
the run is done. Each change of step or state is an intermediate response; progress and the
estimated remaining time are the job's own (measured step times).

When the run stops where a person must say what is true (a step that moved an object was
interrupted: is the crucible of S3 still in the rack or already in the machine?) or faults,
the execution posts a *recoverable error* (ErrorRecoveryService) whose continuation options
are the job's answers; executing one answers the question and resumes the run, and Run Job
goes on. Aborting the error handling (or its timeout) ends Run Job with ``RunInterrupted``;
the run itself stays paused and resumable from the page, the CLI or a new client.
"""

from __future__ import annotations

import asyncio
import datetime
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

from sila2.framework import DefinedExecutionError, Feature
from sila2.server import (
    FeatureImplementationBase,
    MetadataDict,
    ObservableCommandInstanceWithIntermediateResponses,
)

from fxcell import errors
from fxcell.daemon.sila.access import SilaCommands, lock_identifier
from fxcell.daemon.sila.bridge import ErrorMap, LoopBridge, PropertyQueue
from fxcell.errors import FxcellError
from fxcell.events import COMMAND_ORIGIN, DeviceEvent, Event

if TYPE_CHECKING:
    from queue import Queue

    from sila2.server import SilaServer

    from fxcell.daemon.service import CellService

RUN_JOB = "org.fxcell/robot/JobController/v1/Command/RunJob"
RESUME = "resume"
"""The continuation option of a faulted run: resume once the cause is fixed."""

JOB_ERRORS: dict[type[FxcellError], str] = {
    errors.JobSpecError: "InvalidRun",
    errors.ControlHeldError: "ControlHeld",
}


class RunJob_Responses(NamedTuple):
    RunIdentifier: int
    StepsDone: int


class RunJob_IntermediateResponses(NamedTuple):
    Step: str
    StepsDone: int
    StepsTotal: int
    JobState: str


@dataclass(slots=True)
class _Pending:
    """A recoverable error of one Run Job execution."""

    execution: str
    key: tuple[str, ...]  # what it asks (so a repeated status does not re-post it)
    error: dict[str, Any]
    options: dict[str, dict[str, str]]  # identifier -> answers for job.resume
    wake: asyncio.Event
    posted: float = field(default_factory=time.monotonic)
    aborted: bool = False


class Recovery:
    """The recoverable errors of running Run Job executions (state on the loop)."""

    def __init__(self) -> None:
        self.pending: dict[str, _Pending] = {}
        self.timeout: float = 0.0  # s; 0: wait without limit
        self.errors = PropertyQueue([])

    def _publish(self) -> None:
        self.errors.offer([p.error for p in self.pending.values()])

    def post(self, execution: str, status: dict[str, Any], wake: asyncio.Event) -> _Pending:
        questions = status.get("questions") or []
        if questions:
            key = tuple(q["id"] for q in questions)
        else:
            key = ("fault", str(status.get("message") or ""))
        current = self.pending.get(execution)
        if current is not None and current.key == key:
            return current
        options: dict[str, dict[str, str]] = {}
        described: list[dict[str, str]] = []
        if questions:
            # One question at a time (the interrupted step's object): its choices.
            question = questions[0]
            for choice in question["choices"]:
                options[choice] = {question["id"]: choice}
                described.append(
                    {
                        "Identifier": choice,
                        "Description": (
                            f"The {question['object']} of sample {question['sample']} is at "
                            f"{choice}: record it there and resume the run."
                        ),
                        "RequiredInputData": "",
                    }
                )
            identifier, message = "ObjectLocationUnknown", question["text"]
        else:
            options[RESUME] = {}
            described.append(
                {
                    "Identifier": RESUME,
                    "Description": "The cause is fixed (see the message): resume the run.",
                    "RequiredInputData": "",
                }
            )
            identifier = "JobFault"
            message = f"the run faulted: {status.get('message') or 'see the operator page'}"
        error = {
            "ErrorIdentifier": identifier,
            "CommandIdentifier": RUN_JOB,
            "CommandExecutionUUID": execution,
            "ErrorTime": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "ErrorMessage": message,
            "ContinuationOptions": described,
            "DefaultOption": "",  # where an object is, only a person can say
            "AutomaticSelectionTimeout": 0,
        }
        pending = _Pending(execution, key, error, options, wake)
        self.pending[execution] = pending
        self._publish()
        return pending

    def clear(self, execution: str) -> None:
        if self.pending.pop(execution, None) is not None:
            self._publish()

    def find(self, execution: str) -> _Pending | None:
        return self.pending.get(execution)


class JobController(FeatureImplementationBase):
    """``org.fxcell/robot/JobController/v1``."""

    def __init__(
        self,
        parent_server: SilaServer,
        feature: Feature,
        bridge: LoopBridge,
        commands: SilaCommands,
        service: CellService,
        recovery: Recovery,
    ) -> None:
        super().__init__(parent_server=parent_server)
        self.bridge = bridge
        self.commands = commands
        self.service = service
        self.recovery = recovery
        self.errors = ErrorMap(feature, JOB_ERRORS, "JobRefused")
        self.job_state = PropertyQueue("unavailable")
        self.locations = PropertyQueue([])
        self._JobState_producer_queue: Queue[object] = self.job_state.queue
        self._SampleLocations_producer_queue: Queue[object] = self.locations.queue
        self._following: set[asyncio.Event] = set()
        self._closing = False

    def close(self) -> None:
        """End every Run Job execution (the daemon is stopping; runs stay resumable)."""
        self._closing = True
        for wake in self._following:
            wake.set()

    def refresh(self) -> None:
        """Offer the observable properties' current values (on the loop)."""
        status = self.service.jobs.status()
        self.job_state.offer(status["state"])
        self.locations.offer(
            [
                {
                    "SampleId": s["id"],
                    "Crucible": s.get("crucible") or "",
                    "Bead": s.get("bead") or "",
                }
                for s in status.get("samples") or []
            ]
        )

    def JobState_on_subscription(self, *, metadata: MetadataDict) -> None:
        return None

    def SampleLocations_on_subscription(self, *, metadata: MetadataDict) -> None:
        return None

    # ------------------------------------------------------------- commands

    def _call(self, make: Any) -> Any:
        try:
            return self.bridge.run(make)
        except FxcellError as exc:
            raise self.errors.translate(exc) from None

    def _job_command(self, name: str, metadata: MetadataDict) -> None:
        identifier = lock_identifier(metadata)

        async def run() -> None:
            lease, took, client = await self.commands.with_control(identifier)
            token = COMMAND_ORIGIN.set(client)
            try:
                await self.service.jobs.command(name, {})
            finally:
                COMMAND_ORIGIN.reset(token)
                if took:
                    self.service.control.release(lease)

        self._call(run)

    def Pause(self, *, metadata: MetadataDict) -> None:
        self._job_command("pause", metadata)

    def Resume(self, *, metadata: MetadataDict) -> None:
        self._job_command("resume", metadata)

    def Abort(self, *, metadata: MetadataDict) -> None:
        self._job_command("abort", metadata)

    def RunJob(
        self,
        RunName: str,
        Samples: list[Any],
        *,
        metadata: MetadataDict,
        instance: ObservableCommandInstanceWithIntermediateResponses[Any],
    ) -> RunJob_Responses:
        run = {
            "name": RunName or "SiLA run",
            "samples": [
                {
                    "id": s.SampleId,
                    "rack": s.RackSlot,
                    "machine": s.MachineSlot,
                    "tray": s.TraySlot,
                }
                for s in Samples
            ],
        }
        identifier = lock_identifier(metadata)
        execution = str(instance.execution_uuid)
        try:
            result: RunJob_Responses = self._call(
                lambda: self._follow(run, identifier, execution, instance)
            )
        finally:
            self.bridge.call_soon(lambda: self.recovery.clear(execution))
        return result

    async def _follow(
        self,
        run: dict[str, Any],
        identifier: object,
        execution: str,
        instance: ObservableCommandInstanceWithIntermediateResponses[Any],
    ) -> RunJob_Responses:
        job = await self.service.jobs.require()
        cell = self.service.require_cell()
        wake = asyncio.Event()

        def on_event(event: Event) -> None:
            if isinstance(event, DeviceEvent) and event.device == "job":
                wake.set()

        unsubscribe = cell.bus.subscribe(on_event)
        self._following.add(wake)
        try:
            lease, took, client = await self.commands.with_control(identifier)
            token = COMMAND_ORIGIN.set(client)
            try:
                run_id = await job.start(run)
            finally:
                COMMAND_ORIGIN.reset(token)
                if took:
                    self.service.control.release(lease)
            return await self._watch(job, run_id, execution, instance, wake)
        finally:
            self._following.discard(wake)
            unsubscribe()

    async def _watch(
        self,
        job: Any,
        run_id: int,
        execution: str,
        instance: ObservableCommandInstanceWithIntermediateResponses[Any],
        wake: asyncio.Event,
    ) -> RunJob_Responses:
        reported: tuple[Any, ...] | None = None
        while True:
            wake.clear()
            if self._closing:
                raise self._interrupted(run_id, "the daemon is stopping")
            status = job.status()
            if status.get("run") != run_id or self.service.jobs.job is not job:
                raise self._interrupted(run_id, "it was discarded or the job was closed")
            state = status["state"]
            progress = status.get("progress") or {}
            done, total = int(progress.get("done") or 0), int(progress.get("total") or 0)
            step = str(status.get("step") or "")
            now = (step, done, total, state)
            if now != reported:
                reported = now
                if total:
                    instance.progress = min(1.0, done / total)  # type: ignore[misc]
                eta = progress.get("eta")
                if eta is not None:
                    instance.estimated_remaining_time = datetime.timedelta(seconds=float(eta))
                instance.send_intermediate_response(
                    RunJob_IntermediateResponses(step, done, total, state)
                )
            if state == "done":
                return RunJob_Responses(run_id, done)
            timeout: float | None = None
            if state == "fault" or (state == "paused" and status.get("questions")):
                pending = self.recovery.post(execution, status, wake)
                if pending.aborted:
                    raise self._interrupted(run_id, "its error handling was aborted")
                if self.recovery.timeout > 0:
                    timeout = pending.posted + self.recovery.timeout - time.monotonic()
                    if timeout <= 0:
                        raise self._interrupted(
                            run_id, f"no continuation option within {self.recovery.timeout:.0f} s"
                        )
            else:
                self.recovery.clear(execution)
            try:
                async with asyncio.timeout(timeout):
                    await wake.wait()
            except TimeoutError:
                continue  # the deadline is checked above

    def _interrupted(self, run_id: int, why: str) -> DefinedExecutionError:
        return self.errors.error(
            "RunInterrupted",
            f"run {run_id} did not end: {why}. Every object's location stays recorded; a "
            "paused run resumes from the operator page or with 'fxcell job resume'.",
        )


class ErrorRecoveryService(FeatureImplementationBase):
    """``org.silastandard/core/ErrorRecoveryService/v1`` for Run Job executions."""

    def __init__(
        self,
        parent_server: SilaServer,
        feature: Feature,
        bridge: LoopBridge,
        commands: SilaCommands,
        service: CellService,
        recovery: Recovery,
    ) -> None:
        super().__init__(parent_server=parent_server)
        self.feature = feature
        self.bridge = bridge
        self.commands = commands
        self.service = service
        self.recovery = recovery
        self._RecoverableErrors_producer_queue: Queue[object] = recovery.errors.queue

    def RecoverableErrors_on_subscription(self, *, metadata: MetadataDict) -> None:
        return None

    def _error(self, identifier: str, message: str) -> DefinedExecutionError:
        return DefinedExecutionError(self.feature.defined_execution_errors[identifier], message)

    def _pending(self, execution: str) -> _Pending:
        pending = self.recovery.find(execution)
        if pending is None:
            raise self._error(
                "InvalidCommandExecutionUUID",
                f"no unhandled recoverable error of execution {execution!r}",
            )
        return pending

    def ExecuteContinuationOption(
        self,
        CommandExecutionUUID: str,
        ContinuationOption: str,
        InputData: str,
        *,
        metadata: MetadataDict,
    ) -> None:
        identifier = lock_identifier(metadata)

        async def execute() -> None:
            pending = self._pending(CommandExecutionUUID)
            answers = pending.options.get(ContinuationOption)
            if answers is None:
                raise self._error(
                    "UnknownContinuationOption",
                    f"{ContinuationOption!r} is not one of {', '.join(pending.options)}",
                )
            job = await self.service.jobs.require()
            lease, took, client = await self.commands.with_control(identifier)
            token = COMMAND_ORIGIN.set(client)
            try:
                await job.resume(answers)
            finally:
                COMMAND_ORIGIN.reset(token)
                if took:
                    self.service.control.release(lease)
            self.recovery.clear(CommandExecutionUUID)
            pending.wake.set()

        try:
            self.bridge.run(execute)
        except FxcellError as exc:
            # Not a defined error of this command: the message keeps the cell's typed name.
            raise RuntimeError(f"{type(exc).__name__}: {exc}") from None

    def AbortErrorHandling(self, CommandExecutionUUID: str, *, metadata: MetadataDict) -> None:
        async def abort() -> None:
            pending = self._pending(CommandExecutionUUID)
            pending.aborted = True
            pending.wake.set()

        self.bridge.run(abort)

    def SetErrorHandlingTimeout(self, ErrorHandlingTimeout: int, *, metadata: MetadataDict) -> None:
        async def set_timeout() -> None:
            self.recovery.timeout = float(max(0, ErrorHandlingTimeout))
            for pending in self.recovery.pending.values():
                pending.wake.set()

        self.bridge.run(set_timeout)
