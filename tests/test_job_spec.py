"""Run files: shape, slots checked against the layout, fusion cycles, clear errors."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fxcell.config import CellConfig
from fxcell.errors import JobSpecError
from fxcell.job import load_run, validate_run
from fxcell.layout import Layout

LAYOUT = Layout(CellConfig.load().layout)
RACK = LAYOUT.station("rack").slots
TRAY = LAYOUT.station("tray").slots


def run_of(*samples: dict[str, Any]) -> dict[str, Any]:
    return {"samples": list(samples)}


def sample(i: int, **extra: Any) -> dict[str, Any]:
    return {"id": f"S{i}", "rack": RACK[i], "tray": TRAY[i], **extra}


def test_machine_positions_are_assigned_in_order_and_cycles_hold_four() -> None:
    run = validate_run(run_of(*(sample(i) for i in range(10))), LAYOUT)
    assert [s.machine for s in run.samples] == ["A1", "A2", "A3", "A4"] * 2 + ["A1", "A2"]
    assert [s.cycle for s in run.samples] == [0] * 4 + [1] * 4 + [2] * 2
    assert [len(c) for c in run.cycles] == [4, 4, 2]


def test_omitted_positions_take_those_the_cycle_leaves_free() -> None:
    run = validate_run(
        run_of(sample(0, machine="A2"), sample(1), sample(2, machine="A1"), sample(3)), LAYOUT
    )
    assert [s.machine for s in run.samples] == ["A2", "A3", "A1", "A4"]


def test_slot_names_are_canonical_so_lower_and_upper_case_are_one_slot() -> None:
    run = validate_run(run_of({"id": "x", "rack": "b3", "tray": "c4", "machine": "a2"}), LAYOUT)
    assert (run.samples[0].rack, run.samples[0].tray, run.samples[0].machine) == ("B3", "C4", "A2")
    with pytest.raises(JobSpecError, match="rack slot B3 is also used by 'x'") as err:
        validate_run(
            run_of(
                {"id": "x", "rack": "B3", "tray": "A1"}, {"id": "y", "rack": "b3", "tray": "A2"}
            ),
            LAYOUT,
        )
    assert (err.value.sample, err.value.field) == ("'y'", "rack")


@pytest.mark.parametrize(
    ("samples", "who", "field", "words"),
    [
        ([sample(0, rack="E1")], "'S0'", "rack", "A1..D4"),
        ([sample(0, tray="A9")], "'S0'", "tray", "A1..D4"),
        ([sample(0, machine="A5")], "'S0'", "machine", "A1..A4"),
        ([sample(0, rack="rack")], "'S0'", "rack", "not a slot name"),
        ([sample(0), sample(1, tray=TRAY[0])], "'S1'", "tray", "also used by 'S0'"),
        ([sample(0), {**sample(1), "id": "S0"}], "'S0'", "id", "id used by an earlier sample"),
        (
            [sample(0, machine="A3"), sample(1, machine="A3")],
            "'S1'",
            "machine",
            "machine position A3 is also used by 'S0' in fusion cycle 1",
        ),
        ([sample(0, colour="red")], "'S0'", "colour", "Extra inputs"),
        ([{"id": "S0", "rack": 3, "tray": "A1"}], "'S0'", "rack", "string"),
        ([{"rack": "A1", "tray": "A1"}], "#1", "id", "Field required"),
    ],
)
def test_invalid_samples_are_named_with_their_field(
    samples: list[dict[str, Any]], who: str, field: str, words: str
) -> None:
    with pytest.raises(JobSpecError) as err:
        validate_run(run_of(*samples), LAYOUT)
    assert (err.value.sample, err.value.field) == (who, field)
    assert words in str(err.value)
    assert str(err.value).startswith(f"sample {who}, field {field!r}: ")


def test_the_same_machine_position_in_another_cycle_is_fine() -> None:
    samples = [sample(i, machine=["A1", "A2", "A3", "A4"][i % 4]) for i in range(8)]
    run = validate_run(run_of(*samples), LAYOUT)
    assert [s.cycle for s in run.samples if s.machine == "A1"] == [0, 1]


def test_a_run_holds_one_to_sixteen_samples() -> None:
    assert len(validate_run(run_of(*(sample(i) for i in range(16))), LAYOUT).samples) == 16
    with pytest.raises(JobSpecError, match="17 samples; a run holds at most 16"):
        validate_run(run_of(*(sample(i % 16, id=f"X{i}") for i in range(17))), LAYOUT)
    with pytest.raises(JobSpecError, match="samples"):
        validate_run({"samples": []}, LAYOUT)


def test_a_layout_without_the_machine_cannot_run_a_job() -> None:
    cfg = CellConfig.load().layout
    stations = {k: v for k, v in cfg.stations.items() if k != "moulds"}
    layout = Layout(cfg.model_copy(update={"stations": stations}))
    with pytest.raises(JobSpecError, match="no station 'moulds'"):
        validate_run(run_of(sample(0)), layout)


def test_run_files_are_read_as_yaml_or_json(tmp_path: Path) -> None:
    yml = tmp_path / "run.yaml"
    yml.write_text("name: batch 7\nsamples:\n  - {id: S1, rack: B3, tray: C4}\n")
    run = load_run(yml, LAYOUT)
    assert (run.name, run.samples[0].rack, run.samples[0].machine) == ("batch 7", "B3", "A1")
    js = tmp_path / "run.json"
    js.write_text(json.dumps(run.to_dict()))
    assert load_run(js, LAYOUT) == run
    (tmp_path / "bad.yaml").write_text("samples: [\n")
    with pytest.raises(JobSpecError, match="not valid yaml"):
        load_run(tmp_path / "bad.yaml", LAYOUT)
    (tmp_path / "list.yaml").write_text("- {id: S1}\n")
    with pytest.raises(JobSpecError, match="expected a mapping"):
        load_run(tmp_path / "list.yaml", LAYOUT)
    with pytest.raises(JobSpecError, match="cannot read run file"):
        load_run(tmp_path / "missing.yaml", LAYOUT)


# ----------------------------------------------------------------- malformed input at random

_slot_text = st.one_of(
    st.sampled_from([*RACK, "A5", "E1", "a1", "Z9", "", "11", "B"]),
    st.text(max_size=4),
    st.integers(),
    st.none(),
)
_sample = st.fixed_dictionaries(
    {
        "id": st.one_of(
            st.sampled_from(["S1", "S2", "S3", "S4", "S5"]), st.text(max_size=3), st.integers()
        ),
        "rack": _slot_text,
        "tray": _slot_text,
    },
    optional={"machine": _slot_text, "extra": st.integers()},
)
_run = st.one_of(
    st.fixed_dictionaries(
        {"samples": st.lists(_sample, max_size=18)}, optional={"name": st.text(max_size=5)}
    ),
    st.dictionaries(st.text(max_size=8), st.integers(), max_size=3),
)


@given(_run)
def test_any_input_is_a_valid_run_or_a_job_spec_error(data: dict[str, Any]) -> None:
    try:
        run = validate_run(data, LAYOUT)
    except JobSpecError:
        return
    assert 1 <= len(run.samples) <= 16
    assert len({s.id for s in run.samples}) == len(run.samples)
    assert len({s.rack for s in run.samples}) == len(run.samples)
    assert len({s.tray for s in run.samples}) == len(run.samples)
    for cycle in run.cycles:
        assert len(cycle) <= 4
        assert len({s.machine for s in cycle}) == len(cycle)
    for s in run.samples:
        assert s.rack in RACK
        assert s.tray in TRAY
        assert s.machine in LAYOUT.station("machine").slots


POSITIONS = LAYOUT.station("machine").slots


@given(
    st.lists(
        st.tuples(
            st.sampled_from(RACK), st.sampled_from(TRAY), st.none() | st.sampled_from(POSITIONS)
        ),
        min_size=1,
        max_size=16,
    )
)
def test_a_run_is_valid_exactly_when_no_slot_is_used_twice(
    rows: list[tuple[str, str, str | None]],
) -> None:
    data = run_of(
        *(
            {"id": f"S{i}", "rack": r, "tray": t, **({"machine": m} if m else {})}
            for i, (r, t, m) in enumerate(rows)
        )
    )
    given_per_cycle = [[m for _, _, m in rows[c : c + 4] if m] for c in range(0, len(rows), 4)]
    valid = (
        len({r for r, _, _ in rows}) == len(rows)
        and len({t for _, t, _ in rows}) == len(rows)
        and all(len(set(ms)) == len(ms) for ms in given_per_cycle)
    )
    if not valid:
        with pytest.raises(JobSpecError) as err:
            validate_run(data, LAYOUT)
        assert err.value.field in ("rack", "tray", "machine")
        return
    run = validate_run(data, LAYOUT)
    assert [(s.rack, s.tray) for s in run.samples] == [(r, t) for r, t, _ in rows]
    assert all(s.machine == m for s, (_, _, m) in zip(run.samples, rows, strict=True) if m)
    for cycle in run.cycles:
        assert sorted(s.machine for s in cycle) == sorted({s.machine for s in cycle})
