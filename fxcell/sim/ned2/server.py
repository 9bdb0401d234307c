"""The Ned2 simulator process: the robot's TCP server on port 40001, its rosbridge
WebSocket on 9090 (:mod:`fxcell.sim.ned2.rosbridge`) and the simulator's control port
(29990: ``inject FAULT [ARGS]``, ``state``, ``add_object NAME X Y Z [WIDTH]``,
``set_input PIN VALUE``, ``set_joints Q1,...,Q6``; one text line each).

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
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from fxcell.motion import ned2
from fxcell.sim.lifetime import watch_parent
from fxcell.sim.ned2 import CONTROL_PORT, FAULTS, NED2_PORT, ROSBRIDGE_PORT
from fxcell.sim.ned2.protocol import LENGTH, Interpreter
from fxcell.sim.ned2.robot import (
    ANALOG_INPUTS,
    DIGITAL_INPUTS,
    STOPPED,
    Ned2Robot,
    SimObject,
)
from fxcell.sim.ned2.rosbridge import Rosbridge

log = logging.getLogger(__name__)


class Ned2Server:
    """The simulated robot's sockets on ``host``."""

    def __init__(self, host: str, *, time_scale: float = 1.0, calibrated: bool = False) -> None:
        self.host = host
        self.robot = Ned2Robot(time_scale=time_scale, calibrated=calibrated)
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
            robot.objects[name] = SimObject(name, np.array([x, y, z]), width)
            return "ok"
        if verb == "set_input":
            pin, value = args[0], args[1]
            if pin in DIGITAL_INPUTS:
                robot.digital_in[pin] = value in ("1", "HIGH", "true", "True")
            elif pin in ANALOG_INPUTS:
                robot.analog_in[pin] = float(value)
            else:
                return f"error no input {pin}"
            return "ok"
        if verb == "set_joints":
            q = np.array([float(v) for v in args[0].split(",")])
            if q.shape != (6,) or not ned2.within_limits(q) or robot.moving:
                return "error 6 joint positions within the limits, arm at rest"
            robot.joints = q
            return "ok"
        return f"error unknown request {verb!r}"

    async def inject(self, fault: str, *args: str) -> str:
        robot = self.robot
        if fault not in FAULTS:
            return f"error unknown fault {fault!r}"
        if fault == "collision":
            robot.collide()
        elif fault == "stop":
            robot.abort(STOPPED, "Command has been stopped")
        elif fault == "drop_connection":
            for writer in list(self._clients):
                writer.close()
        elif fault == "stall":
            seconds = float(args[0]) if args else 5.0
            self._stall_until = asyncio.get_running_loop().time() + seconds
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


def run(args: argparse.Namespace) -> int:
    if not args.time_scale > 0:
        print("fxcell sim: --time-scale must be > 0", file=sys.stderr)
        return 2
    if args.exit_with_parent:
        watch_parent()
    server = Ned2Server(args.host, time_scale=args.time_scale, calibrated=args.calibrated)
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


def request(host: str, line: str, timeout: float = 5.0) -> str:
    """One request on the simulator's control port (blocking)."""
    import socket

    with socket.create_connection((host, CONTROL_PORT), timeout=timeout) as s:
        s.sendall(line.encode() + b"\n")
        data = b""
        while not data.endswith(b"\n"):
            chunk = s.recv(65536)
            if not chunk:
                break
            data += chunk
    return data.decode("utf-8", "replace").strip()


def state(host: str) -> dict[str, Any]:
    result: dict[str, Any] = json.loads(request(host, "state"))
    return result
