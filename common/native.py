"""Building the project's native CPU kernels: one shared library per service.

A `Library` is compiled from its C++ sources with the system's compiler (`$CXX`, else
g++) against the XLA FFI headers that jaxlib ships, once per source, jaxlib version and
CPU model, next to its sources, by `make` (`python -m services.build_native`, at install and
before every `make test` and `make demo`: a no-op when nothing changed). Loading never
builds: a library missing for the current sources is unavailable (its service uses the JAX
form under `auto`, refuses under `native`). Nothing is downloaded.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path

log = logging.getLogger(__name__)

# -march=native: a library is built on the machine that runs it (the digest names the CPU);
# -ffp-contract=off: no fused multiply-adds, so the kernels' float32 arithmetic is that of
# their JAX forms; -fno-trapping-math: lets floor() be vector code, results unchanged
FLAGS = ("-O3", "-march=native", "-std=c++17", "-shared", "-fPIC", "-pthread",
         "-fopenmp-simd", "-ffp-contract=off", "-fno-trapping-math", "-fno-math-errno")


class NativeUnavailable(RuntimeError):
    """A kernel could not be built or loaded (no compiler, no headers, ...)."""


def cpu_model() -> str:
    """The CPU model (a -march=native build runs only on its own kind)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("model name", "Model", "CPU part")):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.machine()


@dataclass(frozen=True)
class Library:
    """C++ `sources` (with the `headers` they include) built into `<dir>/<stem>-<digest>.so`."""
    sources: tuple[Path, ...]
    headers: tuple[Path, ...] = ()
    stem: str = "_native"

    def path(self) -> Path:
        """Where the library for these sources, this jaxlib and this CPU lives."""
        import jaxlib
        digest = hashlib.sha256(b"".join(s.read_bytes() for s in self.sources + self.headers)
                                + jaxlib.__version__.encode() + " ".join(FLAGS).encode()
                                + cpu_model().encode()).hexdigest()[:12]
        return self.sources[0].with_name(f"{self.stem}-{digest}.so")

    def build(self) -> Path:
        """Compile the library if it is not there (atomically: concurrent builders are safe)."""
        import jax
        out = self.path()
        if out.exists():
            return out
        cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++")
        if not cxx:
            raise NativeUnavailable("no C++ compiler (set CXX or install g++)")
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
        os.close(fd)
        cmd = [cxx, *FLAGS, f"-I{jax.ffi.include_dir()}", *map(str, self.sources), "-o", tmp]
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
            if r.returncode != 0:
                raise NativeUnavailable(f"{' '.join(cmd)} failed:\n{r.stderr[-4000:]}")
            os.replace(tmp, out)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        for old in out.parent.glob(f"{self.stem}-*.so"):
            if old != out:                                  # earlier sources' builds
                old.unlink(missing_ok=True)
        return out

    def load(self) -> ctypes.CDLL:
        """The built library, loaded once per process; NativeUnavailable if it is not built."""
        return _load(self)


@cache
def _load(lib: Library) -> ctypes.CDLL:
    path = lib.path()
    if not path.exists():        # built at install, never on first use (nor while tracing)
        raise NativeUnavailable(f"{path.name} is not built for these sources: run `make` "
                                "(or python -m services.build_native)")
    return ctypes.cdll.LoadLibrary(str(path))


@cache
def loads(load: Callable[[], object], what: str) -> bool:
    """Whether `load` (a library's loader) succeeds here; tried once per process, a failure
    logged once."""
    try:
        load()
    except (NativeUnavailable, OSError) as e:
        log.warning("%s unavailable, using the JAX form: %s", what, e)
        return False
    return True


def use_native(kernel: str, load: Callable[[], object], what: str) -> bool:
    """A `*_kernel` setting resolved: `jax` no, `native` yes (the loader raises where it cannot
    load), `auto` where it loads."""
    if kernel == "jax":
        return False
    if kernel == "native":
        load()
        return True
    return loads(load, what)
