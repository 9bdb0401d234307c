"""The robot-link process: hosts the ur_rtde clients, away from the asyncio loop.

Started by :class:`fxcell.link.client.LinkClient` as ``python -m fxcell.link.process
--fd N --host H ...`` with one end of a socketpair. ur_rtde holds the GIL while it
connects and its reconnect path is fragile, so this process never reconnects: when
the controller link breaks it reports why and exits, and the client starts a fresh
process (with backoff).

Threads: the main thread reads requests; a worker runs calls one at a time (dashboard
round trips, starting the control script); the pump forwards every 500 Hz RTDE sample
(read by :class:`~fxcell.link.rtde_stream.RTDEStream`, or polled from ur_rtde's
``RTDEReceiveInterface`` with ``--receiver ur_rtde``); a pulse thread tells the client
every 10 ms that the process lives and when it last heard from the controller; a
trajectory thread streams ``servoJ`` every 2 ms.

The process is the last line of defence for a moving arm: a trajectory brakes to rest by
itself, within one control cycle, when the client asks it to stop (``TRAJ_STOP``), when the
client has been silent for the trajectory's ``cell_timeout``, and when the state stream
has been silent for its ``stall_timeout``. It brakes along the planned path (the path's
time is slowed to zero on a smooth profile under the braking limits) and then leaves servo
mode, without needing anything from the client or the state stream.

The trajectory thread sends one setpoint per state sample, as each sample arrives: locked
to the controller's clock rather than to a timer of its own (two free-running 2 ms clocks
beat, so that some controller cycles got two setpoints and some none). Which setpoint, and
when to brake or end, is the pure :class:`~fxcell.link.follower.Follower`'s (path advance
and catch-up, braking, splicing, the limit check); this module adds only the I/O. It never
uses ur_rtde's ``initPeriod``/``waitPeriod``: ``waitPeriod`` spins holding the GIL, which
starved the state pump for up to 20 ms per period.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import logging
import os
import queue
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict
from typing import Any

from fxcell.link import wire
from fxcell.link.contract import (
    REQUESTS,
    WIRE_VERSION,
    Dashboard,
    ErrorKind,
    Guard,
    LeaveServo,
    Ping,
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
    TrajectoryStatus,
    stop_reason,
)
from fxcell.link.follower import Follower
from fxcell.link.realtime import (
    LINK_PRIORITY,
    at_normal_priority,
    lower_realtime,
    name_thread,
    request_realtime,
)
from fxcell.link.rtde_stream import UR_RTDE_GETTERS, RTDEStream
from fxcell.protocol import CONTROL_PERIOD, URCAP_SCRIPT_PORT, RobotState, RuntimeState

log = logging.getLogger("fxcell.link.process")

__all__ = ["HANDLERS", "CallError", "Link", "main"]


class CallError(Exception):
    """A call failed in a way the client maps to a typed fxcell error."""

    def __init__(self, kind: ErrorKind, message: str) -> None:
        self.kind = kind
        super().__init__(message)


BUSY_CLIENT_LIMIT = 0.3
"""s: the longest silence of a client whose process the kernel says runs (see
:meth:`Link.heard_at`); the client stops beating by itself when its loop stalls 0.5 s."""


def process_runs(pid: int) -> bool:
    """Whether process ``pid`` exists and is neither stopped (SIGSTOP, a debugger) nor a
    zombie, by ``/proc/PID/stat`` (False where there is no ``/proc``)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return False
    end = stat.rfind(b")")  # the command name may hold spaces and parentheses
    return end > 0 and stat[end + 2 : end + 3] not in (b"T", b"t", b"Z", b"X", b"")


HOLD_FLUSH = 0.05
"""s: the longest wait for the client to be told of a hold before the call goes ahead."""
CALLS_BELOW = 5
"""The call worker's real-time priority is the process's less this: below its state,
trajectory and pulse threads, above the simulator's camera renderer
(``fxcell.sim.camera.RENDER_PRIORITY``) and every normal process."""


