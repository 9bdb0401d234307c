"""Awaiting a condition in a test instead of sleeping for it.

``await until(predicate, "what")`` polls ``predicate`` (a plain or async callable) until it is
true and fails, naming ``what``, if it is not true within ``timeout`` s. A condition that
holds on time costs only its own checks; one that never holds fails clearly instead of
letting the test go on with a wrong premise. ``wait_until`` is the same for plain tests.

``controller_time_passes`` (and ``controller_time_passed``) is for the other kind of wait:
checking that nothing happens within a time. It waits on the simulator's own clock, so a
simulator starved by a busy machine has still had that time to act.
"""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fxcell.testing import SimulatorHandle

POLL = 0.005  # s between checks


async def until(
    predicate: Callable[[], bool | Awaitable[bool]],
    what: str,
    timeout: float = 10.0,  # noqa: ASYNC109
) -> None:
    deadline = time.monotonic() + timeout
    while True:
        result = predicate()
        if inspect.isawaitable(result):
            result = await result
        if result:
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        await asyncio.sleep(POLL)


async def controller_time_passes(sim: SimulatorHandle, seconds: float) -> None:
    """Until the simulated controller's own clock has advanced ``seconds``: for checks that
    nothing happens in that time (a simulator starved by a busy machine has had that time
    to act, which a wall-clock sleep does not promise)."""
    start = float((await asyncio.to_thread(sim.state))["time"])

    async def advanced() -> bool:
        return float((await asyncio.to_thread(sim.state))["time"]) >= start + seconds

    await until(advanced, f"{seconds:g} s of the simulator's controller time", 10.0 + 20 * seconds)


def wait_until(predicate: Callable[[], bool], timeout: float = 5.0, what: str = "it") -> None:
    """``until`` for tests that are not coroutines."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(POLL)


def controller_time_passed(sim: SimulatorHandle, seconds: float) -> None:
    """``controller_time_passes`` for tests that are not coroutines."""
    start = float(sim.state()["time"])
    wait_until(
        lambda: float(sim.state()["time"]) >= start + seconds,
        10.0 + 20 * seconds,
        f"{seconds:g} s of the simulator's controller time",
    )
