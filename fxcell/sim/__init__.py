"""An embedded UR3e (PolyScope 5.x) controller simulator.

Run it as its own process (``python -m fxcell.sim`` or ``fxcell sim``): it serves the
Dashboard (29999), RTDE (30004) and script (30003, 30002) ports on one loopback
address, so the unmodified ur_rtde clients talk to it as to a real controller.
Runtime code never imports this package; it starts the process through
:mod:`fxcell.link.embedded`. Tests use :func:`fxcell.testing.simulator`.
"""
