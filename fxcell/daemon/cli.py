"""Operator commands: ``fxcell daemon`` and the commands that drive a running daemon.

``fxcell status``, ``fxcell power-on``, ``fxcell move-joint 0 -1.57 0 -1.57 0 0``, ...
talk to the daemon at ``--url`` (default ``$FXCELL_URL`` or the configured address)
with the token from ``--token``, ``$FXCELL_TOKEN`` or the daemon's token file.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import logging
import os
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from fxcell.commands import COMMANDS, Arg, Command
from fxcell.errors import ConfigError, FxcellError

_SHORT = {"velocity_factor": "-v", "acceleration_factor": "-a"}


SIM_CRUCIBLES = "16"
SIM_FUSION_TIME = 60.0
SIM_COOLING_TIME = 30.0
"""The embedded UR simulator's fusion machine in the daemon (``--sim-*``)."""


def _robot_kind(value: str) -> str:
    """``--robot``: a robot kind fxcell ships (the address is ``--robot-host``)."""
    from fxcell.robot_specs import SPECS

    if value not in SPECS:
        raise argparse.ArgumentTypeError(
            f"{value!r} is not a robot kind ({', '.join(SPECS)}); "
            "give the robot's address with --robot-host HOST"
        )
    return value


def register(sub: Any) -> None:
    p = sub.add_parser(
        "daemon",
        help="run the cell daemon (HTTP API, WebSocket stream, operator page)",
        description="Run the cell daemon. With no robot host configured it starts the "
        "embedded simulator. Stops cleanly on SIGTERM/SIGINT.",
    )
    p.add_argument(
        "--config",
        help="cell configuration file (default: the shipped cell of --robot: config/cell.yaml "
        "for a ur3e, config/ned2-cell.yaml for a ned2)",
    )
    p.add_argument("--host", help="address to listen on (default: daemon.host, 127.0.0.1)")
    p.add_argument(
        "--port",
        type=int,
        help="port to listen on (default: daemon.port, 8040; 0: a free one, printed at start)",
    )
    p.add_argument(
        "--allow-remote",
        action="store_true",
        help="allow a non-loopback --host (every robot-changing command still needs the token)",
    )
    p.add_argument(
        "--robot",
        type=_robot_kind,
        metavar="KIND",
        help="the robot kind: ur3e or ned2 (default: robot.kind of the configuration; "
        "without --config, the shipped cell of that kind)",
    )
    p.add_argument(
        "--robot-host",
        metavar="HOST",
        help="robot controller address (overrides robot.host)",
    )
    p.add_argument(
        "--sim-time-scale",
        type=float,
        metavar="X",
        help="embedded simulator only: scale its controller delays (e.g. 0.2 for tests)",
    )
    p.add_argument(
        "--sim-crucibles",
        metavar="N|A1,B2,...",
        help="embedded simulator: crucibles with samples in the rack at start "
        f"(default: the full rack, {SIM_CRUCIBLES} for the UR3e cell; 0: none)",
    )
    p.add_argument(
        "--sim-fusion-time",
        type=float,
        metavar="S",
        help=f"embedded simulator: the fusion machine's fusion time (default "
        f"{SIM_FUSION_TIME:g} s; the real Vitriox takes about 600)",
    )
    p.add_argument(
        "--sim-cooling-time",
        type=float,
        metavar="S",
        help=f"embedded simulator: the fusion machine's cooling time (default "
        f"{SIM_COOLING_TIME:g} s)",
    )
    p.add_argument(
        "--sila",
        action="store_true",
        help="also serve SiLA 2 (gRPC, TLS) for lab schedulers (daemon.sila.enabled; "
        "docs/guides/sila.md)",
    )
    p.add_argument(
        "--sila-port", type=int, metavar="PORT", help="SiLA 2 port (default: daemon.sila.port)"
    )
    p.add_argument(
        "--sila-name", metavar="NAME", help="SiLA server name (default: daemon.sila.server_name)"
    )
    p.add_argument(
        "--sila-insecure",
        action="store_true",
        help="SiLA 2 without TLS: development only, against the standard",
    )
    p.add_argument("--no-record", action="store_true", help="do not record MCAP logs")
    p.add_argument(
        "--no-simulator",
        action="store_true",
        help="refuse to start without a robot host (never fall back to the embedded simulator)",
    )
    p.add_argument("--log-dir", help="MCAP directory (default: recorder.directory, logs/)")
    p.set_defaults(func=_run_daemon, default_log_level=logging.INFO)

    def client_parser(name: str, help_text: str) -> argparse.ArgumentParser:
        c: argparse.ArgumentParser = sub.add_parser(name, help=help_text, description=help_text)
        c.add_argument("--url", help="daemon URL (default: $FXCELL_URL or the configured address)")
        c.add_argument("--token", help="bearer token (default: $FXCELL_TOKEN or the token file)")
        c.add_argument("--config", help="cell configuration file (for the default URL and token)")
        c.add_argument("--json", action="store_true", help="print JSON")
        c.add_argument(
            "--force",
            action="store_true",
            help="take control over from the client holding it (it is told on its page)",
        )
        return c

    client_parser("status", "show the state of the cell served by a running daemon").set_defaults(
        func=_client(_status)
    )
    # One subcommand per entry of the command table (power-on, move-joint, stop, ...).
    for command in COMMANDS.values():
        needs = f" (robots with: {', '.join(sorted(command.requires))})" if command.requires else ""
        c = client_parser(command.name.replace("_", "-"), command.summary + needs)
        _add_arguments(c, command)
        if command.kind == "move":
            c.add_argument(
                "--no-wait", action="store_true", help="print the operation id and return at once"
            )
        c.set_defaults(func=_client(_table_command(command)))
    c = client_parser("operations", "list running and recent operations")
    c.set_defaults(func=_client(_operations))
    c = client_parser("cancel", "cancel an operation (a move stops)")
    c.add_argument("operation", help="operation id (op-N)")
    c.set_defaults(func=_client(_cancel))
    job = sub.add_parser("job", help="the fusion-machine job: start, status, pause, resume, abort")
    job_sub = job.add_subparsers(title="job commands", metavar="COMMAND", required=True)
    j = _job_parser(job_sub, "start", "start a run from a run file (YAML or JSON)")
    j.add_argument("file", help="the run file: samples with id, rack, machine, tray slots")
    _job_parser(job_sub, "status", "show the job: state, progress, samples, questions")
    _job_parser(job_sub, "pause", "pause at the next safe point")
    j = _job_parser(job_sub, "resume", "resume (answering recovery questions)")
    j.add_argument(
        "--answer",
        action="append",
        default=[],
        metavar="QUESTION=PLACE",
        help="where an object is, for a recovery question (repeatable)",
    )
    _job_parser(job_sub, "abort", "abort the current step (the arm brakes); resumable")
    _job_parser(job_sub, "confirm", "manual machine mode: the machine was started / is done")
    _job_parser(job_sub, "discard", "forget a paused or faulted run")
    c = client_parser("token", "print the daemon's token (or the operator page URL with it)")
    c.add_argument("--page-url", action="store_true", help="print the page URL that logs in")
    c.set_defaults(func=_token)


