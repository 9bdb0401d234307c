"""Read fxcell's MCAP logs back: messages by topic, decoded, fast enough for hour-long files.

A finished file is read through its summary: chunk indexes say which chunks hold a
topic and message indexes where each message sits, so listing the commands of an
hour (1.8 million state samples) opens only the chunks that have commands and
decodes only those messages. An unfinished file (still recording, or cut off by a
crash) is walked linearly up to its last complete chunk.
"""

from __future__ import annotations

import io
import json
import os
import struct
from collections import Counter
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Schema
from mcap.summary import Summary

from fxcell.errors import RecorderError
from fxcell.recorder import topics
from fxcell.recorder.protobuf import decode_robot_state
from fxcell.recorder.recovery import (
    RawMessage,
    chunk_data,
    is_finished,
    iter_records,
    parse_message,
)

_RECORD = struct.Struct("<BQ")
_MESSAGE_HEADER = struct.Struct("<HIQQ")
_INDEX_ENTRY = struct.Struct("<QQ")
_OP_MESSAGE = 0x05
_OP_SCHEMA = 0x03
_OP_CHANNEL = 0x04


class LogMessage(NamedTuple):
    """One message as recorded (a named tuple: built once per message, so it must be cheap)."""

    topic: str
    log_time: int
    """Nanoseconds since the Unix epoch, when the event reached the recorder."""
    publish_time: int
    data: bytes

    @property
    def time(self) -> float:
        return self.log_time / 1e9


