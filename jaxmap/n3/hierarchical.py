"""Batch selection from the pair store: hierarchical (N3 Algorithm 1) or uniform over pairs.

Both return pairs grouped as `[G, K]`: all K pairs of a group come from one block, i.e. one leaf
voxel, so they share the voxel's 24 corner rows and the feature gather happens once per group.
Hierarchical: G = Nv voxels drawn uniformly from the window, K = Np pairs from each (only Np/3
valid where a block holds fewer than Nt pairs). Uniform: G = batch pairs drawn uniformly from all
pairs in the window, K = 1.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxmap.n3.window import PairStore


class Batch(NamedTuple):
    slots: jax.Array    # [G] int32: block of each group
    points: jax.Array   # [G, K, 3] float32, map frame
    labels: jax.Array   # [G, K] float32
    surface: jax.Array  # [G, K] bool
    mask: jax.Array     # [G, K] bool: pair counts in the loss


def window_slots(in_window):
    """Compact list of window slots. in_window: [S] bool -> (ids [S] int32, n [] int32)."""
    s = in_window.shape[0]
    ids = jnp.nonzero(in_window, size=s, fill_value=0)[0].astype(jnp.int32)
    return ids, in_window.sum().astype(jnp.int32)


def _pair_mask(store: PairStore, slots, j, frame, keyframes):
    """Pairs written in the last `keyframes` frames only (keyframe ablation); keyframes<=0: all."""
    if keyframes <= 0:
        return jnp.ones(j.shape, bool)
    return store.frame[slots[:, None], j] > frame - keyframes


def sample_hierarchical(key, store: PairStore, ids, n, *, nv: int, np_: int, nt: int,
                        frame=0, keyframes: int = 0) -> Batch:
    """Stage 1: Nv blocks uniformly (with replacement) among the n window blocks `ids[:n]`.
    Stage 2: Np pairs uniformly within each; blocks with < Nt pairs contribute Np // 3."""
    kv, kp = jax.random.split(key)
    pick = jax.random.randint(kv, (nv,), 0, jnp.maximum(n, 1))
    slots = ids[pick]                                                    # [Nv]
    cnt = store.count[slots]                                             # [Nv]
    j = jnp.floor(jax.random.uniform(kp, (nv, np_)) * cnt[:, None]).astype(jnp.int32)
    j = jnp.clip(j, 0, store.block_size - 1)
    take = jnp.where(cnt >= nt, np_, max(np_ // 3, 1))
    mask = (jnp.arange(np_)[None, :] < take[:, None]) & (cnt[:, None] > 0) & (n > 0)
    mask &= _pair_mask(store, slots, j, frame, keyframes)
    rows = store.pairs[slots[:, None], j]                                # [Nv, Np, 4]
    return Batch(slots, rows[..., :3], rows[..., 3], store.surface[slots[:, None], j], mask)


def sample_uniform(key, store: PairStore, ids, n, *, batch: int, frame=0, keyframes: int = 0) -> Batch:
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
    mask = (total > 0) & _pair_mask(store, slots, j, frame, keyframes)
    mask = jnp.broadcast_to(mask, (batch, 1))
    rows = store.pairs[slots[:, None], j]
    return Batch(slots, rows[..., :3], rows[..., 3], store.surface[slots[:, None], j], mask)
