"""Scan preprocessing as pure JAX, for the frame program: crop, voxel downsample and grid normals on
padded arrays, so a frame is one compiled program from the raw scan to the trained map.

`jaxmap.preprocess` holds the numpy / scipy reference of the same steps (the tests compare them).
Every function takes sensor-frame points [N, 3] float32 with a validity mask [N] bool (padding
rows are invalid) and keeps static shapes: points are selected by masks, never removed.

Grid normals (`preprocess.normals: grid`): the neighbourhood of a point is the cube of 2 x 2 x 2
cells of side `c` around it (the cells of `floor(p / c - 1/2) + {0, 1}^3`, so the point is at least
c / 2 from the cube's faces), at the finest of `levels` cell sizes c = cell, 2 cell, 4 cell, ...
whose cube holds at least `k` points (else the coarsest): dense near the sensor, metres wide on far
ground. Per-cell counts and first and second moments (relative to the cell's corner, so float32
keeps sub-millimetre covariances 20 m from the sensor) are sorted once per level; a point's cube is
8 binary searches. Costs O(N log N) per level with no capacity to overflow, where k nearest
neighbours on a device need a candidate cap per cell.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxmap.grid.compaction import nonzero_fixed
from jaxmap.grid.features import CORNER_OFFSETS
from jaxmap.preprocess import CUBE_KNN_CAP, DOWNSAMPLE_TIE, MIN_PLANE_POINTS, key_span, layout_of, window_offsets
from jaxmap.range_image import pixels

INT_MAX = jnp.iinfo(jnp.int32).max
DEVICE_NORMALS = "cube_knn"  # what `normals: knn` (the host's k-d tree) becomes on the device
_SAID: set = set()           # the choices `resolve` has logged in this process


def resolve(p, backend: str | None = None):
    """`p` (a PreprocessConfig) with `device` decided, "true" or "false": "auto" is the device where jax
    runs on a GPU or TPU (there the frame program preprocesses a city scan in a few ms, the host's
    k-d tree normals take ~100 ms a scan and would hold the map back) unless outlier removal is on
    (host only), and the host on a CPU (the same cores either way: the host's normals are ~1 % better
    on the validation suite). On the device, `normals: knn` (the host's) becomes cube_knn, the k
    nearest among a hashed-grid cube. The choice is logged once. backend: jax.default_backend()."""
    import dataclasses
    import logging

    if p.device == "false" or (p.device == "true" and p.normals != "knn"):
        return p
    backend = backend or jax.default_backend()
    why = ""
    if p.device == "auto":
        if backend == "cpu":
            return dataclasses.replace(p, device="false")
        if p.outlier_mad > 0:
            why = f"preprocessing on the host: preprocess.outlier_mad={p.outlier_mad:g} runs there only"
            p = dataclasses.replace(p, device="false")
        else:
            why = f"preprocessing on the device (jax backend {backend}; the host would hold the frame program back)"
            p = dataclasses.replace(p, device="true")
    if p.device == "true" and p.normals == "knn":
        why = (why or "preprocessing on the device (preprocess.device=true)") + (
            f"; normals {DEVICE_NORMALS} (knn runs on the host only)")
        p = dataclasses.replace(p, normals=DEVICE_NORMALS)
    if why and why not in _SAID:
        _SAID.add(why)
        logging.getLogger("jaxmap").info("%s", why)
    return p


def crop_mask(points, valid, *, min_range: float, max_range: float, min_z: float, max_z: float):
    """valid & min_range <= |p| <= max_range & min_z <= z <= max_z. points [N, 3] -> [N] bool."""
    r = jnp.linalg.norm(points, axis=1)
    z = points[:, 2]
    return valid & (r >= min_range) & (r <= max_range) & (z >= min_z) & (z <= max_z)


def voxel_keep(points, valid, voxel: float):
    """One point per voxel of side `voxel`: the valid point closest to its voxel's mean (the lowest
    index among those within `DOWNSAMPLE_TIE` voxels of the closest), as `preprocess.voxel_downsample`.
    points [N, 3], valid [N] -> keep [N] bool."""
    n = points.shape[0]
    if voxel <= 0:
        return valid
    q = jnp.floor(points / jnp.float32(voxel)).astype(jnp.int32)
    qx, qy, qz = (jnp.where(valid, q[:, d], INT_MAX) for d in range(3))     # invalid rows sort last
    idx = jnp.arange(n, dtype=jnp.int32)
    sx, sy, sz, order = lax.sort((qx, qy, qz, idx), num_keys=3)
    new = jnp.concatenate([jnp.ones((1,), bool), (sx[1:] != sx[:-1]) | (sy[1:] != sy[:-1]) | (sz[1:] != sz[:-1])])
    seg = jnp.cumsum(new.astype(jnp.int32)) - 1                                  # [N] voxel of each sorted row
    ok = valid[order]
    rel = points[order] - q[order].astype(jnp.float32) * jnp.float32(voxel)     # to the voxel's corner
    cnt = jax.ops.segment_sum(ok.astype(jnp.float32), seg, num_segments=n)
    mean = jax.ops.segment_sum(jnp.where(ok[:, None], rel, 0.0), seg, num_segments=n) / jnp.maximum(cnt, 1.0)[:, None]
    d = jnp.where(ok, jnp.linalg.norm(rel - mean[seg], axis=1), jnp.inf)
    best = jax.ops.segment_min(d, seg, num_segments=n)
    near = d <= best[seg] + DOWNSAMPLE_TIE * voxel
    first = jax.ops.segment_min(jnp.where(near, order, INT_MAX), seg, num_segments=n)
    chosen = ok & (order == first[seg])
    return jnp.zeros((n,), bool).at[order].set(chosen)


def _cell_key(cell, span: int):
    """One int32 per cell [N, 3] int32, cells centred on the sensor (`key_span` cells per axis); the
    key of cell z + 1 is the key of cell z plus one."""
    off = span // 2
    return ((cell[:, 0] + off) * span + (cell[:, 1] + off)) * span + (cell[:, 2] + off)


def _level_moments(points, valid, c: float, span: int):
    """Per-cell moments of one level: (sorted unique cell keys [N] int32, INT_MAX after the last;
    moments [N, 10]: count, first moments (3), second moments xx yy zz xy xz yz), each point relative
    to its cell's corner."""
    n = points.shape[0]
    q = jnp.floor(points / c).astype(jnp.int32)
    key = jnp.where(valid, _cell_key(q, span), INT_MAX)
    skey, order = lax.sort_key_val(key, jnp.arange(n, dtype=jnp.int32))
    new = jnp.concatenate([jnp.ones((1,), bool), skey[1:] != skey[:-1]])
    seg = jnp.cumsum(new.astype(jnp.int32)) - 1
    ok = skey != INT_MAX
    rel = points[order] - q[order].astype(jnp.float32) * c
    x, y, z = rel[:, 0], rel[:, 1], rel[:, 2]
    per_point = jnp.stack([jnp.ones_like(x), x, y, z, x * x, y * y, z * z, x * y, x * z, y * z], axis=1)
    moments = jax.ops.segment_sum(jnp.where(ok[:, None], per_point, 0.0), seg, num_segments=n)
    ukey = jnp.full((n,), INT_MAX, jnp.int32).at[seg].set(skey)   # sorted: equal keys write equal values
    start = jax.ops.segment_min(jnp.arange(n, dtype=jnp.int32), seg, num_segments=n)
    return ukey, moments, order, start


