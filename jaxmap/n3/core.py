"""The N3 mapping engine as pure functions over one state pytree.

    static = N3Static.from_config(cfg)                # frozen, hashable: shapes and modes
    state = init_state(static, cfg, capacities_for(static, cfg))
    state = set_origin(static, state, sensor_xyz_world) # once, before the first frame
    state, frame_stats, train_stats = step(static, state, scan)   # integrate + train, one jit
    ... = step_raw(static, state, raw_scan, rows)      # the same from a raw scan (preprocess.device)
    sdf, valid = query(static, state, points_m)

`integrate(static, state, scan, key)` samples the frame's training pairs, allocates leaf voxels and
their corner feature rows (fixed-capacity hash tables), stores the pairs in their voxels' blocks,
slides the window and lets the frame's free space carve the pairs it contradicts (`window.carve`:
what moved away is erased). `train(static, state, key, active)` runs the K iterations of hierarchical
sampling, loss (BCE + eikonal through `jax.grad`) and Adam in one `lax.fori_loop`. `step` is both
in one compiled program with the state donated, so every table is updated in place.

Capacities are fixed inside jit. Nothing is dropped when one runs out: `integrate` is all or
nothing for the pair store, hash inserts revert themselves on overflow, corner allocation is a
queue worked off `new_voxels_per_pass` voxels at a time, and `FrameStats.ok` is False until the
frame is fully in; then `train` does nothing and the PRNG key does not advance, so the host grows
what the stats name (`grow_for`, outside jit) and calls `step` again with the same scan, with
the same result as if the capacity had been there from the start.

Frames: the state lives in a *map frame* = world - origin, origin = `origin_vox * leaf` (an
integer voxel index, snapped to the coarsest level), so float32 stays precise on large scenes.
"""
from __future__ import annotations

import collections
import dataclasses
import functools
import logging
import math
import time
from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxmap import hostmem
from jaxmap.grid import features as gfeat
from jaxmap.grid import hashing
from jaxmap.n3 import adam, hierarchical, pool, window
from jaxmap.n3.decoder import init_decoder
from jaxmap.n3.field import mlp, n3_loss
from jaxmap.n3.loss import sdf_and_grad
from jaxmap.n3.sampling import sample_frame

log = logging.getLogger("jaxmap")


@dataclasses.dataclass(frozen=True)
class N3Static:
    """Everything that fixes the compiled programs (hashable; a jit static argument). Values that
    do not change shapes or control flow (learning rate, beta, eikonal weight) are in `Hyper`."""

    leaf: float                 # leaf voxel size, metres
    levels: int                 # feature levels L
    feature_dim: int            # D
    hidden_dim: int
    hidden_layers: int
    label_mode: str
    trunc: float
    sigma: float
    n_surface: int
    n_free: int                 # free samples in the band before the truncation region
    n_ray: int                  # free samples along the whole ray
    free_min_range: float       # where the ray's free samples start (metres from the sensor)
    ray_quiet: int              # ray samples use only voxels no frame hit within this many frames
    point_filter: float         # > 0: scan points where the map's SDF exceeds this get no samples
    free_band: float
    free_label: float
    free_label_mode: str
    carve: bool                 # free-space ray samples replace the stored pairs they contradict
    carve_margin: float
    carve_samples: int
    carve_rule: str
    carve_sign: bool            # every ray sample (sign only) raises the pairs stored deeper than it allows
    iters: int
    hierarchical: bool
    nv: int
    np_per_voxel: int
    nt: int
    batch_size: int
    freeze_after_frame: int
    reset_adam: bool
    window_mode: str
    keyframes: int
    block_policy: str
    pairs_per_frame: int
    radius_vox: int             # window half-width in leaf voxels (the crop radius)
    max_load: float
    mask_level: int
    min_leaf_corners: int
    preprocess: object = None   # the PreprocessConfig when scans are preprocessed inside the frame program
    # Corner allocations per `integrate` pass (a static batch of L*8 keys each): a typical frame
    # of the city brings ~1700 new voxels (max ~6000); the first frame ~20000 takes 3 passes.
    new_voxels_per_pass: int = 8192

    @classmethod
    def from_config(cls, cfg) -> "N3Static":
        g, s, t, w, m = cfg.grid, cfg.sampling, cfg.train, cfg.window, cfg.mesh
        leaf = float(g.leaf_vox_size)
        return cls(
            leaf=leaf, levels=g.feature_levels, feature_dim=g.feature_dim, hidden_dim=cfg.decoder.hidden_dim,
            hidden_layers=cfg.decoder.hidden_layers, label_mode=s.label_mode, trunc=s.surface_sample_range_m,
            sigma=s.sigma_m, n_surface=s.surface_sample_n, n_free=s.free_sample_n, n_ray=s.free_ray_n,
            free_min_range=cfg.preprocess.min_range_m, ray_quiet=s.free_ray_quiet_frames, free_band=s.free_band_m,
            point_filter=s.free_point_filter_m,
            free_label=s.surface_sample_range_m if s.free_label_m < 0 else s.free_label_m,
            free_label_mode=s.free_label_mode, carve=w.carve, carve_margin=w.carve_margin_m,
            carve_samples=w.carve_samples, carve_rule=w.carve_rule, carve_sign=w.carve_sign,
            iters=t.iters, hierarchical=t.hierarchical, nv=t.nv, np_per_voxel=t.np_per_voxel, nt=t.nt,
            batch_size=t.batch_size, freeze_after_frame=t.freeze_after_frame, reset_adam=t.reset_adam_each_frame,
            window_mode=w.mode, keyframes=w.keyframes if w.mode == "keyframe" else 0,
            block_policy=w.block_policy, pairs_per_frame=w.pairs_per_frame,
            radius_vox=int(math.ceil(cfg.preprocess.max_range_m / leaf)), max_load=g.max_load,
            mask_level=m.mask_level, min_leaf_corners=m.min_leaf_corners,
            preprocess=cfg.preprocess if cfg.preprocess.device else None,
        )

    @property
    def corners_per_voxel(self) -> int:
        return self.levels * 8

    @property
    def uses_pool(self) -> bool:
        """The replay / keyframe ablations keep a flat pool of pairs instead of per-voxel blocks."""
        return self.window_mode in ("replay", "keyframe")


