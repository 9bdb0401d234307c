"""The cell's event bus: every command, transition, state sample and motion record.

The :class:`~fxcell.cell.cell.Cell` publishes here; the MCAP recorder, the daemon's
WebSocket stream and user subscribers consume. Publishing never blocks: synchronous
subscribers must be quick (hand the event to a queue), and async streams are
bounded queues that drop their oldest entry when a consumer falls behind, counting
what they dropped. Times are wall-clock seconds (``time.time()``).
"""

from __future__ import annotations

import asyncio
import contextvars
import enum
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from fxcell.protocol import RobotState

log = logging.getLogger(__name__)


class Origin(enum.StrEnum):
    """Who issued a command."""

    LIBRARY = "library"
    DAEMON = "daemon"
    REPLAY = "replay"
    INTERNAL = "internal"


COMMAND_ORIGIN: contextvars.ContextVar[str | None] = contextvars.ContextVar(
    "fxcell_command_origin", default=None
)
"""Who sent the commands run in this context, when more precise than the Cell's origin
(the daemon sets the client's name: the page, the CLI, a program)."""


@dataclass(frozen=True, slots=True)
class CommandEvent:
    """A public API call: published once when it starts and once when it ends."""

    command_id: int
    name: str
    args: Mapping[str, Any]
    origin: Origin | str
    started: float
    ended: float | None = None
    outcome: Literal["started", "ok", "error"] = "started"
    error_type: str | None = None
    error_message: str | None = None
    result: Any = None


@dataclass(frozen=True, slots=True)
class TransitionEvent:
    """The robot-mode state machine changed state."""

    time: float
    source: str
    dest: str
    trigger: str
    cause: Literal["command", "observed"]
    detail: str = ""


@dataclass(frozen=True, slots=True)
class StateEvent:
    """One 500 Hz sample of the robot state stream."""

    sample: RobotState


@dataclass(frozen=True, slots=True)
class MotionEvent:
    """A planned path, a time-parameterised trajectory or a tracking report of a move."""

    time: float
    move_id: int
    kind: Literal["path", "trajectory", "tracking", "result"]
    data: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class DeviceEvent:
    """A change of a device beside the arm: ``gripper`` (width, object held, fault) or
    ``job`` (a fusion-machine job's steps and samples); recorded on topic ``/<device>``."""

    time: float
    device: Literal["gripper", "job"]
    data: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class PlacementEvent:
    """A placement check: the annotated camera frame (JPEG) and the verdict (JSON-ready:
    ``ok``, ``reason``, ``positions``, ``obstructions``, ...); recorded on ``/camera/placement``
    (``foxglove.CompressedImage``) and ``/camera/placement/verdict``."""

    time: float
    jpeg: bytes
    report: Mapping[str, Any] = field(default_factory=dict)
    frame_id: str = "camera"


@dataclass(frozen=True, slots=True)
class LogEvent:
    """A log record worth keeping with the session (warnings, errors, notices)."""

    time: float
    level: int
    name: str
    message: str
    file: str = ""
    line: int = 0


Event = (
    CommandEvent
    | TransitionEvent
    | StateEvent
    | MotionEvent
    | DeviceEvent
    | PlacementEvent
    | LogEvent
)
Subscriber = Callable[[Event], None]


class EventStream:
    """An async iterator over bus events of chosen types, with a bounded buffer."""

    def __init__(self, bus: EventBus, types: tuple[type, ...], maxsize: int) -> None:
        self._bus = bus
        self._types = types
        self._queue: asyncio.Queue[Event] = asyncio.Queue(maxsize)
        self.dropped = 0

    def _offer(self, event: Event) -> None:
        if self._types and not isinstance(event, self._types):
            return
        if self._queue.full():
            self._queue.get_nowait()
            self.dropped += 1
        self._queue.put_nowait(event)

    def __aiter__(self) -> EventStream:
        return self

    async def __anext__(self) -> Event:
        return await self._queue.get()

    def close(self) -> None:
        self._bus._streams.discard(self)

    def __enter__(self) -> EventStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EventBus:
    """Fan-out of cell events to synchronous subscribers and async streams.

    Publish only from the event loop's thread.
    """

    def __init__(self) -> None:
        self._subscribers: list[Subscriber] = []
        self._streams: set[EventStream] = set()
        self._next_command_id = 0

    def next_command_id(self) -> int:
        self._next_command_id += 1
        return self._next_command_id

    def publish(self, event: Event) -> None:
        for callback in tuple(self._subscribers):
            try:
                callback(event)
            except Exception:  # a broken subscriber must not break the control path
                log.exception("event subscriber %r failed", callback)
        for stream in tuple(self._streams):
            stream._offer(event)

    def subscribe(self, callback: Subscriber) -> Callable[[], None]:
        """Call ``callback(event)`` for every event; returns the function that unsubscribes."""
        self._subscribers.append(callback)

        def unsubscribe() -> None:
            if callback in self._subscribers:
                self._subscribers.remove(callback)

        return unsubscribe

    def stream(self, *types: type, maxsize: int = 4096) -> EventStream:
        """An async iterator over events of ``types`` (all events if none given).

        Use as ``with bus.stream(StateEvent) as events: async for e in events: ...``.
        """
        stream = EventStream(self, types, maxsize)
        self._streams.add(stream)
        return stream


def now() -> float:
    """Wall-clock time in seconds, the time base of every event."""
    return time.time()
