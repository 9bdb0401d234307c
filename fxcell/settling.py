"""When a move has arrived: the joint tolerances shared by the link process and the move runner.

The move runner waits for every joint within :data:`SETTLE_POSITION` of its target and slower
than :data:`SETTLE_VELOCITY`; if the hold after the last sample ends first (a real arm's
encoders may never read 1e-6 rad), the move still counts as arrived within
:data:`ARRIVE_TOLERANCE`. The link process reports a trajectory settled on the looser bound,
so it never waits on a robot the runner would accept.
"""

from __future__ import annotations

SETTLE_POSITION = 1e-6
"""A move has arrived when every joint is within this of its target (rad)..."""
SETTLE_VELOCITY = 1e-3
"""...and slower than this (rad/s)."""
ARRIVE_TOLERANCE = 1e-4
"""The largest joint error still accepted when the hold ends (rad, about 50 µm at the TCP)."""
REST_VELOCITY = 1e-3
"""After a stop, the robot is at rest below this joint speed (rad/s)..."""
REST_TIME = 0.05
"""...in every state sample over this many seconds of controller time, before a recovery
takes control back or a move is sent again (26 samples of a UR's 500 Hz, whatever rate a
robot kind streams at)."""
