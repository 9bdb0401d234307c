"""The asyncio side of the robot link: spawns, supervises and talks to the link process.

:class:`LinkClient` starts ``fxcell.link.process`` with one end of a socketpair,
reads its framed messages (500 Hz state samples, replies, trajectory reports) and
restarts it with exponential backoff whenever it exits or cannot connect (and kills it
first when a call goes unanswered past its time: its one call worker is stuck). The link
counts as *up* while state samples arrive; it goes down when the process exits (at once),
when the process's own pulses say it has had no state sample for 100 ms (the controller
is gone), or when the process has sent nothing at all for 300 ms (it hangs). Judging the
state stream by the link process's clock keeps a busy event loop, which reads the
samples late, from ever taking a healthy link for a dead one.

While a trajectory runs, a thread of this process that never waits for the GIL beats every
10 ms on a channel of its own (:mod:`fxcell.link.beats`); the link process brakes the
trajectory to rest by itself when the beats stop (see :mod:`fxcell.link.process`). The
thread beats only while the event loop has run within LOOP_STALL_AFTER, so a frozen or
hung process is caught within the beat timeout (100 ms) and a stalled loop within
LOOP_STALL_AFTER, while a loop that is merely late on a busy machine never brakes a healthy
move. A link that goes down with a trajectory running is told to brake at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import itertools
import logging
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fxcell.errors import (
    ConnectionLostError,
    FxcellError,
    InvalidArgumentError,
    LinkContractError,
    RobotLinkError,
    RobotTimeoutError,
)
from fxcell.link import collector, wire
from fxcell.link.beats import BEAT_PERIOD, Beats
from fxcell.link.contract import (
    STATE_STOPS,
    WIRE_VERSION,
    ControlMode,
    Dashboard,
    Guard,
    LeaveServo,
    LinkStatus,
    OutputGroup,
    ReplaceTrajectory,
    Request,
    ServoStop,
    SetOutput,
    SetTool,
    StartControl,
    StartTrajectory,
    StopControl,
    StopReason,
    StopTrajectory,
    TeachMode,
    TrajectoryProgress,
    TrajectoryResult,
    counts_as_sent,
    reply_error,
    stop_reason,
)
from fxcell.link.dashboard import DashboardOperations
from fxcell.link.realtime import LINK_PRIORITY, Scheduling
from fxcell.link.subscription import StateSubscription
from fxcell.protocol import URCAP_SCRIPT_PORT, RobotState

if TYPE_CHECKING:
    from fxcell.calibration import Calibration
    from fxcell.config import RobotConfig

log = logging.getLogger(__name__)

STALE_AFTER = 0.1
"""Seconds without a state sample (by the link process's clock) after which the link
counts as down."""
MUTE_AFTER = 0.3
"""Seconds without any message from the link process after which the link counts as down."""
BEAT_PRIORITY_BELOW = 5
"""The beat thread's SCHED_FIFO priority is the link process's less this (where permitted)."""
WATCHDOG_LATE = 0.1
"""Seconds beyond which the watchdog's wake-up counts as late (its sleeps are ≤ 50 ms)."""
GAP_REPORT = 0.02
"""A pause of the state stream longer than this (controller time, s) is logged as a gap."""
STUCK_BRAKE_WITHIN = 3.0
"""Seconds the running trajectories get to brake along their paths before a link process
whose call worker is stuck is restarted (the longest stop under the braking limits)."""
HOLD_STALE_AFTER = 8.0
"""The same while the link process runs a blocking ur_rtde constructor."""
SELF_BRAKES = frozenset({"state_stalled", "cell_silent"})
"""End reasons of a trajectory the link process braked on its own guard (a fault: logged)."""
RESTART_AFTER = 3.0
"""Seconds of silence after which a live but mute link process is killed and restarted."""
EXPLAIN_SAMPLES = 25
"""State samples a trajectory that failed on the robot's side waits for the one showing why."""
EXPLAIN_WITHIN = 0.1
"""Seconds the same waits at most (the state stream may be down)."""
_STATE_FAILURES = STATE_STOPS | {StopReason.SERVOJ_REFUSED}
"""Failed ends the client holds until a state sample shows why (see _handle_trajectory)."""

__all__ = [
    "LinkClient",
    "LinkStatus",
    "StateSubscription",
    "TrajectoryHandle",
    "TrajectoryProgress",
    "TrajectoryResult",
    "process_link",
]


@dataclass
class TrajectoryHandle:
    """A trajectory the link process is streaming with servoJ at 500 Hz."""

    id: int
    total: int
    _link: LinkClient
    _done: asyncio.Future[TrajectoryResult]
    _replaced: asyncio.Queue[bool] = field(default_factory=asyncio.Queue)
    progress: TrajectoryProgress | None = None
    _progress_event: asyncio.Event = field(default_factory=asyncio.Event)
    _holds_collector: bool = False

    @property
    def done(self) -> bool:
        return self._done.done()

    def _end(self, result: TrajectoryResult | None) -> None:
        """Settle the trajectory (``None``: it never started) and end its collector hold."""
        if not self._done.done():
            if result is None:
                self._done.cancel()
            else:
                self._done.set_result(result)
        if self._holds_collector:
            self._holds_collector = False
            collector.release()

    async def replace_remaining(self, samples: ArrayLike, at_index: int | None = None) -> bool:
        """Replace every sample not yet sent (e.g. by a braking profile).

        With ``at_index``, ``samples[0]`` replaces the trajectory's sample ``at_index``
        and the samples before it are still sent (if the link is already past it, it
        joins ``samples`` at the matching offset). Returns False when the trajectory had
        already ended.
        """
        array = _check_samples(samples)
        if self.done:
            return False
        at = None if at_index is None else int(at_index)
        self._link._send(
            wire.TRAJ_REPLACE, ReplaceTrajectory(self.id, wire.pack_samples(array), at)
        )
        getter = asyncio.ensure_future(self._replaced.get())
        try:
            waitables: set[asyncio.Future[Any]] = {getter, self._done}
            finished, _ = await asyncio.wait(
                waitables, timeout=1.0, return_when=asyncio.FIRST_COMPLETED
            )
        finally:
            getter.cancel()
        if getter in finished and not getter.cancelled():
            return getter.result()
        return False

    async def stop(self, reason: StopReason = StopReason.STOP_REQUESTED) -> TrajectoryResult:
        """Brake to rest along the path now (the link process does it by itself, even
        with the state stream down) and wait for the end report."""
        if not self.done:
            self._link._send_safety(
                wire.TRAJ_STOP, StopTrajectory(self.id, StopReason(reason).value)
            )
        return await self.wait()

    async def wait(self) -> TrajectoryResult:
        """Wait for the end: completed, stopped or failed (never raises for those)."""
        return await asyncio.shield(self._done)

    async def next_progress(self) -> TrajectoryProgress | None:
        """Wait for the next progress report (``None`` once the trajectory ended)."""
        self._progress_event.clear()
        waiter = asyncio.ensure_future(self._progress_event.wait())
        try:
            waitables: set[asyncio.Future[Any]] = {waiter, self._done}
            await asyncio.wait(waitables, return_when=asyncio.FIRST_COMPLETED)
        finally:
            waiter.cancel()
        return None if self.done else self.progress


def _check_samples(samples: ArrayLike) -> NDArray[np.float64]:
    array = np.asarray(samples, dtype=float)
    if array.ndim != 2 or array.shape[1] != 6 or len(array) == 0:
        raise InvalidArgumentError(f"trajectory samples must be (N, 6), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidArgumentError("trajectory samples must be finite")
    return np.ascontiguousarray(array)


class _LinkProtocol(asyncio.Protocol):
    """Splits the link socket's bytes into frames and hands each message on.

    A protocol rather than a StreamReader: one wake-up parses every buffered frame,
    which keeps the 500 Hz stream cheap for the event loop.
    """

    def __init__(self, handle: Callable[[tuple[Any, ...]], None]) -> None:
        self._handle = handle
        self._buffer = bytearray()
        loop = asyncio.get_running_loop()
        self.first_state: asyncio.Future[None] = loop.create_future()
        self.closed: asyncio.Future[None] = loop.create_future()
        self.error: str | None = None

    def data_received(self, data: bytes) -> None:
        buf = self._buffer
        buf += data
        offset = 0
        header = wire.HEADER
        try:
            while len(buf) - offset >= header.size:
                (size,) = header.unpack_from(buf, offset)
                if size > wire.MAX_FRAME:
                    raise ValueError(f"oversized link frame ({size} bytes)")
                end = offset + header.size + size
                if len(buf) < end:
                    break
                message = wire.decode(bytes(buf[offset + header.size : end]))
                offset = end
                if message[0] == wire.STATE and not self.first_state.done():
                    self.first_state.set_result(None)
                try:
                    self._handle(message)
                except Exception:  # a broken callback must not drop the link
                    log.exception("robot link: handling %r failed", message[0])
        except Exception as exc:  # a corrupt stream: drop the link, it restarts
            self.error = f"bad link message: {exc}"
            log.exception("robot link: bad message")
            if not self.closed.done():
                self.closed.set_result(None)
        del buf[:offset]

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(None)


class LinkClient(DashboardOperations):
    """Asyncio client of a supervised robot-link process for one UR controller.

    ``receiver``: ``stream`` (default) reads every RTDE sample with fxcell's own reader;
    ``ur_rtde`` polls ``RTDEReceiveInterface`` (which keeps only the newest sample).
    ``control_mode`` and ``urcap_program``: how ``enable_control`` starts external
    control (the UR's ``script`` upload or ``urcap`` program); the contract's controller
    operations are the Dashboard's (:class:`~fxcell.link.dashboard.DashboardOperations`).

    ``on_state`` is called for every sample, ``on_status`` when the link goes up or
    down and ``on_control`` when external control starts or ends (all synchronous).
    """

    def __init__(
        self,
        host: str,
        *,
        frequency: float = 500.0,
        connect_timeout: float = 10.0,
        backoff_max: float = 5.0,
        urcap_port: int = URCAP_SCRIPT_PORT,
        receiver: Literal["stream", "ur_rtde"] = "stream",
        realtime_priority: int = LINK_PRIORITY,
        control_mode: ControlMode = "script",
        urcap_program: str = "external_control.urp",
        on_state: Callable[[RobotState], None] | None = None,
        on_status: Callable[[LinkStatus, str], None] | None = None,
        on_control: Callable[[bool, str], None] | None = None,
    ) -> None:
        self.host = host
        self.control_mode = control_mode
        self.urcap_program = urcap_program
        self.frequency = frequency
        self.connect_timeout = connect_timeout
        self.backoff_max = backoff_max
        self.urcap_port = urcap_port
        self.receiver = receiver
        self.realtime_priority = realtime_priority
        self._on_state = on_state
        self._on_status = on_status
        self._on_control = on_control
        self.status = LinkStatus.STARTING
        self.latest: RobotState | None = None
        self.control_ready = False
        self.pid: int | None = None
        self.restarts = 0
        self.messages_sent = 0
        """Requests sent to the link process (calls and trajectory messages; see
        :func:`~fxcell.link.contract.counts_as_sent`)."""
        self.last_failure = ""
        self._subscriptions: set[StateSubscription] = set()
        self._writer: asyncio.Transport | None = None
        self._process: subprocess.Popen[bytes] | None = None
        self._supervisor: asyncio.Task[None] | None = None
        self._pending: dict[int, asyncio.Future[Any]] = {}
        self._trajectories: dict[int, TrajectoryHandle] = {}
        """Running trajectories; :meth:`_trajectories_changed` after every change."""
        self._beats: Beats | None = None
        # failed ends waiting for the state sample that explains them (see _handle_trajectory)
        self._unexplained: list[tuple[TrajectoryHandle, TrajectoryResult, int]] = []
        self._ids = itertools.count(1)
        self._restarting: asyncio.Task[None] | None = None  # see _worker_stuck
        self._hold = False
        self._last_sample = 0.0
        self._last_message = 0.0  # time.monotonic() of the newest message of any kind
        self._link_fresh = 0.0  # time.monotonic() (system-wide) of the link's newest sample
        self._link_said = 0.0  # time.monotonic() of the link process's newest pulse
        self._last_timestamp: float | None = None  # controller time of the newest sample
        self._loop_ran = 0.0  # time.monotonic() when the event loop last ran the beat task
        self.scheduling: Scheduling | None = None
        """How the link process is scheduled (SCHED_FIFO where permitted), once it said so."""
        self.gaps = 0
        """State-stream gaps seen (each logged as a warning, so recorded in the MCAP /log)."""
        self._status_changed = asyncio.Event()
        self._closing = False
        self.contract_error: LinkContractError | None = None
        """Set when the link process speaks another wire version: the link is refused."""

    # -- life cycle

    async def start(self, wait: bool = True) -> None:
        """Start the supervisor; with ``wait`` return once the link is up (or raise)."""
        if self._supervisor is None:
            self._supervisor = asyncio.create_task(self._supervise(), name=f"link {self.host}")
        if wait:
            await self.wait_up(self.connect_timeout)

    async def wait_up(self, within: float) -> None:
        try:
            async with asyncio.timeout(within):
                while self.status is not LinkStatus.UP:
                    if self.contract_error is not None:
                        raise self.contract_error
                    if self.status is LinkStatus.CLOSED:
                        raise ConnectionLostError("the robot link is closed")
                    self._status_changed.clear()
                    await self._status_changed.wait()
        except TimeoutError:
            raise RobotLinkError(
                f"no robot link to {self.host} within {within:g} s",
                {"link": self.last_failure} if self.last_failure else None,
            ) from None

    async def close(self) -> None:
        """Stop the supervisor and the link process."""
        if self.status is LinkStatus.UP and not self._closing:
            # the link may still hold servo mode after the last move (for a next one):
            # leave it while the process can, not by killing it
            with contextlib.suppress(FxcellError):
                await self._request(LeaveServo(), 0.5)
        self._closing = True
        if self._restarting is not None:
            self._restarting.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._restarting
        if self._supervisor is not None:
            self._supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._supervisor
            self._supervisor = None
        await self._kill()
        self._fail_all("closed")
        self._set_status(LinkStatus.CLOSED, "closed")

    async def __aenter__(self) -> LinkClient:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def kill_process(self) -> None:
        """Kill the link process abruptly (the supervisor starts a fresh one): for a process
        whose call worker is stuck, and for tests and benchmarks of the supervision."""
        if self._process is not None and self._process.poll() is None:
            self._process.kill()

    # -- status

    def _set_status(self, status: LinkStatus, reason: str) -> None:
        if status is self.status:
            return
        if status is LinkStatus.DOWN and self.status is LinkStatus.UP:
            log.warning("robot link to %s down: %s", self.host, reason)
        self.status = status
        if status is not LinkStatus.UP:
            self.latest = None
            if self.control_ready:
                self.control_ready = False
                if self._on_control is not None:
                    self._on_control(False, reason)
        self._status_changed.set()
        if self._on_status is not None:
            self._on_status(status, reason)

    @property
    def last_sample_time(self) -> float:
        """``time.monotonic()`` when the newest state sample arrived."""
        return self._last_sample

    @property
    def up(self) -> bool:
        return self.status is LinkStatus.UP

    # -- supervision

    async def _supervise(self) -> None:
        backoff = 0.05
        while True:
            started = time.monotonic()
            try:
                await self._run_once()
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # keep supervising whatever happened
                self.last_failure = f"{type(exc).__name__}: {exc}"
                log.warning("robot link to %s failed: %s", self.host, self.last_failure)
            await self._kill()
            self._fail_all(self.last_failure or "link process exited")
            self._set_status(LinkStatus.DOWN, self.last_failure or "link process exited")
            if self.contract_error is not None:
                return  # a process of another version: restarting would not help
            if time.monotonic() - started > 5.0:
                backoff = 0.05
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, self.backoff_max)
            self.restarts += 1

    async def _run_once(self) -> None:
        parent, child = socket.socketpair()
        beats, beats_child = socket.socketpair()
        try:
            # Plain Popen, reaped in _kill: the link's death is seen on the socket, so no
            # asyncio child watcher is needed. Forking from a thread keeps the loop free.
            spawn = asyncio.ensure_future(
                asyncio.to_thread(
                    subprocess.Popen,
                    [
                        sys.executable,
                        "-m",
                        "fxcell.link.process",
                        "--fd",
                        str(child.fileno()),
                        "--host",
                        self.host,
                        "--frequency",
                        str(self.frequency),
                        "--urcap-port",
                        str(self.urcap_port),
                        "--receiver",
                        self.receiver,
                        "--beat-fd",
                        str(beats_child.fileno()),
                        "--rt-priority",
                        str(self.realtime_priority),
                    ],
                    pass_fds=(child.fileno(), beats_child.fileno()),
                    stdin=subprocess.DEVNULL,
                    # its own process group: a Ctrl-C in the terminal reaches only the
                    # owner, which brakes the arm and then stops the link itself
                    process_group=0,
                )
            )
            try:
                self._process = await asyncio.shield(spawn)
            except asyncio.CancelledError:
                # cancelled while forking: the thread still starts the process; end it
                process = await spawn
                process.kill()
                await asyncio.to_thread(process.wait, 5.0)
                raise
            self.pid = self._process.pid
            loop = asyncio.get_running_loop()
            protocol = _LinkProtocol(self._handle)
            transport, _ = await loop.create_connection(lambda: protocol, sock=parent)
        except BaseException:
            parent.close()  # cancelled or failed before the transport took it over
            beats.close()
            raise
        finally:
            child.close()
            beats_child.close()
        self._writer = transport
        self._hold = False  # the watchdog starts with the first sample (status UP)
        self._last_sample = self._last_message = self._link_fresh = time.monotonic()
        self._last_timestamp = None
        watchdog = asyncio.create_task(self._watchdog(), name="link watchdog")
        # just below the link process where permitted: a link process that keeps its 2 ms
        # while the beats wait for a CPU would take a busy machine for a frozen cell
        priority = self.realtime_priority
        below = max(1, priority - BEAT_PRIORITY_BELOW) if priority > 0 else 0
        beater = Beats(beats, priority=below)
        self._beats = beater
        self._trajectories_changed()
        beat = asyncio.create_task(self._beat(beater), name="link beat")
        try:
            try:
                async with asyncio.timeout(self.connect_timeout):
                    await asyncio.wait(
                        {protocol.first_state, protocol.closed},
                        return_when=asyncio.FIRST_COMPLETED,
                    )
            except TimeoutError:
                self.last_failure = f"no state from {self.host} within {self.connect_timeout:g} s"
                return
            await protocol.closed
            if protocol.error is not None:
                self.last_failure = protocol.error
            elif not self.last_failure:
                self.last_failure = "link process exited"
        finally:
            for task in (watchdog, beat):
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            self._beats = None
            beater.close()
            transport.close()
            self._writer = None

    async def _watchdog(self) -> None:
        """Mark the link down when the controller or the link process has gone silent.

        The state stream is judged by the link process's pulses (its own clock): a pulse
        saying its newest sample is STALE_AFTER old means the controller stopped sending.
        Silence of the process itself for MUTE_AFTER means it hangs (a process frozen right
        after a pulse is not a silent controller). A loop that runs late
        reads everything that arrived meanwhile before this task runs again, so it never
        mistakes its own lateness for a dead link.
        """
        ran = time.monotonic()
        while True:
            now = time.monotonic()
            if now - ran > WATCHDOG_LATE:
                # This task waited behind a callback that held the loop up (it may be
                # queued right after it, before the loop polls the socket again): read
                # what arrived meanwhile first, then judge.
                ran = now
                await asyncio.sleep(0.001)
                continue
            ran = now
            silent = now - self._last_sample
            if self.status is not LinkStatus.UP:
                if self.status is LinkStatus.DOWN and silent > RESTART_AFTER and not self._hold:
                    # alive but mute for longer than ur_rtde's own session timeout: the
                    # process is stuck; kill it and let the supervisor start a fresh one
                    log.warning(
                        "robot link to %s mute for %.1f s: restarting it", self.host, silent
                    )
                    self.kill_process()
                    self._last_sample = time.monotonic()
                await asyncio.sleep(0.05)
                continue
            if self._hold:
                if silent >= HOLD_STALE_AFTER:
                    self._down(f"no robot state for {silent:.1f} s")
                await asyncio.sleep(0.05)
                continue
            # The link process's clock is this one (CLOCK_MONOTONIC is system-wide): its
            # newest pulse tells how old the state stream was when it last spoke. Only its
            # own word counts: a process that stopped talking (a ur_rtde call holding its
            # GIL) says nothing of the controller, and gets MUTE_AFTER.
            mute = now - self._last_message
            said = self._link_said - max(self._link_fresh, self._last_sample)
            if said >= STALE_AFTER:
                self._down(f"no robot state for {said * 1000:.0f} ms")
            elif mute >= MUTE_AFTER:
                self._down(f"the link process has been silent for {mute * 1000:.0f} ms")
            else:
                await asyncio.sleep(0.005)

    def _down(self, reason: str) -> None:
        """The link is down: brake every running trajectory, then say so."""
        for traj_id, handle in list(self._trajectories.items()):
            if not handle.done:
                self._send_safety(
                    wire.TRAJ_STOP, StopTrajectory(traj_id, StopReason.LINK_DOWN.value)
                )
        self._set_status(LinkStatus.DOWN, reason)

    @staticmethod
    async def _beat(beats: Beats) -> None:
        """Say every BEAT_PERIOD that the event loop runs (the beat thread reads it)."""
        while True:
            beats.loop_ran()
            await asyncio.sleep(BEAT_PERIOD)

    def _trajectories_changed(self) -> None:
        """Beat while a trajectory runs, and only then."""
        if self._beats is not None:
            self._beats.set_running(bool(self._trajectories))

    async def _kill(self) -> None:
        process, self._process = self._process, None
        if process is None:
            return
        if process.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                process.kill()
            with contextlib.suppress(Exception):
                await asyncio.to_thread(process.wait, 5.0)

    def _fail_all(self, reason: str) -> None:
        error = ConnectionLostError(f"robot link lost: {reason}")
        self._release_ends(force=True)
        for future in self._pending.values():
            if not future.done():
                future.set_exception(error)
        self._pending.clear()
        for handle in list(self._trajectories.values()):
            handle._end(
                TrajectoryResult(
                    "failed",
                    StopReason.LINK_LOST,
                    handle.progress.index if handle.progress else 0,
                    handle.total,
                    None,
                    0.0,
                )
            )
        self._trajectories.clear()
        self._trajectories_changed()

    # -- incoming

    def _handle(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        now = time.monotonic()
        self._last_message = now
        if kind == wire.STATE:
            state = wire.state_from_tuple(message[1], now)
            self._last_sample = now
            previous, self._last_timestamp = self._last_timestamp, state.timestamp
            if previous is not None and state.timestamp - previous > GAP_REPORT:
                self.gaps += 1
                log.warning(
                    "robot state stream gap of %.0f ms (controller time %.3f to %.3f s)",
                    (state.timestamp - previous) * 1000,
                    previous,
                    state.timestamp,
                )
            self.latest = state
            if self.status is not LinkStatus.UP:
                self.last_failure = ""
                self._set_status(LinkStatus.UP, "state stream live")
            if self._on_state is not None:
                self._on_state(state)
            for sub in tuple(self._subscriptions):
                sub.offer(state)
            if self._unexplained:
                self._release_ends(stop_reason(state.safety_mode, state.runtime_state))
        elif kind == wire.REPLY:
            _, request_id, ok, value = message
            future = self._pending.pop(request_id, None)
            if future is not None and not future.done():
                if ok:
                    future.set_result(value)
                else:
                    error_kind, text = value
                    future.set_exception(reply_error(error_kind, text))
        elif kind == wire.TRAJ:
            self._handle_trajectory(message[1], message[2], message[3])
        elif kind == wire.CONTROL:
            _, ready, reason = message
            self.control_ready = bool(ready)
            if self._on_control is not None:
                self._on_control(self.control_ready, str(reason))
        elif kind == wire.PULSE:
            _, link_now, last_state_at = message
            self._link_fresh = max(self._link_fresh, last_state_at)
            self._link_said = max(self._link_said, link_now)
        elif kind == wire.HOLD:
            self._hold = bool(message[1])
            self._last_sample = self._link_fresh = time.monotonic()
        elif kind == wire.FATAL:
            _, text, failures = message
            self.last_failure = str(RobotLinkError(text, failures))
        elif kind == wire.LOG:
            log.log(int(message[1]), "link: %s", message[2])
        elif kind == wire.HELLO:
            self._hello(message[1])
        elif kind == wire.CONNECTED:
            pass  # the process reached the controller; its first state sample brings it up
        else:
            log.warning("robot link: unknown message %r refused", kind)

    def _hello(self, data: dict[str, Any]) -> None:
        version = data.get("wire")
        if version != WIRE_VERSION:
            # the link process is another install's: nothing it says can be trusted
            self.contract_error = LinkContractError(
                f"the robot-link process speaks wire version {version}, this client "
                f"{WIRE_VERSION} (a half-updated install? reinstall fxcell)"
            )
            self.last_failure = str(self.contract_error)
            log.error("robot link refused: %s", self.last_failure)
            self._status_changed.set()
            self.kill_process()
            return
        info = data.get("scheduling")
        if not isinstance(info, dict):
            return
        first = self.scheduling is None
        self.scheduling = Scheduling(**info)
        if first and not self.scheduling.realtime:
            log.warning(
                "robot link process without real-time scheduling: %s (see the real-robot "
                "guide: LimitRTPRIO)",
                self.scheduling.detail,
            )

    def _handle_trajectory(self, traj_id: int, kind: str, data: dict[str, Any]) -> None:
        if kind == "end" and data["status"] == "stopped" and data["reason"] in SELF_BRAKES:
            # a fault whoever still waits for the trajectory (the link may be down already)
            log.warning("robot link to %s braked a move by itself: %s", self.host, data["reason"])
        handle = self._trajectories.get(traj_id)
        if handle is None:
            return
        if kind == "progress":
            handle.progress = TrajectoryProgress(
                data["index"],
                data["total"],
                data["actual_q"],
                data["tracking_error"],
                time.time(),
                data.get("timestamp"),
            )
            handle._progress_event.set()
        elif kind == "replaced":
            handle._replaced.put_nowait(bool(data.get("ok")))
        elif kind == "end":
            self._trajectories.pop(traj_id, None)
            self._trajectories_changed()
            result = TrajectoryResult(
                data["status"],
                StopReason(data["reason"]),
                data["index"],
                data["total"],
                data["actual_q"],
                data["duration"],
                data.get("detail", ""),
            )
            latest = self.latest
            shown = latest is not None and stop_reason(latest.safety_mode, latest.runtime_state)
            if result.status == "failed" and result.reason in _STATE_FAILURES and not shown:
                # The robot refused the stream (a program or safety stop) and the link
                # process told us before the sample showing the stop arrived: end the
                # trajectory after that sample, so that its owner (the Cell) has seen
                # the stop and aborts the move with the stop's own error.
                self._unexplained.append((handle, result, EXPLAIN_SAMPLES))
                asyncio.get_running_loop().call_later(
                    EXPLAIN_WITHIN, functools.partial(self._release_ends, force=True)
                )
            else:
                handle._end(result)

    def _release_ends(self, why: StopReason | None = None, *, force: bool = False) -> None:
        """End the held failed trajectories: all of them when a sample showed the stop
        (``why``, which then names a refused servoJ's cause) or when ``force``d, else
        those that waited long enough."""
        waiting = []
        for handle, result, samples in self._unexplained:
            if why is not None and result.reason is StopReason.SERVOJ_REFUSED:
                result = dataclasses.replace(result, reason=why)
            if why is not None or force or samples <= 1:
                handle._end(result)
            else:
                waiting.append((handle, result, samples - 1))
        self._unexplained = waiting

    # -- outgoing

    def _send(self, *message: Any, counted: bool = True) -> None:
        if self._writer is None or self.status is not LinkStatus.UP:
            raise ConnectionLostError(f"no robot link to {self.host} ({self.status.value})")
        self._writer.write(wire.encode(message))
        self.messages_sent += counted

    def _send_safety(self, *message: Any) -> bool:
        """Send a stop or a beat whenever the process is there, up or down (never raises)."""
        if self._writer is None or self._writer.is_closing():
            return False
        self._writer.write(wire.encode(message))
        return True

    async def _request(self, request: Request, within: float) -> Any:
        """Run ``request`` in the link process; typed fxcell errors on failure."""
        request_id = next(self._ids)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending[request_id] = future
        try:
            self._send(wire.CALL, request_id, request, counted=counts_as_sent(request))
            async with asyncio.timeout(within):
                return await future
        except TimeoutError:
            self._worker_stuck(type(request).__name__, within)
            raise RobotTimeoutError(
                f"robot link request {type(request).__name__} timed out after {within:g} s"
            ) from None
        finally:
            self._pending.pop(request_id, None)

    def _worker_stuck(self, what: str, within: float) -> None:
        """A request unanswered past its time: the link process's one call worker is still
        in it, and every call after it would wait too. It waits on a controller that does
        not answer (ur_rtde waits up to 300 s for its control script to finish a command),
        and only a fresh process gets out of that: brake what runs, then restart it."""
        pid = self.pid
        if pid is None or self._closing or (self._restarting and not self._restarting.done()):
            return
        log.warning(
            "robot link to %s: request %s unanswered after %g s; restarting the link process "
            "(its call worker is stuck)",
            self.host,
            what,
            within,
        )
        self._restarting = asyncio.create_task(
            self._restart_stuck(pid, f"request {what} unanswered after {within:g} s"),
            name=f"link {self.host} restart",
        )

    async def _restart_stuck(self, pid: int, reason: str) -> None:
        """Brake the running trajectories (their thread is not the stuck one), wait up to
        STUCK_BRAKE_WITHIN for them to end, then kill process ``pid`` if it still serves:
        the supervisor starts a fresh one and the cell restores control as after any loss."""
        running = [handle for handle in self._trajectories.values() if not handle.done]
        for handle in running:
            self._send_safety(wire.TRAJ_STOP, StopTrajectory(handle.id, StopReason.LINK_DOWN.value))
        if running:
            ends = [asyncio.shield(handle._done) for handle in running]
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(STUCK_BRAKE_WITHIN):
                    await asyncio.wait(ends)
            for end in ends:
                end.cancel()
        if self.pid == pid:
            self.last_failure = reason
            self.kill_process()

    def _requests_sent(self) -> int:
        return self.messages_sent

    async def dashboard(self, command: str, within: float = 5.0) -> str:
        """Send one Dashboard request line; returns the reply line (UR only: outside the
        link contract, whose operations :class:`DashboardOperations` maps onto it)."""
        return str(await self._request(Dashboard(command), within))

    async def read_calibration(self) -> Calibration:
        """The arm's calibration from the controller's primary interface (port 30001), read
        in a thread; CalibrationError when it cannot be read within 3 s."""
        from fxcell.link.primary import read_calibration

        return await asyncio.to_thread(read_calibration, self.host)

    async def start_control(self, mode: ControlMode, program: str, within: float) -> None:
        """Start external control: ``script`` upload or ``urcap`` program."""
        await self._request(StartControl(mode, program, within), within + 10.0)

    async def stop_control(self, mode: ControlMode, within: float = 5.0) -> None:
        await self._request(StopControl(mode), within)

    async def set_output(
        self, group: OutputGroup, index: int, value: float, within: float = 5.0
    ) -> bool:
        return bool(await self._request(SetOutput(group, int(index), float(value)), within))

    async def set_tool(
        self,
        tcp: tuple[float, ...],
        mass: float,
        cog: tuple[float, float, float],
        within: float = 5.0,
    ) -> bool:
        return bool(await self._request(SetTool(tuple(tcp), float(mass), cog), within))

    async def teach_mode(self, on: bool, within: float = 5.0) -> bool:
        return bool(await self._request(TeachMode(bool(on)), within))

    async def execute_trajectory(
        self,
        samples: ArrayLike,
        *,
        lookahead_time: float = 0.1,
        gain: float = 300.0,
        guard: Guard | None = None,
    ) -> TrajectoryHandle:
        """Stream (N, 6) joint positions spaced 2 ms apart with servoJ at 500 Hz.

        ``guard``: the braking limits and timeouts with which the link process stops the
        trajectory by itself (defaults: 4/8 rad/s², 40 rad/s³; 100 ms without the client,
        80 ms without state)."""
        array = _check_samples(samples)
        if not 0.03 <= lookahead_time <= 0.2:
            raise InvalidArgumentError("lookahead_time must be within [0.03, 0.2] s")
        if not 100 <= gain <= 2000:
            raise InvalidArgumentError("gain must be within [100, 2000]")
        traj_id = next(self._ids)
        handle = TrajectoryHandle(
            traj_id, len(array), self, asyncio.get_running_loop().create_future()
        )
        self._trajectories[traj_id] = handle
        self._trajectories_changed()
        collector.hold()  # released when the trajectory ends, whatever way it ends
        handle._holds_collector = True
        try:
            start = StartTrajectory(
                traj_id, wire.pack_samples(array), lookahead_time, gain, guard or Guard()
            )
            self._send(wire.TRAJ_START, start)
        except BaseException:
            self._trajectories.pop(traj_id, None)
            self._trajectories_changed()
            handle._end(None)
            raise
        return handle

    async def servo_stop(self, within: float = 5.0) -> bool:
        """Stop any streamed trajectory and leave servo mode."""
        return bool(await self._request(ServoStop(), within))

    # -- state stream

    def subscribe(self, maxsize: int = 1024) -> StateSubscription:
        """An async iterator over every state sample (use as a context manager)."""
        return StateSubscription(self._subscriptions, maxsize)

    async def samples(self) -> AsyncIterator[RobotState]:
        with self.subscribe() as sub:
            async for state in sub:
                yield state


def process_link(
    host: str | None,
    robot: RobotConfig,
    *,
    on_state: Callable[[RobotState], None],
    on_status: Callable[[LinkStatus, str], None],
    on_control: Callable[[bool, str], None],
) -> LinkClient:
    """The production :class:`~fxcell.link.backend.LinkFactory`: a :class:`LinkClient`
    (supervised ur_rtde process) to ``host``, configured by ``robot``."""
    if host is None:
        raise RobotLinkError("no controller address for the robot link")
    return LinkClient(
        host,
        frequency=robot.frequency,
        receiver=robot.receiver,
        connect_timeout=robot.connect_timeout,
        backoff_max=robot.reconnect_backoff_max,
        realtime_priority=robot.realtime_priority,
        control_mode=robot.external_control,
        urcap_program=robot.urcap_program,
        urcap_port=robot.urcap_port,
        on_state=on_state,
        on_status=on_status,
        on_control=on_control,
    )


if TYPE_CHECKING:
    from fxcell.link.backend import LinkFactory

    _PROCESS_LINK_IS_A_FACTORY: LinkFactory = process_link
