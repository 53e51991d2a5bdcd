"""Transformable neural implicit maps (IMT): the SO(3)-equivariant prior and the latent map.

The prior (`load_prior()`) turns the points and normals around a voxel into a latent `[18, 3]` of
3-vectors that rotates exactly with the input, and decodes a latent and a query position into an
SDF mean and standard deviation (voxel units) that are exactly invariant to a common rotation.
`rotate(tree, R)` rotates every `Vec`/`Jac`-marked leaf of a pytree (see `jaxmap.imt.vn`).

The latent map (docs/architecture.md): `pool_cells` + `encode_keyframes` / `encode_frame` (a frame's
local map on the world grid), `fuse` / `remove` (eq. 11 on sums), `transform` (eqs. 3-10, onto the
global grid), `mesh` / `query` (decoded SDF, marching cubes). The map of a sequence is pure functions
over one state (`jaxmap.imt.core`: `init`, `integrate` = one compiled `step` per frame, `remap` =
re-encode the keyframes whose pose changed from their pooled cells in an immutable `KeyframeStore`,
or, with `map.remap: transform`, move their latent local maps kept in a `LatentStore`); `ImtMapper`
is their facade over a sequence (`jaxmap imt`).
"""
from jaxmap.config.prior import EncoderConfig, LatentDecoderConfig, PriorConfig
from jaxmap.imt.decoder import Decoder
from jaxmap.imt.encoder import Encoder, encode, encode_with_jacobian
from jaxmap.imt.prior import Prior, init_prior, load_prior, save_prior
from jaxmap.imt.latent_map import (LatentMap, VoxelBatch, encode_cells, encode_frame, encode_keyframes, encode_world,
                                   fuse, pool_cells, remove)
from jaxmap.imt.meshing import mesh, query
from jaxmap.imt.keyframe_store import KeyframeStore, RemapOptions
from jaxmap.imt.latent_store import LatentStore
from jaxmap.imt.core import CellBatch, ImtState, ImtStatic, StepStats, init, integrate, remap, step
from jaxmap.imt.interpolation import transform, transform_batch
from jaxmap.imt.vn import (
    Jac,
    Vec,
    VNLeakyReLU,
    VNLinear,
    gram_upper,
    invariant_features,
    rotate,
    rotate_jacobians,
    vn_inner,
    vn_mean_pool,
)

__all__ = [
    "CellBatch", "ImtState", "ImtStatic", "StepStats", "init", "integrate", "step",
    "KeyframeStore", "LatentMap", "LatentStore", "RemapOptions", "VoxelBatch", "encode_cells", "encode_frame", "encode_keyframes",
    "encode_world", "fuse", "mesh", "pool_cells",
    "query", "remap", "remove", "transform", "transform_batch",
    "Decoder", "LatentDecoderConfig", "Encoder", "EncoderConfig", "Jac", "Prior", "PriorConfig", "VNLeakyReLU",
    "VNLinear", "Vec", "encode", "encode_with_jacobian", "gram_upper", "init_prior", "invariant_features",
    "load_prior", "rotate", "rotate_jacobians", "save_prior", "vn_inner", "vn_mean_pool",
]
