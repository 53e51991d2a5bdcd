"""The equivariant prior: the `Prior` pytree and its shipped weights (save / load); its config is
`jaxmap.config.PriorConfig`, its training `jaxmap.imt.training` (`jaxmap prior train`).

`load_prior(path=None)` returns a `Prior` (a pytree: parameters + static model config) with
`encode`, `encode_with_jacobian` and `decode`; all units are voxels, all positions relative to the
voxel centre (see `encoder.py`, `decoder.py`).
"""
from __future__ import annotations

import functools
import importlib.resources
import json
import os
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from jaxmap.config import from_dict, to_dict
from jaxmap.config.prior import PriorModelConfig
from jaxmap.errors import JaxmapError
from jaxmap.imt.decoder import Decoder
from jaxmap.imt.encoder import Encoder
from jaxmap.imt.encoder import encode as _encode
from jaxmap.imt.encoder import encode_with_jacobian as _encode_with_jacobian

WEIGHTS_FILE = "prior.npz"
DEFAULT_CONFIG = "prior"  # the shipped config (jaxmap/configs/prior.yaml), by name


# ---------------------------------------------------------------------------------------------
# The prior object
# ---------------------------------------------------------------------------------------------


@flax.struct.dataclass
class Prior:
    """Trained encoder + decoder. A pytree (pass it through `jit`); `cfg` is static.

    params: `{"encoder": ..., "decoder": ...}` flax parameter trees.
    """

    params: Any
    cfg: PriorModelConfig = flax.struct.field(pytree_node=False, default=PriorModelConfig())

    @property
    def encoder(self) -> Encoder:
        return Encoder(self.cfg.encoder)

    @property
    def decoder(self) -> Decoder:
        return Decoder(self.cfg.decoder)

    @property
    def latent_channels(self) -> int:
        return 2 * self.cfg.encoder.latent

    def encode(self, points, normals, mask=None):
        """`[..., N, 3]` points/normals (voxel-centred, voxel units), mask `[..., N]` ->
        `(F [..., 18, 3], count [...])`."""
        return _encode(self.encoder, {"params": self.params["encoder"]}, points, normals, mask)

    def encode_with_jacobian(self, points, normals, mask=None):
        """-> `(F [..., 18, 3], J [..., 18, 3, 3], count [...])`; `J = dF/dt` for points + t (exact)."""
        return _encode_with_jacobian(self.encoder, {"params": self.params["encoder"]}, points, normals, mask)

    def per_point(self, points, normals):
        """Per-point features before pooling: points, normals `[P, 3]` (voxel-centred, voxel units) ->
        `[P, 18, 3]` (the map's encode: a voxel's latent is their count-weighted mean)."""
        return self.encoder.apply({"params": self.params["encoder"]}, points, normals, method=Encoder.per_point)

    def decode(self, latent, queries):
        """`(F [..., 18, 3], q [..., 3]) -> (sdf mean [...], std [...])`, voxel units, leading dims
        broadcast (e.g. `F[:, None]` with `q [V, Q, 3]`). Invariant: `decode(F R^T, q R^T) == decode(F, q)`."""
        return self.decoder.apply({"params": self.params["decoder"]}, latent, queries)


def init_prior(cfg: PriorModelConfig, key) -> Prior:
    """Freshly initialised prior (random weights)."""
    return Prior(_init_params(cfg, key), cfg)


@functools.partial(jax.jit, static_argnums=0)
def _init_params(cfg: PriorModelConfig, key):
    """Parameters of a model config, compiled once per config by jit (compiling costs ~1 s)."""
    ke, kd = jax.random.split(key)
    pts = jnp.zeros((1, 4, 3))
    f = jnp.zeros((1, 2 * cfg.encoder.latent, 3))
    enc = Encoder(cfg.encoder).init(ke, pts, pts)["params"]
    dec = Decoder(cfg.decoder).init(kd, f, jnp.zeros((1, 3)))["params"]
    return {"encoder": enc, "decoder": dec}


def count_params(tree) -> int:
    return int(sum(np.size(x) for x in jax.tree_util.tree_leaves(tree)))


def save_prior(prior: Prior, path: str | os.PathLike, meta: dict | None = None) -> int:
    """Write weights (float32), model config and `meta` to one `.npz`. Returns the file size in bytes."""
    flat = traverse_util.flatten_dict(jax.device_get(prior.params), sep="/")
    arrays = {k: np.asarray(v, dtype=np.float32) for k, v in flat.items()}
    arrays["__model_config__"] = np.array(json.dumps(to_dict(prior.cfg)))
    arrays["__meta__"] = np.array(json.dumps(meta or {}))
    path = os.fspath(path)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    tmp = path + ".tmp.npz"
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)
    return os.path.getsize(path)


def shipped_weights_path() -> str:
    return str(importlib.resources.files("jaxmap.imt") / "weights" / WEIGHTS_FILE)


def load_prior(path: str | os.PathLike | None = None, with_meta: bool = False):
    """Load a prior from a `.npz` written by `save_prior` (default: the weights shipped in the package).

    Returns a `Prior` (or `(Prior, meta dict)` with `with_meta`).
    """
    path = shipped_weights_path() if path is None else os.fspath(path)
    if not os.path.isfile(path):
        raise JaxmapError(f"prior weights not found: {path}; train them with `jaxmap prior train prior`")
    with np.load(path) as z:
        cfg = from_dict(PriorModelConfig, json.loads(str(z["__model_config__"])), source=path)
        meta = json.loads(str(z["__meta__"])) if "__meta__" in z else {}
        flat = {k: jnp.asarray(z[k]) for k in z.files if not k.startswith("__")}
    params = traverse_util.unflatten_dict(flat, sep="/")
    prior = Prior(params, cfg)
    ref = jax.eval_shape(functools.partial(_init_params, cfg), jax.random.PRNGKey(0))
    if jax.tree_util.tree_structure(ref) != jax.tree_util.tree_structure(params) or any(
        a.shape != b.shape for a, b in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(params))
    ):
        raise JaxmapError(f"{path}: weights do not match the model config stored with them")
    return (prior, meta) if with_meta else prior