@flax.struct.dataclass
class Hyper:
    lr: jax.Array        # [] Adam learning rate (features and decoder)
    beta: jax.Array      # [] BCE sigmoid scale, metres
    weight_e: jax.Array  # [] eikonal weight


@flax.struct.dataclass
class N3State:
    voxels: hashing.HashTable              # leaf voxel (x, y, z, 0) -> voxel row
    corners: hashing.HashTable             # corner (x, y, z, level) -> feature row
    voxel_coord: jax.Array                 # [V, 3] int32 leaf-voxel coordinate of each voxel row
    voxel_corner_rows: jax.Array           # [V, L*8] int32 feature rows of the voxel's corners (-1: not yet)
    voxels_with_corners: jax.Array         # [] int32: rows [0, this) have their corner rows
    feature_table: jax.Array               # [R, D] float32 corner features
    feature_opt: adam.SparseAdamState      # sparse Adam moments of feature_table
    decoder: dict                          # flax params of the SDF decoder
    decoder_opt: optax.ScaleByAdamState    # Adam moments of the decoder
    store: window.PairStore                # voxel-oriented training pairs and the current window
    pool: pool.PairPool | None             # flat pool of pairs (replay / keyframe ablations), else None
    origin_vox: jax.Array                  # [3] int32: map origin in leaf voxels (world = map + origin)
    key: jax.Array                         # PRNG key, split once per frame
    frame: jax.Array                       # [] int32 frames integrated and trained so far
    hyper: Hyper


class ScanBatch(NamedTuple):
    """One preprocessed scan in the map frame, padded to a bucket size N."""

    points: jax.Array    # [N, 3] float32 map frame
    normals: jax.Array   # [N, 3] float32 unit, oriented towards the sensor
    valid: jax.Array     # [N] bool, False for padding
    sensor: jax.Array    # [3] float32 sensor position, map frame


class RawScan(NamedTuple):
    """One raw scan in the sensor frame, padded to a bucket size N, and its pose in the map frame
    (`preprocess.device`: the frame program crops, downsamples and estimates normals itself)."""

    points: jax.Array       # [N, 3] float32 sensor frame
    valid: jax.Array        # [N] bool, False for padding
    rotation: jax.Array     # [3, 3] float32 R_map_sensor
    translation: jax.Array  # [3] float32 sensor position, map frame


class FrameStats(NamedTuple):
    """What the host reads once per frame (one `jax.device_get`)."""

    ok: jax.Array               # [] bool: the frame is in and trained; False: grow what is flagged, retry
    voxel_overflow: jax.Array   # [] bool: voxel table or voxel rows full
    corner_overflow: jax.Array  # [] bool: corner table or feature rows full
    store_overflow: jax.Array   # [] bool: not enough free blocks
    pending_corners: jax.Array  # [] int32: voxels still waiting for corner rows (another pass needed)
    voxels: jax.Array           # [] int32 leaf voxels allocated
    feature_rows: jax.Array     # [] int32 corner rows allocated
    new_voxels: jax.Array       # [] int32 voxels this pass allocated
    new_feature_rows: jax.Array # [] int32 corner rows this pass allocated
    blocks_needed: jax.Array    # [] int32 (pool ablations: pairs the pool must hold after the frame)
    blocks_free: jax.Array      # [] int32 (pool ablations: 0)
    window_blocks: jax.Array    # [] int32 blocks in the window holding pairs
    store_pairs: jax.Array      # [] int32 pairs held by the store
    free_dropped: jax.Array     # [] int32 free-space samples outside every allocated voxel (train nothing)
    carved: jax.Array           # [] int32 stored pairs that this frame's free space contradicted and changed
    points_filtered: jax.Array  # [] int32 scan points dropped where the map was confidently free
    scan_points: jax.Array      # [] int32 points of the preprocessed scan
    scan_overflow: jax.Array    # [] bool: the preprocessed scan has more points than its rows (grow, retry)


class TrainStats(NamedTuple):
    loss: jax.Array     # [] mean over the K iterations
    bce: jax.Array
    eikonal: jax.Array


@dataclasses.dataclass(frozen=True)
class Capacities:
    """Array sizes of a state (host-side; a change recompiles)."""

    voxel_slots: int     # voxel hash-table slots (power of two)
    voxel_rows: int      # V
    corner_slots: int    # corner hash-table slots (power of two)
    feature_rows: int    # R
    store_blocks: int    # S
    pairs_per_block: int # P
    pool_pairs: int = 0  # pairs of the flat pool (replay / keyframe ablations; 0 = none)

    @classmethod
    def of(cls, state: N3State) -> "Capacities":
        return cls(state.voxels.capacity, state.voxel_coord.shape[0], state.corners.capacity,
                   state.feature_table.shape[0], state.store.n_slots, state.store.block_size,
                   state.pool.capacity if state.pool is not None else 0)


