"""The MCAP flight recorder: every command, transition and 500 Hz state sample of the cell.

``Recorder(directory).attach(bus)`` records a :class:`~fxcell.events.EventBus` into
rotating, chunked, crash-recoverable MCAP files that Foxglove opens directly;
:func:`recover` repairs a file cut off by a crash; :class:`Retention` bounds the
directory's size and age; topic names live in :mod:`fxcell.recorder.topics`.
``fxcell replay`` reads the files back.
"""

from __future__ import annotations

from fxcell.recorder import topics
from fxcell.recorder.recorder import Recorder, RecorderStats
from fxcell.recorder.recovery import RecoveryReport, is_finished, recover, recover_unfinished
from fxcell.recorder.retention import Retention, RetentionReport

__all__ = [
    "Recorder",
    "RecorderStats",
    "RecoveryReport",
    "Retention",
    "RetentionReport",
    "is_finished",
    "recover",
    "recover_unfinished",
    "topics",
]
