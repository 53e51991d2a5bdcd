"""The N3 signed-distance field at a point, and the training loss built on it with `jax.grad`.

The field is `sdf(x) = MLP(sum_c w_c(x) F_c)`: the trilinear weights `w_c(x)` of the point in its
leaf voxel's L*8 corner cells (all levels) times those corners' features `F [L*8, D]`, decoded by
the shared MLP (`decoder.decode`). Everything is written for ONE point and lifted with `jax.vmap`;
the eikonal term takes the spatial gradient with `jax.grad` and the loss is differentiated again by
the optimiser (N3 paper, eq. 1-3; multinerf computes normals the same way).
"""
from __future__ import annotations

import functools

import jax

from jaxmap.grid import features as gfeat
from jaxmap.n3.decoder import decode
from jaxmap.n3.loss import bce_loss, eikonal_loss


@functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3))
def trilinear_weights(x, leaf_vox, leaf: float, levels: int):
    """Weights [L*8] of one point x [3] in the corner cells of its leaf voxel leaf_vox [3] int32
    (`grid.features.corner_weights` for one point).

    Its JVP is the closed-form derivative `d w / d x` (`corner_weights_and_grad`): equal to what
    autodiff gives (tested), but autodiff would differentiate the clamp and the per-axis products
    twice inside the eikonal term, and this rule makes the whole loss 2-3x cheaper.
    """
    return gfeat.corner_weights(x[None], leaf_vox[None], leaf, levels)[0]


@trilinear_weights.defjvp
def _trilinear_weights_jvp(leaf, levels, primals, tangents):
    x, leaf_vox = primals
    w, dw = gfeat.corner_weights_and_grad(x[None], leaf_vox[None], leaf, levels)    # [1, L*8], [1, L*8, 3]
    return w[0], dw[0] @ tangents[0]


def sdf_at(x, corner_feats, leaf_vox, dec_params, *, leaf: float, levels: int):
    """SDF at one map-frame point. x: [3] float32; corner_feats: [L*8, D] features of the point's
    leaf voxel's corners (all levels, zero where unallocated); leaf_vox: [3] int32 the leaf voxel
    whose corners those are. Returns [] float32 (metres, positive towards the sensor)."""
    return decode(dec_params, trilinear_weights(x, leaf_vox, leaf, levels) @ corner_feats)


def group_sdf_and_grad(points, corner_feats, leaf_vox, dec_params, *, leaf: float, levels: int):
    """One voxel's pairs: points [K, 3] sharing corner_feats [L*8, D] and leaf_vox [3].
    Returns (sdf [K], d sdf / d x [K, 3])."""
    f = functools.partial(sdf_at, leaf=leaf, levels=levels)
    return jax.vmap(jax.value_and_grad(f), in_axes=(0, None, None, None))(points, corner_feats, leaf_vox,
                                                                          dec_params)


def n3_loss(corner_feats, dec_params, batch, leaf_vox, beta, weight_e, *, leaf: float, levels: int):
    """BCE + weight_e * eikonal over a batch of groups.

    corner_feats: [G, L*8, D]; batch: `hierarchical.Batch` with points [G, K, 3], labels [G, K],
    surface [G, K], mask [G, K]; leaf_vox: [G, 3] int32; beta, weight_e: [] float32.
    The eikonal term only counts pairs inside the truncation band (`surface`).
    Returns (loss [], (bce [], eikonal [])).
    """
    per_group = functools.partial(group_sdf_and_grad, leaf=leaf, levels=levels)
    sdf, grad = jax.vmap(per_group, in_axes=(0, 0, 0, None))(batch.points, corner_feats, leaf_vox, dec_params)
    l_bce = bce_loss(sdf, batch.labels, beta, batch.mask)
    l_eik = eikonal_loss(grad, batch.mask & batch.surface)
    return l_bce + weight_e * l_eik, (l_bce, l_eik)
