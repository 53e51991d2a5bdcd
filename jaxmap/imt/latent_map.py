"""The transformable latent map: a sparse voxel grid of equivariant latents, and its traceable parts.

Grid and frames: voxel `v` (int32 `[3]`) of side `voxel_size` (metres) has its centre at
`(v + 0.5) * voxel_size` in the frame of the map (the world frame for the global map and for the
local map of a frame, which is encoded on the same world-aligned grid with the frame's pose). A
voxel's latent `F [C, 3]` (C = 18) and translation Jacobian `J [C, 3, 3]` describe the surface points
in its 2x2x2-voxel neighbourhood, relative to its centre and in voxel units (see `encoder.py`); both
are expressed in the map frame. `weight` is the number of points behind the latent (fractional after
an interpolation); a voxel with weight 0 is free and is ignored by every consumer.

Layout (read like mctx's `Tree`: a frozen dataclass of preallocated arrays with sentinels)::

    table       HashTable, capacity T     key (x, y, z, 0) -> row (`jaxmap.grid.hashing`)
    coords      [R, 3] int32              voxel of each row; EMPTY where the row was never used
    latent_sum  [R, C, 3] float32         sum over observations of w_k F_k   (vector_field: rotates)
    weight      [R] float32               sum of w_k; 0 = free
    jac_sum     [R, C, 3, 3] float32|None sum of w_k J_k (jacobian_field); None in the global map,
                                          which nothing transforms (only local maps carry Jacobians)

with `R = T // 2` rows (load <= 0.5), handed out in insertion order, never moved; latents divided on read.

Fusion and removal (IMT paper eq. 11, `scatter`, run inside the compiled steps of `jaxmap.imt.core`;
`local_maps.fuse` / `remove` on a map as a value) store sums, so they touch only the rows of the batch:
`S <- S +- sum_k w_k F_k`, `w <- w +- sum_k w_k` (the same for J), for every entry of a batch at once,
duplicates included. `remove(fuse(M, L), L) == M` up to the rounding of the sums (no division, so no
loss of precision as the weight drains). A touched row whose weight falls below `FREE_WEIGHT` is freed
(sums and weight set to exactly 0), so stale rounding residue never accumulates.

`VoxelBatch` is the flat, table-free form that moves between these functions: per entry a voxel,
latent (a mean), Jacobian (or None), weight and validity. Fusing a batch whose voxels repeat is the
same as fusing them one after the other, which is what lets `transform` hand its trilinear splats
straight to `fuse` and `remap` fuse any number of keyframes in one scatter.

Encoding (`encode_pairs`, inside `core.step`; `local_maps.encode_frame` on a frame as a value): a frame's
points are first pooled into cells of `voxel_size / cells_per_voxel` aligned with the voxel cubes
(`pool_cells`: centroid, mean normal, count), and each cell feeds the 8 voxels whose 2x cube holds it, weighted by its count; the
voxel's latent is the count-weighted mean of the encoder's per-point features at the centroids (a
quadrature of the mean over the points) and its weight the exact number of points. With one cell per
voxel this is 8 x ~2k (cell, voxel) pairs for a room frame instead of 8 x 31k, and the decoded SDF
moves by 0.6 mm (`jaxmap bench imt`); `cells_per_voxel = 0` feeds every point.

Capacity: fixed inside jit; the steps say when the map's table or the encode's scratch table is full, and
the host grows it (`pad_rows`, `encode_capacity`: the caller's `hints` keep the size) and runs them again.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.grid import hashing
from jaxmap.grid.features import CORNER_OFFSETS  # the 8 voxels whose centres surround a point
from jaxmap.imt.encoder import translation_jacobian
from jaxmap.imt.vn import jacobian_field, vector_field
from jaxmap.sizes import quarter_bucket

FREE_WEIGHT = 1e-3      # a touched voxel whose weight falls below this is freed (~ a thousandth of a point)
MAX_LOAD = 0.5          # rows per table slot
_CELL_BUCKET = 2048     # smallest padded cell count of an encode (see bucket)
_CHUNK = 512            # cells per step of the encoder's scan (4096 pairs: the intermediates stay in cache)
_JAC_CHUNK = 64         # the same with Jacobians: three tangents per pair (512 cells: 1.4x slower, 2 cores)


def _inv_weight(w):
    live = w >= FREE_WEIGHT
    return jnp.where(live, 1.0 / jnp.where(live, w, 1.0), 0.0)


@flax.struct.dataclass
class LatentMap:
    """A sparse voxel map of latent sums (a pytree; `voxel_size` is static). See the module docstring."""

    table: hashing.HashTable
    coords: jax.Array                                        # [R, 3] int32, EMPTY where the row is unused
    latent_sum: jax.Array = vector_field()                   # [R, C, 3] float32, sum of w F
    weight: jax.Array = flax.struct.field(default=None)      # [R] float32, 0 = free
    jac_sum: jax.Array | None = jacobian_field(default=None)  # [R, C, 3, 3] float32 sum of w J, or None
    voxel_size: float = flax.struct.field(pytree_node=False, default=0.1)

    @property
    def rows(self) -> int:
        """Row capacity R (static)."""
        return self.weight.shape[0]

    @property
    def channels(self) -> int:
        return self.latent_sum.shape[1]

    @property
    def latent(self) -> jax.Array:
        """[R, C, 3] weighted mean latent (0 where free)."""
        return self.latent_sum * _inv_weight(self.weight)[:, None, None]

    @property
    def jac(self) -> jax.Array | None:
        """[R, C, 3, 3] weighted mean Jacobian (0 where free), None for a map without Jacobians."""
        return None if self.jac_sum is None else self.jac_sum * _inv_weight(self.weight)[:, None, None, None]

    def active(self, min_weight: float = 0.0) -> jax.Array:
        """[R] bool: rows holding a voxel with weight above `min_weight` (and above 0)."""
        return self.weight > max(float(min_weight), 0.0)

    def num_active(self) -> int:
        """Number of voxels with non-zero weight (host int)."""
        return int(np.count_nonzero(np.asarray(self.weight) > 0))

    def nbytes(self) -> int:
        """Bytes of every array of the map (table included)."""
        return int(sum(np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(self)))

    def as_batch(self) -> "VoxelBatch":
        """Every row as a `VoxelBatch` (means; valid = active)."""
        return VoxelBatch(self.coords, self.latent, self.jac, self.weight, self.active())


@flax.struct.dataclass
class VoxelBatch:
    """Flat voxel records, the unit of `fuse` / `remove` / `transform`. Voxels may repeat.

    coords [P, 3] int32 voxel; latent [P, C, 3] mean latent; jac [P, C, 3, 3] mean Jacobian or None;
    weight [P] float32; valid [P] bool. The latent and Jacobian are marked for `vn.rotate`.
    """

    coords: jax.Array
    latent: jax.Array = vector_field()
    jac: jax.Array | None = jacobian_field()
    weight: jax.Array = flax.struct.field(default=None)
    valid: jax.Array = flax.struct.field(default=None)

    def __iter__(self):
        return iter((self.coords, self.latent, self.jac, self.weight, self.valid))

    def _replace(self, **changes) -> "VoxelBatch":
        return dataclasses.replace(self, **changes)

    def nbytes(self) -> int:
        return int(sum(np.asarray(x).nbytes for x in self if x is not None))


def bucket(n: int, smallest: int = _CELL_BUCKET) -> int:
    """Padded cell count of an encode (`jaxmap.sizes.quarter_bucket`, at least `smallest`)."""
    return quarter_bucket(n, smallest)


def concat_batches(batches) -> VoxelBatch:
    """Concatenate `VoxelBatch`es (host or device arrays) along the entry axis (on the host: eager
    device concatenations would compile once per shape). Jacobians are kept only if every batch has them."""
    batches = list(batches)
    jac = np.concatenate([np.asarray(b.jac) for b in batches]) if all(b.jac is not None for b in batches) else None
    cat = [np.concatenate([np.asarray(getattr(b, f)) for b in batches]) for f in ("coords", "latent", "weight",
                                                                                    "valid")]
    return VoxelBatch(cat[0], cat[1], jac, cat[2], cat[3])


def voxel_keys(coords, level=None):
    """[P, 3] voxel coords (+ [P] level column, 0 if None) -> [P, 4] hash keys; numpy in, numpy out."""
    xnp = np if isinstance(coords, np.ndarray) else jnp
    lev = xnp.zeros_like(coords[:, :1]) if level is None else level[:, None].astype(coords.dtype)
    return xnp.concatenate([coords, lev], axis=1)


def empty(voxel_size: float, capacity: int = 1024, channels: int = 18, with_jacobian: bool = False) -> LatentMap:
    """An empty map with a `capacity`-slot table (a power of two) and `capacity // 2` rows. Filled on the host
    and copied (outside jit only): a device fill compiles a program per shape, at the first remap of a map
    that grew."""
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    table = hashing.create_on_host(capacity)
    r = table.capacity // 2
    coords, latent_sum, weight, jac_sum = jax.device_put(
        (np.full((r, 3), hashing.EMPTY, np.int32), np.zeros((r, channels, 3), np.float32), np.zeros((r,), np.float32),
         np.zeros((r, channels, 3, 3), np.float32) if with_jacobian else None), may_alias=False)
    return LatentMap(table, coords, latent_sum, weight, jac_sum, float(voxel_size))


@functools.partial(jax.jit, static_argnums=1)
def _pad_rows_core(m: LatentMap, extra: int) -> LatentMap:
    def pad(x, fill):
        return None if x is None else jnp.concatenate([x, jnp.full((extra,) + x.shape[1:], fill, x.dtype)])

    return LatentMap(m.table, pad(m.coords, hashing.EMPTY), pad(m.latent_sum, 0), pad(m.weight, 0), pad(m.jac_sum, 0),
                     m.voxel_size)


def pad_rows(m: LatentMap, table: hashing.HashTable) -> LatentMap:
    """Attach a (possibly grown) table and pad the row arrays to its row capacity (on the device)."""
    extra = table.capacity // 2 - m.rows
    if extra < 0:
        raise ValueError("a table never shrinks")
    return dataclasses.replace(_pad_rows_core(m, extra) if extra else m, table=table)


def scatter(m: LatentMap, rows: jax.Array, b: VoxelBatch, sign: float) -> LatentMap:
    """Eq. 11 on sums for a batch whose rows are known ([P] int32, -1 = skip). Touches only those rows
    (traceable; `jaxmap.imt.core.step` runs it inside the frame program)."""
    ok = b.valid & (rows >= 0) & (b.weight != 0)
    r = jnp.where(ok, rows, m.rows)  # out of range -> dropped by the scatters (only for skipped entries)
    wk = jnp.where(ok, b.weight, 0.0) * sign                                          # [P]
    weight = m.weight.at[r].add(wk, mode="drop")                                      # [R]
    latent_sum = m.latent_sum.at[r].add(b.latent * wk[:, None, None], mode="drop")
    jac_sum = m.jac_sum
    if jac_sum is not None:
        jac_sum = jac_sum.at[r].add(b.jac * wk[:, None, None, None], mode="drop")
    # free the touched rows whose weight fell below the floor: exact zeros, no rounding residue left
    dead = ok & (weight[jnp.maximum(rows, 0)] < FREE_WEIGHT)
    rd = jnp.where(dead, rows, m.rows)
    weight = weight.at[rd].set(0.0, mode="drop")
    latent_sum = latent_sum.at[rd].set(0.0, mode="drop")
    if jac_sum is not None:
        jac_sum = jac_sum.at[rd].set(0.0, mode="drop")
    coords = m.coords.at[r].set(b.coords, mode="drop")
    return LatentMap(m.table, coords, latent_sum, weight, jac_sum, m.voxel_size)


def to_dict(m: LatentMap | VoxelBatch) -> dict:
    """Host-side `{voxel tuple: (latent, jac or None, weight)}` of the active voxels (a slow reference,
    for tests and inspection). Batches with repeated voxels are not accepted."""
    b = m.as_batch() if isinstance(m, LatentMap) else m
    coords, lat, w, valid = (np.asarray(x) for x in (b.coords, b.latent, b.weight, b.valid))
    jac = None if b.jac is None else np.asarray(b.jac)
    out = {}
    for i in np.flatnonzero(valid & (w > 0)):
        key = tuple(int(c) for c in coords[i])
        if key in out:
            raise ValueError(f"voxel {key} repeats")
        out[key] = (lat[i], None if jac is None else jac[i], float(w[i]))
    return out


# ---------------------------------------------------------------------------------------------
# Encoding
# ---------------------------------------------------------------------------------------------


def pool_cells(points, normals, voxel_size: float, cells_per_voxel: int = 1):
    """Pool points into cells of side `voxel_size / cells_per_voxel` aligned with the voxel cubes.

    points, normals: [N, 3] (any frame whose grid is the voxel grid: the world frame for a map).
    Returns numpy `(centroids [M, 3] float32, normals [M, 3] float32 unit (mean normal), counts [M]
    float32)`. The cell borders are at `(v - 1/2) voxel_size + i voxel_size / cells_per_voxel`, so
    every cell lies inside the 2x cube of each voxel it feeds, and a voxel's count is exact.
    `cells_per_voxel = 0`: every point is its own cell.
    """
    points = np.asarray(points, np.float32)
    normals = np.asarray(normals, np.float32)
    if cells_per_voxel <= 0 or len(points) == 0:
        return points, normals, np.ones(len(points), np.float32)
    k = int(cells_per_voxel)
    idx = np.floor(points.astype(np.float64) * (k / voxel_size) + 0.5 * k).astype(np.int64)
    idx -= idx.min(axis=0)
    span = idx.max(axis=0) + 1
    code = (idx[:, 0] * span[1] + idx[:, 1]) * span[2] + idx[:, 2]
    uniq, inv, cnt = np.unique(code, return_inverse=True, return_counts=True)
    m = len(uniq)
    c = np.stack([np.bincount(inv, points[:, i], m) for i in range(3)], 1) / cnt[:, None]
    n = np.stack([np.bincount(inv, normals[:, i], m) for i in range(3)], 1)
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(nn > 1e-6, n / np.maximum(nn, 1e-12), normals[np.unique(inv, return_index=True)[1]])
    return c.astype(np.float32), n.astype(np.float32), cnt.astype(np.float32)


def encode_pairs(prior, cells, normals, counts, level, min_points, voxel_size: float, capacity: int,
                 with_jacobian: bool):
    """Per-(voxel, level) sums of the encoder's features over cells (traceable; the frame program's encode).

    cells, normals [N, 3] float32 map frame; counts [N] (0 = padding); level [N] int32 (a key column:
    records of different levels never pool); a `capacity`-slot scratch table (static) holds the records.
    -> (coords [R, 3], latent sum [R, C, 3], jac sum [R, C, 3, 3] or None, count [R], level [R], table,
    overflow []), R = capacity // 2; N a multiple of _CHUNK."""
    n = cells.shape[0]
    u = cells / voxel_size - 0.5                                           # [N, 3] continuous voxel index
    base = jnp.floor(u).astype(jnp.int32)
    vox = (base[:, None, :] + jnp.asarray(CORNER_OFFSETS)[None]).reshape(n * 8, 3)   # [8N, 3]
    lev = jnp.repeat(level, 8)
    wp = jnp.repeat(counts, 8)                                             # [8N] points behind each pair
    valid = wp > 0
    table, rows, overflow = hashing.insert(hashing.create(capacity), voxel_keys(vox, lev), valid,
                                           row_capacity=capacity // 2)
    r = capacity // 2
    seg = jnp.where(valid & (rows >= 0), rows, r)                          # [8N], r = dropped
    count = jax.ops.segment_sum(wp, seg, num_segments=r + 1)[:r]           # [R] exact point counts
    c = prior.latent_channels

    def step(acc, chunk):                                                  # `size` cells = 8 `size` pairs
        p, nrm, w, s = chunk
        rel = ((p / voxel_size - 0.5)[:, None] - (jnp.floor(p / voxel_size - 0.5)[:, None]
                                                   + jnp.asarray(CORNER_OFFSETS, jnp.float32)[None])).reshape(-1, 3)
        nr = jnp.repeat(nrm, 8, axis=0)
        if with_jacobian:  # exact, forward mode: one t shared by the chunk's pairs gives each pair's own dF/dp
            f, j = translation_jacobian(lambda t: prior.per_point(rel + t, nr))                # [8n, C, 3, 3]
            fj = jnp.concatenate([f[..., None], j], -1) * w[:, None, None, None]       # [8n, C, 3, 4]
        else:
            fj = (prior.per_point(rel, nr) * w[:, None, None])[..., None]  # [8n, C, 3, 1]
        return acc.at[s].add(fj, mode="drop"), None

    width, size = (4, _JAC_CHUNK) if with_jacobian else (1, _CHUNK)
    acc = jnp.zeros((r, c, 3, width), jnp.float32)
    chunks = (cells.reshape(-1, size, 3), normals.reshape(-1, size, 3), wp.reshape(-1, size * 8),
              seg.reshape(-1, size * 8))
    # only the chunks up to the last cell with a count run the encoder: the padding after it (a frame padded
    # to the largest frame so far, `core.frame_pad`) adds nothing, and an encode costs its own cells
    last = jnp.max(jnp.where(counts > 0, jnp.arange(n, dtype=jnp.int32) + 1, 0))
    acc = jax.lax.fori_loop(0, (last + size - 1) // size,
                            lambda i, a: step(a, jax.tree_util.tree_map(lambda x: x[i], chunks))[0], acc)
    keep = count >= min_points
    coords = jnp.full((r, 3), hashing.EMPTY, jnp.int32).at[seg].set(vox, mode="drop")
    levels = jnp.full((r,), -1, jnp.int32).at[seg].set(lev, mode="drop")
    lat = jnp.where(keep[:, None, None], acc[..., 0], 0.0)
    jac = jnp.where(keep[:, None, None, None], acc[..., 1:], 0.0) if with_jacobian else None
    return coords, lat, jac, jnp.where(keep, count, 0.0), levels, table, overflow


def pad(x, n_pad: int, dtype, fill=0):
    x = np.asarray(x, dtype)
    return np.concatenate([x, np.full((n_pad - len(x),) + x.shape[1:], fill, dtype)])


def encode_capacity(n_pad: int, hints: dict) -> int:
    """Scratch-table slots of an encode of `n_pad` cells: a cell feeds 8 voxels and a voxel's cube holds up
    to 8 cells, so 2 rows per cell covers surfaces; isolated cells (8 rows each, sparse LiDAR) overflow it
    once, and `hints` (n_pad -> slots that sufficed, owned by the caller) remembers the size that worked."""
    return max(1 << max(10, math.ceil(math.log2(4 * n_pad))), hints.get(n_pad, 0))


def mean_of(sums: jax.Array, w: jax.Array) -> jax.Array:
    """Per-row means `sums [R, ...] / w [R]`, 0 where the weight is below FREE_WEIGHT (traceable)."""
    return sums * _inv_weight(w).reshape((-1,) + (1,) * (sums.ndim - 1))


def signed_batch(coords, lat_sum, w, levels, signs, jac_sum=None) -> VoxelBatch:
    """(voxel, slot) sums -> a VoxelBatch of means whose weights carry the slot's sign (traceable); with
    the Jacobians' sums, their means too."""
    mean = lat_sum * _inv_weight(w)[:, None, None]
    jac = None if jac_sum is None else mean_of(jac_sum, w)
    w = w * signs[jnp.maximum(levels, 0)]
    return VoxelBatch(coords, mean, jac, w, w != 0)
