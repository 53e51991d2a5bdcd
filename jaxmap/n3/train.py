"""Training the N3 map on its window: K iterations of (hierarchical) batch selection, loss (BCE +
eikonal through `jax.grad`) and Adam in one `lax.fori_loop`, traced inside the frame program
(`jaxmap.n3.frame.step`).
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from jaxmap.n3 import adam, hierarchical
from jaxmap.n3.field import n3_loss
from jaxmap.n3.state import N3State, N3Static


def _batch(static: N3Static, state: N3State, store, ids, n, key):
    """One iteration's batch: from the flat pool (replay / keyframe ablations), hierarchical or uniform."""
    if static.uses_pool:
        return hierarchical.sample_pool(key, state.pool, state.voxel_coord, batch=static.batch_size)
    if static.hierarchical:
        return hierarchical.sample_hierarchical(key, store, ids, n, nv=static.nv, np_=static.np_per_voxel, nt=static.nt)
    return hierarchical.sample_uniform(key, store, ids, n, batch=static.batch_size)


class TrainStats(NamedTuple):
    loss: jax.Array     # [] mean over the K iterations
    bce: jax.Array
    eikonal: jax.Array


@functools.partial(jax.named_call, name="train")
def train(static: N3Static, state: N3State, key, active=True) -> tuple[N3State, TrainStats]:
    """K iterations of (hierarchical) batch selection, loss and Adam over the current window.

    Features get sparse Adam on the rows each batch touches (O(batch) per iteration, however large
    the map); the decoder gets Adam until frame `freeze_after_frame`. active: [] bool; False runs
    no iteration and leaves the state as it is (a frame that did not fit yet).
    """
    active = jnp.asarray(active, bool)
    store, h = state.store, state.hyper
    ids, n = store.window_ids, store.window_n
    # Both optimisers are `optax.adam(lr)`: updates to add, the learning rate included.
    opt = adam.sparse_adam(h.lr)
    dec_tx = optax.adam(h.lr)
    train_decoder = active & (state.frame < static.freeze_after_frame)
    feature_opt = state.feature_opt
    if static.reset_adam:  # the original N3 code rebuilds its optimiser every frame
        fresh = adam.reset(feature_opt)
        feature_opt = jax.tree_util.tree_map(lambda a, b: jnp.where(active, a, b), fresh, feature_opt)
    loss = functools.partial(n3_loss, leaf=static.leaf, levels=static.levels)
    grad_both = jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)
    grad_feats = jax.value_and_grad(loss, argnums=0, has_aux=True)

    def loss_grad(*args):
        # The decoder's gradient costs ~40 % of the step; once it is frozen it is not computed.
        def feats_only(args):
            out, g = grad_feats(*args)
            return out, (g, jax.tree_util.tree_map(jnp.zeros_like, args[1]))

        return jax.lax.cond(train_decoder, lambda a: grad_both(*a), feats_only, args)

    def body(_, carry):
        table, f_opt, dec, d_opt, key, acc = carry
        key, k = jax.random.split(key)
        with jax.named_scope("batch"):
            b = _batch(static, state, store, ids, n, k)
            rows = state.voxel_corner_rows[jnp.maximum(b.voxel_rows, 0)]                 # [G, L*8]
            feats = table[jnp.maximum(rows, 0)]                                          # [G, L*8, D]
        with jax.named_scope("loss"):
            (loss, (l_bce, l_eik)), (g_feat, g_dec) = loss_grad(feats, dec, b, b.coords, h.beta, h.weight_e)
        with jax.named_scope("adam"):
            upd, f_opt = opt.update(adam.SparseGrads(rows.reshape(-1), g_feat.reshape(-1, table.shape[-1])), f_opt)
            table = adam.apply_updates(table, upd)
            # The decoder's state is optax.adam's first part (scale_by_adam); its learning-rate part has none.
            upd, (d_opt_new, _) = dec_tx.update(g_dec, (d_opt, optax.EmptyState()), dec)
            dec_new = optax.apply_updates(dec, upd)
            dec, d_opt = jax.tree_util.tree_map(lambda a, b: jnp.where(train_decoder, a, b), (dec_new, d_opt_new),
                                                (dec, d_opt))
        return table, f_opt, dec, d_opt, key, acc + jnp.stack([loss, l_bce, l_eik])

    n_iters = jnp.where(active, h.iters, 0)
    carry = (state.feature_table, feature_opt, state.decoder, state.decoder_opt, key, jnp.zeros((3,)))
    table, f_opt, dec, d_opt, _, acc = jax.lax.fori_loop(0, n_iters, body, carry)
    acc = acc / jnp.maximum(h.iters, 1)
    state = state.replace(feature_table=table, feature_opt=f_opt, decoder=dec, decoder_opt=d_opt,
                          frame=state.frame + active.astype(jnp.int32))
    return state, TrainStats(acc[0], acc[1], acc[2])
