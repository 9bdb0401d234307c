"""Operations: commands the daemon runs as tasks that can be listed, awaited and cancelled.

Every command that changes the robot becomes an :class:`Operation` with an id. Long
moves answer at once with the operation; a client then waits on it, lists it or
cancels it — cancelling a move stops the robot (the Cell brakes when its move task is
cancelled). The registry keeps the last finished operations for inspection.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from fxcell.daemon.encoding import error_info, jsonable
from fxcell.errors import MoveStoppedError

log = logging.getLogger(__name__)

Status = Literal["running", "succeeded", "failed", "cancelled"]


@dataclass(slots=True, eq=False)
class Operation:
    id: str
    name: str
    args: Mapping[str, Any]
    client: str
    started: float
    task: asyncio.Task[Any]
    status: Status = "running"
    ended: float | None = None
    result: Any = None
    error: dict[str, Any] | None = None
    done: asyncio.Event = field(default_factory=asyncio.Event)
    cancel_requested: bool = False
    move: bool = False
    lease: str | None = None  # the control lease it runs under (never described)

    def describe(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "name": self.name,
            "args": jsonable(self.args),
            "client": self.client,
            "status": self.status,
            "started": self.started,
            "ended": self.ended,
            "result": self.result,
            "error": self.error,
        }


class OperationRegistry:
    """Running and recently finished operations."""

    def __init__(
        self,
        keep: int = 200,
        on_change: Callable[[Operation], None] = lambda op: None,
    ) -> None:
        self._ops: OrderedDict[str, Operation] = OrderedDict()
        self._keep = keep
        self._ids = itertools.count(1)
        self._on_change = on_change

    def start(
        self,
        name: str,
        args: Mapping[str, Any],
        client: str,
        coro: Awaitable[Any],
        *,
        move: bool = False,
        lease: str | None = None,
    ) -> Operation:
        op_id = f"op-{next(self._ids)}"

        async def run() -> Any:
            return await coro

        task = asyncio.create_task(run(), name=f"fxcell daemon {op_id} {name}")
        op = Operation(op_id, name, dict(args), client, time.time(), task, move=move, lease=lease)
        self._ops[op_id] = op
        task.add_done_callback(lambda t: self._finished(op, t))
        self._on_change(op)
        self._trim()
        return op

    def _finished(self, op: Operation, task: asyncio.Task[Any]) -> None:
        op.ended = time.time()
        if task.cancelled():
            op.status = "cancelled"
            if op.move:  # the Cell braked the robot to rest, as for stop()
                error: BaseException = MoveStoppedError(f"{op.name}() was cancelled ({op.id})")
                op.error = error_info(error)
            else:
                op.error = {
                    "type": "OperationCancelledError",
                    "message": f"{op.name}() was cancelled ({op.id})",
                    "status": 409,
                    "detail": {},
                }
        elif (exc := task.exception()) is not None:
            # A move cancelled or stopped brakes to rest and ends with MoveStoppedError.
            stopped = op.cancel_requested or isinstance(exc, MoveStoppedError)
            op.status = "cancelled" if stopped else "failed"
            op.error = error_info(exc)
            if op.error["status"] >= 500:
                log.warning("operation %s %s failed: %r", op.id, op.name, exc)
        else:
            op.status = "succeeded"
            op.result = jsonable(task.result())
        op.done.set()
        self._on_change(op)

    def _trim(self) -> None:
        finished = [k for k, op in self._ops.items() if op.status != "running"]
        for key in finished[: max(0, len(self._ops) - self._keep)]:
            del self._ops[key]

    def get(self, op_id: str) -> Operation | None:
        return self._ops.get(op_id)

    def all(self, *, running_only: bool = False) -> list[Operation]:
        ops = list(self._ops.values())
        return [op for op in ops if op.status == "running"] if running_only else ops

    def running(self, lease: str | None = None) -> list[Operation]:
        return [
            op
            for op in self._ops.values()
            if op.status == "running" and (lease is None or op.lease == lease)
        ]

    async def wait(self, op: Operation, within: float | None) -> bool:
        """Wait until ``op`` ends (at most ``within`` s); returns whether it ended."""
        if within is None:
            await op.done.wait()
            return True
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(within):
                await op.done.wait()
        return op.done.is_set()

    async def cancel(self, op: Operation, within: float = 5.0) -> None:
        """Cancel ``op`` and wait until its task has finished (the robot has braked)."""
        if op.task.done():
            return
        op.cancel_requested = True
        op.task.cancel()
        await self.wait(op, within)

    async def cancel_all(self, within: float = 2.0) -> None:
        ops = self.running()
        for op in ops:
            op.cancel_requested = True
            op.task.cancel()
        if ops:
            await asyncio.wait([op.task for op in ops], timeout=within)
