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
