"""Multi-level corner features with trilinear interpolation (N3-Mapping, section III-A2).

Features live at the 8 corners of the voxels of the lowest ``L`` octree levels; level ``l`` has voxel
size ``s_l = leaf * 2**l`` (``l = 0 .. L-1``). A point's feature is the sum over levels of the trilinear
interpolation of its level's 8 corner features.

A corner is identified by the hash key ``(x, y, z, level)``: the integer corner coordinate in units of
``s_l`` plus the level, so a corner shared by neighbouring voxels of one level is one key and one row.

The level-``l`` voxel of a point is derived from its *leaf* voxel index by integer floor division,
``v_l = v_0 >> l == floor(v_0 / 2**l)``, never from ``floor(x / s_l)`` (which can disagree with the leaf
index at voxel boundaries in float32: XLA's float division is not correctly rounded everywhere). Hence every point inside one leaf voxel uses the same
``L * 8`` corner rows, and the per-leaf-voxel allocation of the mapper is exact.

Coordinates are float32 metres in a map frame (relative to a map origin, so they stay small).
Index order of the ``L * 8`` corner axis: ``k = l * 8 + c`` with ``c`` enumerating
``itertools.product((0, 1), repeat=3)`` over ``(x, y, z)``, i.e. ``c = 4 * cx + 2 * cy + cz``.
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxmap.grid import hashing

__all__ = [
    "CORNER_OFFSETS",
    "leaf_voxel",
    "level_voxels",
    "corner_keys",
    "corner_weights",
    "corner_weights_and_grad",
    "interpolate",
    "init_features",
    "init_feature_rows",
    "allocate_corners",
    "query_features",
]

CORNER_OFFSETS = np.array(list(itertools.product((0, 1), repeat=3)), dtype=np.int32)  # [8, 3]


@jax.jit
def leaf_voxel(points: jax.Array, leaf: float) -> jax.Array:
    """Leaf voxel index of each point, ``floor(points / leaf)``, made exact and backend-independent.

    XLA's float32 division is not always correctly rounded (XLA:CPU gives ``floor(x / 0.2)`` off by one
    for about 7% of the points lying on voxel faces, and a division by a constant may be compiled as a
    multiplication by its rounded reciprocal), so the estimate ``floor(x / leaf)`` is corrected with
    multiplications and comparisons, which are exact IEEE operations on every backend. The result is
    the unique ``v`` with ``fl(v * leaf) <= x < fl((v + 1) * leaf)`` (``fl``: float32 rounding), so a
    point gets the same voxel on CPU and GPU, inside or outside ``jit`` (XLA flushes subnormal inputs
    to zero, so ``x = -1e-45`` lands in voxel 0). Because ``leaf * 2**l`` is exact in float32, this also
    equals ``leaf_voxel(x, leaf * 2**l) == leaf_voxel(x, leaf) >> l`` for every level.

    Args:
      points: ``[N, 3]`` float32 map-frame coordinates (metres), ``|x / leaf| < 2**24``.
      leaf: leaf voxel size (metres; may be traced).
    Returns:
      ``[N, 3]`` int32 voxel indices.
    """
    points = jnp.asarray(points, jnp.float32)
    leaf32 = jnp.float32(leaf)
    v = jnp.floor(points / leaf32)  # estimate, possibly off by one at faces
    v = jnp.where(v * leaf32 > points, v - 1.0, v)
    v = jnp.where((v + 1.0) * leaf32 <= points, v + 1.0, v)
    return v.astype(jnp.int32)


@functools.partial(jax.jit, static_argnames=("levels",))
def level_voxels(leaf_vox: jax.Array, levels: int) -> jax.Array:
    """Voxel index at each level, derived from the leaf voxel by integer floor division.

    Args:
      leaf_vox: ``[N, 3]`` int32 leaf voxel indices.
      levels: number of levels ``L``.
    Returns:
      ``[N, L, 3]`` int32, ``v_l = floor(v_0 / 2**l)`` (arithmetic right shift: -1 >> 1 == -1).
    """
    leaf_vox = jnp.asarray(leaf_vox, jnp.int32)
    shifts = jnp.arange(levels, dtype=jnp.int32)  # [L]
    return jnp.right_shift(leaf_vox[:, None, :], shifts[None, :, None])  # [N, L, 3]


@functools.partial(jax.jit, static_argnames=("levels",))
def corner_keys(leaf_vox: jax.Array, levels: int) -> jax.Array:
    """Hash keys of the 8 corners of each level's voxel.

    Args:
      leaf_vox: ``[N, 3]`` int32 leaf voxel indices.
      levels: number of levels ``L``.
    Returns:
      ``[N, L * 8, 4]`` int32 keys ``(x, y, z, level)``; corner ``(x, y, z) = v_l + offset``, with
      entry ``l * 8 + c`` for offset ``CORNER_OFFSETS[c]``.
    """
    vl = level_voxels(leaf_vox, levels)  # [N, L, 3]
    n = vl.shape[0]
    xyz = vl[:, :, None, :] + jnp.asarray(CORNER_OFFSETS)[None, None]  # [N, L, 8, 3]
    lev = jnp.broadcast_to(jnp.arange(levels, dtype=jnp.int32)[None, :, None, None], (n, levels, 8, 1))
    return jnp.concatenate([xyz, lev], axis=-1).reshape(n, levels * 8, 4)  # [N, L*8, 4]


@functools.partial(jax.jit, static_argnames=("levels",))
def corner_weights(points: jax.Array, leaf_vox: jax.Array, leaf: float, levels: int) -> jax.Array:
    """Trilinear weights of each point inside each level's voxel.

    ``frac = (x - v_l * s_l) / s_l`` clamped to ``[0, 1]`` (the clamp only absorbs float rounding for
    points inside their leaf voxel) with a straight-through gradient ``d frac / dx = 1 / s_l``, so
    ``d/dx`` is the gradient of the multilinear field of the point's voxel, also on its faces. Corner
    ``c = (cx, cy, cz)`` gets ``prod_d (frac_d if c_d else 1 - frac_d)``. Differentiable w.r.t.
    ``points`` (the eikonal loss takes ``d/dx``); ``leaf_vox`` is integer data. A point far outside
    the given voxel gets the clamped (nearest-face) weights, with the extrapolated gradient.

    Args:
      points: ``[N, 3]`` float32 map-frame coordinates.
      leaf_vox: ``[N, 3]`` int32 leaf voxel indices of the points (normally ``leaf_voxel(points, leaf)``).
      leaf: leaf voxel size (metres).
      levels: number of levels ``L``.
    Returns:
      ``[N, L * 8]`` float32 weights; each level's 8 weights sum to 1.
    """
    points = jnp.asarray(points, jnp.float32)  # [N, 3]
    vl = level_voxels(leaf_vox, levels).astype(jnp.float32)  # [N, L, 3]
    size = jnp.float32(leaf) * (2.0 ** jnp.arange(levels, dtype=jnp.float32))  # [L]
    s = size[None, :, None]  # [1, L, 1]
    raw = (points[:, None, :] - vl * s) / s  # [N, L, 3]
    # Clamp the value, keep the identity gradient (straight-through): on a voxel face the compiler's
    # fused multiply-subtract makes x - v*s exact, e.g. -1e-9 where fl(v*s) == x, and a plain clip
    # would zero d/dx there. a + (clip(a) - a) == clip(a) exactly for a near [0, 1] (Sterbenz).
    frac = raw + lax.stop_gradient(jnp.clip(raw, 0.0, 1.0) - raw)
    off = jnp.asarray(CORNER_OFFSETS, jnp.float32)  # [8, 3]
    f = frac[:, :, None, :]  # [N, L, 1, 3]
    per_axis = off * f + (1.0 - off) * (1.0 - f)  # [N, L, 8, 3]
    w = per_axis[..., 0] * per_axis[..., 1] * per_axis[..., 2]  # [N, L, 8]
    return w.reshape(points.shape[0], levels * 8)


def corner_weights_and_grad(points: jax.Array, leaf_vox: jax.Array, leaf: float, levels: int):
    """Trilinear weights and their analytic derivatives w.r.t. the point.

    Same weights as :func:`corner_weights`; ``dw[n, k, :] = d weights[n, k] / d points[n]`` in closed form
    (d frac / dx = 1 / s_l inside the voxel, as the straight-through gradient there). The mapper's
    eikonal term uses it: the weights do not depend on any parameter, so computing their gradient here
    keeps autodiff from differentiating through them twice.

    Returns: (weights [N, L*8] float32, dw [N, L*8, 3] float32).
    """
    points = jnp.asarray(points, jnp.float32)
    vl = level_voxels(leaf_vox, levels).astype(jnp.float32)                     # [N, L, 3]
    size = jnp.float32(leaf) * (2.0 ** jnp.arange(levels, dtype=jnp.float32))  # [L]
    s = size[None, :, None]
    frac = jnp.clip((points[:, None, :] - vl * s) / s, 0.0, 1.0)                # [N, L, 3]
    off = jnp.asarray(CORNER_OFFSETS, jnp.float32)                              # [8, 3]
    f = frac[:, :, None, :]                                                     # [N, L, 1, 3]
    a = off * f + (1.0 - off) * (1.0 - f)                                       # [N, L, 8, 3]
    da = (2.0 * off - 1.0) / s[..., None]                                       # [1, L, 8|1, 3]
    w = a[..., 0] * a[..., 1] * a[..., 2]
    dw = jnp.stack([da[..., 0] * a[..., 1] * a[..., 2], a[..., 0] * da[..., 1] * a[..., 2],
                    a[..., 0] * a[..., 1] * da[..., 2]], axis=-1)               # [N, L, 8, 3]
    n = points.shape[0]
    return w.reshape(n, levels * 8), dw.reshape(n, levels * 8, 3)


@jax.jit
def interpolate(table: jax.Array, rows: jax.Array, weights: jax.Array) -> jax.Array:
    """Weighted sum of feature rows: ``sum_k weights[:, k] * table[rows[:, k]]``.

    Rows equal to -1 (corners never allocated) contribute zero; they are masked, never used as
    indices. Differentiable w.r.t. ``table`` and ``weights``.

    Args:
      table: ``[R, D]`` float32 feature table.
      rows: ``[N, K]`` int32 rows (``K = L * 8``), -1 where missing.
      weights: ``[N, K]`` float32.
    Returns:
      ``[N, D]`` float32.
    """
    rows = jnp.asarray(rows, jnp.int32)
    ok = rows >= 0  # [N, K]
    feats = jnp.take(table, jnp.where(ok, rows, 0), axis=0)  # [N, K, D]
    feats = jnp.where(ok[..., None], feats, 0.0)  # a masked corner is exactly zero (even if row 0 is inf/nan)
    return jnp.einsum("nk,nkd->nd", weights.astype(table.dtype), feats)


def init_features(key: jax.Array, n_rows: int, dim: int, std: float) -> jax.Array:
    """Feature table initialised with ``N(0, std^2)``.

    Args:
      key: a ``jax.random`` key.
      n_rows, dim: table shape.
      std: standard deviation.
    Returns:
      ``[n_rows, dim]`` float32.
    """
    # The barrier keeps XLA from folding `std` into the normal's own scaling inside a larger program
    # (`jax.jit(init_state)`): the rows are then the same bits however the table is built.
    return jnp.float32(std) * jax.lax.optimization_barrier(jax.random.normal(key, (n_rows, dim), jnp.float32))


FEATURE_INIT_BLOCK = 1 << 16


def init_feature_rows(seed: int, start: int, n: int, dim: int, std: float) -> jax.Array:
    """Rows [start, start + n) of a growing feature table's N(0, std^2) initialisation (host-side).

    Rows come in doubling blocks, [0, B), [B, 2B), [2B, 4B), ..., each from its own key
    (`fold_in(PRNGKey(seed + 2), block start)`, the first from the key itself), so a row's initial
    value does not depend on the table's capacity or on when it grew (threefry draws are prefix-stable).
    Returns ``[n, dim]`` float32.
    """
    base = jax.random.PRNGKey(seed + 2)
    out, lo, hi = [], start, start + n
    b0, b1 = 0, FEATURE_INIT_BLOCK
    while lo < hi:
        if lo < b1:
            key = base if b0 == 0 else jax.random.fold_in(base, b0)
            top = min(hi, b1)
            out.append(init_features(key, top - b0, dim, std)[lo - b0:])
            lo = top
        b0, b1 = b1, 2 * b1
    return jnp.concatenate(out) if out else jnp.zeros((0, dim), jnp.float32)


def allocate_corners(table: hashing.HashTable, leaf_vox: jax.Array, levels: int, valid: jax.Array,
                     row_capacity: int, *, max_probes: int = hashing.DEFAULT_MAX_PROBES):
    """Allocate (insert) the corner keys of all levels of the given leaf voxels (jit-able).

    Args:
      table: the corner hash table.
      leaf_vox: ``[M, 3]`` int32 leaf voxel indices (duplicates are fine).
      levels: number of levels ``L``.
      valid: ``[M]`` bool mask of the voxels to allocate.
      row_capacity: static bound on ``table.count`` after the insert (the feature table's rows, or a
        load-factor limit).
    Returns:
      ``(table, rows [M, L * 8] int32, overflow [] bool, n_new [] int32)``: new rows are
      ``old count .. new count - 1``, -1 for invalid voxels; on overflow the table is unchanged and
      every row is -1 (grow and retry, see ``hashing.insert``).
    """
    keys = corner_keys(leaf_vox, levels)                                          # [M, L*8, 4]
    m = keys.shape[0]
    table, rows, overflow, n_new, _ = hashing.insert_counted(
        table, keys.reshape(-1, 4), jnp.repeat(valid, levels * 8), max_probes, row_capacity)
    return table, rows.reshape(m, -1), overflow, n_new


@functools.partial(jax.jit, static_argnames=("levels", "max_probes"))
def query_features(
    table: hashing.HashTable,
    features: jax.Array,
    points: jax.Array,
    leaf: float,
    levels: int,
    max_probes: int = hashing.DEFAULT_MAX_PROBES,
) -> tuple[jax.Array, jax.Array]:
    """Summed multi-level feature at arbitrary points (lookup, no allocation; jit-compiled).

    Args:
      table: the hash table.
      features: ``[R, D]`` float32 feature table (``R >= table.count``).
      points: ``[N, 3]`` float32 map-frame coordinates.
      leaf: leaf voxel size (traced: changing it does not recompile).
      levels: number of levels ``L`` (static).
    Returns:
      ``(feat [N, D] float32, rows [N, L * 8] int32)``: the corner rows of each point's voxels, -1
      where a corner is not allocated (all ``>= 0`` means the point is fully inside the mapped grid).
    """
    points = jnp.asarray(points, jnp.float32)
    vox = leaf_voxel(points, leaf)  # [N, 3]
    keys = corner_keys(vox, levels)  # [N, L*8, 4]
    rows = hashing.lookup(table, keys.reshape(-1, 4), max_probes=max_probes).reshape(keys.shape[:2])  # [N, L*8]
    w = corner_weights(points, vox, leaf, levels)  # [N, L*8]
    return interpolate(features, rows, w), rows
