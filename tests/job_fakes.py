"""An in-memory cell for the job's tests: a world of objects, a fake gripper arm, a fake machine.

``World`` knows where every object is (``rack:A1`` -> ``crucible:S1``), optionally mirrored in
a JSON file after every change (the "physical world" survives a killed process). ``FakeCell``
satisfies :class:`fxcell.job.JobCell`: ``pick``/``place`` move objects between places and the
gripper, with a few awaits per call where a crash or an abort can strike. ``FakeMachine`` is
the fusion machine on ``FakeIO``: a rising ``machine_start`` with crucibles loaded makes it busy,
after ``fusion_time`` beads appear in the moulds of the loaded positions and it is done; once
the moulds are emptied it is ready again.

Run as a script it is the job process of the SIGKILL test: ``python job_fakes.py DB WORLD RUN``
starts the run (or recovers and resumes it, answering from the world file) and exits when done.
"""

from __future__ import annotations

import asyncio
import functools
import json
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from fxcell.config import CellConfig, JobConfig, LayoutConfig
from fxcell.errors import FxcellError, GripperError, IOTimeoutError, NothingGraspedError
from fxcell.job import Job, JobStore, Run
from fxcell.job.plan import location
from fxcell.layout import Layout
from fxcell.protocol import RobotState

GRIPPER = "gripper"
MACHINE_SIGNALS = ("machine_ready", "machine_busy", "machine_done", "machine_error")


class SimulatedCrash(BaseException):
    """The process died here: nothing after this point runs (not even ``except Exception``)."""


@functools.cache
def _shipped_layout() -> LayoutConfig:
    """The shipped configuration's layout, read once (the crash tests build a fake cell for
    each of their 100+ crash points; reading the configuration's YAML was half their time)."""
    return CellConfig.load().layout


def default_layout() -> Layout:
    """A layout of the shipped configuration's stations (a new one each time)."""
    return Layout(_shipped_layout().model_copy(deep=True))


class World:
    """Where each object is: place -> object (``crucible:S1``, ``bead:S1``)."""

    def __init__(
        self, places: dict[str, str] | None = None, path: Path | None = None, machine: str = "idle"
    ) -> None:
        self.places: dict[str, str] = dict(places or {})
        self.machine = machine
        """The fusion machine's state (``idle``, ``busy``, ``done``): it outlives the PC."""
        self.path = path
        self.save()

    @classmethod
    def for_run(cls, run: Run, path: Path | None = None) -> World:
        return cls({location("rack", s.rack): f"crucible:{s.id}" for s in run.samples}, path)

    @classmethod
    def load(cls, path: Path) -> World:
        data = json.loads(path.read_text())
        return cls(data["places"], path, data["machine"])

    def save(self) -> None:
        if self.path is not None:
            tmp = self.path.with_suffix(".tmp")
            tmp.write_text(json.dumps({"places": self.places, "machine": self.machine}))
            os.replace(tmp, self.path)

    def move(self, src: str, dst: str) -> None:
        assert dst not in self.places, f"{dst} is occupied by {self.places.get(dst)}"
        self.places[dst] = self.places.pop(src)
        self.save()

    def put(self, place: str, obj: str) -> None:
        assert place not in self.places, f"{place} is occupied"
        self.places[place] = obj
        self.save()

    def where(self, obj: str) -> str | None:
        return next((p for p, o in self.places.items() if o == obj), None)


class FakeIO:
    """Digital signals with ``set``/``get``/``wait_for`` as the cell's IO offers them."""

    def __init__(self) -> None:
        self.signals: dict[str, bool] = {}
        self._changed = asyncio.Event()
        self.on_set: list[Any] = []
        self.history: list[tuple[str, bool]] = []
        """Every ``set`` (signal, value), in order."""
        self.tick: Any = None
        """An async callable awaited first in ``set`` and ``wait_for`` (the cell's crash point)."""

    def get(self, signal: str) -> bool:
        return self.signals.get(signal, False)

    def write(self, signal: str, value: bool) -> None:
        """Change a signal (the machine's side)."""
        if self.signals.get(signal, False) != value:
            self.signals[signal] = value
            self._changed.set()
            self._changed = asyncio.Event()

    async def set(self, signal: str, value: bool) -> None:
        if self.tick is not None:
            await self.tick()
        self.write(signal, value)
        self.history.append((signal, value))
        for callback in self.on_set:
            callback(signal, value)

    async def wait_for(self, signal: str, value: bool, timeout: float) -> None:  # noqa: ASYNC109
        if self.tick is not None:
            await self.tick()
        try:
            async with asyncio.timeout(timeout):
                while self.get(signal) != value:
                    await self._changed.wait()
        except TimeoutError:
            raise IOTimeoutError(f"{signal} not {value} within {timeout} s") from None


