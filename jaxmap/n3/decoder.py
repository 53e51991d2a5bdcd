"""The shared SDF decoder: a tiny MLP from the summed multi-level feature to a signed distance.

One implementation, the flax module: `init_decoder` makes its parameters and `decode` applies it in
the hot path (the loss, twice differentiated, and queries). Its compiled program is the one a
plain-jnp copy of the network compiled to (same optimised HLO, bit-identical outputs, measured on
the N3 loss and its gradients), so there is no second copy.
"""
from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp


class SDFDecoder(nn.Module):
    """features [..., D] -> sdf [...] in metres (positive in free space).

    `hidden_layers` fully connected layers of `hidden_dim` with ReLU, then a linear output
    (N3 paper: 2 x 32).
    """

    hidden_dim: int = 32
    hidden_layers: int = 2

    @nn.compact
    def __call__(self, feat):
        h = feat
        for _ in range(self.hidden_layers):
            h = nn.relu(nn.Dense(self.hidden_dim)(h))
        return nn.Dense(1)(h)[..., 0]


def init_decoder(key, feature_dim: int, hidden_dim: int, hidden_layers: int):
    """Returns (module, params)."""
    module = SDFDecoder(hidden_dim, hidden_layers)
    params = module.init(key, jnp.zeros((1, feature_dim), jnp.float32))
    return module, params


def decode(params, feat):
    """`SDFDecoder` on features [..., D] -> sdf [...], its sizes read from `params` (static shapes)."""
    layers = params["params"]
    return SDFDecoder(layers["Dense_0"]["kernel"].shape[1], len(layers) - 1).apply(params, feat)
