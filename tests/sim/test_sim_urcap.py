"""ExternalControl URCap mode: playing external_control.urp fetches the script from the PC."""

from __future__ import annotations

import time

from dashboard_client import DashboardClient
from rtde_control import RTDEControlInterface
from rtde_receive import RTDEReceiveInterface

from fxcell.testing import simulator, urcap_port, uses_urcap_port

from .test_sim_control import START, fresh, wait_until


@uses_urcap_port
def test_urcap_program_requests_the_script_and_runs_it() -> None:
    flags = RTDEControlInterface.FLAG_USE_EXT_UR_CAP | RTDEControlInterface.FLAG_NO_WAIT
    with (
        urcap_port() as port,
        simulator(joints=START, extra_args=["--urcap-port", str(port)]) as sim,
    ):
        sim.bring_up()
        d = DashboardClient(sim.host)
        d.connect()
        c = RTDEControlInterface(sim.host, -1.0, flags, port)
        r = RTDEReceiveInterface(sim.host)
        try:
            d.loadURP("external_control.urp")
            assert not c.isProgramRunning()
            d.play()
            assert d.programState() == "PLAYING external_control.urp"
            wait_until(lambda: sim.state()["control_script"], what="the script from the PC")
            target = [0.3, *START[1:]]
            t0 = time.monotonic()
            assert c.moveJ(target, 1.0, 2.0)
            assert time.monotonic() - t0 < 3.0
            assert fresh(r).getActualQ() == target
            c.stopScript()
            wait_until(lambda: d.programState() == "STOPPED external_control.urp")
        finally:
            c.disconnect()
            r.disconnect()
            d.disconnect()


def test_urcap_program_stops_when_no_pc_serves_the_script() -> None:
    with simulator(joints=START, extra_args=["--urcap-port", "1"]) as sim:
        sim.bring_up()
        assert sim.dashboard("load external_control.urp").startswith("Loading program:")
        assert sim.dashboard("play") == "Starting program"
        wait_until(lambda: sim.dashboard("running") == "Program running: false", timeout=10)
        assert "cannot reach the remote PC" in sim.state()["last_stop_reason"]
