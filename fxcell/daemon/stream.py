"""WebSocket fan-out of robot state, transitions, commands and daemon events.

One synchronous subscriber on the cell's event bus feeds every connected watcher.
State samples (500 Hz) are decimated per watcher to the rate it asked for; a slow
watcher only ever misses state samples (it gets the newest), never transitions,
commands or operation updates. Each state sample is encoded once, whatever the number
of watchers.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from fxcell.daemon.encoding import jsonable
from fxcell.events import (
    CommandEvent,
    DeviceEvent,
    Event,
    LogEvent,
    MotionEvent,
    StateEvent,
    TransitionEvent,
)
from fxcell.protocol import RobotState

MIN_RATE = 1.0
MAX_RATE = 500.0
DEFAULT_RATE = 50.0
TOPICS = frozenset(
    {"state", "transition", "command", "motion", "log", "operation", "control", "device"}
)
MAX_BACKLOG = 2000


def state_message(sample: RobotState, machine_state: str | None) -> dict[str, Any]:
    return {
        "type": "state",
        "state": machine_state,
        "t": sample.timestamp,
        "robot_mode": sample.robot_mode.name,
        "safety_mode": sample.safety_mode.name,
        "runtime_state": sample.runtime_state.name,
        "q": list(sample.actual_q),
        "qd": list(sample.actual_qd),
        "target_q": list(sample.target_q),
        "tcp": list(sample.actual_tcp_pose),
        "speed_scaling": sample.speed_scaling,
        "digital_in": sample.digital_input_bits,
        "digital_out": sample.digital_output_bits,
        "analog_in": [sample.standard_analog_input0, sample.standard_analog_input1],
        "analog_out": [sample.standard_analog_output0, sample.standard_analog_output1],
    }


def event_message(event: Event) -> dict[str, Any] | None:
    """The stream message of a non-state bus event (``None``: not streamed)."""
    if isinstance(event, TransitionEvent):
        return {"type": "transition", **jsonable(event)}
    if isinstance(event, CommandEvent):
        return {"type": "command", **jsonable(event)}
    if isinstance(event, LogEvent):
        return {"type": "log", **jsonable(event)}
    if isinstance(event, DeviceEvent):
        return {"type": "device", **jsonable(event)}
    if isinstance(event, MotionEvent) and event.kind == "result":
        return {"type": "motion", **jsonable(event)}
    return None


PING_PERIOD = 5.0
"""Seconds between two pings the daemon sends every watcher (it answers with a pong)."""
PONG_TIMEOUT = 12.0
"""A watcher that has not answered a ping for this long keeps no control lease alive."""


class Watcher:
    """One WebSocket client: its topics, its state rate and what waits to be sent."""

    def __init__(
        self, topics: frozenset[str], rate: float, client: str | None, lease: str | None = None
    ) -> None:
        self.topics = topics
        self.client = client
        self.lease = lease
        self.last_pong = time.monotonic()
        """When the client last answered a ping (a frozen client stops answering)."""
        self.period = 1.0 / rate
        self._next_due = 0.0
        self._state: str | None = None
        self._backlog: deque[str] = deque()
        self._wakeup = asyncio.Event()
        self.overflowed = False
        self.sent_states = 0

    def set_rate(self, rate: float) -> None:
        self.period = 1.0 / rate
        self._next_due = 0.0

    def offer_state(self, now: float, encode: Callable[[], str]) -> None:
        if "state" not in self.topics or now < self._next_due:
            return
        self._next_due = max(self._next_due + self.period, now + self.period * 0.5)
        self._state = encode()
        self._wakeup.set()

    def offer_control(self, text: str) -> None:
        """A message for this watcher alone, whatever its topics (pings)."""
        self._backlog.append(text)
        self._wakeup.set()

    def offer(self, topic: str, text: str) -> None:
        if topic not in self.topics:
            return
        if len(self._backlog) >= MAX_BACKLOG:
            self.overflowed = True
        else:
            self._backlog.append(text)
        self._wakeup.set()

    async def next_batch(self) -> list[str]:
        """Wait for messages to send: the backlog in order, then the newest state."""
        await self._wakeup.wait()
        self._wakeup.clear()
        batch = list(self._backlog)
        self._backlog.clear()
        if self._state is not None:
            batch.append(self._state)
            self._state = None
            self.sent_states += 1
        return batch


class StreamHub:
    """Fan-out from the event bus (and the daemon) to every watcher."""

    def __init__(self, machine_state: Callable[[], str | None]) -> None:
        self._watchers: set[Watcher] = set()
        self._machine_state = machine_state
        self._encoded: tuple[RobotState | None, str] = (None, "")

    @property
    def watchers(self) -> int:
        return len(self._watchers)

    def watches(self, lease: str) -> bool:
        """Whether a live watcher (one that answers pings) shows this control lease."""
        now = time.monotonic()
        return any(w.lease == lease and now - w.last_pong < PONG_TIMEOUT for w in self._watchers)

    def add(
        self, topics: frozenset[str], rate: float, client: str | None, lease: str | None = None
    ) -> Watcher:
        watcher = Watcher(topics, rate, client, lease)
        self._watchers.add(watcher)
        return watcher

    def remove(self, watcher: Watcher) -> None:
        self._watchers.discard(watcher)

    def _encode_state(self, sample: RobotState) -> str:
        if self._encoded[0] is not sample:
            text = json.dumps(state_message(sample, self._machine_state()))
            self._encoded = (sample, text)
        return self._encoded[1]

    def on_event(self, event: Event) -> None:
        """The bus subscriber: hand each event to the watchers that want it."""
        if not self._watchers:
            return
        if isinstance(event, StateEvent):
            now = time.monotonic()
            sample = event.sample
            for watcher in tuple(self._watchers):
                watcher.offer_state(now, lambda: self._encode_state(sample))
            return
        message = event_message(event)
        if message is not None:
            self.broadcast(message)

    def broadcast(self, message: dict[str, Any]) -> None:
        """Send a daemon message (operation, control, ...) to the watchers of its type."""
        if not self._watchers:
            return
        text = json.dumps(message)
        topic = message["type"]
        for watcher in tuple(self._watchers):
            watcher.offer(topic, text)


def parse_rate(value: str | float | None) -> float:
    """A state rate in Hz within [1, 500]; ValueError otherwise."""
    if value is None:
        return DEFAULT_RATE
    rate = float(value)
    if not math.isfinite(rate) or not MIN_RATE <= rate <= MAX_RATE:
        raise ValueError(f"rate must be between {MIN_RATE:g} and {MAX_RATE:g} Hz, got {value!r}")
    return rate


def parse_topics(value: str | None) -> frozenset[str]:
    if not value:
        return TOPICS
    topics = frozenset(t.strip() for t in value.split(",") if t.strip())
    unknown = topics - TOPICS
    if unknown:
        raise ValueError(
            f"unknown topics {sorted(unknown)}; choose from {', '.join(sorted(TOPICS))}"
        )
    return topics
