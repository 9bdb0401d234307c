"""The cell daemon: HTTP + JSON API (OpenAPI), WebSocket stream and the operator page.

Run it with ``fxcell daemon``; drive it with :class:`fxcell.client.RemoteCell`, the
``fxcell`` operator commands or the web page it serves at ``/``.
"""

from fxcell.daemon.app import create_app
from fxcell.daemon.service import CellService

__all__ = ["CellService", "create_app"]
