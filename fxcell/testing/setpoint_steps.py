"""Per-cycle accelerations of recorded moves against the joint limits.

The ``/robot/state`` samples of an MCAP log carry the controller's target joint velocity
(``target_qd``): what servoJ makes of the setpoints fxcell streams. Two neighbouring
samples give the commanded acceleration of that cycle; this module compares every such
step with the braking acceleration (the largest any motion of fxcell may use) and the
joint speed limits::

    python -m fxcell.testing.setpoint_steps logs/*.mcap

Steps while the controller stops the arm by itself (a safety stop, a stopped program,
power off) are not fxcell's and are left out, as are cycles across a gap in the
controller's clock longer than ``max_gap`` (cycles the controller itself skipped: their
setpoint was held for them before fxcell could send the next one); the cycles right
after a gap are counted (that is where a catch-up jump would show).

Cycles the controller ran on a *held* setpoint (none came in time: the link process was
starved) are counted apart (``held``): servoJ's response to them is the machine's timing,
not a setpoint fxcell sent. They are told from the state alone: servoJ's tracker (the
critically damped one of :func:`fxcell.link.follower.servo_omega`) gives back the setpoint
each cycle ran on, ``s = q + (q̈ + 2ω q̇)/ω²``, and a held one equals the cycle's before.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from fxcell.config import CellConfig
from fxcell.link.follower import servo_omega
from fxcell.protocol import CONTROL_PERIOD, RobotMode, RobotState, RuntimeState, SafetyMode

GAP = 1.5 * CONTROL_PERIOD
"""A step between two samples further apart than this crosses a gap in the clock."""
LOOKAHEAD, GAIN = 0.1, 300.0
"""servoJ's settings of fxcell's moves (fxcell.motion.moves.ExecutionOptions)."""
HELD = 1e-9
"""rad: a cycle whose setpoint moved less than this on every joint ran on a held one."""


@dataclass(frozen=True)
class Step:
    """The largest step of one cycle: which joint, how fast, against its limit."""

    timestamp: float
    joint: int
    velocity_before: float
    velocity_after: float
    acceleration: float
    ratio: float  # |acceleration| / limit
    after_gap: int | None  # cycles since the last clock gap (None: none within 5 cycles)


@dataclass
class Report:
    """Per-cycle acceleration figures of one recorded stream."""

    cycles: int = 0
    """Cycles judged (both samples in normal motion, no gap between them, a fresh setpoint)."""
    gaps: int = 0
    """Gaps in the controller's clock (cycles skipped by the controller)."""
    worst_ratio: float = 0.0
    """The largest commanded acceleration over its limit, any joint, any cycle."""
    worst_speed_ratio: float = 0.0
    """The largest commanded joint speed over its limit."""
    worst_gap_ratio: float = 0.0
    """The largest mean acceleration over its limit across a clock gap (not in
    ``worst_ratio``: the controller held the setpoint for the cycles it skipped)."""
    over: list[Step] = field(default_factory=list)
    """Cycles above ``tolerance`` times the limit (on a fresh setpoint)."""
    held: int = 0
    """Cycles the controller ran on a held setpoint (none came in time), while moving."""
    worst_held_ratio: float = 0.0
    """The largest acceleration over its limit in those cycles (not in ``worst_ratio``)."""

    def over_ratio(self, ratio: float) -> list[Step]:
        return [s for s in self.over if s.ratio > ratio]


def _normal(state: RobotState) -> bool:
    return (
        state.safety_mode == SafetyMode.NORMAL
        and state.runtime_state == RuntimeState.PLAYING
        and state.robot_mode == RobotMode.RUNNING
    )


