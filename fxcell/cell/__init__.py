"""The cell layer: :class:`Cell` (commands, guards, move tasks) and the robot-mode state machine."""

from __future__ import annotations

from fxcell.cell.cell import Cell
from fxcell.cell.statemachine import CellState
from fxcell.results import ProgramStatus

__all__ = ["Cell", "CellState", "ProgramStatus"]
