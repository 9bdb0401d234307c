"""Going on by itself after what needs no human: a robot link that dropped or restarted.

A step of pick or place (a move, a gripper command, a check) that fails because the robot
link went down under it (the link process died or was restarted, the state stream paused;
or the link process braked the move by itself, :class:`~fxcell.errors.LinkBrakeError`)
is not a reason to call the operator: the arm braked (the link process brakes it, or the
controller holds the last setpoint), nothing was lost, and the step can simply be done again
from where the arm is. :func:`resilient` runs such a step: on a failure caused by a lost
link it waits for the link, for the arm seen at rest and for external control
(:meth:`Cell.restore_control <fxcell.cell.cell.Cell.restore_control>`), then runs the step
again, at most ``robot.heal_attempts`` times. Safety stops, timeouts of the robot, Local
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
from typing import TYPE_CHECKING, Literal, TypeVar

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


async def retrying(
    what: str,
    step: Callable[[], Awaitable[T]],
    *,
    attempts: int,
    healable: Callable[[FxcellError], bool],
    restore: Callable[[], Awaitable[object]],
    announce: Callable[[Heal], None],
) -> T:
    """Run ``step``; after a failure ``healable`` accepts, ``restore`` and run it again, at
    most ``attempts`` times, announcing each :class:`Heal`. A failure of ``restore`` counts
    as one of the step (it may be healable too: the link dropped again)."""
    attempt = 0
    reason = ""
    while True:
        try:
            if attempt:
                await restore()
            result = await step()
        except FxcellError as exc:
            if attempt >= attempts or not healable(exc):
                if attempt:
                    announce(Heal(what, attempt, "failed", str(exc)))
                raise
            attempt += 1
            reason = str(exc)
            announce(Heal(what, attempt, "start", reason))
            continue
        if attempt:
            announce(Heal(what, attempt, "done", reason))
        return result


async def resilient(cell: Cell, what: str, step: Callable[[], Awaitable[T]]) -> T:
    """Run ``step`` of a cell; after a failure that a lost link caused, restore control and
    run it again (at most ``robot.heal_attempts`` times). ``step`` must be safe to repeat
    from wherever it left the arm (a move to a target, a gripper command, a check)."""
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
    )
