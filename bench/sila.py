"""STOP over SiLA 2 against STOP over HTTP, same daemon, same run.

Starts ``fxcell daemon --sila`` on the embedded simulator (a child process, as in
production; SiLA over TLS with the daemon's generated certificate) and measures, with the
reference package's generic client (``sila2.client.SilaClient``) and a keep-alive HTTP client:

- **idle STOP**: ``CellController.Stop`` and ``POST /api/cell/stop`` with no move running,
  interleaved call by call (N each), so both see the same machine load: the round trip of
  a robot command through each API (token check, one operation on the daemon's loop);
- **STOP during a move**: a base move started over HTTP, stopped after 0.3-0.8 s by either
  API in turn; the time from sending the stop to its answer (the cell has told the arm to
  brake) and to the operation of the move having ended (the arm at rest on its path).

Peer: the HTTP API, measured in the same run. Target: SiLA STOP p50 and p99 (idle) within
2 ms of HTTP's; during a move, the p50 time until the move's operation ended within
10 ms of HTTP's.
"""

from __future__ import annotations

import argparse
import os
import random
import tempfile
import time
from pathlib import Path

import httpx
import yaml
from _harness import Targets
from sila2.client import SilaClient

from fxcell.daemon.process import DaemonProcess, free_port

TOKEN = "bench-token-0123456789abcdef0123"
MARGIN_MS = 2.0
MOVE_MARGIN_MS = 10.0


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def row(name: str, values: list[float]) -> None:
    ms = [v * 1e3 for v in values]
    print(
        f"  {name:<34} p50 {pct(ms, 0.5):6.2f}  p99 {pct(ms, 0.99):6.2f}  "
        f"max {max(ms):6.2f} ms  (n={len(ms)})"
    )


def idle_stops(
    http: httpx.Client, sila: SilaClient, md: list[object], n: int
) -> tuple[list[float], list[float]]:
    for _ in range(50):  # warm-up
        http.post("/api/cell/stop").raise_for_status()
        sila.CellController.Stop(metadata=md)
    h: list[float] = []
    s: list[float] = []
    for i in range(n):
        order = (0, 1) if i % 2 == 0 else (1, 0)
        for which in order:
            t0 = time.perf_counter()
            if which == 0:
                http.post("/api/cell/stop").raise_for_status()
                h.append(time.perf_counter() - t0)
            else:
                sila.CellController.Stop(metadata=md)
                s.append(time.perf_counter() - t0)
    return h, s


def moving_stop(
    http: httpx.Client, sila: SilaClient, md: list[object], over_sila: bool, home: list[float]
) -> tuple[float, float]:
    """(answer, move ended) seconds after the stop was sent."""
    target = [home[0] + 2.0, *home[1:]]
    op = http.post("/api/cell/move_joint", json={"target": target}, params={"wait": False})
    op.raise_for_status()
    op_id = op.json()["id"]
    time.sleep(random.uniform(0.3, 0.8))  # a moment into the move (not a condition)
    t0 = time.perf_counter()
    if over_sila:
        stopped = sila.CellController.Stop(metadata=md).Stopped
    else:
        stopped = http.post("/api/cell/stop").json()["result"]
    answered = time.perf_counter() - t0
    done = http.post(f"/api/operations/{op_id}/wait", params={"timeout": 10}).json()
    ended = done.get("ended") or done.get("operation", {}).get("ended")
    assert stopped, "no move was running when stop was sent"
    # the operation's end is stamped by the daemon (wall clock); convert our send time
    sent_wall = time.time() - (time.perf_counter() - t0)
    http.post("/api/cell/move_joint", json={"target": home}, params={"wait": True})
    return answered, float(ended) - sent_wall


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("-n", type=int, default=1000, help="idle STOP calls per API")
    parser.add_argument("--moves", type=int, default=10, help="stopped moves per API")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        config = Path(tmp) / "cell.yaml"
        config.write_text(
            yaml.safe_dump(
                {
                    "robot": {"host": None},
                    "daemon": {"token_file": f"{tmp}/token", "sila": {"port": port}},
                    "job": {"database": f"{tmp}/job.sqlite3"},
                    "positions_file": f"{tmp}/positions.yaml",
                }
            )
        )
        print("starting the daemon with --sila on the embedded simulator ...", flush=True)
        with DaemonProcess.start(config, token=TOKEN, extra_args=["--sila"]) as daemon:
            daemon.wait_connected()
            certificate = (Path(tmp) / "sila-cert.pem").read_bytes()
            headers = {"Authorization": f"Bearer {TOKEN}", "X-Fxcell-Client": "bench"}
            with (
                httpx.Client(base_url=daemon.url, headers=headers, timeout=30) as http,
                SilaClient("127.0.0.1", port, root_certs=certificate) as sila,
            ):
                md = [sila.AuthorizationService.AccessToken(TOKEN)]
                r = http.post("/api/cell/init")
                if r.is_error:
                    raise SystemExit(f"init failed: {r.text}")
                # The HTTP client holds control (it moves the arm); STOP needs only the token.
                http.headers["X-Fxcell-Lease"] = r.headers["X-Fxcell-Lease"]
                home = http.get("/api/info").json()["home"]
                http.post("/api/cell/go_home", params={"wait": True}).raise_for_status()
                print(f"measuring {args.n} idle STOPs per API, interleaved ...", flush=True)
                h_idle, s_idle = idle_stops(http, sila, md, args.n)
                print(f"measuring {args.moves} stopped moves per API ...", flush=True)
                h_move: list[tuple[float, float]] = []
                s_move: list[tuple[float, float]] = []
                for i in range(args.moves * 2):
                    over_sila = i % 2 == 1
                    result = moving_stop(http, sila, md, over_sila, home)
                    (s_move if over_sila else h_move).append(result)
    print(
        f"STOP round trips on loopback ({os.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.1f})"
    )
    row("HTTP POST /api/cell/stop (idle)", h_idle)
    row("SiLA CellController.Stop (idle)", s_idle)
    row("HTTP stop during a move: answer", [a for a, _ in h_move])
    row("SiLA stop during a move: answer", [a for a, _ in s_move])
    row("HTTP stop during a move: ended", [e for _, e in h_move])
    row("SiLA stop during a move: ended", [e for _, e in s_move])
    targets = Targets("sila")
    for q, label in ((0.5, "p50"), (0.99, "p99")):
        peer = pct(h_idle, q) * 1e3
        targets.check(
            f"SiLA STOP {label}, idle (bound: HTTP's + {MARGIN_MS:.0f} ms)",
            pct(s_idle, q) * 1e3, "<=", peer + MARGIN_MS, "ms", peer=peer, peer_name="HTTP",
        )  # fmt: skip
    peer = pct([e for _, e in h_move], 0.5) * 1e3
    targets.check(
        f"SiLA STOP during a move, p50 to the move's end (bound: HTTP's + {MOVE_MARGIN_MS:.0f} ms)",
        pct([e for _, e in s_move], 0.5) * 1e3, "<=", peer + MOVE_MARGIN_MS, "ms",
        peer=peer, peer_name="HTTP",
    )  # fmt: skip
    return targets.finish()


if __name__ == "__main__":
    raise SystemExit(main())