def _job_parser(sub: Any, name: str, help_text: str) -> argparse.ArgumentParser:
    c: argparse.ArgumentParser = sub.add_parser(name, help=help_text, description=help_text)
    c.add_argument("--url", help="daemon URL (default: $FXCELL_URL or the configured address)")
    c.add_argument("--token", help="bearer token (default: $FXCELL_TOKEN or the token file)")
    c.add_argument("--config", help="cell configuration file (for the default URL and token)")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--force", action="store_true", help="take control over from its holder")
    c.set_defaults(func=_client(_job_command(name)))
    return c


def _job_command(name: str) -> ClientCommand:
    async def run(cell: Any, args: argparse.Namespace) -> Any:
        if name == "status":
            status = await cell.job_status()
        elif name == "start":
            status = await cell.job_start(args.file)
        elif name == "resume":
            answers = {}
            for item in args.answer:
                key, sep, value = item.partition("=")
                if not sep:
                    raise FxcellError(f"--answer {item!r}: give QUESTION=PLACE")
                answers[key] = value
            status = await cell.job_resume(answers)
        else:
            status = await getattr(cell, f"job_{name}")()
        return status if args.json else format_job(status)

    return run


def format_job(status: dict[str, Any]) -> str:
    """The job's status for a terminal."""
    lines = [f"job:      {status.get('state')}  {status.get('message') or ''}".rstrip()]
    progress = status.get("progress")
    if progress:
        eta = progress.get("eta")
        lines.append(
            f"progress: {progress['done']}/{progress['total']} steps"
            + (f", about {eta / 60:.1f} min left" if eta is not None else "")
        )
    if status.get("step"):
        lines.append(f"step:     {status['step']}")
    for sample in status.get("samples") or []:
        where = sample.get("crucible") or "?"
        bead = f", bead {sample['bead']}" if sample.get("bead") else ""
        lines.append(f"  {sample['id']:<10} crucible {where}{bead}")
    for q in status.get("questions") or []:
        lines.append(f"question {q['id']}: {q['text']} (choices: {', '.join(q['choices'])})")
    prompt = status.get("prompt")
    if prompt:
        text = prompt.get("text", prompt) if isinstance(prompt, dict) else prompt
        lines.append(f"waiting for you: {text} (fxcell job confirm)")
    return "\n".join(lines)


