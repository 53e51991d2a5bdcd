"""Rotation-invariant SDF decoder: latent `[C, 3]` + query `[3]` -> SDF mean and standard deviation.

Frame and units: the query `q` is relative to the voxel centre in voxel units, in the same frame
as the latent rows. Outputs are in voxel units (multiply by the voxel size for metres).

Invariance by construction: the MLP sees only the invariant layer's scalars (`vn.invariant_features`):
the Gram upper triangle of F (`C (C+1) / 2` inner products), `F q` (C) and `|q|^2`. Hence
`decode(F R^T, R q) == decode(F, q)` for every orthogonal R up to float rounding, with no learning
involved (the original IMT decoder, a plain MLP on the flattened latent, only learned this
approximately).

The first dense layer is split into a per-voxel part (on the Gram features) and a per-query part,
which is the same function as one dense layer on the concatenation but lets a voxel's Gram term be
computed once for all of its queries when F is broadcast (e.g. `F [V, 1, C, 3]`, `q [V, Q, 3]`).
"""
from __future__ import annotations


import flax.linen as nn
import jax

from jaxmap.config.prior import LatentDecoderConfig
from jaxmap.imt.vn import invariant_features


class Decoder(nn.Module):
    """`(F [..., C, 3], q [..., 3]) -> (mean [...], std [...])`, leading dims broadcast."""

    cfg: LatentDecoderConfig = LatentDecoderConfig()

    @nn.compact
    def __call__(self, f: jax.Array, q: jax.Array) -> tuple[jax.Array, jax.Array]:
        c = self.cfg
        g, s = invariant_features(f, q)
        h = nn.Dense(c.hidden, name="in_gram")(g) + nn.Dense(c.hidden, use_bias=False, name="in_query")(s)
        h = jax.nn.silu(h)
        for i in range(c.layers - 1):
            h = jax.nn.silu(nn.Dense(c.hidden, name=f"hidden{i}")(h)) + h
        out = nn.Dense(2, name="out")(h)
        mean = out[..., 0]
        std = jax.nn.softplus(out[..., 1]) + c.min_std
        return mean, std
