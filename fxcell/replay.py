"""``fxcell replay FILE``: see what happened in the cell from its MCAP log.

``--summary`` (the default) prints time range, metadata, per-topic counts and rates,
commands with outcomes, transitions, errors and protective stops; ``--timeline`` lists
commands, transitions, mode changes and log records in order; ``--plot OUT.png`` draws
joints, velocities and the TCP over time with commands and state changes marked;
``--re-execute`` re-issues the recorded commands against the embedded simulator and
compares the new state trace with the recorded one; ``--serve`` streams the file to
Foxglove over its WebSocket protocol with play, pause and seek.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from fxcell.commands import COMMANDS
from fxcell.errors import InvalidArgumentError, RecorderError
from fxcell.recorder import topics
from fxcell.recorder.protobuf import decode_robot_state
from fxcell.recorder.reading import LogMessage, LogReader

PROTECTIVE_STOP = "PROTECTIVE_STOP"


# ----------------------------------------------------------------- summary


@dataclass
class CommandRecord:
    """One API call as recorded: its start and (if it ended in the file) its end."""

    command_id: int
    name: str
    args: dict[str, Any]
    origin: str
    started: float
    ended: float | None = None
    outcome: str = "started"
    logged: float = 0.0
    """When the recorder received the start (the time base of the state samples)."""
    result: Any = None
    error_type: str | None = None
    error_message: str | None = None


@dataclass
class Summary:
    path: Path
    finished: bool
    start: float | None
    end: float | None
    metadata: dict[str, dict[str, str]]
    counts: dict[str, int]
    commands: list[CommandRecord] = field(default_factory=list)
    transitions: list[dict[str, Any]] = field(default_factory=list)
    errors: list[tuple[float, str]] = field(default_factory=list)
    protective_stops: list[float] = field(default_factory=list)
    samples: dict[str, list[str]] = field(default_factory=dict)
    """Per job sample, what happened to it (from ``/job``): one line per finished step."""

    @property
    def duration(self) -> float:
        return 0.0 if self.start is None or self.end is None else self.end - self.start

    def rate(self, topic: str) -> float:
        d = self.duration
        n = self.counts.get(topic, 0)
        return (n - 1) / d if d > 0 and n > 1 else 0.0

    @property
    def robot_kind(self) -> str:
        """The robot kind the log was recorded on (its configuration's ``robot.kind``;
        logs from before there were kinds: ``ur3e``)."""
        return recorded_robot_kind(self.metadata)


def recorded_robot_kind(metadata: dict[str, dict[str, str]]) -> str:
    """``robot.kind`` of the configuration a log's metadata carries (``ur3e`` without)."""
    text = metadata.get(topics.METADATA_NAME, {}).get("config")
    try:
        kind = json.loads(text)["robot"]["kind"] if text else DEFAULT_KIND
    except (ValueError, TypeError, KeyError):
        return DEFAULT_KIND
    return str(kind)


DEFAULT_KIND = "ur3e"
"""The robot kind of logs whose configuration names none (recorded before the Ned2)."""


def commands_of(messages: Iterable[tuple[LogMessage, Any]]) -> list[CommandRecord]:
    """Pair the start and end records of each command, in start order."""
    by_id: dict[int, CommandRecord] = {}
    for msg, m in messages:
        rec = by_id.get(m["command_id"])
        if rec is None:
            rec = by_id[m["command_id"]] = CommandRecord(
                m["command_id"], m["name"], m.get("args") or {}, m["origin"], m["started"]
            )
            rec.logged = msg.time
        if m.get("phase") == "end" or m.get("outcome") != "started":
            rec.ended = m.get("ended")
            rec.outcome = m["outcome"]
            rec.error_type = m.get("error_type")
            rec.error_message = m.get("error_message")
            rec.result = m.get("result")
    return sorted(by_id.values(), key=lambda c: (c.started, c.command_id))


def _job_event(s: Summary, t: float, m: dict[str, Any]) -> None:
    """A job event into the per-sample story: where each object went, which steps failed."""
    if m.get("event") != "step" or m.get("phase") != "end":
        return
    for move in m.get("moved") or []:
        line = f"{_rel(t, s.start)}  {move['object']} {move['from']} → {move['to']}"
        s.samples.setdefault(str(move["sample"]), []).append(line)
    if m.get("outcome") not in (None, "done", "ok") and m.get("sample"):
        line = f"{_rel(t, s.start)}  step {m.get('kind')}: {m['outcome']} {m.get('detail') or ''}"
        s.samples.setdefault(str(m["sample"]), []).append(line.rstrip())