# ----------------------------------------------------------------- daemon


def _run_daemon(args: argparse.Namespace) -> int:
    from fxcell.config import CellConfig

    try:
        from fxcell.daemon.server import serve
    except ImportError as exc:
        raise FxcellError(
            f"the daemon needs the cell stack ({exc.name or exc}): pip install 'fxcell[cell]'"
        ) from None

    config = _daemon_config(args.config, args.robot)
    data = config.model_dump()
    for key, value in (("host", args.host), ("port", args.port)):
        if value is not None:
            data["daemon"][key] = value
    if args.allow_remote:
        data["daemon"]["allow_remote"] = True
    if args.robot_host:
        data["robot"]["host"] = args.robot_host
    sila = data["daemon"]["sila"]
    if args.sila:
        sila["enabled"] = True
    for key, value in (("port", args.sila_port), ("server_name", args.sila_name)):
        if value is not None:
            sila[key] = value
    if args.sila_insecure:
        sila["insecure"] = True
    config = CellConfig.from_dict(data, source="command line")
    if getattr(args, "no_simulator", False) and config.robot.host is None:
        raise FxcellError(
            "no robot host configured (robot.host in the configuration, or --robot-host "
            "HOST); --no-simulator refuses to start the embedded simulator"
        )
    record = None if args.no_record else Path(args.log_dir or config.recorder.directory)
    sim = _simulator_options(args, config)
    return serve(config, record=record, simulator_options=sim)


def _daemon_config(path: str | None, kind: str | None) -> Any:
    """The configuration: ``path``, else the shipped cell of ``kind`` (else the UR3e's);
    FxcellError when ``kind`` is not the file's ``robot.kind``."""
    from fxcell.config import CONFIG_DIR, CellConfig
    from fxcell.robot_specs import SPECS

    if path is None:
        return CellConfig.load(None if kind is None else CONFIG_DIR / SPECS[kind].shipped_config)
    config = CellConfig.load(path)
    if kind is not None and config.robot.kind != kind:
        raise FxcellError(
            f"--robot {kind}: {path} configures a {config.robot.kind} (robot.kind); give a "
            f"configuration of a {kind}, or leave out --config for the shipped one"
        )
    return config


