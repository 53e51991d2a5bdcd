"""Padded sizes: the few array sizes that inputs and tables are padded or grown to.

Every distinct array size compiles its own program, so sizes come from a small ladder instead of
the data: a scan is padded to a multiple of `BUCKET_STEP` (`bucket_for`), map tables get power-of-two
slot counts (`pow2`) and row counts in steps of `ROW_STEP` (`round_up`), and batches of query points
are padded to powers of two (`pow2_bucket`). `quarter_bucket` is the finer ladder (2^k times 1, 1.25,
1.5, 1.75) for inputs whose size varies a lot from call to call.
"""
from __future__ import annotations

import math

import numpy as np

BUCKET_STEP = 4096  # scan sizes are padded to multiples of this (static shapes: one compile)
ROW_STEP = 1 << 14  # initial table rows are multiples of this


def pow2(n: float) -> int:
    """Smallest power of two >= int(n), at least 2 (hash-table slot counts)."""
    return 1 << max(int(n) - 1, 1).bit_length()


def round_up(n: float, step: int = ROW_STEP) -> int:
    """n (at least 1) rounded up to a multiple of step."""
    return int(math.ceil(max(n, 1) / step) * step)


def bucket_for(n: int, current: int = 0) -> int:
    """Padded scan size: the current bucket while n fits (an empty scan fits any), else 1.25 n rounded
    up to BUCKET_STEP (a new bucket recompiles the frame program, so it leaves room for the next scans)."""
    if current and n <= current:
        return current
    return int(np.ceil(max(1.25 * n, 1) / BUCKET_STEP) * BUCKET_STEP)


def pow2_bucket(n: int, smallest: int, cap: int) -> int:
    """Smallest power of two >= n, at least `smallest` (a power of two), at most cap (cap itself if
    n > cap): log2(cap / smallest) + 1 shapes at most."""
    b = smallest
    while b < n:
        b <<= 1
    return min(b, cap)


def quarter_bucket(n: int, smallest: int) -> int:
    """Padded size: 2^k times 1, 1.25, 1.5 or 1.75 (>= smallest, a power of two >= 8), so that inputs of
    any size share a handful of compiled shapes and padding wastes at most 25 % of the work."""
    n = max(int(n), smallest)
    k = 1 << (n.bit_length() - 1)
    for f in (4, 5, 6, 7, 8):
        if n <= k * f // 4:
            return k * f // 4
    raise AssertionError(n)
