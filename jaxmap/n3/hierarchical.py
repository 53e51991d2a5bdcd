"""Batch selection from the pair store: hierarchical (N3 Algorithm 1) or uniform over pairs (and
uniform over a flat pool of pairs for the replay / keyframe ablations).

Both return pairs grouped as `[G, K]`: all K pairs of a group come from one block, i.e. one leaf
voxel, so they share the voxel's 24 corner rows and the feature gather happens once per group.
Hierarchical: G = Nv voxels drawn uniformly from the window, K = Np pairs from each (only Np/3
valid where a block holds fewer than Nt pairs). Uniform: G = batch pairs drawn uniformly from all
pairs in the window, K = 1.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxmap.n3 import pool as pairpool
from jaxmap.n3.window import PairStore


class Batch(NamedTuple):
    voxel_rows: jax.Array  # [G] int32: leaf-voxel row of each group (its corner features)
    coords: jax.Array      # [G, 3] int32: that voxel's leaf coordinate
    points: jax.Array   # [G, K, 3] float32, map frame
    labels: jax.Array   # [G, K] float32
    surface: jax.Array  # [G, K] bool
    mask: jax.Array     # [G, K] bool: pair counts in the loss


def _store_batch(store: PairStore, slots, j, mask) -> Batch:
    """The pairs `j [G, K]` of the store blocks `slots [G]` as a Batch (mask [G, K])."""
    rows = store.pairs[slots[:, None], j]                                # [G, K, 4]
    return Batch(store.voxel_of_slot[slots], store.coord[slots], rows[..., :3], rows[..., 3],
                 store.surface[slots[:, None], j], mask)


def draw_block_pairs(u, count, *, nt: int, block_size: int):
    """Stage 2 for ONE block (lifted over the stage-1 blocks with `jax.vmap`).

    u: [Np] uniform draws in [0, 1) for this block; count: [] int32 pairs the block holds.
    Returns (j [Np] int32 pair indices, uniform in [0, count), with replacement; take [Np] bool:
    all Np count if the block holds at least Nt pairs, else only the first Np // 3, none if empty).
    """
    np_ = u.shape[0]
    j = jnp.clip(jnp.floor(u * count).astype(jnp.int32), 0, block_size - 1)
    n_take = jnp.where(count >= nt, np_, max(np_ // 3, 1))
    take = (jnp.arange(np_) < n_take) & (count > 0)
    return j, take


def sample_hierarchical(key, store: PairStore, ids, n, *, nv: int, np_: int, nt: int) -> Batch:
    """Stage 1: Nv blocks uniformly (with replacement) among the n window blocks `ids[:n]`.
    Stage 2: `draw_block_pairs` per block under `vmap` (its uniforms drawn in one [Nv, Np] call)."""
    kv, kp = jax.random.split(key)
    pick = jax.random.randint(kv, (nv,), 0, jnp.maximum(n, 1))
    slots = ids[pick]                                                    # [Nv]
    draw = functools.partial(draw_block_pairs, nt=nt, block_size=store.block_size)
    j, mask = jax.vmap(draw)(jax.random.uniform(kp, (nv, np_)), store.count[slots])   # [Nv, Np] each
    mask &= (n > 0)
    return _store_batch(store, slots, j, mask)


def sample_uniform(key, store: PairStore, ids, n, *, batch: int) -> Batch:
    """`batch` pairs uniformly over all pairs in the window blocks `ids[:n]` (ablation)."""
    s = ids.shape[0]
    counts = jnp.where(jnp.arange(s) < n, store.count[ids], 0)
    cum = jnp.cumsum(counts)
    total = cum[-1]
    u = jax.random.randint(key, (batch,), 0, jnp.maximum(total, 1))
    w = jnp.searchsorted(cum, u, side="right")
    w = jnp.minimum(w, s - 1)
    slots = ids[w]
    j = (u - (cum[w] - counts[w]))[:, None].astype(jnp.int32)          # [B,1]
    j = jnp.clip(j, 0, store.block_size - 1)
    mask = jnp.broadcast_to(total > 0, (batch, 1))
    return _store_batch(store, slots, j, mask)


def sample_pool(key, pool, voxel_coord, *, batch: int) -> Batch:
    """`batch` pairs uniformly from all pairs of a `pool.PairPool` (the replay / keyframe ablations);
    voxel_coord: [V, 3] int32 leaf coordinate of each voxel row."""
    i, mask = pairpool.sample(key, pool, batch=batch)
    v = pool.voxel_row[i]
    rows = pool.pairs[i][:, None]                                         # [B, 1, 4]
    return Batch(v, voxel_coord[jnp.maximum(v, 0)], rows[..., :3], rows[..., 3], pool.surface[i][:, None],
                 mask[:, None] & (v >= 0)[:, None])
