"""``fxcell sim``: run the controller simulator; ``fxcell sim inject``: inject a fault.

``python -m fxcell.sim`` takes the same options as ``fxcell sim``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence
from typing import Any

from fxcell.errors import SimulatorError
from fxcell.link.embedded import FAULTS
from fxcell.protocol import URCAP_SCRIPT_PORT
from fxcell.sim.constants import UNLOCK_DELAY
from fxcell.sim.lifetime import watch_parent
from fxcell.sim.ned2 import FAULTS as NED2_FAULTS


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
        "--robot",
        choices=("ur3e", "ned2"),
        default="ur3e",
        help="the controller to simulate: ur3e (default) or ned2 (Niryo's TCP server on "
        "40001 as pyniryo uses it; only --host, --time-scale and --calibrated apply)",
    )
    p.add_argument(
        "--calibrated",
        action="store_true",
        help="ned2: start calibrated (a real Ned2 boots needing calibration)",
    )
    p.add_argument(
        "--time-scale",
        type=_positive,
        default=1.0,
        help="multiply controller delays (boot, power on, brake release, program start)",
    )
    p.add_argument(
        "--unlock-delay",
        type=_positive,
        default=UNLOCK_DELAY,
        metavar="S",
        help="controller seconds after a protective stop before it may be unlocked; default "
        "5 as on the real controller (tests that are not about that rule shorten it)",
    )
    p.add_argument("--config", help="cell configuration (scene, home): default config/cell.yaml")
    p.add_argument("--joints", type=_joints, help="initial joint positions q1,...,q6 (rad)")
    p.add_argument(
        "--calibration",
        metavar="FILE|nominal",
        help="the arm's factory calibration (UR's calibration.conf); 'nominal': UR's published "
        "model (all-zero deltas); default: typical factory deltas (config/ur3e_calibration.conf)",
    )
    p.add_argument(
        "--urcap-port",
        type=int,
        default=URCAP_SCRIPT_PORT,
        help="the remote PC's port the ExternalControl URCap requests its program from "
        "(its installation's custom port; default %(default)s)",
    )
    p.add_argument(
        "--programs",
        metavar="DIR",
        help="the controller's program directory (/programs: .urp programs with the .script "
        "PolyScope saves next to them, .installation files); default: the shipped store "
        "(external_control.urp, fxcell.urp, default.urp, default.installation)",
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="run the control cycle with SCHED_FIFO priority (if permitted; else reniced)",
    )
    machine = p.add_argument_group("fusion machine and objects")
    machine.add_argument(
        "--no-machine",
        dest="machine",
        action="store_false",
        default=None,
        help="no simulated fusion machine (its input signals are free for set-input)",
    )
    machine.add_argument(
        "--machine",
        dest="machine",
        action="store_true",
        default=None,
        help="host the fusion machine (the UR simulator's default; ned2: on its pins "
        "start=DO1,ready=DI1,busy=DI2,done=DI3,error=DI5, off unless given)",
    )
    machine.add_argument(
        "--machine-io",
        metavar="NAME=SIGNAL,...",
        help="the machine's signals, default start=DO0,ready=DI0,busy=DI1,done=DI2,error=DI3 "
        "(ned2: start=DO1,ready=DI1,busy=DI2,done=DI3,error=DI5)",
    )
    machine.add_argument(
        "--fusion-time",
        type=_positive,
        default=600.0,
        metavar="S",
        help="fusion duration (s, x --time-scale), default 600",
    )
    machine.add_argument(
        "--cooling-time",
        type=_positive,
        default=300.0,
        metavar="S",
        help="cooling duration (s, x --time-scale), default 300",
    )
    machine.add_argument(
        "--crucibles",
        metavar="A1,A2,...|N",
        help="start with crucibles (with samples) in these rack slots, or the first N",
    )
    p.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="exit when the process that started the simulator ends",
    )
    p.set_defaults(func=run)


def register(sub: Any) -> None:
    p = sub.add_parser("sim", help="run the embedded UR3e (or Niryo Ned2) controller simulator")
    add_arguments(p)
    inner = p.add_subparsers(title="simulator commands", metavar="COMMAND")
    i = inner.add_parser("inject", help="inject a fault into a running simulator")
    i.add_argument("--host", default="127.0.0.1", help="the simulator's address")
    i.add_argument("--robot", choices=("ur3e", "ned2"), default="ur3e")
    i.add_argument("fault", choices=sorted({*FAULTS, *NED2_FAULTS}))
    i.add_argument(
        "args",
        nargs="*",
        help="fault arguments (stall_rtde SECONDS; ned2: stall SECONDS, motor_error JOINT)",
    )
    i.set_defaults(func=run_inject)
    push = inner.add_parser(
        "push", help="move the arm by hand while it is in freedrive (teach mode)"
    )
    push.add_argument("--host", default="127.0.0.1", help="the simulator's address")
    push.add_argument(
        "delta",
        nargs="+",
        type=float,
        help="DX DY DZ (m, TCP in the base frame) or six joint deltas (rad)",
    )
    push.set_defaults(func=run_push)
    si = inner.add_parser(
        "set-input",
        help="set a controller input of a running simulator (play a wired device)",
        description="INPUT: DI5 or 5 (standard digital), CI2 (configurable), TI0 (tool), "
        "AI0/AI1 (standard analog), TAI0/TAI1 (tool analog). VALUE: 0/1, or a number for "
        "analog inputs. Inputs the fusion machine drives are refused.",
    )
    si.add_argument("--host", default="127.0.0.1", help="the simulator's address")
    si.add_argument("input", metavar="INPUT")
    si.add_argument("value", metavar="VALUE")
    si.set_defaults(func=run_set_input)
    po = inner.add_parser(
        "place-object",
        help="put an object at a layout slot of a running simulator",
        description="The object's grip point goes to the slot's grip pose. An object "
        "already there keeps its contents; a new crucible carries a sample unless "
        "CONTENTS is '-' (empty).",
    )
    po.add_argument("--host", default="127.0.0.1", help="the simulator's address")
    po.add_argument("name")
    po.add_argument("kind", help="object kind of the layout (crucible, bead)")
    po.add_argument("station")
    po.add_argument("slot")
    po.add_argument("contents", nargs="?", help="what it carries ('-': nothing)")
    po.set_defaults(func=run_place_object)
    oo = inner.add_parser(
        "offset-object",
        help="misplace a standing object of a running simulator (for the camera's check)",
        description="Shift it by DX DY (m, base axes) and lean it --tilt degrees towards "
        "--azimuth (degrees from base +x), turning about its bottom's edge.",
    )
    oo.add_argument("--host", default="127.0.0.1", help="the simulator's address")
    oo.add_argument("name")
    oo.add_argument("dx", type=float)
    oo.add_argument("dy", type=float)
    oo.add_argument("--tilt", type=float, default=0.0, help="degrees")
    oo.add_argument("--azimuth", type=float, default=0.0, help="degrees")
    oo.set_defaults(func=run_offset_object)
    m = inner.add_parser("machine", help="print the simulated fusion machine's state (JSON)")
    m.add_argument("--host", default="127.0.0.1", help="the simulator's address")
    m.set_defaults(func=run_machine)


def run_inject(args: argparse.Namespace) -> int:
    from fxcell.link.embedded import inject

    if args.robot == "ned2":
        from fxcell.link.ned2.embedded import request

        try:
            answer = request(args.host, " ".join(["inject", args.fault, *args.args]))
        except SimulatorError as exc:
            print(f"fxcell sim inject: {exc}", file=sys.stderr)
            return 1
        if not answer.startswith("ok"):
            print(f"fxcell sim inject: {answer}", file=sys.stderr)
            return 1
        print(answer[3:].strip())
        return 0
    print(inject(args.host, args.fault, *args.args))
    return 0


def run_push(args: argparse.Namespace) -> int:
    from fxcell.errors import SimulatorError
    from fxcell.link.embedded import push

    try:
        push(args.host, args.delta)
    except (SimulatorError, OSError) as exc:
        print(f"fxcell sim push: {exc}", file=sys.stderr)
        return 1
    print("pushed")
    return 0


def run_set_input(args: argparse.Namespace) -> int:
    from fxcell.errors import SimulatorError
    from fxcell.link.embedded import set_input

    try:
        print(set_input(args.host, args.input, args.value))
    except SimulatorError as exc:
        print(f"fxcell sim set-input: {exc}", file=sys.stderr)
        return 1
    return 0


def run_offset_object(args: argparse.Namespace) -> int:
    from fxcell.errors import SimulatorError
    from fxcell.link.embedded import offset_object

    try:
        print(offset_object(args.host, args.name, args.dx, args.dy, args.tilt, args.azimuth))
    except SimulatorError as exc:
        print(f"fxcell sim offset-object: {exc}", file=sys.stderr)
        return 1
    return 0


def run_place_object(args: argparse.Namespace) -> int:
    from fxcell.errors import SimulatorError
    from fxcell.link.embedded import place_object

    try:
        print(place_object(args.host, args.name, args.kind, args.station, args.slot, args.contents))
    except SimulatorError as exc:
        print(f"fxcell sim place-object: {exc}", file=sys.stderr)
        return 1
    return 0


def run_machine(args: argparse.Namespace) -> int:
    import json

    from fxcell.errors import SimulatorError
    from fxcell.link.embedded import machine_state

    try:
        print(json.dumps(machine_state(args.host), indent=2))
    except SimulatorError as exc:
        print(f"fxcell sim machine: {exc}", file=sys.stderr)
        return 1
    return 0


def run(args: argparse.Namespace) -> int:
    import faulthandler
    import signal

    from fxcell.config import CellConfig

    faulthandler.register(signal.SIGUSR1, all_threads=True)  # kill -USR1: where is it?
    if args.robot == "ned2":
        from fxcell.sim.ned2.server import run as serve_ned2

        return serve_ned2(args)
    from fxcell.sim.server import run as serve

    if args.exit_with_parent:
        watch_parent()
    from fxcell.calibration import Calibration
    from fxcell.errors import CalibrationError

    if args.programs is not None and not os.path.isdir(args.programs):
        print(f"fxcell sim: --programs {args.programs}: not a directory", file=sys.stderr)
        return 2
    config = CellConfig.load(args.config)
    from fxcell.errors import InvalidArgumentError
    from fxcell.sim.fusion import parse_machine_io

    try:  # each robot's own pins: parsed here, not by the parser both robots share
        machine_io = parse_machine_io(args.machine_io) if args.machine_io else None
    except InvalidArgumentError as exc:
        print(f"fxcell sim: --machine-io: {exc}", file=sys.stderr)
        return 2
    try:
        if args.calibration == "nominal":
            calibration: Calibration | None = Calibration.nominal()
        else:
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
        machine=args.machine is not False,
        machine_io=machine_io,
        fusion_time=args.fusion_time,
        cooling_time=args.cooling_time,
        crucibles=args.crucibles,
        programs=args.programs,
        unlock_delay=args.unlock_delay,
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
