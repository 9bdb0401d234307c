"""``fxcell sim``: run the controller simulator; ``fxcell sim inject``: inject a fault.

``python -m fxcell.sim`` takes the same options as ``fxcell sim``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

from fxcell.link.embedded import FAULTS


def _joints(text: str) -> list[float]:
    try:
        q = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not 6 comma-separated numbers: {text!r}") from None
    if len(q) != 6:
        raise argparse.ArgumentTypeError(f"need 6 joint positions, got {len(q)}")
    return q


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text!r}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1", help="loopback address to serve on")
    p.add_argument(
        "--time-scale",
        type=_positive,
        default=1.0,
        help="multiply controller delays (boot, power on, brake release, program start)",
    )
    p.add_argument("--config", help="cell configuration (scene, home): default config/cell.yaml")
    p.add_argument("--joints", type=_joints, help="initial joint positions q1,...,q6 (rad)")
    p.add_argument(
        "--calibration",
        metavar="FILE",
        help="the arm's factory calibration (UR's calibration.conf): default all-zero deltas",
    )
    p.add_argument(
        "--urcap-port",
        type=int,
        default=50002,
        help="port the ExternalControl URCap requests its program from",
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="run the control cycle with SCHED_FIFO priority (if permitted; else reniced)",
    )
    p.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="exit when the process that started the simulator ends",
    )
    p.set_defaults(func=run)


def register(sub: Any) -> None:
    p = sub.add_parser("sim", help="run the embedded UR3e controller simulator")
    add_arguments(p)
    inner = p.add_subparsers(title="simulator commands", metavar="COMMAND")
    i = inner.add_parser("inject", help="inject a fault into a running simulator")
    i.add_argument("--host", default="127.0.0.1", help="the simulator's address")
    i.add_argument("fault", choices=FAULTS)
    i.add_argument("args", nargs="*", help="fault arguments (stall_rtde SECONDS)")
    i.set_defaults(func=run_inject)


def run_inject(args: argparse.Namespace) -> int:
    from fxcell.link.embedded import inject

    print(inject(args.host, args.fault, *args.args))
    return 0


def _watch_parent() -> None:
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(0)  # the launcher is gone: nobody can stop us any more

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()


def run(args: argparse.Namespace) -> int:
    import faulthandler
    import signal

    from fxcell.config import CellConfig

    faulthandler.register(signal.SIGUSR1, all_threads=True)  # kill -USR1: where is it?
    from fxcell.sim.server import run as serve

    if args.exit_with_parent:
        _watch_parent()
    from fxcell.calibration import Calibration
    from fxcell.errors import CalibrationError

    config = CellConfig.load(args.config)
    try:
        calibration = Calibration.load(args.calibration) if args.calibration else None
    except CalibrationError as exc:
        print(f"fxcell sim: {exc}", file=sys.stderr)
        return 2
    return serve(
        args.host,
        time_scale=args.time_scale,
        config=config,
        joints=args.joints,
        urcap_port=args.urcap_port,
        realtime=args.realtime,
        calibration=calibration,
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fxcell.sim", description=__doc__)
    parser.add_argument("-v", "--verbose", action="count", default=0)
    add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=(logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)],
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return run(args)
    except KeyboardInterrupt:
        return 130
