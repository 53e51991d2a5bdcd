"""Scan preprocessing: mixed pixels and isolated returns dropped on the range image, range/height crop,
voxel downsample, optional outlier removal, PCA normals oriented to the sensor.

Pure numpy + scipy (no open3d), so the mapping core runs on machines that only have JAX.
All functions take and return sensor-frame arrays; the mapper moves them to the map frame.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.spatial import cKDTree

from jaxmap import range_image


CUBE_KNN_CAP = 16      # cube_knn normals: candidates per cell of the cube (in input order)
MIN_PLANE_POINTS = 3   # grid normals: neighbourhoods with fewer points face the sensor
DOWNSAMPLE_TIE = 1e-4   # voxel_downsample: distances to the mean within this many voxels count as equal


def crop(points_s: np.ndarray, min_range: float, max_range: float, min_z: float, max_z: float) -> np.ndarray:
    """Keep points with min_range <= |p| <= max_range and min_z <= z <= max_z.

    points_s: [N,3] float32, sensor frame -> [M,3] float32.
    """
    r = np.linalg.norm(points_s, axis=1)
    keep = (r >= min_range) & (r <= max_range) & (points_s[:, 2] >= min_z) & (points_s[:, 2] <= max_z)
    return points_s[keep]


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per voxel of side `voxel`: the point closest to the voxel's mean, the lowest index
    among those within `DOWNSAMPLE_TIE` * voxel of the closest (deterministic: a voxel of two points
    has two equidistant ones, and float rounding must not pick between them). The reference of
    `jaxmap.preprocess_device.voxel_keep`.

    points: [N,3] float32 -> [M,3] float32, M <= N, in input order; voxel <= 0 returns the input.
    """
    if voxel <= 0 or len(points) == 0:
        return points
    points = np.asarray(points, np.float32)
    q = np.floor(points / np.float32(voxel)).astype(np.int64)
    # Coordinates relative to the voxel's corner, as the device computes them: float32 keeps them exact
    # to ~1e-9 m however far the voxel is from the sensor.
    rel = (points - q.astype(np.float32) * np.float32(voxel)).astype(np.float64)
    q -= q.min(axis=0)
    span = q.max(axis=0) + 1
    # One int64 key per voxel: a 1-D unique is several times faster than np.unique(axis=0).
    keys = (q[:, 0] * span[1] + q[:, 1]) * span[2] + q[:, 2]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    means = np.stack([np.bincount(inverse, weights=rel[:, d], minlength=len(counts)) for d in range(3)], 1)
    means /= counts[:, None]
    d = np.linalg.norm(rel - means[inverse], axis=1)
    best = np.full(len(counts), np.inf)
    np.minimum.at(best, inverse, d)
    near = d <= best[inverse] + DOWNSAMPLE_TIE * voxel
    first = np.full(len(counts), len(points))
    idx = np.nonzero(near)[0]
    np.minimum.at(first, inverse[idx], idx)
    return points[np.sort(first)]


def remove_outliers(points_s: np.ndarray, k: int = 20, n_mad: float = 6.0) -> np.ndarray:
    """Statistical outlier removal for a spinning LiDAR (mixed pixels between a foreground and a
    background, stray returns): drop points whose mean distance to their k nearest neighbours,
    divided by their range (the beam spacing grows with range), exceeds the scan's median of that
    ratio by more than n_mad robust standard deviations (1.4826 MAD).

    points_s: [N,3] float32 sensor frame -> [M,3] float32, M <= N (order kept); n_mad <= 0 keeps all.
    """
    n = len(points_s)
    if n_mad <= 0 or n <= k:
        return points_s
    d, _ = cKDTree(points_s).query(points_s, k=k + 1, workers=-1)          # [N, k+1], self first
    spread = d[:, 1:].mean(axis=1) / np.maximum(np.linalg.norm(points_s, axis=1), 1.0)
    med = np.median(spread)
    mad = 1.4826 * np.median(np.abs(spread - med))
    return points_s[spread <= med + n_mad * max(mad, 1e-9)]


