"""Simulator RTDE streaming: period (median, p99) and CPU share at 500 Hz.

The simulator serves two clients at once, as in a cell: a receive client with ur_rtde's
default recipe (a raw RTDE client in its own process that timestamps every packet on
arrival) and the real ur_rtde RTDEControlInterface streaming servoJ at 500 Hz. The
period is measured from the client side (packet arrivals at the receive client), not by
the simulator; its CPU share comes from /proc over the same window. The simulator runs
at its parent's priority (FXCELL_SIM_PRIORITY=normal, set by the bench harness), like the
peer.

Peer: a plain Python 500 Hz loop (absolute deadlines, time.sleep), run here before the
simulator, whose period is what "steady 500 Hz from Python" costs on this machine.
Targets: p99 arrival period <= the plain loop's p99 + 0.5 ms (same run) and < 15 % of one
core.

    ./dev bench sim_stream [SECONDS] [--realtime]
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time

import numpy as np
from _harness import Targets

from fxcell.link.embedded import stats
from fxcell.testing import simulator

DEFAULT_RECIPE = (
    "timestamp,target_q,target_qd,target_qdd,target_current,target_moment,actual_q,actual_qd,"
    "actual_current,joint_control_output,actual_TCP_pose,actual_TCP_speed,actual_TCP_force,"
    "target_TCP_pose,target_TCP_speed,actual_digital_input_bits,joint_temperatures,"
    "actual_execution_time,robot_mode,joint_mode,safety_mode,actual_tool_accelerometer,"
    "speed_scaling,target_speed_fraction,actual_momentum,actual_main_voltage,"
    "actual_robot_voltage,actual_robot_current,actual_joint_voltage,"
    "actual_digital_output_bits,runtime_state,standard_analog_input0,standard_analog_input1,"
    "standard_analog_output0,standard_analog_output1,robot_status_bits,safety_status_bits,"
    "ft_raw_wrench,payload,payload_cog,payload_inertia"
)

RECEIVER = r"""
import json, socket, struct, sys, time
host, seconds, recipe = sys.argv[1], float(sys.argv[2]), sys.argv[3]
s = socket.create_connection((host, 30004))
s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
def send(kind, payload=b""):
    s.sendall(struct.pack(">HB", len(payload) + 3, kind) + payload)
buf = b""
def packet():
    global buf
    while len(buf) < 3 or len(buf) < struct.unpack_from(">H", buf)[0]:
        chunk = s.recv(65536)
        if not chunk:
            raise SystemExit("the simulator closed the RTDE connection")
        buf += chunk
    size, kind = struct.unpack_from(">HB", buf)
    p, buf = buf[3:size], buf[size:]
    return kind, p
send(86, struct.pack(">H", 2)); packet()
send(79, struct.pack(">d", 500.0) + recipe.encode()); packet()
send(83); packet()
arrivals, stamps = [], []
end = time.perf_counter() + seconds
while True:
    kind, p = packet()
    now = time.perf_counter()
    if kind == 85:
        arrivals.append(now)
        stamps.append(struct.unpack_from(">d", p, 1)[0])
    if now > end:
        break
