"""The transformable latent map: a sparse voxel grid of equivariant latents, with fuse and remove.

Grid and frames: voxel `v` (int32 `[3]`) of side `voxel_size` (metres) has its centre at
`(v + 0.5) * voxel_size` in the frame of the map (the world frame for the global map and for the
local map of a frame, which is encoded on the same world-aligned grid with the frame's pose). A
voxel's latent `F [C, 3]` (C = 18) and translation Jacobian `J [C, 3, 3]` describe the surface points
in its 2x2x2-voxel neighbourhood, relative to its centre and in voxel units (see `encoder.py`); both
are expressed in the map frame. `weight` is the number of points behind the latent (fractional after
an interpolation); a voxel with weight 0 is free and is ignored by every consumer.

Layout (read like mctx's `Tree`: a frozen dataclass of preallocated arrays with sentinels)::

    table   HashTable, capacity T     key (x, y, z, 0) -> row (`jaxmap.grid.hashing`)
    coords  [R, 3] int32              voxel of each row; EMPTY where the row was never used
    latent  [R, C, 3] float32         weighted mean latent (0 where free)
    jac     [R, C, 3, 3] float32      weighted mean Jacobian dF/dt (0 where free)
    weight  [R] float32               observation weight; 0 = free

with `R = T // 2` rows (the table never runs above load 0.5). Rows are handed out in insertion order
and never move; a voxel whose weight is removed down to ~0 keeps its row but is zeroed (freed).

Fusion and removal (IMT paper eq. 11), for every voxel of a batch at once, duplicates included:
`F <- (F w +- sum_k F_k w_k) / (w +- sum_k w_k)`, `w <- w +- sum_k w_k` (the same for J). A voxel
whose new weight is below `FREE_WEIGHT` is freed (latent, Jacobian and weight set to 0): the division
is never by ~0. `remove(fuse(M, L), L) == M` up to float rounding.

`VoxelBatch` is the flat, table-free form that moves between these functions: per entry a voxel,
latent, Jacobian, weight and validity. Fusing a batch whose voxels repeat is the same as fusing them
one after the other, which is what lets `transform` hand its trilinear splats straight to `fuse` and
`remap` batch any number of keyframes into one scatter.

Capacity: `fuse` inserts with `hashing.insert_grow`, which grows the table (outside jit) and logs it;
`encode_frame` retries with a bigger table when its jitted insert reports overflow. Nothing is ever
dropped silently. `remove` of a voxel that the map does not hold raises.
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.errors import DataError
from jaxmap.geometry import transform_points
from jaxmap.grid import hashing
from jaxmap.imt.encoder import per_point_fast

FREE_WEIGHT = 1e-3      # a voxel whose weight falls below this is freed (~ a thousandth of a point)
MAX_LOAD = 0.5          # rows per table slot
_POINT_BUCKET = 4096    # smallest padded point count of encode_frame (see _bucket)

# The 8 corner offsets of a cell: a point feeds the 8 voxels whose centres surround it.
CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int32)


@flax.struct.dataclass
class LatentMap:
    """A sparse voxel map of latents (a pytree; `voxel_size` is static). See the module docstring."""

    table: hashing.HashTable
    coords: jax.Array   # [R, 3] int32, EMPTY where the row is unused
    latent: jax.Array   # [R, C, 3] float32
    jac: jax.Array      # [R, C, 3, 3] float32
    weight: jax.Array   # [R] float32, 0 = free
    voxel_size: float = flax.struct.field(pytree_node=False, default=0.1)

    @property
    def rows(self) -> int:
        """Row capacity R (static)."""
        return self.weight.shape[0]

    @property
    def channels(self) -> int:
        return self.latent.shape[1]

    def active(self) -> jax.Array:
        """[R] bool: rows holding a voxel with non-zero weight."""
        return self.weight > 0

    def num_active(self) -> int:
        """Number of voxels with non-zero weight (host int)."""
        return int(np.count_nonzero(np.asarray(self.weight) > 0))

    def nbytes(self) -> int:
        """Bytes of every array of the map (table included)."""
        return int(sum(np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(self)))

    def as_batch(self) -> "VoxelBatch":
        """Every row as a `VoxelBatch` (valid = active)."""
        return VoxelBatch(self.coords, self.latent, self.jac, self.weight, self.active())


class VoxelBatch(NamedTuple):
    """Flat voxel records, the unit of `fuse` / `remove` / `transform`. Voxels may repeat.

    coords [P, 3] int32 voxel; latent [P, C, 3]; jac [P, C, 3, 3]; weight [P] float32; valid [P] bool.
    """

    coords: jax.Array
    latent: jax.Array
    jac: jax.Array
    weight: jax.Array
    valid: jax.Array

    def compact(self) -> "VoxelBatch":
        """Host-side: only the valid entries, padded with invalid ones to a multiple of 1024 rows
        (so that batches of similar size share compiled shapes)."""
        valid = np.asarray(self.valid)
        idx = np.flatnonzero(valid)
        n = max(1024, -(-len(idx) // 1024) * 1024)
        pad = n - len(idx)

        def take(x, fill):
            x = np.asarray(x)[idx]
            return np.concatenate([x, np.full((pad,) + x.shape[1:], fill, x.dtype)])

        return VoxelBatch(take(self.coords, hashing.EMPTY), take(self.latent, 0), take(self.jac, 0),
                          take(self.weight, 0), np.arange(n) < len(idx))

    def nbytes(self) -> int:
        return int(sum(np.asarray(x).nbytes for x in self))


def concat_batches(batches) -> VoxelBatch:
    """Concatenate `VoxelBatch`es (host or device arrays) along the entry axis (on the host: eager
    device concatenations would compile once per shape)."""
    return VoxelBatch(*[np.concatenate([np.asarray(b[i]) for b in batches]) for i in range(5)])


def _keys4(coords):
    """[P, 3] voxel coords -> [P, 4] hash keys (level column 0); numpy in, numpy out."""
    xnp = np if isinstance(coords, np.ndarray) else jnp
    return xnp.concatenate([coords, xnp.zeros_like(coords[:, :1])], axis=1)


def _host_valid(b: VoxelBatch) -> np.ndarray:
    return np.asarray(b.valid) & (np.asarray(b.weight) > 0)


def empty(voxel_size: float, capacity: int = 1024, channels: int = 18) -> LatentMap:
    """An empty map with a `capacity`-slot table (a power of two) and `capacity // 2` rows."""
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    table = hashing.create(capacity)
    r = table.capacity // 2
    return LatentMap(
        table=table,
        coords=jnp.full((r, 3), hashing.EMPTY, jnp.int32),
        latent=jnp.zeros((r, channels, 3), jnp.float32),
        jac=jnp.zeros((r, channels, 3, 3), jnp.float32),
        weight=jnp.zeros((r,), jnp.float32),
        voxel_size=float(voxel_size),
    )


def _pad_rows(m: LatentMap, table: hashing.HashTable) -> LatentMap:
    """Attach a (possibly grown) table and pad the row arrays to its row capacity."""
    r = table.capacity // 2
    extra = r - m.rows
    if extra < 0:
        raise ValueError("a table never shrinks")

    def pad(x, fill):
        if extra == 0:
            return x
        x = np.asarray(x)
        return np.concatenate([x, np.full((extra,) + x.shape[1:], fill, x.dtype)])

    return LatentMap(table, pad(m.coords, hashing.EMPTY), pad(m.latent, 0), pad(m.jac, 0), pad(m.weight, 0),
                     m.voxel_size)


@functools.partial(jax.jit, static_argnames=("sign",))
def _scatter(m: LatentMap, rows: jax.Array, b: VoxelBatch, sign: float) -> LatentMap:
    """Eq. 11 for a batch whose rows are known ([P] int32, -1 = skip)."""
    ok = b.valid & (rows >= 0) & (b.weight > 0)
    r = jnp.where(ok, rows, m.rows)  # out of range -> dropped by the scatters (only for skipped entries)
    wk = jnp.where(ok, b.weight, 0.0) * sign                                          # [P]
    w_new = m.weight.at[r].add(wk, mode="drop")                                       # [R]
    s_lat = (m.latent * m.weight[:, None, None]).at[r].add(b.latent * wk[:, None, None], mode="drop")
    s_jac = (m.jac * m.weight[:, None, None, None]).at[r].add(b.jac * wk[:, None, None, None], mode="drop")
    live = w_new >= FREE_WEIGHT
    inv = jnp.where(live, 1.0 / jnp.where(live, w_new, 1.0), 0.0)                      # guarded division
    coords = m.coords.at[r].set(b.coords, mode="drop")
    return LatentMap(m.table, coords, s_lat * inv[:, None, None], s_jac * inv[:, None, None, None],
                     jnp.where(live, w_new, 0.0), m.voxel_size)


def fuse(m: LatentMap, b: LatentMap | VoxelBatch, log: bool = True) -> LatentMap:
    """Fuse a local map (or a voxel batch) into `m` (eq. 11, `+`). Grows `m` when needed (host-side,
    logged on the "jaxmap" logger unless `log` is False).

    Both must use the same voxel size (checked for maps) and the same frame.
    """
    if isinstance(b, LatentMap):
        _check_same_grid(m, b)
        b = b.as_batch()
    table, rows = hashing.insert_grow(m.table, _keys4(np.asarray(b.coords)), _host_valid(b), max_load=MAX_LOAD,
                                      log=log)
    return _scatter(_pad_rows(m, table), rows, b, 1.0)


def remove(m: LatentMap, b: LatentMap | VoxelBatch) -> LatentMap:
    """Remove a previously fused local map (or voxel batch) from `m` (eq. 11, `-`).

    Raises ValueError if a voxel of `b` is not in `m` (it was never fused: removing it would be a bug).
    """
    if isinstance(b, LatentMap):
        _check_same_grid(m, b)
        b = b.as_batch()
    valid = _host_valid(b)
    rows = _lookup(m.table, _keys4(np.asarray(b.coords)))
    missing = int(np.count_nonzero(valid & (np.asarray(rows) < 0)))
    if missing:
        raise ValueError(f"remove: {missing} voxels of the local map are not in the global map "
                         "(was it fused into this map?)")
    return _scatter(m, rows, b, -1.0)


_lookup = jax.jit(hashing.lookup)


def _check_same_grid(a: LatentMap, b: LatentMap) -> None:
    if not math.isclose(a.voxel_size, b.voxel_size, rel_tol=1e-6):
        raise ValueError(f"voxel sizes differ: {a.voxel_size} vs {b.voxel_size} m")


def to_dict(m: LatentMap | VoxelBatch) -> dict:
    """Host-side `{voxel tuple: (latent, jac, weight)}` of the active voxels (a slow reference, for
    tests and inspection). Batches with repeated voxels are not accepted."""
    b = m.as_batch() if isinstance(m, LatentMap) else m
    coords, lat, jac, w, valid = (np.asarray(x) for x in b)
    out = {}
    for i in np.flatnonzero(valid & (w > 0)):
        key = tuple(int(c) for c in coords[i])
        if key in out:
            raise ValueError(f"voxel {key} repeats")
        out[key] = (lat[i], jac[i], float(w[i]))
    return out


# ---------------------------------------------------------------------------------------------
# Encoding a frame
# ---------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("voxel_size", "capacity", "with_jacobian"))
def _encode_core(prior, points_w, normals_w, mask, min_points, voxel_size: float, capacity: int,
                 with_jacobian: bool = True):
    """points_w, normals_w: [N, 3] float32 world frame; mask [N] bool -> (LatentMap, overflow [] bool)."""
    n = points_w.shape[0]
    u = points_w / voxel_size - 0.5                                       # [N, 3] continuous voxel index
    base = jnp.floor(u).astype(jnp.int32)                                 # [N, 3]
    vox = (base[:, None, :] + jnp.asarray(CORNERS)[None]).reshape(n * 8, 3)  # [8N, 3]
    rel = (u[:, None, :] - vox.reshape(n, 8, 3)).reshape(n * 8, 3)       # [8N, 3] in [-1, 1] (voxel units)
    nrm = jnp.repeat(normals_w, 8, axis=0)                                # [8N, 3]
    valid = jnp.repeat(mask, 8)                                           # [8N]
    table, rows, overflow = hashing.insert(hashing.create(capacity), _keys4(vox), valid,
                                           row_capacity=capacity // 2)
    r = capacity // 2
    seg = jnp.where(valid & (rows >= 0), rows, r)                         # [8N], r = dropped
    count = jax.ops.segment_sum(valid.astype(jnp.float32), seg, num_segments=r + 1)[:r]  # [R]
    def pooled(t):
        f = per_point_fast(prior.cfg.encoder, prior.params["encoder"], rel + t, nrm)   # [8N, C, 3]
        f = jnp.where(valid[:, None, None], f, 0.0)
        s = jax.ops.segment_sum(f, seg, num_segments=r + 1)[:r]          # [R, C, 3]
        return s / jnp.maximum(count, 1.0)[:, None, None]

    t0 = jnp.zeros((3,), jnp.float32)
    if with_jacobian:
        lat, jvp = jax.linearize(pooled, t0)
        jac = jax.vmap(jvp, in_axes=0, out_axes=-1)(jnp.eye(3, dtype=jnp.float32))  # [R, C, 3, 3]
    else:
        lat = pooled(t0)
        jac = jnp.zeros(lat.shape + (3,), jnp.float32)
    keep = count >= min_points
    coords = jnp.full((r, 3), hashing.EMPTY, jnp.int32).at[seg].set(vox, mode="drop")
    m = LatentMap(table, coords, jnp.where(keep[:, None, None], lat, 0.0),
                  jnp.where(keep[:, None, None, None], jac, 0.0), jnp.where(keep, count, 0.0), voxel_size)
    return m, overflow


def _bucket(n: int) -> int:
    """Padded point count: 2^k times 1, 1.25, 1.5 or 1.75 (>= 4096), so that frames of any size
    share a handful of compiled shapes and padding wastes at most 25 % of the work."""
    n = max(int(n), _POINT_BUCKET)
    k = 1 << (n.bit_length() - 1)
    for f in (4, 5, 6, 7, 8):
        if n <= k * f // 4:
            return k * f // 4
    raise AssertionError(n)


def encode_world(prior, points_w, normals_w, voxel_size: float, min_points: int = 10,
                 with_jacobian: bool = True, capacity: int | None = None) -> LatentMap:
    """Encode world-frame points and normals on the world grid (see `encode_frame`)."""
    points_w = np.asarray(points_w, np.float32)
    normals_w = np.asarray(normals_w, np.float32)
    if points_w.ndim != 2 or points_w.shape[1] != 3 or normals_w.shape != points_w.shape:
        raise ValueError(f"points and normals must both be [N,3], got {points_w.shape} and {normals_w.shape}")
    if not (np.all(np.isfinite(points_w)) and np.all(np.isfinite(normals_w))):
        raise DataError("encode: points or normals contain NaN/inf; drop them first (jaxmap.io does)")
    n = len(points_w)
    n_pad = _bucket(n)
    pts = np.zeros((n_pad, 3), np.float32)
    nrm = np.zeros((n_pad, 3), np.float32)
    pts[:n], nrm[:n] = points_w, normals_w
    mask = np.arange(n_pad) < n
    if capacity is None:
        # A frame has n/8 (dense surfaces at voxel/4 spacing) to n/3 (sparse, small frames) voxels: n_pad/2
        # rows cover both, so a retry (a second encode and a compile) is rare.
        capacity = 1 << max(10, math.ceil(math.log2(n_pad)))
    while True:
        m, overflow = _encode_core(prior, pts, nrm, mask, jnp.float32(min_points), float(voxel_size),
                                   int(capacity), with_jacobian)
        if not bool(overflow):
            return m
        capacity *= 2
        if capacity > hashing.MAX_CAPACITY:
            raise hashing.CapacityError(f"encode: more than {hashing.MAX_CAPACITY // 2} voxels in one frame")


def encode_frame(prior, points, normals, pose, voxel_size: float, min_points: int = 10,
                 with_jacobian: bool = True) -> LatentMap:
    """The local map of one frame, on the world-aligned grid.

    Args:
      prior: a `jaxmap.imt.Prior` (`load_prior()`).
      points: [N, 3] float32, sensor frame (downsampled to about voxel_size / 4 spacing, as the prior
        was trained with up to 64 points per 2x2x2-voxel neighbourhood).
      normals: [N, 3] float32 unit normals, sensor frame.
      pose: [4, 4] T_world_sensor.
      voxel_size: metres.
      min_points: voxels fed by fewer points are dropped (weight 0).
      with_jacobian: compute the translation Jacobians (needed by `transform`; 3 extra JVPs).
    Returns:
      A `LatentMap` in the world frame: each point feeds the 8 voxels whose 2x cube contains it;
      latent = mean of the per-point encoder features, weight = number of points.
    """
    pose = np.asarray(pose, np.float64)
    pw = transform_points(pose, np.asarray(points, np.float64)).astype(np.float32)
    nw = (np.asarray(normals, np.float64) @ pose[:3, :3].T).astype(np.float32)
    return encode_world(prior, pw, nw, voxel_size, min_points, with_jacobian)
