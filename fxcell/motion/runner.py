"""One move, one owner: typed move targets and :class:`MoveRunner`, a status object per move.

A :class:`MoveRunner` owns the task of one move (as ophyd-async's status objects own
theirs): it starts it, knows the execution streaming it, stops it (braking to rest on a
jerk-limited profile) and holds why it was aborted. The Cell keeps one runner per
running move; :meth:`MotionController.runner <fxcell.motion.moves.MotionController.runner>`
builds one that plans a :data:`MoveTarget` and executes the plan.

Light on purpose (no numpy): the Cell imports it before the motion stack is loaded.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from fxcell.errors import FxcellError

if TYPE_CHECKING:
    from fxcell.geometry import Pose
    from fxcell.motion.moves import MoveExecution


@dataclass(frozen=True)
class JointTarget:
    """Joint positions (rad), reached on a collision-free joint-space path."""

    joints: Sequence[float]


@dataclass(frozen=True)
class PoseTarget:
    """A TCP pose (a Pose, [x, y, z, qx, qy, qz, qw] or [x, y, z, r, p, y]); ``linear``:
    on a straight TCP line, else a joint-space move to the IK solution nearest the start."""

    pose: Pose | Sequence[float]
    linear: bool = False


@dataclass(frozen=True)
class DistanceTarget:
    """A TCP displacement [dx, dy, dz] (m, base axes) on a straight line, orientation kept."""

    distance: Sequence[float]


@dataclass(frozen=True)
class RelativeTarget:
    """The seed's relative move: to ``start_pose``, then to ``target_pose`` (both checked
    before the robot moves)."""

    start_pose: Pose | Sequence[float]
    target_pose: Pose | Sequence[float]


MoveTarget = JointTarget | PoseTarget | DistanceTarget | RelativeTarget
"""What a move goes to; :meth:`fxcell.motion.moves.MotionPlanner.plan` plans each kind."""


class MoveRunner:
    """A move's status object: its task, its stop, its result.

    ``work(runner)`` is the move (plan and stream); it reports the execution it streams
    through :attr:`execution`, so that :meth:`stop` can brake it gracefully.
    """

    def __init__(
        self, work: Callable[[MoveRunner], Coroutine[Any, Any, Any]], name: str = "move"
    ) -> None:
        self.name = name
        self._work = work
        self.task: asyncio.Task[Any] | None = None
        self.execution: MoveExecution | None = None
        """The execution streaming the current leg (None while planning or done)."""
        self.error: FxcellError | None = None
        """Why the move was aborted (a safety stop, a lost link, ...), raised to its caller."""
        self.stopping = False
        """True once a stop was asked: the move is braking to rest."""

    def start(self) -> asyncio.Task[Any]:
        """Start the move's task (once)."""
        if self.task is None:
            self.task = asyncio.create_task(self._work(self), name=f"move {self.name}")
        return self.task

    @property
    def running(self) -> bool:
        return self.task is not None and not self.task.done()

    def abort(self, error: FxcellError) -> None:
        """End the move now (its execution still brakes to rest); its caller gets ``error``."""
        if self.task is not None and not self.task.done():
            if self.error is None:
                self.error = error
            self.task.cancel()

    async def stop(
        self, error: FxcellError, *, graceful: bool = True, within: float = 10.0
    ) -> None:
        """Brake to rest and wait until the move has ended.

        Graceful: the execution brakes itself, and the move's ``MoveStoppedError``
        carries what it did; otherwise, or if it has not ended ``within`` s, the task is
        aborted with ``error``.
        """
        task = self.task
        if task is None or task.done():
            return
        self.stopping = True
        if graceful and self.execution is not None:
            self.execution.request_stop()
            with contextlib.suppress(BaseException):
                async with asyncio.timeout(within):
                    await asyncio.shield(task)
            if task.done():
                return
        self.abort(error)
        with contextlib.suppress(BaseException):
            await task


__all__ = [
    "DistanceTarget",
    "JointTarget",
    "MoveRunner",
    "MoveTarget",
    "PoseTarget",
    "RelativeTarget",
]
