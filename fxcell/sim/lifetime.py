"""A simulator process ends with the process that launched it (``--exit-with-parent``)."""

from __future__ import annotations

import os
import threading
import time


def watch_parent() -> None:
    """Exit at once when the launching process is gone (nobody could stop us any more)."""
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()
