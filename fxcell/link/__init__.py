"""The robot link: a supervised process holding the ur_rtde clients, and its asyncio client.

Names load lazily, so that the link process (``python -m fxcell.link.process``) does not
import the asyncio client.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from fxcell.link.client import (
        LinkClient,
        LinkStatus,
        StateSubscription,
        TrajectoryHandle,
        TrajectoryProgress,
        TrajectoryResult,
    )

__all__ = [
    "LinkClient",
    "LinkStatus",
    "StateSubscription",
    "TrajectoryHandle",
    "TrajectoryProgress",
    "TrajectoryResult",
]


def __getattr__(name: str) -> Any:
    if name not in __all__:
        raise AttributeError(f"module 'fxcell.link' has no attribute {name!r}")
    value = getattr(importlib.import_module("fxcell.link.client"), name)
    globals()[name] = value
    return value
