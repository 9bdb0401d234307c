"""Log retention: keep the log directory within a total size and an age, oldest first.

Only finished fxcell logs are candidates (``<prefix>_*.mcap`` files that no recorder holds
locked): the file being written, and files another process is still writing, are never
touched. Files older than ``max_age`` go first; then the oldest go until the rest fit in
``max_total_size``.
"""

from __future__ import annotations

import fcntl
import logging
import os
import time
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path

from fxcell.errors import InvalidArgumentError
from fxcell.recorder.topics import FILE_SUFFIX

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Retention:
    """Limits on a log directory (``None``: no limit of that kind)."""

    max_total_size: int | None = None
    """Bytes all logs may take together (the running file counts but is never removed)."""
    max_age: float | None = None
    """Seconds since a log was last written after which it is removed."""

    def __post_init__(self) -> None:
        if self.max_total_size is not None and self.max_total_size <= 0:
            raise InvalidArgumentError(f"max_total_size must be > 0, got {self.max_total_size}")
        if self.max_age is not None and not self.max_age > 0:
            raise InvalidArgumentError(f"max_age must be > 0 s, got {self.max_age}")


@dataclass
class RetentionReport:
    """What one pass removed and what is left."""

    removed: list[Path] = field(default_factory=list)
    freed: int = 0
    kept_bytes: int = 0


def _is_locked(path: Path) -> bool:
    """Whether a recorder (this process or another) holds ``path`` open for writing."""
    try:
        with open(path, "rb") as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    except OSError:
        return True  # vanished or unreadable: not ours to delete
    return False


def enforce(
    directory: Path,
    retention: Retention,
    *,
    keep: Collection[Path] = (),
    prefix: str = "fxcell",
    now: float | None = None,
    dry_run: bool = False,
) -> RetentionReport:
    """Remove the oldest finished logs in ``directory`` until ``retention`` holds.

    ``dry_run`` only reports what would be removed.
    """
    report = RetentionReport()
    if retention.max_total_size is None and retention.max_age is None:
        return report
    now = time.time() if now is None else now
    keep_resolved = {p.resolve() for p in keep}
    entries: list[tuple[float, int, Path, bool]] = []  # mtime, size, path, removable
    for path in directory.glob(f"{prefix}_*{FILE_SUFFIX}"):
        try:
            st = path.stat()
        except OSError:
            continue
        removable = path.resolve() not in keep_resolved
        entries.append((st.st_mtime, st.st_size, path, removable))
    entries.sort(key=lambda e: (e[0], e[2].name))  # oldest first
    total = sum(size for _, size, _, _ in entries)
    for mtime, size, path, removable in entries:
        too_old = retention.max_age is not None and now - mtime > retention.max_age
        too_big = retention.max_total_size is not None and total > retention.max_total_size
        if not (too_old or too_big):
            continue
        if not removable or _is_locked(path):
            continue
        total -= size
        report.removed.append(path)
        report.freed += size
        if dry_run:
            continue
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("log retention: cannot remove %s: %s", path, exc)
            total += size
            report.removed.pop()
            report.freed -= size
            continue
        log.info(
            "log retention removed %s (%.1f MB, %s)",
            path.name,
            size / 1e6,
            "too old" if too_old else "over the size limit",
        )
    report.kept_bytes = total
    return report
