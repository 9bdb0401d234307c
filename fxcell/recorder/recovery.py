"""Recover MCAP files cut off by a crash: keep everything up to the last complete chunk.

A file whose writer never ran ``finish()`` has no summary and no footer, and its
last record may be cut in the middle. :func:`iter_records` walks the records and
stops at the first one that is truncated or whose chunk fails its CRC;
:func:`recover` rewrites what it found as a finished file (in place by default).
A file a recorder still writes is locked (``flock``) and left alone.
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import json
import logging
import mmap
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Header, Metadata, Schema
from mcap.writer import Writer

from fxcell.errors import RecorderError
from fxcell.recorder import topics

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
_RECORD = struct.Struct("<BQ")
_MESSAGE_HEADER = struct.Struct("<HIQQ")


def is_finished(path: Path) -> bool:
    """True if the file ends with the MCAP footer magic (its writer finished it)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            if f.tell() < 2 * len(MAGIC):
                return False
            f.seek(-len(MAGIC), os.SEEK_END)
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def is_locked(path: Path) -> bool:
    """True if a recorder (in any process) is writing the file right now."""
    try:
        with open(path, "rb") as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
            return False
    except OSError:
        return False


@dataclass(frozen=True, slots=True)
class RawMessage:
    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes


@dataclass
class RecoveryReport:
    """What :func:`recover` kept."""

    source: Path
    output: Path
    messages: int
    chunks: int
    bad_chunks: int
    kept_bytes: int
    """Bytes of the original up to the end of the last complete record."""
    total_bytes: int
    start_time: int | None
    end_time: int | None

    def __str__(self) -> str:
        span = ""
        if self.start_time is not None and self.end_time is not None:
            span = f", {(self.end_time - self.start_time) / 1e9:.3f} s of data"
        lost = self.total_bytes - self.kept_bytes
        return (
            f"{self.output}: {self.messages} messages in {self.chunks} chunks{span}; "
            f"{lost} trailing bytes unreadable"
            + (f", {self.bad_chunks} corrupt chunks skipped" if self.bad_chunks else "")
        )


def chunk_records(chunk: Chunk) -> Iterator[tuple[int, memoryview]]:
    """(opcode, body) of each record inside a chunk, after checking its CRC."""
    data = chunk_data(chunk)
    view = memoryview(data)
    pos, end = 0, len(data)
    unpack = _RECORD.unpack_from
    while pos + 9 <= end:
        opcode, length = unpack(view, pos)
        body_end = pos + 9 + length
        if body_end > end:
            raise RecorderError("record runs past the end of its chunk")
        yield opcode, view[pos + 9 : body_end]
        pos = body_end


def chunk_data(chunk: Chunk) -> bytes:
    """The records of a chunk, decompressed, after checking its CRC."""
    data: bytes
    if chunk.compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size
        )
    elif chunk.compression == "lz4":
        import lz4.frame  # type: ignore[import-untyped]

        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise RecorderError(f"unsupported chunk compression {chunk.compression!r}")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise RecorderError("chunk CRC mismatch")
    return data


def parse_message(body: bytes | memoryview) -> RawMessage:
    channel_id, sequence, log_time, publish_time = _MESSAGE_HEADER.unpack_from(body)
    return RawMessage(channel_id, sequence, log_time, publish_time, bytes(body[22:]))


def _read(cls: Any, body: bytes | memoryview) -> Any:
    return cls.read(ReadDataStream(io.BytesIO(body)))


@dataclass
class _Walk:
    """State of a walk through a possibly truncated file."""

    kept_bytes: int = 0
    chunks: int = 0
    bad_chunks: int = 0
    finished: bool = False


def iter_records(path: Path, walk: _Walk | None = None) -> Iterator[Any]:
    """Header, Schema, Channel, RawMessage, Metadata and Attachment records in file order.

    Chunks are opened; a truncated record or a chunk failing its CRC ends the walk
    (the data after a torn write cannot be trusted). Index and summary records are skipped.
    """
    walk = walk if walk is not None else _Walk()
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size < len(MAGIC):  # cut off right after it was created: an empty log
            if f.read() != MAGIC[:size]:
                raise RecorderError(f"{path} is not an MCAP file")
            return
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            if mm[: len(MAGIC)] != MAGIC:
                raise RecorderError(f"{path} is not an MCAP file")
            pos = walk.kept_bytes = len(MAGIC)
            while pos + 9 <= size:
                opcode, length = _RECORD.unpack_from(mm, pos)
                end = pos + 9 + length
                if end > size:
                    break  # torn write
                body = mm[pos + 9 : end]
                if opcode == Opcode.CHUNK:
                    try:
                        chunk = _read(Chunk, body)
                        inner = [_record(op, bytes(rec)) for op, rec in chunk_records(chunk)]
                    except Exception:  # corrupt: stop, later data is suspect
                        walk.bad_chunks += 1
                        break
                    walk.chunks += 1
                    yield from (item for item in inner if item is not None)
                elif opcode == Opcode.DATA_END:  # the summary after it repeats what we saw
                    walk.kept_bytes = end
                    walk.finished = True
                    break
                else:
                    item = _record(opcode, body)
                    if item is not None:
                        yield item
                walk.kept_bytes = pos = end