def summarize(path: str | Path) -> Summary:
    """Read what ``--summary`` shows (fast: only the low-rate topics are decoded)."""
    reader = LogReader(path)
    s = Summary(
        reader.path,
        reader.finished,
        None if reader.start_time is None else reader.start_time / 1e9,
        None if reader.end_time is None else reader.end_time / 1e9,
        reader.metadata,
        reader.counts,
    )
    command_msgs = []
    in_stop = False
    wanted = (
        topics.COMMANDS, topics.TRANSITIONS, topics.ROBOT_MODES, topics.LOG, topics.RECORDER,
        topics.JOB,
    )  # fmt: skip
    for msg, m in reader.decoded(wanted):
        if msg.topic == topics.JOB:
            _job_event(s, msg.time, m)
            continue
        if msg.topic == topics.COMMANDS:
            command_msgs.append((msg, m))
            if m.get("outcome") == "error":
                s.errors.append(
                    (msg.time, f"{m['name']}: {m.get('error_type')}: {m.get('error_message')}")
                )
        elif msg.topic == topics.TRANSITIONS:
            s.transitions.append({**m, "logged": msg.time})
        elif msg.topic == topics.ROBOT_MODES:
            stopped = m.get("safety_mode") == PROTECTIVE_STOP
            if stopped and not in_stop:
                s.protective_stops.append(msg.time)
            in_stop = stopped
        elif msg.topic == topics.LOG and m.get("level", 0) >= 4:
            s.errors.append((msg.time, f"log {m.get('name')}: {m.get('message')}"))
        elif msg.topic == topics.RECORDER and m.get("level") == "error":
            s.errors.append((msg.time, f"recorder: {m.get('message')}"))
    s.commands = commands_of(command_msgs)
    return s


def _utc(t: float | None) -> str:
    if t is None:
        return "-"
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def _rel(t: float | None, t0: float | None) -> str:
    if t is None or t0 is None:
        return "        -"
    return f"{t - t0:+9.3f}s"


def _args(args: dict[str, Any], limit: int = 70) -> str:
    text = ", ".join(f"{k}={v}" for k, v in args.items())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def format_summary(s: Summary) -> str:
    lines = [f"file: {s.path}" + ("" if s.finished else "  (unfinished: read to its last chunk)")]
    lines.append(f"time: {_utc(s.start)} → {_utc(s.end)} ({s.duration:.3f} s)")
    meta = s.metadata.get(topics.METADATA_NAME, {})
    lines.append(f"robot kind: {s.robot_kind}")
    for key in ("fxcell_version", "controller_version", "serial", "robot"):
        if key in meta:
            lines.append(f"{key}: {meta[key]}")
    if topics.RECOVERY_METADATA_NAME in s.metadata:
        rec = s.metadata[topics.RECOVERY_METADATA_NAME]
        lines.append(
            f"recovered after a crash: kept {rec.get('kept_bytes')} of "
            f"{rec.get('source_bytes')} bytes"
        )
    lines.append("topics:")
    for topic in sorted(s.counts):
        lines.append(f"  {topic:<22} {s.counts[topic]:>9} msgs  {s.rate(topic):9.2f} Hz")
    ok = sum(c.outcome == "ok" for c in s.commands)
    err = sum(c.outcome == "error" for c in s.commands)
    lines.append(f"commands: {len(s.commands)} ({ok} ok, {err} failed)")
    for c in s.commands:
        took = f" in {c.ended - c.started:.3f} s" if c.ended is not None else ""
        outcome = c.outcome if c.outcome != "error" else f"error {c.error_type}"
        lines.append(f"  {_rel(c.started, s.start)}  {c.name}({_args(c.args)}) → {outcome}{took}")
    lines.append(f"transitions: {len(s.transitions)}")
    for t in s.transitions:
        lines.append(
            f"  {_rel(t['time'], s.start)}  {t['source']} → {t['dest']} "
            f"({t['trigger']}, {t['cause']})"
        )
    lines.append(f"protective stops: {len(s.protective_stops)}")
    for t0 in s.protective_stops:
        lines.append(f"  {_rel(t0, s.start)}")
    lines.append(f"errors: {len(s.errors)}")
    for t0, text in s.errors:
        lines.append(f"  {_rel(t0, s.start)}  {text}")
    if s.samples:
        lines.append(f"job samples: {len(s.samples)}")
        for sample, story in sorted(s.samples.items()):
            lines.append(f"  {sample}")
            lines.extend(f"    {line}" for line in story)
    return "\n".join(lines)


