"""The N3 map's state: its static shape (`N3Static`), its arrays (`N3State`), their sizes
(`Capacities`), and the empty map.

    static = N3Static.from_config(cfg)                # frozen, hashable: shapes and modes
    state = init_state(static, cfg, capacities_for(static, cfg))
    state = set_origin(static, state, sensor_xyz_world) # once, before the first frame

Frames: the state lives in a *map frame* = world - origin, origin = `origin_vox * leaf` (an
integer voxel index, snapped to the coarsest level), so float32 stays precise on large scenes.
"""
from __future__ import annotations

import dataclasses
import math

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxmap.grid import hashing
from jaxmap.grid.features import init_feature_rows
from jaxmap.n3 import adam, evidence as n3evidence, pool, window
from jaxmap.preprocess import layout_of
from jaxmap.n3.decoder import init_decoder
from jaxmap.sizes import pow2, round_up


@dataclasses.dataclass(frozen=True)
class N3Static:
    """Everything that fixes the compiled programs (hashable; a jit static argument). Values that
    do not change shapes or control flow (learning rate, beta, eikonal weight, iterations a frame) are
    in `Hyper`: a config that changes only those runs the program already compiled."""

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
    #                             (preprocess.device true, or auto on a GPU: `preprocess_device.resolve`)
    evidence: bool = False      # free-space evidence per voxel (`jaxmap.n3.evidence`): evidence.enabled and
    #                             the scans' range-image layout known (`image`)
    evidence_requested: bool = False  # evidence.enabled (without a layout the frame program warns it runs without)
    evidence_margin: float = 0.1
    void_frames: int = 2
    raise_pairs: bool = True
    evidence_range: float = 40.0  # voxels farther from the sensor are not tested (metres)
    image: object = None        # the scans' range_image.Layout (evidence: the frame's range image; None: off)
    # Corner allocations per `integrate` pass (a static batch of L*8 keys each): a typical frame
    # of the city brings ~1700 new voxels (max ~6000); the first frame ~20000 takes 3 passes.
    new_voxels_per_pass: int = 8192

    @classmethod
    def from_config(cls, cfg) -> "N3Static":
        g, s, t, w, m = cfg.grid, cfg.sampling, cfg.train, cfg.window, cfg.mesh
        leaf = float(g.leaf_vox_size)
        on_device = _on_device(cfg.preprocess)
        return cls(
            leaf=leaf, levels=g.feature_levels, feature_dim=g.feature_dim, hidden_dim=cfg.decoder.hidden_dim,
            hidden_layers=cfg.decoder.hidden_layers, label_mode=s.label_mode, trunc=s.surface_sample_range_m,
            sigma=s.sigma_m, n_surface=s.surface_sample_n, n_free=s.free_sample_n, n_ray=s.free_ray_n,
            free_min_range=cfg.preprocess.min_range_m, ray_quiet=s.free_ray_quiet_frames, free_band=s.free_band_m,
            point_filter=s.free_point_filter_m,
            free_label=s.surface_sample_range_m if s.free_label_m < 0 else s.free_label_m,
            free_label_mode=s.free_label_mode, carve=w.carve, carve_margin=w.carve_margin_m,
            carve_samples=w.carve_samples, carve_rule=w.carve_rule, carve_sign=w.carve_sign,
            hierarchical=t.hierarchical, nv=t.nv, np_per_voxel=t.np_per_voxel, nt=t.nt,
            batch_size=t.batch_size, freeze_after_frame=t.freeze_after_frame, reset_adam=t.reset_adam_each_frame,
            window_mode=w.mode, keyframes=w.keyframes if w.mode == "keyframe" else 0,
            block_policy=w.block_policy, pairs_per_frame=w.pairs_per_frame,
            radius_vox=int(math.ceil(cfg.preprocess.max_range_m / leaf)), max_load=g.max_load,
            mask_level=m.mask_level, min_leaf_corners=m.min_leaf_corners,
            preprocess=on_device,
            evidence=cfg.evidence.enabled and cfg.preprocess.image_rows > 0, evidence_requested=cfg.evidence.enabled,
            evidence_margin=cfg.evidence.margin_m,
            void_frames=cfg.evidence.void_frames, raise_pairs=cfg.evidence.raise_pairs,
            evidence_range=cfg.evidence.max_range_m,
            image=layout_of(cfg.preprocess) if cfg.evidence.enabled or on_device is not None else None,
        )

    @property
    def corners_per_voxel(self) -> int:
        return self.levels * 8

    @property
    def uses_pool(self) -> bool:
        """The replay / keyframe ablations keep a flat pool of pairs instead of per-voxel blocks."""
        return self.window_mode in ("replay", "keyframe")


