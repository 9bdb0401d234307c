"""The seed library's ``fx_*`` functions, synchronous, on top of the async :class:`Cell`.

For migrating the lab's existing scripts: every function keeps its seed name and
returns what the thesis specifies (booleans for commands, values for queries). A
failed command logs the reason and returns ``False``, as the seed did; use
:class:`fxcell.Cell` for typed errors.

The functions share one Cell, opened on first use from ``config/cell.yaml`` (no
host there: the embedded simulator) and driven by an event loop in a background
thread. :func:`fx_connect` chooses another host or configuration, :func:`fx_close`
closes it.
"""

from __future__ import annotations

import asyncio
import atexit
import logging
import math
import threading
from collections.abc import Callable, Coroutine, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from fxcell.cell import Cell
from fxcell.commands import COMMANDS
from fxcell.config import CellConfig
from fxcell.errors import FxcellError

log = logging.getLogger(__name__)

T = TypeVar("T")

_lock = threading.RLock()
_loop: asyncio.AbstractEventLoop | None = None
_thread: threading.Thread | None = None
_cell: Cell | None = None
_velocity_factor = 1.0
_acceleration_factor = 1.0


def _ensure_loop() -> asyncio.AbstractEventLoop:
    global _loop, _thread
    with _lock:
        if _loop is None or not _loop.is_running():
            loop = asyncio.new_event_loop()
            started = threading.Event()

            def run() -> None:
                asyncio.set_event_loop(loop)
                loop.call_soon(started.set)
                loop.run_forever()

            _thread = threading.Thread(target=run, name="fxcell.compat loop", daemon=True)
            _thread.start()
            started.wait()
            _loop = loop
        return _loop


def _run(coro: Coroutine[Any, Any, T]) -> T:
    future: Future[T] = asyncio.run_coroutine_threadsafe(coro, _ensure_loop())
    return future.result()


def fx_connect(
    host: str | None = None, config: str | Path | CellConfig | None = None, **kwargs: Any
) -> bool:
    """Open the shared Cell (closing any previous one); True when connected."""
    global _cell
    fx_close()
    cfg = config if isinstance(config, CellConfig) else CellConfig.load(config)
    cell = Cell(host, config=cfg, **kwargs)
    try:
        _run(cell.open())
    except FxcellError as exc:
        log.error("fx_connect failed: %s", exc)
        return False
    with _lock:
        _cell = cell
    return True


def fx_close() -> None:
    """Close the shared Cell (and the embedded simulator it started)."""
    global _cell
    with _lock:
        cell, _cell = _cell, None
    if cell is not None:
        _run(cell.close())


atexit.register(fx_close)


def fx_cell() -> Cell:
    """The shared Cell, opened on first use."""
    with _lock:
        if _cell is None and not fx_connect():
            raise FxcellError("fx_connect() failed: see the log")
        assert _cell is not None
        return _cell


def _ok(name: str, coro_factory: Any) -> bool:
    try:
        _run(coro_factory(fx_cell()))
    except FxcellError as exc:
        log.error("%s failed: %s", name, exc)
        return False
    return True


# ----------------------------------------------------------------- from the command table
# A seed function that is one command of the table without arguments is derived from it:
# a command returns True on success (False, logged, on failure), a query its value as the
# seed did (lists for tuples).


def _command_function(name: str) -> Callable[[], bool]:
    entry = COMMANDS[name]
    if entry.kind == "query" or any(a.required for a in entry.args):
        raise TypeError(f"{name} is not a command without arguments")

    def function() -> bool:
        return _ok(f"fx_{name}", lambda c: c.run_command(name))

    function.__name__ = function.__qualname__ = f"fx_{name}"
    function.__doc__ = f"{entry.doc}\n\nTrue on success; False (the reason logged) on failure."
    return function


def _query_function(name: str, convert: Callable[[Any], T]) -> Callable[[], T]:
    entry = COMMANDS[name]
    if entry.kind != "query":
        raise TypeError(f"{name} is not a query")

    def function() -> T:
        return convert(_run(fx_cell().run_command(name)))

    function.__name__ = function.__qualname__ = f"fx_{name}"
    function.__doc__ = entry.doc
    return function


fx_power_on: Callable[[], bool] = _command_function("power_on")
fx_brake_release: Callable[[], bool] = _command_function("brake_release")
fx_power_off: Callable[[], bool] = _command_function("power_off")
fx_init: Callable[[], bool] = _command_function("init")
fx_start_external_control: Callable[[], bool] = _command_function("start_external_control")
fx_stop_external_control: Callable[[], bool] = _command_function("stop_external_control")
fx_shutdown: Callable[[], bool] = _command_function("shutdown")
fx_stop: Callable[[], bool] = _command_function("stop")
fx_is_in_remote_control: Callable[[], bool] = _query_function("is_in_remote_control", bool)
fx_get_velocity: Callable[[], list[float]] = _query_function("get_velocity", list)
fx_get_current_joint_values: Callable[[], list[float]] = _query_function(
    "get_current_joint_values", list
)
fx_get_current_pose: Callable[[], list[float]] = _query_function("get_current_pose", list)
fx_get_current_rpy: Callable[[], list[float]] = _query_function("get_current_rpy", list)
fx_get_current_pose_rpy: Callable[[], list[float]] = _query_function("get_current_pose_rpy", list)
fx_gripper_activate: Callable[[], bool] = _command_function("gripper_activate")
fx_gripper_open: Callable[[], bool] = _command_function("gripper_open")
fx_gripper_close: Callable[[], bool] = _command_function("gripper_close")
fx_get_gripper_width: Callable[[], float] = _query_function("get_gripper_width", float)


