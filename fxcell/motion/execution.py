"""How a kind's link takes a streamed plan (:class:`ExecutionOptions`): servo lookahead and
gain, whether setpoints lead the servo's lag, settling. Light (no numpy, no planner), so
that a robot kind (:mod:`fxcell.robots`) names its options without loading the motion
stack."""

from __future__ import annotations

from dataclasses import dataclass

from fxcell.settling import ARRIVE_TOLERANCE, REST_VELOCITY, SETTLE_POSITION, SETTLE_VELOCITY

__all__ = ["ExecutionOptions"]


@dataclass
class ExecutionOptions:
    """How a plan is streamed."""

    lookahead_time: float = 0.1
    """servoJ lookahead (s), with ``gain`` UR's defaults: the lag is compensated (below),
    and a soft tracker turns a setpoint that comes a cycle late (a busy link process) into
    ``ω²·q̇·Δt`` of acceleration, 0.8 rad/s² per rad/s here, where the stiffest setting
    (0.03 s, 2000; ω ≈ 107/s) made it 23 rad/s² per rad/s, several times the braking
    limit (see fxcell.link.follower.servo_omega)."""
    gain: float = 300.0
    """servoJ gain (see ``lookahead_time``)."""
    compensate_lag: bool = True
    """Lead the setpoints by servoJ's lag (≈ lookahead·(300/gain)^¼, URCL issue #86),
    so the executed motion equals the planned one; the last sample is unchanged."""
    brake_lead: int = 0
    """Samples between the link's estimated index and the sample the braking replaces.
    Erring late costs nothing: the link then joins the braking profile a few samples in,
    where it differs from the original by ~½·Δa·t² (µrad); erring early delays the stop."""
    settle_timeout: float = 0.5
    """How long the target is held after the last sample for the robot to settle (s)."""
    settle_position: float = SETTLE_POSITION
    """A move has arrived when every joint is within this of its target (rad)..."""
    settle_velocity: float = SETTLE_VELOCITY
    """...and slower than this (rad/s)."""
    arrive_tolerance: float = ARRIVE_TOLERANCE
    """If the hold ends first (a real arm's encoders may never read 1e-6 rad), the move
    still counts as arrived within this (rad, about 50 µm at the TCP); else TrackingError."""
    rest_velocity: float = REST_VELOCITY
    """After a stop, the robot is at rest below this joint speed (rad/s)."""

    @property
    def lag(self) -> float:
        return float(self.lookahead_time * (300.0 / self.gain) ** 0.25)
