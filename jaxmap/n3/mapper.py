"""N3 mapping: state pytree, per-frame update, SDF queries and meshes.

Per frame (DESIGN.md section 3):
  preprocess (numpy) -> world/map frame -> sample pairs (jit) -> allocate leaf voxels and their
  24 corner rows (hash inserts, grown outside jit) -> store pairs in their voxel's block and slide
  the window (jit) -> K training iterations in one compiled `lax.fori_loop` over a compact copy of
  the feature rows the window touches (jit) -> write those rows back.

Frames: `points_s` are in the sensor frame, `pose` is T_world_sensor. Internally everything lives in
a *map frame* = world - origin (origin = first sensor position snapped to the coarsest voxel), so
float32 stays precise on large scenes; `sdf()` and `mesh()` take and return world coordinates.
"""
from __future__ import annotations

import functools
import logging
import math
import time

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxmap.config import MapConfig
from jaxmap.errors import CapacityError
from jaxmap.geometry import validate_pose
from jaxmap.grid import features as gfeat
from jaxmap.grid import hashing
from jaxmap.n3 import hierarchical, window
from jaxmap.n3.decoder import init_decoder, mlp_with_input_grad
from jaxmap.n3.loss import bce_loss, eikonal_loss, sdf_and_grad
from jaxmap.n3.sampling import sample_frame
from jaxmap.preprocess import preprocess_scan

log = logging.getLogger("jaxmap")


@flax.struct.dataclass
class N3State:
    voxels: hashing.HashTable      # leaf voxel (x, y, z, 0) -> voxel row
    corners: hashing.HashTable     # corner (x, y, z, level) -> feature row
    voxel_coord: jax.Array         # [V, 3] int32: leaf-voxel coordinate of each voxel row
    voxel_corner_rows: jax.Array   # [V, L*8] int32: feature rows of the voxel's corners, all levels
    features: jax.Array            # [R, 4, D] float32: per row (value, Adam mu, Adam nu, grad accumulator)
    feat_count: jax.Array          # [] int32: Adam step count of the features
    decoder: dict                  # flax params of the SDF decoder
    dec_opt: optax.OptState        # Adam state of the decoder
    store: window.PairStore        # voxel-oriented training pairs
    key: jax.Array                 # PRNG key, split once per frame
    frame: jax.Array               # [] int32: frames integrated so far


