"""The visibility-aware variance update as a native CPU kernel (va_counts.cc, XLA FFI).

`planner.va_kernel` chooses: `jax` (the vectorised form of visibility.py, every
backend), `native` (this kernel; a CPU backend only) or `auto` (native on a CPU
when it builds, else jax). Both compute the same variances from the same float32
cells; tests/test_visibility.py checks each against the dense float64 reference.

The library is compiled from its source with the system's C++ compiler
(`$CXX`, else g++) against the XLA FFI headers that jaxlib ships, once per
source and jaxlib version, next to the source; `make` builds it at install
(`python -m services.planner.native`), and the first use builds it if it is
missing. Nothing is downloaded.
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
from functools import lru_cache
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("va_counts.cc")
TARGET = "vamppi_va_counts"
# -march=native: the library is built on the machine that runs it (the digest names the
# CPU); -ffp-contract=off: no fused multiply-adds, so the cells are JAX's float32 cells;
# -fno-trapping-math: lets the cell loop (floor) be vector code, results unchanged
FLAGS = ("-O3", "-march=native", "-std=c++17", "-shared", "-fPIC", "-pthread",
         "-fopenmp-simd", "-ffp-contract=off", "-fno-trapping-math")


class NativeUnavailable(RuntimeError):
    """The kernel could not be built or loaded (no compiler, no headers, ...)."""


def _cpu() -> str:
    """The CPU model (a -march=native build runs only on its own kind)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("model name", "Model", "CPU part")):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.machine()


def library_path() -> Path:
    """Where the library for this source and this jaxlib lives."""
    import jaxlib
    digest = hashlib.sha256(SOURCE.read_bytes() + jaxlib.__version__.encode()
                            + " ".join(FLAGS).encode() + _cpu().encode()).hexdigest()[:12]
    return SOURCE.with_name(f"_va_counts-{digest}.so")


def build() -> Path:
    """Compile the library if it is not there (atomically: concurrent builders are safe)."""
    out = library_path()
    if out.exists():
        return out
    cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++")
    if not cxx:
        raise NativeUnavailable("no C++ compiler (set CXX or install g++)")
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    cmd = [cxx, *FLAGS, f"-I{jax.ffi.include_dir()}", str(SOURCE), "-o", tmp]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        if r.returncode != 0:
            raise NativeUnavailable(f"{' '.join(cmd)} failed:\n{r.stderr[-4000:]}")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    for old in out.parent.glob("_va_counts-*.so"):         # earlier sources' builds
        if old != out:
            old.unlink(missing_ok=True)
    return out


@lru_cache(maxsize=1)
def _register() -> str:
    lib = ctypes.cdll.LoadLibrary(str(build()))
    jax.ffi.register_ffi_target(TARGET, jax.ffi.pycapsule(lib.VaCounts), platform="cpu")
    return TARGET


def available() -> bool:
    """Whether the kernel can run here: a CPU backend and a library that builds and loads."""
    if jax.default_backend() != "cpu":
        return False
    try:
        _register()
    except (NativeUnavailable, OSError) as e:
        log.warning("native visibility kernel unavailable, using the JAX form: %s", e)
        return False
    return True


def use_native(kernel: str) -> bool:
    """`planner.va_kernel` resolved on this machine."""
    if kernel == "jax":
        return False
    if kernel == "native":
        if jax.default_backend() != "cpu":
            raise NativeUnavailable(f"planner.va_kernel = native needs a CPU backend, "
                                    f"this one is {jax.default_backend()}")
        _register()
        return True
    return available()


def threads(requested: int) -> int:
    """`planner.va_threads`: 0 = the cores this process may run on."""
    if requested > 0:
        return requested
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


def va_variance(mean: Any, variance: Any, origin: Any, states: Any, skip: Any, rows: Any,
                cols: Any,
                offsets: tuple[tuple[int, int], ...], grid: np.ndarray, weights: np.ndarray, *,
                resolution: float, height: float, gamma: float, rays: int, points: int,
                lag: int, pad: int, n_threads: int) -> Any:
    """The variance (K, T, Q * P) each trajectory meets at its query cells: the map's
    variance times exp(-gamma C), C the splatted counts; skip (K, T): how many of each
    ray's nearest points do not count (they still block); see va_counts.cc."""
    k, t, p = rows.shape
    out = jax.ShapeDtypeStruct((k, t, weights.shape[1] * p), jnp.float32)
    call = jax.ffi.ffi_call(_register(), out, vmap_method="sequential")
    return call(jnp.asarray(mean, jnp.float32), jnp.asarray(variance, jnp.float32),
                jnp.asarray(origin, jnp.float32), jnp.asarray(states, jnp.float32),
                jnp.asarray(skip, jnp.int32), rows.astype(jnp.int32), cols.astype(jnp.int32),
                jnp.asarray(offsets, jnp.int32), jnp.asarray(grid, jnp.float32),
                jnp.asarray(weights, jnp.float32),
                resolution=np.float32(resolution), height=np.float32(height),
                gamma=np.float32(gamma), rays=np.int64(rays), points=np.int64(points),
                lag=np.int64(lag), pad=np.int64(pad), threads=np.int64(n_threads))
