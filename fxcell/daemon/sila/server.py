"""The daemon's SiLA 2 server (``fxcell daemon --sila``): the cell as a lab instrument.

One :class:`SilaCellServer` beside the HTTP API, over the same
:class:`~fxcell.daemon.service.CellService`: the same Cell, job, control lease, operations
and record. It is the reference ``sila2`` package's :class:`~sila2.server.SilaServer` with
these features (definitions in ``features/``, the standard ones from ``sila2``):

- ``SiLAService`` (name from ``daemon.sila.server_name``, the stable UUID of
  :mod:`~fxcell.daemon.sila.identity`), ``AuthorizationService`` (the daemon's token),
  ``LockController`` (the control lease: :mod:`~fxcell.daemon.sila.access`);
- ``CellController``, ``LabwareTransferManipulatorController``, ``SimulationController``
  (:mod:`~fxcell.daemon.sila.cell`); ``JobController``, ``ErrorRecoveryService``
  (:mod:`~fxcell.daemon.sila.job`).

TLS with the certificate of :mod:`~fxcell.daemon.sila.identity` unless ``daemon.sila.insecure``.
Discovery: the server is announced over zeroconf as ``<uuid>._sila._tcp.local.`` with its
certificate in the TXT record (as SiLA 2 specifies for self-signed ones), on the interface of
the daemon's address only (a daemon on loopback announces on loopback).

Starting, stopping and announcing block (gRPC, zeroconf's probing): they run in worker
threads. Observable properties are refreshed from the loop 20 times a second.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import socket
from typing import Any

from sila2.discovery.service_info import SilaServiceInfo
from sila2.features.authorizationservice import AuthorizationServiceFeature
from sila2.features.lockcontroller import LockControllerFeature
from sila2.framework import Command, Feature
from sila2.framework.abc.sila_error import SilaError
from sila2.server import SilaServer
from zeroconf import InterfaceChoice, IPVersion, Zeroconf

from fxcell._version import __version__
from fxcell.config import CellConfig
from fxcell.daemon.service import CellService
from fxcell.daemon.sila.access import AccessToken, Affected, CellLock, SilaCommands
from fxcell.daemon.sila.bridge import LoopBridge, load_feature
from fxcell.daemon.sila.cell import (
    CellController,
    LabwareTransferManipulatorController,
    SimulationController,
)
from fxcell.daemon.sila.identity import Identity, load_or_create
from fxcell.daemon.sila.job import ErrorRecoveryService, JobController, Recovery
from fxcell.errors import ConfigError

log = logging.getLogger(__name__)

SERVER_TYPE = "RobotCell"
VENDOR_URL = "https://fxcell.example/"
REFRESH_PERIOD = 0.05  # s between refreshes of the observable properties
FEATURE_FILES = (
    "CellController",
    "JobController",
    "ErrorRecoveryService",
    "SimulationController",
    "LabwareTransferManipulatorController",
)
UNPROTECTED = {("CellController", "Stop")}
"""Commands that need no lock: Stop needs only the token, as over HTTP."""


class SilaCellServer:
    """The SiLA 2 server of a daemon (see the module docstring)."""

    def __init__(self, service: CellService, config: CellConfig, token: str) -> None:
        self.service = service
        self.config = config
        self.token = token
        self.identity: Identity | None = None
        self.server: SilaServer | None = None
        self.cell: CellController | None = None
        self.job: JobController | None = None
        self._zeroconf: Zeroconf | None = None
        self._announced: SilaServiceInfo | None = None
        self._refresher: asyncio.Task[None] | None = None
        self._features: dict[str, Feature] = {}

    @property
    def address(self) -> str:
        return f"{self.config.daemon.host}:{self.config.daemon.sila.port}"

    async def start(self) -> None:
        """Build the server, listen, announce it; raises ConfigError when it cannot listen."""
        bridge = LoopBridge(asyncio.get_running_loop())
        self.identity = await asyncio.to_thread(load_or_create, self.config)
        self.server = await asyncio.to_thread(self._build, bridge, self.identity)
        await asyncio.to_thread(self._listen, self.server, self.identity)
        quiet = _QuietSila(set(self.server.features))
        for handler in logging.getLogger().handlers:
            handler.addFilter(quiet)
        self._refresher = asyncio.create_task(self._refresh(), name="fxcell sila properties")
        if self.config.daemon.sila.discovery:
            try:
                await asyncio.to_thread(self._announce, self.server, self.identity)
            except OSError as exc:  # no multicast on this interface: serve without discovery
                log.error("SiLA discovery not available on %s: %s", self.config.daemon.host, exc)

    def _build(self, bridge: LoopBridge, identity: Identity) -> SilaServer:
        sila = self.config.daemon.sila
        server = SilaServer(
            server_name=sila.server_name,
            server_type=SERVER_TYPE,
            server_description=(
                "fxcell robot cell: a UR3e arm with a Robotiq Hand-E gripper preparing XRF "
                "samples (crucibles, fusion machine, beads)"
            ),
            server_version=__version__,
            server_vendor_url=VENDOR_URL,
            server_uuid=identity.server_uuid,
            max_grpc_workers=32,
            max_child_task_workers=32,
        )
        features = {name: load_feature(name) for name in FEATURE_FILES}
        self._features = features
        service = self.service
        lock = CellLock(server, service, bridge, self._protected)
        commands = SilaCommands(service, lock)
        recovery = Recovery()
        self.cell = CellController(server, features["CellController"], bridge, commands, service)
        self.job = JobController(
            server, features["JobController"], bridge, commands, service, recovery
        )
        server.set_feature_implementation(
            AuthorizationServiceFeature, AccessToken(server, self.token)
        )
        server.set_feature_implementation(LockControllerFeature, lock)
        server.set_feature_implementation(features["CellController"], self.cell)
        server.set_feature_implementation(features["JobController"], self.job)
        server.set_feature_implementation(
            features["ErrorRecoveryService"],
            ErrorRecoveryService(
                server, features["ErrorRecoveryService"], bridge, commands, service, recovery
            ),
        )
        server.set_feature_implementation(
            features["SimulationController"],
            SimulationController(
                server, features["SimulationController"], self.config.robot.host is None
            ),
        )
        server.set_feature_implementation(
            features["LabwareTransferManipulatorController"],
            LabwareTransferManipulatorController(
                server,
                features["LabwareTransferManipulatorController"],
                bridge,
                commands,
                service,
            ),
        )
        return server

    def _protected(self) -> Affected:
        """Every command that needs the lock while the server is locked."""
        protected: Affected = []
        for name, feature in self._features.items():
            commands: dict[str, Command] = {
                **feature._unobservable_commands,
                **feature._observable_commands,
            }
            protected += [
                command for ident, command in commands.items() if (name, ident) not in UNPROTECTED
            ]
        return protected

    def _listen(self, server: SilaServer, identity: Identity) -> None:
        sila = self.config.daemon.sila
        host = self.config.daemon.host
        try:
            if sila.insecure:
                log.warning(
                    "SiLA 2 server without encryption (daemon.sila.insecure): development only"
                )
                server.start_insecure(host, sila.port, enable_discovery=False)
            else:
                server.start(
                    host,
                    sila.port,
                    private_key=identity.private_key,
                    cert_chain=identity.certificate,
                    enable_discovery=False,
                )
        except RuntimeError as exc:
            raise ConfigError(f"daemon.sila: cannot listen on {self.address}: {exc}") from None

    def _announce(self, server: SilaServer, identity: Identity) -> None:
        host = self.config.daemon.host
        unspecified = _unspecified(host)
        interfaces: Any = InterfaceChoice.All if unspecified else [host]
        version = IPVersion.V6Only if ":" in host else IPVersion.V4Only
        zeroconf = Zeroconf(interfaces=interfaces, ip_version=version)
        ca = None if self.config.daemon.sila.insecure else identity.certificate
        info = SilaServiceInfo(
            server, socket.gethostname() if unspecified else host, self.config.daemon.sila.port, ca
        )
        try:
            zeroconf.register_service(info)
        except BaseException:
            zeroconf.close()
            raise
        self._zeroconf, self._announced = zeroconf, info

    async def _refresh(self) -> None:
        while True:
            for feature in (self.cell, self.job):
                if feature is not None:
                    try:
                        feature.refresh()
                    except Exception:  # a broken refresh must not stop the others
                        log.exception("SiLA property refresh failed")
            await asyncio.sleep(REFRESH_PERIOD)

    async def stop(self, within: float = 1.0) -> None:
        """Stop serving: calls in flight end, subscriptions close, the announcement goes."""
        if self._refresher is not None:
            self._refresher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._refresher
        if self.job is not None:
            self.job.close()
        server, self.server = self.server, None
        if server is None:
            return
        stopping = asyncio.ensure_future(asyncio.to_thread(self._stop, server, within))
        done, _ = await asyncio.wait({stopping}, timeout=within + 0.5)
        if not done:
            log.error("the SiLA server did not stop within %.1f s", within + 0.5)

    def _stop(self, server: SilaServer, within: float) -> None:
        zeroconf, info = self._zeroconf, self._announced
        self._zeroconf = self._announced = None
        if zeroconf is not None:
            with contextlib.suppress(Exception):
                if info is not None:
                    zeroconf.unregister_service(info)
            zeroconf.close()
        if server.running:
            server.stop(grace_period=within / 2)


class _QuietSila(logging.Filter):
    """Keeps the ``sila2`` package's chatter out of the daemon's log: its per-call INFO
    records, and the traceback it logs for every error answered to a client (a refused
    command is the client's to handle; the daemon records its operations anyway)."""

    PREFIXES = ("sila2", "SubscriptionManagerThread[", "observable-command-manager-")

    def __init__(self, features: set[str]) -> None:
        super().__init__()
        self.features = features

    def filter(self, record: logging.LogRecord) -> bool:
        name = record.name
        if not (name.startswith(self.PREFIXES) or name in self.features):
            return True
        if record.levelno < logging.WARNING:
            return False
        exc = record.exc_info[1] if record.exc_info else None
        if exc is None:  # "Raising exception as RpcError", logged with no exception at hand
            return record.levelno > logging.ERROR or "RpcError" not in record.getMessage()
        return not isinstance(exc, SilaError)


def _unspecified(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_unspecified
    except ValueError:
        return False
