"""A local map as a value, outside a sequence: encode points, fuse / remove, transform (eqs. 3-11).

    local = encode_frame(prior, points_s, normals_s, pose, voxel_size=0.1)   # [N,3] sensor frame -> world grid
    m = fuse(m, local); m = remove(m, local)                                  # eq. 11 on sums
    moved = transform(local, T)                                               # SE(3) + interpolation

Each is a thin host wrapper over the compiled programs of the map of a sequence (`jaxmap.imt.core`):
an encode is `core.step` on an empty map (the frame program: encode + fuse; with `with_jacobian` the
map keeps the Jacobians' sums), `fuse` / `remove` are `core.fuse_step` (the step's fusion alone) on a
copy of the map (the steps donate their state; the given map is left as it was), the map grown as the
step's stats ask (`core.run`, `core.fuse_batch`). So a local map is encoded and fused exactly as a frame
of a sequence is. The map of a keyframe store at some poses is `keyframes_map` (`core.apply_keyframes`,
what a remap runs).

Grid and frames as `jaxmap.imt.latent_map`: a local map is on the world-aligned grid of its voxel size.
"""
from __future__ import annotations

import math

import jax
import numpy as np

from jaxmap.errors import DataError
from jaxmap.geometry import SE3
from jaxmap.imt import core
from jaxmap.imt import latent_map as lm
from jaxmap.imt.interpolation import transform_batch
from jaxmap.snapshot import copy_arrays


def _points_and_normals(points, normals) -> tuple[np.ndarray, np.ndarray]:
    """Both as float32 [N,3], checked (a ValueError for shapes, a DataError for NaN/inf)."""
    points = np.asarray(points, np.float32)
    normals = np.asarray(normals, np.float32)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must both be [N,3], got {points.shape} and {normals.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(normals))):
        raise DataError("encode: points or normals contain NaN/inf; drop them first (jaxmap.io does)")
    return points, normals


def encode_cells(prior, cells, normals, counts, voxel_size: float, min_points: int = 10,
                 with_jacobian: bool = True, capacity: int | None = None, hints: dict | None = None) -> lm.LatentMap:
    """The local map of pooled cells (`latent_map.pool_cells`: centroids and mean normals [M, 3], counts
    [M]), map frame: `core.step` on an empty map of `capacity` slots (default: what the encode's scratch
    table holds; grown when full). hints: {padded cell count: scratch-table size that sufficed}, kept by
    the caller across encodes (an overflow grows it once, not every call). See `encode_frame`."""
    cells, normals = _points_and_normals(cells, normals)
    n_pad = lm.bucket(len(cells))
    hints = {} if hints is None else hints
    static = core.ImtStatic(float(voxel_size), int(min_points), 0)
    batch = core.CellBatch(lm.pad(cells, n_pad, np.float32), lm.pad(normals, n_pad, np.float32),
                           lm.pad(counts, n_pad, np.float32), np.zeros(n_pad, np.int32),
                           np.ones(core.FRAME_SLOTS, np.float32))
    cap = capacity or lm.encode_capacity(n_pad, hints)
    empty = lm.empty(voxel_size, cap, prior.latent_channels, with_jacobian)
    state, _, _ = core.run(static, core.ImtState(empty, jax.device_put(np.int32(0))), prior, batch, hints, False)
    return state.map


def encode_world(prior, points_w, normals_w, voxel_size: float, min_points: int = 10,
                 with_jacobian: bool = True, capacity: int | None = None, cells_per_voxel: int = 1,
                 hints: dict | None = None) -> lm.LatentMap:
    """Encode world-frame points and normals on the world grid (see `encode_frame`)."""
    points_w, normals_w = _points_and_normals(points_w, normals_w)
    c, n, k = lm.pool_cells(points_w, normals_w, voxel_size, cells_per_voxel)
    return encode_cells(prior, c, n, k, voxel_size, min_points, with_jacobian, capacity, hints)


def encode_frame(prior, points, normals, pose, voxel_size: float, min_points: int = 10,
                 with_jacobian: bool = True, cells_per_voxel: int = 1, hints: dict | None = None) -> lm.LatentMap:
    """The local map of one frame, on the world-aligned grid.

    Args:
      prior: a `jaxmap.imt.Prior` (`load_prior()`).
      points: [N, 3] float32, sensor frame (downsampled to about voxel_size / 4 spacing, as the prior
        was trained with up to 64 points per 2x2x2-voxel neighbourhood).
      normals: [N, 3] float32 unit normals, sensor frame.
      pose: [4, 4] T_world_sensor.
      voxel_size: metres.
      min_points: voxels fed by fewer points are dropped (weight 0).
      with_jacobian: keep the translation Jacobians (needed by `transform`; exact, forward mode).
      cells_per_voxel: points are pooled into cells of voxel_size / cells_per_voxel first (0 = none).
      hints: {padded cell count: scratch-table size that sufficed}, kept by the caller across frames.
    Returns:
      A `LatentMap` in the world frame: each cell feeds the 8 voxels whose 2x cube contains it;
      latent = count-weighted mean of the per-point encoder features, weight = number of points.
    """
    T_w_s = SE3.from_matrix(np.asarray(pose, np.float64))
    pw = T_w_s.apply(np.asarray(points, np.float64)).astype(np.float32)
    nw = T_w_s.rotation().apply(np.asarray(normals, np.float64)).astype(np.float32)
    return encode_world(prior, pw, nw, voxel_size, min_points, with_jacobian, cells_per_voxel=cells_per_voxel,
                        hints=hints)


