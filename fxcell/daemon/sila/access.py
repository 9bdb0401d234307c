"""Who may do what over SiLA: the daemon's token, the lock (the control lease), commands.

- **Token**: every call but SiLAService's carries the daemon's bearer token as the standard
  ``AuthorizationService`` metadata ``AccessToken`` (the token file's content, as for HTTP);
  a missing or wrong one is refused (``InvalidAccessToken``) before anything runs.
- **Lock**: ``LockController`` is the cell's control lease (:mod:`fxcell.daemon.control`).
  Locking takes control as the client ``SiLA client (LockController)`` (the operator page
  shows it; locking is refused while another client, HTTP or SiLA, holds control); while it
  is locked, every command that changes the robot must carry the lock identifier, and each
  such call renews the lease. The lease stays alive while the lock is (its timeout counts
  from the last call that carried it; 0: until unlocked); an operator who takes control
  over with force ends the lock.
- **Unlocked**: a command that changes the robot takes control for its own duration, as an
  HTTP client's would, and is refused while someone else holds control (``ControlHeld``).
  ``Stop`` needs the token only, never control.
"""

from __future__ import annotations

import asyncio
import hmac
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sila2.features.authorizationservice import (
    AuthorizationServiceBase,
    AuthorizationServiceFeature,
    InvalidAccessToken,
)
from sila2.features.lockcontroller import (
    InvalidLockIdentifier,
    LockControllerBase,
    LockControllerFeature,
    LockServer_Responses,
    ServerAlreadyLocked,
    ServerNotLocked,
    UnlockServer_Responses,
)
from sila2.framework import Command, Feature, FullyQualifiedIdentifier, Metadata, Property
from sila2.server import MetadataDict, MetadataInterceptor

from fxcell.commands import get_command
from fxcell.daemon.control import Holder
from fxcell.daemon.sila.bridge import LoopBridge
from fxcell.errors import ControlHeldError, MoveStoppedError

if TYPE_CHECKING:
    from sila2.server import SilaServer

    from fxcell.daemon.service import CellService


def _metadata(feature: Feature, identifier: str) -> Metadata[Any]:
    node = feature[identifier]
    assert isinstance(node, Metadata)
    return node


ACCESS_TOKEN = _metadata(AuthorizationServiceFeature, "AccessToken")
LOCK_IDENTIFIER = _metadata(LockControllerFeature, "LockIdentifier")
LOCK_CLIENT = "SiLA client (LockController)"
UNLOCKED_CLIENT = "SiLA client"
Affected = list[Feature | Command | Property | FullyQualifiedIdentifier]


class AccessToken(AuthorizationServiceBase):
    """``AuthorizationService``: the daemon's token on every call but SiLAService's."""

    def __init__(self, parent_server: SilaServer, token: str) -> None:
        super().__init__(parent_server=parent_server)
        self._server = parent_server
        self._token = token.encode()
        parent_server.add_metadata_interceptor(_TokenCheck(self))

    def valid(self, token: object) -> bool:
        return isinstance(token, str) and hmac.compare_digest(token.encode(), self._token)

    def get_calls_affected_by_AccessToken(self) -> Affected:
        return [
            feature
            for feature in self._server.features.values()
            if feature._identifier not in ("SiLAService", "AuthorizationService")
        ]


class _TokenCheck(MetadataInterceptor):
    def __init__(self, access: AccessToken) -> None:
        super().__init__([ACCESS_TOKEN])
        self.access = access

    def intercept(
        self, parameters: Any, metadata: MetadataDict, target_call: FullyQualifiedIdentifier
    ) -> None:
        if not self.access.valid(metadata.get(ACCESS_TOKEN)):
            raise InvalidAccessToken(
                "send the daemon's token (its token file, or FXCELL_TOKEN) as the metadata "
                "AuthorizationService.AccessToken"
            )


@dataclass(slots=True)
class _Lock:
    identifier: str
    lease: str
    timeout: float  # s; 0: none
    last_used: float  # monotonic

    def expired(self, now: float) -> bool:
        return self.timeout > 0 and now - self.last_used > self.timeout


