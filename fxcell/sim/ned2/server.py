"""The Ned2 simulator process: the robot's TCP server on port 40001, its rosbridge
WebSocket on 9090 (:mod:`fxcell.sim.ned2.rosbridge`) and the simulator's control port
(29990: ``inject FAULT [ARGS]``, ``state``, ``add_object NAME X Y Z [WIDTH]``,
``place_object NAME KIND STATION SLOT [CONTENTS]``, ``objects``, ``machine``,
``set_input PIN VALUE``, ``set_joints Q1,...,Q6``; one text line each).

With ``machine=True`` (``--machine``) it hosts the simulated fusion machine
(:mod:`fxcell.sim.fusion`, the UR simulator's) on the Ned2's panel pins
(:data:`~fxcell.sim.ned2.robot.MACHINE_SIGNALS`: start DO1, ready DI1, busy DI2, done DI3,
error DI5; ``--machine-io``), at the ``machine`` and ``moulds`` stations of the cell's layout
(``--config``, default the shipped Ned2 cell), advanced every
:data:`~fxcell.sim.fusion.SENSE_PERIOD` on the simulator's clock; its faults
(``machine_error``, ``machine_reset``, ``door_open``, ``door_close``) are injected as the
robot's. Without it the simulator is a bare Ned2, every pin free, as pyniryo sees a robot.

Like the robot's server the TCP server serves one client at a time (a second connection
waits until the first closes) and answers a command only once it has finished (a move
holds its connection until the arm arrives); the rosbridge serves any number of clients
at once, so a stop reaches a move that holds the TCP connection.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import signal
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fxcell.errors import FxcellError, InvalidArgumentError
from fxcell.motion import ned2
from fxcell.sim.fusion import (
    COOLING_TIME,
    FUSION_TIME,
    SEAT_TOLERANCE,
    SENSE_PERIOD,
    FusionMachine,
    object_at,
    parse_machine_io,
    slots_of,
)
from fxcell.sim.fusion import FAULTS as MACHINE_FAULTS
from fxcell.sim.lifetime import watch_parent
from fxcell.sim.ned2 import CONTROL_PORT, FAULTS, NED2_PORT, ROSBRIDGE_PORT
from fxcell.sim.ned2.protocol import LENGTH, Interpreter
from fxcell.sim.ned2.robot import (
    DIGITAL_INPUTS,
    DIGITAL_OUTPUTS,
    MACHINE_SIGNALS,
    STOPPED,
    Ned2Robot,
    new_object,
)
from fxcell.sim.ned2.rosbridge import Rosbridge

if TYPE_CHECKING:
    from fxcell.config import CellConfig
    from fxcell.layout import Layout
    from fxcell.sim.gripper import SimObject
    from fxcell.sim.signals import Signal


_NOT_FAULTS = frozenset(
    {"power_restore", "clear_motor_error", "tool_connect", "machine_reset", "door_close"}
)
"""Injections that undo a fault: not counted in the state's ``faults`` (the tests count
the faults they did not inject)."""

log = logging.getLogger(__name__)


class Ned2Server:
    """The simulated robot's sockets on ``host``."""

    def __init__(
        self,
        host: str,
        *,
        time_scale: float = 1.0,
        calibrated: bool = False,
        config: CellConfig | None = None,
        machine: bool = False,
        machine_io: Mapping[str, Signal] | None = None,
        fusion_time: float = FUSION_TIME,
        cooling_time: float = COOLING_TIME,
        crucibles: str | None = None,
    ) -> None:
        self.host = host
        self.robot = Ned2Robot(time_scale=time_scale, calibrated=calibrated)
        self.layout: Layout | None = None
        self.machine: FusionMachine | None = None
        if machine or crucibles:
            self.layout = _layout(config)
        if machine:
            assert self.layout is not None
            self.machine = FusionMachine(
                self.layout,
                self.robot.objects,
                self.robot,
                time_scale=time_scale,
                fusion_time=fusion_time,
                cooling_time=cooling_time,
                signals=machine_io if machine_io is not None else ned2_machine_io(None),
            )
        if crucibles:
            assert self.layout is not None
            rack = self.layout.station("rack")
            for slot in slots_of(rack, crucibles):
                self.place_object(f"crucible-{slot}", rack.config.holds, "rack", slot, "sample")
        self.rosbridge = Rosbridge(self.robot)
        self._slot = asyncio.Lock()  # one client at a time, as the robot's server
        self._clients: set[asyncio.StreamWriter] = set()
        self._tcp: asyncio.Server | None = None
        self._control: asyncio.Server | None = None
        self._stall_until = 0.0
        self._tasks: set[asyncio.Task[Any]] = set()
        self.powered = True
        self._closing = False

    # ---------------------------------------------------------------- serving

    async def start(self) -> None:
        self._tcp = await asyncio.start_server(self._client, self.host, NED2_PORT)
        await self.rosbridge.start(self.host, ROSBRIDGE_PORT)
        self._control = await asyncio.start_server(self._control_client, self.host, CONTROL_PORT)
        if self.machine is not None:
            task = asyncio.create_task(self._run_machine(), name="fusion machine")
            self._tasks.add(task)

    async def _run_machine(self) -> None:
        """Advance the fusion machine on the simulator's clock (s since it started):
        it reads the start output, senses its positions and drives its inputs."""
        assert self.machine is not None
        loop = asyncio.get_running_loop()
        start = loop.time()
        while True:
            self.machine.tick(loop.time() - start)
            await asyncio.sleep(SENSE_PERIOD)

    async def serve(
        self,
        *,
        announce: bool = True,
        handle_signals: bool = True,
        on_listening: Callable[[], None] | None = None,
    ) -> None:
        await self.start()
        stop = asyncio.Event()
        if handle_signals:
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
        if announce:
            print(
                f"fxcell sim (ned2) listening on {self.host}: tcp {NED2_PORT}, "
                f"rosbridge {ROSBRIDGE_PORT}, control {CONTROL_PORT}",
                flush=True,
            )
        if on_listening is not None:
            on_listening()
        try:
            await stop.wait()
        finally:
            await self.close()

    async def close(self) -> None:
        self._closing = True
        for server in (self._tcp, self._control):
            if server is not None:
                server.close()
        for writer in list(self._clients):
            writer.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.rosbridge.close()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._clients.add(writer)
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        try:
            async with self._slot:
                await self._serve_client(reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        except asyncio.CancelledError:
            if not self._closing:
                raise
            # the simulator shuts down: end quietly (asyncio's stream callback would report
            # a cancelled handler as an error)
        finally:
            self._clients.discard(writer)
            if task is not None:
                self._tasks.discard(task)
            writer.close()

    async def _serve_client(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        interpreter = Interpreter(self.robot)
        while not writer.is_closing():
            head = await reader.readexactly(LENGTH.size)
            body = await reader.readexactly(LENGTH.unpack(head)[0])
            try:
                request = json.loads(body.decode())
            except (UnicodeDecodeError, ValueError) as exc:
                # the robot's server reads the frame, fails to decode it and drops the client
                log.info("client sent a frame that is not JSON (%s): disconnecting", exc)
                return
            answer = await interpreter.interpret(request)
            delay = self._stall_until - asyncio.get_running_loop().time()
            if delay > 0:  # a stalled server: the answer comes that much later
                await asyncio.sleep(delay)
            if writer.is_closing():
                return
            writer.write(answer)
            await writer.drain()

    # ---------------------------------------------------------------- control port

    async def _control_client(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        try:
            line = (await reader.readline()).decode("utf-8", "replace").strip()
            try:
                answer = await self.control(line)
            except (ValueError, KeyError, IndexError) as exc:
                answer = f"error {exc}"
            writer.write(answer.encode() + b"\n")
            await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()

    async def control(self, line: str) -> str:
        words = line.split()
        if not words:
            return "error empty request"
        verb, args = words[0], words[1:]
        robot = self.robot
        if verb == "state":
            return json.dumps({**robot.state(), "powered": self.powered})
        if verb == "inject":
            return await self.inject(args[0], *args[1:])
        if verb == "add_object":
            name, x, y, z = args[0], float(args[1]), float(args[2]), float(args[3])
            width = float(args[4]) if len(args) > 4 else 0.02
            robot.objects[name] = new_object(name, np.array([x, y, z]), width)
            return "ok"
        if verb == "place_object":
            return self._place_object(args)
        if verb == "objects":
            return json.dumps({n: self._object_json(o) for n, o in robot.objects.items()})
        if verb == "machine":
            if self.machine is None:
                return "error the simulator has no fusion machine (start it with --machine)"
            return json.dumps(self.machine.report())
        if verb == "set_input":
            pin, value = args[0], args[1]
            try:
                if pin in DIGITAL_INPUTS:
                    robot.set_input(pin, 1.0 if value in ("1", "HIGH", "true", "True") else 0.0)
                else:
                    robot.set_input(pin, float(value))
            except InvalidArgumentError as exc:
                return f"error {exc}"
            return "ok"
        if verb == "set_joints":
            q = np.array([float(v) for v in args[0].split(",")])
            if q.shape != (6,) or not ned2.within_limits(q) or robot.moving:
                return "error 6 joint positions within the limits, arm at rest"
            robot.joints = q
            return "ok"
        return f"error unknown request {verb!r}"

    # ---------------------------------------------------------------- the world

    def place_object(
        self, name: str, kind: str, station: str, slot: str, contents: str | None = None
    ) -> str:
        """Put a new object (or move one) with its grip point at a layout slot's grip pose."""
        if self.layout is None:
            raise InvalidArgumentError("the simulator has no layout (start it with --machine)")
        objects = self.layout.config.objects
        if kind not in objects:
            known = ", ".join(sorted(objects)) or "none"
            raise InvalidArgumentError(f"unknown object kind {kind!r} (known: {known})")
        st, slot = self.layout.slot(station, slot)
        if st.config.holds != kind:
            raise InvalidArgumentError(f"station {st.name!r} holds {st.config.holds}s, not {kind}s")
        there = object_at(self.robot.objects, st, slot)
        if there is not None and there.name != name:
            raise InvalidArgumentError(f"{st.name} {slot} is taken by {there.name}")
        if self.robot.held == name:
            raise InvalidArgumentError(f"{name} is in the gripper")
        size = objects[kind]
        self.robot.objects[name] = new_object(
            name,
            st.grip_pose(slot).position,
            size.width,
            kind=kind,
            height=size.height,
            mass=size.mass,
            contents=contents,
        )
        return f"{name} placed in {st.name} {slot}"

    def _place_object(self, args: list[str]) -> str:
        if len(args) not in (4, 5):
            return "error place_object NAME KIND STATION SLOT [CONTENTS]"
        name, kind, station, slot = args[:4]
        contents: str | None
        if len(args) == 5:  # "-": empty
            contents = None if args[4] == "-" else args[4]
        elif name in self.robot.objects:  # an object moved keeps its contents
            contents = self.robot.objects[name].contents
        else:  # a new crucible comes with a sample
            contents = "sample" if kind == "crucible" else None
        try:
            return "ok " + self.place_object(name, kind, station, slot, contents)
        except FxcellError as exc:
            return f"error place_object: {exc}"

    def _object_json(self, obj: SimObject) -> dict[str, object]:
        """An object's JSON plus the layout slot it stands in (``station``/``slot``, or None)."""
        data = obj.as_json()
        data["station"] = data["slot"] = None
        if obj.held_from is None and self.layout is not None:
            for st in self.layout:
                if st.config.holds != obj.kind:
                    continue
                for slot in st.slots:
                    gap = np.linalg.norm(st.grip_pose(slot).position - obj.pose.position)
                    if gap <= SEAT_TOLERANCE:
                        data["station"], data["slot"] = st.name, slot
                        return data
        return data

    async def inject(self, fault: str, *args: str) -> str:
        robot = self.robot
        if fault not in FAULTS:
            return f"error unknown fault {fault!r}"
        machine = self.machine
        if fault in MACHINE_FAULTS:
            if machine is None:
                return "error the simulator has no fusion machine (start it with --machine)"
            if args:
                return f"error {fault} takes no arguments"
        if fault not in _NOT_FAULTS and fault != "collision":  # that one counts itself
            robot.faults.append(f"injected {fault} {' '.join(args)}".strip())
        if machine is not None and fault in MACHINE_FAULTS:
            text = machine.inject(fault)
            robot.log.append(f"injected {fault}")
            return f"ok {fault}: {text}"
        if fault == "collision":
            robot.collide()
        elif fault == "stop":
            robot.abort(STOPPED, "Command has been stopped")
        elif fault == "drop_connection":
            for writer in list(self._clients):
                writer.close()
            self.rosbridge.cut()
        elif fault == "stall":
            seconds = float(args[0]) if args else 5.0
            self._stall_until = asyncio.get_running_loop().time() + seconds
            self.rosbridge.stalled_until = self._stall_until
        elif fault == "power_loss":
            robot.power_loss()
            self.powered = False
            if self._tcp is not None:
                self._tcp.close()
                self._tcp = None
            for writer in list(self._clients):
                writer.close()
            await self.rosbridge.drop()
        elif fault == "power_restore":
            if not self.powered:
                self._tcp = await asyncio.start_server(self._client, self.host, NED2_PORT)
                await self.rosbridge.start(self.host, ROSBRIDGE_PORT)
                self.powered = True
        elif fault == "motor_error":
            joint = int(args[0]) if args else 2
            if not 1 <= joint <= 6:
                return "error joint 1..6"
            robot.motor_error = joint
            robot.abort(-111, f"Hardware error on joint_{joint}")
        elif fault == "clear_motor_error":
            robot.motor_error = 0
        elif fault == "gripper_drop":
            robot.drop_held()
        elif fault == "tool_disconnect":
            robot.drop_held()
            robot.tool = "NONE"
        elif fault == "tool_connect":
            robot.tool = "GRIPPER_1"
        elif fault == "uncalibrate":
            robot.calibrated = False
        robot.log.append(f"injected {fault}")
        return f"ok {fault}"


# -------------------------------------------------------------------- the process


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1", help="loopback address to serve on")
    p.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        help="multiply the robot's durations (moves, calibration, gripper)",
    )
    p.add_argument(
        "--calibrated", action="store_true", help="start calibrated (a real Ned2 boots needing it)"
    )
    p.add_argument("--exit-with-parent", action="store_true", help=argparse.SUPPRESS)
    p.add_argument(
        "--config",
        help="the cell configuration whose layout places the machine and the rack "
        "(default: the shipped Ned2 cell, config/ned2-cell.yaml)",
    )
    machine = p.add_argument_group("fusion machine and objects")
    machine.add_argument(
        "--machine",
        action="store_true",
        default=None,
        help="host the simulated fusion machine on the Ned2's pins (default: a bare Ned2)",
    )
    machine.add_argument(
        "--machine-io",
        metavar="NAME=PIN,...",
        help="the machine's pins, default "
        + ",".join(f"{k}={v}" for k, v in MACHINE_SIGNALS.items()),
    )
    machine.add_argument(
        "--fusion-time", type=float, default=FUSION_TIME, metavar="S",
        help=f"fusion duration (s, x --time-scale), default {FUSION_TIME:g}",
    )  # fmt: skip
    machine.add_argument(
        "--cooling-time", type=float, default=COOLING_TIME, metavar="S",
        help=f"cooling duration (s, x --time-scale), default {COOLING_TIME:g}",
    )  # fmt: skip
    machine.add_argument(
        "--crucibles",
        metavar="A1,A2,...|N",
        help="start with crucibles (with samples) in these rack slots, or the first N",
    )


def ned2_machine_io(text: str | None) -> dict[str, Signal]:
    """``"start=DO1,ready=DI1"`` over :data:`MACHINE_SIGNALS`: the machine's signals on the
    Ned2's pins (InvalidArgumentError for a pin the Ned2 lacks)."""
    return parse_machine_io(text, MACHINE_SIGNALS, (*DIGITAL_INPUTS, *DIGITAL_OUTPUTS))


def _layout(config: CellConfig | None) -> Layout:
    from fxcell.config import CONFIG_DIR, CellConfig
    from fxcell.layout import Layout
    from fxcell.robot_specs import NED2_SPEC

    if config is None:
        config = CellConfig.load(CONFIG_DIR / NED2_SPEC.shipped_config)
    if config.robot.kind != "ned2":
        raise InvalidArgumentError(
            f"--config: a {config.robot.kind} cell; the Ned2 simulator takes a Ned2 cell's "
            "configuration (robot.kind: ned2)"
        )
    return Layout(config.layout)


def run(args: argparse.Namespace) -> int:
    if not args.time_scale > 0:
        print("fxcell sim: --time-scale must be > 0", file=sys.stderr)
        return 2
    if args.exit_with_parent:
        watch_parent()
    from fxcell.config import CellConfig

    try:
        config = None if args.config is None else CellConfig.load(Path(args.config))
        signals = None if args.machine_io is None else ned2_machine_io(args.machine_io)
        server = Ned2Server(
            args.host,
            time_scale=args.time_scale,
            calibrated=args.calibrated,
            config=config,
            # `fxcell sim --robot ned2` shares the UR simulator's parser, whose --no-machine
            # sets False: only --machine (True) hosts the machine on a Ned2
            machine=args.machine is True,
            machine_io=signals,
            fusion_time=args.fusion_time,
            cooling_time=args.cooling_time,
            crucibles=args.crucibles,
        )
    except FxcellError as exc:
        print(f"fxcell sim: {exc}", file=sys.stderr)
        return 2
    try:
        asyncio.run(server.serve())
    except OSError as exc:
        print(f"fxcell sim: cannot listen on {args.host}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m fxcell.sim.ned2", description="the embedded Niryo Ned2 simulator"
    )
    parser.add_argument("-v", "--verbose", action="count", default=0)
    add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=(logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)],
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    return run(args)
