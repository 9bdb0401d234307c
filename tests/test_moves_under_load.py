"""Moves beside CPU burners never brake on a state stream the busy machine delayed.

CI runs on two cores that other jobs may keep busy. The simulator keeps its 2 ms cycle
(SCHED_FIFO, tests/conftest.py) and the robot-link process asks for SCHED_FIFO itself
(``fxcell.link.realtime``); without the latter, two busy loops starved the link's state
pump for 80+ ms while the controller's samples waited in its socket (22880 bytes unread,
measured 2026-11-26), and the move braked on ``state_stalled`` or the link went down.
This test runs moves beside one burner per core and counts those brakes; the stall
timeout itself is unchanged (``tests/test_follower.py`` judges its meaning).
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
from collections.abc import Iterator

import pytest

from fxcell.cell import Cell
from fxcell.config import CellConfig
from fxcell.testing import SimulatorHandle

pytestmark = [pytest.mark.timeout(120), pytest.mark.alone]  # the burners are the load

CONFIG = CellConfig.load()
MOVES = 16
BURNERS = 2  # one per core of the CI machine
BURN_FOR = 110  # s: a burner ends by itself even if this test is killed


@pytest.fixture
def burners() -> Iterator[None]:
    code = f"import time\nend = time.monotonic() + {BURN_FOR}\nwhile time.monotonic() < end: pass"
    procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(BURNERS)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


def realtime_permitted() -> bool:
    """Whether a process of this user may take SCHED_FIFO (asked in a short-lived thread:
    Linux schedules threads one by one, so this test's own scheduling stays as it is)."""
    if not hasattr(os, "sched_setscheduler"):
        return False
    ok: list[bool] = []

    def ask() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except OSError:
            ok.append(False)
        else:
            ok.append(True)

    thread = threading.Thread(target=ask)
    thread.start()
    thread.join()
    return ok[0]


@pytest.mark.skipif(
    not realtime_permitted(),
    reason="without real-time scheduling (CAP_SYS_NICE or RLIMIT_RTPRIO) burners starve the link",
)
async def test_moves_beside_cpu_burners_never_brake_on_a_stalled_state_stream(
    sim: SimulatorHandle, burners: None, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="fxcell")
    home = list(CONFIG.home)
    async with Cell(sim.host, config=CONFIG) as cell:
        await cell.init()
        await cell.set_velocity_factor(0.3)
        for k in range(MOVES):
            target = [home[0] + (0.2 if k % 2 == 0 else 0.0), *home[1:]]
            await cell.move_joint(target)
    stalls = [r.getMessage() for r in caplog.records if "stalled" in r.getMessage()]
    downs = [r.getMessage() for r in caplog.records if "no robot state" in r.getMessage()]
    assert stalls == []
    assert downs == []
