"""SE(3) transform of a latent map onto the global grid (IMT paper section III-B, eqs. 3-10): the
interpolation of moved voxels (`transform_batch`, `splat_trilinear`); `local_maps.transform` fuses them.

A local map `L` (voxel centres `c_m`, latents `F_m`, Jacobians `J_m`, weights `w_m`, all in frame A)
and a pose `T = [R | t]` from frame A to the global frame. Then, per local voxel:

1. its centre moves, `c'_m = T c_m` (eq. 3), and its latent and Jacobian rotate,
   `F'_m = F_m R^T`, `J'_m = R J_m R^T` (eq. 4; `vn.rotate`, a pytree map);
2. `c'_m` generally falls between global voxel centres, so the latent is re-expressed at a nearby
   global centre `c_n` by a first-order expansion. With `t_nm = (c_n - c'_m) / voxel_size` (voxel
   units, global frame), moving the centre by `+t_nm` moves the voxel's points by `-t_nm` relative
   to it, so `F_n|m = F'_m - J'_m t_nm` (`jacobian_sign = -1`, the default). The paper (eq. 5, 9) and
   the original code use `+`, which measures worse (`jaxmap bench imt`); `jacobian_sign = 0` drops
   the term.
3. the expansions are combined with one of two weightings (`method`):
   * ``"trilinear"`` (default): each local voxel splats onto the 8 global voxels around `c'_m` with
     trilinear weights sharpened by a power (2 by default) and renormalised, `s_nm` (a partition of
     unity, so the total weight is conserved):
     `F_n = sum_m s_nm w_m F_n|m / sum_m s_nm w_m`, `w_n = sum_m s_nm w_m`. The splats are returned
     as a `VoxelBatch` and summed by `fuse`, so batching many local maps is a concatenation.
   * ``"softmax"`` (the paper's eq. 9-10): every global voxel within one voxel of some `c'_m` gathers
     its K nearest local voxels by lattice lookup in the local map's hash table (the 27 lattice
     neighbours of `T^-1 c_n`, K of them kept by distance), `s_nm = softmax(-|t_nm|^2 / temperature)`,
     `F_n = sum_m s_nm F_n|m`, `w_n = sum_m s_nm w_m`. The paper's temperature is 1 / voxel_size^2
     in voxel units (distances in metres), which makes the weights nearly uniform.
   `jaxmap bench imt` measures both; trilinear is the default because it measures better and keeps
   the weight mass (see docs/remapping.md).

Everything runs inside `jit` with static shapes: the output of a map with R rows has 8R entries.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.geometry import einsum, matmul
from jaxmap.grid import hashing
from jaxmap.grid.features import CORNER_OFFSETS
from jaxmap.imt.latent_map import LatentMap, VoxelBatch, voxel_keys
from jaxmap.imt.vn import rotate

METHODS = ("trilinear", "softmax")
_NEIGHBOURS = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], np.int32)


@functools.partial(jax.jit, static_argnames=("voxel_size", "jacobian_sign", "power", "keep_jacobian"))
def splat_trilinear(b: VoxelBatch, T: jax.Array, voxel_size: float, jacobian_sign: float = -1.0,
                    power: float = 2.0, keep_jacobian: bool = False, exact=None) -> VoxelBatch:
    """Trilinear splats of a voxel batch moved by `T` ([4, 4], frame of b -> global).

    power: the 8 trilinear weights of a local voxel are raised to this power and renormalised to
    sum 1 (so the weight mass is still conserved); > 1 favours the nearest global voxels, whose
    first-order expansions are the most accurate (power 2 lowers the two-branch error by 20-40 %
    against plain trilinear weights, `jaxmap bench imt`).

    b: [P] entries -> [8P] entries on the global grid (fuse them: `local_maps.transform` / `core.move_step`).
    `T` may also be [P, 4, 4] (one pose per entry: many keyframes at once). The rotation of the latents
    and Jacobians is `vn.rotate` of the batch itself (its fields are marked), mapped over the entries.
    keep_jacobian: give each splat the rotated Jacobian too (for a map that will be transformed again).
    exact: [P] bool or None: entries whose `T` is the identity, placed on their own voxel exactly (one
    splat of the whole weight, the latent unchanged: what the map holds before any move), not through
    `(c + 0.5) s / s - 0.5`, which float32 rounds off the lattice.
    `T` may also be [P, 3, 4] (the top rows).
    """
    T = jnp.asarray(T, jnp.float32)
    if T.ndim == 2:
        T = jnp.broadcast_to(T, (b.coords.shape[0],) + T.shape)
    R, t = T[:, :3, :3], T[:, :3, 3]                                       # [P, 3, 3], [P, 3]
    c = (b.coords.astype(jnp.float32) + 0.5) * voxel_size                  # [P, 3] metres
    u = (einsum("pij,pj->pi", R, c) + t) / voxel_size - 0.5                # [P, 3] continuous global index
    if exact is not None:
        u = jnp.where(exact[:, None], b.coords.astype(jnp.float32), u)
    base = jnp.floor(u)
    frac = u - base
    rb = jax.vmap(rotate)(b, R)                                             # F R^T, R J R^T per entry
    lat, jac = rb.latent, rb.jac
    corners = jnp.asarray(CORNER_OFFSETS, jnp.float32)                            # [8, 3]
    s = jnp.prod(jnp.where(corners[None] > 0, frac[:, None], 1.0 - frac[:, None]), axis=-1)  # [P, 8]
    if power != 1.0:
        s = s ** power
        s = s / jnp.sum(s, axis=-1, keepdims=True)
    tnm = (base[:, None] + corners[None]) - u[:, None]                     # [P, 8, 3] voxel units
    lat_n = lat[:, None] + jacobian_sign * einsum("pcak,pnk->pnca", jac, tnm)   # [P, 8, C, 3]
    p = b.coords.shape[0]
    w = s * b.weight[:, None]                                              # [P, 8]
    valid = b.valid[:, None] & (b.weight[:, None] > 0) & (s > 1e-6)
    coords = (base[:, None] + corners[None]).astype(jnp.int32)
    jac_n = None
    if keep_jacobian:
        jac_n = jnp.broadcast_to(jac[:, None], (p, 8) + jac.shape[1:]).reshape((p * 8,) + jac.shape[1:])
    return VoxelBatch(coords.reshape(p * 8, 3), lat_n.reshape((p * 8,) + lat.shape[1:]), jac_n,
                      w.reshape(p * 8), valid.reshape(p * 8))


@functools.partial(jax.jit, static_argnames=("jacobian_sign", "k"))
def _softmax_core(m: LatentMap, T: jax.Array, temperature, jacobian_sign: float, k: int):
    """Paper eq. 9-10 on a whole map -> (VoxelBatch of distinct global voxels, [8R] entries; overflow)."""
    vs = m.voxel_size
    T = jnp.asarray(T, jnp.float32)
    R, t = T[:3, :3], T[:3, 3]
    active = m.active()
    c = (m.coords.astype(jnp.float32) + 0.5) * vs
    u = (matmul(c, R.T) + t) / vs - 0.5                                     # [R, 3]
    cand = (jnp.floor(u)[:, None] + jnp.asarray(CORNER_OFFSETS)[None]).astype(jnp.int32).reshape(-1, 3)  # [8R, 3]
    cvalid = jnp.repeat(active, 8)
    # Unique candidate global voxels: a scratch hash table gives each distinct voxel one row.
    cap = 1 << int(np.ceil(np.log2(max(2, 16 * m.rows))))
    _, rows, overflow = hashing.insert(hashing.create(cap), voxel_keys(cand), cvalid)
    placed = cvalid & (rows >= 0)
    idx_all = jnp.arange(cand.shape[0], dtype=jnp.int32)
    rep = jnp.full((cap,), cand.shape[0], jnp.int32).at[jnp.where(placed, rows, cap)].min(idx_all, mode="drop")
    first = placed & (rep[jnp.maximum(rows, 0)] == idx_all)               # one entry per distinct voxel
    # Their centres in the local grid's continuous index, and the 27 lattice neighbours there.
    cn = (cand.astype(jnp.float32) + 0.5) * vs                              # [8R, 3] global metres
    x = matmul(cn - t, R) / vs - 0.5                                        # [8R, 3] = T^-1 c_n, local index
    nb = jnp.round(x).astype(jnp.int32)[:, None] + jnp.asarray(_NEIGHBOURS)[None]   # [8R, 27, 3]
    nrow = hashing.lookup(m.table, voxel_keys(nb.reshape(-1, 3))).reshape(nb.shape[:2])  # [8R, 27]
    ok = (nrow >= 0) & active[jnp.maximum(nrow, 0)]
    d2 = jnp.sum((x[:, None] - nb.astype(jnp.float32)) ** 2, axis=-1)       # |t_nm|^2, rotation invariant
    d2 = jnp.where(ok, d2, jnp.inf)
    neg, idx = jax.lax.top_k(-d2, k)                                        # K nearest, [8R, K]
    d2k = -neg
    okk = jnp.isfinite(d2k)
    rk = jnp.take_along_axis(nrow, idx, axis=1)
    keep = first & (d2k[:, 0] < 1.0)                                        # a neighbour within one voxel
    logits = jnp.where(okk, -d2k / temperature, -jnp.inf)
    s = jax.nn.softmax(jnp.where(okk.any(-1, keepdims=True), logits, 0.0), axis=-1) * okk   # [8R, K]
    rk = jnp.maximum(rk, 0)
    mr = rotate(m, R)                                                       # the map's marked fields, F R^T, R J R^T
    lat, jac = mr.latent[rk], mr.jac[rk]                                    # [8R, K, C, 3], [8R, K, C, 3, 3]
    tnm = matmul(x[:, None] - nb.astype(jnp.float32)[jnp.arange(nb.shape[0])[:, None], idx], R.T)   # world frame
    lat_n = lat + jacobian_sign * einsum("nmcak,nmk->nmca", jac, tnm)
    latent = jnp.einsum("nm,nmca->nca", s, lat_n)
    jacn = jnp.einsum("nm,nmcak->ncak", s, jac)
    w = jnp.sum(s * m.weight[rk], axis=-1)
    return VoxelBatch(cand, latent, jacn, jnp.where(keep, w, 0.0), keep), overflow


def transform_batch(m: LatentMap, T, *, method: str = "trilinear", jacobian_sign: float = -1.0,
                    temperature: float = 1.0, k: int = 8, splat_power: float = 2.0,
                    keep_jacobian: bool = False) -> VoxelBatch:
    """The map `m` moved by `T` ([4, 4], m's frame -> global), interpolated onto the global grid, as a
    `VoxelBatch` to fuse / remove (`local_maps.transform` fuses it into an empty map; same arguments)
    (with Jacobians only if `keep_jacobian`). `m` must carry Jacobians unless jacobian_sign is 0."""
    if method not in METHODS:
        raise ValueError(f"unknown interpolation method {method!r}; choose one of {METHODS}")
    T = np.asarray(T, np.float32)
    if T.shape != (4, 4):
        raise ValueError(f"T must be [4,4], got {T.shape}")
    if m.jac_sum is None and jacobian_sign != 0:
        raise ValueError("transform: this map has no Jacobians (encode with with_jacobian=True, or jacobian_sign=0)")
    if m.jac_sum is None:
        m = dataclasses.replace(m, jac_sum=jnp.zeros(m.latent_sum.shape + (3,), jnp.float32))
    if method == "trilinear":
        return splat_trilinear(m.as_batch(), T, m.voxel_size, float(jacobian_sign), float(splat_power),
                               bool(keep_jacobian))
    out, overflow = _softmax_core(m, T, jnp.float32(temperature), float(jacobian_sign), int(k))
    if not keep_jacobian:
        out = dataclasses.replace(out, jac=None)
    if bool(overflow):  # 16x slots for at most 8x keys: only an adversarial hash clustering gets here
        raise hashing.CapacityError("transform: the scratch table of candidate voxels overflowed")
    return out
