"""Host memory of this process: resident size now and at its peak, and giving freed heap back.

XLA's CPU compiler takes about a gigabyte of heap while it compiles the frame program and frees it
afterwards, but glibc keeps freed heap mapped, so the process would hold it for the whole drive;
`trim()` hands it back to the operating system (a no-op where there is no glibc).
"""
from __future__ import annotations

import ctypes
import os
import resource


def rss_mb() -> float:
    """Resident memory of this process now (MB), from /proc (0.0 where there is none)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB), from getrusage."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def trim() -> None:
    """Return freed heap memory to the operating system (glibc's malloc_trim)."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def limit_arenas(n: int = 2) -> None:
    """glibc gives every thread that allocates its own malloc arena (up to 8 per core); XLA's worker
    threads, the prefetch and checkpoint threads then leave ~600 MB of freed-but-kept memory spread
    over arenas in a mapping run. Two arenas keep the peak RSS of `jaxmap map` on the city near 1 GB
    instead of 2.7 GB (same speed). Same as MALLOC_ARENA_MAX=2; a no-op off glibc."""
    if "MALLOC_ARENA_MAX" in os.environ:
        return
    try:
        ctypes.CDLL("libc.so.6").mallopt(-8, n)  # M_ARENA_MAX
    except (OSError, AttributeError):
        pass
