"""A run's steps, in order: what the robot and the machine do, and what each step moves.

Per fusion cycle: for each sample pick its crucible from the rack and place it in its machine
position; go home (out of the machine's zone); start the machine; wait until it is done (the
beads then exist, in the moulds); for each sample pick its bead from its mould and place it on
its tray slot; for each sample return its crucible from the machine to its rack slot. The run
ends with the arm at home.
"""

from __future__ import annotations

from dataclasses import dataclass

from fxcell.job.spec import MACHINE, MOULDS, RACK, TRAY, Run
from fxcell.job.store import BEAD, CRUCIBLE, GRIPPER

PICK = "pick"
PLACE = "place"
HOME = "home"
START = "start_machine"
WAIT = "wait_machine"

_PREFIX = {RACK: "rack", TRAY: "tray", MACHINE: "machine", MOULDS: "mould"}
_PLACE_NAMES = {
    RACK: "rack slot",
    TRAY: "tray slot",
    MACHINE: "machine position",
    MOULDS: "mould",
}


def location(station: str, slot: str) -> str:
    """The stored name of a place: ``rack:B3``, ``machine:A2``, ``mould:A2``, ``tray:C4``."""
    return f"{_PREFIX[station]}:{slot}"


def describe_location(loc: str) -> str:
    """``rack:B3`` -> ``rack slot B3``; ``gripper`` -> ``the gripper``."""
    if loc == GRIPPER:
        return "the gripper"
    prefix, _, slot = loc.partition(":")
    station = {v: k for k, v in _PREFIX.items()}.get(prefix, prefix)
    return f"{_PLACE_NAMES.get(station, prefix)} {slot}"


@dataclass(frozen=True)
class Step:
    """One step of the plan. Pick and place steps move one object (``idx``, ``obj``)."""

    seq: int
    action: str
    cycle: int
    station: str | None = None
    slot: str | None = None
    idx: int | None = None
    obj: str | None = None

    @property
    def kind(self) -> str:
        """The step's kind (durations are measured per kind): ``pick:rack``, ``home``, ..."""
        return f"{self.action}:{self.station}" if self.station else self.action

    @property
    def moves_object(self) -> bool:
        return self.action in (PICK, PLACE)

    @property
    def source(self) -> str:
        """Where the step's object is before it (pick and place only)."""
        assert self.station is not None
        assert self.slot is not None
        return location(self.station, self.slot) if self.action == PICK else GRIPPER

    @property
    def dest(self) -> str:
        """Where the step's object is after it (pick and place only)."""
        assert self.station is not None
        assert self.slot is not None
        return GRIPPER if self.action == PICK else location(self.station, self.slot)

    def describe(self, run: Run) -> str:
        if self.moves_object:
            assert self.idx is not None
            assert self.station is not None
            sample = run.samples[self.idx].id
            where = f"{_PLACE_NAMES[self.station]} {self.slot}"
            prep = "from" if self.action == PICK else "in" if self.station != TRAY else "on"
            return f"{self.action} the {self.obj} of sample {sample} {prep} {where}"
        return {
            HOME: "go home",
            START: f"start fusion cycle {self.cycle + 1}",
            WAIT: f"wait for fusion cycle {self.cycle + 1}",
        }[self.action]


def make_plan(run: Run) -> list[Step]:
    """Every step of ``run``, in order (``seq`` counts from 0)."""
    steps: list[Step] = []

    def add(
        action: str,
        cycle: int,
        station: str | None = None,
        slot: str | None = None,
        idx: int | None = None,
        obj: str | None = None,
    ) -> None:
        steps.append(Step(len(steps), action, cycle, station, slot, idx, obj))

    for c, samples in enumerate(run.cycles):
        for s in samples:
            add(PICK, c, RACK, s.rack, s.index, CRUCIBLE)
            add(PLACE, c, MACHINE, s.machine, s.index, CRUCIBLE)
        add(HOME, c)
        add(START, c)
        add(WAIT, c)
        for s in samples:
            add(PICK, c, MOULDS, s.mould, s.index, BEAD)
            add(PLACE, c, TRAY, s.tray, s.index, BEAD)
        for s in samples:
            add(PICK, c, MACHINE, s.machine, s.index, CRUCIBLE)
            add(PLACE, c, RACK, s.rack, s.index, CRUCIBLE)
    add(HOME, len(run.cycles) - 1)
    return steps


def initial_locations(run: Run) -> dict[tuple[int, str], str]:
    """Where the objects are before the run: every crucible in its rack slot."""
    return {(s.index, CRUCIBLE): location(RACK, s.rack) for s in run.samples}


def final_locations(run: Run) -> dict[tuple[int, str], str]:
    """Where the objects are after the run: crucibles back in the rack, beads on the tray."""
    out = initial_locations(run)
    out.update({(s.index, BEAD): location(TRAY, s.tray) for s in run.samples})
    return out
