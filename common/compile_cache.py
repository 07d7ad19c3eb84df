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

import hashlib
import logging
import os
import sys
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any

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


# -- traced programs kept on disk (jax.export) ------------------------------------------
#
# The compilation cache skips XLA's compile, not JAX's tracing and lowering: for the
# planner's solver those took about 3.7 s of every process start (trace 2.7 s, lower
# 1.0 s, loading the compiled program 1.1 s; a 2-core CPU). `Traced` keeps the lowered
# program (jax.export's serialized StableHLO) beside the compiled ones, so a later
# process deserializes and compiles (from the cache) without tracing.

SOURCES = ("common", "services")          # the packages whose code a traced program is


@lru_cache(maxsize=1)
def code_digest() -> str:
    """A digest of everything a traced program may have been built from: every Python,
    TOML and C++ source and built library under `SOURCES`, JAX's version and this
    interpreter's. Any change to any of them is a new key."""
    import jax
    import jaxlib
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256(f"{jax.__version__} {jaxlib.__version__} {sys.version}".encode())
    for pkg in SOURCES:
        for f in sorted((root / pkg).rglob("*")):
            if f.suffix in (".py", ".toml", ".cc", ".h", ".so") and f.is_file():
                h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()


class Traced:
    """`fn` (jitted, positional array arguments) traced once per argument signature per
    code digest, on disk: the first process exports it into `cache_dir()/traced`, the
    next ones deserialize it. Either way the program runs as the exported call, jitted with
    its arguments pinned (`_pinned`), so every process runs the same compiled program (bit
    for bit the one `fn` compiles to: tests/test_compile_cache.py). `salt`: what `fn`
    bakes in besides its arguments (its static parameters, the machine facts it reads
    while tracing); `custom_calls`: the FFI targets it may call, registered by whoever
    computed `salt`. With the cache off, `fn` itself runs. A file that does not
    deserialize is traced again, with a warning."""

    def __init__(self, name: str, fn: Callable, salt: str, custom_calls: tuple[str, ...] = ()):
        self.name, self.fn, self.salt, self.custom_calls = name, fn, salt, custom_calls
        self._calls: dict[Any, Callable] = {}

    def __call__(self, *args: Any) -> Any:
        import jax
        leaves, tree = jax.tree_util.tree_flatten(args)
        sig = (tree, tuple((tuple(x.shape), str(x.dtype)) for x in leaves))
        call = self._calls.get(sig)
        if call is None:
            call = self._calls[sig] = self._program(args, sig)
        return call(*args)

    def _program(self, args: tuple, sig: Any) -> Callable:
        import jax
        from jax import export
        directory = cache_dir()
        if directory is None:
            return self.fn
        backend = jax.devices()[0]
        key = hashlib.sha256(f"{self.salt}\0{sig}\0{backend.platform} {backend.device_kind}"
                             .encode()).hexdigest()[:32]
        path = directory / "traced" / code_digest()[:24] / f"{self.name}-{key}.bin"
        if path.is_file():
            try:
                return _pinned(export.deserialize(bytearray(path.read_bytes())))
            except Exception as exc:                       # truncated, corrupt: trace anew
                log.warning("%s does not deserialize (%s): tracing again", path, exc)
        checks = [export.DisabledSafetyCheck.custom_call(c) for c in self.custom_calls]
        exported = export.export(self.fn, disabled_checks=checks)(*args)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
            tmp.write_bytes(exported.serialize())
            os.replace(tmp, path)
            _prune(path.parent.parent, path.parent)
        except OSError as exc:
            log.warning("cannot keep the traced %s in %s (%s)", self.name, path.parent, exc)
        return _pinned(exported)


def _pinned(exported: Any) -> Callable:
    """`exported` jitted with every argument and result on the default device. Left
    unspecified, jit lowers anew for arguments a previous call committed to it (the
    state a solve returns), and that second program compiles for seconds, in the loop."""
    import jax
    on = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    return jax.jit(exported.call, in_shardings=on, out_shardings=on)


KEEP_CODES = 4                    # the traced programs of this many code digests are kept


def _prune(traced: Path, current: Path) -> None:
    """Remove the traced programs of all but the `KEEP_CODES` most recently written code
    digests (the current one always kept): each edit of the sources is a new digest."""
    import shutil
    others = sorted((d for d in traced.iterdir() if d.is_dir() and d != current),
                    key=lambda d: d.stat().st_mtime, reverse=True)
    for d in others[KEEP_CODES - 1:]:
        shutil.rmtree(d, ignore_errors=True)
