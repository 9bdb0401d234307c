"""``fxcell logs``: maintenance of MCAP logs (recover files cut off by a crash)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser("logs", help="MCAP log maintenance: recover crashed recordings")
    logs = p.add_subparsers(title="log commands", metavar="ACTION", required=True)
    r = logs.add_parser(
        "recover",
        help="rewrite a log cut off by a crash as a finished file",
        description=(
            "Keep everything up to the last complete chunk of each FILE and finish it "
            "(in place unless --output is given). A directory recovers every unfinished "
            "log in it. Files a recorder is still writing are refused."
        ),
    )
    r.add_argument("files", nargs="+", type=Path, metavar="FILE", help="log file or directory")
    r.add_argument("-o", "--output", type=Path, help="write the recovered log here (one FILE)")
    r.set_defaults(func=run_recover)


def run_recover(args: argparse.Namespace) -> int:
    from fxcell.errors import InvalidArgumentError
    from fxcell.recorder.recovery import is_finished, recover, recover_unfinished

    if args.output is not None and len(args.files) != 1:
        raise InvalidArgumentError("--output needs exactly one FILE")
    for path in args.files:
        if path.is_dir():
            reports = recover_unfinished(path)
            for report in reports:
                print(f"recovered {report}")
            if not reports:
                print(f"{path}: no unfinished logs")
            continue
        if args.output is None and is_finished(path):
            print(f"{path}: already finished, nothing to recover")
            continue
        print(f"recovered {recover(path, args.output)}")
    return 0