def _record(opcode: int, body: bytes | memoryview) -> Any:
    if opcode == Opcode.MESSAGE:
        return parse_message(body)
    if opcode == Opcode.SCHEMA:
        return _read(Schema, body)
    if opcode == Opcode.CHANNEL:
        return _read(Channel, body)
    if opcode == Opcode.METADATA:
        return _read(Metadata, body)
    if opcode == Opcode.ATTACHMENT:
        return _read(Attachment, body)
    if opcode == Opcode.HEADER:
        return _read(Header, body)
    return None


def recover(
    path: str | os.PathLike[str], output: str | os.PathLike[str] | None = None
) -> RecoveryReport:
    """Rewrite the readable part of ``path`` as a finished MCAP file.

    ``output`` defaults to ``path`` itself (replaced atomically once the new file is
    complete). Raises :class:`RecorderError` if the file is being recorded or is not MCAP.
    """
    src = Path(path)
    dst = Path(output) if output is not None else src
    if not src.is_file():
        raise RecorderError(f"no such log file: {src}")
    if is_locked(src):
        raise RecorderError(f"{src} is being recorded right now; recover it after it stops")
    tmp = dst.with_name(dst.name + ".recovering")
    walk = _Walk()
    messages = 0
    start: int | None = None
    end: int | None = None
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    pending_channels: dict[int, Channel] = {}
    library = "fxcell"
    try:
        with open(tmp, "wb") as out:
            writer = Writer(out)
            started = False
            for rec in iter_records(src, walk):
                if isinstance(rec, Header):
                    library = rec.library or library
                    continue
                if not started:
                    writer.start(profile="", library=library)
                    started = True
                if isinstance(rec, Schema):
                    if rec.id not in schema_ids:
                        schema_ids[rec.id] = writer.register_schema(
                            rec.name, rec.encoding, rec.data
                        )
                elif isinstance(rec, Channel):
                    pending_channels[rec.id] = rec
                elif isinstance(rec, RawMessage):
                    new = channel_ids.get(rec.channel_id)
                    if new is None:
                        ch = pending_channels.get(rec.channel_id)
                        if ch is None:
                            continue  # its channel record was lost: cannot be decoded
                        new = channel_ids[rec.channel_id] = writer.register_channel(
                            ch.topic, ch.message_encoding, schema_ids.get(ch.schema_id, 0),
                            dict(ch.metadata),
                        )  # fmt: skip
                    writer.add_message(new, rec.log_time, rec.data, rec.publish_time, rec.sequence)
                    messages += 1
                    start = rec.log_time if start is None else min(start, rec.log_time)
                    end = rec.log_time if end is None else max(end, rec.log_time)
                elif isinstance(rec, Metadata):
                    writer.add_metadata(rec.name, dict(rec.metadata))
                elif isinstance(rec, Attachment):
                    writer.add_attachment(
                        rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data
                    )
            if not started:
                writer.start(profile="", library=library)
            total = src.stat().st_size
            writer.add_metadata(
                topics.RECOVERY_METADATA_NAME,
                {
                    "source": src.name,
                    "source_bytes": str(total),
                    "kept_bytes": str(walk.kept_bytes),
                    "messages": str(messages),
                    "chunks": str(walk.chunks),
                    "corrupt_chunks": str(walk.bad_chunks),
                    "was_finished": json.dumps(walk.finished),
                },
            )
            writer.finish()  # type: ignore[no-untyped-call]
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, dst)
    except RecorderError:
        tmp.unlink(missing_ok=True)
        raise
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise RecorderError(f"cannot recover {src}: {exc}") from None
    return RecoveryReport(
        src, dst, messages, walk.chunks, walk.bad_chunks, walk.kept_bytes, total, start, end
    )


def recover_unfinished(directory: Path) -> list[RecoveryReport]:
    """Recover every unfinished, unlocked ``*.mcap`` in ``directory`` in place."""
    reports = []
    for path in sorted(directory.glob("*.mcap")):
        if is_finished(path) or is_locked(path):
            continue
        try:
            reports.append(recover(path))
        except RecorderError as exc:
            log.error("cannot recover %s: %s", path, exc)
    for stale in directory.glob("*.mcap.recovering"):  # a recovery that was itself cut off
        with contextlib.suppress(OSError):
            stale.unlink()
    return reports
