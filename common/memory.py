"""The process's allocator: large freed buffers kept instead of handed back to the OS.

glibc's malloc returns freed buffers above its (dynamic) mmap threshold to the OS and
trims the heap's top past its trim threshold, so every megabyte-sized buffer made anew
page-faults in again: a 1.3 MB map message took 6 ms to encode that way on this VM and
0.15 ms once its buffers stay (docs/bus.md); VA-MPPI's iteration at K = 800 spent about
7 ms of its 63 in page faults on XLA's buffers. Every
`vamppi` command and every bus session raises both thresholds once per process, at the
price of keeping up to a few hundred MB of freed memory mapped.
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger(__name__)

MALLOC_MMAP_THRESHOLD = 64 << 20
MALLOC_TRIM_THRESHOLD = 256 << 20
_malloc_tuned: bool | None = None


def keep_large_buffers() -> bool:
    """Let freed large buffers stay in the process (glibc only; a no-op elsewhere).
    Returns whether the allocator took the settings."""
    global _malloc_tuned
    if _malloc_tuned is None:
        try:
            import ctypes
            libc = ctypes.CDLL("libc.so.6")
            _malloc_tuned = (libc.mallopt(-3, MALLOC_MMAP_THRESHOLD) == 1    # M_MMAP_THRESHOLD
                             and libc.mallopt(-1, MALLOC_TRIM_THRESHOLD) == 1)  # M_TRIM_...
        except (OSError, AttributeError):
            _malloc_tuned = False
        log.debug("malloc thresholds raised: %s", _malloc_tuned)
    return _malloc_tuned


# ----------------------------------------------------------------------------- a GPU shared
GPU_HEADROOM = 0.9      # of a GPU's memory, what vamppi's processes on it may take together
# JAX processes of one pipeline on one machine: sensor, mapper, planner, and a planner
# swapping in beside the running one (vamppi swap) or standing by
PIPELINE_PROCESSES = 4


def device_share(processes: int) -> dict[str, str]:
    """The JAX settings by which `processes` processes share one GPU: none preallocates
    (JAX's default takes 75 % of the GPU's memory at start, so a second process would find
    none), each grows its pool on demand up to its share of `GPU_HEADROOM`. For the
    environment of each process, before it starts JAX; on a CPU they change nothing."""
    share = GPU_HEADROOM / max(1, processes)
    return {"XLA_PYTHON_CLIENT_PREALLOCATE": "false",
            "XLA_PYTHON_CLIENT_MEM_FRACTION": f"{share:.3f}"}


SHARED_ENV = "VAMPPI_GPU_SHARED"     # the settings vamppi chose (not the user), by name


def share_device(processes: int, environ: dict[str, str] | None = None) -> dict[str, str]:
    """`device_share(processes)` into `environ` (default os.environ): what the user set
    stays, what a vamppi parent chose for its own share (named in SHARED_ENV) is
    replaced; returns what it set."""
    env = os.environ if environ is None else environ
    ours = set(filter(None, env.get(SHARED_ENV, "").split(",")))
    set_ = {k: v for k, v in device_share(processes).items() if k in ours or k not in env}
    if set_:
        env.update(set_)
        env[SHARED_ENV] = ",".join(sorted(ours | set(set_)))
    return set_