def _simulator_options(args: argparse.Namespace, config: Any) -> dict[str, Any]:
    """What the kind's embedded simulator is started with: the time scale and the fusion
    machine with crucibles in the rack (the UR simulator's machine on its DO0/DI0-DI3, the
    Ned2 simulator's on the Ned2's pins, in the configuration's layout)."""
    kind = config.robot.kind
    sim: dict[str, Any] = {}
    if args.sim_time_scale:
        sim["time_scale"] = args.sim_time_scale
    if kind == "ur3e":
        crucibles = SIM_CRUCIBLES if args.sim_crucibles is None else args.sim_crucibles
        extra = []
    else:
        # the Ned2 simulator is a bare robot unless told: the cell's machine, its layout
        stations = config.layout.stations
        if "machine" not in stations or "moulds" not in stations or "rack" not in stations:
            given = [
                option
                for option, value in (
                    ("--sim-crucibles", args.sim_crucibles),
                    ("--sim-fusion-time", args.sim_fusion_time),
                    ("--sim-cooling-time", args.sim_cooling_time),
                )
                if value is not None
            ]
            if given:
                raise FxcellError(
                    f"{', '.join(given)}: the layout has no rack, machine and moulds "
                    "stations, so the simulator hosts no fusion machine"
                )
            return sim
        rack = stations["rack"]
        full = rack.rows * rack.columns
        crucibles = str(full) if args.sim_crucibles is None else args.sim_crucibles
        extra = ["--machine"]
        if args.config is not None:
            extra += ["--config", str(Path(args.config).resolve())]
    fusion = SIM_FUSION_TIME if args.sim_fusion_time is None else args.sim_fusion_time
    cooling = SIM_COOLING_TIME if args.sim_cooling_time is None else args.sim_cooling_time
    extra += ["--fusion-time", str(fusion), "--cooling-time", str(cooling)]
    if crucibles not in ("", "0"):
        extra += ["--crucibles", crucibles]
    sim["extra_args"] = extra
    return sim


# ----------------------------------------------------------------- client commands

ClientCommand = Callable[[Any, argparse.Namespace], Awaitable[Any]]


def _client(command: ClientCommand) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        from fxcell.client import RemoteCell, default_client_name

        url, token = _endpoint(args)

        async def main() -> Any:
            name = default_client_name("fxcell CLI").rsplit(", pid", 1)[0] + ")"
            async with RemoteCell(url, token, name=name) as cell:
                if getattr(args, "force", False):
                    await cell.take_control(force=True)
                return await command(cell, args)

        result = asyncio.run(main())
        if dataclasses.is_dataclass(result) and not isinstance(result, type):
            result = dataclasses.asdict(result)
        if result is not None:
            if args.json or not isinstance(result, str):
                print(json.dumps(result, indent=2, default=str))
            else:
                print(result)
        return 0

    return run


def _endpoint(args: argparse.Namespace) -> tuple[str, str | None]:
    from fxcell.config import CellConfig
    from fxcell.daemon.auth import read_token

    config = CellConfig.load(getattr(args, "config", None))
    url = getattr(args, "url", None) or os.environ.get("FXCELL_URL")
    if not url:
        if not config.daemon.port:
            raise ConfigError(
                "daemon.port is 0 (a free port picked at start): give the address the daemon "
                "printed with --url or FXCELL_URL"
            )
        host = config.daemon.host
        host = "127.0.0.1" if host in ("0.0.0.0", "::") else host
        url = f"http://{host}:{config.daemon.port}"
    token = getattr(args, "token", None) or read_token(config.daemon.token_file)
    return url, token


async def _status(cell: Any, args: argparse.Namespace) -> Any:
    snap = await cell.snapshot()
    if args.json:
        return snap
    robot = snap.get("robot") or {}
    control = snap.get("control")
    lines = [
        f"robot:        {snap.get('kind', '-')}",
        f"state:        {snap['state']}",
        f"robot mode:   {robot.get('robot_mode', '-')}",
        f"safety mode:  {robot.get('safety_mode', '-')}",
        f"program:      {robot.get('runtime_state', '-')}",
        "joints (rad): " + " ".join(f"{v:+.4f}" for v in robot.get("q", [])),
        "tcp:          " + " ".join(f"{v:+.4f}" for v in robot.get("tcp", [])),
        f"control:      {control['client'] if control else 'free'}",
        f"allowed:      {', '.join(snap.get('allowed', []))}",
    ]
    cal = snap.get("calibration")
    if cal:
        checksum = f", checksum {cal['checksum']}" if cal.get("checksum") else ""
        lines.append(f"arm model:    {cal['model']} ({cal['source']}{checksum})")
    for op in snap.get("operations", []):
        lines.append(f"running:      {op['id']} {op['name']} ({op['client']})")
    if snap.get("cell_error"):
        lines.append(f"cell error:   {snap['cell_error']}")
    return "\n".join(lines)