def pow2(n: int) -> int:
    return 1 << max(int(n) - 1, 1).bit_length()


def _round_up(n: float, step: int = 1 << 14) -> int:
    return int(math.ceil(max(n, 1) / step) * step)


def capacities_for(static: N3Static, cfg) -> Capacities:
    """Initial sizes from the config, so that a drive of a few hundred metres never grows.

    The window (a cube of half-width = crop radius) holds about `2 pi r^2 / leaf^2` surface voxels
    (ground disc plus as much again of facades, cars and trees); the store gets 1.5x that many
    blocks (or `window.initial_blocks` if larger). The map keeps 4 windows' worth of voxels and
    2.5 corner rows per voxel (2.2 measured on the city) before anything grows; hash tables get the
    power-of-two slot counts that keep them under `max_load`.
    """
    r = cfg.preprocess.max_range_m
    window_voxels = 2.0 * math.pi * r * r / static.leaf**2
    blocks = max(_round_up(1.5 * window_voxels), pow2(cfg.window.initial_blocks))
    voxels = _round_up(4 * window_voxels + 2 * static.new_voxels_per_pass)
    rows = _round_up(2.5 * voxels)
    pool_pairs = 0
    if static.uses_pool:  # the ablations: no blocks; the pool starts at ~16 frames' worth (a scan
        # brings about one point per window voxel) and doubles when full
        blocks, pool_pairs = 16, _round_up(16 * window_voxels * (static.n_surface + static.n_free + static.n_ray))
    return Capacities(voxel_slots=pow2(voxels / static.max_load), voxel_rows=voxels,
                      corner_slots=pow2(rows / static.max_load), feature_rows=rows,
                      store_blocks=blocks, pairs_per_block=cfg.window.pairs_per_voxel, pool_pairs=pool_pairs)


FEATURE_INIT_BLOCK = 1 << 16


def _init_features(seed: int, start: int, n: int, dim: int, std: float) -> jax.Array:
    """Rows [start, start + n) of the feature table's N(0, std^2) initialisation.

    Rows come in doubling blocks, [0, B), [B, 2B), [2B, 4B), ..., each from its own key
    (`fold_in(seed + 2, block start)`, the first from the key itself), so a row's initial value does
    not depend on the table's capacity or on when it grew (threefry draws are prefix-stable).
    """
    base = jax.random.PRNGKey(seed + 2)
    out, lo, hi = [], start, start + n
    b0, b1 = 0, FEATURE_INIT_BLOCK
    while lo < hi:
        if lo < b1:
            key = base if b0 == 0 else jax.random.fold_in(base, b0)
            top = min(hi, b1)
            out.append(gfeat.init_features(key, top - b0, dim, std)[lo - b0:])
            lo = top
        b0, b1 = b1, 2 * b1
    return jnp.concatenate(out) if out else jnp.zeros((0, dim), jnp.float32)


def init_state(static: N3Static, cfg, caps: Capacities) -> N3State:
    """An empty map with the given capacities (host-side)."""
    t = cfg.train
    _, dec = init_decoder(jax.random.PRNGKey(t.seed + 1), static.feature_dim, static.hidden_dim,
                          static.hidden_layers)
    table = _init_features(t.seed, 0, caps.feature_rows, static.feature_dim, cfg.grid.feature_std)
    return N3State(
        voxels=hashing.create(caps.voxel_slots),
        corners=hashing.create(caps.corner_slots),
        voxel_coord=jnp.zeros((caps.voxel_rows, 3), jnp.int32),
        voxel_corner_rows=jnp.full((caps.voxel_rows, static.corners_per_voxel), -1, jnp.int32),
        voxels_with_corners=jnp.zeros((), jnp.int32),
        feature_table=table,
        feature_opt=adam.sparse_adam().init(table),
        decoder=dec,
        decoder_opt=optax.scale_by_adam().init(dec),
        store=window.create(caps.store_blocks, caps.pairs_per_block, caps.voxel_rows),
        pool=pool.create(caps.pool_pairs) if static.uses_pool else None,
        origin_vox=jnp.zeros((3,), jnp.int32),
        key=jax.random.PRNGKey(t.seed),
        frame=jnp.zeros((), jnp.int32),
        hyper=Hyper(lr=jnp.float32(t.lr), beta=jnp.float32(t.sigma_sigmoid_m), weight_e=jnp.float32(t.weight_e)),
    )


def set_origin(static: N3Static, state: N3State, sensor_world: np.ndarray) -> N3State:
    """Map origin at the sensor position (world, metres), snapped to the coarsest voxel level."""
    coarse = 1 << (static.levels - 1)
    k = np.round(np.asarray(sensor_world, np.float64) / (static.leaf * coarse))
    return state.replace(origin_vox=jnp.asarray(k * coarse, jnp.int32))


def origin_world(static: N3Static, state: N3State) -> np.ndarray:
    """[3] float64 world position of the map frame's origin."""
    return np.asarray(jax.device_get(state.origin_vox), np.float64) * static.leaf


# ---------------------------------------------------------------------------------------------
# integrate: sample, allocate, store, slide
# ---------------------------------------------------------------------------------------------


