"""The robot-mode state machine: defined as data in ``statecharts/robot.yaml``.

The YAML is loaded into a pytransitions ``HierarchicalAsyncMachine`` (nested states
separated by ``.``) and drawn as a Mermaid ``stateDiagram-v2`` by :func:`to_mermaid`.
The machine follows the controller: :func:`observed_state` maps one RTDE sample (plus
what the link knows) to the state it implies, and :meth:`RobotStateMachine.sync` moves
the machine there through the declared ``observe_*`` transition, or by a forced
``resync`` when none is declared. All changes pass through one queue consumed by one
task, as the pytransitions asyncio notes advise; callbacks never await moves.
"""

from __future__ import annotations

import argparse
import asyncio
import enum
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml
from transitions.extensions.asyncio import HierarchicalAsyncMachine, NestedAsyncState

from fxcell.config import parse_yaml
from fxcell.errors import ConfigError, InvalidStateError
from fxcell.events import TransitionEvent, now
from fxcell.protocol import AT_REST_SPEED, SAFETY_STOPS, RobotMode, RobotState, RuntimeState
from fxcell.resources import resource_dir

log = logging.getLogger(__name__)

STATECHART_DIR = resource_dir("statecharts")
STATECHART = STATECHART_DIR / "robot.yaml"
CONNECTED = "connected"
SEPARATOR = "."


class CellState(enum.StrEnum):
    """Public names of the machine's leaf states (``cell.state``)."""

    DISCONNECTED = "disconnected"
    BOOTING = "booting"
    POWER_OFF = "power_off"
    POWERING_ON = "powering_on"
    IDLE = "idle"
    BACKDRIVE = "backdrive"
    PROGRAM_STOPPED = "running.program_stopped"
    EXTERNAL_CONTROL_READY = "running.external_control_ready"
    MOVING = "running.moving"
    STOPPING = "running.stopping"
    FREEDRIVE = "running.freedrive"
    PROTECTIVE_STOP = "protective_stop"
    SAFEGUARD_STOP = "safeguard_stop"
    EMERGENCY_STOP = "emergency_stop"
    FAULT = "fault"
    SHUTTING_DOWN = "shutting_down"

    @property
    def is_running(self) -> bool:
        return self.value.startswith("running.")


def machine_name(state: CellState | str) -> str:
    """The pytransitions name of a public state (``idle`` -> ``connected.idle``)."""
    state = str(state)
    return state if state == CellState.DISCONNECTED else f"{CONNECTED}{SEPARATOR}{state}"


def public_name(name: str) -> CellState:
    """The public state of a pytransitions state name."""
    prefix = CONNECTED + SEPARATOR
    return CellState(name[len(prefix) :] if name.startswith(prefix) else name)


# ----------------------------------------------------------------- the definition


@dataclass(frozen=True)
class Statechart:
    """The machine definition as read from YAML (MarkupMachine-style dicts)."""

    name: str
    title: str
    initial: str
    states: list[dict[str, Any]]
    transitions: list[dict[str, Any]]
    commands: dict[str, tuple[str, ...]]

    def leaf_states(self) -> list[str]:
        """Full machine names of every leaf state, in definition order."""
        out: list[str] = []

        def walk(states: list[dict[str, Any]], prefix: str) -> None:
            for state in states:
                name = prefix + state["name"]
                if state.get("children"):
                    walk(state["children"], name + SEPARATOR)
                else:
                    out.append(name)

        walk(self.states, "")
        return out

    def next_step(self, state: CellState) -> str:
        """What the operator does to get on from ``state`` (the state's ``next`` text)."""
        target = machine_name(state)

        def find(states: list[dict[str, Any]], prefix: str) -> str:
            for item in states:
                name = prefix + item["name"]
                if name == target:
                    return str(item.get("next", ""))
                if item.get("children") and target.startswith(name + SEPARATOR):
                    return find(item["children"], name + SEPARATOR)
            return ""

        return find(self.states, "")

    def allowed(self, command: str) -> tuple[CellState, ...]:
        """The public states in which ``command`` may be sent."""
        try:
            patterns = self.commands[command]
        except KeyError:
            raise KeyError(f"statechart has no guard for command {command!r}") from None
        out: list[CellState] = []
        for pattern in patterns:
            if pattern.endswith(".*"):
                base = pattern[:-1]
                out.extend(s for s in CellState if s.value.startswith(base))
            else:
                out.append(CellState(pattern))
        return tuple(out)


