"""The beam tables of the synthetic LiDARs: each beam's elevation, as a real spinning sensor fires them.

    elevations_deg("uniform", 64)        # 64 beams evenly spaced from -25 to +2 deg (the suite's first sensor)
    elevations_deg("hdl64", seed=3)      # KITTI's Velodyne HDL-64E: two blocks, per-beam calibration jitter
    elevations_deg("vlp32")              # a Velodyne VLP-32C: dense near the horizon, sparse below

Real sensors rarely space their beams evenly, and the range image that the veil and the free-space
evidence read (`jaxmap.range_image`) must follow the sensor's own beams: the suite scans with these
tables so that a rule tuned on even beams cannot pass for one that works on a real sensor.

- uniform: `beams` elevations evenly spaced over UNIFORM_DEG (the layout of `jaxmap synth` until now).
- hdl64: the HDL-64E S2 of the KITTI car: an upper block of 32 lasers from +2.0 to -8.33 deg (~0.33 deg
  apart) and a lower block of 32 from -8.83 to -24.9 deg (~0.52 deg apart); every laser is off its nominal
  elevation by N(0, HDL64_JITTER_DEG) (a calibrated unit's table is not regular), fixed by the seed.
- vlp32: the VLP-32C's published table (-25 to +15 deg; 0.33 deg apart around the horizon, 3.5 to
  9.4 deg apart at the bottom): a sensor whose mean spacing (1.29 deg) is wrong almost everywhere.
"""
from __future__ import annotations

import numpy as np

UNIFORM_DEG = (-25.0, 2.0)
HDL64_UPPER_DEG = (2.0, -8.33)
HDL64_LOWER_DEG = (-8.83, -24.9)
HDL64_JITTER_DEG = 0.03
VLP32C_DEG = (-25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0,
              -2.667, -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333,
              1.667, 2.333, 3.333, 4.667, 7.0, 10.333, 15.0)
PATTERNS = ("uniform", "hdl64", "vlp32")
# the azimuth steps a turn of each named sensor takes (KITTI's scans hold ~2000 returns a beam, de-skewed; the
# suite keeps the default city's 1024 so that a run costs what the others do; the VLP-32C at 10 Hz: 0.2 deg)
AZIMUTH_STEPS = {"hdl64": 1024, "vlp32": 1800}


def parse(spec) -> tuple[str, int | None]:
    """(pattern, beams or None) of a `--beams` value: a count (uniform beams) or a pattern's name."""
    if spec is None:
        return "uniform", None
    if isinstance(spec, (int, np.integer)):
        return "uniform", int(spec)
    s = str(spec).strip().lower()
    if s.isdigit():
        return "uniform", int(s)
    if s in PATTERNS:
        return s, None
    raise ValueError(f"unknown beam pattern {spec!r}: a number of uniform beams, or one of {', '.join(PATTERNS)}")


def elevations_deg(pattern: str = "uniform", beams: int | None = None, seed: int = 0) -> np.ndarray:
    """[B] float64 beam elevations (degrees, ascending) of a pattern; beams: the count (uniform only: the
    named sensors have their own)."""
    if pattern == "uniform":
        if not beams or beams < 1:
            raise ValueError("uniform beams need a count >= 1")
        return np.linspace(UNIFORM_DEG[0], UNIFORM_DEG[1], int(beams))
    if beams not in (None, len_of(pattern)):
        raise ValueError(f"the {pattern} sensor has {len_of(pattern)} beams, not {beams}")
    if pattern == "hdl64":
        nominal = np.r_[np.linspace(*HDL64_UPPER_DEG, 32), np.linspace(*HDL64_LOWER_DEG, 32)]
        jitter = np.random.default_rng(np.random.SeedSequence([seed, 640])).normal(0.0, HDL64_JITTER_DEG, 64)
        return np.sort(nominal + jitter)
    if pattern == "vlp32":
        return np.asarray(VLP32C_DEG, np.float64)
    raise ValueError(f"unknown beam pattern {pattern!r}; choose from {', '.join(PATTERNS)}")


def len_of(pattern: str) -> int:
    return {"hdl64": 64, "vlp32": 32}[pattern]
