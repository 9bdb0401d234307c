"""A run of the fusion-machine job: which samples, from which rack slot, to which tray slot.

A run file (YAML or JSON) or dict::

    name: batch 2026-11-23          # optional
    samples:
      - {id: S1, rack: A1, tray: A1, machine: A1}   # machine position optional
      - {id: S2, rack: A2, tray: A2}

Samples form fusion cycles in order, four at a time (the machine's positions). A sample
without ``machine`` gets the first position its cycle leaves free. :func:`validate_run`
checks everything against the :class:`~fxcell.layout.Layout` before anything moves: the
slots exist, no rack or tray slot is used twice, machine positions are unique within a
cycle, at most 16 samples, ids unique. Errors are :class:`~fxcell.errors.JobSpecError`
naming the sample and the field.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from fxcell.errors import JobSpecError, LayoutError
from fxcell.layout import Layout

RACK = "rack"
TRAY = "tray"
MACHINE = "machine"
MOULDS = "moulds"
MAX_SAMPLES = 16


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


class SampleSpec(_Strict):
    """One sample as written in a run file."""

    id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.:-]*$")
    rack: str
    """The crucible's slot in the rack (``B3``)."""
    tray: str
    """Where its glass bead goes on the tray."""
    machine: str | None = None
    """The machine position (``A1``..``A4``); its mould has the same name."""


class RunSpec(_Strict):
    """A run as written in a file: a name and its samples."""

    name: str = Field("", max_length=200)
    samples: list[SampleSpec] = Field(min_length=1)


@dataclass(frozen=True)
class Sample:
    """A validated sample: canonical slot names, its machine position and fusion cycle."""

    index: int
    id: str
    rack: str
    machine: str
    tray: str
    cycle: int

    @property
    def mould(self) -> str:
        return self.machine


@dataclass(frozen=True)
class Run:
    """A validated run."""

    name: str
    samples: tuple[Sample, ...]

    @property
    def cycles(self) -> list[list[Sample]]:
        out: list[list[Sample]] = []
        for s in self.samples:
            if s.cycle == len(out):
                out.append([])
            out[s.cycle].append(s)
        return out

    def to_dict(self) -> dict[str, Any]:
        """The run as a dict :func:`validate_run` accepts (machine positions filled in)."""
        return {
            "name": self.name,
            "samples": [
                {"id": s.id, "rack": s.rack, "machine": s.machine, "tray": s.tray}
                for s in self.samples
            ],
        }


def _label(raw: Any, index: int) -> str:
    """How to name sample ``index`` of the raw input in an error."""
    try:
        sid = raw["samples"][index]["id"]
    except (KeyError, IndexError, TypeError):
        sid = None
    return repr(sid) if isinstance(sid, str) and sid else f"#{index + 1}"


def parse_run(data: Mapping[str, Any]) -> RunSpec:
    """Check the shape of a run dict (types, keys); :class:`JobSpecError` on the first problem."""
    try:
        return RunSpec.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = err["loc"]
        msg = err["msg"]
        if len(loc) >= 2 and loc[0] == "samples" and isinstance(loc[1], int):
            field = str(loc[2]) if len(loc) > 2 else None
            raise JobSpecError(msg, _label(data, loc[1]), field) from None
        where = ".".join(str(p) for p in loc) or "run"
        raise JobSpecError(f"{where}: {msg}") from None


def _slot(layout: Layout, station: str, slot: str, sample: str, field: str) -> str:
    try:
        return layout.slot(station, slot)[1]
    except LayoutError as exc:
        raise JobSpecError(str(exc), sample, field) from None


def validate_run(data: RunSpec | Mapping[str, Any], layout: Layout) -> Run:
    """A run checked against ``layout``; :class:`JobSpecError` names the sample and field."""
    spec = data if isinstance(data, RunSpec) else parse_run(data)
    for station in (RACK, TRAY, MACHINE, MOULDS):
        try:
            layout.station(station)
        except LayoutError as exc:
            raise JobSpecError(f"the layout cannot run the job: {exc}") from None
    positions = layout.station(MACHINE).slots
    per_cycle = len(positions)
    if len(spec.samples) > MAX_SAMPLES:
        raise JobSpecError(f"{len(spec.samples)} samples; a run holds at most {MAX_SAMPLES}")
    ids: set[str] = set()
    used: dict[tuple[str, str], str] = {}
    rows: list[tuple[str, str, str | None, str]] = []
    for i, s in enumerate(spec.samples):
        label = repr(s.id)
        if s.id in ids:
            raise JobSpecError("id used by an earlier sample", label, "id")
        ids.add(s.id)
        rack = _slot(layout, RACK, s.rack, label, "rack")
        tray = _slot(layout, TRAY, s.tray, label, "tray")
        machine = None if s.machine is None else _slot(layout, MACHINE, s.machine, label, "machine")
        _slot(layout, MOULDS, machine or positions[0], label, "machine")
        for station, slot, field in ((RACK, rack, "rack"), (TRAY, tray, "tray")):
            other = used.get((station, slot))
            if other is not None:
                raise JobSpecError(f"{station} slot {slot} is also used by {other}", label, field)
            used[(station, slot)] = label
        cycle = i // per_cycle
        if machine is not None:
            for j in range(cycle * per_cycle, i):
                if rows[j][2] == machine:
                    raise JobSpecError(
                        f"machine position {machine} is also used by {rows[j][0]!r} "
                        f"in fusion cycle {cycle + 1}",
                        label,
                        "machine",
                    )
        rows.append((s.id, rack, machine, tray))
    samples: list[Sample] = []
    for start in range(0, len(rows), per_cycle):
        cycle_rows = rows[start : start + per_cycle]
        free = [p for p in positions if p not in {r[2] for r in cycle_rows}]
        for k, (sid, rack, machine, tray) in enumerate(cycle_rows):
            if machine is None:
                machine = free.pop(0)
            samples.append(Sample(start + k, sid, rack, machine, tray, start // per_cycle))
    return Run(spec.name, tuple(samples))


def load_run(path: str | Path, layout: Layout) -> Run:
    """Read a run file (YAML, or JSON, which is YAML too) and validate it."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise JobSpecError(f"cannot read run file {path}: {exc.strerror}") from None
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (ValueError, yaml.YAMLError) as exc:
        raise JobSpecError(
            f"{path}: not valid {path.suffix.lstrip('.') or 'YAML'}: {exc}"
        ) from None
    if not isinstance(data, dict):
        raise JobSpecError(f"{path}: expected a mapping with 'samples'")
    return validate_run(data, layout)