def _normalise_states(raw: Any, where: str) -> list[dict[str, Any]]:
    if not isinstance(raw, list):
        raise ConfigError(f"{where}: 'states' must be a list")
    out: list[dict[str, Any]] = []
    for item in raw:
        state = {"name": item} if isinstance(item, str) else dict(item)
        if "name" not in state:
            raise ConfigError(f"{where}: a state has no name: {item!r}")
        if "children" in state:
            state["children"] = _normalise_states(state["children"], where)
        out.append(state)
    return out


def read_statechart(path: str | Path) -> Statechart:
    """Read any statechart YAML file (the robot's, the job's): states, transitions, commands."""
    path = Path(path)
    try:
        data = parse_yaml(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read statechart {path}: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping")
    unknown = set(data) - {"name", "title", "initial", "states", "transitions", "commands"}
    if unknown:
        raise ConfigError(f"{path}: unknown keys {sorted(unknown)}")
    commands = {str(k): tuple(str(s) for s in v) for k, v in (data.get("commands") or {}).items()}
    chart = Statechart(
        name=str(data.get("name", path.stem)),
        title=str(data.get("title", data.get("name", path.stem))),
        initial=str(data["initial"]),
        states=_normalise_states(data.get("states"), str(path)),
        transitions=[dict(t) for t in data.get("transitions") or []],
        commands=commands,
    )
    leaves = set(chart.leaf_states())
    names = {
        SEPARATOR.join(n.split(SEPARATOR)[:i])
        for n in leaves
        for i in range(1, 1 + n.count(SEPARATOR) + 1)
    }
    for t in chart.transitions:
        sources = t["source"] if isinstance(t["source"], list) else [t["source"]]
        for name in [*sources, t["dest"]]:
            if name not in names:
                raise ConfigError(
                    f"{path}: transition {t['trigger']!r} names unknown state {name!r}"
                )
    return chart


def load_statechart(path: str | Path | None = None) -> Statechart:
    """Read and check the robot-mode statechart (default: ``statecharts/robot.yaml``)."""
    path = Path(path) if path is not None else STATECHART
    chart = read_statechart(path)
    leaves = set(chart.leaf_states())
    missing = {machine_name(s) for s in CellState} - leaves
    extra = leaves - {machine_name(s) for s in CellState}
    if missing or extra:
        raise ConfigError(f"{path}: states differ from CellState: {missing=} {extra=}")
    for command in chart.commands:
        try:
            chart.allowed(command)
        except ValueError as exc:
            raise ConfigError(f"{path}: commands.{command}: {exc}") from None
    return chart


# ----------------------------------------------------------------- the diagram


def _mermaid_id(name: str) -> str:
    return name.replace(SEPARATOR, "__")


def to_mermaid(chart: Statechart) -> str:
    """Draw the chart as a Mermaid ``stateDiagram-v2`` (deterministic text)."""
    lines = ["---", f"title: {chart.title}", "---", "stateDiagram-v2", "  direction LR"]

    def add_states(states: list[dict[str, Any]], prefix: str, indent: str) -> None:
        for state in states:
            name = prefix + state["name"]
            sid = _mermaid_id(name)
            children = state.get("children")
            if children:
                lines.append(f'{indent}state "{state["name"]}" as {sid} {{')
                initial = name + SEPARATOR + str(state.get("initial", children[0]["name"]))
                lines.append(f"{indent}  [*] --> {_mermaid_id(initial)}")
                add_states(children, name + SEPARATOR, indent + "  ")
                lines.append(f"{indent}}}")
            else:
                lines.append(f'{indent}state "{state["name"]}" as {sid}')
                if state.get("description"):
                    desc = str(state["description"]).replace(":", " -").replace('"', "'")
                    lines.append(f"{indent}{sid} : {desc}")

    add_states(chart.states, "", "  ")
    lines.append(f"  [*] --> {_mermaid_id(chart.initial)}")
    edges: dict[tuple[str, str], list[str]] = {}
    for t in chart.transitions:
        sources = t["source"] if isinstance(t["source"], list) else [t["source"]]
        for source in sources:
            edges.setdefault((source, t["dest"]), []).append(str(t["trigger"]))
    for (source, dest), triggers in edges.items():
        lines.append(f"  {_mermaid_id(source)} --> {_mermaid_id(dest)} : {' / '.join(triggers)}")
    return "\n".join(lines) + "\n"


def diagram_path(chart_path: Path = STATECHART) -> Path:
    return chart_path.with_suffix(".mmd")


# ----------------------------------------------------------------- observed state


_BOOTING_MODES = {
    RobotMode.NO_CONTROLLER,
    RobotMode.DISCONNECTED,
    RobotMode.CONFIRM_SAFETY,
    RobotMode.BOOTING,
    RobotMode.UPDATING_FIRMWARE,
}
_SAFETY_STATES = {mode: CellState(stop) for mode, stop in SAFETY_STOPS.items()}
_MODE_STATES = {
    RobotMode.POWER_OFF: CellState.POWER_OFF,
    RobotMode.POWER_ON: CellState.POWERING_ON,
    RobotMode.IDLE: CellState.IDLE,
    RobotMode.BACKDRIVE: CellState.BACKDRIVE,
}


def observed_state(
    sample: RobotState | None,
    *,
    control_ready: bool = False,
    moving: bool = False,
    stopping: bool = False,
    shutting_down: bool = False,
    freedrive: bool = False,
) -> CellState:
    """The state one RTDE sample implies (``None``: no live sample, the link is down).

    ``control_ready``: the link holds a control interface whose script is PLAYING;
    ``moving``/``stopping``: the Cell runs / brakes a move task. An arm still in motion
    with no move task (braking after an aborted move) is ``stopping``: external control
    is ready only once the arm is at rest. ``freedrive``: the Cell put the arm in teach mode
    (it may move by hand).
    """
    if sample is None:
        return CellState.DISCONNECTED
    if shutting_down:
        return CellState.SHUTTING_DOWN
    safety = _SAFETY_STATES.get(sample.safety_mode)
    if safety is not None:
        return safety
    if sample.robot_mode in _BOOTING_MODES:
        return CellState.BOOTING
    if sample.robot_mode != RobotMode.RUNNING:
        return _MODE_STATES[sample.robot_mode]
    if not control_ready or sample.runtime_state != RuntimeState.PLAYING:
        return CellState.PROGRAM_STOPPED
    if stopping:
        return CellState.STOPPING
    if freedrive:
        return CellState.FREEDRIVE
    if moving:
        return CellState.MOVING
    if max(map(abs, sample.actual_qd)) > AT_REST_SPEED:
        return CellState.STOPPING
    return CellState.EXTERNAL_CONTROL_READY


# ----------------------------------------------------------------- the machine


class _State(NestedAsyncState):
    separator = SEPARATOR


class _Machine(HierarchicalAsyncMachine):
    state_cls = _State


def machine_states(states: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """A chart's states as pytransitions takes them (without ``description``/``next``)."""
    out = []
    for state in states:
        state = {k: v for k, v in state.items() if k not in ("description", "next")}
        if "children" in state:
            state["children"] = machine_states(state["children"])
        out.append(state)
    return out


class _Model:
    state: str


Cause = Literal["command", "observed"]


@dataclass
class _Request:
    target: CellState | None
    trigger: str
    cause: Cause
    detail: str
    done: asyncio.Future[bool]


class RobotStateMachine:
    """The robot-mode machine of one Cell: guards, one input queue, transition events.

    Start :meth:`run` as a task the owner keeps (and cancels on close). ``on_transition``
    is called synchronously for every state change.
    """

    def __init__(
        self,
        chart: Statechart | None = None,
        on_transition: Callable[[TransitionEvent], None] | None = None,
    ) -> None:
        self.chart = chart or load_statechart()
        self._on_transition = on_transition
        self._model = _Model()
        self._machine = _Machine(
            model=self._model,
            states=machine_states(self.chart.states),
            transitions=self.chart.transitions,
            initial=self.chart.initial,
            auto_transitions=False,
            ignore_invalid_triggers=False,
            name=self.chart.name,
        )
        self._queue: asyncio.Queue[_Request] = asyncio.Queue()
        self._changed = asyncio.Event()
        self._edges = [
            (
                str(t["trigger"]),
                [str(x) for x in (t["source"] if isinstance(t["source"], list) else [t["source"]])],
                str(t["dest"]),
            )
            for t in self.chart.transitions
        ]
        self._allowed = {cmd: frozenset(self.chart.allowed(cmd)) for cmd in self.chart.commands}
        self._next_steps = {s: self.chart.next_step(s) for s in CellState}

    @property
    def state(self) -> CellState:
        return public_name(self._model.state)

    def allowed(self, command: str) -> frozenset[CellState]:
        return self._allowed[command]

    def check(self, command: str, name: str | None = None) -> CellState:
        """Raise :class:`InvalidStateError` unless ``command`` is allowed now.

        ``name``: the public call to name in the error when it differs from the guard
        (``move_joint`` is guarded as ``move``).
        """
        state = self.state
        allowed = self._allowed[command]
        if state not in allowed:
            order = [s for s in CellState if s in allowed]
            raise InvalidStateError(
                name or command,
                state.value,
                [s.value for s in order],
                next_step=self._next_steps.get(state, ""),
            )
        return state

    # -- input

    def sync(self, target: CellState, cause: Cause = "observed", detail: str = "") -> None:
        """Queue a move to ``target`` (no-op if already there when processed)."""
        self._queue.put_nowait(_Request(target, "", cause, detail, self._future()))

    def fire(
        self, trigger: str, cause: Cause = "command", detail: str = ""
    ) -> asyncio.Future[bool]:
        """Queue a named trigger; the future tells whether it was valid in the state then."""
        request = _Request(None, trigger, cause, detail, self._future())
        self._queue.put_nowait(request)
        return request.done

    @staticmethod
    def _future() -> asyncio.Future[bool]:
        return asyncio.get_running_loop().create_future()

    async def wait_changed(self) -> None:
        """Return at the next state change."""
        self._changed.clear()
        await self._changed.wait()

    async def run(self) -> None:
        """Consume the input queue forever (the owner cancels this task)."""
        while True:
            request = await self._queue.get()
            try:
                ok = await self._apply(request)
            except Exception as exc:  # a broken callback must not kill the machine
                log.exception("state machine request %r failed", request)
                if not request.done.done():
                    request.done.set_exception(exc)
                continue
            if not request.done.done():
                request.done.set_result(ok)

    def drain(self) -> None:
        """Apply every queued request now, synchronously where possible (used on close)."""
        while not self._queue.empty():
            request = self._queue.get_nowait()
            if not request.done.done():
                request.done.cancel()

    async def _apply(self, request: _Request) -> bool:
        if request.target is None:
            source = self.state
            trigger = request.trigger
            if trigger not in self._machine.get_triggers(self._model.state):
                return False
            await self._model.trigger(trigger)  # type: ignore[attr-defined]
            if self.state != source:
                self._emit(source, self.state, trigger, request.cause, request.detail)
            return True
        dest = machine_name(request.target)
        for _ in range(3):  # follow declared transitions, at most three steps
            if self._model.state == dest:
                return True
            step = self._path_step(self._model.state, dest)
            if step is None:
                break
            source = self.state
            await self._model.trigger(step)  # type: ignore[attr-defined]
            self._emit(source, self.state, step, request.cause, request.detail)
        if self._model.state != dest:  # no declared path: force
            source = self.state
            self._machine.set_state(dest, self._model)
            self._emit(source, self.state, "resync", request.cause, request.detail)
        return True

    def _path_step(self, current: str, dest: str) -> str | None:
        """A declared trigger leading from ``current`` to ``dest`` (or to its parent)."""
        partial = None
        for trigger, sources, target in self._edges:
            if not any(current == s or current.startswith(s + SEPARATOR) for s in sources):
                continue
            if target == dest:
                return trigger
            if partial is None and dest.startswith(target + SEPARATOR):
                partial = trigger
        return partial

    def _emit(
        self, source: CellState, dest: CellState, trigger: str, cause: Cause, detail: str
    ) -> None:
        self._changed.set()
        if self._on_transition is not None:
            event = TransitionEvent(now(), source.value, dest.value, trigger, cause, detail)
            self._on_transition(event)


# ----------------------------------------------------------------- CLI


DOC = STATECHART_DIR.parent / "docs" / "ARCHITECTURE.md"
DOC_BEGIN = "<!-- statechart:begin (generated by `fxcell statechart`) -->"
DOC_END = "<!-- statechart:end -->"


def with_diagram(doc: str, diagram: str) -> str:
    """``doc`` with the text between the statechart markers replaced by ``diagram``."""
    head, sep, rest = doc.partition(DOC_BEGIN)
    _, sep2, tail = rest.partition(DOC_END)
    if not sep or not sep2:
        return doc
    return f"{head}{DOC_BEGIN}\n```mermaid\n{diagram}```\n{DOC_END}{tail}"


def _chart_text(path: Path) -> str:
    chart = load_statechart(path) if path == STATECHART else read_statechart(path)
    return to_mermaid(chart)


def _command(args: argparse.Namespace) -> int:
    if args.chart or args.output:
        paths = [Path(args.chart) if args.chart else STATECHART]
    else:  # every chart shipped: the robot's first, then the others (the job's)
        paths = [STATECHART, *sorted(p for p in STATECHART_DIR.glob("*.yaml") if p != STATECHART)]
    if args.output == "-":
        for path in paths:
            print(_chart_text(path), end="")
        return 0
    targets: list[tuple[Path, str]] = []
    for path in paths:
        text = _chart_text(path)
        out = Path(args.output) if args.output else diagram_path(path)
        targets.append((out, text))
        if path == STATECHART and args.chart is None and args.output is None and DOC.exists():
            targets.append((DOC, with_diagram(DOC.read_text(), text)))
    stale = [path for path, want in targets if (path.read_text() if path.exists() else "") != want]
    if args.check:
        for path in stale:
            print(f"{path} is stale: run `fxcell statechart`")
        if not stale:
            print(", ".join(str(diagram_path(p)) for p in paths) + " is current")
        return 1 if stale else 0
    for path, want in targets:
        if path in stale:
            path.write_text(want)
            print(f"wrote {path}")
    return 0


def register(sub: Any) -> None:
    """Add ``fxcell statechart``: draw the Mermaid diagram from the YAML definition."""
    parser = sub.add_parser(
        "statechart",
        help="draw statecharts/*.mmd (and the robot's copy in docs/ARCHITECTURE.md) from the YAML",
    )
    parser.add_argument("--chart", help="one statechart YAML (default: every statecharts/*.yaml)")
    parser.add_argument(
        "-o", "--output", help="output file with --chart, '-' for stdout (default: beside it)"
    )
    parser.add_argument("--check", action="store_true", help="exit 1 if the diagram is stale")
    parser.set_defaults(func=_command)
