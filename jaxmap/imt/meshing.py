"""SDF queries and meshes of a latent map (DI-Fusion / IMT style, stitched with tent weights).

Every active voxel `v` decodes the SDF mean and standard deviation (voxel units, scaled to metres
here) at points `q` relative to its centre. Its 2x2x2 neighbourhood is where its latent was encoded,
so a voxel speaks for `|q|_inf < 1` and with the tent weight `prod_i (1 - |q_i|)`, which is 1 at its
centre and 0 at its neighbours' centres. A point's SDF is the tent-weighted mean over the (up to 8)
active voxels around it: a partition of unity where all 8 are present, and a smooth blend across
voxel borders (no seams), normalised where some are missing.

`query(prior, m, points_w)` does this for arbitrary points (8 decodes per point).

`mesh(prior, m, resolution=4, ...)` evaluates the same field on the lattice of spacing
`voxel_size / resolution` (aligned with the voxel grid: voxel centres are lattice points, so
`resolution` must be even). It is computed voxel by voxel: each voxel decodes its
`(2 resolution - 1)^3` lattice points in one batch (the decoder's per-voxel Gram layer once), the
weighted values are summed per lattice point on the host, and `jaxmap.mesh.extract_mesh` runs
marching cubes over the cells of the active voxels. Lattice points whose blended std (metres)
exceeds `sigma_threshold_m` are invalid, so the triangles there are dropped.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.grid import hashing
from jaxmap.grid.features import CORNER_OFFSETS
from jaxmap.imt.latent_map import LatentMap, voxel_keys
from jaxmap.mesh import extract_mesh


def _tent(q):
    return jnp.prod(jnp.clip(1.0 - jnp.abs(q), 0.0, 1.0), axis=-1)


@jax.jit
def _query_core(prior, m: LatentMap, points_w, min_weight):
    vs = m.voxel_size
    u = points_w / vs - 0.5                                                 # [P, 3]
    vox = jnp.floor(u).astype(jnp.int32)[:, None] + jnp.asarray(CORNER_OFFSETS)[None]   # [P, 8, 3]
    rows = hashing.lookup(m.table, voxel_keys(vox.reshape(-1, 3))).reshape(vox.shape[:2])
    ok = (rows >= 0) & (m.weight[jnp.maximum(rows, 0)] > jnp.maximum(min_weight, 0.0))  # weight floor
    q = u[:, None] - vox.astype(jnp.float32)                               # [P, 8, 3] voxel units
    w = jnp.where(ok, _tent(q), 0.0)                                         # [P, 8]
    mean, std = prior.decode(m.latent[jnp.maximum(rows, 0)], q)              # [P, 8]
    tot = jnp.sum(w, -1)
    inv = jnp.where(tot > 0, 1.0 / jnp.where(tot > 0, tot, 1.0), 0.0)
    return jnp.sum(w * mean, -1) * inv * vs, jnp.sum(w * std, -1) * inv * vs, tot > 1e-6


def query(prior, m: LatentMap, points_w, chunk: int = 1 << 15, min_weight: float = 0.0):
    """SDF of the map at world points. points_w: [P, 3] float32 (metres, map frame).

    Returns numpy `(sdf [P] metres, std [P] metres, valid [P] bool)`; invalid where no voxel with weight
    above `min_weight` covers the point (sdf and std are 0 there): low-weight voxels are not decoded.
    """
    points_w = np.asarray(points_w, np.float32).reshape(-1, 3)
    out = []
    for s in range(0, len(points_w), chunk):
        p = points_w[s:s + chunk]
        n = len(p)
        pad = 1 << max(10, int(np.ceil(np.log2(n))))
        p = np.concatenate([p, np.zeros((pad - n, 3), np.float32)])
        out.append([np.asarray(x)[:n] for x in _query_core(prior, m, p, jnp.float32(min_weight))])
    if not out:
        return np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, bool)
    return tuple(np.concatenate([o[i] for o in out]) for i in range(3))


@functools.partial(jax.jit, static_argnames=("resolution",))
def _decode_voxels(prior, latent, resolution: int):
    """latent [B, C, 3] -> (mean, std) [B, Q] voxel units at the Q = (2r-1)^3 lattice offsets."""
    k = np.arange(-(resolution - 1), resolution)
    q = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3).astype(np.float32) / resolution
    return prior.decode(latent[:, None], jnp.asarray(q)[None])


def lattice_values(prior, m: LatentMap, resolution: int = 4, min_weight: float = 0.0, batch: int = 512):
    """Tent-blended SDF mean/std (metres) on the lattice points covered by the active voxels.

    Returns `(codes [L] int64 sorted, mean [L], std [L], voxels [V, 3])`: `codes` encode lattice
    indices `i` (position `i * voxel_size / resolution`) as `_encode(i)`; `voxels` are the active
    voxels (weight > min_weight) that were decoded.
    """
    r = int(resolution)
    if r < 2 or r % 2:
        raise ValueError(f"mesh resolution per voxel must be an even integer >= 2, got {resolution}")
    w = np.asarray(m.weight)
    sel = np.flatnonzero(w > max(min_weight, 0.0))
    vox = np.asarray(m.coords)[sel].astype(np.int64)
    if len(sel) == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0), vox
    k = np.arange(-(r - 1), r)
    off = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3)            # [Q, 3]
    tent = np.prod(1.0 - np.abs(off) / r, axis=-1)                                    # [Q]
    lat = np.asarray(m.latent)[sel]
    n = len(sel)
    nb = -(-n // batch) * batch
    lat = np.concatenate([lat, np.zeros((nb - n,) + lat.shape[1:], lat.dtype)])
    means, stds = [], []
    for s in range(0, nb, batch):
        mu, sd = _decode_voxels(prior, lat[s:s + batch], r)
        means.append(np.asarray(mu))
        stds.append(np.asarray(sd))
    mu = np.concatenate(means)[:n]                                                     # [V, Q]
    sd = np.concatenate(stds)[:n]
    idx = (r * vox + r // 2)[:, None, :] + off[None]                                  # [V, Q, 3] lattice index
    codes = _encode(idx.reshape(-1, 3))
    uniq, inv = np.unique(codes, return_inverse=True)
    tw = np.broadcast_to(tent, mu.shape).reshape(-1)
    wsum = np.bincount(inv, weights=tw, minlength=len(uniq))
    mean = np.bincount(inv, weights=tw * mu.reshape(-1), minlength=len(uniq)) / wsum * m.voxel_size
    std = np.bincount(inv, weights=tw * sd.reshape(-1), minlength=len(uniq)) / wsum * m.voxel_size
    return uniq, mean, std, vox


_OFF = 1 << 20  # lattice indices in [-2^20, 2^20): +-2.6 km at 2.5 mm lattice spacing


def _encode(idx: np.ndarray) -> np.ndarray:
    i = np.asarray(idx, np.int64) + _OFF
    if i.size and (i.min() < 0 or i.max() >= 2 * _OFF):
        raise ValueError("lattice index out of range: the map spans more than 2^21 lattice steps")
    return (i[..., 0] << 42) | (i[..., 1] << 21) | i[..., 2]


def mesh(prior, m: LatentMap, resolution: int = 4, sigma_threshold_m: float = 0.15, min_weight: float = 0.0,
         min_component_faces: int = 0):
    """Marching-cubes mesh of the latent map (trimesh.Trimesh, map frame, metres).

    resolution: lattice points per voxel side (even); sigma_threshold_m: drop triangles where the
    decoded std (metres) exceeds this (<= 0: keep all); min_weight: voxels with weight <= this are not
    decoded.
    """
    codes, mean, std, vox = lattice_values(prior, m, resolution, min_weight)
    h = m.voxel_size / resolution
    ok = np.isfinite(mean)
    if sigma_threshold_m > 0:
        ok &= std <= sigma_threshold_m

    def sdf_fn(points):
        c = _encode(np.round(np.asarray(points, np.float64) / h).astype(np.int64))
        pos = np.clip(np.searchsorted(codes, c), 0, max(len(codes) - 1, 0))
        found = (codes[pos] == c) if len(codes) else np.zeros(len(c), bool)
        valid = found & ok[pos] if len(codes) else found
        return np.where(valid, mean[pos] if len(codes) else 0.0, 1.0).astype(np.float32), valid

    return extract_mesh(sdf_fn, vox, m.voxel_size, h, min_component_faces=min_component_faces)