def _bucket(n: int, minimum: int = 1024) -> int:
    """Pad sizes to at most ~4 buckets per octave, so recompiles are rare and waste <= 25 %."""
    n = max(int(n), minimum)
    p = 1 << (n - 1).bit_length()
    step = max(p // 8, 1)
    return int(math.ceil(n / step) * step)


# --------------------------------------------------------------------------------------------
# Jitted pieces. Static arguments are config values; arrays are state.
# --------------------------------------------------------------------------------------------

_sample = jax.jit(sample_frame, static_argnames=(
    "label_mode", "trunc", "sigma", "n_surface", "n_free", "free_band", "free_label"))


@functools.partial(jax.jit, static_argnames=("leaf",))
def _leaf_keys(points, leaf: float):
    vox = gfeat.leaf_voxel(points, leaf)
    return vox, jnp.concatenate([vox, jnp.zeros_like(vox[:, :1])], axis=-1)


@jax.jit
def _set_rows(arr, rows, values):
    """arr[rows] = values where rows >= 0 (rows -1 dropped)."""
    tgt = jnp.where(rows >= 0, rows, arr.shape[0])
    return arr.at[tgt].set(values, mode="drop")


@functools.partial(jax.jit, static_argnames=("radius_vox", "mode", "keyframes"), donate_argnums=(0,))
def _update_store(store, vox_rows, vox_coords, points, labels, surface, frame, center_vox, *,
                  radius_vox: int, mode: str, keyframes: int):
    """Slide the window, give new voxels blocks, append the frame's pairs; return window slots."""
    store = window.release(store, window.in_window(store, center_vox, radius_vox, mode=mode, frame=frame,
                                                   keyframes=keyframes))
    store, slots, overflow = window.assign_slots(store, vox_rows, vox_coords)
    store = window.write_pairs(store, slots, points, labels, surface, frame)
    inside = window.in_window(store, center_vox, radius_vox, mode=mode, frame=frame, keyframes=keyframes)
    ids, n = hierarchical.window_slots(inside & (store.count > 0))
    return store, ids, n, overflow


@functools.partial(jax.jit, static_argnames=("radius_vox", "mode", "keyframes"))
def _slots_needed(store, vox_rows, center_vox, frame, *, radius_vox: int, mode: str, keyframes: int):
    """(blocks this frame needs, slots free once the window has slid): checked before the
    donated update so that a full store is grown outside jit instead of dropping pairs."""
    keep = window.in_window(store, center_vox, radius_vox, mode=mode, frame=frame, keyframes=keyframes)
    released = (store.voxel_of_slot >= 0) & ~keep
    v = store.slot_of_voxel.shape[0]
    touched = jnp.zeros((v,), bool).at[jnp.where(vox_rows >= 0, vox_rows, v)].set(True, mode="drop")
    slot = store.slot_of_voxel
    has_block = (slot >= 0) & ~released[jnp.maximum(slot, 0)]
    return jnp.sum(touched & ~has_block), jnp.sum((store.voxel_of_slot < 0) | released)


VALUE, MU, NU, ACC = 0, 1, 2, 3  # the middle axis of N3State.features


def sparse_adam(packed, count, rows, grads, *, lr: float, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8):
    """Adam on the feature rows a batch touched ("lazy" Adam, as for sparse embeddings).

    packed: [R, 4, D] (value, mu, nu, accumulator; the accumulator is zero between calls);
    count: [] int32 step; rows: [M] int32 (-1 ignored, duplicates allowed); grads: [M, D].
    Duplicate rows' gradients are summed in the accumulator first, so each touched row takes exactly
    dense Adam's step; rows the batch does not touch keep values and moments. Every occurrence of a
    row computes the same new values, so the scatter is deterministic. One scatter-add, one gather
    and one scatter-set of [M, 4, D]: O(M D), not O(R D), and no sort.
    """
    r = packed.shape[0]
    idx = jnp.where(rows >= 0, rows, r)                                          # r: dropped
    packed = packed.at[idx, ACC].add(grads, mode="drop")
    x = packed.at[idx].get(mode="fill", fill_value=0.0)                         # [M, 4, D]
    count = count + 1
    t = count.astype(jnp.float32)
    g = x[:, ACC]
    mu = b1 * x[:, MU] + (1.0 - b1) * g
    nu = b2 * x[:, NU] + (1.0 - b2) * g * g
    value = x[:, VALUE] - lr * (mu / (1.0 - b1**t)) / (jnp.sqrt(nu / (1.0 - b2**t)) + eps)
    new = jnp.stack([value, mu, nu, jnp.zeros_like(value)], axis=1)
    return packed.at[idx].set(new, mode="drop"), count


@functools.partial(
    jax.jit,
    static_argnames=("module", "iters", "hier", "nv", "np_", "nt", "batch", "keyframes", "leaf", "levels", "lr",
                     "beta", "weight_e", "train_decoder", "reset_adam"),
    donate_argnums=(0,),
)
def _train_frame(features, feat_count, dec_params, dec_opt, store, voxel_corner_rows,
                 ids, n, key, frame, *, module, iters: int, hier: bool, nv: int, np_: int, nt: int, batch: int,
                 keyframes: int, leaf: float, levels: int, lr: float, beta: float, weight_e: float,
                 train_decoder: bool, reset_adam: bool):
    """K iterations of (hierarchical) sampling, loss and Adam, in one compiled call.

    Features get sparse Adam on the rows each batch touches, so an iteration costs O(batch), however
    large the map or the window; the decoder gets optax Adam until it is frozen.
    """
    if reset_adam:  # the original N3 code rebuilds its optimiser every frame
        features = features.at[:, MU:NU + 1].set(0.0)
        feat_count = jnp.zeros_like(feat_count)
    dec_tx = optax.adam(lr)

    def loss_fn(feats, dec, w, dw, b):
        f = jnp.einsum("gkc,gcd->gkd", w, feats)                                  # [G, K, D]
        if weight_e > 0:
            sdf, g_f = mlp_with_input_grad(dec, f)
            # d sdf / dx = sum_c (feats_c . d sdf / d f) d w_c / dx, with w and dw fixed w.r.t. parameters
            grad = jnp.einsum("gkc,gkcx->gkx", jnp.einsum("gkd,gcd->gkc", g_f, feats), dw)
            l_eik = eikonal_loss(grad, b.mask & b.surface)
        else:
            sdf, l_eik = module.apply(dec, f), jnp.zeros(())
        l_bce = bce_loss(sdf, b.labels, beta, b.mask)
        return l_bce + weight_e * l_eik, (l_bce, l_eik)

    grad_fn = jax.value_and_grad(loss_fn, argnums=(0, 1) if train_decoder else (0,), has_aux=True)

    def body(i, carry):
        table, cnt, dec, dec_state, key, acc = carry
        key, k = jax.random.split(key)
        if hier:
            b = hierarchical.sample_hierarchical(k, store, ids, n, nv=nv, np_=np_, nt=nt, frame=frame,
                                                 keyframes=keyframes)
        else:
            b = hierarchical.sample_uniform(k, store, ids, n, batch=batch, frame=frame, keyframes=keyframes)
        rows = voxel_corner_rows[jnp.maximum(store.voxel_of_slot[b.slots], 0)]   # [G, L*8]
        feats = table[rows, VALUE]                                               # [G, L*8, D]
        n_groups, per_group = b.points.shape[:2]
        vox = jnp.repeat(store.coord[b.slots], per_group, axis=0)                # [G*K, 3]
        w, dw = gfeat.corner_weights_and_grad(b.points.reshape(-1, 3), vox, leaf, levels)
        w, dw = w.reshape(n_groups, per_group, -1), dw.reshape(n_groups, per_group, -1, 3)
        (loss, (l_bce, l_eik)), grads = grad_fn(feats, dec, w, dw, b)
        table, cnt = sparse_adam(table, cnt, rows.reshape(-1), grads[0].reshape(-1, table.shape[-1]), lr=lr)
        if train_decoder:
            dupd, dec_state = dec_tx.update(grads[1], dec_state, dec)
            dec = optax.apply_updates(dec, dupd)
        return table, cnt, dec, dec_state, key, acc + jnp.stack([loss, l_bce, l_eik])

    carry = (features, feat_count, dec_params, dec_opt, key, jnp.zeros((3,)))
    features, feat_count, dec_params, dec_opt, _, acc = jax.lax.fori_loop(0, iters, body, carry)
    return features, feat_count, dec_params, dec_opt, acc / iters


@functools.partial(jax.jit, static_argnames=("module", "leaf", "levels", "mask_level", "min_leaf_corners"))
def _query(features, corners, decoder, points_m, *, module, leaf: float, levels: int, mask_level: int,
           min_leaf_corners: int = 8):
    """SDF at map-frame points [N,3] -> (sdf [N], valid [N]).

    A point is valid where the 8 corners of its level-`mask_level` voxel have features (0 = only inside
    allocated leaf voxels; 1 = inside their 2x parents, which closes the gaps between LiDAR rings on
    grazing ground, as SHINE/N3 mesh at `mc_vis_level` 1), and at least `min_leaf_corners` of the 8
    corners of its leaf voxel have features (8 ~ allocated leaf voxels; fewer dilates the leaf region by
    up to one voxel without filling whole parents). Corners without features count as zero.
    """
    vox = gfeat.leaf_voxel(points_m, leaf)
    keys = gfeat.corner_keys(vox, levels)                                       # [N, L*8, 4]
    rows = hashing.lookup(corners, keys.reshape(-1, 4)).reshape(keys.shape[:2])
    valid = jnp.all(rows[:, mask_level * 8:(mask_level + 1) * 8] >= 0, axis=1)
    valid &= jnp.sum(rows[:, :8] >= 0, axis=1) >= min_leaf_corners
    w = gfeat.corner_weights(points_m, vox, leaf, levels)
    f = gfeat.interpolate(features[:, VALUE], rows, w)
    return module.apply(decoder, f), valid


@functools.partial(jax.jit, static_argnames=("module", "leaf", "levels", "mask_level", "min_leaf_corners"))
def _query_grad(features, corners, decoder, points_m, *, module, leaf: float, levels: int, mask_level: int,
                min_leaf_corners: int = 8):
    def f(p):
        return _query(features, corners, decoder, p, module=module, leaf=leaf, levels=levels,
                      mask_level=mask_level, min_leaf_corners=min_leaf_corners)[0]

    sdf, grad = sdf_and_grad(f, points_m)
    return sdf, grad


def mesh_cells(leaf_voxels: np.ndarray, mask_level: int) -> np.ndarray:
    """Leaf cells [M,3] covered by the level-`mask_level` parents of allocated leaf voxels [N,3]."""
    if mask_level == 0 or len(leaf_voxels) == 0:
        return leaf_voxels
    k = 1 << mask_level
    parents = np.unique(np.floor_divide(leaf_voxels, k), axis=0)
    offs = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return (parents[:, None, :] * k + offs[None]).reshape(-1, 3).astype(np.int32)


# --------------------------------------------------------------------------------------------
# The public mapper.
# --------------------------------------------------------------------------------------------


class N3Mapper:
    """Online N3 mapping of a range-scan sequence.

    >>> m = N3Mapper(cfg)                      # cfg: jaxmap.config.MapConfig
    >>> m.add_frame(points_s, pose)            # points_s [N,3] sensor frame; pose [4,4] T_world_sensor
    >>> sdf, valid = m.sdf(points_w)           # [M,3] world frame -> [M], [M]
    >>> mesh = m.mesh(res=0.1)                 # trimesh.Trimesh, world frame
    >>> m.save("runs/x/checkpoint"); m2 = N3Mapper.load("runs/x/checkpoint")
    """

    def __init__(self, cfg: MapConfig | None = None):
        self.cfg = cfg or MapConfig()
        g, t = self.cfg.grid, self.cfg.train
        self.levels = g.feature_levels
        self.leaf = float(g.leaf_vox_size)
        self.module, dec_params = init_decoder(jax.random.PRNGKey(t.seed + 1), g.feature_dim,
                                               self.cfg.decoder.hidden_dim, self.cfg.decoder.hidden_layers)
        self.origin: np.ndarray | None = None      # [3] float64, world position of the map frame
        self.timings: list[dict] = []
        n_rows = 1 << 16
        feat = gfeat.init_features(jax.random.PRNGKey(t.seed + 2), n_rows, g.feature_dim, g.feature_std)
        n_vox = 1 << 15
        self.state = N3State(
            voxels=hashing.create(_pow2(n_vox * 2)),
            corners=hashing.create(_pow2(n_rows * 2)),
            voxel_coord=jnp.zeros((n_vox, 3), jnp.int32),
            voxel_corner_rows=jnp.full((n_vox, self.levels * 8), -1, jnp.int32),
            features=_pack(feat),
            feat_count=jnp.zeros((), jnp.int32),
            decoder=dec_params,
            dec_opt=optax.adam(t.lr).init(dec_params),
            store=window.create(_pow2(self.cfg.window.initial_blocks), self.cfg.window.pairs_per_voxel, n_vox),
            key=jax.random.PRNGKey(t.seed),
            frame=jnp.zeros((), jnp.int32),
        )

    # ---- capacity management (outside jit; growth is logged, nothing is dropped) ----

    def _ensure_voxel_rows(self, n: int):
        s = self.state
        v = s.voxel_coord.shape[0]
        if n <= v:
            return
        nv = _pow2(n)
        log.debug("growing voxel arrays %d -> %d", v, nv)
        self.state = s.replace(
            voxel_coord=jnp.zeros((nv, 3), jnp.int32).at[:v].set(s.voxel_coord),
            voxel_corner_rows=jnp.full((nv, self.levels * 8), -1, jnp.int32).at[:v].set(s.voxel_corner_rows),
            store=window.grow(s.store, n_voxel_rows=nv),
        )

    def _ensure_feature_rows(self, n: int):
        s = self.state
        r, _, d = s.features.shape
        if n <= r:
            return
        nr = _pow2(n)
        log.debug("growing feature table %d -> %d rows", r, nr)
        key = jax.random.fold_in(jax.random.PRNGKey(self.cfg.train.seed + 2), r)
        extra = _pack(gfeat.init_features(key, nr - r, d, self.cfg.grid.feature_std))
        self.state = s.replace(features=jnp.concatenate([s.features, extra]))

    # ---- the per-frame update ----

    def add_frame(self, points_s: np.ndarray, pose: np.ndarray) -> dict:
        """Integrate one scan. points_s: [N,3] float32 sensor frame; pose: [4,4] T_world_sensor.

        Returns timings (seconds: preprocess, sampling, training) and store/feature statistics.
        """
        cfg = self.cfg
        pose = np.asarray(pose, np.float64)
        validate_pose(pose, where=f"pose of frame {int(self.state.frame)}")
        points_s = np.asarray(points_s, np.float32)
        if points_s.ndim != 2 or points_s.shape[1] != 3:
            raise ValueError(f"points must be [N,3], got {points_s.shape}")
        finite = np.all(np.isfinite(points_s), axis=1)
        if not finite.all():
            log.warning("frame %d: dropped %d NaN/inf points", int(self.state.frame), int((~finite).sum()))
            points_s = points_s[finite]
        if self.origin is None:
            coarse = self.leaf * 2 ** (self.levels - 1)
            self.origin = np.round(pose[:3, 3] / coarse) * coarse

        t0 = time.perf_counter()
        pts_s, nrm_s = preprocess_scan(points_s, cfg.preprocess)
        R, t = pose[:3, :3], pose[:3, 3]
        pts_m = (pts_s.astype(np.float64) @ R.T + (t - self.origin)).astype(np.float32)
        nrm_m = (nrm_s @ R.T.astype(np.float32)).astype(np.float32)
        origin_m = (t - self.origin).astype(np.float32)
        n = len(pts_m)
        n_pad = _bucket(n)
        pad = n_pad - n
        pts_p = np.concatenate([pts_m, np.repeat(origin_m[None] + 1.0, pad, 0)]) if pad else pts_m
        nrm_p = np.concatenate([nrm_m, np.tile([[0, 0, 1.0]], (pad, 1)).astype(np.float32)]) if pad else nrm_m
        valid = np.arange(n_pad) < n
        t1 = time.perf_counter()

        s = self.state
        key, k_sample, k_train = jax.random.split(s.key, 3)
        sc = cfg.sampling
        trunc = sc.surface_sample_range_m
        samples = _sample(k_sample, jnp.asarray(pts_p), jnp.asarray(nrm_p), jnp.asarray(valid), jnp.asarray(origin_m),
                          label_mode=sc.label_mode, trunc=trunc, sigma=sc.sigma_m, n_surface=sc.surface_sample_n,
                          n_free=sc.free_sample_n, free_band=sc.free_band_m,
                          free_label=trunc if sc.free_label_m < 0 else sc.free_label_m)
        vox, vkeys = _leaf_keys(samples.points, self.leaf)
        # Leaf voxels are allocated where near-surface samples land (all feature levels at once).
        alloc = samples.valid & samples.surface
        n_before = int(s.voxels.count)
        voxels, vrows = hashing.insert_grow(s.voxels, vkeys, alloc, max_load=cfg.grid.max_load)
        n_after = int(voxels.count)
        self.state = s.replace(voxels=voxels)
        self._ensure_voxel_rows(n_after)
        s = self.state
        voxel_coord = _set_rows(s.voxel_coord, vrows, vox)
        corners, voxel_corner_rows = s.corners, s.voxel_corner_rows
        if n_after > n_before:
            new_rows = np.arange(n_before, n_after)
            m_pad = _bucket(len(new_rows))
            rows_p = np.full(m_pad, -1, np.int32)
            rows_p[: len(new_rows)] = new_rows
            corners, crows = gfeat.allocate_corners(corners, voxel_coord[jnp.maximum(jnp.asarray(rows_p), 0)],
                                                    self.levels, max_load=cfg.grid.max_load,
                                                    valid=jnp.asarray(rows_p >= 0))      # [M, L*8]
            voxel_corner_rows = _set_rows(voxel_corner_rows, jnp.asarray(rows_p), crows)
        self.state = s.replace(corners=corners, voxel_coord=voxel_coord, voxel_corner_rows=voxel_corner_rows)
        self._ensure_feature_rows(int(corners.count))
        s = self.state

        # Free-space samples are kept where their leaf voxel has features; elsewhere they would
        # train nothing but the decoder's empty-space output (counted, not silently lost).
        free_rows = hashing.lookup(s.voxels, vkeys)
        rows_all = jnp.where(samples.valid & (samples.surface | (free_rows >= 0)), jnp.maximum(vrows, free_rows), -1)
        n_free_dropped = int(jnp.sum(samples.valid & ~samples.surface & (free_rows < 0)))

        wc = cfg.window
        radius_vox = int(math.ceil(cfg.preprocess.max_range_m / self.leaf))
        center_vox = jnp.asarray(np.floor(origin_m / self.leaf).astype(np.int32))
        keyframes = wc.keyframes if wc.mode == "keyframe" else 0
        frame = s.frame
        needed, free = _slots_needed(s.store, rows_all, center_vox, frame, radius_vox=radius_vox, mode=wc.mode,
                                     keyframes=keyframes)
        if int(needed) > int(free):
            grow_to = _pow2(s.store.n_slots + int(needed) - int(free))
            log.info("pair store full (%d blocks): growing to %d blocks", s.store.n_slots, grow_to)
            s = s.replace(store=window.grow(s.store, n_slots=grow_to))
        store, ids, n_win, overflow = _update_store(
            s.store, rows_all, vox, samples.points, samples.labels, samples.surface, frame, center_vox,
            radius_vox=radius_vox, mode=wc.mode, keyframes=keyframes)
        if bool(overflow):  # cannot happen after the check above; never continue with lost pairs
            raise CapacityError("pair store overflowed after growing; please report this bug")
        self.state = s.replace(store=store)
        s = self.state
        t2 = time.perf_counter()

        tc = cfg.train
        train_decoder = int(frame) < tc.freeze_after_frame
        feats, cnt, dec, dec_opt, losses = _train_frame(
            s.features, s.feat_count, s.decoder, s.dec_opt, s.store, s.voxel_corner_rows,
            ids, n_win, k_train, frame, module=self.module, iters=tc.iters, hier=tc.hierarchical, nv=tc.nv,
            np_=tc.np_per_voxel, nt=tc.nt, batch=tc.batch_size, keyframes=keyframes, leaf=self.leaf,
            levels=self.levels, lr=tc.lr, beta=tc.sigma_sigmoid_m, weight_e=tc.weight_e,
            train_decoder=train_decoder, reset_adam=tc.reset_adam_each_frame)
        losses = np.asarray(losses)
        self.state = s.replace(features=feats, feat_count=cnt, decoder=dec,
                               dec_opt=dec_opt, key=key, frame=frame + 1)
        t3 = time.perf_counter()
        info = {
            "frame": int(frame), "points": n, "preprocess_s": t1 - t0, "sampling_s": t2 - t1,
            "training_s": t3 - t2, "total_s": t3 - t0, "loss": float(losses[0]), "bce": float(losses[1]),
            "eikonal": float(losses[2]), "window_voxels": int(n_win), "store_pairs": int(window.total_pairs(s.store)),
            "store_bytes": store_bytes(s.store), "leaf_voxels": int(s.voxels.count),
            "feature_rows": int(s.corners.count), "feature_bytes": int(s.corners.count) * s.features.shape[-1] * 4,
            "free_dropped": n_free_dropped,
        }
        self.timings.append(info)
        return info

    # ---- queries ----

    def _query_batches(self, points_w: np.ndarray, fn, batch: int = 1 << 16):
        pts = np.asarray(points_w, np.float64)
        origin = self.origin if self.origin is not None else np.zeros(3)
        out = []
        s = self.state
        for i in range(0, len(pts), batch):
            chunk = (pts[i:i + batch] - origin).astype(np.float32)
            m = len(chunk)
            if m < batch:
                chunk = np.concatenate([chunk, np.zeros((batch - m, 3), np.float32)])
            res = fn(s.features, s.corners, s.decoder, jnp.asarray(chunk), module=self.module,
                     leaf=self.leaf, levels=self.levels, mask_level=self.cfg.mesh.mask_level,
                     min_leaf_corners=self.cfg.mesh.min_leaf_corners)
            out.append([np.asarray(r)[:m] for r in res])
        if not out:
            return None
        return [np.concatenate([o[k] for o in out]) for k in range(len(out[0]))]

    def sdf(self, points_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (metres) at world points [N,3] -> (sdf [N] float32, valid [N] bool)."""
        res = self._query_batches(points_w, _query)
        if res is None:
            return np.zeros(0, np.float32), np.zeros(0, bool)
        return res[0], res[1]

    def sdf_grad(self, points_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(sdf [N], d sdf / d x [N,3]) at world points [N,3] (for planners)."""
        res = self._query_batches(points_w, _query_grad)
        if res is None:
            return np.zeros(0, np.float32), np.zeros((0, 3), np.float32)
        return res[0], res[1]

    def mesh(self, res: float | None = None, min_component_faces: int | None = None):
        """Marching-cubes mesh of the zero level set, world frame (trimesh.Trimesh)."""
        from jaxmap.mesh import extract_mesh

        res = float(res or self.cfg.mesh.resolution_m)
        mcf = self.cfg.mesh.min_component_faces if min_component_faces is None else min_component_faces
        n = int(self.state.voxels.count)
        cells = mesh_cells(np.asarray(self.state.voxel_coord[:n]), self.cfg.mesh.mask_level)
        origin = self.origin if self.origin is not None else np.zeros(3)
        # Lattice aligned to the world origin (one fixed grid for every method): res must divide leaf.
        k = self.leaf / res
        if abs(k - round(k)) > 1e-6:
            raise ValueError(f"mesh resolution {res} must divide the leaf voxel size {self.leaf}")

        def sdf_fn(p_m):
            s, v = self.sdf(p_m.astype(np.float64) + origin)
            return s, v

        mesh = extract_mesh(sdf_fn, cells, self.leaf, res, min_component_faces=mcf)
        mesh.apply_translation(origin)
        return mesh

    # ---- persistence ----

    def save(self, path: str) -> None:
        from jaxmap.checkpoint import save_mapper

        save_mapper(self, path)

    @classmethod
    def load(cls, path: str) -> "N3Mapper":
        from jaxmap.checkpoint import load_mapper

        return load_mapper(path)


def _pack(values):
    """[R, D] initial feature values -> [R, 4, D] (value, mu = 0, nu = 0, accumulator = 0)."""
    return jnp.concatenate([values[:, None], jnp.zeros((values.shape[0], 3, values.shape[1]), values.dtype)], 1)


def store_bytes(store: window.PairStore) -> int:
    """Bytes of the pair store's arrays (the sliding window's memory)."""
    return int(sum(np.prod(x.shape) * x.dtype.itemsize for x in jax.tree_util.tree_leaves(store)))


def _pow2(n: int) -> int:
    return 1 << max(int(n) - 1, 1).bit_length()
