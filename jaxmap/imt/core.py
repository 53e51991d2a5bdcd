"""The transformable latent map as pure functions over one state pytree (the N3 core's pattern).

    static = ImtStatic.from_config(cfg)             # frozen, hashable: grid and encode settings
    state = init(static, capacity, channels)        # an empty map (world frame)
    store = KeyframeStore()                         # immutable: `add` / `with_poses` return new stores
    state, store, stats = integrate(static, state, store, prior, cells, pose, frame, hints)
    state, store, changed = remap(static, state, store, prior, new_poses, opts, hints)

A frame is ONE compiled program, `step`: the frame's pooled cells are encoded (`latent_map.encode_pairs`,
per (voxel, keyframe slot) sums in a scratch hash table), turned into signed means, inserted into the
map's hash table and scattered into its sums (eq. 11), with the state donated (updated in place). It
returns one small `StepStats` that the host reads once (`jax.device_get`). Capacities are fixed inside
jit and nothing is dropped: when the scratch table or the map's table is full, the step changes
nothing (the insert reverts itself, the scatter is masked) and says so; the host grows what is full
(`hints` for the scratch table, `grow` for the map, both outside jit) and runs the same batch again,
with the same result as if the capacity had been there from the start.

Frames: the map is in the world frame; the keyframe store keeps every keyframe's pooled cells in its
*sensor* frame (`remap.KeyframeStore`), and every encode, the first fusion as much as a removal or a
re-fusion by `remap`, takes its world-frame cells from one function, `KeyframeStore.cells_at` (float64
on the host), so a removal subtracts exactly what was fused: `remove(fuse(M, L), L) == M` up to the
rounding of the sums.

`ImtState.active` counts the voxels with weight > 0; every step updates it from the rows it touched,
so the host never copies the weight vector to count them.

Compiled shapes: one `step` per (map capacity, padded cell count `latent_map.bucket`, slots, scratch
capacity). The encoder is now compiled with each map capacity (3.2 s a program on a 2-core CPU, 1.7 s
for the encode alone), so a cold first run compiles more than separate encode / fuse programs did
(40-frame small room: +10 s); the persistent compile cache (`jaxmap.compile_cache`) keeps them.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.grid import hashing
from jaxmap.imt import latent_map as lm
from jaxmap.imt.remap import GROUP_CELLS, GROUP_SLOTS, KeyframeStore, RemapOptions, moved_keyframes

log = logging.getLogger("jaxmap")

FRAME_SLOTS = 8          # keyframe slots of a frame's batch (one used): the padded slot count of an encode
REMAP_MIN_CELLS = 4096   # smallest padded cell count of a remap group


@dataclasses.dataclass(frozen=True)
class ImtStatic:
    """What fixes the compiled programs besides array shapes (hashable; a jit static argument)."""

    voxel_size: float          # metres
    min_points: int            # voxels fed by fewer points of a keyframe are dropped
    cells_per_voxel: int       # pooling of a frame's points before encoding (0 = every point)

    @classmethod
    def from_config(cls, cfg) -> "ImtStatic":
        c = cfg.map
        return cls(float(c.voxel_size_m), int(c.min_points), int(c.cells_per_voxel))


@flax.struct.dataclass
class ImtState:
    map: lm.LatentMap        # the global map (world frame, latent sums, no Jacobians)
    active: jax.Array        # [] int32 voxels with weight > 0


class CellBatch(NamedTuple):
    """Pooled cells of one or more keyframes, world frame, padded (host numpy)."""

    cells: np.ndarray        # [N, 3] float32 centroids
    normals: np.ndarray      # [N, 3] float32 unit mean normals
    counts: np.ndarray       # [N] float32 points behind each cell (0 = padding)
    slot: np.ndarray         # [N] int32 keyframe slot of each cell
    signs: np.ndarray        # [S] float32 +1 (fuse) / -1 (remove) per slot


class StepStats(NamedTuple):
    """What the host reads once per step."""

    ok: jax.Array              # [] bool: the batch is in the map; False: grow what is flagged, run it again
    encode_overflow: jax.Array  # [] bool: the scratch table of the encode was full (double `hints`)
    map_overflow: jax.Array    # [] bool: the map's table was full (`grow`)
    new_voxels: jax.Array      # [] int32 distinct voxels the map lacked (counted when map_overflow)
    map_rows: jax.Array        # [] int32 rows of the map's table in use
    active: jax.Array          # [] int32 voxels with weight > 0 after the step
    local_voxels: jax.Array    # [] int32 (voxel, slot) records with weight != 0 in the batch


def init(static: ImtStatic, capacity: int, channels: int) -> ImtState:
    """An empty map with a `capacity`-slot table (a power of two, >= 1024)."""
    cap = 1 << max(10, int(np.ceil(np.log2(max(capacity, 2)))))
    return ImtState(lm.empty(static.voxel_size, cap, channels), jnp.zeros((), jnp.int32))


@jax.jit
def count_active(m: lm.LatentMap) -> jax.Array:
    """[] int32 voxels of `m` with weight > 0 (on the device; for a map built outside `step`)."""
    return jnp.sum(m.weight > 0, dtype=jnp.int32)


def state_of(m: lm.LatentMap) -> ImtState:
    """The state of a map built elsewhere (a checkpoint, `latent_map.fuse`)."""
    return ImtState(m, count_active(m))


def _distinct_missing(table: hashing.HashTable, keys: jax.Array, valid: jax.Array) -> jax.Array:
    """[] int32 distinct valid keys not in `table` (a sort; run only when the insert overflowed)."""
    missing = valid & (hashing.lookup(table, keys) < 0)
    k = jnp.where(missing[:, None], keys, hashing.EMPTY)
    order = jnp.lexsort((k[:, 3], k[:, 2], k[:, 1], k[:, 0]))
    ks, ms = k[order], missing[order]
    first = jnp.concatenate([jnp.ones((1,), bool), jnp.any(ks[1:] != ks[:-1], axis=-1)])
    return jnp.sum(ms & first, dtype=jnp.int32)


def _active_delta(before: jax.Array, after: jax.Array, rows: jax.Array, r_cap: int) -> jax.Array:
    """Change of the active count over the distinct rows of a scatter ([P] rows, r_cap = skipped)."""
    p = rows.shape[0]
    idx = jnp.arange(p, dtype=jnp.int32)
    first = jnp.full((r_cap + 1,), p, jnp.int32).at[rows].min(idx)[rows] == idx   # one entry per row
    first &= rows < r_cap
    r = jnp.minimum(rows, r_cap - 1)
    return jnp.sum(first & (after[r] > 0), dtype=jnp.int32) - jnp.sum(first & (before[r] > 0), dtype=jnp.int32)


@functools.partial(jax.jit, static_argnums=(0, 4), donate_argnums=1)
def step(static: ImtStatic, state: ImtState, prior, batch: CellBatch, encode_capacity: int):
    """Encode + fuse of one batch of cells, one compiled program, the state donated.

    Returns (state, StepStats); when `stats.ok` is False the state is unchanged: grow and call again."""
    m = state.map
    coords, lat_sum, _, w, levels, _, enc_over = lm.encode_pairs(
        prior, batch.cells, batch.normals, batch.counts, batch.slot, jnp.float32(static.min_points),
        static.voxel_size, encode_capacity, False)
    b = lm.signed_batch(coords, lat_sum, w, levels, batch.signs)
    keys = lm.voxel_keys(b.coords)
    live = b.valid & (b.weight != 0) & ~enc_over
    limit = max(1, int(lm.MAX_LOAD * m.table.capacity))
    table, rows, map_over = hashing.insert(m.table, keys, live, row_capacity=limit)
    new = jax.lax.cond(map_over, _distinct_missing, lambda *a: jnp.zeros((), jnp.int32), m.table, keys, live)
    ok = ~enc_over & ~map_over
    rows = jnp.where(ok, rows, -1)
    out = lm.scatter(lm.LatentMap(table, m.coords, m.latent_sum, m.weight, m.jac_sum, m.voxel_size), rows, b, 1.0)
    r = jnp.where(b.valid & (rows >= 0) & (b.weight != 0), rows, m.rows)
    active = state.active + _active_delta(m.weight, out.weight, r, m.rows)
    stats = StepStats(ok, enc_over, map_over, new, table.count, active, jnp.sum(live, dtype=jnp.int32))
    return ImtState(out, active), stats


def grow(state: ImtState, capacity: int) -> ImtState:
    """The state with its map's table rehashed into `capacity` slots and its rows padded (outside jit)."""
    return ImtState(lm.pad_rows(state.map, hashing.grow(state.map.table, capacity)), state.active)


