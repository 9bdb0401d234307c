"""What the cell is taught: named positions and re-taught station frames, in one YAML file.

The file (``positions_file`` of the configuration) holds::

    positions:
      above_rack: {joints: [...6 rad], pose: [x, y, z, rx, ry, rz], taught: <ISO time>,
                   previous: {joints: ..., pose: ..., taught: ...}}
    frames:
      rack: {origin: [x, y, z], x_point: [...], xy_point: [...], taught: ..., previous: {...}}

Every write goes to a temporary file in the same directory, is flushed to disk and then
renamed over the old one, so a crash leaves either the old or the new file, never half of
one. Re-teaching keeps the value it replaces under ``previous``.
"""

from __future__ import annotations

import datetime
import os
import re
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from fxcell.errors import ConfigError, InvalidArgumentError, UnknownPositionError
from fxcell.layout import LayoutConfig

_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,63}$")
FRAME_POINTS = ("origin", "x_point", "xy_point")


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


class TaughtStore:
    """The taught positions and frames of one cell (read on creation, written on teach)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.positions: dict[str, dict[str, Any]] = {}
        self.frames: dict[str, dict[str, Any]] = {}
        self._load()

    def _load(self) -> None:
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return
        except OSError as exc:
            raise ConfigError(f"cannot read taught positions {self.path}: {exc.strerror}") from None
        try:
            data = yaml.safe_load(text) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{self.path}: not valid YAML: {exc}") from None
        if not isinstance(data, dict) or not set(data) <= {"positions", "frames"}:
            raise ConfigError(f"{self.path}: expected the keys 'positions' and 'frames'")
        self.positions = dict(data.get("positions") or {})
        self.frames = dict(data.get("frames") or {})
        for name, entry in self.positions.items():
            joints = entry.get("joints") if isinstance(entry, dict) else None
            if not isinstance(joints, list) or len(joints) != 6:
                raise ConfigError(f"{self.path}: position {name!r} needs six joint values")

    def _save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        data = {"positions": self.positions, "frames": self.frames}
        text = yaml.safe_dump(data, sort_keys=True, default_flow_style=None)
        fd, tmp = tempfile.mkstemp(prefix=".positions-", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        dir_fd = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)  # the rename itself survives a power loss
        finally:
            os.close(dir_fd)

    # ------------------------------------------------------------ positions

    def position(self, name: str) -> dict[str, Any]:
        """The taught position ``name`` or :class:`UnknownPositionError` listing the known ones."""
        try:
            return self.positions[name]
        except (KeyError, TypeError):
            known = ", ".join(sorted(self.positions)) or "none taught yet"
            raise UnknownPositionError(f"no taught position {name!r} (known: {known})") from None

    def teach_position(self, name: str, joints: Sequence[float], pose: Sequence[float]) -> None:
        """Store (or re-teach, keeping the old value as ``previous``) position ``name``."""
        check_name(name)
        entry: dict[str, Any] = {
            "joints": [float(v) for v in joints],
            "pose": [float(v) for v in pose],
            "taught": _now(),
        }
        old = self.positions.get(name)
        if old is not None:
            entry["previous"] = {k: v for k, v in old.items() if k != "previous"}
        self.positions[name] = entry
        self._save()

    # ------------------------------------------------------------ frames

    def teach_frame_point(
        self, station: str, point: str, position: Sequence[float], current: dict[str, Any]
    ) -> dict[str, Any]:
        """Record one of a station frame's three points. The frame changes only once all
        three have been re-taught (in any order), so that planning never uses a frame made of
        old and new points; ``current`` is the frame in use. Returns ``{"applied": bool,
        "pending": [points still to teach], "frame": the frame in use afterwards}``."""
        check_frame_point(station, point)
        entry = dict(self.frames.get(station) or {k: list(current[k]) for k in FRAME_POINTS})
        pending = dict(entry.get("pending") or {})
        pending[point] = [float(v) for v in position]
        if set(pending) == set(FRAME_POINTS):
            previous = {k: list(current[k]) for k in FRAME_POINTS}
            if "taught" in entry:
                previous["taught"] = entry["taught"]
            entry = {**pending, "taught": _now(), "previous": previous}
        else:
            entry["pending"] = pending
        self.frames[station] = entry
        self._save()
        frame = {k: entry[k] for k in FRAME_POINTS}
        waiting = entry.get("pending")
        missing = [] if waiting is None else [k for k in FRAME_POINTS if k not in waiting]
        return {"applied": waiting is None, "pending": missing, "frame": frame}

    def apply_frames(self, layout: LayoutConfig) -> LayoutConfig:
        """``layout`` with the taught frames in place of the configured ones."""
        if not self.frames:
            return layout
        data = layout.model_dump()
        for station, frame in self.frames.items():
            if station in data["stations"]:
                data["stations"][station]["frame"] = {k: frame[k] for k in FRAME_POINTS}
        try:
            return LayoutConfig.model_validate(data)
        except ValueError as exc:
            raise ConfigError(f"{self.path}: taught frames: {exc}") from None


def check_frame_point(station: str, point: str) -> str:
    """``point`` if it names a point of a station frame, else InvalidArgumentError."""
    if point not in FRAME_POINTS:
        raise InvalidArgumentError(
            f"{station}: frame point must be one of {', '.join(FRAME_POINTS)}, not {point!r}"
        )
    return point


def check_name(name: str) -> str:
    if not isinstance(name, str) or not _NAME.match(name):
        raise InvalidArgumentError(
            f"position name {name!r}: a letter, then letters, digits, '_' or '-' (≤ 64)"
        )
    return name