def _cube_moments(points, ukey, moments, c: float, span: int):
    """Count [N] and covariance [N, 3, 3] of the points in each point's 2 x 2 x 2 cube, and the cube's
    cells: index into the level's cells [8, N] int32, -1 where the cell holds no point."""
    base = jnp.floor(points / c - 0.5).astype(jnp.int32)                      # [N, 3] the cube's first cell
    tot = jnp.zeros(points.shape[:1] + (10,), jnp.float32)
    cells = []
    last = ukey.shape[0] - 1
    for oc in CORNER_OFFSETS:
        key = _cell_key(base + oc, span)
        if oc[2] == 0:
            # One binary search per column of the cube: cell z + 1 has key + 1, so it is the next
            # entry of the sorted keys when cell z is there and the same entry when it is not.
            j = jnp.minimum(jnp.searchsorted(ukey, key), last)
        else:
            j = jnp.minimum(j + (ukey[j] == key - 1), last)
        hit = ukey[j] == key
        cells.append(jnp.where(hit, j, -1))
        mo = jnp.where(hit[:, None], moments[j], 0.0)
        m, a, b = mo[:, 0], mo[:, 1:4], mo[:, 4:]
        # Moments about the cell's corner, moved to the cube's corner (shift t = offset * c).
        t = oc.astype(np.float32) * np.float32(c)
        shift = jnp.stack([2 * a[:, 0] * t[0], 2 * a[:, 1] * t[1], 2 * a[:, 2] * t[2],
                           a[:, 0] * t[1] + a[:, 1] * t[0], a[:, 0] * t[2] + a[:, 2] * t[0],
                           a[:, 1] * t[2] + a[:, 2] * t[1]], axis=1)
        tt = np.array([t[0] ** 2, t[1] ** 2, t[2] ** 2, t[0] * t[1], t[0] * t[2], t[1] * t[2]], np.float32)
        tot += jnp.concatenate([m[:, None], a + m[:, None] * t, b + shift + m[:, None] * tt], axis=1)
    cnt = tot[:, 0]
    inv = 1.0 / jnp.maximum(cnt, 1.0)
    mean = tot[:, 1:4] * inv[:, None]
    e = tot[:, 4:] * inv[:, None]
    xx = e[:, 0] - mean[:, 0] ** 2
    yy = e[:, 1] - mean[:, 1] ** 2
    zz = e[:, 2] - mean[:, 2] ** 2
    xy = e[:, 3] - mean[:, 0] * mean[:, 1]
    xz = e[:, 4] - mean[:, 0] * mean[:, 2]
    yz = e[:, 5] - mean[:, 1] * mean[:, 2]
    cov = jnp.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], axis=1).reshape(-1, 3, 3)
    return cnt, cov, jnp.stack(cells)