def _as_batch(m: lm.LatentMap, b: lm.LatentMap | lm.VoxelBatch) -> lm.VoxelBatch:
    if isinstance(b, lm.LatentMap):
        if not math.isclose(m.voxel_size, b.voxel_size, rel_tol=1e-6):
            raise ValueError(f"voxel sizes differ: {m.voxel_size} vs {b.voxel_size} m")
        b = b.as_batch()
    if m.jac_sum is not None and b.jac is None:
        raise ValueError("this map keeps Jacobians: the batch must carry them too")
    return b


def fuse(m: lm.LatentMap, b: lm.LatentMap | lm.VoxelBatch, log: bool = True) -> lm.LatentMap:
    """`m` with a local map (or a voxel batch) fused (eq. 11, `+`; entries with negative weights are
    removed): `core.fuse_step` on a copy of `m`, grown when needed (logged on the "jaxmap" logger unless
    `log` is False). Jacobians of `b` are dropped when `m` keeps none. Both on the same grid and frame."""
    b = _as_batch(m, b)
    state, _ = core.fuse_batch(core.state_of(copy_arrays(m)), b, log)
    return state.map


def remove(m: lm.LatentMap, b: lm.LatentMap | lm.VoxelBatch) -> lm.LatentMap:
    """`m` with a previously fused local map (or voxel batch) removed (eq. 11, `-`): `fuse` of the batch
    with its weights negated. Raises ValueError if a voxel of `b` is not in `m` (it was never fused:
    removing it would be a bug); `m` is left as it was."""
    b = _as_batch(m, b)
    b = b._replace(weight=-np.asarray(b.weight))
    state, stats = core.fuse_batch(core.state_of(copy_arrays(m)), b, False)
    if int(stats.map_rows) > int(m.table.count):
        raise ValueError("remove: a voxel of the batch is not in the global map (was it ever fused?)")
    return state.map


def keyframes_map(prior, store, ids, poses, voxel_size: float, min_points: int = 10,
                  hints: dict | None = None) -> lm.LatentMap:
    """The map of keyframes `ids` of a `KeyframeStore` at `poses` ([len(ids), 4, 4]), each encoded from its
    stored cells as a remap does (`core.apply_keyframes`), into an empty map (no Jacobians)."""
    static = core.ImtStatic(float(voxel_size), int(min_points), 0)
    state = core.init(static, 1024, prior.latent_channels)
    return core.apply_keyframes(static, state, store, prior, list(ids), np.asarray(poses, np.float64),
                                np.ones(len(ids), np.float32), {} if hints is None else hints).map


def transform(m: lm.LatentMap, T, *, method: str = "trilinear", jacobian_sign: float = -1.0,
              temperature: float = 1.0, k: int = 8, splat_power: float = 2.0) -> lm.LatentMap:
    """The map `m` moved by `T` ([4, 4], m's frame -> global) and interpolated onto the global grid
    (`interpolation.transform_batch`, fused into an empty map).

    method: "trilinear" (splat, weight-conserving) or "softmax" (paper eq. 9-10, K nearest).
    jacobian_sign: -1 (correct first-order term), +1 (paper eq. 5/9), 0 (no Jacobian term).
    temperature: softmax temperature in voxel units^2 (paper: 1 / voxel_size^2).
    splat_power: trilinear only, see `interpolation.splat_trilinear` (1 = plain trilinear weights).
    Returns a new `LatentMap` on the global grid (same voxel size), with Jacobians if `m` has them.
    """
    keep = m.jac_sum is not None
    b = transform_batch(m, T, method=method, jacobian_sign=jacobian_sign, temperature=temperature, k=k,
                        splat_power=splat_power, keep_jacobian=keep)
    # Splats reach ~2x as many voxels as the map has; start there so the table grows at most once.
    cap = 1 << max(10, int(np.ceil(np.log2(4 * max(m.num_active(), 1)))))
    return fuse(lm.empty(m.voxel_size, capacity=cap, channels=m.channels, with_jacobian=keep), b, log=False)