def estimate_normals(points_s: np.ndarray, k: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """PCA normals from the k nearest neighbours, oriented towards the sensor at the origin.

    points_s: [N,3] float32, sensor frame.
    Returns (normals [N,3] float32 unit, planarity [N] float32 in [0,1]: 1 - l_min / l_mid,
    low where the neighbourhood is degenerate, e.g. a single scan line).
    """
    n = len(points_s)
    if n == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0,), np.float32)
    k = int(min(k, n))
    tree = cKDTree(points_s)
    _, idx = tree.query(points_s, k=k, workers=-1)
    idx = idx.reshape(n, k)
    # Neighbourhoods relative to their query point keep float32 accurate (the scan spans ~100 m).
    nb = points_s[idx] - points_s[:, None, :]                # [N,k,3] float32
    c = nb - nb.mean(axis=1, keepdims=True)
    # The 6 distinct covariance entries as plain products: several times faster than an einsum.
    xx, yy, zz = (c[..., 0] ** 2).sum(1), (c[..., 1] ** 2).sum(1), (c[..., 2] ** 2).sum(1)
    xy, xz, yz = (c[..., 0] * c[..., 1]).sum(1), (c[..., 0] * c[..., 2]).sum(1), (c[..., 1] * c[..., 2]).sum(1)
    cov = np.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], axis=1).reshape(n, 3, 3) / k   # [N,3,3]
    evals, evecs = np.linalg.eigh(cov)                        # ascending
    normals = evecs[:, :, 0].astype(np.float64)
    # Orient towards the sensor (origin of the sensor frame): n . (0 - p) > 0.
    flip = np.einsum("ni,ni->n", normals, -points_s) < 0
    normals[flip] = -normals[flip]
    planarity = 1.0 - evals[:, 0] / np.maximum(evals[:, 1], 1e-12)
    return normals.astype(np.float32), planarity.astype(np.float32)


def key_span(max_range: float, cell: float) -> int:
    """Cells per axis of the packed cell keys of points within `max_range` (one cell of margin and one
    for the 2 x 2 x 2 cube's far side on each side)."""
    return 2 * int(math.ceil(max_range / cell)) + 4


def check_grid(max_range: float, cell: float) -> bool:
    """Whether cell keys of the finest level fit int32 (span^3 < 2^31)."""
    return key_span(max_range, cell) ** 3 < 2**31


def grid_normals(points_s: np.ndarray, cell: float, levels: int, k: int,
                 knn_cap: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """PCA normals over hashed-grid neighbourhoods, oriented towards the sensor at the origin: the
    reference (float64) of `jaxmap.preprocess_device.grid_normals`, whose docstring defines them
    (knn_cap > 0: the k nearest among the first knn_cap points of each cell of the chosen cube).

    points_s: [N,3] float32 sensor frame -> (normals [N,3] float32 unit, neighbours [N] int).
    """
    n = len(points_s)
    if n == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0,), np.int64)
    p = points_s.astype(np.float64)
    chosen_n = np.zeros(n, np.int64)
    chosen_cov = np.zeros((n, 3, 3))
    done = np.zeros(n, bool)
    cand = np.full((n, 8 * max(knn_cap, 1)), -1)
    for lv in range(levels):
        tot_n, tot_1, tot_2, level_cand = _cube_sums(points_s, p, cell * (1 << lv), knn_cap)
        mean = tot_1 / np.maximum(tot_n, 1)[:, None]
        cov = (tot_2 / np.maximum(tot_n, 1)[:, None]).reshape(n, 3, 3) - mean[:, :, None] * mean[:, None, :]
        take = ~done & ((tot_n >= k) | (lv == levels - 1))
        chosen_n[take], chosen_cov[take] = tot_n[take], cov[take]
        cand[take] = level_cand[take].reshape(int(take.sum()), cand.shape[1])
        done |= take
    if knn_cap > 0:
        # The k nearest of the candidates (the point itself among them), as scipy's kNN would pick them.
        d2 = np.where(cand >= 0, np.sum((p[np.maximum(cand, 0)] - p[:, None, :]) ** 2, -1), np.inf)
        nearest = np.argsort(d2, axis=1, kind="stable")[:, :k]
        use = np.isfinite(np.take_along_axis(d2, nearest, 1))
        x = p[np.take_along_axis(np.maximum(cand, 0), nearest, 1)] - p[:, None, :]
        chosen_n = use.sum(1)
        mean = (x * use[:, :, None]).sum(1) / np.maximum(chosen_n, 1)[:, None]
        c = (x - mean[:, None, :]) * use[:, :, None]
        chosen_cov = np.einsum("nki,nkj->nij", c, c) / np.maximum(chosen_n, 1)[:, None, None]
    _, evecs = np.linalg.eigh(chosen_cov)
    normals = evecs[:, :, 0]
    flip = np.einsum("ni,ni->n", normals, -p) < 0
    normals[flip] = -normals[flip]
    # Fewer than 3 points span no plane: the direction to the sensor is the only honest guess.
    few = chosen_n < MIN_PLANE_POINTS
    normals[few] = -p[few] / np.maximum(np.linalg.norm(p[few], axis=1, keepdims=True), 1e-9)
    return normals.astype(np.float32), chosen_n


