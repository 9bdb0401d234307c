"""The controller's program directory (``/programs``): a directory on this machine.

The Dashboard's ``load`` finds programs (``.urp``) and installations (``.installation``)
here; a path is the controller's (``/programs/x.urp``, or relative to ``/programs``) and
maps into the store's directory (nothing outside it is reachable). PolyScope saves each
program's URScript next to it (``x.script``): playing a program runs that script through
the simulator's URScript interpreter; a program without one plays and idles, and
``external_control.urp`` asks the PC for its program as the ExternalControl URCap does.

The default store (``default_programs/`` in this package) holds the programs the embedded
default needs: ``external_control.urp``, ``fxcell.urp``, ``default.urp`` and
``default.installation``. ``fxcell sim --programs DIR`` serves another directory.
"""

from __future__ import annotations

import posixpath
from pathlib import Path

CONTROLLER_DIR = "/programs"
URCAP_PROGRAM = "external_control.urp"
DEFAULT_DIR = Path(__file__).resolve().parent / "default_programs"


class ProgramStore:
    """Programs and installations in ``directory``, seen as the controller's /programs."""

    def __init__(self, directory: Path | str = DEFAULT_DIR) -> None:
        self.directory = Path(directory)

    def controller_path(self, requested: str) -> str:
        """The path as the controller reports it (``x.urp`` -> ``/programs/x.urp``)."""
        path = requested.strip()
        if not path.startswith("/"):
            path = f"{CONTROLLER_DIR}/{path}"
        return posixpath.normpath(path)

    def find(self, requested: str) -> tuple[str, Path | None]:
        """The controller path of ``requested`` and its file, or None when there is none."""
        full = self.controller_path(requested)
        prefix = CONTROLLER_DIR + "/"
        if not full.startswith(prefix) or "\x00" in full:
            return full, None
        file = self.directory / full[len(prefix) :]
        try:
            return full, file if file.is_file() else None
        except (OSError, ValueError):  # a name too long for the file system, ...
            return full, None

    def script(self, program: str) -> str | None:
        """The URScript PolyScope saved next to ``program`` (a controller path), if any."""
        full, file = self.find(program)
        if file is None or not full.endswith(".urp"):
            return None
        script = file.with_suffix(".script")
        try:
            return script.read_text(encoding="utf-8") if script.is_file() else None
        except (OSError, ValueError):
            return None
