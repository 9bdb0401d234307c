"""What the simulated controller tells its clients, as typed messages.

The controller emits these through ``Controller.on_robot_message``; the protocol modules
encode them (:func:`fxcell.sim.primary.encode_robot_message` for the primary/secondary
interfaces). The controller knows no wire format, so it imports no protocol module.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class TextMessage:
    """A text for the operator (``textmsg``, an error a program survives)."""

    text: str
    time: float  # controller time, s


@dataclass(frozen=True, slots=True)
class RuntimeException:
    """A compile or runtime error of a program, where it happened in the script."""

    text: str
    line: int
    column: int
    time: float  # controller time, s


RobotMessage = TextMessage | RuntimeException

__all__ = ["RobotMessage", "RuntimeException", "TextMessage"]
