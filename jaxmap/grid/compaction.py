"""Compaction of batched loops: a batch whose entries finish at different rounds is gathered into
smaller static buffers as it goes (`staged_while`), with the prefix sums that place the survivors.

The hash table's probing (`jaxmap.grid.hashing`) runs on it; the pair store and the device
preprocessing use `prefix_sum` / `nonzero_fixed` to pack selections into fixed-size arrays.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

SHRINK = 8  # batch compaction factor between stages
MIN_STAGE = 512  # no compaction stage smaller than this


def prefix_sum(x: jax.Array) -> jax.Array:
    """Inclusive prefix sum along axis 0 as a parallel scan: on XLA's CPU backend ``jnp.cumsum``
    lowers to a reduce-window that is 3-5x slower at the 10^5-10^6 sizes of a frame."""
    return lax.associative_scan(jnp.add, x, axis=0)


def nonzero_fixed(mask: jax.Array, size: int, fill_value: int) -> jax.Array:
    """``jnp.nonzero(mask, size=size, fill_value=fill_value)[0]`` (1-D, int32) through `prefix_sum`."""
    n = mask.shape[0]
    pos = prefix_sum(mask.astype(jnp.int32)) - 1
    out = jnp.full((size,), fill_value, jnp.int32)
    return out.at[jnp.where(mask, pos, size)].set(jnp.arange(n, dtype=jnp.int32), mode="drop")


def nonzero_from(mask: jax.Array, size: int, start) -> jax.Array:
    """Indices [size] int32 of the first `size` True entries of mask [n] counted from entry `start` (a traced
    int, wrapping past the end), n where there are fewer: a window over a selection larger than a fixed
    buffer that the caller moves from call to call, so that every entry has its turn."""
    n = mask.shape[0]
    idx = nonzero_fixed(jnp.roll(mask, -start), size, n)
    return jnp.where(idx < n, (idx + start) % n, n)


def stage_sizes(n: int) -> list[int]:
    """Static buffer sizes of the compaction stages of a batch of ``n`` keys: n/8, n/64, ... (>= 512)."""
    sizes = []
    while n // SHRINK >= MIN_STAGE:
        n = n // SHRINK
        sizes.append(n)
    return sizes


def staged_while(guard, live, body, kill, const, state, shared, sizes):
    """``while guard(shared) and any(live): body`` over a batch, shrinking the batch as keys finish.

    Most keys resolve in the first one or two probe rounds and a few need ten or more, so running every
    round over the whole batch wastes most of the work. Stage ``k`` runs rounds until at most
    ``sizes[k]`` keys are live, then the live keys are gathered (``jnp.nonzero`` with a static size)
    into a buffer of that size, the next stage runs on it, and its per-key state is scattered back.
    Semantics are those of one loop over the whole batch: finished keys take no part in a round.

    Args:
      guard: ``shared -> [] bool`` (e.g. round < bound).
      live: ``(const, state, shared) -> [n] bool`` keys still working.
      body: ``(const, state, shared) -> (state, shared)``: one round.
      kill: ``(const, state, ok [m]) -> (const, state)``: disable the padding entries (``~ok``) of a stage.
      const: pytree of ``[n, ...]`` per-key inputs (gathered into stages, never written back).
      state: pytree of ``[n, ...]`` per-key state (gathered, then scattered back).
      shared: pytree carried whole (table arrays, round counter).
      sizes: static stage sizes, decreasing.
    Returns:
      ``(state, shared)``.
    """
    limit = sizes[0] if sizes else 0

    def cond(carry):
        st, sh = carry
        return guard(sh) & (jnp.sum(live(const, st, sh), dtype=jnp.int32) > limit)

    state, shared = lax.while_loop(cond, lambda c: body(const, *c), (state, shared))
    if not sizes:
        return state, shared
    n = jax.tree_util.tree_leaves(const)[0].shape[0]
    sel = nonzero_fixed(live(const, state, shared), sizes[0], n)  # [m]
    ok = sel < n  # [m]
    take = jnp.where(ok, sel, 0)  # [m]
    sub_const = jax.tree_util.tree_map(lambda x: x[take], const)
    sub_state = jax.tree_util.tree_map(lambda x: x[take], state)
    sub_const, sub_state = kill(sub_const, sub_state, ok)
    sub_state, shared = staged_while(guard, live, body, kill, sub_const, sub_state, shared, sizes[1:])
    put = jnp.where(ok, sel, n)  # [m] padding writes nowhere
    state = jax.tree_util.tree_map(lambda full, sub: full.at[put].set(sub, mode="drop"), state, sub_state)
    return state, shared
