"""The flight recorder: the cell's event bus into rotating, crash-recoverable MCAP files.

The bus subscriber (:meth:`Recorder.submit`) only timestamps the event and appends it
to a bounded deque: about a microsecond on the event loop. A writer thread drains the
deque, encodes (protobuf for the 500 Hz state, JSON for the rest), computes the link
frames for Foxglove's 3D panel, and writes zstd chunks that it closes every
``chunk_duration`` seconds, so a crash (SIGKILL, power loss) loses at most one chunk.
A full or failing disk never reaches the control path: the recorder logs it loudly,
counts what it drops, reports through ``on_error`` and retries with a new file.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import logging
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Final

from mcap.writer import CompressionType, Writer

from fxcell._version import __version__
from fxcell.errors import InvalidArgumentError, RecorderError
from fxcell.events import (
    CommandEvent,
    DeviceEvent,
    Event,
    EventBus,
    LogEvent,
    MotionEvent,
    PlacementEvent,
    StateEvent,
    TransitionEvent,
)
from fxcell.jsonable import to_jsonable
from fxcell.recorder import topics
from fxcell.recorder.frames import LinkFrames
from fxcell.recorder.protobuf import encode_robot_state
from fxcell.recorder.recovery import recover_unfinished
from fxcell.recorder.retention import Retention, enforce
from fxcell.recorder.schemas import (
    dumps,
    foxglove_log_level,
    placement_messages,
    timestamp,
    topic_schemas,
)

if TYPE_CHECKING:
    from fxcell.robots.description import ArmDescription

log = logging.getLogger(__name__)

MAX_CHUNK_BYTES: Final = 8 * 1024 * 1024
"""Upper bound of a chunk in memory; chunks normally close on time, not on size."""
TF_RATE: Final = 30.0
"""Hz: how often the arm's ``/tf`` frames are written (from the robot states)."""
RETRY_INTERVAL: Final = 5.0
"""Seconds between attempts to open a new file after a write failed."""
REPORT_INTERVAL: Final = 5.0
"""Seconds between repeated reports while the recorder is dropping messages."""

ErrorCallback = Callable[[str], None]


@dataclass(frozen=True, slots=True)
class RecorderStats:
    """What the recorder did so far."""

    messages_written: int
    """Messages in chunks that reached the file."""
    messages_dropped: int
    """Messages lost: queue full (disk too slow), write failures, unencodable events."""
    messages_pending: int
    """Messages queued or in the open chunk."""
    chunks_written: int
    bytes_written: int
    files: tuple[Path, ...]
    queue_high_water: int
    errors: int
    last_error: str | None = None
    per_topic: Mapping[str, int] = field(default_factory=dict)
    """Messages encoded per topic (including the open chunk)."""


@dataclass(frozen=True, slots=True)
class _MetadataUpdate:
    values: dict[str, str]


@dataclass(slots=True)
class _OpenFile:
    path: Path
    stream: IO[bytes]
    writer: Writer
    channels: dict[str, int]
    sequence: dict[int, int]
    opened: float  # monotonic
    chunks: int = 0


