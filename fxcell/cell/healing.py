"""Going on by itself after what needs no human: a robot link that dropped or restarted.

A step of pick or place (a move, a gripper command, a check) that fails because the robot
link went down under it (the link process died or was restarted, the state stream paused;
or the link process braked the move by itself, :class:`~fxcell.errors.LinkBrakeError`)
is not a reason to call the operator: the arm braked (the link process brakes it, or the
controller holds the last setpoint), nothing was lost, and the step can simply be done again
from where the arm is. :func:`resilient` runs such a step: on a failure caused by a lost
link it waits for the link, for the arm seen at rest and for external control
(:meth:`Cell.restore_control <fxcell.cell.cell.Cell.restore_control>`), then runs the step
again. It gives up after ``robot.heal_attempts`` recoveries in a row in which the arm got no
further (a move interrupted again and again still ends: each attempt starts where the last
one braked), and after four times as many in all. Safety stops, timeouts of the robot, Local
control, bad targets and gripper findings (nothing grasped, object lost) are never healed:
they raise as before.

Each recovery is logged as a warning (the recorder keeps it in ``/log``) and announced as a
:class:`Heal` to the listener in :data:`HEAL_LISTENER`, which a job sets around its steps to
record and show them.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from contextvars import ContextVar
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, Protocol, TypeVar

from fxcell.errors import (
    ConnectionLostError,
    FxcellError,
    InvalidStateError,
    LinkBrakeError,
    MoveStoppedError,
    RobotTimeoutError,
)

if TYPE_CHECKING:
    from fxcell.cell.cell import Cell
    from fxcell.protocol import RobotState

log = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True)
class Heal:
    """One recovery: ``phase`` ``start`` (the step failed, the cell recovers), ``done`` (the
    step ran again and succeeded) or ``failed`` (the recovery itself failed: it raises)."""

    what: str
    attempt: int
    phase: Literal["start", "done", "failed"]
    reason: str


HEAL_LISTENER: ContextVar[Callable[[Heal], None] | None] = ContextVar(
    "fxcell_heal_listener", default=None
)
"""Called with every :class:`Heal` of the steps run in this context (a job sets it)."""


def healable(cell: Cell, error: FxcellError, losses_before: int) -> bool:
    """Whether ``error`` came from a lost link (and so needs no human)."""
    if isinstance(error, ConnectionLostError | LinkBrakeError):
        return True  # the link went down, or its guard braked the arm (a paused stream)
    if not isinstance(error, MoveStoppedError | InvalidStateError | RobotTimeoutError):
        return False  # safety stops, gripper findings, bad targets, Local control, ...
    if type(error) is MoveStoppedError and cell.link_losses == losses_before:
        return False  # someone stopped the move
    return cell.link_losses != losses_before or cell.link_recovering


def announce(heal: Heal) -> None:
    """Log ``heal`` (the recorder keeps the log in ``/log``) and tell the context's listener."""
    if heal.phase == "start":
        log.warning(
            "%s interrupted (%s): recovering, attempt %d", heal.what, heal.reason, heal.attempt
        )
    elif heal.phase == "done":
        log.warning("%s done after recovering (attempt %d)", heal.what, heal.attempt)
    else:
        log.warning("%s: recovery %d failed: %s", heal.what, heal.attempt, heal.reason)
    listener = HEAL_LISTENER.get()
    if listener is not None:
        listener(heal)


PROGRESS = 2e-3
"""rad: a joint that moved this far between two recoveries means the step got further."""


async def retrying(
    what: str,
    step: Callable[[], Awaitable[T]],
    *,
    attempts: int,
    healable: Callable[[FxcellError], bool],
    restore: Callable[[], Awaitable[object]],
    announce: Callable[[Heal], None],
    moved: Callable[[], bool] | None = None,
) -> T:
    """Run ``step``; after a failure ``healable`` accepts, ``restore`` and run it again,
    announcing each :class:`Heal`. A failure of ``restore`` counts as one of the step (it
    may be healable too: the link dropped again).

    It raises after ``attempts`` recoveries in a row without progress, and after
    ``4 * attempts`` in all. ``moved``, asked after each recovery, says whether the arm got
    further since it was last asked (or since the step began); without it no recovery is
    progress.
    """
    attempt = 0  # recoveries in all
    stuck = 0  # recoveries since the arm last got further
    reason = ""
    while True:
        try:
            if attempt:
                await restore()
                if moved is not None and moved():
                    stuck = 0
            result = await step()
        except FxcellError as exc:
            if stuck >= attempts or attempt >= 4 * attempts or not healable(exc):
                if attempt:
                    announce(Heal(what, attempt, "failed", str(exc)))
                raise
            attempt += 1
            stuck += 1
            reason = str(exc)
            announce(Heal(what, attempt, "start", reason))
            continue
        if attempt:
            announce(Heal(what, attempt, "done", reason))
        return result


class Arm(Protocol):
    """Where :func:`arm_moved` reads the arm's joints (a :class:`Cell`, a job's cell)."""

    @property
    def robot_state(self) -> RobotState | None: ...


def arm_moved(cell: Arm) -> Callable[[], bool]:
    """A ``moved`` for :func:`retrying`: whether the arm's joints are more than
    :data:`PROGRESS` from where they were at the previous call (the first: from now; no
    sample to compare with is no progress)."""

    def joints() -> tuple[float, ...] | None:
        state = cell.robot_state
        return state.actual_q if state is not None else None

    last = joints()

    def moved() -> bool:
        nonlocal last
        now = joints()
        if now is None:
            return False
        went = last is not None and any(
            abs(a - b) > PROGRESS for a, b in zip(now, last, strict=True)
        )
        last = now
        return went

    return moved


async def resilient(cell: Cell, what: str, step: Callable[[], Awaitable[T]]) -> T:
    """Run ``step`` of a cell; after a failure that a lost link caused, restore control and
    run it again (within ``robot.heal_attempts``, see :func:`retrying`). ``step`` must be
    safe to repeat from wherever it left the arm (a move to a target, a gripper command, a
    check)."""
    losses = cell.link_losses

    async def counted() -> T:
        nonlocal losses
        losses = cell.link_losses
        return await step()

    return await retrying(
        what,
        counted,
        attempts=cell.config.robot.heal_attempts,
        healable=lambda exc: healable(cell, exc, losses),
        restore=cell.restore_control,
        announce=announce,
        moved=arm_moved(cell),
    )
