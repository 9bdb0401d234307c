"""fxcell: run a Universal Robots UR3e cell from asyncio Python."""

from fxcell._version import __version__
from fxcell.errors import FxcellError

__all__ = ["FxcellError", "__version__"]
