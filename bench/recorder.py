"""The flight recorder's cost: CPU per message, share of one core at 500 Hz, drops, replay speed.

Three parts, one process:

1. micro: CPU per message, in rounds of 2000 messages of a realistic session (states
   at 500 Hz with commands, transitions, motion and log records; log times on a simulated
   clock at the session's pace, so chunks hold 1 s of data as in real use), for
   - fxcell: ``Recorder.submit`` on the caller plus the writer thread's CPU (encoding,
     /tf frames, chunking, zstd, file writes), measured with the thread's CPU clock;
   - peer ``mcap raw``: the bare ``mcap`` Writer given the state samples already encoded,
     flushed every 500 (1 s chunks): the library's own floor;
   - peer ``mcap + json``: the same Writer with the states encoded as JSON, the common
     approach (performance anchors: about 20 µs per message).
2. session: a real-time session at 500 Hz for ``--duration`` seconds (default 60; the
   10-minute figure with ``--long``): writer-thread and submit CPU as a share of one
   core, drops, submit latency p99. Submit CPU is timed per call with the thread's CPU
   clock; the same timing around an empty call beside each one (before and after it in
   turn) measures what the clock reads cost (more than a submit), and that is subtracted.
3. replay: ``fxcell replay --summary`` of a ``--hours`` long file (default 1 h, about
   1.8 million state samples), written by the recorder with a simulated clock; then every
   state sample of it read back and decoded (``LogReader`` + ``decode_robot_state``).

Peers: the bare mcap writer (raw and with JSON) for the CPU per message; the
performance anchors' 110k–160k decoded messages/s for the read-back.

Targets: micro and session <= 2 % of one core at 500 Hz, zero drops, summary of a
one-hour file < 5 s, state samples decoded >= 100k/s.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from _harness import Targets
from mcap.writer import Writer

from fxcell.events import Event, StateEvent
from fxcell.recorder import Recorder, topics
from fxcell.recorder.protobuf import decode_robot_state, encode_robot_state
from fxcell.recorder.reading import LogReader
from fxcell.recorder.synthetic import Planned, SyntheticSession, play
from fxcell.replay import format_summary, summarize

ROUND = 2000
TCP = (-0.00025, 0.00245, 0.14789, 0.0, 0.0, -1.5708)


def thread_cpu(thread: threading.Thread) -> float:
    assert thread.ident is not None
    return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def fmt(values: list[float]) -> str:
    return f"median {statistics.median(values):6.2f} µs  p99 {pct(values, 0.99):6.2f} µs"


# ----------------------------------------------------------------- 1. micro


def planned_for(seconds: float) -> list[Planned]:
    session = SyntheticSession(seconds, move_every=1.0, protective_stop_at=seconds / 2, tcp=TCP)
    return list(session.events())


def micro(rounds: int, directory: Path) -> dict[str, list[float]]:
    planned = planned_for(ROUND / 500 + 0.1)[:ROUND]
    events = [p.event for p in planned]
    results: dict[str, list[float]] = {"fxcell": [], "mcap raw": [], "mcap + json": []}

    # log times advance as in the real session (2 ms per sample), so chunks hold 1 s of data
    now = [time.time_ns()]
    rec = Recorder(directory / "micro", tcp=TCP, fsync=False, clock=lambda: now[0])
    writer_thread = rec._thread
    base = now[0]
    for r in range(rounds):
        offset = base + int(r * (ROUND / 500 + 0.1) * 1e9)
        c0, s0 = thread_cpu(writer_thread), time.thread_time()
        for p in planned:
            now[0] = offset + int(p.at * 1e9)
            rec.submit(p.event)
        s1 = time.thread_time()
        while rec._queue:  # wait until the writer thread has taken the whole round
            time.sleep(0.002)
        time.sleep(0.002)
        c1 = thread_cpu(writer_thread)
        results["fxcell"].append(((c1 - c0) + (s1 - s0)) / len(events) * 1e6)
    rec.close()

    states = [e.sample for e in events if isinstance(e, StateEvent)]
    encoded = [encode_robot_state(s) for s in states]
    as_json = [asdict(s) for s in states]
    for label, encode in (
        ("mcap raw", lambda i: encoded[i]),
        ("mcap + json", lambda i: json.dumps(as_json[i]).encode()),
    ):
        path = directory / f"{label.replace(' ', '_').replace('+', 'plus')}.mcap"
        with open(path, "wb") as f:
            w = Writer(f)
            w.start()
            sid = w.register_schema("s", "jsonschema", b"{}")
            cid = w.register_channel("/robot/state", "json", sid)
            t = time.time_ns()
            for _ in range(rounds):
                c0 = time.thread_time()
                for i in range(len(states)):
                    t += 2_000_000
                    w.add_message(cid, t, encode(i), t)
                    if i % 500 == 499:  # 1 s chunks, as the recorder writes them
                        w.flush()
                w.flush()
                results[label].append((time.thread_time() - c0) / len(states) * 1e6)
            w.finish()
    return results


# ----------------------------------------------------------------- 2. session


def _nothing(event: Event) -> None:
    """The empty call timed beside each submit (its timing cost is subtracted)."""


def session(duration: float, directory: Path) -> dict[str, float]:
    rec = Recorder(directory / "session", tcp=TCP)
    submit_times: list[float] = []  # wall time of each call (preemption included)
    # CPU time of the calls on the calling thread. Reading a thread's CPU clock is a system
    # call (1.5-5 µs here, more than a submit): the same timing around an empty call, made
    # beside each submit (before and after it in turn, so neither is always the colder),
    # measures that cost, and it is subtracted.
    cpu = {"submit": 0.0, "empty": 0.0}
    turn = [0]

    def timed(label: str, call: Callable[[Event], None], event: Event) -> None:
        c0 = time.thread_time()
        t0 = time.perf_counter()
        call(event)
        t1 = time.perf_counter()
        cpu[label] += time.thread_time() - c0
        if label == "submit":
            submit_times.append(t1 - t0)

    def timed_submit(event: Event) -> None:
        turn[0] ^= 1
        if turn[0]:
            timed("submit", rec.submit, event)
            timed("empty", _nothing, event)
        else:
            timed("empty", _nothing, event)
            timed("submit", rec.submit, event)

    c0 = thread_cpu(rec._thread)
    wall0 = time.monotonic()
    n = play(SyntheticSession(duration, tcp=TCP), timed_submit, realtime=True)
    wall = time.monotonic() - wall0
    c1 = thread_cpu(rec._thread)
    rec.close()
    stats = rec.stats
    writer_cpu = c1 - c0
    submit = max(0.0, cpu["submit"] - cpu["empty"])
    return {
        "events": n,
        "wall_s": wall,
        "writer_cpu_s": writer_cpu,
        "submit_cpu_s": submit,
        "timer_cpu_s": cpu["empty"],
        "core_share_pct": (writer_cpu + submit) / wall * 100,
        "writer_share_pct": writer_cpu / wall * 100,
        "cpu_per_event_us": (writer_cpu + submit) / n * 1e6,
        "submit_p50_us": pct(submit_times, 0.5) * 1e6,
        "submit_p99_us": pct(submit_times, 0.99) * 1e6,
        "submit_max_us": max(submit_times) * 1e6,
        "dropped": stats.messages_dropped,
        "written": stats.messages_written,
        "bytes": stats.bytes_written,
        "queue_high_water": stats.queue_high_water,
    }


# ----------------------------------------------------------------- 3. replay


def hour_file(hours: float, directory: Path) -> Path:
    now = [time.time_ns()]

    def clock() -> int:
        return now[0]

    rec = Recorder(directory / "hour", tcp=TCP, clock=clock, fsync=False, max_queue=10**6)
    session = SyntheticSession(
        hours * 3600, move_every=5.0, protective_stop_at=hours * 1800 + 0.2, tcp=TCP
    )
    start = now[0]
    for i, p in enumerate(session.events()):
        now[0] = start + int(p.at * 1e9)
        rec.submit(p.event)
        if i % 20000 == 0:  # keep the queue short: chunks close on log time
            while rec.stats.messages_pending > 5000:
                time.sleep(0.001)
    rec.close()
    (path,) = rec.stats.files
    return path


def timed(fn: Callable[[], object]) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0, help="real-time session, s")
    parser.add_argument("--long", action="store_true", help="a 10-minute session")
    parser.add_argument("--hours", type=float, default=1.0, help="length of the replay file")
    parser.add_argument("--rounds", type=int, default=30, help="micro-benchmark rounds")
    parser.add_argument("--skip", action="append", default=[], help="micro, session or replay")
    args = parser.parse_args()
    if args.long:
        args.duration = max(args.duration, 600.0)
    targets = Targets("recorder")
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        if "micro" not in args.skip:
            print(f"== CPU per message, {args.rounds} rounds of {ROUND} messages")
            res = micro(args.rounds, directory)
            for label, values in res.items():
                print(f"  {label:<12} {fmt(values)}")
            fx = statistics.median(res["fxcell"])
            raw = statistics.median(res["mcap raw"])
            js = statistics.median(res["mcap + json"])
            print(f"  ratio fxcell / mcap raw    {fx / raw:5.2f}")
            print(f"  ratio fxcell / mcap + json {fx / js:5.2f}")
            print(f"  at 500 Hz: fxcell {fx * 500 / 1e4:.2f} % of one core (target <= 2 %)")
            targets.check(
                "micro: CPU at 500 Hz", fx * 500 / 1e4, "<=", 2.0, "% core",
                peer=js * 500 / 1e4, peer_name="mcap + json",
            )  # fmt: skip
        if "session" not in args.skip:
            print(f"== real-time session at 500 Hz for {args.duration:.0f} s")
            s = session(args.duration, directory)
            for k, v in s.items():
                print(f"  {k:<18} {v:,.3f}" if isinstance(v, float) else f"  {k:<18} {v:,}")
            targets.check(
                f"session {args.duration:.0f} s: CPU at 500 Hz", s["core_share_pct"], "<=", 2.0,
                "% core",
            )  # fmt: skip
            targets.check(f"session {args.duration:.0f} s: drops", s["dropped"], "==", 0)
        if "replay" not in args.skip:
            print(f"== replay summary of a {args.hours:g} h file")
            gen, path = timed(lambda: hour_file(args.hours, directory))
            assert isinstance(path, Path)
            size = path.stat().st_size
            print(f"  wrote {path.name}: {size / 1e6:.1f} MB in {gen:.1f} s")
            times = []
            for _ in range(3):
                t, summary = timed(lambda: summarize(path))
                times.append(t)
            text = format_summary(summary)  # type: ignore[arg-type]
            print("  " + "\n  ".join(text.splitlines()[:8]))
            print(f"  summary: median {statistics.median(times):.2f} s, max {max(times):.2f} s"
                  f" (target < 5 s)")  # fmt: skip
            targets.check(f"summary of a {args.hours:g} h file", max(times), "<", 5.0, "s")
            t0 = time.perf_counter()
            decoded = 0
            for msg in LogReader(path).messages([topics.ROBOT_STATE]):
                decode_robot_state(msg.data)
                decoded += 1
            rate = decoded / (time.perf_counter() - t0)
            print(f"  read back and decoded {decoded:,} state samples: {rate:,.0f} /s")
            targets.check(
                "state samples decoded per second", rate, ">=", 100_000, "/s",
                peer=110_000, peer_name="anchor, low end",
            )  # fmt: skip
    return targets.finish()


if __name__ == "__main__":
    sys.exit(main())
