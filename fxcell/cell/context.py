"""What the parts of a :class:`~fxcell.cell.Cell` (gripper, IO, camera, pick and place) use of it.

The Cell hands each part a :class:`CellContext`, not itself: the recording of commands, the
robot link, the newest state sample, the held object and the event bus. The parts never
import the Cell, so ``fxcell.cell`` has no circle of imports and a part can be driven by a
context made in a test.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from fxcell.config import CellConfig
    from fxcell.events import EventBus
    from fxcell.layout import Layout
    from fxcell.link import StateSubscription
    from fxcell.link.backend import LinkBackend
    from fxcell.protocol import RobotState


class Recording(Protocol):
    """Runs a command as a recorded one: ``async with record("io_set", signal=...) as out``
    publishes its start and its end (``out["result"]``, or the error that ended it)."""

    def __call__(
        self, name: str, /, **args: Any
    ) -> AbstractAsyncContextManager[dict[str, Any]]: ...


@dataclass(frozen=True)
class CellContext:
    """The Cell as its parts see it. Values that change while the cell runs (the
    configuration when a station frame is re-taught, the host once the embedded simulator
    runs, the newest sample) are read through the functions, never copied."""

    bus: EventBus
    """Where the parts publish their events (``DeviceEvent``, ``PlacementEvent``)."""
    command: Recording
    """Runs a command of the table: refused first (nothing sent, the refusal recorded) by
    its checks against the configuration and the guard the command table names."""
    record: Recording
    """Records a command without the table's guard: for a part whose own check refuses it
    (the gripper's: no power on the tool flange)."""
    link: Callable[[], LinkBackend]
    """The robot link; :class:`~fxcell.errors.ConnectionLostError` while the cell is closed."""
    sample: Callable[[], RobotState]
    """The newest 500 Hz state sample; :class:`~fxcell.errors.ConnectionLostError` without one."""
    latest: Callable[[], RobotState | None]
    """The newest state sample, or None while the link is down."""
    states: Callable[[int], StateSubscription]
    """Every state sample from now on (``with states(maxsize) as samples``)."""
    hold: Callable[[str | None], Awaitable[None]]
    """The gripper now holds an object of this kind (None: nothing): collision checking
    carries it and the payload on the controller includes it."""
    config: Callable[[], CellConfig]
    layout: Callable[[], Layout]
    host: Callable[[], str | None]
    """The controller's address (None until the embedded simulator runs)."""
    timeout: Callable[[], float]
    """The cell's command timeout (s)."""