def integrate(static: N3Static, state: N3State, scan: ScanBatch, key, fits=True) -> tuple[N3State, FrameStats]:
    """Put one scan into the map (one pass; see the module docstring for `ok` and retries).
    fits: [] bool, False when the preprocessed scan did not fit its rows (nothing is stored)."""
    fits = jnp.asarray(fits, bool)
    scan = scan._replace(valid=scan.valid & fits)
    n = scan.points.shape[0]
    ns, nf = static.n_surface, static.n_free + static.n_ray   # nf: free samples of both kinds
    n_filtered = jnp.zeros((), jnp.int32)
    if static.point_filter > 0:
        # PIN-SLAM's dynamic filter: a scan point where the map, as trained so far, is confidently free
        # (SDF above the threshold in a voxel whose block holds at least Nt pairs: only voxels near
        # surfaces are allocated, so this is space the map once held as surface, or next to one, and
        # later saw free) is something that moved in, or an artifact (a mixed pixel between a
        # foreground and a background): it gets no samples, so it neither draws a surface nor marks its
        # voxel as hit (which would shield it from carving).
        sdf, q_ok = query(static, state, scan.points)
        pv = gfeat.leaf_voxel(scan.points, static.leaf)
        prow = hashing.lookup(state.voxels, jnp.concatenate([pv, jnp.zeros_like(pv[:, :1])], -1))
        pslot = window.block_of(state.store, prow)
        trained = (pslot >= 0) & (state.store.count[jnp.maximum(pslot, 0)] >= max(static.nt, 1))
        # (once the decoder is frozen: before that the field is still finding its shape)
        mature = state.frame >= static.freeze_after_frame
        drop = scan.valid & q_ok & trained & (sdf > static.point_filter) & mature
        n_filtered = jnp.sum(drop, dtype=jnp.int32)
        scan = scan._replace(valid=scan.valid & ~drop)
    samples = sample_frame(key, scan.points, scan.normals, scan.valid, scan.sensor, label_mode=static.label_mode,
                           trunc=static.trunc, sigma=static.sigma, n_surface=ns, n_free=static.n_free,
                           free_band=static.free_band, free_label=static.free_label,
                           free_label_mode=static.free_label_mode, n_ray=static.n_ray,
                           min_range=static.free_min_range)
    vox = gfeat.leaf_voxel(samples.points, static.leaf)                           # [N*(ns+nf), 3]
    vkeys = jnp.concatenate([vox, jnp.zeros_like(vox[:, :1])], -1).reshape(n, ns + nf, 4)
    valid = samples.valid.reshape(n, ns + nf)

    # Leaf voxels where near-surface samples land (all feature levels at once).
    v_rows_cap = state.voxel_coord.shape[0]
    v_limit = min(int(static.max_load * state.voxels.capacity), v_rows_cap)
    voxels, surf_rows, v_over, n_new_v, _ = hashing._insert_impl(
        state.voxels, vkeys[:, :ns].reshape(-1, 4), valid[:, :ns].reshape(-1), hashing.DEFAULT_MAX_PROBES, v_limit)
    surf_vox = vox.reshape(n, ns + nf, 3)[:, :ns].reshape(-1, 3)
    voxel_coord = state.voxel_coord.at[jnp.where(surf_rows >= 0, surf_rows, v_rows_cap)].set(surf_vox, mode="drop")

    # Corner rows for up to `new_voxels_per_pass` voxels that have none yet (a queue: rows are
    # handed out in order, so those voxels are rows [voxels_with_corners, count)).
    k = static.new_voxels_per_pass
    done = state.voxels_with_corners
    pend = done + jnp.arange(k, dtype=jnp.int32)
    pend_ok = pend < voxels.count
    ckeys = gfeat.corner_keys(voxel_coord[jnp.minimum(pend, v_rows_cap - 1)], static.levels)  # [k, L*8, 4]
    c_limit = min(int(static.max_load * state.corners.capacity), state.feature_table.shape[0])
    corners, crows, c_over, n_new_c, _ = hashing._insert_impl(
        state.corners, ckeys.reshape(-1, 4), jnp.repeat(pend_ok, static.corners_per_voxel),
        hashing.DEFAULT_MAX_PROBES, c_limit)
    wrote = pend_ok & ~c_over
    voxel_corner_rows = state.voxel_corner_rows.at[jnp.where(wrote, pend, v_rows_cap)].set(
        crows.reshape(k, -1), mode="drop")
    done = done + jnp.sum(wrote, dtype=jnp.int32)
    pending = voxels.count - done

    # Free-space samples train where their leaf voxel has features; elsewhere they would only train
    # the decoder's empty-space output (counted in the stats, not silently lost).
    free_rows = hashing.lookup(voxels, vkeys[:, ns:].reshape(-1, 4)).reshape(n, nf)
    free_ok = valid[:, ns:] & (free_rows >= 0)
    ray_ok = jnp.zeros((n, 0), bool)
    ray_any = free_ok[:, static.n_free:]   # every ray sample in an allocated voxel (before the honesty rules)
    if static.n_ray:
        # A ray sample in a voxel this frame hits may pass centimetres from a surface that is not its
        # own hit (a pole beside the ray), where its label (distance to its own hit's tangent plane)
        # would lie: such samples are dropped. What moved away is hit by nobody any more.
        v_cap = state.voxel_coord.shape[0]
        hit_voxel = jnp.zeros((v_cap,), bool).at[jnp.where(surf_rows >= 0, surf_rows, v_cap)].set(True, mode="drop")
        ray_ok = free_ok[:, static.n_free:] & ~hit_voxel[jnp.maximum(free_rows[:, static.n_free:], 0)]
        # ... and so are those in voxels an earlier frame hit within the last `ray_quiet` frames: a
        # static surface is hit again and again (a 10 Hz LiDAR's rings sweep the road), what moved
        # away is not, so only the space of what left is carved and trained free.
        slot = window.block_of(state.store, free_rows[:, static.n_free:])
        recent = (slot >= 0) & (state.store.last_hit[jnp.maximum(slot, 0)] >= state.frame - static.ray_quiet)
        ray_ok &= ~recent
        free_ok = free_ok.at[:, static.n_free:].set(ray_ok)
    rows = jnp.concatenate([jnp.where(valid[:, :ns], surf_rows.reshape(n, ns), -1),
                            jnp.where(free_ok, free_rows, -1)], axis=1).reshape(-1)
    allowed = ~v_over & ~c_over & (pending == 0) & fits
    carved = jnp.zeros((), jnp.int32)
    center = gfeat.leaf_voxel(scan.sensor[None], static.leaf)[0]
    if static.uses_pool:  # the replay / keyframe ablations: the frame's pairs go to the flat pool
        new_pool, pst = pool.update(state.pool, rows, samples.points, samples.labels, samples.surface,
                                    state.frame, allowed, keyframes=static.keyframes)
        zero = jnp.zeros((), jnp.int32)
        store, ok, needed, free, pairs = state.store, pst.ok, pst.needed, zero, new_pool.n
    else:
        store, ids, n_win, sst = window.update(
            state.store, rows, vox, samples.points, samples.labels, samples.surface, state.frame, center, allowed,
            jax.random.fold_in(key, 1), radius_vox=static.radius_vox, policy=static.block_policy,
            pairs_per_frame=static.pairs_per_frame)
        store = store.replace(window_ids=jnp.where(sst.ok, ids, state.store.window_ids),
                              window_n=jnp.where(sst.ok, n_win, state.store.window_n))
        new_pool, ok, needed, free = None, sst.ok, sst.blocks_needed, sst.blocks_free
        if static.carve and static.n_ray:
            lab = samples.labels.reshape(n, ns + nf)[:, ns + static.n_free:].reshape(-1)
            pts = samples.points.reshape(n, ns + nf, 3)[:, ns + static.n_free:].reshape(-1, 3)
            store, carved = window.carve(
                store, jnp.where(ray_ok, free_rows[:, static.n_free:], -1).reshape(-1), pts, lab,
                ray_ok.reshape(-1) & sst.ok, state.frame, jax.random.fold_in(key, 2), margin=static.carve_margin,
                max_samples=static.carve_samples, quiet_frames=static.ray_quiet, rule=static.carve_rule)
            if static.carve_sign:
                # The one thing every ray sample is sure of is its sign: the ray passed through it, so it
                # is outside every object, f(y) > 0, and f(x) > -|x - y| nearby. A pair stored deeper
                # inside than that is gone, whatever hit the voxel lately (no quiet rule needed).
                store, signed = window.carve(
                    store, jnp.where(ray_any, free_rows[:, static.n_free:], -1).reshape(-1), pts,
                    jnp.zeros_like(lab), ray_any.reshape(-1) & sst.ok, state.frame, jax.random.fold_in(key, 3),
                    margin=static.carve_margin, max_samples=static.carve_samples, quiet_frames=-1, rule="raise")
                carved = carved + signed
        pairs = window.total_pairs(store)
    state = state.replace(voxels=voxels, corners=corners, voxel_coord=voxel_coord,
                          voxel_corner_rows=voxel_corner_rows, voxels_with_corners=done, store=store, pool=new_pool)
    stats = FrameStats(
        ok=ok, voxel_overflow=v_over, corner_overflow=c_over, store_overflow=allowed & ~ok,
        pending_corners=pending, voxels=voxels.count, feature_rows=corners.count, new_voxels=n_new_v,
        new_feature_rows=n_new_c, blocks_needed=needed, blocks_free=free, window_blocks=store.window_n,
        store_pairs=pairs, free_dropped=jnp.sum(valid[:, ns:] & (free_rows < 0), dtype=jnp.int32),
        carved=carved, points_filtered=n_filtered, scan_points=jnp.sum(scan.valid, dtype=jnp.int32),
        scan_overflow=~fits,
    )
    return state, stats


