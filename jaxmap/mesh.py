"""Marching cubes on one fixed global lattice, for every method that produces an SDF.

Every mesh that jaxmap evaluates (the N3 map, the transformable latent map, the TSDF baseline) goes
through :func:`extract_mesh`, so every method is meshed on the *same* lattice: the points
``origin + k * resolution`` for integer ``k`` (world frame, metres). Two methods compared at the same
``resolution`` and ``origin`` therefore place their sample points at identical positions, and
differences between their meshes come from their SDFs, not from the meshing (N3 paper, section IV-A:
"marching cubes on the same fixed-size grid to ensure fairness").

Conventions
-----------
- SDF sign: ``sdf > 0`` outside (free space, in front of the surface as seen by the sensor),
  ``sdf < 0`` inside/behind. Faces are oriented so that their normals (right-hand rule,
  ``cross(v1 - v0, v2 - v0)``) point towards positive sdf; a closed surface therefore has a positive
  signed volume.
- The region to mesh is the union of axis-aligned cubes ("cells") of side ``cell_size`` at integer
  coordinates ``cells``: cell ``c`` covers ``origin + c * cell_size .. origin + (c + 1) * cell_size``.
  ``cell_size`` must be an integer multiple ``r`` of ``resolution``, so each cell holds ``r^3``
  marching-cubes cubes and the lattice is the same for every cell.
- Masking: ``sdf_fn`` returns a validity flag per sample; a marching-cubes cube produces triangles only
  if all 8 of its corner samples are valid and the cube lies in one of the given cells. Nothing is
  meshed in unobserved space and no spurious surface appears at the border of the observed region.

Implementation
--------------
Cells are grouped into bricks of ``chunk_cells^3`` cells. A brick is a dense block of
``(chunk_cells * r + 1)^3`` lattice samples (one sample of overlap with the next brick, so the cubes of
neighbouring bricks are disjoint: no duplicate faces). Only samples that are corners of cubes inside the
given cells are evaluated; bricks are collected into groups so that ``sdf_fn`` sees large batches (padded
to power-of-two sizes, at most ``max_points_per_call``, so a jitted ``sdf_fn`` compiles only a handful of
shapes). ``skimage.measure.marching_cubes`` (Lewiner) runs per brick, on the brick cropped to its valid
cubes. Triangles of invalid cubes are dropped, vertices that brick borders share are merged (they agree
to float32 rounding; merged within 1e-3 lattice units), degenerate and duplicate faces are removed and,
optionally, small connected components.

This module imports numpy at import time only; scipy, scikit-image and trimesh are imported lazily.
"""
from __future__ import annotations

import logging
import os
from typing import Callable

import numpy as np

from jaxmap.errors import DataError
from jaxmap.grid.features import CORNER_OFFSETS
from jaxmap.sizes import pow2_bucket

log = logging.getLogger(__name__)

SdfFn = Callable[[np.ndarray], "tuple[np.ndarray, np.ndarray] | np.ndarray"]

# Two vertices closer than this (in lattice units) are the same vertex. Vertices that a brick border
# shares are computed by two marching-cubes calls and agree to float32 rounding (~1e-5 lattice units
# for bricks of <= 256 samples); distinct vertices of a brick are never this close unless they sit on
# the same sample (an exactly-zero sdf), where merging them is what we want.
_MERGE_TOL = 1e-3
_MIN_BUCKET = 1 << 12
_DEFAULT_BRICK_SAMPLES = 32  # lattice intervals per brick side when chunk_cells is not given


def _unique_rows(a: np.ndarray, return_inverse: bool = False):
    """np.unique(a, axis=0) for int64 [M,3] rows, via packed int64 keys when the span allows (much faster
    than the void-dtype sort of axis=0). Rows come back in lexicographic order either way."""
    lo = a.min(axis=0)
    span = a.max(axis=0) - lo + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0**62:
        return np.unique(a, axis=0, return_inverse=return_inverse)
    r = a - lo
    key = (r[:, 0] * span[1] + r[:, 1]) * span[2] + r[:, 2]
    out = np.unique(key, return_index=True, return_inverse=return_inverse)
    rows = a[out[1]]
    return (rows, out[2].reshape(-1)) if return_inverse else rows


def _empty_mesh():
    import trimesh

    return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)


