"""The cell daemon: HTTP + JSON API (OpenAPI), WebSocket stream and the operator page.

Run it with ``fxcell daemon``; drive it with :class:`fxcell.client.RemoteCell`, the
``fxcell`` operator commands or the web page it serves at ``/``. Submodules:
``app`` (routes), ``service`` (what the routes serve), ``server`` (running it),
``operations``, ``control``, ``auth``, ``guard`` (request hygiene), ``connection``
(deadlines for reading a request), ``stream``, ``notify``, ``cli``. Nothing is
imported here, so that the CLI's registration stays cheap.
"""