# ---------------------------------------------------------------------------------------------
# train: K iterations in one loop
# ---------------------------------------------------------------------------------------------


def train(static: N3Static, state: N3State, key, active=True) -> tuple[N3State, TrainStats]:
    """K iterations of (hierarchical) batch selection, loss and Adam over the current window.

    Features get sparse Adam on the rows each batch touches (O(batch) per iteration, however large
    the map); the decoder gets Adam until frame `freeze_after_frame`. active: [] bool; False runs
    no iteration and leaves the state as it is (a frame that did not fit yet).
    """
    active = jnp.asarray(active, bool)
    store, h = state.store, state.hyper
    ids, n = store.window_ids, store.window_n
    opt = adam.sparse_adam()
    dec_tx = optax.scale_by_adam()
    train_decoder = active & (state.frame < static.freeze_after_frame)
    feature_opt = state.feature_opt
    if static.reset_adam:  # the original N3 code rebuilds its optimiser every frame
        fresh = adam.reset(feature_opt)
        feature_opt = jax.tree_util.tree_map(lambda a, b: jnp.where(active, a, b), fresh, feature_opt)
    loss = functools.partial(n3_loss, leaf=static.leaf, levels=static.levels)
    grad_both = jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)
    grad_feats = jax.value_and_grad(loss, argnums=0, has_aux=True)

    def loss_grad(*args):
        # The decoder's gradient costs ~40 % of the step; once it is frozen it is not computed.
        def feats_only(args):
            out, g = grad_feats(*args)
            return out, (g, jax.tree_util.tree_map(jnp.zeros_like, args[1]))

        return jax.lax.cond(train_decoder, lambda a: grad_both(*a), feats_only, args)

    def body(_, carry):
        table, f_opt, dec, d_opt, key, acc = carry
        key, k = jax.random.split(key)
        if static.uses_pool:
            b = hierarchical.sample_pool(k, state.pool, state.voxel_coord, batch=static.batch_size)
        elif static.hierarchical:
            b = hierarchical.sample_hierarchical(k, store, ids, n, nv=static.nv, np_=static.np_per_voxel,
                                                 nt=static.nt)
        else:
            b = hierarchical.sample_uniform(k, store, ids, n, batch=static.batch_size)
        rows = state.voxel_corner_rows[jnp.maximum(b.voxel_rows, 0)]                     # [G, L*8]
        feats = table[jnp.maximum(rows, 0)]                                              # [G, L*8, D]
        (loss, (l_bce, l_eik)), (g_feat, g_dec) = loss_grad(feats, dec, b, b.coords, h.beta,
                                                             h.weight_e)
        table, f_opt = opt.update(table, f_opt, rows.reshape(-1), g_feat.reshape(-1, table.shape[-1]), h.lr)
        upd, d_opt_new = dec_tx.update(g_dec, d_opt, dec)
        dec_new = jax.tree_util.tree_map(lambda p, u: p - h.lr * u, dec, upd)
        dec, d_opt = jax.tree_util.tree_map(lambda a, b: jnp.where(train_decoder, a, b), (dec_new, d_opt_new),
                                            (dec, d_opt))
        return table, f_opt, dec, d_opt, key, acc + jnp.stack([loss, l_bce, l_eik])

    n_iters = jnp.where(active, static.iters, 0)
    carry = (state.feature_table, feature_opt, state.decoder, state.decoder_opt, key, jnp.zeros((3,)))
    table, f_opt, dec, d_opt, _, acc = jax.lax.fori_loop(0, n_iters, body, carry)
    acc = acc / static.iters
    state = state.replace(feature_table=table, feature_opt=f_opt, decoder=dec, decoder_opt=d_opt,
                          frame=state.frame + active.astype(jnp.int32))
    return state, TrainStats(acc[0], acc[1], acc[2])


