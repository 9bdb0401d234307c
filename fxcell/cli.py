"""The ``fxcell`` command line.

Each subcommand lives with the concept it drives and exposes
``register(subparsers)``, which adds its parser and sets ``func`` to a callable
taking the parsed arguments and returning an exit code. Registration must stay
cheap: heavy imports happen inside ``func``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Callable, Sequence
from typing import Any

from fxcell._version import __version__
from fxcell.errors import FxcellError

# Modules that contribute subcommands, in the order ``--help`` lists them.
SUBCOMMAND_MODULES: tuple[str, ...] = (
    "fxcell.info",
    "fxcell.cell.statemachine",
    "fxcell.daemon.cli",
    "fxcell.sim.cli",
    "fxcell.link.primary",
    "fxcell.replay",
    "fxcell.recorder.commands",
)

Handler = Callable[[argparse.Namespace], int]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fxcell",
        description=(
            "Run a UR3e cell from Python: the cell daemon, the embedded controller "
            "simulator, statecharts and MCAP log tools."
        ),
    )
    parser.add_argument("--version", action="version", version=f"fxcell {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)"
    )
    sub = parser.add_subparsers(title="commands", metavar="COMMAND")
    for name in SUBCOMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ImportError as exc:  # a light install (fxcell[client]) lacks the cell stack
            for command in CELL_ONLY.get(name, ()):
                _needs_cell_extra(sub, command, exc)
            continue
        module.register(sub)
    return parser


# The packages of the `cell` extra: a light install (`fxcell[client]`) lacks them.
CELL_STACK = frozenset(
    {
        "numpy", "pinocchio", "coal", "hppfcl", "ompl", "ruckig", "rtde_control",
        "rtde_receive", "rtde_io", "dashboard_client", "mcap", "zstandard", "fastapi",
        "starlette", "uvicorn", "matplotlib", "foxglove", "transitions",
    }
)  # fmt: skip

# What each module contributes, for a light install that cannot import it.
CELL_ONLY: dict[str, tuple[str, ...]] = {
    "fxcell.info": ("info",),
    "fxcell.cell.statemachine": ("statechart",),
    "fxcell.sim.cli": ("sim",),
    "fxcell.replay": ("replay",),
    "fxcell.recorder.commands": ("logs",),
}


def _needs_cell_extra(sub: Any, command: str, exc: ImportError) -> None:
    why = f"'fxcell {command}' needs the cell stack ({exc.name or exc}): pip install 'fxcell[cell]'"
    p = sub.add_parser(command, help=f"(needs fxcell[cell]) {why}", add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)

    def refuse(args: argparse.Namespace) -> int:
        raise FxcellError(why)

    p.set_defaults(func=refuse)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # A subcommand may set ``default_log_level`` (the daemon logs INFO); each -v lowers it.
    base: int = getattr(args, "default_log_level", logging.WARNING)
    logging.basicConfig(
        level=max(logging.DEBUG, base - 10 * args.verbose),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if args.verbose < 2:  # pytransitions narrates every callback at INFO: only with -vv
        logging.getLogger("transitions").setLevel(logging.WARNING)
    func: Handler | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 0
    try:
        return func(args)
    except FxcellError as exc:
        print(f"fxcell: error: {exc}", file=sys.stderr)
        return 1
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] not in CELL_STACK:
            raise
        print(
            f"fxcell: error: this command needs the cell stack ({exc.name}): "
            "pip install 'fxcell[cell]'",
            file=sys.stderr,
        )
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into a command that stopped reading (| head)
        sys.stderr.close()
        return 0