def _grown_capacity(capacity: int, rows: int, new: int) -> int:
    """The smallest doubling (at least one) of `capacity` that holds rows + new under MAX_LOAD (as
    `hashing.insert_grow`)."""
    out = capacity * 2
    while rows + new > lm.MAX_LOAD * out:
        out *= 2
    if out > hashing.MAX_CAPACITY:
        raise hashing.CapacityError(f"the latent map needs more than {hashing.MAX_CAPACITY} slots")
    return out


def run(static: ImtStatic, state: ImtState, prior, batch: CellBatch, hints: dict, log_growth: bool = True):
    """`step` until the batch is in, growing the scratch table (`hints`) or the map as its stats ask.
    Returns (state, StepStats as numpy)."""
    n_pad = len(batch.counts)
    while True:
        cap = lm.encode_capacity(n_pad, hints)
        state, stats = step(static, state, prior, batch, cap)
        stats = jax.device_get(stats)  # the one host read of a step
        if stats.ok:
            hints[n_pad] = cap
            return state, stats
        if stats.encode_overflow:
            if 2 * cap > hashing.MAX_CAPACITY:
                raise hashing.CapacityError(f"encode: more than {hashing.MAX_CAPACITY // 2} voxels in one batch")
            hints[n_pad] = 2 * cap
            continue
        old = state.map.table.capacity
        new_cap = _grown_capacity(old, int(stats.map_rows), int(stats.new_voxels))
        if log_growth:
            log.info("latent map: growing %d -> %d slots (%d voxels + %d new)", old, new_cap, int(stats.map_rows),
                     int(stats.new_voxels))
        state = grow(state, new_cap)