@functools.partial(jax.jit, static_argnums=0, donate_argnums=1)
def step(static: N3Static, state: N3State, scan: ScanBatch):
    """integrate + train of one frame, one compiled program, the state donated (updated in place).
    Returns (state, FrameStats, TrainStats); when `FrameStats.ok` is False nothing was trained and
    the key did not advance: grow (`grow_for`) and call again with the same scan."""
    key, k_sample, k_train = jax.random.split(state.key, 3)
    state, fstats = integrate(static, state, scan, k_sample)
    state, tstats = train(static, state, k_train, active=fstats.ok)
    return state.replace(key=jnp.where(fstats.ok, key, state.key)), fstats, tstats


def prepare_scan(static: N3Static, raw: RawScan, rows: int) -> tuple[ScanBatch, jax.Array, jax.Array]:
    """Crop, downsample and normals of a raw scan (`jaxmap.preprocess_device`), its kept points in
    their input order moved to the map frame and packed into `rows` rows (padding as `scan.to_batch`).
    Returns (ScanBatch [rows], points kept [] int32, overflow [] bool: more kept points than rows)."""
    from jaxmap.preprocess_device import preprocess_scan

    pts_s, nrm_s, valid, kept = preprocess_scan(raw.points, raw.valid, static.preprocess, rows)
    # Elementwise, not a matmul: a GPU's float32 matmul may round through TF32 (centimetres at 20 m).
    pts = jnp.sum(pts_s[:, None, :] * raw.rotation[None], axis=-1) + raw.translation
    nrm = jnp.sum(nrm_s[:, None, :] * raw.rotation[None], axis=-1)
    pts = jnp.where(valid[:, None], pts, raw.translation + 1.0)
    nrm = jnp.where(valid[:, None], nrm, np.array([0.0, 0.0, 1.0], np.float32))
    return ScanBatch(pts, nrm, valid, raw.translation), kept, kept > rows


@functools.partial(jax.jit, static_argnums=(0, 3), donate_argnums=1)
def step_raw(static: N3Static, state: N3State, raw: RawScan, rows: int):
    """`step` of a raw scan: preprocessing, integrate and train in one compiled program. When the
    preprocessed scan has more points than `rows`, nothing is stored or trained (`scan_overflow`)."""
    scan, kept, overflow = prepare_scan(static, raw, rows)
    key, k_sample, k_train = jax.random.split(state.key, 3)
    state, fstats = integrate(static, state, scan, k_sample, fits=~overflow)
    state, tstats = train(static, state, k_train, active=fstats.ok)
    fstats = fstats._replace(scan_points=kept)
    return state.replace(key=jnp.where(fstats.ok, key, state.key)), fstats, tstats