def check_states(
    states: Iterable[RobotState],
    acceleration: Sequence[float],
    velocity: Sequence[float],
    *,
    tolerance: float = 1.05,
    max_gap: float = GAP,
    lookahead: float = LOOKAHEAD,
    gain: float = GAIN,
) -> Report:
    """Judge every cycle of ``states`` (in stream order) against the per-joint limits."""
    report = Report()
    previous: RobotState | None = None
    since_gap: int | None = None
    omega = servo_omega(lookahead, gain)
    w2, w1 = omega * omega, 2 * omega
    setpoint: list[float] | None = None  # the one the previous cycle ran on
    for state in states:
        if previous is None or not (_normal(state) and _normal(previous)):
            previous, since_gap, setpoint = state, None, None
            continue
        dt = state.timestamp - previous.timestamp
        if dt <= 0:
            previous = state
            continue
        if dt > max_gap:
            report.gaps += 1
            setpoint = None
            for v0, v1, limit in zip(
                previous.target_qd, state.target_qd, acceleration, strict=True
            ):
                report.worst_gap_ratio = max(report.worst_gap_ratio, abs(v1 - v0) / dt / limit)
            previous, since_gap = state, 0
            continue
        since_gap = None if since_gap is None or since_gap >= 5 else since_gap + 1
        ran_on = [
            q + ((v1 - v0) / dt + w1 * v0) / w2
            for q, v0, v1 in zip(
                previous.target_q, previous.target_qd, state.target_qd, strict=True
            )
        ]
        held = (
            setpoint is not None
            and max(abs(a - b) for a, b in zip(ran_on, setpoint, strict=True)) < HELD
            and max(map(abs, previous.target_qd)) > 1e-3
        )
        setpoint = ran_on
        worst: Step | None = None
        for j, (v0, v1, limit, vmax) in enumerate(
            zip(previous.target_qd, state.target_qd, acceleration, velocity, strict=True)
        ):
            a = (v1 - v0) / dt
            ratio = abs(a) / limit
            report.worst_speed_ratio = max(report.worst_speed_ratio, abs(v1) / vmax)
            if worst is None or ratio > worst.ratio:
                worst = Step(state.timestamp, j, v0, v1, a, ratio, since_gap)
        assert worst is not None
        previous = state
        if held:
            report.held += 1
            report.worst_held_ratio = max(report.worst_held_ratio, worst.ratio)
            continue
        report.cycles += 1
        report.worst_ratio = max(report.worst_ratio, worst.ratio)
        if worst.ratio > tolerance:
            report.over.append(worst)
    return report


def read_states(path: str | Path) -> list[RobotState]:
    """The ``/robot/state`` samples of one MCAP log, in file order."""
    from fxcell.recorder import topics
    from fxcell.recorder.reading import LogReader

    return [state for _, state in LogReader(path).decoded([topics.ROBOT_STATE])]


def check_log(path: str | Path, config: CellConfig | None = None, **kwargs: float) -> Report:
    """:func:`check_states` on a log, with the configured braking and speed limits."""
    limits = (config or CellConfig.load()).limits
    return check_states(read_states(path), limits.braking_acceleration, limits.velocity, **kwargs)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fxcell.testing.setpoint_steps")
    parser.add_argument("logs", nargs="+", type=Path)
    parser.add_argument("--tolerance", type=float, default=1.05)
    parser.add_argument("--show", type=int, default=5, help="worst steps listed per log")
    parser.add_argument("--lookahead", type=float, default=LOOKAHEAD, help="servoJ's, s")
    parser.add_argument("--gain", type=float, default=GAIN, help="servoJ's")
    args = parser.parse_args(argv)
    total = over = over15 = near_gap = 0
    worst = 0.0
    for path in args.logs:
        report = check_log(path, tolerance=args.tolerance, lookahead=args.lookahead, gain=args.gain)
        n15 = len(report.over_ratio(1.5))
        gap = sum(1 for s in report.over if s.after_gap is not None)
        total, over, over15 = total + report.cycles, over + len(report.over), over15 + n15
        near_gap += gap
        worst = max(worst, report.worst_ratio)
        print(
            f"{path.name}: {report.cycles} cycles, {report.gaps} clock gaps, "
            f"{len(report.over)} over {args.tolerance:g}x ({n15} over 1.5x, {gap} within 5 "
            f"cycles of a gap); worst {report.worst_ratio:.2f}x the braking acceleration, "
            f"speed {report.worst_speed_ratio:.2f}x its limit; across gaps "
            f"{report.worst_gap_ratio:.2f}x; {report.held} cycles on a held setpoint, "
            f"worst {report.worst_held_ratio:.2f}x"
        )
        for s in sorted(report.over, key=lambda s: -s.ratio)[: args.show]:
            print(
                f"   t={s.timestamp:.3f} joint {s.joint + 1}: {s.velocity_before:+.4f} -> "
                f"{s.velocity_after:+.4f} rad/s ({s.acceleration:+.1f} rad/s², {s.ratio:.1f}x)"
                + (f", {s.after_gap} cycles after a gap" if s.after_gap is not None else "")
            )
    print(
        f"all: {total} cycles on fresh setpoints, {over} over {args.tolerance:g}x, "
        f"{over15} over 1.5x, "
        f"{near_gap} within 5 cycles of a gap; worst {worst:.2f}x"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
