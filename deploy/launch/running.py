"""Finding the running pipeline: each `vamppi up` announces its router on this machine.

`vamppi up` writes `<runtime dir>/up-<pid>.json` (its router's endpoint, vehicle,
certificates, start time) while it runs and removes it when it ends; the runtime dir is
`$XDG_RUNTIME_DIR/vamppi`, else `/tmp/vamppi-<uid>` (mode 0700). A bus command given no
`--connect` (health, record, replay, view, swap) connects to the newest live one
(`locate`); a file whose process is gone is ignored and removed.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any


def runtime_dir() -> Path:
    base = os.environ.get("XDG_RUNTIME_DIR")
    return Path(base) / "vamppi" if base else Path(tempfile.gettempdir()) / f"vamppi-{os.getuid()}"


@dataclass(frozen=True)
class Running:
    """One live `vamppi up`."""
    pid: int
    endpoint: str
    vehicle: str
    certs: str
    started: float


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:           # another user's: alive, not ours to use
        return True
    return True


@contextlib.contextmanager
def announce(endpoint: str, vehicle: str, certs: str) -> Iterator[Path]:
    """While the block runs, this process's router is findable (`locate`)."""
    d = runtime_dir()
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    path = d / f"up-{os.getpid()}.json"
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({"pid": os.getpid(), "endpoint": endpoint, "vehicle": vehicle,
                               "certs": certs, "started": time.time()}))
    tmp.replace(path)
    try:
        yield path
    finally:
        path.unlink(missing_ok=True)


def running(vehicle: str | None = None) -> list[Running]:
    """The live `vamppi up`s of this machine (of `vehicle` if given), newest first."""
    out = []
    d = runtime_dir()
    for path in d.glob("up-*.json") if d.is_dir() else ():
        try:
            r = Running(**json.loads(path.read_text()))
        except (OSError, ValueError, TypeError):
            continue                  # being written, or not ours
        if not _alive(r.pid):
            path.unlink(missing_ok=True)
            continue
        if vehicle is None or r.vehicle == vehicle:
            out.append(r)
    return sorted(out, key=lambda r: -r.started)


def locate(vehicle: str) -> Running | None:
    """The newest live `vamppi up` of `vehicle` on this machine, or None."""
    found = running(vehicle)
    return found[0] if found else None


def bus_overrides(r: Running) -> dict[str, Any]:
    """The bus settings of a client of `r`'s router."""
    return {"bus.mode": "client", "bus.connect": (r.endpoint,), "bus.listen": (),
            **({"bus.certs": r.certs} if r.certs else {})}
