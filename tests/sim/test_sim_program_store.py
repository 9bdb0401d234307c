"""The controller's program directory: Dashboard ``load`` of programs and installations,
and UR's own ``example_control_loop`` against the program it loads and plays."""

from __future__ import annotations

import os
import queue
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from dashboard_client import DashboardClient

from fxcell.testing import simulator

from .test_sim_primary import ur_pose_matrix
from .test_sim_rtde import dh_forward

pytestmark = pytest.mark.timeout(120)

VENDOR = Path(__file__).parent / "vendor"
EXAMPLES = VENDOR / "examples"
# the two setpoints of UR's example_control_loop.py
SETP1 = [-0.12, -0.43, 0.14, 0, 3.11, 0.04]
SETP2 = [-0.12, -0.51, 0.21, 0, 3.11, 0.04]
AT_SETP1 = [0.998, -0.867, 1.367, -2.032, -1.558, -0.573]  # elbow up, near SETP1

# The URScript PolyScope saves next to rtde_control_loop.urp (written here from the
# program's tree; its thread that copies the registers into ``setp`` is folded into the
# main loop, which reads them before every check).
CONTROL_LOOP_SCRIPT = """def rtde_control_loop():
  setp = p[0, 0, 0, 0, 0, 0]
  rtde_set_watchdog("input_int_register_0", 1, "PAUSE")
  write_output_integer_register(0, 1)
  while (True):
    tmp = p[0, 0, 0, 0, 0, 0]
    tmp[0] = read_input_float_register(0)
    tmp[1] = read_input_float_register(1)
    tmp[2] = read_input_float_register(2)
    tmp[3] = read_input_float_register(3)
    tmp[4] = read_input_float_register(4)
    tmp[5] = read_input_float_register(5)
    setp = tmp
    if (read_input_integer_register(0) == 1 and setp != p[0, 0, 0, 0, 0, 0]):
      # Valid pose received from client
      movel(setp, a=1.2, v=0.08)
      # Confirm that move was executed
      write_output_integer_register(0, 0)
      # Wait until script acknowledges confirmation
      while (read_input_integer_register(0) == 1):
        sync()
      end
      # Request next pose
      write_output_integer_register(0, 1)
    end
    sync()
  end
end
"""


@pytest.fixture
def store(tmp_path: Path) -> Path:
    shutil.copy(EXAMPLES / "rtde_control_loop.urp", tmp_path)
    (tmp_path / "rtde_control_loop.script").write_text(CONTROL_LOOP_SCRIPT)
    (tmp_path / "cell").mkdir()
    (tmp_path / "cell" / "site.installation").write_text("<Installation/>")
    return tmp_path


def test_load_answers_the_documented_replies_for_present_and_missing_files(store: Path) -> None:
    with simulator(programs=store) as sim:
        replies = {
            "load /programs/rtde_control_loop.urp": (
                "Loading program: /programs/rtde_control_loop.urp"
            ),
            "load rtde_control_loop.urp": "Loading program: /programs/rtde_control_loop.urp",
            "load missing.urp": "File not found: /programs/missing.urp",
            "load /programs/../etc/passwd.urp": "File not found: /etc/passwd.urp",
            "load fxcell.urp": "File not found: /programs/fxcell.urp",  # not in this store
            "load rtde_control_loop.script": (
                "Error while loading program: /programs/rtde_control_loop.script"
            ),
            "load installation cell/site.installation": (
                "Loading installation: cell/site.installation"
            ),
            "load installation missing.installation": "File not found: missing.installation",
            "saveLog": "Log saved to disk",
        }
        for request, reply in replies.items():
            assert sim.dashboard(request) == reply, request
        d = DashboardClient(sim.host)
        d.connect()
        try:
            d.loadURP("/programs/rtde_control_loop.urp")
            assert d.getLoadedProgram() == "Loaded program: /programs/rtde_control_loop.urp"
            with pytest.raises(RuntimeError):
                d.loadURP("/programs/missing.urp")
        finally:
            d.disconnect()


def test_the_default_store_holds_the_programs_the_embedded_default_plays() -> None:
    with simulator() as sim:
        for name in ("external_control.urp", "fxcell.urp", "default.urp"):
            assert sim.dashboard(f"load {name}") == f"Loading program: /programs/{name}"
        assert sim.dashboard("load installation default.installation") == (
            "Loading installation: default.installation"
        )
        assert sim.dashboard("load rtde_control_loop.urp") == (
            "File not found: /programs/rtde_control_loop.urp"
        )


def test_urs_example_control_loop_moves_between_its_setpoints(store: Path) -> None:
    with simulator(programs=store, joints=AT_SETP1) as sim:
        sim.bring_up()
        d = DashboardClient(sim.host)
        d.connect()
        try:
            d.loadURP("/programs/rtde_control_loop.urp")
            d.play()
            assert d.programState() == "PLAYING rtde_control_loop.urp"
        finally:
            d.disconnect()
        # UR's example, unmodified but for the robot's address it has as a constant
        source = (EXAMPLES / "example_control_loop.py").read_text()
        assert 'ROBOT_HOST = "localhost"' in source
        source = source.replace('ROBOT_HOST = "localhost"', f'ROBOT_HOST = "{sim.host}"')
        env = dict(os.environ, PYTHONPATH=str(VENDOR), PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            [sys.executable, "-c", source],
            cwd=EXAMPLES,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        lines: queue.Queue[str] = queue.Queue()

        def drain() -> None:
            assert proc.stdout is not None
            for line in proc.stdout:
                lines.put(line)
            lines.put("")

        reader = threading.Thread(target=drain, daemon=True)
        reader.start()
        confirmed: list[np.ndarray] = []
        output: list[str] = []
        try:
            deadline = time.monotonic() + 60
            while len(confirmed) < 3:
                line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
                output.append(line)
                assert line, f"the example ended: {''.join(output)}"
                if line.startswith("Move to confirmed pose = "):
                    q = [float(v) for v in line.split("=", 1)[1].strip(" []\n").split(",")]
                    confirmed.append(dh_forward(q))
        finally:
            proc.terminate()
            proc.wait(10)
            reader.join(5)
            if proc.stdout is not None:
                proc.stdout.close()
        # it went to SETP2, back to SETP1, to SETP2 again
        for T, setp in zip(confirmed, (SETP2, SETP1, SETP2), strict=True):
            assert np.allclose(T, ur_pose_matrix(setp), atol=1e-6), output
        assert sum(line.startswith("New pose = ") for line in output) >= 3
