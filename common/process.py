"""What a child process does when its parent is gone."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable


def when_orphaned(action: Callable[[], None], poll_s: float = 0.5) -> None:
    """Call `action` once, from a daemon thread, when this process's parent goes away (a
    launcher or an experiment killed outright, with no chance to stop its children)."""
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        action()

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()
