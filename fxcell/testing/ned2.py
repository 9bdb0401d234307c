"""The Ned2 simulator in its own process on a free loopback address, for tests and
scripts: ``with ned2_simulator() as sim: NiryoRobot(sim.host)``.

Test support: the runtime never imports it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from typing import Any

from fxcell.link.ned2.embedded import Ned2Simulator, free_ned2_host
from fxcell.testing.handles import ProcessHandle

__all__ = ["Ned2SimulatorHandle", "free_ned2_host", "ned2_simulator"]

TEST_TIME_SCALE = 0.05  # moves and calibration 20x faster than the robot's


class Ned2SimulatorHandle(ProcessHandle):
    """A running Ned2 simulator (``.host``): pyniryo connects to ``host`` on 40001.

    ``inject`` a fault (:data:`fxcell.link.ned2.SIMULATOR_FAULTS`), read its ``state()``, put an
    object where the gripper can take it (``add_object``) or at a layout slot
    (``place_object``), read its ``objects()`` and fusion ``machine()`` (started with
    ``--machine`` in ``extra_args``), set an input (``set_input``), or wait for a state
    value (``wait_for``)."""

    def __init__(self, time_scale: float, calibrated: bool, extra_args: Sequence[str] = ()) -> None:
        self._sim = Ned2Simulator(
            time_scale=time_scale, calibrated=calibrated, extra_args=extra_args
        )

    @property
    def host(self) -> str:
        return self._sim._host()

    def start(self) -> Ned2SimulatorHandle:
        self._sim.start()
        return self

    def stop(self) -> None:
        self._sim.stop()

    def _request(self, line: str) -> str:
        return self._sim.request(line)

    def inject(self, fault: str, *args: object) -> str:
        return self._sim.inject(fault, *args)

    def state(self) -> dict[str, Any]:
        result: dict[str, Any] = self._sim.state()
        return result

    def add_object(self, name: str, position: Sequence[float], width: float = 0.02) -> None:
        """An object whose grip point is at ``position`` (base_link, m)."""
        x, y, z = (float(v) for v in position)
        self._request(f"add_object {name} {x!r} {y!r} {z!r} {width!r}")

    def place_object(
        self, name: str, kind: str, station: str, slot: str, contents: str | None = None
    ) -> None:
        """An object of a layout kind at a slot's grip pose (a new crucible: with a sample)."""
        words = [name, kind, station, slot] + ([] if contents is None else [contents])
        self._request("place_object " + " ".join(words))

    def objects(self) -> dict[str, Any]:
        """Every object: kind, pose, held, contents and the layout slot it stands in."""
        result: dict[str, Any] = json.loads(self._request("objects"))
        return result

    def machine(self) -> dict[str, Any]:
        """The simulated fusion machine's report (state, positions, moulds, pins, log)."""
        result: dict[str, Any] = json.loads(self._request("machine"))
        return result

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
    time_scale: float = TEST_TIME_SCALE,
    *,
    calibrated: bool = False,
    extra_args: Sequence[str] = (),
) -> Ned2SimulatorHandle:
    """A Ned2 simulator process on a free loopback address, for ``with``/``async with``
    (``extra_args``: its command-line options, e.g. ``--machine``).

    >>> with ned2_simulator() as sim:  # doctest: +SKIP
    ...     robot = NiryoRobot(sim.host)
    """
    return Ned2SimulatorHandle(time_scale, calibrated, extra_args)