class _Outbox:
    """The link's messages to the client, written by a thread of their own.

    A client that does not read (its event loop stalled, its process frozen) fills the
    socket's buffer, and a blocking write would then hold the thread that sent it: the
    trajectory thread would stop braking, and go on along its path once the client reads
    again. Sending therefore only queues. While more than ``MAX_BACKLOG`` bytes wait, state
    samples are dropped (the client sees a gap in controller time), never other messages.
    """

    MAX_BACKLOG = 1 << 20  # bytes: ~5 s of state samples

    def __init__(self, sock: socket.socket, failed: threading.Event) -> None:
        self.sock = sock
        self.failed = failed  # set when the socket is gone
        self._cond = threading.Condition()
        self._queue: list[bytes] = []
        self._bytes = 0
        self._busy = False  # the writer holds a batch
        self._closed = False
        self.dropped = 0  # state samples dropped since the last report
        self._thread = threading.Thread(target=self._write, name="outbox", daemon=True)
        self._thread.start()

    def put(self, kind: str, data: bytes) -> None:
        """Queue one encoded message (never blocks on the socket)."""
        with self._cond:
            if self._closed:
                return
            if kind == wire.STATE and self._bytes > self.MAX_BACKLOG:
                self.dropped += 1
                return
            self._queue.append(data)
            self._bytes += len(data)
            if len(self._queue) == 1:
                self._cond.notify_all()

    def _write(self) -> None:
        while True:
            with self._cond:
                self._busy = False
                self._cond.notify_all()  # for flush()
                while not self._queue and not self._closed:
                    self._cond.wait()
                if not self._queue:
                    return
                batch, self._queue, self._bytes = self._queue, [], 0
                dropped, self.dropped = self.dropped, 0
                self._busy = True
            if dropped:
                text = f"{dropped} state samples dropped: the client did not read"
                batch.append(wire.encode((wire.LOG, logging.WARNING, text)))
            try:
                self.sock.sendall(b"".join(batch))
            except OSError:
                self.failed.set()
                with self._cond:
                    self._closed, self._queue, self._busy = True, [], False
                    self._cond.notify_all()
                return

    def flush(self, timeout: float) -> bool:
        """Wait until everything queued is written (at most ``timeout`` s)."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._queue and not self._busy, timeout)

    def close(self, timeout: float) -> None:
        """Write what is queued (at most ``timeout`` s), then end the writer."""
        self.flush(timeout)
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout)


class Link:
    def __init__(self, sock: socket.socket, args: argparse.Namespace) -> None:
        self.sock = sock
        self.args = args
        self.host: str = args.host
        self._calls: queue.Queue[tuple[int, Request] | None] = queue.Queue()
        self._stop = threading.Event()
        self.dashboard: Any = None
        self.receive: Any = None
        self.stream: RTDEStream | None = None
        self.control: Any = None
        self.io: Any = None  # ur_rtde RTDEIOInterface, opened on the first output set
        self._control_live = False
        self.latest: RobotState | None = None
        self._traj_lock = threading.Lock()
        self._traj: _Trajectory | None = None
        self.last_state_at = 0.0  # time.monotonic() of the newest state sample
        self._tick = threading.Condition()
        self._samples = 0  # state samples received (the controller's clock)
        self.last_heard = time.monotonic()  # ... and of the newest message from the client
        self.client_pid = os.getppid()  # the cell process that started this one
        # the client's beat channel (one byte per beat, from a thread of the client process)
        self.beats = socket.socket(fileno=args.beat_fd) if args.beat_fd is not None else None
        self.outbox = _Outbox(sock, self._stop)

    # -- sending

    def send(self, *message: Any) -> None:
        """Send a message to the client (queued: never blocks, see :class:`_Outbox`)."""
        self.outbox.put(message[0], wire.encode(message))

    # -- life cycle

    def connect(self) -> bool:
        import dashboard_client

        failures: dict[str, str] = {}
        try:
            self.dashboard = dashboard_client.DashboardClient(self.host)
            self.dashboard.connect(int(self.args.timeout * 1000))
        except Exception as exc:
            failures["dashboard"] = str(exc) or type(exc).__name__
        try:
            if self.args.receiver == "ur_rtde":
                import rtde_receive

                self.receive = rtde_receive.RTDEReceiveInterface(self.host, self.args.frequency)
            else:
                self.stream = RTDEStream(self.host, self.args.frequency, self.args.timeout)
                self.stream.connect()
        except Exception as exc:
            failures["rtde_receive"] = str(exc) or type(exc).__name__
        if failures:
            self.send(wire.FATAL, f"cannot connect to {self.host}", failures)
            return False
        self.send(wire.CONNECTED, {"host": self.host})
        return True

    def run(self) -> int:
        scheduling = getattr(self.args, "scheduling", None)
        hello: dict[str, Any] = {"pid": os.getpid(), "wire": WIRE_VERSION}
        if scheduling is not None:
            hello["scheduling"] = asdict(scheduling)
        self.send(wire.HELLO, hello)
        if not self.connect():
            return 2
        # ur_rtde and the imports are loaded for good: no full collection need scan them
        # again (a 20+ ms pause stalls the 500 Hz stream)
        gc.freeze()
        threads = [
            threading.Thread(target=self._pump, name="pump", daemon=True),
            threading.Thread(target=self._worker, name="worker", daemon=True),
            threading.Thread(target=self._reader, name="reader", daemon=True),
            threading.Thread(target=self._pulse, name="pulse", daemon=True),
        ]
        if self.beats is not None:
            threads.append(threading.Thread(target=self._beats, name="beats", daemon=True))
        for t in threads:
            t.start()
        self._stop.wait()
        self._stop_trajectory(StopReason.LINK_CLOSING)
        return 3

    def lost(self, reason: str) -> None:
        if not self._stop.is_set():
            self.send(wire.FATAL, "robot link lost", {"rtde_receive": reason})
            self._stop.set()

    def _pulse(self) -> None:
        """Every 10 ms: this process lives, and when its newest state sample came."""
        while not self._stop.wait(PULSE_PERIOD):
            self.send(wire.PULSE, time.monotonic(), self.last_state_at)

    def _beats(self) -> None:
        """Each byte on the beat channel: the client process lives and its loop is not stalled."""
        assert self.beats is not None
        while not self._stop.is_set():
            try:
                data = self.beats.recv(64)
            except OSError:
                return
            if not data:
                return  # the client closed it (or died: its main socket says so too)
            self.last_heard = time.monotonic()

    def heard_within(self, timeout: float, now: float) -> bool:
        """Whether the client was heard within ``timeout`` s of ``now``: by the beat or
        reader thread, or by beats still waiting in the channel (those threads starved of
        the CPU or the GIL must not make a live client look silent)."""
        if now - self.last_heard <= timeout:
            return True
        if self.beats is None:
            return False
        try:
            pending = self.beats.recv(64, socket.MSG_DONTWAIT)
        except OSError:  # nothing waiting (BlockingIOError) or the channel is gone
            return False
        if not pending:
            return False
        self.last_heard = now
        return True

    def heard_at(self, timeout: float, now: float) -> float:
        """When the client counts as last heard, for a trajectory's ``cell_timeout``.

        Silent for longer than ``timeout`` while the kernel says its process runs (not
        stopped, not gone), it is not frozen but unscheduled: on a busy machine its beat
        thread waits for the GIL that a descheduled thread of its own holds. Such a client
        gets up to :data:`BUSY_CLIENT_LIMIT` before the trajectory brakes; a stopped one
        (SIGSTOP, a debugger) brakes it after ``timeout`` as before.
        """
        if self.heard_within(timeout, now):
            return self.last_heard
        if now - self.last_heard < BUSY_CLIENT_LIMIT and process_runs(self.client_pid):
            return now - 0.5 * timeout  # within it (now - timeout may round beyond it)
        return self.last_heard

    # -- reader

    def _reader(self) -> None:
        try:
            while not self._stop.is_set():
                header = self._recv_exact(wire.HEADER.size)
                if header is None:
                    break
                (size,) = wire.HEADER.unpack(header)
                body = self._recv_exact(size)
                if body is None:
                    break
                self.last_heard = time.monotonic()
                try:
                    message = wire.decode(body)
                except Exception as exc:  # another contract's class, or corrupt
                    text = f"undecodable message refused: {type(exc).__name__}: {exc}"
                    self.send(wire.LOG, logging.ERROR, text)
                    continue
                self._dispatch(message)
        finally:
            self._stop.set()  # the client went away: exit

    def _recv_exact(self, n: int) -> bytes | None:
        chunks = bytearray()
        while len(chunks) < n:
            try:
                chunk = self.sock.recv(n - len(chunks))
            except OSError:
                return None
            if not chunk:
                return None
            chunks += chunk
        return bytes(chunks)

    def _dispatch(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == wire.CALL and len(message) == 3:
            _, request_id, request = message
            self._calls.put((request_id, request))
        elif kind == wire.CALL and len(message) > 1 and isinstance(message[1], int):
            text = f"a request of another contract (wire version {WIRE_VERSION} here)"
            self.send(wire.REPLY, message[1], False, ("contract", text))
        elif kind == wire.BEAT:
            pass  # last_heard is enough
        elif kind == wire.TRAJ_START and isinstance(message[1], StartTrajectory):
            start = message[1]
            samples = wire.unpack_samples(start.samples)
            self._start_trajectory(start.id, samples, start.lookahead_time, start.gain, start.guard)
        elif kind == wire.TRAJ_REPLACE and isinstance(message[1], ReplaceTrajectory):
            replace = message[1]
            with self._traj_lock:
                traj = self._traj
            if traj is not None and traj.id == replace.id:
                traj.replace(wire.unpack_samples(replace.samples), replace.at_index)
            else:
                self.send(wire.TRAJ, replace.id, "replaced", {"ok": False})
        elif kind == wire.TRAJ_STOP and isinstance(message[1], StopTrajectory):
            stop = message[1]
            with self._traj_lock:
                traj = self._traj
            if traj is not None and traj.id == stop.id:
                traj.stop(self._reason(stop.reason))
        else:
            self.send(wire.LOG, logging.WARNING, f"unknown message {kind!r} refused")

    def _reason(self, text: object) -> StopReason:
        """A stop's reason from the wire (one the contract does not name still stops)."""
        try:
            return StopReason(str(text))
        except ValueError:
            self.send(wire.LOG, logging.WARNING, f"unknown stop reason {text!r}: stopping")
            return StopReason.STOP_REQUESTED

    # -- state pump

    def _pump(self) -> None:
        if self.stream is not None:
            self._pump_stream()
        else:
            self._pump_ur_rtde()

    def _publish(self, state: RobotState) -> None:
        self.last_state_at = time.monotonic()
        with self._tick:  # the sample and its number together (see next_sample)
            self.latest = state
            self._samples += 1
            self._tick.notify_all()
        self.send(wire.STATE, wire.state_to_tuple(state))
        if self._control_live and state.runtime_state != RuntimeState.PLAYING:
            # the control program ended (pendant stop, safety stop, power off): the
            # interface stays for a re-upload, but it accepts no commands now
            self._control_live = False
            self.send(wire.CONTROL, False, "control program stopped")

    def _control_ready(self, reason: str) -> None:
        self._control_live = True
        self.send(wire.CONTROL, True, reason)

    def _pump_stream(self) -> None:
        """Forward every RTDE packet (the kernel buffers them: a late wake-up loses none)."""
        assert self.stream is not None
        try:
            for state in self.stream.samples():
                if self._stop.is_set():
                    return
                self._publish(state)
        except Exception as exc:
            self.lost(f"RTDE connection dropped: {exc}")

    def _pump_ur_rtde(self) -> None:
        """Poll RTDEReceiveInterface (it keeps only the newest sample: late polls lose some)."""
        r = self.receive
        last = None
        last_new = time.monotonic()
        while not self._stop.is_set():
            try:
                ts = r.getTimestamp()
                if ts != last:
                    last = ts
                    last_new = time.monotonic()
                    self._publish(self._sample(r, ts))
                    time.sleep(0.0012)
                    continue
                if time.monotonic() - last_new > 0.004 and not r.isConnected():
                    self.lost("RTDE connection dropped")
                    return
            except Exception as exc:
                self.lost(f"RTDE receive failed: {exc}")
                return
            time.sleep(0.0002)

    @staticmethod
    def _sample(r: Any, ts: float) -> RobotState:
        """One sample from ur_rtde's getters (``ts`` is the one already read)."""
        values: dict[str, Any] = {}
        for attr, getter in UR_RTDE_GETTERS:
            value = getattr(r, getter)()
            values[attr] = tuple(value) if isinstance(value, list) else value
        values["timestamp"] = ts
        return RobotState(**values)

    def next_sample(
        self, seen: int, timeout: float, woken: Callable[[], bool] | None = None
    ) -> tuple[int, RobotState | None]:
        """Wait until a state sample newer than number ``seen`` arrives (at most
        ``timeout`` s, or until ``woken()`` after a notify of ``_tick``); returns the
        newest sample's number and the sample."""
        with self._tick:
            if woken is None:
                self._tick.wait_for(lambda: self._samples != seen, timeout)
            else:
                self._tick.wait_for(lambda: self._samples != seen or woken(), timeout)
            return self._samples, self.latest

    # -- calls

    def _worker(self) -> None:
        # The calls run at real-time priority below the state, trajectory and beat threads
        # (CALLS_BELOW): at normal priority, a busy machine kept this thread off the CPUs
        # for up to 0.6 s at a time (measured), and preempted while it held the GIL it
        # would silence the whole process. But ur_rtde's commands (stopScript, setTcp,
        # ...) busy-wait until the control script is ready for them, without the GIL:
        # they run at normal priority (at_normal_priority), as a spin at real-time
        # priority held a CPU above every process of the machine (two links doing so at
        # once: both silent ~0.95 s, until the kernel's real-time throttling).
        lower_realtime(CALLS_BELOW)
        name_thread("link-calls")
        while not self._stop.is_set():
            item = self._calls.get()
            if item is None:
                return
            self.answer(*item)

    def answer(self, request_id: int, request: object) -> None:
        """Run one request (its handler from :data:`HANDLERS`, by its type) and reply."""
        try:
            handler = HANDLERS.get(type(request)) if isinstance(request, REQUESTS) else None
            if handler is None:
                raise CallError(
                    "contract",
                    f"the link process (wire version {WIRE_VERSION}) has no request "
                    f"{type(request).__name__}",
                )
            if not isinstance(request, (Dashboard, Ping)):
                self._after_trajectory()
            value = handler(self, request)
        except CallError as exc:
            self.send(wire.REPLY, request_id, False, (exc.kind, str(exc)))
        except Exception as exc:
            self.send(wire.REPLY, request_id, False, ("robot", f"{type(exc).__name__}: {exc}"))
        else:
            self.send(wire.REPLY, request_id, True, value)

    def do_dashboard(self, request: Dashboard) -> str:
        return self.dashboard_line(request.command)

    def dashboard_line(self, command: str) -> str:
        """One dashboard request line; returns the reply line."""
        try:
            self.dashboard.send(command + "\n")
            reply: str = self.dashboard.receive()
        except Exception as exc:
            raise CallError("connection", f"dashboard {command!r}: {exc}") from None
        return reply.strip()

    def do_leave_servo(self, request: LeaveServo) -> bool:
        """Leave servo mode: the worker ended a hold before this call (_after_trajectory)."""
        return True

    def do_ping(self, request: Ping) -> str:
        return "pong"

    def _wait_playing(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            state = self.latest
            if state is not None and state.runtime_state == RuntimeState.PLAYING:
                return True
            time.sleep(0.005)
        return False

    def do_start_control(self, request: StartControl) -> bool:
        """Start external control (script upload or URCap program); True when PLAYING."""
        import rtde_control

        mode, program, timeout = request.mode, request.program, request.timeout

        c = self.control
        if c is not None:
            state = self.latest
            playing = state is not None and state.runtime_state == RuntimeState.PLAYING
            # ur_rtde's isProgramRunning() reads its own receive channel, which can still
            # say PLAYING a few cycles after the state stream showed the program stop
            if playing and c.isConnected() and c.isProgramRunning():
                self._control_ready("already running")
                return True
            if mode == "script" and c.isConnected():
                with self.held(), at_normal_priority():
                    c.reuploadScript()
                if not self._wait_playing(timeout):
                    raise CallError("timeout", "control script did not start")
                self._probe(c, timeout)
                self._control_ready("script re-uploaded")
                return True
            if mode == "urcap" and c.isConnected():
                self._play_urcap(program, timeout)
                self._probe(c, timeout)
                self._control_ready("URCap program restarted")
                return True
            c = None  # _drop_control must hold the last reference (see there)
            self._drop_control("reconnecting control interface")
        self._stop_leftover_program()
        try:
            self._hold_stream()
            with at_normal_priority():
                c = self._connect_control(rtde_control, mode)
        except Exception as exc:
            raise CallError("robot", f"cannot start external control: {exc}") from None
        finally:
            self.send(wire.HOLD, False)
        self.control = c
        if mode == "urcap":
            self._play_urcap(program, timeout)
        elif not self._wait_playing(timeout):
            raise CallError("timeout", "control script did not start")
        self._probe(c, timeout)
        self._control_ready(f"external control ({mode})")
        return True

    def _connect_control(self, rtde_control: Any, mode: str) -> Any:
        """A new ur_rtde control interface: it uploads the control script, or with the
        URCap waits for the program to connect (ur_rtde blocks holding the GIL)."""
        if mode == "urcap":
            flags = rtde_control.RTDEControlInterface.Flags
            return rtde_control.RTDEControlInterface(
                self.host,
                self.args.frequency,
                flags.FLAG_USE_EXT_UR_CAP | flags.FLAG_NO_WAIT,
                self.args.urcap_port,
            )
        return rtde_control.RTDEControlInterface(self.host, self.args.frequency)

    def _probe(self, c: Any, timeout: float) -> None:
        """Wait until the control script answers a harmless command (it accepts commands)."""
        deadline = time.monotonic() + timeout
        why = "no answer"
        while True:
            try:
                with at_normal_priority():
                    answered = c.servoStop()  # harmless; True once the script processed it
                if answered:
                    return
            except Exception as exc:
                why = str(exc)
            if time.monotonic() > deadline:
                raise CallError("timeout", f"control script does not answer: {why}")
            time.sleep(0.01)

    def _stop_leftover_program(self) -> None:
        """Stop a program still playing (e.g. the script of a previous link process).

        ur_rtde's own path for this (command 255, then dashboard ``stop``) fails when
        the script ends before the ``stop`` arrives.
        """
        state = self.latest
        if state is None or state.runtime_state == RuntimeState.STOPPED:
            return
        self.dashboard_line("stop")
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            state = self.latest
            if state is not None and state.runtime_state == RuntimeState.STOPPED:
                return
            time.sleep(0.005)

    def _play_urcap(self, program: str, timeout: float) -> None:
        reply = self.dashboard_line(f"load {program}")
        if "Loading program" not in reply:
            raise CallError("robot", f"load {program}: {reply}")
        reply = self.dashboard_line("play")
        if reply != "Starting program":
            raise CallError("robot", f"play: {reply}")
        if not self._wait_playing(timeout):
            raise CallError("timeout", f"{program} did not start playing")

    def do_stop_control(self, request: StopControl) -> bool:
        mode = request.mode
        self._stop_trajectory(StopReason.EXTERNAL_CONTROL_STOPPED)
        if self.control is not None:
            with self.held(), at_normal_priority(), contextlib.suppress(Exception):
                self.control.stopScript()
        if mode == "urcap":
            self.dashboard_line("stop")
        self._drop_control("external control stopped")
        return True

    def _drop_control(self, reason: str) -> None:
        self._control_live = False
        c, self.control = self.control, None
        if c is not None:
            # disconnect() and the destructor both block holding the GIL (~0.5 s): the
            # last reference must go inside the hold.
            with self.held(), at_normal_priority():
                with contextlib.suppress(Exception):
                    c.disconnect()
                del c
        self.send(wire.CONTROL, False, reason)

    def _hold_stream(self) -> None:
        """Tell the client the state stream may pause, and wait until it has been told: the
        call that follows may hold the GIL, and the writer thread needs it to send."""
        self.send(wire.HOLD, True)
        self.outbox.flush(HOLD_FLUSH)

    @contextlib.contextmanager
    def held(self) -> Iterator[None]:
        """Tell the client the state stream may pause: a ur_rtde call may hold the GIL."""
        self._hold_stream()
        try:
            yield
        finally:
            self.send(wire.HOLD, False)

    def do_servo_stop(self, request: ServoStop) -> bool:
        self._stop_trajectory(StopReason.SERVO_STOP)
        c = self.control
        if c is None:
            return False
        with at_normal_priority():
            return bool(c.servoStop())

    def do_set_output(self, request: SetOutput) -> bool:
        """Set a digital (0/1) or analog (fraction of range) output through RTDE's IO recipe."""
        import rtde_io

        group, index, value = request.group, request.index, request.value

        if self.io is None or not self.io.isConnected():
            try:
                with self.held(), at_normal_priority():
                    self.io = rtde_io.RTDEIOInterface(self.host)
            except Exception as exc:
                raise CallError("connection", f"cannot open the RTDE IO interface: {exc}") from None
        io = self.io
        if group == "standard":
            ok = io.setStandardDigitalOut(index, bool(value))
        elif group == "configurable":
            ok = io.setConfigurableDigitalOut(index, bool(value))
        elif group == "tool":
            ok = io.setToolDigitalOut(index, bool(value))
        elif group == "analog":
            ok = io.setAnalogOutputVoltage(index, float(value))
        else:
            raise CallError("argument", f"no output group {group!r}")
        return bool(ok)

    def _require_control(self, what: str) -> Any:
        c = self.control
        if c is None or not c.isProgramRunning():
            raise CallError(
                "robot", f"{what} needs external control (the control script is not running)"
            )
        return c

    def do_set_tool(self, request: SetTool) -> bool:
        """Set the TCP (flange frame) and the payload on the controller."""
        c = self._require_control("setting the tool")
        with at_normal_priority():
            return bool(c.setTcp(list(request.tcp))) and bool(
                c.setPayload(request.mass, list(request.cog))
            )

    def do_teach_mode(self, request: TeachMode) -> bool:
        """Enter or leave teach mode (freedrive: the arm can be moved by hand)."""
        self._stop_trajectory(StopReason.TEACH_MODE)
        c = self._require_control("freedrive")
        with at_normal_priority():
            return bool(c.teachMode() if request.on else c.endTeachMode())

    # -- trajectories

    def _after_trajectory(self) -> None:
        """Wait for a trajectory that has reported its end to leave servo mode, so that a
        call never uses the control interface at the same time as its servoStop."""
        with self._traj_lock:
            traj = self._traj
        if (
            traj is not None
            and traj.ended.is_set()
            and traj.thread is not threading.current_thread()
        ):
            traj.release(keep_servo=False)
            traj.thread.join(5.0)

    def _start_trajectory(
        self,
        traj_id: int,
        samples: wire.Samples,
        lookahead: float,
        gain: float,
        guard: Guard | None = None,
    ) -> None:
        with self._traj_lock:
            old = self._traj
        # a trajectory holding its target after a normal end hands servo mode on
        if old is not None:
            if not old.release(keep_servo=True):
                old.stop(StopReason.SUPERSEDED)
            old.thread.join(5.0)
        traj = _Trajectory(self, traj_id, samples, lookahead, gain, guard or Guard())
        with self._traj_lock:
            self._traj = traj
        traj.thread.start()

    def _stop_trajectory(self, reason: StopReason) -> None:
        with self._traj_lock:
            traj = self._traj
        if traj is not None:
            traj.stop(reason)
            if traj.thread is not threading.current_thread():
                traj.thread.join(3.0)  # the longest stop under the braking limits


HANDLERS: dict[type[Request], Callable[[Link, Any], object]] = {
    Dashboard: Link.do_dashboard,
    Ping: Link.do_ping,
    LeaveServo: Link.do_leave_servo,
    StartControl: Link.do_start_control,
    StopControl: Link.do_stop_control,
    ServoStop: Link.do_servo_stop,
    SetOutput: Link.do_set_output,
    SetTool: Link.do_set_tool,
    TeachMode: Link.do_teach_mode,
}
"""Each request type's handler: the one table the worker dispatches by."""
if set(HANDLERS) != set(REQUESTS):  # pragma: no cover - caught by the unit tests too
    raise ImportError(f"link requests without a handler: {set(REQUESTS) - set(HANDLERS)}")

PULSE_PERIOD = 0.01  # s between two PULSE messages to the client


class _Trajectory:
    """Streams one (N, 6) joint trajectory with servoJ, one setpoint per controller cycle;
    brakes by itself. What to send and when to stop is the :class:`~fxcell.link.follower.
    Follower`'s; this thread adds the I/O: ur_rtde's servoJ, the state samples and the
    clock, and the messages to the client."""

    PROGRESS_EVERY = Follower.PROGRESS_EVERY
    CATCH_UP = Follower.CATCH_UP
    HOLD = Follower.HOLD
    SETTLE_MAX = Follower.SETTLE_MAX

    def __init__(
        self,
        link: Link,
        traj_id: int,
        samples: wire.Samples,
        lookahead: float,
        gain: float,
        guard: Guard,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.link = link
        self.id = traj_id
        self.clock = clock  # the link process's monotonic clock (a test's own, stepped)
        self.samples = samples
        self.lookahead = lookahead
        self.gain = gain
        self.guard = guard
        self._lock = threading.Lock()
        self._replacement: tuple[wire.Samples, int | None] | None = None
        self._stop_reason: StopReason | None = None
        self._poked = False  # stop() wants the thread awake now
        self.ended = threading.Event()  # the end is reported; servo mode is being left
        self._holding = False
        self._will_hold = False  # it ended at its target and is about to hold it
        self._released = threading.Event()
        self._keep_servo = False
        self.servo_kept = False  # the hold ended handing servo mode to the next trajectory
        self.hold_started = threading.Event()  # it ended at its target and holds it
        self.thread = threading.Thread(target=self._run, name=f"trajectory-{traj_id}", daemon=True)

    def replace(self, samples: wire.Samples, at_index: int | None = None) -> None:
        """Replace the samples not yet sent; with ``at_index``, ``samples[0]`` takes the
        place of the current trajectory's sample ``at_index`` (the ones before it are
        still sent), so a braking profile starts exactly where it was computed from."""
        with self._lock:
            self._replacement = (samples, at_index)

    def stop(self, reason: StopReason) -> None:
        """Brake to rest along the path (now: the thread is woken, not left to wait for
        the next state sample)."""
        with self._lock:
            if self._stop_reason is None:
                self._stop_reason = reason
        with self.link._tick:
            self._poked = True
            self.link._tick.notify_all()

    def _is_poked(self) -> bool:
        return self._poked

    def release(self, *, keep_servo: bool) -> bool:
        """End the hold after a completed trajectory: for the next trajectory
        (``keep_servo``: no servoStop in between) or for a call; True if it was not
        yet past its hold (the next trajectory can take servo mode over). That includes
        the moment between its end report and the start of its hold: the cell may start
        the next move at once, and the hold hands servo mode on as soon as it starts
        instead of holding the target for all of HOLD while the next move waits."""
        with self._lock:
            if self._released.is_set() or (keep_servo and not (self._holding or self._will_hold)):
                return False
            self._keep_servo = keep_servo
            self._released.set()
        with self.link._tick:
            self.link._tick.notify_all()  # wake the hold now, not at the next sample
        return True

    def _take_requests(self, follower: Follower) -> None:
        """Hand the stop request and a replacement that came since the last cycle on."""
        with self._lock:
            replacement, self._replacement = self._replacement, None
            reason = self._stop_reason
        if reason is not None:
            follower.stop(reason)
        if replacement is not None:
            follower.replace(*replacement)

    def _run(self) -> None:
        link = self.link
        started = self.clock()
        c = link.control
        seen = link._samples
        clock = link.latest.timestamp if link.latest is not None else None
        follower = Follower(
            self.samples, self.guard, self.lookahead, gain=self.gain, now=started, clock=clock
        )
        status: TrajectoryStatus = "completed"
        reason = StopReason.NONE
        detail = ""
        cycled = started  # the clock at this thread's previous cycle
        if c is None:
            status, reason = "failed", StopReason.NO_EXTERNAL_CONTROL
        else:
            cell_timeout = self.guard.cell_timeout
            try:
                while True:
                    now = self.clock()
                    self._take_requests(follower)
                    braking = follower.braking
                    out = follower.cycle(
                        now,
                        link.latest,
                        heard_at=link.heard_at(cell_timeout, now)
                        if cell_timeout is not None
                        else None,
                        state_at=link.last_state_at,
                    )
                    if braking is None and follower.braking is not None:
                        self._explain_stall(now, cycled)
                    cycled = now
                    self._tell(follower)
                    if out.target is None:
                        status, reason = out.status or "completed", out.reason
                        break
                    ok = c.servoJ(
                        list(out.target), 0.0, 0.0, CONTROL_PERIOD, self.lookahead, self.gain
                    )
                    if not ok:
                        state = link.latest
                        why = None
                        if state is not None:
                            why = stop_reason(state.safety_mode, state.runtime_state)
                        status, reason = "failed", why or StopReason.SERVOJ_REFUSED
                        break
                    if out.progress is not None:
                        self._progress(
                            out.progress, len(follower.samples), out.target, out.answered
                        )
                    # One setpoint per controller cycle, sent when the cycle's state sample
                    # arrives (locked to the controller's clock); without samples a 3 ms
                    # timer paces the stream until the stall brakes it.
                    before = seen
                    seen, latest = link.next_sample(seen, 1.5 * CONTROL_PERIOD, self._is_poked)
                    # (a poke lost to a stop() between these two lines waits for the sample)
                    poked, self._poked = self._poked, False
                    new = seen != before and latest is not None
                    follower.advance(
                        self.clock(), latest.timestamp if new and latest else None, poked=poked
                    )
            except Exception as exc:
                status, reason, detail = "failed", StopReason.LINK_ERROR, str(exc)
        state = link.latest
        at_target = status == "completed" or (status == "stopped" and reason is StopReason.SETTLED)
        with self._lock:  # before the end report: the next trajectory may follow at once
            self._will_hold = c is not None and at_target
        # The end is reported before servo mode is left (a controller round trip): the
        # setpoints have stopped, and the next call that needs the control interface
        # waits for this thread first (Link._after_trajectory).
        link.send(
            wire.TRAJ,
            self.id,
            "end",
            {
                "status": status,
                "reason": reason.value,
                "detail": detail,
                "index": follower.index,
                "total": len(follower.samples),
                "actual_q": state.actual_q if state is not None else None,
                "duration": self.clock() - started,
            },
        )
        self.ended.set()
        if c is not None and at_target and self._hold(c, follower):
            self.servo_kept = True
        elif c is not None:
            with contextlib.suppress(Exception):
                c.servoStop()
        with link._traj_lock:
            if link._traj is self:
                link._traj = None

    def _explain_stall(self, now: float, cycled: float) -> None:
        """Log where a stalled state stream stalled: in the controller (nothing unread)
        or in this process (samples waiting in the socket while its threads waited for a
        CPU)."""
        link = self.link
        if now - link.last_state_at <= self.guard.stall_timeout:
            return  # it brakes for another reason
        unread = link.stream.unread() if link.stream is not None else -1
        self.link.send(
            wire.LOG,
            logging.WARNING,
            f"state stalled: newest sample {1e3 * (now - link.last_state_at):.1f} ms old, "
            f"{unread} bytes unread from the controller, this thread's previous cycle "
            f"{1e3 * (now - cycled):.1f} ms ago",
        )

    def _tell(self, follower: Follower) -> None:
        """Send what the follower has to say (a braking warning, a splice's outcome)."""
        if not follower.notices:
            return
        for notice in follower.notices:
            if notice.kind == "log":
                self.link.send(wire.LOG, notice.level, notice.text)
            else:
                self.link.send(wire.TRAJ, self.id, notice.kind, dict(notice.data))
        follower.notices.clear()

    def _hold(self, c: Any, follower: Follower) -> bool:
        """Keep servoing the target for up to ``HOLD`` s after a completed trajectory;
        True if the next trajectory takes servo mode over. Leaving servo mode and entering
        it again cost 7-9 ms and 3-5 ms of controller round trips, which back-to-back
        moves then do not pay."""
        link = self.link
        until = self.clock() + self.HOLD
        seen = link._samples
        with self._lock:
            self._holding = True
            if self._stop_reason is StopReason.SETTLED:
                self._stop_reason = None  # the stop that ended it; any other ends the hold
        follower.begin_hold()
        self.hold_started.set()
        try:
            while self.clock() < until:
                if self._released.is_set():
                    with self._lock:
                        return self._keep_servo
                self._take_requests(follower)
                target = follower.hold_target(link.latest)
                if target is None:
                    return False
                if not c.servoJ(list(target), 0.0, 0.0, CONTROL_PERIOD, self.lookahead, self.gain):
                    return False
                seen = self._next_sample_or_release(seen)
        except Exception:
            return False
        finally:
            with self._lock:
                self._holding = self._will_hold = False
                self._released.set()  # too late to take over now
        return False

    def _next_sample_or_release(self, seen: int) -> int:
        seen, _ = self.link.next_sample(seen, 1.5 * CONTROL_PERIOD, self._released.is_set)
        return seen

    def _progress(
        self, index: int, total: int, commanded: tuple[float, ...], timestamp: float | None
    ) -> None:
        """Report that setpoint ``index`` went out for the state sample of controller time
        ``timestamp``: the client counts the link's index at any later sample in controller
        cycles from there, not by its own clock."""
        state = self.link.latest
        actual = state.actual_q if state is not None else None
        error = wire.max_abs_difference(commanded, actual) if actual else float("nan")
        self.link.send(
            wire.TRAJ,
            self.id,
            "progress",
            {"index": index, "total": total, "actual_q": actual, "tracking_error": error,
             "timestamp": timestamp},
        )  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fxcell.link.process")
    parser.add_argument("--fd", type=int, required=True)
    parser.add_argument("--beat-fd", type=int, default=None)
    parser.add_argument("--host", required=True)
    parser.add_argument("--frequency", type=float, default=500.0)
    parser.add_argument("--timeout", type=float, default=2.0)
    parser.add_argument("--urcap-port", type=int, default=URCAP_SCRIPT_PORT)
    parser.add_argument("--rt-priority", type=int, default=LINK_PRIORITY)
    parser.add_argument(
        "--receiver",
        choices=("stream", "ur_rtde"),
        default="stream",
        help="state source: fxcell's RTDE reader (every sample) or RTDEReceiveInterface",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    # before any thread starts (ur_rtde's included): they inherit the policy
    args.scheduling = request_realtime(args.rt_priority)
    sock = socket.socket(fileno=args.fd)
    link = Link(sock, args)
    code = link.run()
    link.outbox.close(1.0)  # the last messages (a FATAL, a trajectory's end) still go out
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)
    # ur_rtde's destructors can block or crash on a broken link: leave without them.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    main()