@functools.partial(jax.jit, static_argnums=0)
def count_kept(static: N3Static, raw: RawScan):
    """Points a raw scan keeps after crop and downsample (sizes the first frame's rows)."""
    from jaxmap.preprocess_device import crop_mask, voxel_keep

    p = static.preprocess
    keep = crop_mask(raw.points, raw.valid, min_range=p.min_range_m, max_range=p.max_range_m, min_z=p.min_z_m,
                     max_z=p.max_z_m)
    return jnp.sum(voxel_keep(raw.points, keep, p.vox_down_m), dtype=jnp.int32)


# ---------------------------------------------------------------------------------------------
# queries
# ---------------------------------------------------------------------------------------------


def query(static: N3Static, state: N3State, points_m):
    """SDF at map-frame points [N, 3] -> (sdf [N] float32, valid [N] bool).

    A point is valid where the 8 corners of its level-`mask_level` voxel have features (0 = only
    inside allocated leaf voxels; 1 = inside their 2x parents, which closes the gaps between LiDAR
    rings on grazing ground, as SHINE/N3 mesh at `mc_vis_level` 1), and at least `min_leaf_corners`
    of the 8 corners of its leaf voxel have features. Corners without features count as zero.
    """
    vox = gfeat.leaf_voxel(points_m, static.leaf)
    keys = gfeat.corner_keys(vox, static.levels)                                   # [N, L*8, 4]
    rows = hashing.lookup(state.corners, keys.reshape(-1, 4)).reshape(keys.shape[:2])
    ml = static.mask_level
    valid = jnp.all(rows[:, ml * 8:(ml + 1) * 8] >= 0, axis=1)
    valid &= jnp.sum(rows[:, :8] >= 0, axis=1) >= static.min_leaf_corners
    w = gfeat.corner_weights(points_m, vox, static.leaf, static.levels)
    f = gfeat.interpolate(state.feature_table, rows, w)
    return jax.vmap(mlp, in_axes=(None, 0))(state.decoder, f), valid


@functools.partial(jax.jit, static_argnums=0)
def query_jit(static: N3Static, state: N3State, points_m):
    return query(static, state, points_m)


@functools.partial(jax.jit, static_argnums=0)
def query_grad_jit(static: N3Static, state: N3State, points_m):
    """(sdf [N], d sdf / d x [N, 3]) at map-frame points [N, 3]."""
    return sdf_and_grad(lambda p: query(static, state, p)[0], points_m)


# ---------------------------------------------------------------------------------------------
# growth (host side, outside jit)
# ---------------------------------------------------------------------------------------------