def _knn_in_cube(points, valid, k: int, cap: int, level, cells, orders, starts, counts):
    """Covariance [N, 3, 3] and count [N] of each point's k nearest neighbours (itself included) among
    the first `cap` points (in input order) of each cell of its cube at its chosen `level` [N]:
    cells [L, 8, N], orders / starts / counts [L, N] of each level (`_level_moments`)."""
    n = points.shape[0]
    rows = jnp.arange(n)
    cell = cells[level[None, :], jnp.arange(8)[:, None], rows[None, :]]           # [8, N]
    lv = level[None, :]
    start = starts[lv, jnp.maximum(cell, 0)]
    count = jnp.where(cell >= 0, counts[lv, jnp.maximum(cell, 0)], 0)
    i = jnp.arange(cap)
    pos = start[:, :, None] + i                                                  # [8, N, cap]
    ok = i < count[:, :, None]
    cand = orders[lv[:, :, None], jnp.minimum(pos, n - 1)]                      # point indices
    cand = jnp.transpose(cand, (1, 0, 2)).reshape(n, 8 * cap)
    ok = jnp.transpose(ok, (1, 0, 2)).reshape(n, 8 * cap)
    rel = points[cand] - points[:, None, :]                                      # relative: float32 stays exact
    return _nearest_covariance(rel, ok, valid, k)


def _nearest_covariance(rel, ok, valid, k: int):
    """Count [N] and covariance [N, 3, 3] of the k nearest of each point's candidates: rel [N, C, 3]
    relative to the point, ok [N, C] the real ones, valid [N]."""
    d2 = jnp.where(ok, jnp.sum(rel * rel, -1), jnp.inf)
    neg, nb = lax.top_k(-d2, k)                                                  # [N, k]
    use = jnp.isfinite(neg) & valid[:, None]
    x = jnp.take_along_axis(rel, nb[:, :, None], axis=1)                         # [N, k, 3]
    m = use.astype(jnp.float32)
    cnt = jnp.sum(m, 1)
    mean = jnp.sum(x * m[:, :, None], 1) / jnp.maximum(cnt, 1.0)[:, None]
    c = (x - mean[:, None, :]) * m[:, :, None]
    cov = jnp.einsum("nki,nkj->nij", c, c, precision=lax.Precision.HIGHEST) / jnp.maximum(cnt, 1.0)[:, None, None]
    return cnt, cov