def _cube_sums(points_s: np.ndarray, p: np.ndarray, c: float, knn_cap: int):
    """One level of grid_normals: the 2x2x2 cube of cells of size c nearest each point.

    points_s: [N,3] float32 sensor frame, p: the same as float64. Returns the cube's point count [N],
    coordinate sums [N,3] and outer-product sums [N,9] (float64), and candidates [N,8,max(knn_cap,1)]:
    the first knn_cap points (input order) of each of the cube's cells, -1 where there are none.
    """
    n = len(points_s)
    offsets = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)])
    # Cell coordinates as float32 computes them, so both sides put a point in the same cell.
    q = np.floor(points_s / np.float32(c)).astype(np.int64)
    cells, inverse = np.unique(q, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    cnt = np.bincount(inverse, minlength=len(cells)).astype(np.float64)
    s1 = np.stack([np.bincount(inverse, p[:, d], len(cells)) for d in range(3)], 1)
    s2 = np.stack([np.bincount(inverse, p[:, a] * p[:, b], len(cells)) for a in range(3) for b in range(3)], 1)
    index = {tuple(cc): i for i, cc in enumerate(cells)}
    base = np.floor(points_s / np.float32(c) - np.float32(0.5)).astype(np.int64)
    tot_n, tot_1, tot_2 = np.zeros(n), np.zeros((n, 3)), np.zeros((n, 9))
    members = np.argsort(inverse, kind="stable")              # each cell's points, in input order
    first = np.searchsorted(inverse[members], np.arange(len(cells)))
    level_cand = np.full((n, 8, max(knn_cap, 1)), -1)
    for oi, o in enumerate(offsets):
        j = np.array([index.get(tuple(cc), -1) for cc in base + o])
        hit = j >= 0
        tot_n[hit] += cnt[j[hit]]
        tot_1[hit] += s1[j[hit]]
        tot_2[hit] += s2[j[hit]]
        for i in range(knn_cap):
            ok = hit & (i < cnt[np.maximum(j, 0)])
            level_cand[ok, oi, i] = members[first[j[ok]] + i]
    return tot_n, tot_1, tot_2, level_cand


def normals_of(points_s: np.ndarray, cfg, raw_s: np.ndarray | None = None) -> np.ndarray:
    """Normals [M,3] float32 of sensor-frame points [M,3] by `cfg.normals` (a PreprocessConfig); raw_s
    [N, 3]: the raw scan they were taken from (range_image normals: its range image)."""
    if cfg.normals in ("grid", "cube_knn"):
        cap = CUBE_KNN_CAP if cfg.normals == "cube_knn" else 0
        return grid_normals(points_s, cfg.normal_cell_m, cfg.normal_levels, cfg.normal_knn, cap)[0]
    if cfg.normals == "range_image":
        return range_image_normals(points_s, points_s if raw_s is None else raw_s, layout_of(cfg, raw_s),
                                   cfg.normal_knn)[0]
    return estimate_normals(points_s, cfg.normal_knn)[0]


RANGE_WINDOW = (2, 4)  # range_image normals: a point's window of pixels, half-sizes (rows, columns)


def window_offsets() -> np.ndarray:
    """[K, 2] (row, column) offsets of the pixels of a point's window (`RANGE_WINDOW`), its own first."""
    hr, hc = RANGE_WINDOW
    off = [(dr, dc) for dr in range(-hr, hr + 1) for dc in range(-hc, hc + 1)]
    off.sort(key=lambda o: (o != (0, 0)))
    return np.array(off, np.int32)


def nearest_return_image(raw_s: np.ndarray, layout: range_image.Layout) -> np.ndarray:
    """[rows * cols, 3] float64: the nearest return of each pixel of the raw scan raw_s [N, 3] (sensor
    frame), NaN where the pixel has none (`range_image.min_range_image`'s returns themselves)."""
    row, col, rng, inside = range_image.pixels(np.asarray(raw_s, np.float32), layout)
    ok = inside & np.isfinite(rng) & (rng > 0)
    flat = row[ok].astype(np.int64) * layout.cols + col[ok]
    order = np.lexsort((rng[ok], flat))
    f = flat[order]
    first = np.r_[True, f[1:] != f[:-1]] if len(f) else np.zeros(0, bool)
    xyz = np.full((layout.rows * layout.cols, 3), np.nan)
    xyz[f[first]] = np.asarray(raw_s, np.float64)[ok][order][first]
    return xyz


def range_image_normals(points_s: np.ndarray, raw_s: np.ndarray, layout: range_image.Layout,
                        k: int) -> tuple[np.ndarray, np.ndarray]:
    """PCA normals from the scan's own range-image neighbours (`preprocess.normals: range_image`): a
    spinning LiDAR's organised scan gives each point its neighbours for free, the nearest returns of the
    pixels around its pixel (`RANGE_WINDOW`, `nearest_return_image`; columns wrap), of which the k
    nearest in space make its plane; oriented towards the sensor, the direction to the sensor where
    fewer than 3 span none. The reference (float64) of `jaxmap.preprocess_device.range_image_normals`.

    points_s [M, 3] float32 (the preprocessed points), raw_s [N, 3] the raw scan they come from, sensor
    frame -> (normals [M, 3] float32 unit, neighbours [M] int)."""
    m = len(points_s)
    if m == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0,), np.int64)
    xyz = nearest_return_image(raw_s, layout)
    p = np.asarray(points_s, np.float64)
    row, col, _, _ = range_image.pixels(np.asarray(points_s, np.float32), layout)
    off = window_offsets()
    rr, cc = row[:, None] + off[:, 0], (col[:, None] + off[:, 1]) % layout.cols
    inside = (rr >= 0) & (rr < layout.rows)
    cand = xyz[np.clip(rr, 0, layout.rows - 1) * layout.cols + cc]              # [M, K, 3]
    rel = cand - p[:, None, :]
    d2 = np.where(inside & np.isfinite(rel[..., 0]), np.sum(np.nan_to_num(rel) ** 2, -1), np.inf)
    nearest = np.argsort(d2, axis=1, kind="stable")[:, :k]
    use = np.isfinite(np.take_along_axis(d2, nearest, 1))
    x = np.nan_to_num(np.take_along_axis(rel, nearest[:, :, None], 1)) * use[:, :, None]
    cnt = use.sum(1)
    mean = x.sum(1) / np.maximum(cnt, 1)[:, None]
    c = (x - mean[:, None, :]) * use[:, :, None]
    cov = np.einsum("nki,nkj->nij", c, c) / np.maximum(cnt, 1)[:, None, None]
    normals = np.linalg.eigh(cov)[1][:, :, 0]
    flip = np.einsum("ni,ni->n", normals, -p) < 0
    normals[flip] = -normals[flip]
    few = cnt < MIN_PLANE_POINTS
    normals[few] = -p[few] / np.maximum(np.linalg.norm(p[few], axis=1, keepdims=True), 1e-9)
    return normals.astype(np.float32), cnt