def fx_gripper_move(width: float, speed: float = 0.150, force: float = 185.0) -> bool:
    """Move the gripper's fingers to an opening (m) at a speed (m/s), force at most (N)."""
    return _ok("fx_gripper_move", lambda c: c.gripper_move(width, speed=speed, grip_force=force))


# ----------------------------------------------------------------- kinematic functions


def _move(name: str, factory: Any) -> bool:
    return _ok(name, factory)


def fx_go_home(velocity_factor: float = 1, acceleration_factor: float = 1) -> bool:
    """Move to the home joints [0, -π/2, 0, -π/2, 0, 0] (or the configured home)."""
    return _move("fx_go_home", lambda c: c.go_home(velocity_factor, acceleration_factor))


def fx_move_distance(
    distance_vector: Sequence[float], velocity_factor: float = 1, acceleration_factor: float = 1
) -> bool:
    """Move the TCP by [dx, dy, dz] metres along the base axes."""
    return _move(
        "fx_move_distance",
        lambda c: c.move_distance(list(distance_vector), velocity_factor, acceleration_factor),
    )


def fx_move_joint(
    target: Sequence[float], velocity_factor: float = 1, acceleration_factor: float = 1
) -> bool:
    """Move to joint values (rad, 1x6)."""
    return _move(
        "fx_move_joint",
        lambda c: c.move_joint(list(target), velocity_factor, acceleration_factor),
    )


def fx_move_pose(target: Any, velocity_factor: float = 1, acceleration_factor: float = 1) -> bool:
    """Move the TCP to a pose: [x, y, z, qx, qy, qz, qw] or [x, y, z, roll, pitch, yaw]."""
    return _move(
        "fx_move_pose", lambda c: c.move_pose(target, velocity_factor, acceleration_factor)
    )


def fx_move_relative(
    start_pose: Any, target_pose: Any, velocity_factor: float = 1, acceleration_factor: float = 1
) -> bool:
    """Move to ``start_pose``, then to ``target_pose``."""
    return _move(
        "fx_move_relative",
        lambda c: c.move_relative(start_pose, target_pose, velocity_factor, acceleration_factor),
    )


# ----------------------------------------------------------------- general functions


def fx_get_robot_mode() -> str:
    """The robot mode name, e.g. ``"RUNNING"`` (the seed stripped ``"Robotmode: "``)."""
    return _run(fx_cell().get_robot_mode()).name


def fx_unlock_protective_stop() -> bool:
    """Unlock a protective stop (waiting out the controller's 5 s rule)."""
    return _ok("fx_unlock_protective_stop", lambda c: c.unlock_protective_stop(wait=True))


# ----------------------------------------------------------------- additional functions


@dataclass(frozen=True)
class ProgramStateReply:
    """What the seed's ``GetProgramState`` service returned: ``state`` and ``program_name``."""

    state: str
    program_name: str


def fx_get_program_state() -> ProgramStateReply:
    """The program state (``"PLAYING"``/``"STOPPED"``/``"PAUSED"``) and program name."""
    status = _run(fx_cell().get_program_state())
    return ProgramStateReply(status.state.value, status.program)


def fx_get_acceleration_scaling_factor() -> float:
    """The default acceleration factor used by the move functions, in (0, 1]."""
    return _acceleration_factor


def fx_set_acceleration_factor(acceleration_factor: float) -> bool:
    """Set the default acceleration factor; False (and unchanged) unless in (0, 1]."""
    global _acceleration_factor
    if not _valid_factor(acceleration_factor):
        return False
    _acceleration_factor = float(acceleration_factor)
    _apply_factors()
    return True


def fx_get_velocity_scaling_factor() -> float:
    """The default velocity factor used by the move functions, in (0, 1]."""
    return _velocity_factor


def fx_set_velocity_factor(velocity_factor: float) -> bool:
    """Set the default velocity factor; False (and unchanged) unless in (0, 1]."""
    global _velocity_factor
    if not _valid_factor(velocity_factor):
        return False
    _velocity_factor = float(velocity_factor)
    _apply_factors()
    return True


def _apply_factors() -> None:
    """Make the factors the open Cell's defaults (moves of this module pass their own)."""
    with _lock:
        cell = _cell
    if cell is not None:
        _run(cell.set_velocity_factor(_velocity_factor))
        _run(cell.set_acceleration_factor(_acceleration_factor))


def fx_get_max_acceleration() -> list[float]:
    """The configured maximum joint accelerations, rad/s² (1x6)."""
    with _lock:
        config = _cell.config if _cell is not None else CellConfig.load()
    return list(config.limits.acceleration)


def _valid_factor(value: Any) -> bool:
    try:
        f = float(value)
    except (TypeError, ValueError):
        return False
    return math.isfinite(f) and 0.0 < f <= 1.0


# ----------------------------------------------------------------- testing functions


__all__ = [name for name in dir() if name.startswith("fx_")] + ["ProgramStateReply"]