class FakeMachine:
    """The fusion machine: idle (ready) -> busy -> done -> (moulds emptied) -> idle."""

    def __init__(self, world: World, io: FakeIO, fusion_time: float = 0.0) -> None:
        self.world = world
        self.io = io
        self.fusion_time = fusion_time
        self.cycles = 0
        self._timer: asyncio.TimerHandle | None = None
        io.on_set.append(self._on_set)
        if world.machine == "busy":  # it went on fusing while the job's process was down
            io.write("machine_busy", True)
            self._timer = asyncio.get_running_loop().call_later(fusion_time, self._finish)
        elif world.machine == "done":
            io.write("machine_done", True)
        self.changed()

    @property
    def state(self) -> str:
        if self.io.get("machine_busy"):
            return "busy"
        if self.io.get("machine_done"):
            return "done"
        return "idle"

    def _on_set(self, signal: str, value: bool) -> None:
        if signal == "machine_start" and value and self.state == "idle":
            loaded = [p for p in self.world.places if p.startswith("machine:")]
            if loaded and not self.io.get("machine_error"):
                self.io.write("machine_ready", False)
                self.io.write("machine_busy", True)
                self.world.machine = "busy"
                self.world.save()
                if self.fusion_time <= 0:
                    self._finish()
                else:
                    loop = asyncio.get_running_loop()
                    self._timer = loop.call_later(self.fusion_time, self._finish)

    def _finish(self) -> None:
        self._timer = None
        places = self.world.places
        for place, obj in list(places.items()):
            if place.startswith("machine:") and obj.startswith("crucible:"):
                mould = "mould:" + place.split(":")[1]
                assert mould not in places, f"{mould} is occupied"
                places[mould] = "bead:" + obj.split(":")[1]
        self.cycles += 1
        self.world.machine = "done"
        self.world.save()  # beads and state in one write: the machine pours, then says so
        self.io.write("machine_busy", False)
        self.io.write("machine_done", True)

    def changed(self) -> None:
        """The world changed: once the moulds are empty the machine is ready again."""
        moulds = [p for p in self.world.places if p.startswith("mould:")]
        if self.state == "done" and not moulds:
            self.io.write("machine_done", False)
            self.world.machine = "idle"
            self.world.save()
        if self.state == "idle":
            self.io.write("machine_ready", not self.io.get("machine_error"))

    def fail(self) -> None:
        self.io.write("machine_error", True)
        self.io.write("machine_ready", False)

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()