def layout_of(cfg, points_s: np.ndarray | None = None) -> range_image.Layout | None:
    """The range-image layout a PreprocessConfig sets (`image_rows` > 0: a beam table `image_beams_deg`, else
    a uniform grid), else the one read off the raw scan `points_s` [N, 3] (sensor frame), else None."""
    if cfg.image_rows > 0:
        if cfg.image_beams_deg:
            return range_image.beam_layout(np.radians(cfg.image_beams_deg), cfg.image_cols,
                                           math.radians(cfg.image_az0_deg))
        return range_image.Layout(rows=cfg.image_rows, cols=cfg.image_cols, elev0=math.radians(cfg.image_elev0_deg),
                                  elev_step=math.radians(cfg.image_elev_step_deg), az0=math.radians(cfg.image_az0_deg))
    if points_s is None:
        return None
    return layout_of(with_layout(cfg, points_s))


def with_layout(cfg, points_s: np.ndarray):
    """cfg (a PreprocessConfig) with its range-image layout fixed: read off the raw scan points_s [N, 3]
    when `image_rows` is 0 (the first scan of a run; every later scan then uses the same image). A beam
    table given in the config (`image_beams_deg`) is kept: only the columns are read off the scan."""
    if cfg.image_rows > 0:
        return cfg
    lay = range_image.estimate_layout(points_s)
    if cfg.image_beams_deg:
        lay = range_image.beam_layout(np.radians(cfg.image_beams_deg), lay.cols, lay.az0)
    # the beam table in degrees, rounded well below a beam's spread (1e-6 deg): the layout reads back the same
    return dataclasses.replace(cfg, image_rows=lay.rows, image_cols=lay.cols,
                               image_elev0_deg=math.degrees(lay.elev0), image_elev_step_deg=math.degrees(lay.elev_step),
                               image_az0_deg=math.degrees(lay.az0),
                               image_beams_deg=tuple(round(math.degrees(b), 6) for b in lay.beams))


