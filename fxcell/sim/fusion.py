"""A simulated Vitriox 4+ fusion machine, wired to the controller's digital IO.

Four crucible positions (layout station ``machine``) and four moulds (station ``moulds``):
position *i* pours into mould *i*. A crucible stands in a position when it is not held and its
grip point is within :data:`SEAT_TOLERANCE` of the position's grip pose.

States: ``idle`` (no crucible) ⇄ ``loaded`` (at least one) → ``fusing`` → ``cooling`` →
``done`` (a glass bead in the mould of every position whose crucible held a sample; the
crucibles are empty) → ``idle`` once every mould is empty. A fault (``machine_error``, a
crucible taken out or put in during a cycle, the door opened during a cycle) aborts the cycle
without beads and latches the ``error`` state until ``machine_reset``. An open door
(``door_open``) reports ``error`` and clears ``ready`` until ``door_close``.

IO (defaults; see :data:`DEFAULT_SIGNALS`): robot → machine ``start`` DO0 (a rising edge while
ready starts a cycle when at least one crucible is loaded and every mould is empty; otherwise
the machine logs and ignores it); machine → robot ``ready`` DI0 (idle or loaded, no fault, door
closed), ``busy`` DI1 (fusing or cooling), ``done`` DI2, ``error`` DI3 (a fault or the door
open). The machine owns its input signals. It is advanced on the controller's clock
(:meth:`FusionMachine.tick`), its sensors look every :data:`SENSE_PERIOD`; its durations are
multiplied by the simulator's time scale.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Mapping
from enum import StrEnum
from typing import Protocol

import numpy as np

from fxcell.errors import InvalidArgumentError
from fxcell.layout import Layout, Station
from fxcell.sim.gripper import SimObject
from fxcell.sim.signals import Signal, parse_signal

log = logging.getLogger(__name__)

POSITIONS_STATION = "machine"
MOULDS_STATION = "moulds"
SEAT_TOLERANCE = 0.005  # m: an object's grip point this close to a slot's grip pose is in it
SENSE_PERIOD = 0.01  # s: how often the machine's sensors look at its positions and moulds
FUSION_TIME = 600.0  # s before time scaling
COOLING_TIME = 300.0  # s before time scaling
OWNER = "the fusion machine"
DEFAULT_SIGNALS: dict[str, str] = {
    "start": "DO0",
    "ready": "DI0",
    "busy": "DI1",
    "done": "DI2",
    "error": "DI3",
}
OUTPUT_SIGNALS = ("start",)  # robot -> machine; the rest are machine -> robot
FAULTS = ("machine_error", "machine_reset", "door_open", "door_close")


class MachineIO(Protocol):
    """The robot's digital IO as the machine wires to it: it reads the robot's outputs and
    drives the inputs it owns (listed in ``input_owners``, pin name -> owner, so that nothing
    else sets them)."""

    input_owners: dict[str, str]

    def output(self, signal: Signal) -> bool:
        """The level of a digital output."""
        ...

    def input(self, signal: Signal) -> float:
        """The value of an input (1.0/0.0 for digital ones)."""
        ...

    def set_input(self, signal: Signal, value: float, owner: str | None = None) -> None:
        """Set an input (InvalidArgumentError when another owner drives it)."""
        ...


class MachineState(StrEnum):
    IDLE = "idle"
    LOADED = "loaded"
    FUSING = "fusing"
    COOLING = "cooling"
    DONE = "done"
    ERROR = "error"


_BUSY = (MachineState.FUSING, MachineState.COOLING)  # looked up once, not every cycle


def parse_machine_io(
    text: str | None,
    defaults: Mapping[str, str] = DEFAULT_SIGNALS,
    pins: Collection[str] | None = None,
) -> dict[str, Signal]:
    """``"start=DO0,ready=DI0"`` over ``defaults`` (the UR's :data:`DEFAULT_SIGNALS`) →
    every signal's :class:`Signal`.

    ``start`` must be a digital output, the others distinct digital inputs; with ``pins``
    (the robot's pin names, e.g. the Ned2's DI1-DI5, DO1-DO4) every signal must be one.
    """
    names = dict(defaults)
    for item in (text or "").split(","):
        if not item.strip():
            continue
        key, sep, value = item.partition("=")
        key = key.strip().lower()
        if not sep or key not in names:
            raise InvalidArgumentError(
                f"machine IO: expected NAME=SIGNAL with NAME one of "
                f"{', '.join(DEFAULT_SIGNALS)}, got {item.strip()!r}"
            )
        names[key] = value.strip()
    signals = {key: parse_signal(value) for key, value in names.items()}
    for key, sig in signals.items():
        if pins is not None and str(sig) not in pins:
            raise InvalidArgumentError(
                f"machine IO: {key}={sig} is not a pin of the robot (it has {', '.join(pins)})"
            )
        if not sig.is_digital:
            raise InvalidArgumentError(f"machine IO: {key}={sig} is not a digital signal")
        if sig.is_input == (key in OUTPUT_SIGNALS):
            wanted = "a digital output (DO, CO, TO)" if key in OUTPUT_SIGNALS else "an input"
            raise InvalidArgumentError(f"machine IO: {key} must be {wanted}, not {sig}")
    inputs = [str(s) for k, s in signals.items() if k not in OUTPUT_SIGNALS]
    if len(set(inputs)) != len(inputs):
        raise InvalidArgumentError(f"machine IO: inputs must be distinct, got {inputs}")
    return signals


def slots_of(station: Station, spec: str) -> list[str]:
    """``"A1,B2"`` (slot names) or ``"N"`` (the first N slots) → the station's slot names."""
    spec = spec.strip()
    if spec.isdigit():
        n = int(spec)
        if not 0 <= n <= len(station.slots):
            raise InvalidArgumentError(
                f"station {station.name!r} has {len(station.slots)} slots, not {n}"
            )
        return station.slots[:n]
    slots = [station.index(s) for s in spec.split(",") if s.strip()]
    names = [station.slots[r * station.config.columns + c] for r, c in slots]
    if len(set(names)) != len(names):
        raise InvalidArgumentError(f"a slot is named twice in {spec!r}")
    return names


def object_at(objects: Mapping[str, SimObject], station: Station, slot: str) -> SimObject | None:
    """The object (not held) standing in ``slot`` of ``station``, if any."""
    target = station.grip_pose(slot).position
    for obj in objects.values():
        if obj.held_from is not None or obj.kind != station.config.holds:
            continue
        if float(np.linalg.norm(obj.pose.position - target)) <= SEAT_TOLERANCE:
            return obj
    return None


class FusionMachine:
    """The machine's state, advanced by :meth:`tick` on the controller's clock."""

    def __init__(
        self,
        layout: Layout,
        objects: dict[str, SimObject],
        io: MachineIO,
        *,
        time_scale: float = 1.0,
        fusion_time: float = FUSION_TIME,
        cooling_time: float = COOLING_TIME,
        signals: Mapping[str, Signal] | None = None,
    ) -> None:
        self.positions = layout.station(POSITIONS_STATION)
        self.moulds = layout.station(MOULDS_STATION)
        if len(self.moulds.slots) < len(self.positions.slots):
            raise InvalidArgumentError(
                f"the machine has {len(self.positions.slots)} positions but "
                f"{len(self.moulds.slots)} moulds"
            )
        if not (fusion_time > 0 and cooling_time > 0):
            raise InvalidArgumentError("fusion and cooling times must be > 0")
        self.objects = objects
        self.io = io
        self.fusion_time = fusion_time * time_scale
        self.cooling_time = cooling_time * time_scale
        self.signals = dict(signals) if signals is not None else parse_machine_io(None)
        self.mould_of = dict(zip(self.positions.slots, self.moulds.slots, strict=False))
        # the layout is fixed for the simulator's life: slot grip points once, as plain floats
        self._seats = {
            st.name: [(slot, tuple(st.grip_pose(slot).position.tolist())) for slot in st.slots]
            for st in (self.positions, self.moulds)
        }
        self.state = MachineState.IDLE
        self.fault: str | None = None
        self.door_open = False
        self.phase_end = 0.0
        self.charge: dict[str, str] = {}  # position slot -> crucible name, during a cycle
        self.time = 0.0
        self.messages: list[str] = []
        self._start_level = False
        self._written: dict[str, bool] = {}
        self._written_from: tuple[object, ...] | None = None
        self._next_sense = 0.0
        for key, sig in self.signals.items():
            if sig.is_input:
                io.input_owners[str(sig)] = f"{OWNER} ({key})"
        self._write_signals()

    # ------------------------------------------------------------------ world

    def _occupants(self, station: Station) -> dict[str, SimObject]:
        """Slot → the object (not held, of the station's kind) in it; plain floats, as this
        runs every control cycle."""
        seats = self._seats[station.name]
        kind = station.config.holds
        tolerance = SEAT_TOLERANCE * SEAT_TOLERANCE
        found: dict[str, SimObject] = {}
        for obj in self.objects.values():
            if obj.held_from is not None or obj.kind != kind:
                continue
            x, y, z = obj.pose.position.tolist()
            for slot, (sx, sy, sz) in seats:
                if (x - sx) ** 2 + (y - sy) ** 2 + (z - sz) ** 2 <= tolerance:
                    found.setdefault(slot, obj)
                    break
        return found

    def crucibles(self) -> dict[str, SimObject]:
        """Position slot → the crucible standing in it."""
        return self._occupants(self.positions)

    def mould_contents(self) -> dict[str, SimObject | None]:
        """Mould slot → the object lying in it (or None)."""
        found = self._occupants(self.moulds)
        return {slot: found.get(slot) for slot in self.moulds.slots}

    # ------------------------------------------------------------------ cycle

    @property
    def busy(self) -> bool:
        return self.state in _BUSY

    @property
    def ready(self) -> bool:
        return (
            self.state in (MachineState.IDLE, MachineState.LOADED)
            and self.fault is None
            and not self.door_open
        )

    def tick(self, now: float) -> None:
        """Advance to controller time ``now`` (s): inputs, phases, outputs."""
        self.time = now
        level = self.io.output(self.signals["start"])
        if level == self._start_level and now < self._next_sense and not self.busy:
            self._write_signals()  # no edge, nothing sensed, no phase running: only outputs
            return
        rising = level and not self._start_level
        self._start_level = level
        sense = rising or now >= self._next_sense
        if sense:
            self._next_sense = now + SENSE_PERIOD
        if self.busy:
            present = self.charge
            if sense:
                present = {slot: obj.name for slot, obj in self.crucibles().items()}
            if present != self.charge:
                self._abort("a crucible was taken out or put in during the cycle")
            elif now >= self.phase_end - 1e-9:
                if self.state == MachineState.FUSING:
                    self.state = MachineState.COOLING
                    self.phase_end += self.cooling_time
                    self._note("fusion done, cooling")
                else:
                    self._pour()
        elif self.state != MachineState.ERROR and sense:
            self._settle()
        if rising:
            self._start()
        self._write_signals()

    def _settle(self) -> None:
        """idle/loaded from the crucibles present; done until every mould is empty."""
        if self.state == MachineState.DONE or self.state == MachineState.ERROR:
            if any(o is not None for o in self.mould_contents().values()):
                self.state = MachineState.DONE
                return
            if self.state == MachineState.DONE:
                self._note("moulds empty")
        self.state = MachineState.LOADED if self.crucibles() else MachineState.IDLE

    def _start(self) -> None:
        if not self.ready:
            why = "door open" if self.door_open else self.fault or self.state.value
            self._note(f"start ignored: not ready ({why})")
            return
        crucibles = self.crucibles()
        if not crucibles:
            self._note("start ignored: no crucible loaded")
            return
        occupied = [s for s, o in self.mould_contents().items() if o is not None]
        if occupied:
            self._note(f"start ignored: moulds not empty ({', '.join(occupied)})")
            return
        self.charge = {slot: obj.name for slot, obj in crucibles.items()}
        self.state = MachineState.FUSING
        self.phase_end = self.time + self.fusion_time
        self._note(f"fusing {', '.join(f'{s}: {n}' for s, n in self.charge.items())}")

    def _pour(self) -> None:
        bead = self.moulds.kind
        for slot, name in self.charge.items():
            crucible = self.objects.get(name)
            if crucible is None or crucible.contents is None:
                continue
            mould = self.mould_of[slot]
            bead_name = f"{name}.bead"
            n = 1
            while bead_name in self.objects:  # a crucible fused twice: keep the first bead
                n += 1
                bead_name = f"{name}.bead-{n}"
            self.objects[bead_name] = SimObject(
                bead_name,
                self.moulds.config.holds,
                bead.width,
                bead.height,
                bead.mass,
                self.moulds.grip_pose(mould),
                contents=crucible.contents,
            )
            crucible.contents = None
            self._note(f"{bead_name} in mould {mould}")
        self.charge = {}
        self.state = MachineState.DONE
        self._note("done")

    def _abort(self, reason: str) -> None:
        if self.busy:
            reason = f"{reason}: cycle aborted"
            self.charge = {}
        self.fault = reason
        self.state = MachineState.ERROR
        log.warning("fusion machine: %s", reason)
        self.messages.append(f"{self.time:.3f} error: {reason}")

    def _note(self, text: str) -> None:
        log.info("fusion machine: %s", text)
        self.messages.append(f"{self.time:.3f} {text}")
        del self.messages[:-100]

    def _write_signals(self) -> None:
        # the signals follow from these alone: nothing to work out while they stay the same
        given = (self.state, self.fault, self.door_open)
        if given == self._written_from:
            return
        self._written_from = given
        values = {
            "ready": self.ready,
            "busy": self.busy,
            "done": self.state == MachineState.DONE,
            "error": self.fault is not None or self.door_open,
        }
        if values == self._written:
            return
        self._written = values
        for key, value in values.items():
            sig = self.signals[key]
            self.io.set_input(sig, 1.0 if value else 0.0, owner=f"{OWNER} ({key})")

    # ------------------------------------------------------------------ faults, report

    def inject(self, fault: str) -> str:
        """``machine_error``, ``machine_reset``, ``door_open`` or ``door_close``."""
        if fault == "machine_error":
            self._abort("machine error (injected)")
            text = "machine error"
        elif fault == "machine_reset":
            if self.fault is None:
                text = "machine reset (no fault)"
            else:
                self.fault = None
                self._settle()
                text = "machine reset"
                self._note(text)
        elif fault == "door_open":
            if self.busy:
                self._abort("door opened during the cycle")
            self.door_open = True
            text = "door open"
            self._note(text)
        elif fault == "door_close":
            self.door_open = False
            text = "door closed"
            self._note(text)
        else:
            raise InvalidArgumentError(f"unknown machine fault {fault!r}; known: {FAULTS}")
        self._write_signals()
        return text

    @property
    def time_left(self) -> float:
        """Controller seconds until done (0 unless fusing or cooling)."""
        if self.state == MachineState.FUSING:
            return max(0.0, self.phase_end - self.time) + self.cooling_time
        if self.state == MachineState.COOLING:
            return max(0.0, self.phase_end - self.time)
        return 0.0

    def report(self) -> dict[str, object]:
        """The machine as JSON: state, time left, positions, moulds, IO bits, recent log."""
        crucibles = self.crucibles()
        positions: dict[str, object] = {}
        for slot in self.positions.slots:
            c = crucibles.get(slot)
            positions[slot] = None if c is None else {"crucible": c.name, "contents": c.contents}
        moulds = {s: (None if o is None else o.name) for s, o in self.mould_contents().items()}
        io = {}
        for key, sig in self.signals.items():
            value = self.io.output(sig) if not sig.is_input else bool(self.io.input(sig))
            io[key] = {"signal": str(sig), "value": int(value)}
        return {
            "state": self.state.value,
            "fault": self.fault,
            "door_open": self.door_open,
            "ready": self.ready,
            "time": self.time,
            "time_left": self.time_left,
            "fusion_time": self.fusion_time,
            "cooling_time": self.cooling_time,
            "charge": dict(self.charge),
            "positions": positions,
            "moulds": moulds,
            "io": io,
            "log": self.messages[-20:],
        }
