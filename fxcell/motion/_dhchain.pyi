"""Types of the C extension built from ``_dhchain.c`` (see hatch_build.py)."""

from collections.abc import Sequence

class Chain:
    """As :class:`fxcell.motion.kinematics.DHChain`, in C."""

    def __init__(
        self,
        theta: Sequence[float],
        a: Sequence[float],
        d: Sequence[float],
        alpha: Sequence[float],
        tcp: Sequence[float],
    ) -> None: ...
    def frame(self, q: Sequence[float], /) -> list[float]: ...
    def frame_and_jacobian(self, q: Sequence[float], /) -> tuple[list[float], list[float]]: ...
    def newton(
        self,
        q: Sequence[float],
        target: Sequence[float],
        iterations: int = 20,
        converged: float = 1e-12,
        rounding: float = 1e-11,
        /,
    ) -> tuple[list[float], float]: ...
    def settle(
        self,
        q: Sequence[float],
        target: Sequence[float],
        iterations: int = 60,
        converged: float = 1e-12,
        stationary: float = 1e-6,
        /,
    ) -> tuple[list[float], float, float]: ...
    def valley(
        self, q: Sequence[float], target: Sequence[float], converged: float = 1e-12, /
    ) -> list[tuple[list[float], float]]: ...
    def nearest(
        self,
        starts: Sequence[tuple[float, Sequence[float]]],
        target: Sequence[float],
        seed: Sequence[float],
        lower: Sequence[float],
        upper: Sequence[float],
        newton_iterations: int,
        settle_iterations: int,
        converged: float,
        rounding: float,
        stationary: float,
        accepted: float,
        factor: float,
        near: float,
        /,
    ) -> tuple[list[float] | None, float, float, float, int]: ...
    def hot_path(
        self,
        geom: Sequence[float],
        tcp: Sequence[float],
        tcp_inv: Sequence[float],
        tcp_identity: bool,
        start_lower: Sequence[float],
        start_upper: Sequence[float],
        lower: Sequence[float],
        upper: Sequence[float],
        newton_iterations: int,
        settle_iterations: int,
        converged: float,
        rounding: float,
        stationary: float,
        accepted: float,
        factor: float,
        near: float,
        singular_move: float,
        lenient_h2: float,
        lenient_c3: float,
        edge_c3: float,
        lenient_wrist: float,
        wrist_eps: float,
        branches: int,
        /,
    ) -> None: ...
    def fast(self, target: Sequence[float], seed: Sequence[float], /) -> list[float] | None: ...
