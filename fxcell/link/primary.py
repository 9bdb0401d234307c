"""A small client of the controller's primary interface (port 30001): reads the calibration.

The controller sends, to every client of 30001/30002, a version message and then a robot-state
message (type 16) about 10 times a second: a 4-byte length (header included) and a 1-byte type,
then sub-packages, each a 4-byte length (header included), a 1-byte type and its body. The
kinematics info sub-package (type 5) holds the calibrated DH parameters (see
:mod:`fxcell.calibration`). Blocking sockets: call it from a thread.
"""

from __future__ import annotations

import argparse
import json
import socket
import struct
import time
from typing import Any

from fxcell.calibration import KINEMATICS_INFO_TYPE, Calibration
from fxcell.errors import CalibrationError

PRIMARY_PORT = 30001
ROBOT_STATE_MESSAGE = 16
_HEADER = struct.Struct(">IB")
_MAX_MESSAGE = 1 << 20


def kinematics_info_of(message: bytes) -> bytes | None:
    """The kinematics info sub-package (header included) of a robot-state message body
    (the bytes after the message's own 5-byte header), or None."""
    at = 0
    while at + _HEADER.size <= len(message):
        size, kind = _HEADER.unpack_from(message, at)
        if size < _HEADER.size or at + size > len(message):
            raise CalibrationError(f"malformed robot-state message: sub-package of {size} bytes")
        if kind == KINEMATICS_INFO_TYPE:
            return message[at : at + size]
        at += size
    return None


def read_calibration(host: str, port: int = PRIMARY_PORT, timeout: float = 3.0) -> Calibration:
    """Connect to the primary interface and return the calibration of the first robot-state
    message that has a kinematics info; CalibrationError if none arrives within ``timeout``
    seconds or the connection fails."""
    deadline = time.monotonic() + timeout
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock:
            buffer = b""
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                sock.settimeout(left)
                chunk = sock.recv(65536)
                if not chunk:
                    raise CalibrationError(f"{host}:{port} closed the primary interface")
                buffer += chunk
                while len(buffer) >= _HEADER.size:
                    size, kind = _HEADER.unpack_from(buffer)
                    if size < _HEADER.size or size > _MAX_MESSAGE:
                        raise CalibrationError(f"{host}:{port}: malformed message ({size} bytes)")
                    if len(buffer) < size:
                        break
                    message, buffer = buffer[_HEADER.size : size], buffer[size:]
                    if kind == ROBOT_STATE_MESSAGE:
                        package = kinematics_info_of(message)
                        if package is not None:
                            return Calibration.from_kinematics_info(package)
    except TimeoutError:
        pass
    except OSError as exc:
        raise CalibrationError(
            f"cannot read the calibration from {host}:{port}: {exc.strerror or exc}"
        ) from None
    raise CalibrationError(
        f"no kinematics info from {host}:{port} within {timeout:g} s "
        "(the controller's primary interface sent no robot state with one)"
    )


# ----------------------------------------------------------------- fxcell calibration show


def register(sub: Any) -> None:
    p = sub.add_parser(
        "calibration",
        help="the arm's factory calibration (DH deltas, checksums)",
        description="Show the arm's factory calibration: UR's per-joint DH deltas and checksums.",
    )
    actions = p.add_subparsers(title="actions", metavar="ACTION", required=True)
    show = actions.add_parser("show", help="print the deltas and the checksum")
    source = show.add_mutually_exclusive_group()
    source.add_argument("--file", help="a calibration.conf (UR's format)")
    source.add_argument("--host", help="read it from this controller's primary interface")
    show.add_argument("--port", type=int, default=PRIMARY_PORT, help="primary interface port")
    show.add_argument("--config", help="cell configuration: its robot.calibration (and host)")
    show.add_argument("--json", action="store_true", help="print JSON")
    show.set_defaults(func=run_show)


def run_show(args: argparse.Namespace) -> int:
    from fxcell.config import CellConfig

    if args.file:
        calibration, origin = Calibration.load(args.file), args.file
    elif args.host:
        calibration = read_calibration(args.host, args.port)
        origin = f"controller {args.host}"
    else:
        robot = CellConfig.load(args.config).robot
        if robot.calibration is None:
            calibration, origin = Calibration.nominal(), "nominal (robot.calibration not set)"
        elif robot.calibration == "controller":
            if robot.host is None:
                raise CalibrationError(
                    "robot.calibration is 'controller' but robot.host is not set"
                )
            calibration = read_calibration(robot.host, args.port)
            origin = f"controller {robot.host}"
        else:
            calibration, origin = Calibration.load(robot.calibration), robot.calibration
    summary = calibration.summary()
    if args.json:
        print(json.dumps({"source": origin, **summary}, indent=2))
        return 0
    print(f"calibration of {origin}: checksum {calibration.checksum}")
    print(f"{'joint':>5} {'Δθ (rad)':>12} {'Δa (m)':>12} {'Δd (m)':>12} {'Δα (rad)':>12}  checksum")
    sums = calibration.joint_checksums()
    for j in range(6):
        print(
            f"{j + 1:>5} {calibration.delta_theta[j]:>12.9f} {calibration.delta_a[j]:>12.9f} "
            f"{calibration.delta_d[j]:>12.9f} {calibration.delta_alpha[j]:>12.9f}  0x{sums[j]:08x}"
        )
    return 0
