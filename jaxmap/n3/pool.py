"""A flat pool of training pairs for the paper's data-replay ablations (N3 paper, Table III).

`window.mode: replay` keeps every pair of every past frame (no per-voxel cap; memory grows with the
sequence) and trains on pairs drawn uniformly from all of them; `window.mode: keyframe` keeps the
pairs of the last N frames only. Neither has the voxel-oriented store's per-voxel blocks, so they
live here: one array of pairs with the leaf-voxel row of each, appended to each frame (all or
nothing: when the pool is full the frame is refused and the host grows it, doubling).
"""
from __future__ import annotations

from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp

from jaxmap.grid.compaction import prefix_sum


@flax.struct.dataclass
class PairPool:
    pairs: jax.Array      # [C, 4] float32: x, y, z (map frame), label
    surface: jax.Array    # [C] bool: in the truncation band (eikonal term)
    frame: jax.Array      # [C] int32: frame that produced the pair
    voxel_row: jax.Array  # [C] int32: leaf-voxel row of the pair
    n: jax.Array          # [] int32: pairs held, `[:n]`

    @property
    def capacity(self) -> int:
        return self.pairs.shape[0]


def create(capacity: int) -> PairPool:
    c = int(capacity)
    return PairPool(pairs=jnp.zeros((c, 4), jnp.float32), surface=jnp.zeros((c,), bool),
                    frame=jnp.full((c,), -1, jnp.int32), voxel_row=jnp.full((c,), -1, jnp.int32),
                    n=jnp.zeros((), jnp.int32))


def grow(pool: PairPool, capacity: int) -> PairPool:
    """A larger pool with the same contents (outside jit)."""
    fresh = create(capacity)
    return fresh.replace(**{k: getattr(fresh, k).at[: pool.capacity].set(getattr(pool, k))
                            for k in ("pairs", "surface", "frame", "voxel_row")}, n=pool.n)


class PoolStats(NamedTuple):
    ok: jax.Array      # [] bool: the frame's pairs are in (False: nothing changed; grow and retry)
    needed: jax.Array  # [] int32: pairs the pool must hold after this frame


def _compact(pool: PairPool, keep) -> PairPool:
    """Move the kept pairs `keep [C] bool` to the front, in order."""
    c = pool.capacity
    dest = jnp.where(keep, prefix_sum(keep.astype(jnp.int32)) - 1, c)
    put = lambda a, fill: jnp.full_like(a, fill).at[dest].set(a, mode="drop")  # noqa: E731
    return pool.replace(pairs=put(pool.pairs, 0.0), surface=put(pool.surface, False), frame=put(pool.frame, -1),
                        voxel_row=put(pool.voxel_row, -1), n=jnp.sum(keep, dtype=jnp.int32))


def update(pool: PairPool, voxel_rows, points, labels, surface, frame, allowed=True, *, keyframes: int = 0):
    """Append a frame's pairs (voxel_rows [M] int32, -1 = drop; points [M, 3]; labels [M]; surface [M]).

    keyframes > 0: first forget the pairs of frames older than the last `keyframes` (this one
    included). All or nothing: if the pairs do not fit, or `allowed` is False, the pool comes back
    unchanged with ok False. Returns (pool, PoolStats).
    """
    c = pool.capacity
    held = jnp.arange(c) < pool.n
    if keyframes > 0:
        kept = _compact(pool, held & (pool.frame > frame - keyframes))
    else:
        kept = pool
    real = voxel_rows >= 0
    needed = kept.n + jnp.sum(real, dtype=jnp.int32)
    ok = jnp.asarray(allowed, bool) & (needed <= c)
    dest = jnp.where(real & ok, kept.n + prefix_sum(real.astype(jnp.int32)) - 1, c)
    new = kept.replace(
        pairs=kept.pairs.at[dest].set(jnp.concatenate([points, labels[:, None]], -1), mode="drop"),
        surface=kept.surface.at[dest].set(surface, mode="drop"),
        frame=kept.frame.at[dest].set(frame, mode="drop"),
        voxel_row=kept.voxel_row.at[dest].set(voxel_rows, mode="drop"),
        n=jnp.where(ok, needed, kept.n),
    )
    if keyframes > 0:  # (the compaction moved pairs: undo it too; the pool holds only N frames here)
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, pool)
    return new, PoolStats(ok, needed)


def sample(key, pool: PairPool, *, batch: int):
    """`batch` pairs uniformly (with replacement) from the pool: (index [batch] int32, mask [batch])."""
    i = jax.random.randint(key, (batch,), 0, jnp.maximum(pool.n, 1))
    return i, jnp.broadcast_to(pool.n > 0, (batch,))
