"""A bounded async iterator over a robot link's state samples.

Shared by every :class:`~fxcell.link.backend.LinkBackend` implementation (the link
client, the in-process fake): ``link.subscribe()`` returns one.
"""

from __future__ import annotations

import asyncio
import collections

from fxcell.protocol import RobotState


class StateSubscription:
    """An async iterator over state samples with a bounded buffer (oldest dropped).

    It adds itself to ``subscriptions`` (the link offers each sample to every member)
    and leaves it on :meth:`close`. Made for 500 Hz: a sample costs a deque append and,
    when a reader waits, one future; :meth:`next_within` bounds the wait without a timer
    per sample."""

    def __init__(self, subscriptions: set[StateSubscription], maxsize: int) -> None:
        self._subscriptions = subscriptions
        self._buffer: collections.deque[RobotState] = collections.deque(
            maxlen=maxsize if maxsize > 0 else None
        )
        self._waiters: list[asyncio.Future[None]] = []
        self._timed: asyncio.Future[None] | None = None  # the wait of next_within
        self._deadline = 0.0  # loop time at which that wait times out
        self._timer: asyncio.TimerHandle | None = None
        self.dropped = 0
        subscriptions.add(self)

    def offer(self, state: RobotState) -> None:
        """Queue one sample (the oldest is dropped when the buffer is full)."""
        buffer = self._buffer
        if len(buffer) == buffer.maxlen:
            self.dropped += 1  # the append drops the oldest
        buffer.append(state)
        if self._waiters:
            for waiter in self._waiters:
                if not waiter.done():
                    waiter.set_result(None)
            self._waiters.clear()

    def __aiter__(self) -> StateSubscription:
        return self

    async def __anext__(self) -> RobotState:
        buffer = self._buffer
        while not buffer:
            waiter = asyncio.get_running_loop().create_future()
            self._waiters.append(waiter)
            await waiter
        return buffer.popleft()

    async def next_within(self, timeout: float) -> RobotState:  # noqa: ASYNC109
        """The next sample; :class:`TimeoutError` if none has come ``timeout`` s after the
        call (one such reader at a time).

        The same deadline as ``async with asyncio.timeout(timeout)`` around each call, but
        a reader that calls it for every sample keeps one timer: it is re-armed, when it
        fires, to the deadline of the call waiting then, instead of a timer per call."""
        buffer = self._buffer
        if not buffer:
            loop = asyncio.get_running_loop()
            self._deadline = loop.time() + timeout
            if self._timer is None:
                self._timer = loop.call_at(self._deadline, self._expire)
            while not buffer:
                waiter = self._timed = loop.create_future()
                self._waiters.append(waiter)
                await waiter
        return buffer.popleft()

    def _expire(self) -> None:
        self._timer = None
        waiter = self._timed
        if waiter is None or waiter.done():
            return  # no bounded wait now: the next one arms the timer again
        loop = waiter.get_loop()
        if loop.time() < self._deadline:  # a later wait than the one that armed it
            self._timer = loop.call_at(self._deadline, self._expire)
        else:
            self._timed = None
            waiter.set_exception(TimeoutError())

    def close(self) -> None:
        self._subscriptions.discard(self)
        timed = self._timed
        if self._timer is not None and (timed is None or timed.done()):
            self._timer.cancel()  # (a bounded wait still under way keeps its deadline)
            self._timer = None

    def __enter__(self) -> StateSubscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
