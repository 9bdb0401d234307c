"""Synthetic cell sessions for exercising the recorder without a robot.

A realistic event stream: 500 Hz robot-state samples of an arm moving between
waypoints (positions, velocities, accelerations, currents, TCP pose from the real
kinematics), the commands of a session with start and end records, state-machine
transitions, a protective stop with its failing move, and log records. Used by the
recorder's tests and by ``bench/recorder.py``; it never touches a robot.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from fxcell.events import (
    CommandEvent,
    Event,
    LogEvent,
    MotionEvent,
    Origin,
    StateEvent,
    TransitionEvent,
)
from fxcell.protocol import (
    CONTROL_PERIOD,
    RobotMode,
    RobotState,
    RobotStatusBits,
    RuntimeState,
    SafetyMode,
    SafetyStatusBits,
)

HOME = (0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0)
WAYPOINTS = (
    HOME,
    (0.6, -1.2, 0.9, -1.3, -1.57, 0.2),
    (-0.4, -1.8, 1.2, -0.9, -1.2, -0.5),
    (1.0, -1.0, 0.5, -1.6, -1.57, 1.0),
)


@dataclass(frozen=True, slots=True)
class Planned:
    """An event and when to publish it, in seconds from the session start."""

    at: float
    event: Event


class SyntheticSession:
    """A cell session of ``duration`` seconds: states at ``rate`` Hz, a move every ``move_every`` s.

    ``protective_stop_at`` (seconds) puts the robot in protective stop for 0.5 s there
    and fails the move in progress. Times of events start at ``t0`` (wall clock).
    """

    def __init__(
        self,
        duration: float,
        *,
        rate: float = 1 / CONTROL_PERIOD,
        move_every: float = 2.0,
        protective_stop_at: float | None = None,
        t0: float | None = None,
        tcp: tuple[float, ...] | None = None,
    ) -> None:
        from fxcell.motion.kinematics import Kinematics

        self.duration = duration
        self.rate = rate
        self.move_every = move_every
        self.protective_stop_at = protective_stop_at
        self.t0 = time.time() if t0 is None else t0
        self._kin = Kinematics.ur3e(tcp)
        self._command_id = 0

    def _state(
        self, t: float, q: tuple[float, ...], qd: tuple[float, ...], stop: bool
    ) -> RobotState:
        tcp = self._kin.forward(q).as_ur()
        qdd = tuple(-v * 2.0 for v in qd)
        return RobotState(
            timestamp=1000.0 + t,
            robot_mode=RobotMode.RUNNING,
            safety_mode=SafetyMode.PROTECTIVE_STOP if stop else SafetyMode.NORMAL,
            runtime_state=RuntimeState.PLAYING,
            robot_status_bits=int(RobotStatusBits.POWER_ON | RobotStatusBits.PROGRAM_RUNNING),
            safety_status_bits=int(
                SafetyStatusBits.PROTECTIVE_STOPPED if stop else SafetyStatusBits.NORMAL_MODE
            ),
            target_q=q,
            target_qd=qd,
            target_qdd=qdd,
            actual_q=tuple(v + 1e-5 for v in q),
            actual_qd=qd,
            actual_current=tuple(0.3 + 0.5 * v for v in qd),
            target_tcp_pose=tcp,
            actual_tcp_pose=tcp,
            actual_tcp_speed=(0.0,) * 6,
            speed_scaling=1.0,
            output_int_registers=(2, 0, 0),
            received_at=t,
        )

    def _command(self, at: float, name: str, args: dict[str, object], took: float,
                 error: tuple[str, str] | None = None) -> list[Planned]:  # fmt: skip
        self._command_id += 1
        cid = self._command_id
        started = self.t0 + at
        start = CommandEvent(cid, name, args, Origin.LIBRARY, started)
        end = CommandEvent(
            cid, name, args, Origin.LIBRARY, started, started + took,
            "error" if error else "ok",
            error[0] if error else None, error[1] if error else None,
        )  # fmt: skip
        return [Planned(at, start), Planned(at + took, end)]

    def events(self) -> Iterator[Planned]:
        """The session's events in publishing order (the same on every call)."""
        self._command_id = 0
        planned: list[Planned] = []
        t0 = self.t0
        planned += self._command(0.0, "power_on", {}, 0.01)
        planned.append(
            Planned(0.01, TransitionEvent(t0 + 0.01, "power_off", "idle", "power_on", "command"))
        )
        planned += self._command(0.02, "brake_release", {}, 0.01)
        planned.append(
            Planned(0.03, TransitionEvent(t0 + 0.03, "idle", "ready", "brake_release", "command"))
        )
        move_times = [
            0.05 + i * self.move_every for i in range(int(self.duration / self.move_every) + 1)
        ]
        move_times = [m for m in move_times if m + self.move_every * 0.8 < self.duration]
        moves: list[tuple[float, float, tuple[float, ...], tuple[float, ...]]] = []
        stop_at = self.protective_stop_at
        for i, at in enumerate(move_times):
            a, b = WAYPOINTS[i % len(WAYPOINTS)], WAYPOINTS[(i + 1) % len(WAYPOINTS)]
            took = self.move_every * 0.8
            error = None
            if stop_at is not None and at <= stop_at < at + took:
                took = stop_at - at
                error = ("ProtectiveStopError", "the robot went into protective stop")
            planned += self._command(at, "move_joint", {"q": list(b), "vf": 0.5}, took, error)
            planned.append(Planned(at, MotionEvent(t0 + at, i + 1, "path", {"waypoints": [a, b]})))
            planned.append(
                Planned(
                    at + took, MotionEvent(t0 + at + took, i + 1, "result", {"ok": error is None})
                )
            )
            moves.append((at, at + took, a, b))
        if stop_at is not None:
            planned.append(
                Planned(
                    stop_at,
                    TransitionEvent(
                        t0 + stop_at,
                        "ready",
                        "protective_stop",
                        "protective_stop",
                        "observed",
                        "safety_mode PROTECTIVE_STOP",
                    ),
                )
            )
            planned.append(
                Planned(stop_at, LogEvent(t0 + stop_at, 40, "fxcell.cell.cell", "protective stop"))
            )
            planned += self._command(stop_at + 0.5, "unlock_protective_stop", {}, 0.01)
            planned.append(
                Planned(
                    stop_at + 0.51,
                    TransitionEvent(
                        t0 + stop_at + 0.51,
                        "protective_stop",
                        "ready",
                        "unlock_protective_stop",
                        "command",
                    ),
                )
            )
        planned.sort(key=lambda p: p.at)

        # interleave the 500 Hz state stream
        period = 1.0 / self.rate
        n = int(self.duration * self.rate)
        k = 0
        q: tuple[float, ...] = HOME
        for i in range(n):
            t = i * period
            while k < len(planned) and planned[k].at <= t:
                yield planned[k]
                k += 1
            qd: tuple[float, ...] = (0.0,) * 6
            for m_start, m_end, qa, qb in moves:
                if m_start <= t < m_end:
                    s = (t - m_start) / (m_end - m_start)
                    blend = 0.5 - 0.5 * math.cos(math.pi * s)
                    rate = 0.5 * math.pi * math.sin(math.pi * s) / (m_end - m_start)
                    q = tuple(x + (y - x) * blend for x, y in zip(qa, qb, strict=True))
                    qd = tuple((y - x) * rate for x, y in zip(qa, qb, strict=True))
                    break
            stop = stop_at is not None and stop_at <= t < stop_at + 0.5
            yield Planned(t, StateEvent(self._state(t, q, qd, stop)))
        yield from planned[k:]


def play(
    session: SyntheticSession, submit: Callable[[Event], None], *, realtime: bool = False
) -> int:
    """Publish the session through ``submit(event)``; returns the number of events.

    ``realtime`` paces the events at their planned times (500 Hz for the states).
    """
    count = 0
    start = time.monotonic()
    for p in session.events():
        if realtime:
            delay = p.at - (time.monotonic() - start)
            if delay > 0:
                time.sleep(delay)
        submit(p.event)
        count += 1
    return count
