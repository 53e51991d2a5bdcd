"""What a run keeps of each frame: the records its map returns (one dict per frame, in `timings`), and
their medians (timing.json's summary).

An N3 map's record is typed in its own module (`jaxmap.n3.mapper.N3Record`); here only what every run
does with the records."""
from __future__ import annotations

from typing import Iterable

import numpy as np


def medians(timings: list[dict], keys: Iterable[str], skip_first: int = 1, p95: Iterable[str] = ()) -> dict:
    """`median_<key>` (and `p95_<key>` for the keys in `p95`) over the records after the first `skip_first`
    (compiling) frames, and the count of frames that had no point to map (`empty_frames`: empty scans, or
    all cropped away)."""
    rows = timings[skip_first:] if len(timings) > skip_first else timings
    out = {}
    for name, stat, ks in (("median", np.median, keys), ("p95", lambda v: np.percentile(v, 95), p95)):
        for k in ks:
            vals = [r[k] for r in rows if k in r]
            out[f"{name}_{k}"] = float(stat(vals)) if vals else float("nan")
    out["empty_frames"] = int(sum(1 for r in timings if r.get("points", 1) == 0))
    return out