# ----------------------------------------------------------------- timeline


def timeline(
    path: str | Path,
    *,
    topic_names: Sequence[str] | None = None,
    start: float | None = None,
    end: float | None = None,
) -> list[str]:
    """Readable lines of the low-rate topics; ``start``/``end`` in seconds from the file start."""
    reader = LogReader(path)
    wanted = list(topic_names) if topic_names else list(topics.EVENT_TOPICS)
    unknown = [t for t in wanted if t not in topics.ALL_TOPICS]
    if unknown:
        raise InvalidArgumentError(f"unknown topic(s) {unknown}; topics: {topics.ALL_TOPICS}")
    t0 = reader.start_time or 0
    lo = None if start is None else t0 + int(start * 1e9)
    hi = None if end is None else t0 + int(end * 1e9)
    lines = []
    for msg, m in reader.decoded(wanted, start=lo, end=hi):
        lines.append(f"{_rel(msg.time, t0 / 1e9)}  {msg.topic:<20} {_describe(msg.topic, m)}")
    return lines


def _describe(topic: str, m: Any) -> str:
    if topic == topics.COMMANDS:
        if m.get("phase") == "start":
            return f"▶ #{m['command_id']} {m['name']}({_args(m.get('args') or {})}) [{m['origin']}]"
        took = ""
        if m.get("ended") is not None:
            took = f" after {m['ended'] - m['started']:.3f} s"
        if m["outcome"] == "error":
            return (
                f"✗ #{m['command_id']} {m['name']}: {m['error_type']}: {m['error_message']}{took}"
            )
        return f"✓ #{m['command_id']} {m['name']}{took}"
    if topic == topics.TRANSITIONS:
        detail = f" — {m['detail']}" if m.get("detail") else ""
        return f"{m['source']} → {m['dest']} ({m['trigger']}, {m['cause']}){detail}"
    if topic == topics.ROBOT_MODES:
        return f"robot {m['robot_mode']}, safety {m['safety_mode']}, program {m['runtime_state']}"
    if topic == topics.LOG:
        level = ("?", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL")[int(m.get("level", 0)) % 6]
        return f"{level} {m.get('name')}: {m.get('message')}"
    if topic == topics.RECORDER:
        return f"{m.get('level')}: {m.get('message')}"
    if topic == topics.MOTION:
        return f"move #{m['move_id']} {m['kind']}"
    if topic == topics.ROBOT_STATE:
        return f"q={[round(v, 4) for v in m.actual_q]} mode={m.robot_mode.name}"
    text = str(m)
    return text if len(text) < 100 else text[:99] + "…"


# ----------------------------------------------------------------- plot


def plot(path: str | Path, out: str | Path, *, max_points: int = 20_000) -> Path:
    """Joint positions, velocities and TCP position over time, commands and transitions marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    reader = LogReader(path)
    n = reader.counts.get(topics.ROBOT_STATE, 0)
    if n == 0:
        raise RecorderError(f"{path} has no {topics.ROBOT_STATE} samples to plot")
    stride = max(1, math.ceil(n / max_points))
    t0 = (reader.start_time or 0) / 1e9
    times, q, qd, tcp = [], [], [], []
    for i, msg in enumerate(reader.messages([topics.ROBOT_STATE])):
        if i % stride:
            continue  # decode only the samples that are drawn
        s = decode_robot_state(msg.data)
        times.append(msg.time - t0)
        q.append(s.actual_q)
        qd.append(s.actual_qd)
        tcp.append(s.actual_tcp_pose[:3])
    summary = summarize(path)
    fig, (events, *axes) = plt.subplots(
        4, 1, figsize=(13, 9.5), sharex=True, gridspec_kw={"height_ratios": [1.1, 2, 2, 2]}
    )
    t = np.asarray(times)
    for ax, data, label in (
        (axes[0], q, "joint position (rad)"),
        (axes[1], qd, "joint velocity (rad/s)"),
    ):
        arr = np.asarray(data)
        for j in range(arr.shape[1]):
            ax.plot(t, arr[:, j], lw=0.8, label=f"q{j + 1}")
        ax.set_ylabel(label)
        ax.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7, frameon=False)
    arr = np.asarray(tcp)
    for j, name in enumerate("xyz"):
        axes[2].plot(t, arr[:, j], lw=0.8, label=name)
    axes[2].set_ylabel("TCP position (m)")
    axes[2].set_xlabel(f"time (s) from {_utc(t0)}")
    axes[2].legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7, frameon=False)

    # Commands and transitions get lanes of their own above the plots; labels closer than
    # a minimum spacing are merged ("init +3") so that they never overlap.
    span = max(float(t[-1]) if len(t) else 0.0, 1e-9)
    min_gap = span / 45
    lanes: list[tuple[float, str, list[tuple[float, str]]]] = [
        (
            1.0,
            "tab:green",
            [
                (c.logged - t0, c.name + (" ✗" if c.outcome == "error" else ""))
                for c in summary.commands
            ],
        ),
        (0.0, "tab:purple", [(tr["logged"] - t0, str(tr["dest"])) for tr in summary.transitions]),
    ]
    for y, colour, marks in lanes:
        for x, _ in marks:
            for ax in axes:
                ax.axvline(x, color=colour, lw=0.5, ls="--" if y else ":", alpha=0.6)
        up = y > 0  # command labels rise above their lane, transition labels hang below
        for x, text in _declutter(sorted(marks), min_gap):
            events.annotate(
                text, (x, y), xytext=(0, 3 if up else -3), textcoords="offset points",
                rotation=30 if up else -30, rotation_mode="anchor", fontsize=6.5,
                color=colour, ha="left", va="bottom" if up else "top",
            )  # fmt: skip
        events.plot([x for x, _ in marks], [y] * len(marks), "|", color=colour, ms=8)
    for c in summary.commands:
        if c.outcome == "error":
            events.plot([c.logged - t0], [1.0], "x", color="tab:red", ms=6)
    for ps in summary.protective_stops:
        for ax in (events, *axes):
            ax.axvline(ps - t0, color="black", lw=1.2)
    events.set_ylim(-2.2, 3.2)
    events.set_yticks([0.0, 1.0], ["transitions", "commands"], fontsize=7)
    events.tick_params(axis="y", length=0)
    for side in ("top", "right"):
        events.spines[side].set_visible(False)
    fig.suptitle(f"{Path(path).name}: commands, transitions, protective stops (black)")
    fig.tight_layout()
    fig.subplots_adjust(right=0.92)
    out = Path(out)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def _declutter(marks: list[tuple[float, str]], min_gap: float) -> list[tuple[float, str]]:
    """Labels for time-sorted marks: marks within ``min_gap`` of a group's first merge into it."""
    groups: list[tuple[float, str, int]] = []
    for x, text in marks:
        if groups and x - groups[-1][0] < min_gap:
            first_x, first_text, n = groups[-1]
            groups[-1] = (first_x, first_text, n + 1)
        else:
            groups.append((x, text, 0))
    return [(x, f"{text} +{n}" if n else text) for x, text, n in groups]


# ----------------------------------------------------------------- CLI


def register(sub: Any) -> None:
    p = sub.add_parser(
        "replay",
        help="summarise, list, plot, re-execute or serve an MCAP log",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", type=Path, help="an fxcell .mcap log")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--summary", action="store_true", help="overview (the default)")
    what.add_argument("--timeline", action="store_true", help="chronological listing")
    what.add_argument("--plot", metavar="OUT.png", type=Path, help="plot joints and TCP")
    what.add_argument(
        "--re-execute", action="store_true", help="re-issue the commands against the simulator"
    )
    what.add_argument("--serve", action="store_true", help="stream to Foxglove (WebSocket)")
    p.add_argument("--topic", action="append", help="timeline: only this topic (repeatable)")
    p.add_argument("--start", type=float, help="timeline: from this many seconds into the file")
    p.add_argument("--end", type=float, help="timeline: up to this many seconds into the file")
    p.add_argument("--host", default="127.0.0.1", help="serve: address to bind")
    p.add_argument("--port", type=int, default=8765, help="serve: WebSocket port")
    p.add_argument("--speed", type=float, default=1.0, help="serve: initial playback speed")
    p.add_argument(
        "--tolerance", type=float, default=None, help="re-execute: joint deviation (rad) allowed"
    )
    p.add_argument("--config", type=Path, help="re-execute: cell configuration under test")
    p.add_argument(
        "--time-scale", type=float, default=1.0, help="re-execute: simulator controller delays"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.timeline:
        for line in timeline(args.file, topic_names=args.topic, start=args.start, end=args.end):
            print(line)
        return 0
    if args.plot is not None:
        out = plot(args.file, args.plot)
        print(f"wrote {out}")
        return 0
    if args.re_execute:
        return reexecute_cli(
            args.file, tolerance=args.tolerance, config=args.config, time_scale=args.time_scale
        )
    if args.serve:
        from fxcell.recorder.serve import serve

        serve(args.file, host=args.host, port=args.port, speed=args.speed)
        return 0
    print(format_summary(summarize(args.file)))
    return 0


# ----------------------------------------------------------------- re-execute

MOVE_COMMANDS = frozenset(c.name for c in COMMANDS.values() if c.kind == "move")
JOINT_TOLERANCE = 0.01
"""rad: largest joint deviation of a re-executed move's path that counts as equal."""
RESULT_TOLERANCE = 1e-3
"""Largest difference of numeric command results (m, rad) that counts as equal."""


@dataclass
class Trace:
    """Joint positions of a session: host receive time (s, wall clock), controller time, q."""

    times: list[float] = field(default_factory=list)
    controller: list[float] = field(default_factory=list)
    q: list[tuple[float, ...]] = field(default_factory=list)

    def add(self, when: float, sample: Any) -> None:
        self.times.append(when)
        self.controller.append(sample.timestamp)
        self.q.append(tuple(sample.actual_q))

    def window(self, start: float, end: float) -> tuple[Any, Any]:
        """Samples received in [start, end], on the controller's clock (exact 2 ms steps,
        free of the host's delivery jitter)."""
        import numpy as np

        t = np.asarray(self.times)
        i, j = np.searchsorted(t, start), np.searchsorted(t, end, side="right")
        return np.asarray(self.controller[i:j]), np.asarray(self.q[i:j]).reshape(-1, 6)

    def at(self, when: float) -> tuple[float, ...] | None:
        import bisect

        i = bisect.bisect_right(self.times, when) - 1
        return self.q[i] if i >= 0 else None


@dataclass
class Comparison:
    """One recorded command and its re-execution."""

    name: str
    args: dict[str, Any]
    recorded_outcome: str
    outcome: str
    recorded_duration: float | None
    duration: float | None
    joint_deviation: float | None = None
    """rad: largest joint difference of the two paths (moves) or of the joints at the start."""
    result_deviation: float | None = None
    problems: list[str] = field(default_factory=list)


@dataclass
class ReexecuteReport:
    path: Path
    comparisons: list[Comparison]

    @property
    def unexpected(self) -> list[str]:
        return [f"{c.name}: {p}" for c in self.comparisons for p in c.problems]

    def format(self) -> str:
        lines = [f"re-executed {len(self.comparisons)} commands of {self.path}"]
        for c in self.comparisons:
            dev = "" if c.joint_deviation is None else f"  Δq {c.joint_deviation:.2e} rad"
            res = "" if c.result_deviation is None else f"  Δresult {c.result_deviation:.2e}"
            took = "" if c.duration is None else f" {c.duration:.3f} s"
            was = "" if c.recorded_duration is None else f" (recorded {c.recorded_duration:.3f} s)"
            flag = "  ✗ " + "; ".join(c.problems) if c.problems else "  ✓"
            lines.append(
                f"  {c.name}({_args(c.args, 40)}) → {c.outcome}{took}{was}{dev}{res}{flag}"
            )
        n = len(self.unexpected)
        lines.append(f"unexpected deviations: {n}" + ("" if n else " (matches the recording)"))
        return "\n".join(lines)


def top_level_commands(commands: Sequence[CommandRecord]) -> list[CommandRecord]:
    """The commands a user issued: drop those another (non-move) command issued itself.

    ``init()`` calls ``power_on()``, ``brake_release()``, ... which are recorded too;
    re-issuing both would do things twice. Calls during a move (``stop()``) are kept.
    """
    out = []
    for c in commands:
        inner = any(
            o.command_id < c.command_id
            and o.name not in MOVE_COMMANDS
            and o.ended is not None
            and c.ended is not None
            and o.started <= c.started
            and c.ended <= o.ended
            for o in commands
        )
        if not inner and c.origin != "internal":
            out.append(c)
    return out


def _numeric_deviation(a: Any, b: Any) -> float | None:
    """Largest absolute difference of two JSON values of the same shape (None: not numeric)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return None if a == b else math.inf
    if isinstance(a, int | float) and isinstance(b, int | float):
        return abs(float(a) - float(b))
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return math.inf
        devs = [_numeric_deviation(x, y) for x, y in zip(a, b, strict=True)]
        nums = [d for d in devs if d is not None]
        return max(nums) if nums else None
    return None if a == b else math.inf


PATH_STEP = 1e-3
"""rad: the spacing to which a compared joint path is filled in between its samples."""


def _path_deviation(rec: Any, new: Any, block: int = 64) -> float | None:
    """Largest joint distance (max over joints) between two joint paths, either way round.

    A symmetric Hausdorff distance between the paths: where the robot went, free of
    when it got there (streaming jitter on a busy host shifts the timing, not the path).
    Each sample is measured to the other path's line between its samples (filled in every
    :data:`PATH_STEP`), not to its samples alone: a controller running late streams one
    sample for several cycles, and such a gap in the stream is not a step in the path.
    """
    import numpy as np

    a, b = np.asarray(rec, dtype=float), np.asarray(new, dtype=float)
    if len(a) == 0 or len(b) == 0:
        return None

    def filled(y: Any) -> Any:
        if len(y) < 2:
            return y
        steps = np.maximum(np.ceil(np.max(np.abs(np.diff(y, axis=0)), axis=1) / PATH_STEP), 1)
        starts = np.repeat(y[:-1], steps.astype(int), axis=0)
        deltas = np.repeat(np.diff(y, axis=0) / steps[:, None], steps.astype(int), axis=0)
        within = np.concatenate([np.arange(n) for n in steps.astype(int)])
        return np.vstack([starts + deltas * within[:, None], y[-1:]])

    def directed(x: Any, y: Any) -> float:
        worst = 0.0
        for i in range(0, len(x), block):
            d = np.max(np.abs(x[i : i + block, None, :] - y[None, :, :]), axis=2)
            worst = max(worst, float(np.max(np.min(d, axis=1))))
        return worst

    return max(directed(a, filled(b)), directed(b, filled(a)))


async def reexecute(
    path: str | Path,
    *,
    config: Any = None,
    time_scale: float = 1.0,
    joint_tolerance: float = JOINT_TOLERANCE,
    result_tolerance: float = RESULT_TOLERANCE,
) -> ReexecuteReport:
    """Re-issue the recorded commands against a fresh embedded simulator, on the recorded timing.

    The simulator starts at the recorded first joint positions; each command goes out
    at its recorded offset from the first one (never before the command it followed
    has finished). Outcomes, numeric results and, for moves, the joint paths (where the
    robot went, not when: a busy host shifts the timing) are compared with the recording.
    ``config`` (a CellConfig, default the standard configuration) is the setup under
    test: a different TCP shows up as a deviation of pose results and pose moves; its
    robot kind must be the one the log was recorded on (InvalidArgumentError).
    """
    import asyncio
    import time

    from fxcell.cell import Cell
    from fxcell.config import CellConfig
    from fxcell.events import Event, Origin, StateEvent

    summary = summarize(path)
    config = config if config is not None else CellConfig()
    if summary.robot_kind != config.robot.kind:
        raise InvalidArgumentError(
            f"{path} was recorded on a {summary.robot_kind} cell: re-execute it with the "
            f"configuration of a {summary.robot_kind} cell, not a {config.robot.kind} one"
        )
    reader = LogReader(path)
    recorded = Trace()
    for msg, sample in reader.decoded([topics.ROBOT_STATE]):
        recorded.add(msg.time, sample)
    commands = top_level_commands(summary.commands)
    if not commands:
        raise RecorderError(f"{path} has no commands to re-execute")
    first_q = recorded.q[0] if recorded.q else None

    new = Trace()

    def on_event(event: Event) -> None:
        if isinstance(event, StateEvent):
            new.add(time.time(), event.sample)

    options: dict[str, Any] = {"time_scale": time_scale}
    if first_q is not None and len(first_q) == 6:
        options["joints"] = list(first_q)
    cell = Cell(None, config=config, origin=Origin.REPLAY, simulator_options=options)
    cell.bus.subscribe(on_event)
    results: dict[int, tuple[str, Any, float, float]] = {}

    async def issue(c: CommandRecord) -> None:
        t0 = time.time()
        try:
            # Only the command's own parameters: the record may carry context (the
            # external control mode of start_external_control, ...).
            value = await cell.run_command(c.name, **COMMANDS[c.name].known_args(c.args))
            outcome: tuple[str, Any] = ("ok", value)
        except Exception as exc:
            outcome = (f"error {type(exc).__name__}", None)
        results[c.command_id] = (outcome[0], outcome[1], t0, time.time())

    async with cell:
        from fxcell.cell.statemachine import CellState

        await cell.wait_for_state(*[s for s in CellState if s is not CellState.DISCONNECTED])
        start_new = time.time()
        start_rec = commands[0].started
        running: list[asyncio.Task[None]] = []
        previous: CommandRecord | None = None
        for c in commands:
            if c.name not in COMMANDS:
                results[c.command_id] = ("error unknown command", None, time.time(), time.time())
                continue
            sequential = (
                previous is not None
                and previous.ended is not None
                and (c.started >= previous.ended)
            )
            if sequential and running:
                await asyncio.gather(*running)
                running.clear()
            delay = start_new + (c.started - start_rec) - time.time()
            if delay > 0:
                await asyncio.sleep(delay)
            running.append(asyncio.create_task(issue(c)))
            previous = c
        await asyncio.gather(*running)

    comparisons = []
    for c in commands:
        outcome, value, t0, t1 = results[c.command_id]
        rec_outcome = "ok" if c.outcome == "ok" else f"error {c.error_type}"
        comp = Comparison(
            c.name,
            c.args,
            rec_outcome,
            outcome,
            None if c.ended is None else c.ended - c.started,
            t1 - t0,
        )
        if outcome != rec_outcome:
            comp.problems.append(f"outcome {outcome}, recorded {rec_outcome}")
        if c.name in MOVE_COMMANDS and c.ended is not None:
            comp.joint_deviation = _path_deviation(
                recorded.window(c.logged, c.logged + (c.ended - c.started))[1],
                new.window(t0, t1)[1],
            )
        else:
            a, b = recorded.at(c.logged), new.at(t0)
            if a is not None and b is not None:
                comp.joint_deviation = max(abs(x - y) for x, y in zip(a, b, strict=False))
        if comp.joint_deviation is not None and comp.joint_deviation > joint_tolerance:
            comp.problems.append(f"joints differ by {comp.joint_deviation:.4f} rad")
        if c.name not in MOVE_COMMANDS and outcome == "ok" and c.outcome == "ok":
            comp.result_deviation = _numeric_deviation(c.result, _jsonable_result(value))
            if comp.result_deviation is not None and comp.result_deviation > result_tolerance:
                comp.problems.append(f"result differs by {comp.result_deviation:.4g}")
        comparisons.append(comp)
    return ReexecuteReport(Path(path), comparisons)


def _jsonable_result(value: Any) -> Any:
    from fxcell.jsonable import to_jsonable

    return json.loads(json.dumps(to_jsonable(value)))


def reexecute_cli(
    path: Path, *, tolerance: float | None, config: Path | None = None, time_scale: float = 1.0
) -> int:
    import asyncio

    from fxcell.config import CellConfig

    cfg = CellConfig.load(config)
    report = asyncio.run(
        reexecute(
            path,
            config=cfg,
            time_scale=time_scale,
            joint_tolerance=tolerance if tolerance is not None else JOINT_TOLERANCE,
        )
    )
    print(report.format())
    return 1 if report.unexpected else 0
