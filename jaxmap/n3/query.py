"""Reading the N3 map: SDF (and its gradient) at map-frame points (`query`, pure; the frame program's
point filter uses it too), and host-side wrappers: world -> map frame in float64, fixed-size chunks
(one compile for any number of points), and the marching-cubes mesh.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.config import ConfigError
from jaxmap.grid import hashing
from jaxmap.grid.features import leaf_voxel, query_features
from jaxmap.n3 import evidence as n3evidence
from jaxmap.mesh import extract_mesh
from jaxmap.n3.decoder import decode
from jaxmap.n3.loss import sdf_and_grad
from jaxmap.n3.state import N3State, N3Static, origin_world

CHUNK = 1 << 16  # points per compiled query call


def query(static: N3Static | QueryStatic, state: N3State, points_m):
    """SDF at map-frame points [N, 3] -> (sdf [N] float32, valid [N] bool) (static: an N3Static, or the
    QueryStatic of one: the fields a query reads).

    A point is valid where the 8 corners of its level-`mask_level` voxel have features (0 = only
    inside allocated leaf voxels; 1 = inside their 2x parents, which closes the gaps between LiDAR
    rings on grazing ground, as SHINE/N3 mesh at `mc_vis_level` 1), and at least `min_leaf_corners`
    of the 8 corners of its leaf voxel have features, and its leaf voxel is not void (free-space evidence:
    seen free since its last hit, `jaxmap.n3.evidence`). Corners without features count as zero.
    """
    f, rows = query_features(state.corners, state.feature_table, points_m, static.leaf, static.levels)
    ml = static.mask_level
    valid = jnp.all(rows[:, ml * 8:(ml + 1) * 8] >= 0, axis=1)                     # rows: [N, L*8]
    valid &= jnp.sum(rows[:, :8] >= 0, axis=1) >= static.min_leaf_corners
    if static.evidence:
        vrow = voxel_rows(static, state, points_m)
        valid &= ~((vrow >= 0) & n3evidence.void(state.evidence, static.void_frames)[jnp.maximum(vrow, 0)])
    return jax.vmap(decode, in_axes=(None, 0))(state.decoder, f), valid


def voxel_rows(static: N3Static, state: N3State, points_m):
    """The voxel row of the leaf voxel of each map-frame point [N, 3] -> [N] int32 (-1: not allocated)."""
    pv = leaf_voxel(points_m, static.leaf)
    return hashing.lookup(state.voxels, jnp.concatenate([pv, jnp.zeros_like(pv[:, :1])], -1))


@dataclasses.dataclass(frozen=True)
class QueryStatic:
    """What `query` reads of an N3Static (the compiled query programs' static argument): maps whose configs
    differ only in what a query does not read (training, window, preprocessing, the submaps' layout) share
    their query programs, in one process and in the compile cache."""

    leaf: float
    levels: int
    mask_level: int
    min_leaf_corners: int
    evidence: bool
    void_frames: int

    @classmethod
    def of(cls, static) -> "QueryStatic":
        return cls(static.leaf, static.levels, static.mask_level, static.min_leaf_corners, static.evidence,
                   static.void_frames)


def query_view(state: N3State) -> N3State:
    """What a query and the mesh read of a state (hash tables, features, decoder, evidence, origin): without
    the pair store, the Adam moments and the voxels' corner rows, a third of the memory of the whole (and one
    pytree for a map being mapped and one read back: one compiled query program for both)."""
    return state.replace(store=None, pool=None, feature_opt=None, decoder_opt=None, voxel_corner_rows=None)


@functools.partial(jax.jit, static_argnums=0)
def _query_jit(qs: QueryStatic, view: N3State, points_m):
    return query(qs, view, points_m)


@functools.partial(jax.jit, static_argnums=0)
def _query_grad_jit(qs: QueryStatic, view: N3State, points_m):
    return sdf_and_grad(lambda p: query(qs, view, p)[0], points_m)


def query_jit(static: N3Static, state: N3State, points_m):
    """(sdf [N], valid [N]) at map-frame points [N, 3], compiled once per QueryStatic and shapes."""
    return _query_jit(QueryStatic.of(static), query_view(state), points_m)


def query_grad_jit(static: N3Static, state: N3State, points_m):
    """(sdf [N], d sdf / d x [N, 3]) at map-frame points [N, 3]."""
    return _query_grad_jit(QueryStatic.of(static), query_view(state), points_m)


def query_world(static: N3Static, state: N3State, points_w, grad: bool = False, small_tail: bool = False):
    """SDF at world points [N, 3] -> (sdf [N] float32, valid [N] bool), or with `grad`
    (sdf [N], d sdf / d x [N, 3]), in CHUNK-sized compiled calls. small_tail: the last call is padded to
    the next power of two from 4096 instead of CHUNK (a map of submaps reads many small parts: four
    more compiled sizes, against up to 16x the points computed)."""
    pts = np.asarray(points_w, np.float64).reshape(-1, 3) - origin_world(static, state)
    fn = query_grad_jit if grad else query_jit
    out = []
    for i in range(0, len(pts), CHUNK):
        chunk = pts[i:i + CHUNK].astype(np.float32)
        m = len(chunk)
        if m < CHUNK:
            size = min(max(4096, 1 << (m - 1).bit_length()), CHUNK) if small_tail else CHUNK
            chunk = np.concatenate([chunk, np.zeros((size - m, 3), np.float32)])
        out.append([np.asarray(r)[:m] for r in fn(static, state, chunk)])
    if not out:
        return np.zeros(0, np.float32), (np.zeros((0, 3), np.float32) if grad else np.zeros(0, bool))
    return tuple(np.concatenate([o[k] for o in out]) for k in range(2))


def mesh_cells(leaf_voxels: np.ndarray, mask_level: int) -> np.ndarray:
    """Leaf cells [M,3] covered by the level-`mask_level` parents of allocated leaf voxels [N,3]."""
    if mask_level == 0 or len(leaf_voxels) == 0:
        return leaf_voxels
    k = 1 << mask_level
    parents = np.unique(np.floor_divide(leaf_voxels, k), axis=0)
    offs = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return (parents[:, None, :] * k + offs[None]).reshape(-1, 3).astype(np.int32)


def check_mesh_resolution(leaf: float, res: float) -> None:
    """ConfigError unless the mesh resolution `res` is positive and divides the leaf voxel size."""
    k = leaf / res if res > 0 else 0.0
    if res <= 0 or abs(k - round(k)) > 1e-6:
        raise ConfigError(f"mesh resolution {res:g} m must be positive and divide the leaf voxel size "
                          f"{leaf:g} m (e.g. {leaf / 2:g} or {leaf:g})")


def extract_mesh_of(static: N3Static, state: N3State, res: float, min_component_faces: int):
    """Marching-cubes mesh of the zero level set (trimesh.Trimesh, world frame) on the lattice
    `k * res` of the map frame, whose origin is a multiple of the coarsest voxel: `res` must divide
    the leaf voxel size, so every method and run meshes on the same world lattice."""
    check_mesh_resolution(static.leaf, res)
    n = int(state.voxels.count)
    coords = np.asarray(state.voxel_coord[:n])
    if static.evidence:
        # only the parents of leaves that are not void: a parent whose every allocated leaf is void holds
        # no surface (its unallocated leaves have no evidence of their own, and are meshed with their parent)
        coords = coords[~np.asarray(n3evidence.void(state.evidence, static.void_frames)[:n])]
    cells = mesh_cells(coords, static.mask_level)
    origin = origin_world(static, state)

    def sdf_fn(p_m):
        return query_world(static, state, p_m.astype(np.float64) + origin)

    mesh = extract_mesh(sdf_fn, cells, static.leaf, res, min_component_faces=min_component_faces)
    mesh.apply_translation(origin)
    return mesh
