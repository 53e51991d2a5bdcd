"""Reading the N3 map: SDF (and its gradient) at world points, and the marching-cubes mesh.

Host-side wrappers over the jitted `core.query`: world -> map frame in float64, fixed-size chunks
(one compile for any number of points).
"""
from __future__ import annotations

import numpy as np

from jaxmap.n3 import core

CHUNK = 1 << 16  # points per compiled query call


def query_world(static: core.N3Static, state: core.N3State, points_w, grad: bool = False):
    """SDF at world points [N, 3] -> (sdf [N] float32, valid [N] bool), or with `grad`
    (sdf [N], d sdf / d x [N, 3]), in CHUNK-sized compiled calls."""
    pts = np.asarray(points_w, np.float64).reshape(-1, 3) - core.origin_world(static, state)
    fn = core.query_grad_jit if grad else core.query_jit
    out = []
    for i in range(0, len(pts), CHUNK):
        chunk = pts[i:i + CHUNK].astype(np.float32)
        m = len(chunk)
        if m < CHUNK:
            chunk = np.concatenate([chunk, np.zeros((CHUNK - m, 3), np.float32)])
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


def extract_mesh_of(static: core.N3Static, state: core.N3State, res: float, min_component_faces: int):
    """Marching-cubes mesh of the zero level set (trimesh.Trimesh, world frame) on the lattice
    `k * res` of the map frame, whose origin is a multiple of the coarsest voxel: `res` must divide
    the leaf voxel size, so every method and run meshes on the same world lattice."""
    from jaxmap.config import ConfigError
    from jaxmap.mesh import extract_mesh

    k = static.leaf / res
    if res <= 0 or abs(k - round(k)) > 1e-6:
        raise ConfigError(f"mesh resolution {res:g} m must be positive and divide the leaf voxel size "
                          f"{static.leaf:g} m (e.g. {static.leaf / 2:g} or {static.leaf:g})")
    n = int(state.voxels.count)
    cells = mesh_cells(np.asarray(state.voxel_coord[:n]), static.mask_level)
    origin = core.origin_world(static, state)

    def sdf_fn(p_m):
        return query_world(static, state, p_m.astype(np.float64) + origin)

    mesh = extract_mesh(sdf_fn, cells, static.leaf, res, min_component_faces=min_component_faces)
    mesh.apply_translation(origin)
    return mesh
