"""Where fxcell's shipped resources are: the default configuration and the statecharts.

The repository keeps ``config/`` and ``statecharts/`` at its top level; the wheel maps them
into the package as ``fxcell/_resources/config`` and ``fxcell/_resources/statecharts``
(hatchling's ``force-include`` in ``pyproject.toml``). An installed fxcell reads them from
there; a source checkout (editable install, tests) reads the top-level folders.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path
from typing import Literal

Resource = Literal["config", "statecharts"]

_SOURCE_ROOT = Path(__file__).resolve().parent.parent


def resource_dir(name: Resource) -> Path:
    """The directory holding the shipped ``config`` or ``statecharts`` files."""
    packaged = Path(str(files("fxcell"))) / "_resources" / name
    if packaged.is_dir():
        return packaged
    return _SOURCE_ROOT / name