def _call_sdf(sdf_fn: SdfFn, points: np.ndarray, max_points_per_call: int) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate sdf_fn on points [K,3] float32 in padded batches; returns (sdf [K] float32, valid [K] bool).

    Batches have power-of-two sizes (padding repeats the last point), so a jitted sdf_fn compiles at most
    log2(max_points_per_call / 4096) + 1 shapes. Non-finite sdf values count as invalid.
    """
    k = len(points)
    sdf = np.empty(k, np.float32)
    valid = np.empty(k, bool)
    start = 0
    while start < k:
        stop = min(start + max_points_per_call, k)
        batch = points[start:stop]
        size = pow2_bucket(stop - start, _MIN_BUCKET, max_points_per_call)
        if size > len(batch):
            pad = np.repeat(batch[-1:], size - len(batch), axis=0)
            batch = np.concatenate([batch, pad], axis=0)
        out = sdf_fn(batch)
        if isinstance(out, tuple):
            s, v = out
            v = np.asarray(v, dtype=bool).reshape(-1)
        else:
            s, v = out, None
        s = np.asarray(s, dtype=np.float32).reshape(-1)
        if len(s) != size or (v is not None and len(v) != size):
            raise ValueError(f"sdf_fn returned {len(s)} values for {size} points; it must return one per point")
        n = stop - start
        sdf[start:stop] = s[:n]
        valid[start:stop] = np.isfinite(s[:n]) if v is None else (v[:n] & np.isfinite(s[:n]))
        start = stop
    return sdf, valid


class _Brick:
    """One brick: which of its cubes are inside the cells and which lattice samples it needs."""

    __slots__ = ("offset", "cube_occ", "need", "start", "stop")

    def __init__(self, offset, cube_occ, need):
        self.offset = offset  # [3] int64, global lattice index of the brick's sample (0, 0, 0)
        self.cube_occ = cube_occ  # [n, n, n] bool: cube lies inside one of the given cells
        self.need = need  # [n+1]^3 bool: sample is a corner of such a cube
        self.start = 0  # range of this brick's samples in the group's evaluation buffer
        self.stop = 0


def _prepare_brick(brick_coord, local_cells, chunk_cells: int, r: int) -> _Brick:
    n = chunk_cells * r
    occ = np.zeros((chunk_cells,) * 3, dtype=bool)
    occ[local_cells[:, 0], local_cells[:, 1], local_cells[:, 2]] = True
    cube_occ = occ
    if r > 1:
        cube_occ = occ.repeat(r, axis=0).repeat(r, axis=1).repeat(r, axis=2)
    need = np.zeros((n + 1,) * 3, dtype=bool)
    for dx, dy, dz in CORNER_OFFSETS:  # a marching-cubes cube's corners, in lattice units
        need[dx:dx + n, dy:dy + n, dz:dz + n] |= cube_occ
    return _Brick(np.asarray(brick_coord, dtype=np.int64) * n, cube_occ, need)


def _mesh_brick(br: _Brick, sdf: np.ndarray, valid: np.ndarray):
    """Marching cubes of one evaluated brick -> (vertices [V,3] float64 global lattice coords, faces [F,3])."""
    from skimage.measure import marching_cubes

    n = br.cube_occ.shape[0]
    vol_valid = np.zeros(br.need.shape, dtype=bool)
    vol_valid[br.need] = valid
    if not vol_valid.any():
        return None
    vals = sdf[valid]
    vmin, vmax = float(vals.min()), float(vals.max())
    if vmin > 0.0 or vmax < 0.0:
        return None  # no zero crossing among valid samples
    cube_ok = br.cube_occ.copy()
    for dx, dy, dz in CORNER_OFFSETS:  # a marching-cubes cube's corners, in lattice units
        cube_ok &= vol_valid[dx:dx + n, dy:dy + n, dz:dz + n]
    if not cube_ok.any():
        return None
    # Crop to the bounding box of the valid cubes (+1 sample): marching cubes costs ~10 ns per cube.
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for a in range(3):
        other = tuple(b for b in range(3) if b != a)
        idx = np.nonzero(cube_ok.any(axis=other))[0]
        lo[a], hi[a] = idx[0], idx[-1] + 1  # cubes lo..hi-1 -> samples lo..hi
    # Invalid samples get a positive placeholder; every cube touching one is dropped below anyway.
    placeholder = np.float32(max(abs(vmax), abs(vmin), 1.0) + 1.0)
    vol = np.full(br.need.shape, placeholder, dtype=np.float32)
    vol[br.need] = np.where(valid, sdf, placeholder)
    vol = np.ascontiguousarray(vol[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1])
    ok = cube_ok[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    if min(vol.shape) < 2:
        return None
    try:
        # 'descent' (default) orients faces towards increasing sdf for array axes (x, y, z).
        verts, faces, _, _ = marching_cubes(vol, level=0.0)
    except (RuntimeError, ValueError):
        return None  # no surface in this brick
    if len(faces) == 0:
        return None
    # The cube a triangle came from: its vertices lie in the closed cube [c, c+1]^3, so per axis
    # c is in [max ceil(v) - 1, min floor(v)]; the range has two values only for a triangle lying exactly
    # on a cube face (exact zeros), then both cubes sharing that face must be valid.
    tv = verts[faces]  # [F,3,3] float32, vertex coordinates are exact integers on lattice planes
    shape = np.array(ok.shape)
    c_hi = np.clip(np.floor(tv).min(axis=1).astype(np.int64), 0, shape - 1)
    c_lo = np.clip(np.ceil(tv).max(axis=1).astype(np.int64) - 1, 0, shape - 1)
    keep = ok[c_hi[:, 0], c_hi[:, 1], c_hi[:, 2]] & ok[c_lo[:, 0], c_lo[:, 1], c_lo[:, 2]]
    if not keep.any():
        return None
    faces = faces[keep]
    used = np.unique(faces)
    remap = np.full(len(verts), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    gverts = verts[used].astype(np.float64) + (br.offset + lo)[None, :]
    return gverts, remap[faces]


def _merge_border_vertices(verts: np.ndarray, faces: np.ndarray, brick_n: int) -> tuple[np.ndarray, np.ndarray]:
    """Merge the copies of vertices on brick borders (global lattice coords) and clean the faces."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    on_border = np.any(np.mod(verts, brick_n) == 0.0, axis=1)
    cand = np.nonzero(on_border)[0]
    rep = np.arange(len(verts))
    if len(cand) > 1:
        pairs = cKDTree(verts[cand]).query_pairs(_MERGE_TOL, output_type="ndarray")
        if len(pairs):
            m = len(cand)
            g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
            _, label = connected_components(g, directed=False)
            # representative = smallest candidate index of each group
            first = np.full(label.max() + 1, np.iinfo(np.int64).max, dtype=np.int64)
            np.minimum.at(first, label, cand)
            rep[cand] = first[label]
    faces = rep[faces]
    # Degenerate faces (two corners merged) and duplicates (same vertex triple, same orientation).
    good = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces = faces[good]
    if len(faces) > 1:
        roll = np.argmin(faces, axis=1)
        rows = np.arange(len(faces))
        canon = np.stack([faces[rows, (roll + i) % 3] for i in range(3)], axis=1)
        order = np.lexsort((canon[:, 2], canon[:, 1], canon[:, 0]))
        c = canon[order]
        dup = np.zeros(len(faces), bool)
        dup[order[1:]] = np.all(c[1:] == c[:-1], axis=1)
        faces = faces[~dup]
    return verts, faces


