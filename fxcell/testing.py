"""Helpers for testing fxcell and cell scripts built on it.

Use as a pytest plugin (``-p fxcell.testing`` or ``pytest_plugins = ["fxcell.testing"]``)
to get the fixtures below. This module is test support: the runtime never imports it.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest
import pytest_asyncio


def _describe(task: asyncio.Task[object]) -> str:
    coro = task.get_coro()
    where = getattr(coro, "__qualname__", repr(coro))
    return f"{task.get_name()} ({where})"


@pytest_asyncio.fixture(autouse=True)
async def fxcell_no_leaked_tasks() -> AsyncIterator[None]:
    """Fail the test if it leaves asyncio tasks running after its fixtures are torn down."""
    before = set(asyncio.all_tasks())
    yield
    for _ in range(3):  # let tasks that are finishing right now finish
        await asyncio.sleep(0)
    current = asyncio.current_task()
    leaked = [t for t in asyncio.all_tasks() - before if t is not current and not t.done()]
    if leaked:
        names = ", ".join(_describe(t) for t in leaked)
        for task in leaked:
            task.cancel()
        await asyncio.gather(*leaked, return_exceptions=True)
        pytest.fail(f"test leaked {len(leaked)} asyncio task(s): {names}", pytrace=False)