class Recorder:
    """Record the cell's events to MCAP files in ``directory``.

    Files are named by their start time (``fxcell_20260131T142501.123Z.mcap``, UTC)
    and rotate when they reach ``rotate_size`` bytes or ``rotate_duration`` seconds.
    Unfinished files of earlier sessions in ``directory`` are recovered first.

    ``metadata`` (fxcell version, config snapshot, controller version, serial, ...)
    is written into every file; non-string values are stored as JSON. ``arm`` is the
    robot kind's description (its URDF and the ``/tf`` frames; None: the UR3e with
    ``tcp``, its tool centre point in the flange frame, None: the flange).
    ``on_error(message)`` is called from the writer thread when the recorder starts
    dropping messages or cannot write; use ``loop.call_soon_threadsafe`` in it.
    ``clock`` stamps each event's log time (ns since the epoch) as it is submitted.
    ``capture_logs``: records of the ``fxcell`` loggers at this level or above (as far as
    the loggers emit them) go to ``/log`` too; ``None`` turns that off.
    ``retention`` bounds the directory's total size and age: each time a file is opened,
    the oldest finished logs are removed (never the running file, nor a locked one).
    """

    def __init__(
        self,
        directory: str | os.PathLike[str],
        *,
        chunk_duration: float = 1.0,
        rotate_size: int = 512 * 1024 * 1024,
        rotate_duration: float = 3600.0,
        metadata: Mapping[str, Any] | None = None,
        tcp: Sequence[float] | None = None,
        arm: ArmDescription | None = None,
        tf_rate: float = TF_RATE,
        max_queue: int = 30_000,
        fsync: bool = True,
        compression: str = "zstd",
        prefix: str = "fxcell",
        recover: bool = True,
        on_error: ErrorCallback | None = None,
        retry_interval: float = RETRY_INTERVAL,
        clock: Callable[[], int] = time.time_ns,
        capture_logs: int | None = logging.INFO,
        retention: Retention | None = None,
    ) -> None:
        if not chunk_duration > 0:
            raise InvalidArgumentError(f"chunk_duration must be > 0 s, got {chunk_duration!r}")
        if not rotate_size > 0 or not rotate_duration > 0:
            raise InvalidArgumentError("rotate_size and rotate_duration must be > 0")
        if not tf_rate >= 0:
            raise InvalidArgumentError(f"tf_rate must be >= 0 Hz, got {tf_rate!r}")
        if max_queue < 1:
            raise InvalidArgumentError(f"max_queue must be >= 1, got {max_queue!r}")
        try:
            self._compression = {
                "zstd": CompressionType.ZSTD,
                "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE,
            }[compression]
        except KeyError:
            raise InvalidArgumentError(
                f"compression must be zstd, lz4 or none, got {compression!r}"
            ) from None
        self.directory = Path(directory)
        self.chunk_duration = float(chunk_duration)
        self.rotate_size = int(rotate_size)
        self.rotate_duration = float(rotate_duration)
        self._metadata = {
            str(k): v if isinstance(v, str) else dumps(to_jsonable(v)).decode()
            for k, v in (metadata or {}).items()
        }
        self._metadata.setdefault("fxcell_version", __version__)
        self._prefix = prefix
        self._retention = retention
        self._fsync = fsync
        self._max_queue = max_queue
        self._on_error = on_error
        self._retry_interval = retry_interval
        self._clock = clock
        # The writer wakes 4 times a chunk: batches of ~125 states at 500 Hz keep its caches
        # warm (0.1 s cost 0.1-0.15 % of a core more), and a crash loses at most a chunk.
        self._poll = min(0.25, self.chunk_duration / 4)
        self._tf_period_ns = int(1e9 / tf_rate) if tf_rate > 0 else 0
        self._frames = LinkFrames(tcp, arm) if tf_rate > 0 else None
        self._schemas = topic_schemas()

        # shared with the submitting thread: the deque, and counters each side owns
        self._queue: collections.deque[tuple[int, Event | _MetadataUpdate]] = collections.deque()
        self._dropped_full = 0  # written by submit() only
        self._closed = False
        self._unsubscribe: Callable[[], None] | None = None

        # writer-thread state
        self._file: _OpenFile | None = None
        self._files: list[Path] = []
        self._written = 0
        self._dropped_write = 0
        self._pending = 0
        self._chunk_started: float | None = None  # monotonic, for the flush timer
        self._chunk_first_ns: int | None = None  # log time of the chunk's first message
        self._chunk_ns = int(self.chunk_duration * 1e9)
        self._chunks = 0
        self._bytes_closed = 0  # bytes of files already closed
        self._bytes_current = 0
        self._per_topic: collections.Counter[str] = collections.Counter()
        self._high_water = 0
        self._errors = 0
        self._last_error: str | None = None
        self._retry_at = 0.0
        self._reported_dropped = 0
        self._last_report = 0.0
        self._last_modes: tuple[int, ...] | None = None
        self._last_io: tuple[int, int] | None = None
        self._last_tf_ns = 0
        self._queue_warned = False
        self._unknown_types: set[type] = set()
        self._dead = False  # the writer thread failed: everything submitted is dropped

        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecorderError(f"cannot create log directory {self.directory}: {exc}") from None
        if recover:
            for report in recover_unfinished(self.directory):
                log.warning("recovered unfinished log %s", report)
        try:
            self._open_file()
        except OSError as exc:
            raise RecorderError(f"cannot start a log in {self.directory}: {exc}") from None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fxcell-recorder", daemon=True)
        self._thread.start()
        self._log_handler: logging.Handler | None = None
        if capture_logs is not None:
            self._log_handler = _LogCapture(self.submit, capture_logs)
            logging.getLogger("fxcell").addHandler(self._log_handler)

    # ------------------------------------------------------------- producer side

    def attach(self, bus: EventBus) -> None:
        """Record every event published on ``bus`` from now on."""
        if self._unsubscribe is not None:
            raise RecorderError("this recorder is already attached to an event bus")
        self._unsubscribe = bus.subscribe(self.submit)

    def submit(self, event: Event) -> None:
        """Queue one event for writing: never blocks (drops and counts when full)."""
        if self._closed:
            return
        if self._dead or len(self._queue) >= self._max_queue:
            self._dropped_full += 1
            return
        self._queue.append((self._clock(), event))

    def update_metadata(self, values: Mapping[str, Any]) -> None:
        """Add to the file's metadata (e.g. controller version and serial once connected).

        The current file gets another ``fxcell`` metadata record with everything known so
        far (readers take the last one); later files start with it.
        """
        update = {
            str(k): v if isinstance(v, str) else dumps(to_jsonable(v)).decode()
            for k, v in values.items()
        }
        if not self._closed:
            self._queue.append((self._clock(), _MetadataUpdate(update)))

    def close(self, timeout: float = 30.0) -> None:
        """Write what is queued, finish the current file and stop the writer thread."""
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        if self._log_handler is not None:
            logging.getLogger("fxcell").removeHandler(self._log_handler)
            self._log_handler = None
        self._closed = True
        self._stop.set()
        self._thread.join(timeout)
        if self._thread.is_alive():
            log.error("recorder: the writer did not finish within %.0f s (disk stalled?)", timeout)

    async def aclose(self) -> None:
        """:meth:`close` without blocking the event loop."""
        import asyncio

        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        await asyncio.to_thread(self.close)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def stats(self) -> RecorderStats:
        """A snapshot of the counters (cheap; safe from any thread)."""
        return RecorderStats(
            messages_written=self._written,
            messages_dropped=self._dropped_full + self._dropped_write,
            messages_pending=len(self._queue) + self._pending,
            chunks_written=self._chunks,
            bytes_written=self._bytes_closed + self._bytes_current,
            files=tuple(self._files),
            queue_high_water=self._high_water,
            errors=self._errors,
            last_error=self._last_error,
            per_topic=dict(self._per_topic),
        )

    @property
    def current_file(self) -> Path | None:
        f = self._file
        return f.path if f is not None else None

    # ------------------------------------------------------------- writer thread

    def _run(self) -> None:
        try:
            while True:
                stopping = self._stop.is_set()
                depth = len(self._queue)
                if depth > self._high_water:
                    self._high_water = depth
                self._drain()
                now = time.monotonic()
                if self._file is None and now >= self._retry_at and not stopping:
                    self._reopen()
                started = self._chunk_started
                if started is not None and now - started >= self.chunk_duration - self._poll:
                    self._flush()
                self._report(now, depth)
                if stopping and not self._queue:
                    break
                self._stop.wait(self._poll)
        except Exception as exc:  # a bug here must be loud, never silent
            self._dead = True
            self._dropped_write += self._pending + len(self._queue)
            self._pending = 0
            self._queue.clear()
            log.exception("recorder writer thread failed")
            self._error(f"recorder writer failed: {exc!r}")
        finally:
            self._finish_file()

    def _drain(self) -> None:
        queue = self._queue
        handlers = self._handlers
        while True:
            try:
                t, event = queue.popleft()
            except IndexError:
                return
            first = self._chunk_first_ns
            if first is not None and t - first >= self._chunk_ns:
                self._flush()  # a chunk never spans more than chunk_duration of log time
            if self._file is None:
                self._dropped_write += 1
                continue
            handler = handlers.get(type(event))
            if handler is None:
                if type(event) not in self._unknown_types:
                    self._unknown_types.add(type(event))
                    log.warning("recorder: %s events are not recorded", type(event).__name__)
                continue
            try:
                handler(self, t, event)
            except OSError as exc:
                self._fail(exc)
            except Exception:
                self._dropped_write += 1
                log.exception("recorder cannot encode %s", type(event).__name__)

    def _add(self, topic: str, log_time: int, data: bytes, publish_time: int) -> None:
        f = self._file
        assert f is not None
        channel = f.channels[topic]
        seq = f.sequence[channel] = f.sequence[channel] + 1
        f.writer.add_message(channel, log_time, data, publish_time, seq)
        self._pending += 1
        self._per_topic[topic] += 1
        if self._chunk_started is None:
            self._chunk_started = time.monotonic()
            self._chunk_first_ns = log_time

    # ----- one handler per event type

    def _on_state(self, t: int, event: StateEvent) -> None:
        s = event.sample
        self._add(topics.ROBOT_STATE, t, encode_robot_state(s), t)
        modes = (
            s.robot_mode,
            s.safety_mode,
            s.runtime_state,
            s.robot_status_bits,
            s.safety_status_bits,
        )
        if modes != self._last_modes:
            self._last_modes = modes
            msg = {
                "controller_time": s.timestamp,
                "robot_mode": _name(s.robot_mode),
                "safety_mode": _name(s.safety_mode),
                "runtime_state": _name(s.runtime_state),
                "robot_status_bits": int(s.robot_status_bits),
                "safety_status_bits": int(s.safety_status_bits),
            }
            self._add(topics.ROBOT_MODES, t, dumps(msg), t)
        io = (s.digital_input_bits, s.digital_output_bits)
        if io != self._last_io:
            self._last_io = io
            msg = {
                "controller_time": s.timestamp,
                "digital_input_bits": int(s.digital_input_bits),
                "digital_output_bits": int(s.digital_output_bits),
                "analog_inputs": [s.standard_analog_input0, s.standard_analog_input1],
                "analog_outputs": [s.standard_analog_output0, s.standard_analog_output1],
            }
            self._add(topics.IO, t, dumps(msg), t)
        if self._frames is not None and t - self._last_tf_ns >= self._tf_period_ns:
            self._last_tf_ns = t
            data = self._frames.transforms_json(s.actual_q, t // 1_000_000_000, t % 1_000_000_000)
            if data is not None:
                self._add(topics.TF, t, data, t)

    def _on_command(self, t: int, e: CommandEvent) -> None:
        msg = {
            "command_id": e.command_id,
            "name": e.name,
            "args": to_jsonable(dict(e.args)),
            "origin": str(e.origin.value if hasattr(e.origin, "value") else e.origin),
            "phase": "start" if e.outcome == "started" else "end",
            "started": e.started,
            "ended": e.ended,
            "outcome": e.outcome,
            "error_type": e.error_type,
            "error_message": e.error_message,
            "result": to_jsonable(e.result),
        }
        when = e.started if e.ended is None else e.ended
        self._add(topics.COMMANDS, t, dumps(msg), int(when * 1e9))

    def _on_transition(self, t: int, e: TransitionEvent) -> None:
        msg = {
            "time": e.time,
            "source": e.source,
            "dest": e.dest,
            "trigger": e.trigger,
            "cause": e.cause,
            "detail": e.detail,
        }
        self._add(topics.TRANSITIONS, t, dumps(msg), int(e.time * 1e9))

    def _on_motion(self, t: int, e: MotionEvent) -> None:
        msg = {"time": e.time, "move_id": e.move_id, "kind": e.kind, "data": to_jsonable(e.data)}
        self._add(topics.MOTION, t, dumps(msg), int(e.time * 1e9))

    def _on_device(self, t: int, e: DeviceEvent) -> None:
        msg = {"time": e.time, **to_jsonable(dict(e.data))}
        topic = topics.GRIPPER if e.device == "gripper" else topics.JOB
        self._add(topic, t, dumps(msg), int(e.time * 1e9))

    def _on_placement(self, t: int, e: PlacementEvent) -> None:
        ns = int(e.time * 1e9)
        report = to_jsonable(dict(e.report))
        image, annotations, verdict = placement_messages(ns, e.jpeg, report, e.frame_id)
        self._add(topics.CAMERA_PLACEMENT, t, image, ns)
        self._add(topics.CAMERA_PLACEMENT_ANNOTATIONS, t, annotations, ns)
        self._add(topics.CAMERA_PLACEMENT_VERDICT, t, verdict, ns)

    def _on_log(self, t: int, e: LogEvent) -> None:
        ns = int(e.time * 1e9)
        msg = {
            "timestamp": timestamp(ns),
            "level": foxglove_log_level(e.level),
            "message": e.message,
            "name": e.name,
            "file": e.file,
            "line": e.line,
        }
        self._add(topics.LOG, t, dumps(msg), ns)

    def _on_metadata(self, t: int, update: _MetadataUpdate) -> None:
        self._metadata.update(update.values)
        f = self._file
        assert f is not None
        f.writer.add_metadata(topics.METADATA_NAME, dict(self._metadata))

    _handlers: Final[dict[type, Callable[[Recorder, int, Any], None]]] = {
        StateEvent: _on_state,
        CommandEvent: _on_command,
        TransitionEvent: _on_transition,
        MotionEvent: _on_motion,
        DeviceEvent: _on_device,
        PlacementEvent: _on_placement,
        LogEvent: _on_log,
        _MetadataUpdate: _on_metadata,
    }

    # ----- files

    def _new_path(self) -> Path:
        now = datetime.now(UTC)
        stem = f"{self._prefix}_{now:%Y%m%dT%H%M%S}.{now.microsecond // 1000:03d}Z"
        path = self.directory / f"{stem}{topics.FILE_SUFFIX}"
        n = 1
        while path.exists():
            path = self.directory / f"{stem}-{n}{topics.FILE_SUFFIX}"
            n += 1
        return path

    def _open_file(self) -> None:
        path = self._new_path()
        stream = self._open_stream(path)
        try:
            # held while recording: tells recovery at the next start this file is in use
            fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            writer = Writer(stream, chunk_size=MAX_CHUNK_BYTES, compression=self._compression)
            writer.start(profile="", library=f"fxcell/{__version__}")
            writer.add_metadata(topics.METADATA_NAME, self._metadata)
            channels: dict[str, int] = {}
            for topic, (name, encoding, data, msg_encoding) in self._schemas.items():
                schema_id = writer.register_schema(name, encoding, data)
                channels[topic] = writer.register_channel(topic, msg_encoding, schema_id)
            self._file = _OpenFile(
                path,
                stream,
                writer,
                channels,
                dict.fromkeys(channels.values(), 0),
                time.monotonic(),
            )
            self._files.append(path)
            self._bytes_current = 0
            self._last_modes = None
            self._last_tf_ns = 0
            if self._frames is not None:
                urdf = self._frames.urdf()
                if urdf is not None:
                    ns = self._clock()
                    writer.add_attachment(
                        ns, ns, self._frames.attachment, topics.URDF_MEDIA_TYPE, urdf.encode()
                    )
                    self._add(topics.ROBOT_DESCRIPTION, ns, dumps({"data": urdf}), ns)
            self._flush(rotate=False)  # a new file holds at least one chunk of events
        except BaseException:
            self._file = None
            stream.close()
            path.unlink(missing_ok=True)
            raise
        log.info("recording to %s", path)
        if self._retention is not None:
            enforce(self.directory, self._retention, keep=(path,), prefix=self._prefix)

    def _open_stream(self, path: Path) -> IO[bytes]:
        """The file a log is written to (tests substitute a failing disk here)."""
        return open(path, "xb")  # lives as long as the file is recorded

    def _flush(self, rotate: bool = True) -> None:
        """Close the open chunk and push it to the disk (the crash-loss boundary)."""
        f = self._file
        if f is None:
            return
        try:
            f.writer.flush()  # type: ignore[no-untyped-call]
            if self._fsync:
                os.fsync(f.stream.fileno())
            self._bytes_current = f.stream.tell()
        except OSError as exc:
            self._fail(exc)
            return
        if self._pending:
            f.chunks += 1
            self._chunks += 1
        self._written += self._pending
        self._pending = 0
        self._chunk_started = self._chunk_first_ns = None
        if rotate and (
            self._bytes_current >= self.rotate_size
            or time.monotonic() - f.opened >= self.rotate_duration
        ):
            self._finish_file()
            self._reopen()

    def _finish_file(self) -> None:
        f = self._file
        if f is None:
            return
        try:
            f.writer.finish()  # type: ignore[no-untyped-call]  # closes the last chunk, writes the summary and footer
            f.stream.flush()
            if self._fsync:
                os.fsync(f.stream.fileno())
            size = f.stream.tell()
            f.stream.close()
        except OSError as exc:
            self._fail(exc)
            return
        if self._pending:
            self._chunks += 1
        self._written += self._pending
        self._pending = 0
        self._chunk_started = self._chunk_first_ns = None
        self._bytes_closed += size
        self._bytes_current = 0
        self._file = None
        log.info("finished log %s (%d bytes)", f.path, size)

    def _reopen(self) -> None:
        try:
            self._open_file()
        except OSError as exc:
            self._retry_at = time.monotonic() + self._retry_interval
            self._error(f"recorder cannot open a new log in {self.directory}: {exc}")

    def _fail(self, exc: OSError) -> None:
        """A write failed (disk full, I/O error): drop the open chunk, retry later."""
        f = self._file
        self._file = None
        self._dropped_write += self._pending
        self._pending = 0
        self._chunk_started = self._chunk_first_ns = None
        self._retry_at = time.monotonic() + self._retry_interval
        if f is not None:
            with contextlib.suppress(OSError):
                f.stream.close()
            if f.chunks == 0:  # nothing useful in it: do not leave empty files behind
                f.path.unlink(missing_ok=True)
                if f.path in self._files:
                    self._files.remove(f.path)
        where = f.path if f is not None else self.directory
        self._error(f"recorder cannot write {where}: {exc}; dropping messages until it can")

    # ----- reporting

    def _error(self, message: str) -> None:
        self._errors += 1
        self._last_error = message
        log.error("%s", message)
        if self._on_error is not None:
            try:
                self._on_error(message)
            except Exception:
                log.exception("recorder on_error callback failed")

    def _report(self, now: float, depth: int) -> None:
        if depth > self._max_queue // 2 and not self._queue_warned:
            self._queue_warned = True
            log.warning(
                "recorder queue at %d of %d messages: the disk is slow", depth, self._max_queue
            )
        elif depth < self._max_queue // 4:
            self._queue_warned = False
        dropped = self._dropped_full + self._dropped_write
        if dropped == self._reported_dropped:
            return
        if self._reported_dropped and now - self._last_report < REPORT_INTERVAL:
            return
        new = dropped - self._reported_dropped
        self._reported_dropped = dropped
        self._last_report = now
        message = f"recorder dropped {new} messages ({dropped} in total): " + (
            "queue full, the disk is too slow" if self._dropped_full else "write failures"
        )
        self._error(message)
        if self._file is not None:
            notice = {"level": "error", "message": message, "dropped": dropped,
                      "written": self._written}  # fmt: skip
            try:
                t = self._clock()
                self._add(topics.RECORDER, t, dumps(notice), t)
            except OSError as exc:
                self._fail(exc)


class _LogCapture(logging.Handler):
    """Hands ``fxcell`` log records to the recorder as LogEvents (from any thread)."""

    def __init__(self, submit: Callable[[Event], None], level: int) -> None:
        super().__init__(level)
        self._submit = submit

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = record.getMessage()
        except Exception:  # a malformed record must not break the caller
            message = str(record.msg)
        self._submit(
            LogEvent(
                record.created, record.levelno, record.name, message, record.pathname,
                record.lineno or 0,
            )
        )  # fmt: skip


def _name(value: Any) -> str:
    return str(getattr(value, "name", value))
