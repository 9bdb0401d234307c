"""The simulated fusion machine's model, ticked directly (no sockets), and the IO signal names."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fxcell.config import CellConfig
from fxcell.errors import InvalidArgumentError
from fxcell.geometry import Pose
from fxcell.layout import Layout
from fxcell.sim.controller import IOState
from fxcell.sim.fusion import SENSE_PERIOD, FusionMachine, MachineState, parse_machine_io, slots_of
from fxcell.sim.gripper import SimObject
from fxcell.sim.signals import KINDS, Signal, parse_signal, parse_value

FUSION = 10.0
COOLING = 5.0
SCALE = 0.1  # fusion 1 s, cooling 0.5 s of controller time
DT = 0.002


@pytest.fixture(scope="module")
def layout() -> Layout:
    return Layout(CellConfig.load().layout)


class Bench:
    """A machine with its world and IO, on a clock the test advances."""

    def __init__(self, layout: Layout, **options: object) -> None:
        self.layout = layout
        self.objects: dict[str, SimObject] = {}
        self.io = IOState()
        self.machine = FusionMachine(
            layout,
            self.objects,
            self.io,
            time_scale=SCALE,
            fusion_time=FUSION,
            cooling_time=COOLING,
            **options,  # type: ignore[arg-type]
        )
        self.now = 0.0
        self.tick()

    def tick(self, seconds: float = SENSE_PERIOD) -> None:
        """Advance ``seconds`` (by default long enough for the sensors to look once)."""
        end = self.now + seconds
        while self.now < end - 1e-12:
            self.now += DT
            self.machine.tick(self.now)

    def put(self, name: str, station: str, slot: str, contents: str | None = "sample") -> None:
        st_ = self.layout.station(station)
        kind = self.layout.config.objects[st_.config.holds]
        self.objects[name] = SimObject(
            name,
            st_.config.holds,
            kind.width,
            kind.height,
            kind.mass,
            st_.grip_pose(slot),
            contents=contents,
        )

    def start(self, level: bool = True) -> None:
        bit = parse_signal("DO0").bit
        self.io.standard_digital = (self.io.standard_digital & ~(1 << bit)) | (int(level) << bit)
        self.tick(DT)

    def bits(self) -> dict[str, int]:
        return {
            k: int(self.io.input(parse_signal(s)))
            for k, s in {"ready": "DI0", "busy": "DI1", "done": "DI2", "error": "DI3"}.items()
        }


def test_a_full_cycle_pours_a_bead_per_filled_crucible_into_the_matching_mould(
    layout: Layout,
) -> None:
    b = Bench(layout)
    assert b.machine.state == MachineState.IDLE
    assert b.bits() == {"ready": 1, "busy": 0, "done": 0, "error": 0}
    b.put("crucible-A1", "machine", "A1")
    b.put("crucible-B2", "machine", "A3")
    b.put("empty-one", "machine", "A4", contents=None)
    b.tick()
    assert b.machine.state == MachineState.LOADED
    assert b.bits()["ready"] == 1

    b.start()
    assert b.machine.state == MachineState.FUSING
    assert b.bits() == {"ready": 0, "busy": 1, "done": 0, "error": 0}
    assert b.machine.time_left == pytest.approx((FUSION + COOLING) * SCALE, abs=2 * DT)
    b.tick(FUSION * SCALE - 2 * DT)
    assert b.machine.state == MachineState.FUSING
    b.tick(2 * DT)
    assert b.machine.state == MachineState.COOLING
    assert b.bits()["busy"] == 1
    b.tick(COOLING * SCALE)
    assert b.machine.state == MachineState.DONE
    assert b.bits() == {"ready": 0, "busy": 0, "done": 1, "error": 0}

    moulds = layout.station("moulds")
    beads = {n: o for n, o in b.objects.items() if o.kind == "bead"}
    assert sorted(beads) == ["crucible-A1.bead", "crucible-B2.bead"]
    for name, mould in (("crucible-A1.bead", "A1"), ("crucible-B2.bead", "A3")):
        assert np.allclose(beads[name].pose.position, moulds.grip_pose(mould).position)
        assert beads[name].contents == "sample"
        assert beads[name].width == layout.config.objects["bead"].width
        assert beads[name].mass == layout.config.objects["bead"].mass
    assert b.objects["crucible-A1"].contents is None
    assert b.objects["crucible-B2"].contents is None

    # done until every mould is empty; then the crucibles still standing make it loaded
    b.start(False)
    del b.objects["crucible-A1.bead"]
    b.tick()
    assert b.machine.state == MachineState.DONE
    b.objects["crucible-B2.bead"].pose = layout.station("tray").grip_pose("A1")
    b.tick()
    assert b.machine.state == MachineState.LOADED
    for name in ("crucible-A1", "crucible-B2", "empty-one"):
        del b.objects[name]
    b.tick()
    assert b.machine.state == MachineState.IDLE
    assert b.bits() == {"ready": 1, "busy": 0, "done": 0, "error": 0}


def test_start_without_crucibles_or_while_not_ready_is_logged_and_ignored(
    layout: Layout,
) -> None:
    b = Bench(layout)
    b.start()
    assert b.machine.state == MachineState.IDLE
    assert "no crucible" in b.machine.messages[-1]
    b.start(False)
    b.put("c", "machine", "A2")
    b.machine.inject("door_open")
    b.start()
    assert b.machine.state == MachineState.LOADED
    assert "not ready" in b.machine.messages[-1]


def test_only_a_rising_edge_of_start_starts_a_cycle(layout: Layout) -> None:
    b = Bench(layout)
    b.start()  # high while nothing is loaded: ignored
    b.put("c", "machine", "A1")
    b.tick(0.1)
    assert b.machine.state == MachineState.LOADED
    b.start(False)
    b.start()
    assert b.machine.state == MachineState.FUSING


def test_a_held_crucible_or_one_off_its_seat_is_not_loaded(layout: Layout) -> None:
    b = Bench(layout)
    b.put("c", "machine", "A1")
    seat = b.objects["c"].pose
    b.objects["c"].pose = Pose(seat.position + np.array([0.0, 0.006, 0.0]), seat.rotation)
    b.tick()
    assert b.machine.state == MachineState.IDLE
    b.objects["c"].pose = seat
    b.objects["c"].held_from = seat.inverse() @ seat
    b.tick()
    assert b.machine.state == MachineState.IDLE
    b.objects["c"].held_from = None
    b.tick()
    assert b.machine.state == MachineState.LOADED


@pytest.mark.parametrize("change", ["taken_out", "put_in"])
def test_a_crucible_moved_during_the_cycle_aborts_it_with_an_error_and_no_beads(
    layout: Layout, change: str
) -> None:
    b = Bench(layout)
    b.put("c1", "machine", "A1")
    b.start()
    b.tick(0.2)
    if change == "taken_out":
        b.objects["c1"].pose = layout.station("rack").grip_pose("A1")
    else:
        b.put("c2", "machine", "A2")
    b.tick()
    assert b.machine.state == MachineState.ERROR
    assert b.bits() == {"ready": 0, "busy": 0, "done": 0, "error": 1}
    assert "during the cycle" in (b.machine.fault or "")
    b.tick((FUSION + COOLING) * SCALE)
    assert not [o for o in b.objects.values() if o.kind == "bead"]
    assert b.objects["c1"].contents == "sample"
    b.machine.inject("machine_reset")
    b.tick()
    assert b.bits()["error"] == 0
    assert b.machine.state == (MachineState.IDLE if change == "taken_out" else MachineState.LOADED)


def test_machine_error_during_cooling_aborts_and_latches_until_reset(layout: Layout) -> None:
    b = Bench(layout)
    b.put("c1", "machine", "A1")
    b.start()
    b.tick(FUSION * SCALE + 0.1)
    assert b.machine.state == MachineState.COOLING
    b.machine.inject("machine_error")
    b.tick(COOLING * SCALE + 0.1)
    assert b.machine.state == MachineState.ERROR
    assert b.bits() == {"ready": 0, "busy": 0, "done": 0, "error": 1}
    assert not [o for o in b.objects.values() if o.kind == "bead"]
    b.start(False)
    b.start()  # not ready: ignored
    assert b.machine.state == MachineState.ERROR
    assert b.machine.inject("machine_reset") == "machine reset"
    b.tick()
    assert b.machine.state == MachineState.LOADED
    assert b.bits() == {"ready": 1, "busy": 0, "done": 0, "error": 0}


def test_an_open_door_reports_error_and_not_ready_until_closed(layout: Layout) -> None:
    b = Bench(layout)
    b.machine.inject("door_open")
    b.tick()
    assert b.bits() == {"ready": 0, "busy": 0, "done": 0, "error": 1}
    assert b.machine.state == MachineState.IDLE
    b.machine.inject("door_close")
    b.tick()
    assert b.bits() == {"ready": 1, "busy": 0, "done": 0, "error": 0}


def test_opening_the_door_during_fusion_aborts_the_cycle(layout: Layout) -> None:
    b = Bench(layout)
    b.put("c1", "machine", "A1")
    b.start()
    b.machine.inject("door_open")
    b.machine.inject("door_close")
    b.tick((FUSION + COOLING) * SCALE + 0.1)
    assert b.machine.state == MachineState.ERROR
    assert not [o for o in b.objects.values() if o.kind == "bead"]


def test_the_machine_owns_its_inputs_and_leaves_the_others_free(layout: Layout) -> None:
    b = Bench(layout)
    with pytest.raises(InvalidArgumentError, match=r"DI2 is driven by the fusion machine \(done\)"):
        b.io.set_input(parse_signal("DI2"), 1)
    b.io.set_input(parse_signal("DI5"), 1)
    b.io.set_input(parse_signal("AI0"), 4.2)
    b.tick()
    assert b.io.input_bits == 1 << 5 | 1 << 0  # DI5 and the machine's ready
    assert b.io.analog_in[0] == 4.2


def test_machine_io_can_be_rewired(layout: Layout) -> None:
    b = Bench(layout, signals=parse_machine_io("start=CO1,ready=DI4,error=TI1"))
    assert b.io.input_bits == 1 << 4
    b.io.set_input(parse_signal("DI0"), 1)  # free now
    b.put("c1", "machine", "A1")
    b.start()  # DO0 is no longer the start signal
    assert b.machine.state == MachineState.LOADED
    b.io.configurable_digital = 1 << 1
    b.tick()
    assert b.machine.state == MachineState.FUSING
    assert b.io.input_bits == 1 << 0 | 1 << 1  # DI0 set by hand, busy on DI1
    b.machine.inject("machine_error")
    assert b.io.input_bits >> 17 & 1


def test_report_lists_state_positions_moulds_and_io(layout: Layout) -> None:
    b = Bench(layout)
    b.put("c1", "machine", "A2")
    b.start()
    r = b.machine.report()
    assert r["state"] == "fusing"
    assert r["positions"] == {
        "A1": None,
        "A2": {"crucible": "c1", "contents": "sample"},
        "A3": None,
        "A4": None,
    }
    assert r["moulds"] == dict.fromkeys(["A1", "A2", "A3", "A4"])
    assert r["io"]["start"] == {"signal": "DO0", "value": 1}
    assert r["io"]["busy"] == {"signal": "DI1", "value": 1}
    assert r["time_left"] == pytest.approx((FUSION + COOLING) * SCALE, abs=2 * DT)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("start=DI0", "start must be a digital output"),
        ("ready=DO1", "ready must be an input"),
        ("busy=DI0", "distinct"),
        ("error=AI0", "not a digital signal"),
        ("stop=DO1", "NAME=SIGNAL"),
        ("ready", "NAME=SIGNAL"),
        ("ready=DI9", "0..7"),
    ],
)
def test_bad_machine_io_is_refused(text: str, message: str) -> None:
    with pytest.raises(InvalidArgumentError, match=message):
        parse_machine_io(text)


def test_machine_io_defaults() -> None:
    assert {k: str(v) for k, v in parse_machine_io("").items()} == {
        "start": "DO0",
        "ready": "DI0",
        "busy": "DI1",
        "done": "DI2",
        "error": "DI3",
    }


def test_crucible_slots_by_name_or_count(layout: Layout) -> None:
    rack = layout.station("rack")
    assert slots_of(rack, "3") == ["A1", "A2", "A3"]
    assert slots_of(rack, "16") == rack.slots
    assert slots_of(rack, "b2, a1") == ["B2", "A1"]
    for bad in ("17", "A5", "E1", "A1,A1", "x"):
        with pytest.raises(InvalidArgumentError):
            slots_of(rack, bad)


@given(st.sampled_from(sorted(KINDS)), st.data())
def test_signal_names_round_trip(kind: str, data: st.DataObject) -> None:
    index = data.draw(st.integers(0, KINDS[kind][0] - 1))
    sig = Signal(kind, index)
    assert parse_signal(str(sig)) == sig
    assert parse_signal(f" {kind.lower()}{index} ") == sig


@given(st.integers(0, 7))
def test_a_bare_number_is_a_standard_digital_input(index: int) -> None:
    assert parse_signal(str(index)) == Signal("DI", index)


@given(st.text(max_size=6))
def test_signal_parser_accepts_only_known_names(text: str) -> None:
    try:
        sig = parse_signal(text)
    except InvalidArgumentError:
        return
    assert sig.kind in KINDS
    assert 0 <= sig.index < KINDS[sig.kind][0]


def test_digital_bits_follow_the_rtde_layout() -> None:
    assert [parse_signal(n).bit for n in ("DI0", "DI7", "CI0", "CI7", "TI0", "TI1")] == [
        0,
        7,
        8,
        15,
        16,
        17,
    ]
    assert parse_signal("TO1").bit == 17
    with pytest.raises(InvalidArgumentError):
        _ = parse_signal("AI0").bit
    for bad in ("TI2", "AI2", "DI8", "XI0", "", "D", "-1"):
        with pytest.raises(InvalidArgumentError):
            parse_signal(bad)


def test_values_are_bits_for_digital_and_floats_for_analog() -> None:
    di, ai = parse_signal("DI1"), parse_signal("AI1")
    assert [parse_value(di, v) for v in ("1", "0", "true", "off")] == [1.0, 0.0, 1.0, 0.0]
    assert parse_value(ai, "4.2") == 4.2
    for sig, bad in ((di, "2"), (di, "0.5"), (ai, "nan"), (ai, "x")):
        with pytest.raises(InvalidArgumentError):
            parse_value(sig, bad)
