"""The Ned2 simulator in its own process on a free loopback address, for tests and
scripts: ``with ned2_simulator() as sim: NiryoRobot(sim.host)``.

Test support: the runtime never imports it.
"""

from __future__ import annotations

import json
import random
import time
from collections.abc import Sequence
from typing import Any

from fxcell.errors import InvalidArgumentError, SimulatorError
from fxcell.link.embedded import EmbeddedSimulator, address_is_free
from fxcell.sim.ned2 import FAULTS, PORTS
from fxcell.sim.ned2.server import request
from fxcell.testing.handles import ProcessHandle

__all__ = ["Ned2SimulatorHandle", "free_ned2_host", "ned2_simulator"]

TEST_TIME_SCALE = 0.05  # moves and calibration 20x faster than the robot's


def free_ned2_host(attempts: int = 200) -> str:
    """A random 127.0.0.x (x in 2..253) on which the Ned2 simulator's ports are free."""
    rng = random.SystemRandom()
    for _ in range(attempts):
        host = f"127.0.0.{rng.randint(2, 253)}"
        if address_is_free(host, PORTS):
            return host
    raise SimulatorError("no free loopback address for the Ned2 simulator")


class _Process(EmbeddedSimulator):
    def __init__(self, time_scale: float, calibrated: bool) -> None:
        super().__init__(time_scale=time_scale)
        self.calibrated = calibrated

    def command(self, host: str) -> list[str]:
        cmd = [self.python, "-m", "fxcell.sim.ned2", "--host", host]
        cmd += ["--time-scale", repr(self.time_scale), "--exit-with-parent"]
        return cmd + (["--calibrated"] if self.calibrated else [])

    def start(self) -> str:
        if self.process is not None:
            raise SimulatorError("simulator already started")
        last = ""
        for _ in range(5):
            host = free_ned2_host()
            ok, last = self._launch(host)
            if ok:
                self.host = host
                return host
        raise SimulatorError(f"Ned2 simulator did not start: {last}")


class Ned2SimulatorHandle(ProcessHandle):
    """A running Ned2 simulator (``.host``): pyniryo connects to ``host`` on 40001.

    ``inject`` a fault (:data:`fxcell.sim.ned2.FAULTS`), read its ``state()``, put an
    object where the gripper can take it (``add_object``), set an input
    (``set_input``), or wait for a state value (``wait_for``)."""

    def __init__(self, time_scale: float, calibrated: bool) -> None:
        self._sim = _Process(time_scale, calibrated)

    @property
    def host(self) -> str:
        return self._sim._host()

    def start(self) -> Ned2SimulatorHandle:
        self._sim.start()
        return self

    def stop(self) -> None:
        self._sim.stop()

    def _request(self, line: str) -> str:
        try:
            answer = request(self.host, line)
        except OSError as exc:
            raise SimulatorError(f"Ned2 simulator at {self.host} does not answer: {exc}") from None
        if answer.startswith("error"):
            raise InvalidArgumentError(f"Ned2 simulator refused {line!r}: {answer}")
        return answer

    def inject(self, fault: str, *args: object) -> str:
        if fault not in FAULTS:
            raise InvalidArgumentError(f"unknown fault {fault!r}; known: {', '.join(FAULTS)}")
        return self._request(" ".join(["inject", fault, *map(str, args)]))

    def state(self) -> dict[str, Any]:
        result: dict[str, Any] = json.loads(self._request("state"))
        return result

    def add_object(self, name: str, position: Sequence[float], width: float = 0.02) -> None:
        """An object whose grip point is at ``position`` (base_link, m)."""
        x, y, z = (float(v) for v in position)
        self._request(f"add_object {name} {x!r} {y!r} {z!r} {width!r}")

    def set_input(self, pin: str, value: object) -> None:
        self._request(f"set_input {pin} {value}")

    def set_joints(self, q: Sequence[float]) -> None:
        self._request("set_joints " + ",".join(repr(float(v)) for v in q))

    def wait_for(self, key: str, value: object, timeout: float = 10.0) -> None:
        """Wait until ``state()[key] == value``."""
        deadline = time.monotonic() + timeout
        while (current := self.state().get(key)) != value:
            if time.monotonic() > deadline:
                raise TimeoutError(f"Ned2 simulator {key} is {current!r}, not {value!r}")
            time.sleep(0.01)


def ned2_simulator(
    time_scale: float = TEST_TIME_SCALE, *, calibrated: bool = False
) -> Ned2SimulatorHandle:
    """A Ned2 simulator process on a free loopback address, for ``with``/``async with``.

    >>> with ned2_simulator() as sim:  # doctest: +SKIP
    ...     robot = NiryoRobot(sim.host)
    """
    return Ned2SimulatorHandle(time_scale, calibrated)
