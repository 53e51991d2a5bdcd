"""Transformable neural implicit maps (IMT): the SO(3)-equivariant prior and the latent map.

The prior (`load_prior()`) turns the points and normals around a voxel into a latent `[18, 3]` of
3-vectors that rotates exactly with the input, and decodes a latent and a query position into an
SDF mean and standard deviation (voxel units) that are exactly invariant to a common rotation.
`rotate(tree, R)` rotates every `Vec`/`Jac`-marked leaf of a pytree (see `jaxmap.imt.vn`).

The latent map (docs/architecture.md) is pure functions over one state (`jaxmap.imt.core`: `init`,
`integrate` = one compiled `step` per frame, encode and fuse, `remap` = re-encode the keyframes whose
pose changed from their pooled cells in an immutable `KeyframeStore`, or, with `map.remap: transform`,
move their latent local maps kept in a `LatentStore`); `ImtMapper` is their facade over a sequence
(`jaxmap imt`). A local map as a value (`jaxmap.imt.local_maps`, thin wrappers over the same compiled
programs): `pool_cells` + `encode_frame` / `encode_world` / `encode_cells` (a frame's local map on the
world grid), `fuse` / `remove` (eq. 11 on sums), `transform` (eqs. 3-10, onto the global grid),
`keyframes_map`; `mesh` / `query` (decoded SDF, marching cubes).
"""
from jaxmap.config.prior import EncoderConfig, LatentDecoderConfig, PriorConfig
from jaxmap.imt.decoder import Decoder
from jaxmap.imt.encoder import Encoder, encode, encode_with_jacobian
from jaxmap.imt.prior import Prior, init_prior, load_prior, save_prior
from jaxmap.imt.latent_map import LatentMap, VoxelBatch, pool_cells
from jaxmap.imt.meshing import mesh, query
from jaxmap.imt.keyframe_store import KeyframeStore, RemapOptions
from jaxmap.imt.latent_store import LatentStore
from jaxmap.imt.core import CellBatch, ImtState, ImtStatic, StepStats, init, integrate, remap, step
from jaxmap.imt.interpolation import transform_batch
from jaxmap.imt.local_maps import encode_cells, encode_frame, encode_world, fuse, keyframes_map, remove, transform
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
    "KeyframeStore", "LatentMap", "LatentStore", "RemapOptions", "VoxelBatch", "encode_cells", "encode_frame", "keyframes_map",
    "encode_world", "fuse", "mesh", "pool_cells",
    "query", "remap", "remove", "transform", "transform_batch",
    "Decoder", "LatentDecoderConfig", "Encoder", "EncoderConfig", "Jac", "Prior", "PriorConfig", "VNLeakyReLU",
    "VNLinear", "Vec", "encode", "encode_with_jacobian", "gram_upper", "init_prior", "invariant_features",
    "load_prior", "rotate", "rotate_jacobians", "save_prior", "vn_inner", "vn_mean_pool",
]
