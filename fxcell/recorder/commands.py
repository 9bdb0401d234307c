"""``fxcell logs``: maintenance of MCAP logs (recover crashed files, apply retention)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser(
        "logs", help="MCAP log maintenance: recover crashed recordings, prune old ones"
    )
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
    p = logs.add_parser(
        "prune",
        help="remove the oldest finished logs beyond a total size or age",
        description=(
            "Apply log retention to DIR now (the daemon does it whenever it opens a log): "
            "remove finished logs older than --max-age, then the oldest until the rest fit "
            "in --max-size. Files a recorder is writing are never touched. Defaults come from "
            "the configuration's recorder section."
        ),
    )
    p.add_argument("directory", type=Path, nargs="?", metavar="DIR", help="default: config's")
    p.add_argument("--config", type=Path, help="cell configuration (default: the packaged one)")
    p.add_argument("--max-size", type=float, metavar="GB", help="total size limit in GB (1e9 B)")
    p.add_argument("--max-age", type=float, metavar="DAYS", help="age limit in days")
    p.add_argument("--dry-run", action="store_true", help="list what would be removed")
    p.set_defaults(func=run_prune)


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


def run_prune(args: argparse.Namespace) -> int:
    from fxcell.config import CellConfig
    from fxcell.recorder.retention import Retention, enforce

    rec = CellConfig.load(args.config).recorder
    directory = args.directory if args.directory is not None else rec.directory
    max_size = int(args.max_size * 1e9) if args.max_size is not None else rec.max_total_size
    max_age = args.max_age * 86400.0 if args.max_age is not None else rec.max_age
    retention = Retention(max_size, max_age)
    if not directory.is_dir():
        print(f"{directory}: no such log directory")
        return 1
    report = enforce(directory, retention, dry_run=args.dry_run)
    verb = "would remove" if args.dry_run else "removed"
    for path in report.removed:
        print(f"{verb} {path}")
    print(
        f"{verb} {len(report.removed)} file(s), {report.freed / 1e6:.1f} MB; "
        f"{report.kept_bytes / 1e6:.1f} MB kept"
    )
    return 0