def _drop_small_components(faces: np.ndarray, n_verts: int, min_faces: int) -> np.ndarray:
    """Remove connected components (vertex-connected) with fewer than min_faces faces."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if min_faces <= 0 or len(faces) == 0:
        return faces
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]], axis=0)
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_verts, n_verts))
    _, label = connected_components(g, directed=False)
    comp = label[faces[:, 0]]
    count = np.bincount(comp, minlength=label.max() + 1)
    return faces[count[comp] >= min_faces]


def extract_mesh(
    sdf_fn: SdfFn,
    cells,
    cell_size: float,
    resolution: float,
    *,
    origin=(0.0, 0.0, 0.0),
    chunk_cells: int | None = None,
    min_component_faces: int = 0,
    max_points_per_call: int = 2**18,
):
    """Mesh the zero level set of an SDF inside a set of cells, on the global lattice.

    Args:
      sdf_fn: ``points [K,3] float32 (world frame, metres) -> (sdf [K] float32, valid [K] bool)``; a bare
        sdf array is accepted too (valid = finite). Called with K a power of two <= max_points_per_call
        (>= 4096); may return numpy or jax arrays. Sign: > 0 in free space, < 0 inside.
      cells: [M,3] integer cell coordinates; cell c covers ``origin + c*cell_size .. + cell_size``.
        Duplicates are fine.
      cell_size: cell side in metres; must be an integer multiple of ``resolution``.
      resolution: lattice spacing in metres (the marching-cubes voxel size).
      origin: [3] world position of lattice point 0 (and of the corner of cell (0, 0, 0)). Keep the
        default for comparisons between methods: same origin and resolution = same lattice.
      chunk_cells: cells per brick side (default: about 32 lattice intervals per brick side).
      min_component_faces: connected components with fewer faces are removed (0 keeps all).
      max_points_per_call: largest batch handed to sdf_fn.

    Returns:
      trimesh.Trimesh in world coordinates (float64 vertices), faces oriented towards positive sdf;
      empty when there are no cells or no zero crossing.
    """
    cells = np.asarray(cells)
    if cells.size == 0:
        return _empty_mesh()
    cells, r, chunk_cells = _checked_lattice(cells, cell_size, resolution, chunk_cells, max_points_per_call)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    all_verts, all_faces = _mesh_bricks(sdf_fn, cells, chunk_cells, r, origin, resolution, max_points_per_call)
    if not all_faces:
        return _empty_mesh()
    verts = np.concatenate(all_verts, axis=0)
    faces = np.concatenate(all_faces, axis=0)
    verts, faces = _merge_border_vertices(verts, faces, chunk_cells * r)
    faces = _drop_small_components(faces, len(verts), int(min_component_faces))
    if len(faces) == 0:
        return _empty_mesh()
    return _trimesh_of(verts, faces, origin, resolution)


def extract_mesh_groups(sdf_fn_of: Callable[[int], SdfFn], groups, cell_size: float, resolution: float, *,
                        origin=(0.0, 0.0, 0.0), min_component_faces: int = 0, max_points_per_call: int = 2**18):
    """`extract_mesh` of the union of several groups of cells meshed one group after another, each with its
    own SDF function `sdf_fn_of(g)` (a map of submaps meshes each submap's cells while that submap and its
    neighbours are in memory). The groups must not share cells; the pieces are welded on the common lattice
    (vertices at the same lattice position merged) before small components are dropped, so a surface that
    crosses from one group into the next is one component, as in one `extract_mesh` call."""
    parts_v, parts_f, n = [], [], 0
    chunk_cells = None
    for g, cells in enumerate(groups):
        cells = np.asarray(cells)
        if cells.size == 0:
            continue
        cells, r, chunk_cells = _checked_lattice(cells, cell_size, resolution, None, max_points_per_call)
        vs, fs = _mesh_bricks(sdf_fn_of(g), cells, chunk_cells, r, np.asarray(origin, np.float64).reshape(3),
                              resolution, max_points_per_call)
        # the faces of `_mesh_bricks` index into the concatenation of its own vertex arrays
        parts_v += vs
        parts_f += [f + n for f in fs]
        n += sum(len(v) for v in vs)
    if not parts_f:
        return _empty_mesh()
    verts = np.concatenate(parts_v, axis=0)
    faces = np.concatenate(parts_f, axis=0)
    # one vertex per lattice position: the groups' copies of a vertex on the faces they share
    _, first, inverse = np.unique(np.round(verts * 1024.0).astype(np.int64), axis=0, return_index=True,
                                  return_inverse=True)
    faces = first[inverse.reshape(-1)][faces]
    verts, faces = _merge_border_vertices(verts, faces, chunk_cells * int(round(cell_size / resolution)))
    faces = _drop_small_components(faces, len(verts), int(min_component_faces))
    if len(faces) == 0:
        return _empty_mesh()
    return _trimesh_of(verts, faces, origin, resolution)


def _checked_lattice(cells: np.ndarray, cell_size: float, resolution: float, chunk_cells, max_points_per_call: int):
    """`extract_mesh`'s arguments checked: (cells [M,3] int64, lattice intervals per cell, cells per brick side)."""
    if cells.ndim != 2 or cells.shape[1] != 3:
        raise ValueError(f"cells must have shape [M,3], got {cells.shape}")
    if not np.issubdtype(cells.dtype, np.integer):
        if not np.all(np.mod(cells, 1) == 0):
            raise ValueError("cells must hold integer coordinates")
    cells = cells.astype(np.int64)
    if not (resolution > 0 and cell_size > 0):
        raise ValueError(f"cell_size ({cell_size}) and resolution ({resolution}) must be positive")
    ratio = cell_size / resolution
    r = int(round(ratio))
    if r < 1 or abs(ratio - r) > 1e-6 * max(1.0, ratio):
        raise ValueError(
            f"cell_size {cell_size} m is not an integer multiple of resolution {resolution} m "
            f"(ratio {ratio:.6g}); pick a resolution such as {cell_size / max(1, round(ratio))} m"
        )
    if max_points_per_call < 1:
        raise ValueError("max_points_per_call must be >= 1")
    if chunk_cells is None:
        chunk_cells = max(1, _DEFAULT_BRICK_SAMPLES // r)
    chunk_cells = int(chunk_cells)
    if chunk_cells < 1:
        raise ValueError("chunk_cells must be >= 1")
    return cells, r, chunk_cells


def _mesh_bricks(sdf_fn: SdfFn, cells, chunk_cells: int, r: int, origin, resolution: float,
                 max_points_per_call: int) -> tuple[list, list]:
    """Marching cubes brick by brick, the samples of several bricks evaluated in one batch.
    Returns (vertex arrays [V_i,3] lattice coordinates, face arrays [F_i,3] into their concatenation)."""
    cells = _unique_rows(cells)
    bcoord = np.floor_divide(cells, chunk_cells)
    local = cells - bcoord * chunk_cells
    bricks, inverse = _unique_rows(bcoord, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(bricks) + 1))

    all_verts: list[np.ndarray] = []
    all_faces: list[np.ndarray] = []
    n_verts = 0
    group: list[_Brick] = []
    group_points: list[np.ndarray] = []
    group_size = 0

    def flush():
        nonlocal n_verts, group_size
        if not group:
            return
        pts = np.concatenate(group_points, axis=0)
        sdf, valid = _call_sdf(sdf_fn, pts, max_points_per_call)
        for br in group:
            out = _mesh_brick(br, sdf[br.start:br.stop], valid[br.start:br.stop])
            if out is None:
                continue
            v, f = out
            all_verts.append(v)
            all_faces.append(f + n_verts)
            n_verts += len(v)
        group.clear()
        group_points.clear()
        group_size = 0

    for b in range(len(bricks)):
        idx = order[bounds[b]:bounds[b + 1]]
        br = _prepare_brick(bricks[b], local[idx], chunk_cells, r)
        ijk = np.stack(np.nonzero(br.need), axis=1)  # C order == order of vol[need]
        pts = (origin + (ijk + br.offset) * resolution).astype(np.float32)
        br.start, br.stop = group_size, group_size + len(pts)
        group.append(br)
        group_points.append(pts)
        group_size += len(pts)
        if group_size >= max_points_per_call:
            flush()
    flush()
    return all_verts, all_faces


def _trimesh_of(verts: np.ndarray, faces: np.ndarray, origin, resolution: float):
    """trimesh.Trimesh in world coordinates of the vertices [V,3] (lattice) that faces [F,3] use."""
    import trimesh

    used = np.unique(faces)
    remap = np.full(len(verts), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    world = origin + verts[used] * resolution
    return trimesh.Trimesh(vertices=world, faces=remap[faces], process=False)


def save_mesh(mesh, path) -> str:
    """Write a trimesh.Trimesh as binary PLY (creating parent folders); returns the path.

    An empty mesh is written too (a PLY with zero vertices and faces), so a pipeline always leaves a file
    that `jaxmap eval` can report on.
    """
    path = os.fspath(path)
    parent = os.path.dirname(os.path.abspath(path))
    os.makedirs(parent, exist_ok=True)
    if not path.lower().endswith(".ply"):
        raise DataError(f"{path}: meshes are written as PLY; use a .ply file name")
    data = mesh.export(file_type="ply")
    with open(path, "wb") as f:
        f.write(data)
    return path
