"""The robot link: a supervised process holding the ur_rtde clients, and its asyncio client.

Only the client is imported here; ``fxcell.link.process`` runs in its own process.
"""

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
