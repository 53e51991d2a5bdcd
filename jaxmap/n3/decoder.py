"""The shared SDF decoder: a tiny MLP from the summed multi-level feature to a signed distance."""
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


def mlp_with_input_grad(params, feat):
    """The decoder's forward pass and its gradient w.r.t. the input, written out explicitly.

    params: the flax params of `SDFDecoder`; feat: [..., D]. Returns (sdf [...], d sdf / d feat [..., D]).
    Equal to `SDFDecoder.apply` and its `jax.grad`; written by hand because the eikonal loss
    differentiates this gradient again, and one reverse pass over these few matmuls is much cheaper
    than autodiff of autodiff.
    """
    layers = params["params"]
    names = sorted(layers, key=lambda k: int(k.split("_")[-1]))
    h, masks = feat, []
    for name in names[:-1]:
        z = h @ layers[name]["kernel"] + layers[name]["bias"]
        m = z > 0
        h = jnp.where(m, z, 0.0)
        masks.append(m)
    out = layers[names[-1]]
    sdf = (h @ out["kernel"] + out["bias"])[..., 0]
    g = jnp.broadcast_to(out["kernel"][:, 0], h.shape)
    for name, m in zip(reversed(names[:-1]), reversed(masks)):
        g = jnp.where(m, g, 0.0) @ layers[name]["kernel"].T
    return sdf, g