def _plane_normals(cov, cnt, points, valid):
    """The planes' normals [N, 3] of covariances [N, 3, 3] of `cnt` [N] points around points [N, 3]
    (sensor frame), facing the sensor; the direction to the sensor where fewer than 3 points span no
    plane (the only honest guess), +z on invalid rows."""
    normals = smallest_eigenvector(cov)
    flip = jnp.sum(normals * points, axis=1) > 0          # orient towards the sensor: n . (0 - p) > 0
    normals = jnp.where(flip[:, None], -normals, normals)
    view = -points / jnp.maximum(jnp.linalg.norm(points, axis=1, keepdims=True), 1e-9)
    normals = jnp.where((cnt < MIN_PLANE_POINTS)[:, None], view, normals)
    return jnp.where(valid[:, None], normals, np.array([0.0, 0.0, 1.0], np.float32))


def smallest_eigenvector(cov):
    """Unit eigenvector of the smallest eigenvalue of symmetric 3 x 3 matrices [N, 3, 3] -> [N, 3], in
    closed form (the trigonometric eigenvalues, then the largest cross product of two rows of
    cov - l_min I): several times faster than a batched `eigh` on a CPU. Where the smallest
    eigenvalue is not simple (no plane: a line, a single point) the result is some unit vector."""
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    p1 = a01**2 + a02**2 + a12**2
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    pp = jnp.sqrt(jnp.maximum(p2 / 6.0, 1e-30))
    b00, b11, b22 = (a00 - q) / pp, (a11 - q) / pp, (a22 - q) / pp
    b01, b02, b12 = a01 / pp, a02 / pp, a12 / pp
    det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    phi = jnp.arccos(jnp.clip(det / 2.0, -1.0, 1.0)) / 3.0
    lam = q + 2.0 * pp * jnp.cos(phi + 2.0 * jnp.pi / 3.0)                    # the smallest eigenvalue
    r0 = jnp.stack([a00 - lam, a01, a02], -1)
    r1 = jnp.stack([a01, a11 - lam, a12], -1)
    r2 = jnp.stack([a02, a12, a22 - lam], -1)
    c = jnp.stack([jnp.cross(r0, r1), jnp.cross(r0, r2), jnp.cross(r1, r2)], 1)   # [N, 3, 3]
    norm2 = jnp.sum(c * c, -1)
    best = jnp.argmax(norm2, axis=1)
    v = jnp.take_along_axis(c, best[:, None, None], axis=1)[:, 0]
    n = jnp.sqrt(jnp.take_along_axis(norm2, best[:, None], axis=1))
    return jnp.where(n > 1e-30, v / jnp.maximum(n, 1e-30), np.array([0.0, 0.0, 1.0], np.float32))


def grid_normals(points, valid, *, cell: float, levels: int, k: int, max_range: float, knn_cap: int = 0):
    """PCA normals over hashed-grid neighbourhoods (module docstring), oriented towards the sensor at
    the origin. knn_cap > 0: over the k nearest neighbours among the first `knn_cap` points of each cell
    of the chosen cube instead of the whole cube (`preprocess.normals: cube_knn`).
    points [N, 3] float32 sensor frame, valid [N] -> (normals [N, 3] unit float32,
    neighbours [N] float32: points in the neighbourhood used; 0 for invalid rows)."""
    n = points.shape[0]
    chosen_n = jnp.zeros((n,), jnp.float32)
    chosen_cov = jnp.zeros((n, 3, 3), jnp.float32)
    level = jnp.zeros((n,), jnp.int32)
    done = ~valid
    per_level = []
    for lv in range(levels):
        c = cell * (1 << lv)
        span = key_span(max_range, c)
        ukey, moments, order, start = _level_moments(points, valid, c, span)
        cnt, cov, cells = _cube_moments(points, ukey, moments, c, span)
        per_level.append((cells, order, start, moments[:, 0].astype(jnp.int32)))
        take = ~done & ((cnt >= k) | (lv == levels - 1))
        chosen_n = jnp.where(take, cnt, chosen_n)
        chosen_cov = jnp.where(take[:, None, None], cov, chosen_cov)
        level = jnp.where(take, lv, level)
        done = done | take
    if knn_cap > 0:
        cells, orders, starts, counts = (jnp.stack(a) for a in zip(*per_level))
        chosen_n, chosen_cov = _knn_in_cube(points, valid, k, knn_cap, level, cells, orders, starts, counts)
    return _plane_normals(chosen_cov, chosen_n, points, valid), jnp.where(valid, chosen_n, 0.0)


