"""Who controls the cell: one client at a time, any number may watch.

A client (named by the ``X-Fxcell-Client`` header) takes control with its first
command that changes the robot, or explicitly. Others are refused with
:class:`~fxcell.errors.ControlHeldError` ("controlled by ...") until the holder
releases control or its lease runs out. The lease is renewed by every command of the
holder and does not run out while the holder has an operation running or a stream
open. ``force`` takes control over from a holder that went away.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from fxcell.errors import ControlHeldError


@dataclass(slots=True)
class Holder:
    client: str
    since: float  # wall clock
    last_seen: float  # monotonic


class ControlLock:
    """The control lease of the cell."""

    def __init__(
        self,
        lease: float = 30.0,
        *,
        keeps_alive: Callable[[str], bool] = lambda client: False,
        on_change: Callable[[Holder | None], None] = lambda holder: None,
    ) -> None:
        self.lease = lease
        self._keeps_alive = keeps_alive
        self._on_change = on_change
        self._holder: Holder | None = None

    @property
    def holder(self) -> Holder | None:
        """The current holder, ``None`` when control is free (an expired lease is free)."""
        holder = self._holder
        if holder is None:
            return None
        if time.monotonic() - holder.last_seen > self.lease and not self._keeps_alive(
            holder.client
        ):
            self._holder = None
            self._on_change(None)
            return None
        return holder

    def acquire(self, client: str, *, force: bool = False) -> Holder:
        """Take or renew control for ``client``; raises ControlHeldError if another holds it."""
        holder = self.holder
        now = time.monotonic()
        if holder is not None and holder.client == client:
            holder.last_seen = now
            return holder
        if holder is not None and not force:
            held = time.time() - holder.since
            raise ControlHeldError(
                f"the cell is controlled by {holder.client!r} (for {held:.0f} s); "
                "wait until it releases control or take over with force",
                status=409,
            )
        self._holder = Holder(client, time.time(), now)
        self._on_change(self._holder)
        return self._holder

    def release(self, client: str) -> bool:
        """Release control if ``client`` holds it; returns whether it did."""
        holder = self.holder
        if holder is None or holder.client != client:
            return False
        self._holder = None
        self._on_change(None)
        return True

    def describe(self) -> dict[str, object] | None:
        holder = self.holder
        if holder is None:
            return None
        return {"client": holder.client, "since": holder.since}
