"""N3 loss: BCE on sigmoid(sdf / beta) against sigmoid(label / beta), plus the eikonal term.

L = BCE(sigmoid(f(x)/beta), sigmoid(s/beta)) + weight_e * (|grad_x f(x)| - 1)^2, the eikonal term
on pairs inside the truncation band (N3 paper, eq. 1-3). Both are means over the valid pairs.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import optax


def bce_loss(pred_sdf, label_sdf, beta: float, mask):
    """Mean over `mask` of BCE with logits pred/beta and targets sigmoid(label/beta). All [...]."""
    target = jax.nn.sigmoid(label_sdf / beta)
    per = optax.sigmoid_binary_cross_entropy(pred_sdf / beta, target)
    # The BCE of a soft target has a non-zero floor (its entropy); subtract it so a perfect fit reads 0.
    floor = optax.sigmoid_binary_cross_entropy(label_sdf / beta, target)
    m = mask.astype(per.dtype)
    return jnp.sum((per - floor) * m) / jnp.maximum(m.sum(), 1.0)


def eikonal_loss(grad_x, mask):
    """Mean over `mask` of (|grad|-1)^2. grad_x: [..., 3]; mask: [...]."""
    norm = jnp.sqrt(jnp.sum(grad_x**2, axis=-1) + 1e-12)
    m = mask.astype(norm.dtype)
    return jnp.sum((norm - 1.0) ** 2 * m) / jnp.maximum(m.sum(), 1.0)


def sdf_and_grad(sdf_fn, points):
    """sdf_fn maps [..., 3] -> [...] pointwise. Returns (sdf [...], d sdf / d x [..., 3])."""
    sdf, vjp = jax.vjp(sdf_fn, points)
    (grad,) = vjp(jnp.ones_like(sdf))
    return sdf, grad