def _on_device(p):
    """The PreprocessConfig of a frame program that preprocesses its scans itself, else None (the host does)."""
    if p.device == "auto" or (p.device == "true" and p.normals == "knn"):  # not decided yet (`MapStart` decides)
        from jaxmap.preprocess_device import resolve

        p = resolve(p)
    return p if p.device == "true" else None


@flax.struct.dataclass
class Hyper:
    lr: jax.Array        # [] Adam learning rate (features and decoder)
    beta: jax.Array      # [] BCE sigmoid scale, metres
    weight_e: jax.Array  # [] eikonal weight
    iters: jax.Array     # [] int32 training iterations a frame (train.iters; the loop's trip count is traced)


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
    decoder_opt: optax.ScaleByAdamState    # Adam moments of the decoder (optax.adam's state, less its empty lr part)
    store: window.PairStore                # voxel-oriented training pairs and the current window
    pool: pool.PairPool | None             # flat pool of pairs (replay / keyframe ablations), else None
    evidence: n3evidence.Evidence | None   # per voxel row: frames seen free since the last hit (None: off)
    origin_vox: jax.Array                  # [3] int32: map origin in leaf voxels (world = map + origin)
    key: jax.Array                         # PRNG key, split once per frame
    frame: jax.Array                       # [] int32 frames integrated and trained so far
    hyper: Hyper


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
    blocks = max(round_up(1.5 * window_voxels), pow2(cfg.window.initial_blocks))
    voxels = round_up(4 * window_voxels + 2 * static.new_voxels_per_pass)
    rows = round_up(2.5 * voxels)
    pool_pairs = 0
    if static.uses_pool:  # the ablations: no blocks; the pool starts at ~16 frames' worth (a scan
        # brings about one point per window voxel) and doubles when full
        blocks, pool_pairs = 16, round_up(16 * window_voxels * (static.n_surface + static.n_free + static.n_ray))
    return Capacities(voxel_slots=pow2(voxels / static.max_load), voxel_rows=voxels,
                      corner_slots=pow2(rows / static.max_load), feature_rows=rows,
                      store_blocks=blocks, pairs_per_block=cfg.window.pairs_per_voxel, pool_pairs=pool_pairs)


def init_state(static: N3Static, cfg, caps: Capacities) -> N3State:
    """An empty map with the given capacities (host-side)."""
    t = cfg.train
    _, dec = init_decoder(jax.random.PRNGKey(t.seed + 1), static.feature_dim, static.hidden_dim,
                          static.hidden_layers)
    table = init_feature_rows(t.seed, 0, caps.feature_rows, static.feature_dim, cfg.grid.feature_std)
    return N3State(
        voxels=hashing.create(caps.voxel_slots),
        corners=hashing.create(caps.corner_slots),
        voxel_coord=jnp.zeros((caps.voxel_rows, 3), jnp.int32),
        voxel_corner_rows=jnp.full((caps.voxel_rows, static.corners_per_voxel), -1, jnp.int32),
        voxels_with_corners=jnp.zeros((), jnp.int32),
        feature_table=table,
        feature_opt=adam.sparse_adam(t.lr).init(table),
        decoder=dec,
        decoder_opt=optax.scale_by_adam().init(dec),
        store=window.create(caps.store_blocks, caps.pairs_per_block, caps.voxel_rows),
        pool=pool.create(caps.pool_pairs) if static.uses_pool else None,
        evidence=n3evidence.create(caps.voxel_rows) if static.evidence else None,
        origin_vox=jnp.zeros((3,), jnp.int32),
        key=jax.random.PRNGKey(t.seed),
        frame=jnp.zeros((), jnp.int32),
        hyper=Hyper(lr=jnp.float32(t.lr), beta=jnp.float32(t.sigma_sigmoid_m), weight_e=jnp.float32(t.weight_e),
                    iters=jnp.int32(t.iters)),
    )


def set_origin(static: N3Static, state: N3State, sensor_world: np.ndarray) -> N3State:
    """Map origin at the sensor position (world, metres), snapped to the coarsest voxel level."""
    return state.replace(origin_vox=jnp.asarray(origin_vox_for(static, sensor_world)))


def origin_vox_for(static: N3Static, sensor_world: np.ndarray) -> np.ndarray:
    """[3] int32: `set_origin`'s map origin in leaf voxels (world = map + origin_vox * leaf), on the host."""
    coarse = 1 << (static.levels - 1)
    k = np.round(np.asarray(sensor_world, np.float64) / (static.leaf * coarse))
    return (k * coarse).astype(np.int32)


def origin_world(static: N3Static, state: N3State) -> np.ndarray:
    """[3] float64 world position of the map frame's origin."""
    return np.asarray(jax.device_get(state.origin_vox), np.float64) * static.leaf
