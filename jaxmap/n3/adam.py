"""Sparse ("lazy") Adam for a feature table, as an optax gradient transformation.

A batch touches a few thousand rows of a table of up to millions; dense Adam would read and write
every row each step. `sparse_adam(learning_rate)` is an `optax.GradientTransformation` like
`optax.adam(learning_rate)`: `update` returns the updates to add (the learning rate and the sign
included) and the new state, and `apply_updates` adds them. Its gradients and updates are sparse,
the rows the batch touched and their values:

    opt = sparse_adam(lr, b1=0.9, b2=0.999, eps=1e-8)
    state = opt.init(table)                                       # table: [R, D]
    updates, state = opt.update(SparseGrads(rows, grads), state)  # rows: [M] int32, grads: [M, D]
    table = apply_updates(table, updates)

A row that a step touches takes exactly dense Adam's step with the summed gradient of its
occurrences in the batch; rows it does not touch keep their values *and* moments (that is what
"lazy" means: dense Adam would still decay their moments and move them). Bias correction uses a
step count *per row* (the steps that touched it): a row first touched at global step 5000 takes the
steps of a fresh Adam (about lr each), where one global count would scale its first steps by up to
~6x (the moments start at zero, but 1 - b^t has long reached 1). No `jit` inside: callers jit.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax


class SparseAdamState(NamedTuple):
    count: jax.Array    # [R] int32: steps that touched each row (its bias correction)
    moments: jax.Array  # [R, 3, D] float32: per row (mu, nu, acc); `acc` is zero between steps, the
                        # scratch in which a step sums the gradients of duplicate rows without an
                        # O(R) buffer or a sort. Packed because one gather/scatter of a row's 96
                        # bytes is ~3x faster on the CPU than three of 32 (measured: 1.4 vs 4.9 ms
                        # per step of 24k rows); read it through `mu` / `nu`.

    @property
    def mu(self) -> jax.Array:
        """[R, D] first moments."""
        return self.moments[:, _MU]

    @property
    def nu(self) -> jax.Array:
        """[R, D] second moments."""
        return self.moments[:, _NU]


_MU, _NU, _ACC = 0, 1, 2


class SparseGrads(NamedTuple):
    rows: jax.Array    # [M] int32 rows of the batch (-1 = padding, duplicates allowed)
    values: jax.Array  # [M, D] their gradients


class SparseUpdates(NamedTuple):
    rows: jax.Array    # [M] int32 rows to change (R, out of range, where nothing changes)
    values: jax.Array  # [M, D] to add to them (every occurrence of a row carries the same value)


def sparse_adam(learning_rate, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8) -> optax.GradientTransformation:
    """Lazy Adam over table rows. learning_rate: [] (may be traced: changing it never recompiles)."""

    def init(table: jax.Array) -> SparseAdamState:
        r, d = table.shape
        return SparseAdamState(count=jnp.zeros((r,), jnp.int32), moments=jnp.zeros((r, 3, d), table.dtype))

    def update(grads: SparseGrads, state: SparseAdamState, params=None, active=True):
        """One step on the rows of a batch -> (SparseUpdates, state).

        active: [] bool, False makes the step a no-op (counts included). Cost O(M D): one
        scatter-add, gathers of the touched rows, one scatter-set per array. Every occurrence of a
        row computes the same new values, so the scatter-sets are deterministic.
        """
        del params
        r = state.count.shape[0]
        idx = jnp.where((grads.rows >= 0) & active, grads.rows, r)          # r: out of range, dropped
        moments = state.moments.at[idx, _ACC].add(grads.values, mode="drop")
        x = moments.at[idx].get(mode="fill", fill_value=0.0)                # [M, 3, D]
        g = x[:, _ACC]                                                      # summed per row
        c = state.count.at[idx].get(mode="fill", fill_value=0) + 1          # [M] this step's count
        t = c.astype(jnp.float32)[:, None]
        mu = b1 * x[:, _MU] + (1.0 - b1) * g
        nu = b2 * x[:, _NU] + (1.0 - b2) * g * g
        step = learning_rate * (mu / (1.0 - b1**t)) / (jnp.sqrt(nu / (1.0 - b2**t)) + eps)
        new = jnp.stack([mu, nu, jnp.zeros_like(mu)], axis=1)
        return (SparseUpdates(idx, -step),
                SparseAdamState(count=state.count.at[idx].set(c, mode="drop"),
                                moments=moments.at[idx].set(new, mode="drop")))

    return optax.GradientTransformation(init, update)


def apply_updates(table: jax.Array, updates: SparseUpdates) -> jax.Array:
    """`optax.apply_updates` for sparse updates: table [R, D] with the updates added to their rows."""
    value = table.at[updates.rows].get(mode="fill", fill_value=0.0) + updates.values
    return table.at[updates.rows].set(value, mode="drop")


def reset(state: SparseAdamState) -> SparseAdamState:
    """Fresh moments and step count (the original N3 code rebuilds its optimiser every frame)."""
    return SparseAdamState(count=jnp.zeros_like(state.count), moments=jnp.zeros_like(state.moments))
