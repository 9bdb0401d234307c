"""Launch the embedded Ned2 simulator (``python -m fxcell.sim.ned2``) as a subprocess: the
Ned2 kind's simulator, started by the Cell when a Ned2 cell has no robot host.

Like the UR simulator's launcher (:class:`fxcell.link.embedded.EmbeddedSimulator`, whose
process handling it reuses) it puts the simulator on a free loopback address of its own
(its ports are the robot's fixed ones), waits for its ``listening`` line, and ends it at
``stop()``; it never imports :mod:`fxcell.sim`. The simulated robot boots as a real Ned2
does, needing calibration (``Cell.init()`` calibrates it), unless ``calibrated`` is set.
"""

from __future__ import annotations

import json
import random
from collections.abc import Mapping, Sequence
from typing import Any

from fxcell.errors import InvalidArgumentError, SimulatorError
from fxcell.link.embedded import EmbeddedSimulator, control_request, free_loopback_host
from fxcell.link.ned2 import SIMULATOR_CONTROL_PORT, SIMULATOR_FAULTS, SIMULATOR_PORTS

__all__ = ["SIM_MODULE", "Ned2Simulator", "free_ned2_host", "ned2_simulator", "request"]

SIM_MODULE = "fxcell.sim.ned2"

OPTIONS = frozenset(
    {"host", "time_scale", "calibrated", "joints", "startup_timeout", "python", "extra_args"}
)
"""What :func:`ned2_simulator` takes of the Cell's ``simulator_options``."""


def free_ned2_host(rng: random.Random | None = None, attempts: int = 200) -> str:
    """A random 127.0.0.x (x in 2..253) on which every Ned2 simulator port is free
    (:func:`~fxcell.link.embedded.free_loopback_host` with the Ned2's ports)."""
    return free_loopback_host(rng, attempts, ports=SIMULATOR_PORTS, what="Ned2 simulator")


def request(host: str, line: str, timeout: float = 5.0) -> str:
    """One line to the Ned2 simulator's control port and its one-line answer
    (SimulatorError when it does not answer)."""
    return control_request(
        host, line, port=SIMULATOR_CONTROL_PORT, timeout=timeout, what="Ned2 simulator"
    )


class Ned2Simulator(EmbeddedSimulator):
    """One Ned2 simulator process. ``start()`` returns its address once it listens.

    ``host=None`` picks a free loopback address (another one if that is taken before the
    simulator binds it); ``time_scale`` multiplies the robot's durations (moves,
    calibration, gripper); ``calibrated`` boots it calibrated; ``joints`` places the arm
    there once it listens (re-execution starts where a recording started)."""

    def __init__(
        self,
        host: str | None = None,
        *,
        time_scale: float = 1.0,
        calibrated: bool = False,
        joints: Sequence[float] | None = None,
        startup_timeout: float = 30.0,
        python: str | None = None,
        extra_args: Sequence[str] = (),
    ) -> None:
        super().__init__(
            host,
            time_scale=time_scale,
            startup_timeout=startup_timeout,
            python=python,
            extra_args=extra_args,
        )
        self.calibrated = calibrated
        self.joints = None if joints is None else [float(v) for v in joints]

    def command(self, host: str) -> list[str]:
        cmd = [self.python, "-m", SIM_MODULE, "--host", host]
        cmd += ["--time-scale", repr(self.time_scale), "--exit-with-parent"]
        if self.calibrated:
            cmd.append("--calibrated")
        return cmd + self.extra_args

    what = "Ned2 simulator"

    def _free_host(self) -> str:
        return free_ned2_host()

    def _listening(self) -> None:
        if self.joints is not None:
            self.set_joints(self.joints)
        super()._listening()

    def request(self, line: str) -> str:
        """A control-port request; InvalidArgumentError when the simulator refuses it."""
        answer = request(self._host(), line)
        if answer.startswith("error"):
            raise InvalidArgumentError(f"Ned2 simulator refused {line!r}: {answer}")
        return answer

    def inject(self, fault: str, *args: object) -> str:
        """Inject ``fault`` (:data:`fxcell.link.ned2.SIMULATOR_FAULTS`)."""
        if fault not in SIMULATOR_FAULTS:
            known = ", ".join(SIMULATOR_FAULTS)
            raise InvalidArgumentError(f"unknown Ned2 fault {fault!r}; known: {known}")
        return self.request(" ".join(["inject", fault, *map(str, args)]))

    def state(self) -> Any:
        """The simulator's own view of the robot (joints, calibration, learning mode, ...)."""
        answer = self.request("state")
        try:
            return json.loads(answer)
        except ValueError:
            raise SimulatorError(f"Ned2 simulator sent a bad state reply: {answer!r}") from None

    def set_joints(self, q: Sequence[float]) -> None:
        """Place the resting arm at joints ``q`` without moving."""
        self.request("set_joints " + ",".join(repr(float(v)) for v in q))


def ned2_simulator(options: Mapping[str, Any]) -> Ned2Simulator:
    """The Ned2 kind's simulator launcher: a :class:`Ned2Simulator` from the Cell's
    ``simulator_options`` (``time_scale``, ``calibrated``, ...; InvalidArgumentError
    naming an option it does not take)."""
    unknown = sorted(set(options) - OPTIONS)
    if unknown:
        raise InvalidArgumentError(
            f"the Ned2 simulator takes no option {', '.join(unknown)} "
            f"(it takes {', '.join(sorted(OPTIONS))})"
        )
    return Ned2Simulator(**options)
