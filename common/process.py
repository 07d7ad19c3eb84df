"""How a vamppi process stops: on a signal within a second, and with its parent.

- `stop_on_signals(stop)`: SIGINT and SIGTERM set `stop`, the main loop unwinds its
  `with` blocks and the process exits; if it has not after `grace_s` (the main thread
  inside a long compilation, or wedged) it exits anyway. The signal is seen at once by a
  thread reading the interpreter's wakeup fd, which the C-level handler writes whatever
  the main thread is doing; the Python-level handler alone runs only when the main thread
  next executes Python.
- `exit_now(code)`: a service whose main loop has unwound (bus closed, files written)
  exits without the interpreter's finalization, which takes 0.2 s once JAX is loaded.
- `die_with_parent()`: the kernel sends SIGKILL when the parent dies (Linux
  PR_SET_PDEATHSIG), so a launcher killed outright leaves no children behind. Not
  SIGTERM: a child blocked in a put to the launcher's dead router holds the interpreter
  lock until the link's lease runs out (10 s), and no Python-level stop runs meanwhile.
- `when_orphaned(action)`: the portable watch of the same, by polling the parent.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import NoReturn

log = logging.getLogger(__name__)

STOP_GRACE_S = 0.5           # a stopped service is gone within a second of the signal
_PR_SET_PDEATHSIG = 1


def stop_on_signals(stop: threading.Event, grace_s: float = STOP_GRACE_S,
                    signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
    """Set `stop` on any of `signals`; exit with 128 + the signal's number if the process
    is still running `grace_s` later. Call from the main thread."""
    r, w = os.pipe()
    os.set_blocking(w, False)
    for sig in signals:
        signal.signal(sig, lambda *_: stop.set())
    signal.set_wakeup_fd(w, warn_on_full_buffer=False)

    def watch() -> None:
        got = os.read(r, 1)
        stop.set()
        time.sleep(grace_s)
        code = 128 + (got[0] if got else signal.SIGTERM)
        log.warning("still running %.1f s after signal %d: exiting now", grace_s, code - 128)
        logging.shutdown()
        os._exit(code)

    threading.Thread(target=watch, daemon=True, name="signal-watch").start()


def exit_now(code: int) -> NoReturn:
    """Flush stdout, stderr and the logs, then end the process with `code` at once."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    logging.shutdown()
    os._exit(code)


PARENT_ENV = "VAMPPI_PARENT"  # the launcher's pid, as it started the child


def die_with_parent(sig: int = signal.SIGKILL) -> bool:
    """Ask the kernel for `sig` when the parent process dies; False where it cannot
    (not Linux). Sends it at once if the parent (`$VAMPPI_PARENT` where the launcher set
    it) is already gone."""
    parent = int(os.environ.get(PARENT_ENV, os.getppid()))
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, sig, 0, 0, 0) != 0:
            return False
    except (OSError, AttributeError):
        return False
    if os.getppid() != parent:                       # died before the request took
        os.kill(os.getpid(), sig)
    return True


def when_orphaned(action: Callable[[], None], poll_s: float = 0.5) -> None:
    """Call `action` once, from a daemon thread, when this process's parent goes away (a
    launcher or an experiment killed outright, with no chance to stop its children)."""
    parent = int(os.environ.get(PARENT_ENV, os.getppid()))

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        action()

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()
