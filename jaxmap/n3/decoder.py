"""The shared SDF decoder: a tiny MLP from the summed multi-level feature to a signed distance."""
from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp


class SDFDecoder(nn.Module):
    """features [..., D] -> sdf [...] in metres (positive in free space). The parameters are used by
    `jaxmap.n3.field.mlp`, the same network written for one feature vector.

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
