"""What every simulator handle of the test support shares: ``with`` and ``async with``."""

from __future__ import annotations

import asyncio
from types import TracebackType
from typing import Self


class ProcessHandle:
    """A handle on a process that ``start`` starts and ``stop`` stops (for subclasses):
    ``with`` and ``async with`` (the latter forks and waits from a worker thread)."""

    def start(self) -> Self:
        raise NotImplementedError

    def stop(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    async def __aenter__(self) -> Self:
        await asyncio.to_thread(self.start)
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await asyncio.to_thread(self.stop)