def grow_for(static: N3Static, state: N3State, stats: FrameStats, seed: int, feature_std: float,
             headroom: dict) -> N3State:
    """Grow (doubling) whatever `stats` says is full or will be within a frame or two.

    headroom: host-side maxima seen so far ({"voxels", "feature_rows", "blocks"} per pass), so that
    growth happens between frames, not as a failed pass. Returns the state unchanged when nothing
    needs to grow. Every growth is logged; it changes array shapes, so the next `step` compiles.
    """
    caps = Capacities.of(state)
    voxels, rows = int(stats.voxels), int(stats.feature_rows)
    v_need = voxels + 2 * max(headroom.get("voxels", 0), static.new_voxels_per_pass // 4)
    c_need = rows + 2 * max(headroom.get("feature_rows", 0), static.new_voxels_per_pass // 2)
    v_rows, r_rows = caps.voxel_rows, caps.feature_rows
    while v_need > v_rows or (bool(stats.voxel_overflow) and v_rows == caps.voxel_rows):
        v_rows *= 2
    while c_need > r_rows or (bool(stats.corner_overflow) and r_rows == caps.feature_rows):
        r_rows *= 2
    v_slots = max(caps.voxel_slots, pow2(v_rows / static.max_load))
    c_slots = max(caps.corner_slots, pow2(r_rows / static.max_load))
    if static.uses_pool:
        need = int(stats.blocks_needed) + 2 * max(int(stats.blocks_needed) - int(stats.store_pairs), 0)
        cap = caps.pool_pairs
        while need > cap:
            cap *= 2
        if cap != caps.pool_pairs:
            log.info("growing the pair pool %d -> %d pairs", caps.pool_pairs, cap)
            state = state.replace(pool=pool.grow(state.pool, cap))
        return state
    blocks = caps.store_blocks
    used = caps.store_blocks - int(stats.blocks_free) + int(stats.blocks_needed)
    b_need = used + headroom.get("blocks", 0)
    while b_need > blocks or (bool(stats.store_overflow) and blocks == caps.store_blocks):
        blocks *= 2
    if v_rows != caps.voxel_rows:
        log.info("growing the voxel table %d -> %d voxels (%d in use)", caps.voxel_rows, v_rows, voxels)
        state = state.replace(
            voxels=hashing.grow(state.voxels, v_slots) if v_slots != caps.voxel_slots else state.voxels,
            voxel_coord=_pad_rows(state.voxel_coord, v_rows, 0),
            voxel_corner_rows=_pad_rows(state.voxel_corner_rows, v_rows, -1),
            store=window.grow(state.store, n_voxel_rows=v_rows),
        )
    if r_rows != caps.feature_rows:
        log.info("growing the feature table %d -> %d rows (%d in use)", caps.feature_rows, r_rows, rows)
        extra = _init_features(seed, caps.feature_rows, r_rows - caps.feature_rows, static.feature_dim, feature_std)
        o = state.feature_opt
        state = state.replace(
            corners=hashing.grow(state.corners, c_slots) if c_slots != caps.corner_slots else state.corners,
            feature_table=jnp.concatenate([state.feature_table, extra]),
            feature_opt=o._replace(count=_pad_rows(o.count, r_rows, 0), moments=_pad_rows(o.moments, r_rows, 0.0)),
        )
    if blocks != caps.store_blocks:
        log.info("growing the pair store %d -> %d blocks", caps.store_blocks, blocks)
        state = state.replace(store=window.grow(state.store, n_slots=blocks))
    return state


def _pad_rows(x: jax.Array, n: int, fill) -> jax.Array:
    if x.shape[0] >= n:
        return x
    return jnp.concatenate([x, jnp.full((n - x.shape[0],) + x.shape[1:], fill, x.dtype)])


frames_held_jit = jax.jit(window.frames_held_fraction, static_argnums=3)


def store_bytes(store) -> int:
    """Bytes of the arrays of a pair store or pool (the training pairs' memory)."""
    return int(sum(np.prod(x.shape) * x.dtype.itemsize for x in jax.tree_util.tree_leaves(store)))


# ---------------------------------------------------------------------------------------------
# one frame on the host: compile once per shape, retry passes, plan growth
# ---------------------------------------------------------------------------------------------

# (static, capacities, scan bucket, preprocessed rows) -> compiled `step` / `step_raw`, least recently
# used first. Bounded: an XLA:CPU frame program keeps its machine code in ~2,000 memory maps, a Linux
# process may hold 65,530 (vm.max_map_count), and a process that maps many times (a notebook, the test
# suite) aborted inside XLA once an unbounded cache had kept every program it ever compiled. Capacities
# only grow during a drive, so a drive never returns to an evicted key.
_EXECUTABLES: collections.OrderedDict = collections.OrderedDict()
EXECUTABLES_KEPT = 4
COMPILE_SECONDS: list = []  # seconds of every compile of `step` in this process (benchmarks read it)


def compiled_step(static: N3Static, state: N3State, batch, rows: int = 0):
    """The compiled `step` (a ScanBatch) or `step_raw` (a RawScan, `rows` preprocessed rows) for these
    shapes, compiled (and logged) on first use. Compiling ahead of time, instead of on the first
    call, lets the log say what the wait is before it starts. Returns fn(state, batch)."""
    raw = isinstance(batch, RawScan)
    key = (static, Capacities.of(state), batch.points.shape[0], rows if raw else 0)
    fn = _EXECUTABLES.get(key)
    if fn is not None:
        _EXECUTABLES.move_to_end(key)
    else:
        from jaxmap import compile_cache

        est = compile_cache.estimate("n3_step")
        log.info("compiling the mapper (one time for these table sizes%s)",
                 f", up to about {est:.0f} s" if est else ", usually 5-30 s the first time on a machine")
        t0 = time.perf_counter()
        fn = (step_raw.lower(static, state, batch, rows) if raw else step.lower(static, state, batch)).compile()
        secs = time.perf_counter() - t0
        hostmem.trim()  # the compiler's ~1 GB of freed heap back to the system, not held for the drive
        compile_cache.record("n3_step", secs)
        COMPILE_SECONDS.append(secs)
        log.info("compiled in %.1f s", secs)
        _EXECUTABLES[key] = fn
        while len(_EXECUTABLES) > EXECUTABLES_KEPT:
            _EXECUTABLES.popitem(last=False)
    return fn


def forget_compiled() -> None:
    """Drop the compiled frame programs this process keeps (their memory maps go with them)."""
    _EXECUTABLES.clear()


def run_frame(static: N3Static, state: N3State, batch: ScanBatch, headroom: dict, *, seed: int,
              feature_std: float):
    """Integrate and train one frame, growing capacities as its stats ask (host side).

    Returns (state, FrameStats, TrainStats, passes) as numpy values; `headroom` (the largest
    per-pass allocations seen) is updated in place and used to grow before a table is full. A
    RawScan is preprocessed into `headroom["scan_rows"]` rows, grown when its points do not fit.
    """
    from jaxmap.n3.scan import bucket_for

    passes = 0
    while True:
        rows = headroom.get("scan_rows", 0)
        state, fs, ts = compiled_step(static, state, batch, rows)(state, batch)
        fs, ts = jax.device_get((fs, ts))  # the one host sync of a pass
        passes += 1
        if bool(fs.scan_overflow):
            headroom["scan_rows"] = bucket_for(int(fs.scan_points))
            log.info("growing the preprocessed scan %d -> %d rows", rows, headroom["scan_rows"])
            continue
        if int(fs.voxels) > 2 * int(fs.new_voxels):  # not the first frames, where everything is new
            headroom["voxels"] = max(headroom.get("voxels", 0), int(fs.new_voxels))
            headroom["feature_rows"] = max(headroom.get("feature_rows", 0), int(fs.new_feature_rows))
            headroom["blocks"] = max(headroom.get("blocks", 0), int(fs.blocks_needed))
        state = grow_for(static, state, fs, seed, feature_std, headroom)
        if bool(fs.ok):
            return state, fs, ts, passes
        if passes > 64:
            raise RuntimeError(f"frame did not fit after {passes} passes ({fs}); please report this bug")