send(80)  # pause the stream before the (slow) JSON dump
print(json.dumps({"arrivals": arrivals, "stamps": stamps}))
"""


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def describe(periods_s: np.ndarray) -> str:
    ms = periods_s * 1e3
    return (
        f"median {np.median(ms):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms, "
        f"p99.9 {np.percentile(ms, 99.9):.3f} ms, max {ms.max():.3f} ms"
    )


def plain_loop(seconds: float) -> np.ndarray:
    """The peer: a plain Python 500 Hz loop on absolute deadlines."""
    period = 0.002
    ticks = []
    deadline = time.perf_counter() + period
    end = time.perf_counter() + seconds
    while deadline < end:
        delay = deadline - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        ticks.append(time.perf_counter())
        deadline += period
    return np.diff(np.asarray(ticks))


def main() -> int:
    from rtde_control import RTDEControlInterface

    numbers = [a for a in sys.argv[1:] if not a.startswith("--")]
    seconds = float(numbers[0]) if numbers else 10.0
    print(f"sim_stream: {seconds:g} s windows, {os.cpu_count()} CPUs, load {os.getloadavg()}")
    peer = plain_loop(seconds)
    print(f"peer  plain Python 500 Hz loop: {describe(peer)}")

    extra = ["--realtime"] if "--realtime" in sys.argv else []
    with simulator(
        time_scale=0.05, joints=[0.0, -1.2, 1.2, -1.57, -1.57, 0.0], extra_args=extra
    ) as sim:
        sim.bring_up()
        pid = sim._sim.process.pid  # type: ignore[union-attr]
        control = RTDEControlInterface(sim.host)
        receiver = subprocess.Popen(
            [sys.executable, "-c", RECEIVER, sim.host, str(seconds + 1.5), DEFAULT_RECIPE],
            stdout=subprocess.PIPE,
            text=True,
        )
        time.sleep(0.5)  # the receiver connects and starts its stream
        stats(sim.host, reset=True)
        cpu0, wall0 = cpu_seconds(pid), time.perf_counter()
        q0 = [0.0, -1.2, 1.2, -1.57, -1.57, 0.0]
        deadline = time.perf_counter()
        i = 0
        window_end = time.perf_counter() + seconds  # the receiver streams 1 s longer
        while time.perf_counter() < window_end:
            s = 0.2 * math.sin(2 * math.pi * 0.25 * i * 0.002)
            control.servoJ([q0[0] + s, *q0[1:5], q0[5] - s], 0.5, 0.5, 0.002, 0.1, 300)
            i += 1
            deadline += 0.002
            delay = deadline - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.05:
                deadline = time.perf_counter()
        cpu1, wall1 = cpu_seconds(pid), time.perf_counter()
        own = stats(sim.host)
        out, _ = receiver.communicate()
        state = sim.state()
        print(f"simulator: {state['safety_mode']}, {state['last_stop_reason'] or 'no stop'}")
        control.servoStop()
        control.stopScript()
        control.disconnect()

    data = json.loads(out)
    arrivals = np.diff(np.asarray(data["arrivals"]))
    stamps = np.diff(np.asarray(data["stamps"]))
    share = (cpu1 - cpu0) / (wall1 - wall0)
    print(
        f"sim   send period measured by the simulator: median {own['period_ms_median']:.3f} ms, "
        f"p99 {own['period_ms_p99']:.3f} ms, max {own['period_ms_max']:.3f} ms "
        f"({own['send_cycles']} cycles, {own['late_cycles']} late)"
    )
    print(f"sim   packet arrival period at the receive client: {describe(arrivals)}")
    print(
        f"sim   controller timestamps: {len(stamps) + 1} packets, steps of 2 ms: "
        f"{np.mean(np.isclose(stamps, 0.002, atol=1e-9)) * 100:.2f} %, "
        f"late cycles caught up: {state['late_cycles']}"
    )
    print(f"sim   CPU share while serving receive + control (servoJ 500 Hz): {share * 100:.1f} %")
    print(f"servoJ commands sent: {i}")
    p99, peer_p99 = np.percentile(arrivals, 99), np.percentile(peer, 99)
    print(f"ratio p99 arrival period / peer loop period: {p99 / peer_p99:.2f}")
    targets = Targets("sim_stream")
    # Relative to the plain loop: a 500 Hz Python loop on this 2-core VM itself shows a p99
    # period of 2.6-3.9 ms from run to run, so no absolute figure below that can be met.
    targets.check(
        "p99 RTDE arrival period (bound: plain loop's p99 + 0.5 ms)", p99 * 1e3, "<=",
        peer_p99 * 1e3 + 0.5, "ms", peer=peer_p99 * 1e3, peer_name="plain 500 Hz loop",
    )  # fmt: skip
    targets.check("simulator CPU share (receive + servoJ)", share * 100, "<", 15.0, "% core")
    return targets.finish()


if __name__ == "__main__":
    raise SystemExit(main())