def preprocess_scan(points, valid, cfg, rows: int):
    """Crop, downsample and normals of one padded scan. cfg: a PreprocessConfig (static values).

    points [N, 3] float32 sensor frame, valid [N] bool -> (points [rows, 3], normals [rows, 3],
    valid [rows] bool, kept [] int32): the kept points in input order, packed into `rows` rows (the
    first `rows` of them when more are kept: the caller checks `kept > rows`)."""
    n = points.shape[0]
    keep = crop_mask(points, valid, min_range=cfg.min_range_m, max_range=cfg.max_range_m, min_z=cfg.min_z_m,
                     max_z=cfg.max_z_m)
    keep = voxel_keep(points, keep, cfg.vox_down_m)
    idx = nonzero_fixed(keep, rows, n)
    ok = idx < n
    pts = jnp.where(ok[:, None], points[jnp.minimum(idx, n - 1)], 0.0)
    # Normals of the packed rows only: a scan keeps ~3/4 of its points, and this is most of the cost.
    if cfg.normals == "range_image":
        normals, _ = range_image_normals(pts, ok, points, valid, layout_of(cfg), cfg.normal_knn)
    else:
        normals, _ = grid_normals(pts, ok, cell=cfg.normal_cell_m, levels=cfg.normal_levels, k=cfg.normal_knn,
                                  max_range=cfg.max_range_m, knn_cap=CUBE_KNN_CAP if cfg.normals == "cube_knn" else 0)
    return pts, normals, ok, jnp.sum(keep, dtype=jnp.int32)


def range_image_normals(points, valid, raw, raw_valid, layout, k: int):
    """PCA normals from the scan's own range-image neighbours (`jaxmap.preprocess.range_image_normals`,
    its float64 reference, says how): static shapes throughout, the window a fixed set of pixels, the k
    nearest of its returns by `lax.top_k`. points [M, 3] float32 sensor frame, valid [M]; raw [N, 3],
    raw_valid [N]: the raw scan (the range image's returns); layout: its `range_image.Layout` ->
    (normals [M, 3] unit float32, neighbours [M] float32; 0 for invalid rows)."""
    hw = layout.rows * layout.cols
    row, col, rng, inside = pixels(raw, layout, jnp)
    ok = raw_valid & inside & jnp.isfinite(rng) & (rng > 0)
    flat = jnp.where(ok, row * layout.cols + col, hw)
    nearest = jnp.full((hw + 1,), jnp.inf, jnp.float32).at[flat].min(rng)
    is_nearest = ok & (rng == nearest[flat])
    xyz = jnp.full((hw, 3), jnp.nan, jnp.float32).at[jnp.where(is_nearest, flat, hw)].set(raw, mode="drop")
    prow, pcol, _, _ = pixels(points, layout, jnp)
    off = jnp.asarray(window_offsets())
    rr, cc = prow[:, None] + off[:, 0], (pcol[:, None] + off[:, 1]) % layout.cols
    in_image = (rr >= 0) & (rr < layout.rows)
    rel = xyz[jnp.clip(rr, 0, layout.rows - 1) * layout.cols + cc] - points[:, None, :]   # [M, K, 3] relative
    good = in_image & jnp.isfinite(rel[..., 0])
    cnt, cov = _nearest_covariance(jnp.where(good[..., None], rel, 0.0), good, valid, k)
    return _plane_normals(cov, cnt, points, valid), jnp.where(valid, cnt, 0.0)