def drop_veil(points_s: np.ndarray, cfg, image: np.ndarray | None = None) -> np.ndarray:
    """The raw scan [N, 3] (sensor frame) without its mixed pixels and isolated returns
    (`range_image.veil_keep` with tolerance `veil_m`; 0 = all kept). Runs before the crop: a return's
    neighbours in the range image must all be there. image: the scan's range image in cfg's layout, when
    the caller has built it."""
    if cfg.veil_m <= 0 or len(points_s) == 0:
        return points_s
    return points_s[range_image.veil_keep(points_s, layout_of(cfg, points_s), cfg.veil_m, image=image)]


def preprocess_scan(points_s: np.ndarray, cfg) -> tuple[np.ndarray, np.ndarray]:
    """Drop mixed pixels, crop, downsample and estimate normals. cfg: a PreprocessConfig.

    points_s: [N,3] float32 sensor frame -> (points [M,3] float32, normals [M,3] float32), sensor frame.
    """
    return preprocess_points(drop_veil(points_s, cfg), cfg)


def preprocess_points(points_s: np.ndarray, cfg) -> tuple[np.ndarray, np.ndarray]:
    """`preprocess_scan` after the veil filter: crop, downsample, outliers, normals."""
    pts = crop(points_s, cfg.min_range_m, cfg.max_range_m, cfg.min_z_m, cfg.max_z_m)
    pts = voxel_downsample(pts, cfg.vox_down_m)
    if cfg.outlier_mad > 0:
        pts = remove_outliers(pts, cfg.normal_knn, cfg.outlier_mad)
    return pts.astype(np.float32), normals_of(pts, cfg, points_s)
