"""fxcell: run a Universal Robots UR3e cell from asyncio Python."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from fxcell.errors import FxcellError

if TYPE_CHECKING:
    from fxcell._version import __version__
    from fxcell.cell import Cell
    from fxcell.cell.statemachine import CellState
    from fxcell.client import RemoteCell
    from fxcell.commands import CellCommands
    from fxcell.config import CellConfig
    from fxcell.protocol import ProgramState, RobotMode, RobotState, SafetyMode
    from fxcell.results import MoveResult, ProgramStatus

# Loaded on first use, so that ``import fxcell`` (and the robot-link process, which
# imports fxcell.link) stays fast; even the version (importlib.metadata is slow).
_LAZY = {
    "__version__": "fxcell._version",
    "Cell": "fxcell.cell",
    "ProgramStatus": "fxcell.results",
    "CellConfig": "fxcell.config",
    "CellState": "fxcell.cell.statemachine",
    "CellCommands": "fxcell.commands",
    "RemoteCell": "fxcell.client",
    "MoveResult": "fxcell.results",
    "ProgramState": "fxcell.protocol",
    "RobotMode": "fxcell.protocol",
    "RobotState": "fxcell.protocol",
    "SafetyMode": "fxcell.protocol",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'fxcell' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


__all__ = [
    "Cell",
    "CellCommands",
    "CellConfig",
    "CellState",
    "FxcellError",
    "MoveResult",
    "ProgramState",
    "ProgramStatus",
    "RemoteCell",
    "RobotMode",
    "RobotState",
    "SafetyMode",
    "__version__",
]