class LogReader:
    """One fxcell MCAP file, finished or not."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise RecorderError(f"no such log file: {self.path}")
        self.finished = is_finished(self.path)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: dict[str, bytes] = {}
        self._summary: Summary | None = None
        self._counts: Counter[str] = Counter()
        self._start: int | None = None
        self._end: int | None = None
        try:
            if self.finished:
                self._read_summary()
            else:
                self._scan()
        except RecorderError:
            raise
        except Exception as exc:
            raise RecorderError(f"cannot read {self.path}: {exc}") from None

    # ------------------------------------------------------------- overview

    def _read_summary(self) -> None:
        with open(self.path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None or summary.statistics is None:
                raise RecorderError(f"{self.path} has no summary section")
            self._summary = summary
            self.schemas = dict(summary.schemas)
            self.channels = dict(summary.channels)
            for meta in reader.iter_metadata():
                self.metadata[meta.name] = dict(meta.metadata)
            for att in reader.iter_attachments():
                self.attachments[att.name] = bytes(att.data)
        stats = summary.statistics
        for cid, n in stats.channel_message_counts.items():
            if cid in self.channels:
                self._counts[self.channels[cid].topic] += n
        if stats.message_count:
            self._start, self._end = stats.message_start_time, stats.message_end_time

    def _scan(self) -> None:
        from mcap.records import Attachment, Metadata

        for rec in iter_records(self.path):
            if isinstance(rec, RawMessage):
                ch = self.channels.get(rec.channel_id)
                if ch is not None:
                    self._counts[ch.topic] += 1
                t = rec.log_time
                self._start = t if self._start is None else min(self._start, t)
                self._end = t if self._end is None else max(self._end, t)
            elif isinstance(rec, Schema):
                self.schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                self.channels[rec.id] = rec
            elif isinstance(rec, Metadata):
                self.metadata[rec.name] = dict(rec.metadata)
            elif isinstance(rec, Attachment):
                self.attachments[rec.name] = bytes(rec.data)

    @property
    def counts(self) -> dict[str, int]:
        """Messages per topic."""
        return dict(self._counts)

    @property
    def start_time(self) -> int | None:
        return self._start

    @property
    def end_time(self) -> int | None:
        return self._end

    @property
    def duration(self) -> float:
        if self._start is None or self._end is None:
            return 0.0
        return (self._end - self._start) / 1e9

    def topic_schema(self, topic: str) -> tuple[Channel, Schema | None] | None:
        for ch in self.channels.values():
            if ch.topic == topic:
                return ch, self.schemas.get(ch.schema_id)
        return None

    # ------------------------------------------------------------- messages

    def messages(
        self,
        topic_names: Iterable[str] | None = None,
        *,
        start: int | None = None,
        end: int | None = None,
    ) -> Iterator[LogMessage]:
        """Raw messages of ``topic_names`` (all if None) in file order, within [start, end)."""
        wanted = None if topic_names is None else set(topic_names)
        names = {cid: ch.topic for cid, ch in self.channels.items()}
        ids = {cid for cid, t in names.items() if wanted is None or t in wanted}
        if not ids:
            return
        if self._summary is not None and self._summary.chunk_indexes:
            dense = wanted is None or bool(wanted & {topics.ROBOT_STATE, topics.TF})
            yield from self._indexed(ids, names, dense, start, end)
            return
        for rec in iter_records(self.path):
            if (
                isinstance(rec, RawMessage)
                and rec.channel_id in ids
                and (start is None or rec.log_time >= start)
                and (end is None or rec.log_time < end)
            ):
                yield LogMessage(names[rec.channel_id], rec.log_time, rec.publish_time, rec.data)

    def _indexed(
        self,
        ids: set[int],
        names: dict[int, str],
        dense: bool,
        start: int | None,
        end: int | None,
    ) -> Iterator[LogMessage]:
        assert self._summary is not None
        with open(self.path, "rb") as f:
            for ci in self._summary.chunk_indexes:
                if start is not None and ci.message_end_time < start:
                    continue
                if end is not None and ci.message_start_time >= end:
                    continue
                present = ids & ci.message_index_offsets.keys()
                if not present:
                    continue
                f.seek(ci.chunk_start_offset + 9)
                chunk = Chunk.read(ReadDataStream(io.BytesIO(f.read(ci.chunk_length - 9))))
                if dense:
                    yield from _scan_chunk(chunk, ids, names, start, end)
                    continue
                offsets: list[int] = []
                for cid in present:
                    f.seek(ci.message_index_offsets[cid])
                    _op, length = _RECORD.unpack(f.read(9))
                    body = f.read(length)
                    (n,) = struct.unpack_from("<I", body, 2)
                    offsets.extend(o for _, o in _INDEX_ENTRY.iter_unpack(body[6 : 6 + n]))
                data = _decompress(chunk)
                for off in sorted(offsets):
                    _op, length = _RECORD.unpack_from(data, off)
                    msg = parse_message(memoryview(data)[off + 9 : off + 9 + length])
                    if (start is None or msg.log_time >= start) and (
                        end is None or msg.log_time < end
                    ):
                        yield LogMessage(
                            names[msg.channel_id], msg.log_time, msg.publish_time, msg.data
                        )

    def decoded(
        self,
        topic_names: Iterable[str] | None = None,
        *,
        start: int | None = None,
        end: int | None = None,
    ) -> Iterator[tuple[LogMessage, Any]]:
        """Messages with their payload decoded: JSON as dicts, robot state as RobotState."""
        for msg in self.messages(topic_names, start=start, end=end):
            yield msg, decode(msg.topic, msg.data)


def decode(topic: str, data: bytes) -> Any:
    """Decode one message payload of an fxcell topic."""
    if topic == topics.ROBOT_STATE:
        return decode_robot_state(data)
    return json.loads(data)


def _decompress(chunk: Chunk) -> bytes:
    if chunk.compression == "zstd":
        import zstandard

        return bytes(
            zstandard.ZstdDecompressor().decompress(
                chunk.data, max_output_size=chunk.uncompressed_size
            )
        )
    if chunk.compression == "lz4":
        import lz4.frame  # type: ignore[import-untyped]

        return bytes(lz4.frame.decompress(chunk.data))
    return bytes(chunk.data)


def _scan_chunk(
    chunk: Chunk, ids: set[int], names: dict[int, str], start: int | None, end: int | None
) -> Iterator[LogMessage]:
    """The messages of ``ids`` in one chunk: one flat loop over the decompressed records (for
    the dense topics this is the read-back's inner loop, run once per message)."""
    data = chunk_data(chunk)
    if type(data) is not bytes:
        data = bytes(data)
    pos, size = 0, len(data)
    unpack_record = _RECORD.unpack_from
    unpack_header = _MESSAGE_HEADER.unpack_from
    new = tuple.__new__  # LogMessage._make without the classmethod call
    while pos + 9 <= size:
        opcode, length = unpack_record(data, pos)
        body = pos + 9
        pos = body + length
        if pos > size:
            raise RecorderError("record runs past the end of its chunk")
        if opcode != _OP_MESSAGE:
            continue
        if length < 22:
            raise RecorderError("message record shorter than its header")
        cid, _seq, log_time, publish_time = unpack_header(data, body)
        if cid in ids and (start is None or log_time >= start) and (end is None or log_time < end):
            yield new(LogMessage, (names[cid], log_time, publish_time, data[body + 22 : pos]))