def _add_arguments(parser: argparse.ArgumentParser, command: Command) -> None:
    """Arguments of a table command: required ones positional (when there is one, or all are
    scalars: ``pick rack B3``), the others options."""
    required = [a for a in command.args if a.required]
    positional = len(required) == 1 or all(a.type.length is None for a in required)
    for arg in command.args:
        kind = arg.type
        unit = f" ({kind.unit})" if kind.unit else ""
        options: dict[str, Any] = {"help": arg.doc + unit}
        if kind.scalar == "bool":
            options["action"] = "store_true"
        elif kind.scalar == "str":
            options["type"] = str
        elif kind.scalar == "level":
            options["type"] = _level
        else:
            options["type"] = float
            if kind.length is not None:
                low, high = kind.length
                options["nargs"] = low if low == high else "+"
                options["metavar"] = arg.name[0].upper()
        if arg.required and positional:
            parser.add_argument(arg.name, **options)
            continue
        flags = [f"--{arg.name.replace('_', '-')}"]
        if arg.name in _SHORT:
            flags.insert(0, _SHORT[arg.name])
        parser.add_argument(*flags, dest=arg.name, required=arg.required, **options)


def _level(text: str) -> bool | float:
    """An IO value on the command line: on/off, true/false, 1/0, or a number (analog)."""
    word = text.strip().lower()
    if word in ("on", "true", "yes", "1"):
        return True
    if word in ("off", "false", "no", "0"):
        return False
    try:
        return float(word)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"not an IO value: {text!r} (on/off or a number)"
        ) from None


def _arguments(command: Command, args: argparse.Namespace) -> dict[str, Any]:
    values = {a.name: getattr(args, a.name) for a in command.args}
    return {k: v for k, v in values.items() if v is not None and _given(command, k, v)}


def _given(command: Command, name: str, value: Any) -> bool:
    arg: Arg = next(a for a in command.args if a.name == name)
    return arg.required or value != arg.default


def _table_command(command: Command) -> ClientCommand:
    name = command.name

    async def run(cell: Any, args: argparse.Namespace) -> Any:
        from fxcell.daemon.encoding import jsonable

        body = _arguments(command, args)
        if command.kind == "move":
            op = await cell.start(name, **body)
            if args.no_wait:
                return op.id
            try:
                return await op.wait()
            except KeyboardInterrupt:
                await op.cancel()
                raise
        result = await cell.run_command(name, **body)
        if command.kind == "command" and command.result.annotation == "None":
            return f"{name}: done (state {await cell.get_state()})"
        return jsonable(result)

    return run


async def _operations(cell: Any, args: argparse.Namespace) -> Any:
    ops = await cell.operations()
    if args.json:
        return ops
    return (
        "\n".join(f"{op['id']:<8} {op['status']:<10} {op['name']:<24} {op['client']}" for op in ops)
        or "no operations"
    )


async def _cancel(cell: Any, args: argparse.Namespace) -> Any:
    op = await cell.operation(args.operation)
    return await op.cancel()


def _token(args: argparse.Namespace) -> int:
    from fxcell.config import CellConfig
    from fxcell.daemon.auth import read_token

    config = CellConfig.load(args.config)
    token = read_token(config.daemon.token_file)
    if token is None:
        print(
            f"fxcell: error: no token yet ({config.daemon.token_file}); start the daemon once",
            file=sys.stderr,
        )
        return 1
    if args.page_url:
        url, _ = _endpoint(args)
        print(f"{url}/#token={token}")
    else:
        print(token)
    return 0
