"""Who controls the cell: one client at a time, any number may watch.

Control is a lease, tied to authentication: an authenticated client takes control with
its first command that changes the robot (or explicitly, ``POST /api/control``) and gets a
lease id back (``X-Fxcell-Lease`` response header, and in the body of ``POST
/api/control``). Its later commands carry the id (``X-Fxcell-Lease`` request header);
anyone else, whatever name it gives, is refused with
:class:`~fxcell.errors.ControlHeldError` ("controlled by ...") until the holder releases
control or its lease runs out. The lease is renewed by every command that carries it and
does not run out while the holder has an operation running or a stream open that shows
the lease and answers the daemon's pings. ``force`` takes control over from a holder that
went away. The client's name (``X-Fxcell-Client``) is for people: the page shows it.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass

from fxcell.errors import ControlHeldError

LEASE_HEADER = "X-Fxcell-Lease"


@dataclass(slots=True)
class Holder:
    client: str  # the name it gave
    lease: str  # the secret its commands carry
    since: float  # wall clock
    last_seen: float  # monotonic


class ControlLock:
    """The control lease of the cell."""

    def __init__(
        self,
        lease: float = 30.0,
        *,
        keeps_alive: Callable[[Holder], bool] = lambda holder: False,
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
        if time.monotonic() - holder.last_seen > self.lease and not self._keeps_alive(holder):
            self._holder = None
            self._on_change(None)
            return None
        return holder

    def acquire(self, client: str, lease: str | None = None, *, force: bool = False) -> Holder:
        """Renew the lease ``lease``, or take control (free, or ``force``); raises
        ControlHeldError when another client holds it."""
        holder = self.holder
        now = time.monotonic()
        if holder is not None and lease is not None and secrets.compare_digest(lease, holder.lease):
            holder.last_seen = now
            return holder
        if holder is not None and not force:
            held = time.time() - holder.since
            raise ControlHeldError(
                f"the cell is controlled by {holder.client!r} (for {held:.0f} s); "
                "wait until it releases control or take over with force",
                status=409,
            )
        self._holder = Holder(client, secrets.token_urlsafe(18), time.time(), now)
        self._on_change(self._holder)
        return self._holder

    def release(self, lease: str | None) -> bool:
        """Release control if ``lease`` is the holder's; returns whether it did."""
        holder = self.holder
        if holder is None or lease is None or not secrets.compare_digest(lease, holder.lease):
            return False
        self._holder = None
        self._on_change(None)
        return True

    def is_holder(self, lease: str | None) -> bool:
        holder = self.holder
        return (
            holder is not None and lease is not None and secrets.compare_digest(lease, holder.lease)
        )

    def describe(self) -> dict[str, object] | None:
        """Who holds control (never the lease id)."""
        holder = self.holder
        if holder is None:
            return None
        return {"client": holder.client, "since": holder.since}