class CellLock(LockControllerBase):
    """``LockController`` mapped to the cell's control lease (see the module docstring)."""

    def __init__(
        self,
        parent_server: SilaServer,
        service: CellService,
        bridge: LoopBridge,
        protected: Callable[[], Affected],
    ) -> None:
        super().__init__(parent_server=parent_server)
        self.service = service
        self.bridge = bridge
        self._protected = protected
        self._lock: _Lock | None = None
        service.lease_keepers.append(self._keeps_alive)
        parent_server.add_metadata_interceptor(_LockCheck(self))

    # ------------------------------------------------------------- on the loop

    def _current(self) -> _Lock | None:
        """The lock if it still holds control (else it is forgotten, control released)."""
        lock = self._lock
        if lock is None:
            return None
        holder = self.service.control.holder
        if holder is None or holder.lease != lock.lease:
            self._lock = None  # taken over, or the lease ran out
            return None
        if lock.expired(time.monotonic()):
            self._lock = None
            self.service.control.release(lock.lease)
            return None
        return lock

    def _keeps_alive(self, holder: Holder) -> bool:
        lock = self._lock
        return (
            lock is not None and lock.lease == holder.lease and not lock.expired(time.monotonic())
        )

    async def _lock_server(self, identifier: str, seconds: float) -> None:
        if self._current() is not None:
            raise ServerAlreadyLocked("the server is locked by another SiLA client")
        try:
            holder = self.service.control.acquire(LOCK_CLIENT)
        except ControlHeldError as exc:
            raise ServerAlreadyLocked(f"ControlHeldError: {exc}") from None
        self._lock = _Lock(identifier, holder.lease, seconds, time.monotonic())

    async def _unlock_server(self, identifier: str) -> None:
        lock = self._current()
        if lock is None:
            raise ServerNotLocked
        if not hmac.compare_digest(identifier.encode(), lock.identifier.encode()):
            raise InvalidLockIdentifier
        self._lock = None
        self.service.control.release(lock.lease)

    async def _use(self, identifier: object) -> None:
        lock = self._current()
        if (
            lock is None
            or not isinstance(identifier, str)
            or not hmac.compare_digest(identifier.encode(), lock.identifier.encode())
        ):
            holder = self.service.control.describe()
            who = f" (control is held by {holder['client']!r})" if holder else ""
            raise InvalidLockIdentifier(f"the lock identifier is not the server's lock{who}")
        lock.last_used = time.monotonic()
        self.service.control.acquire(LOCK_CLIENT, lock.lease)  # renews the lease

    def lease_for(self, identifier: object) -> str | None:
        """The control lease of a call that carried the valid lock identifier (loop)."""
        lock = self._current()
        if lock is None or not isinstance(identifier, str):
            return None
        return (
            lock.lease
            if hmac.compare_digest(identifier.encode(), lock.identifier.encode())
            else None
        )

    # ------------------------------------------------------------- SiLA (gRPC threads)

    def get_IsLocked(self, *, metadata: MetadataDict) -> bool:
        async def locked() -> bool:
            self._current()
            return self.service.control.holder is not None

        return self.bridge.run(locked)

    def LockServer(
        self, LockIdentifier: str, Timeout: int, *, metadata: MetadataDict
    ) -> LockServer_Responses:
        self.bridge.run(lambda: self._lock_server(LockIdentifier, max(0, Timeout)))
        return LockServer_Responses()

    def UnlockServer(
        self, LockIdentifier: str, *, metadata: MetadataDict
    ) -> UnlockServer_Responses:
        self.bridge.run(lambda: self._unlock_server(LockIdentifier))
        return UnlockServer_Responses()

    def get_calls_affected_by_LockIdentifier(self) -> Affected:
        # Read on every call (gRPC thread): the lock identifier is needed only while locked.
        lock = self._lock
        if lock is None or lock.expired(time.monotonic()):
            return []
        return self._protected()

    def check(self, identifier: object) -> None:
        """Check and renew the lock for a call that carried ``identifier`` (gRPC thread)."""
        self.bridge.run(lambda: self._use(identifier))


class _LockCheck(MetadataInterceptor):
    def __init__(self, lock: CellLock) -> None:
        super().__init__([LOCK_IDENTIFIER])
        self.lock = lock

    def intercept(
        self, parameters: Any, metadata: MetadataDict, target_call: FullyQualifiedIdentifier
    ) -> None:
        self.lock.check(metadata.get(LOCK_IDENTIFIER))


def lock_identifier(metadata: MetadataDict) -> object:
    """The lock identifier a call carried (``None`` when it carried none or none was needed)."""
    return metadata.get(LOCK_IDENTIFIER)


class SilaCommands:
    """Cell commands for SiLA calls: control as described above, then one operation each
    (recorded, listed and cancellable like an HTTP client's)."""

    def __init__(self, service: CellService, lock: CellLock) -> None:
        self.service = service
        self.lock = lock

    async def run(self, name: str, args: Mapping[str, Any], identifier: object) -> Any:
        """Run command ``name`` of the command table (on the loop); its result."""
        command = get_command(name)
        lease: str | None = None
        took = False
        client = UNLOCKED_CLIENT
        if command.needs_control:
            given = self.lock.lease_for(identifier)
            client = LOCK_CLIENT if given is not None else UNLOCKED_CLIENT
            lease = self.service.control.acquire(client, given).lease
            took = given is None
        try:
            await self.service.wait_cell()
            op = self.service.start_operation(
                name, args, client, lambda: self.service.call(name, **args), lease=lease
            )
            # The operation is its own task: a SiLA client that goes away does not cancel it.
            await asyncio.shield(op.done.wait())
            if op.task.cancelled():
                raise MoveStoppedError(f"{name}() was cancelled ({op.id})")
            exc = op.task.exception()
            if exc is not None:
                raise exc
            return op.task.result()
        finally:
            if took and lease is not None:
                self.service.control.release(lease)

    async def with_control(self, identifier: object) -> tuple[str, bool, str]:
        """Take control for a job command: the lease, whether it was taken just for this
        command (release it after), and the client's name."""
        given = self.lock.lease_for(identifier)
        client = LOCK_CLIENT if given is not None else UNLOCKED_CLIENT
        lease = self.service.control.acquire(client, given).lease
        return lease, given is None, client
