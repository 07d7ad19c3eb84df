"""JAX's persistent compilation cache, for every vamppi process.

Compiling the planner's solver takes 5 to 7 s on a 2-core CPU (docs/running.md),
the sensor's and the mapper's programs about a second each; every service start, planner
hot swap, experiment, replay and test process paid it again. JAX can keep
compiled XLA programs on disk, keyed by the program, its compile options, the
JAX and jaxlib versions and the device, so a stale entry is never used: a later
process compiling the same program loads it in under a second.

    VAMPPI_JAX_CACHE   the directory (default $XDG_CACHE_HOME/vamppi/jax, else
                       ~/.cache/vamppi/jax); "off" or "0" turns the cache off.

Only programs that took at least `MIN_COMPILE_S` to compile are stored.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

ENV = "VAMPPI_JAX_CACHE"
MIN_COMPILE_S = 0.25
log = logging.getLogger(__name__)


def cache_dir(environ: dict[str, str] | None = None) -> Path | None:
    """Where the cache lives, or None when it is turned off."""
    env = os.environ if environ is None else environ
    value = env.get(ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "0", "off", "false", "no") else Path(value)
    base = env.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "vamppi" / "jax"


def enable() -> Path | None:
    """Point JAX's persistent cache at `cache_dir()`; returns it (None: off).

    Through JAX's own environment variables, so the processes this one starts
    (the services of `vamppi up`) use it too and JAX need not be imported here;
    if it already is, its configuration is updated as well. Call before the
    first compilation. A directory that cannot be created leaves the cache off
    with a warning (compiling still works, only slower)."""
    path = cache_dir()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        log.warning("JAX compilation cache off: cannot create %s (%s)", path, exc)
        return None
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(path)
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = str(MIN_COMPILE_S)
    if "jax" in sys.modules:
        import jax
        jax.config.update("jax_compilation_cache_dir", str(path))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
    return path