class FakeGripper:
    """The gripper's object detection over the world; ``readable=False`` (the default):
    it cannot be read (a fake without a gripper), so the job asks the operator."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.readable = False
        self.holding = False

    async def get_width(self) -> float:
        if not self.readable:
            raise GripperError("the fake cell has no gripper to read")
        self.holding = GRIPPER in self.world.places
        return 0.0 if self.holding else 0.05


class FakeCell:
    """A :class:`fxcell.job.JobCell` over a :class:`World`.

    ``crash_at``: raise :class:`SimulatedCrash` at that await (counted over the cell's life).
    ``gate``: when set to an unset event, every pick and place waits on it mid-step.
    """

    def __init__(self, world: World, *, fusion_time: float = 0.0, delay: float = 0.0) -> None:
        self.layout = default_layout()
        self.world = world
        self.io = FakeIO()
        self.io.tick = self._tick
        self.machine = FakeMachine(world, self.io, fusion_time)
        self.delay = delay
        self.crash_at: int | None = None
        self.crashed = False
        self.ticks = 0
        self.gate: asyncio.Event | None = None
        self.in_step = asyncio.Event()
        self.homes = 0
        self.moves: list[tuple[str, str, str]] = []
        self.camera: Any = None
        """A ``fxcell.testing.vision.VisionBench``: the machine's positions are looked at
        (rendered from the world); ``None``: the cell has no camera."""
        self.robot_state: RobotState | None = None
        """The arm's latest sample (a fake cell has none unless a test sets one)."""
        self.faults: dict[str, Any] = {}
        """Machine slot -> the ``Fault`` its crucible stands in (default: seated)."""
        self.next_place_fault: Any = None
        """The next crucible placed in the machine stands like this (e.g. 4 mm off)."""
        self.checks: list[Any] = []
        self.gripper = FakeGripper(world)
        self.held: str | None = None
        self.restores = 0

    async def declare_held(self, kind: str | None = None) -> None:
        self.held = kind

    async def restore_control(self) -> None:
        self.restores += 1

    async def _tick(self) -> None:
        self.ticks += 1
        if self.crashed:  # the process is dead: nothing it does reaches the world any more
            raise SimulatedCrash("after the crash")
        if self.crash_at is not None and self.ticks == self.crash_at:
            self.crashed = True
            raise SimulatedCrash(f"crash at tick {self.ticks}")
        await asyncio.sleep(self.delay)

    def _place(self, station: str, slot: str) -> str:
        _, slot = self.layout.slot(station, slot)
        if station in ("machine", "moulds") and self.io.get("machine_busy"):
            raise FxcellError(f"interlock: the machine is busy, no move into {station}")
        return location(station, slot)

    async def pick(self, station: str, slot: str) -> None:
        place = self._place(station, slot)
        self.moves.append(("pick", station, slot))
        await self._tick()  # approach
        assert GRIPPER not in self.world.places, "pick with a full gripper"
        self.in_step.set()
        if self.gate is not None:
            await self.gate.wait()
        await self._tick()  # descend, close
        if place not in self.world.places:
            raise NothingGraspedError(f"nothing between the fingers at {place}")
        self.world.move(place, GRIPPER)
        if station == "machine":
            self.faults.pop(slot, None)
        self.held = self.layout.station(station).config.holds
        self.machine.changed()
        await self._tick()  # retreat

    async def place(self, station: str, slot: str) -> None:
        place = self._place(station, slot)
        self.moves.append(("place", station, slot))
        await self._tick()  # approach
        assert GRIPPER in self.world.places, "place with an empty gripper"
        self.in_step.set()
        if self.gate is not None:
            await self.gate.wait()
        await self._tick()  # descend, open
        self.world.move(GRIPPER, place)
        if station == "machine" and self.next_place_fault is not None:
            self.faults[slot] = self.next_place_fault
            self.next_place_fault = None
        self.held = None
        self.machine.changed()
        await self._tick()  # retreat

    async def inspect_placement(self, expected: Any) -> Any:
        if self.camera is None:
            return None
        from fxcell.testing.vision import Fault

        positions = {
            p.split(":")[1]: self.faults.get(p.split(":")[1], Fault.seated())
            for p, obj in self.world.places.items()
            if p.startswith("machine:") and obj.startswith("crucible:")
        }
        report = self.camera.check(self.camera.render(positions), set(expected))
        self.checks.append(report)
        return report

    async def go_home(self) -> None:
        self.homes += 1
        await self._tick()


def expected_world(run: Run) -> dict[str, str]:
    """Every crucible back in its rack slot, every bead on its tray slot."""
    out = {location("rack", s.rack): f"crucible:{s.id}" for s in run.samples}
    out.update({location("tray", s.tray): f"bead:{s.id}" for s in run.samples})
    return out


def answers_from(world: World, job: Job) -> dict[str, str]:
    """Answer the job's recovery questions with where the objects really are."""
    out = {}
    for q in job.questions.values():
        where = world.where(f"{q.object}:{q.sample}")
        assert where in q.choices, f"{q.object} of {q.sample} is at {where}, not in {q.choices}"
        out[q.id] = where
    return out


def sample_run(n: int, layout: Layout | None = None) -> Run:
    """``n`` samples: S1.. in rack A1.., beads to the tray slots in reverse order."""
    from fxcell.job import validate_run

    layout = layout or default_layout()
    rack = layout.station("rack").slots
    tray = layout.station("tray").slots
    data = {
        "name": f"{n} samples",
        "samples": [{"id": f"S{i + 1}", "rack": rack[i], "tray": tray[-1 - i]} for i in range(n)],
    }
    return validate_run(data, layout)


def iter_places(world: World) -> Iterator[tuple[str, str]]:
    return iter(sorted(world.places.items()))


async def _script(db: Path, world_path: Path, run_file: Path) -> int:
    world = World.load(world_path)
    cell = FakeCell(world, fusion_time=0.01, delay=0.002)
    store = JobStore(db)
    job = Job(cell, store, JobConfig(start_timeout=5.0, done_timeout=30.0))
    await job.recover()
    if job.state == "paused":
        await job.resume(answers_from(world, job))
    else:
        await job.start(run_file)
    print("started", flush=True)
    await job.wait_state("done", "fault", "paused")
    print(job.state, job.message, flush=True)
    cell.machine.close()
    store.close()
    return 0 if job.state == "done" else 1


if __name__ == "__main__":
    sys.exit(asyncio.run(_script(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]))))