def cell_batch(store: KeyframeStore, ids, poses, signs, n_pad: int, slots: int) -> CellBatch:
    """The world-frame cells of keyframes `ids` at `poses` (`KeyframeStore.cells_at`), padded to `n_pad`
    cells and `slots` slots, with their signs."""
    pts, nrm, cnt, slot = store.cells_at(ids, poses)
    if n_pad < len(pts) or slots < len(ids):
        raise ValueError(f"{len(pts)} cells / {len(ids)} keyframes do not fit {n_pad} / {slots}")
    sg = np.ones(slots, np.float32)
    sg[:len(ids)] = signs
    return CellBatch(lm.pad(pts, n_pad, np.float32), lm.pad(nrm, n_pad, np.float32), lm.pad(cnt, n_pad, np.float32),
                     lm.pad(slot, n_pad, np.int32), sg)


def integrate(static: ImtStatic, state: ImtState, store: KeyframeStore, prior, cells, pose, frame: int,
              hints: dict):
    """Keep a frame's pooled cells as a keyframe and fuse them, in one `step`.

    cells: `(centroids [M, 3], normals [M, 3], counts [M])` pooled on the world grid at `pose`
    (`latent_map.pool_cells`); pose: [4, 4] T_world_sensor. The keyframe's cells are stored in its sensor
    frame and the step encodes them as `store.cells_at` gives them back, as `remap` will.
    Returns (state, store with the keyframe appended, StepStats)."""
    store = store.add(frame, *cells, pose)
    k = len(store) - 1
    batch = cell_batch(store, [k], store.poses()[k:], [1.0], lm.bucket(len(cells[0])), FRAME_SLOTS)
    state, stats = run(static, state, prior, batch, hints)
    return state, store, stats


def _groups(sizes: list[int]):
    """Consecutive groups of keyframes of at most GROUP_CELLS cells and GROUP_SLOTS keyframes."""
    start = 0
    while start < len(sizes):
        stop, total = start + 1, sizes[start]
        while stop < len(sizes) and stop - start < GROUP_SLOTS and total + sizes[stop] <= GROUP_CELLS:
            total += sizes[stop]
            stop += 1
        yield slice(start, stop)
        start = stop


def apply_keyframes(static: ImtStatic, state: ImtState, store: KeyframeStore, prior, ids, poses, signs,
                    hints: dict) -> ImtState:
    """Fuse (sign +1) or remove (-1) the contributions of keyframes `ids` at `poses`, one `step` per group
    (a keyframe's removal and re-fusion stay in one group when they are adjacent)."""
    for sl in _groups([len(store.counts[k]) for k in ids]):
        n = sum(len(store.counts[k]) for k in ids[sl])
        batch = cell_batch(store, ids[sl], poses[sl], signs[sl], lm.bucket(n, REMAP_MIN_CELLS), GROUP_SLOTS)
        state, _ = run(static, state, prior, batch, hints, log_growth=False)
    return state


def remap(static: ImtStatic, state: ImtState, store: KeyframeStore, prior, new_poses,
          opts: RemapOptions = RemapOptions(), hints: dict | None = None):
    """Move every keyframe whose pose changed to its new pose ([K, 4, 4] T_world_sensor, K = len(store)).

    The moved keyframes' contributions at their fused poses are removed (-w) and added at the new poses
    (+w) in the same steps; when more than `opts.rebuild_fraction` of them moved, the map is rebuilt
    from every keyframe. Returns (state, new store whose `pose_fused` are the new poses, moved ids); the
    given store is left as it was."""
    hints = {} if hints is None else hints
    new_poses = np.asarray(new_poses, np.float64)
    if new_poses.shape != (len(store), 4, 4):
        raise ValueError(f"remap: expected {len(store)} poses [K,4,4], got shape {new_poses.shape}")
    changed = moved_keyframes(store, new_poses, opts)
    if not changed:
        return state, store, []
    rebuild = len(changed) > opts.rebuild_fraction * len(store)
    if rebuild:
        ids = list(range(len(store)))
        state = init(static, state.map.table.capacity, state.map.channels)
        state = apply_keyframes(static, state, store, prior, ids, new_poses, np.ones(len(ids), np.float32), hints)
    else:
        # removal and fusion of a keyframe side by side: its -w and +w land in one scatter
        ids = [k for k in changed for _ in (0, 1)]
        poses = np.stack([P for k in changed for P in (store.poses()[k], new_poses[k])])
        signs = np.tile(np.array([-1.0, 1.0], np.float32), len(changed))
        state = apply_keyframes(static, state, store, prior, ids, poses, signs, hints)
    log.info("remap: %d of %d keyframes moved%s", len(changed), len(store),
             " (rebuilt from every keyframe)" if rebuild else "")
    return state, store.with_poses(changed, new_poses[changed]), changed
