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
*sensor* frame (`keyframe_store.KeyframeStore`), and every encode, the first fusion as much as a removal or a
re-fusion by `remap`, takes its world-frame cells from one function, `KeyframeStore.cells_at` (float64
on the host), so a removal subtracts exactly what was fused: `remove(fuse(M, L), L) == M` up to the
rounding of the sums.

`ImtState.active` counts the voxels with weight > 0; every step updates it from the rows it touched,
so the host never copies the weight vector to count them.

Remap methods (`ImtStatic.remap`, `map.remap`): "reencode" keeps each keyframe's pooled cells
(`KeyframeStore`) and a remap re-encodes a moved keyframe at its old pose (-w) and its new pose (+w)
with the frame program itself, padded to shapes the frames compiled (`apply_keyframes`); "transform"
keeps each keyframe's latent local map with Jacobians (`LatentStore`, float16; the step encodes with
Jacobians and fuses the rounded latents) and a remap moves the stored maps: `move_step`, one program
of MOVE_ROWS stored voxels splatted by their keyframe's motion (`move_keyframes`). Either way the
batches of a remap are dispatched without waiting and their stats read once (`_dispatch_all`).

Compiled shapes: one `step` per (map capacity, padded cell count `latent_map.bucket`, slots, scratch
capacity). The encoder is now compiled with each map capacity (3.2 s a program on a 2-core CPU, 1.7 s
for the encode alone), so a cold first run compiles more than separate encode / fuse programs did
(40-frame small room: +10 s); the persistent compile cache (`jaxmap.compile_cache`) keeps them. A
remap builds no program of its own: the frames leave `step` compiled at the map's capacity and pad,
the encode runs only the chunks that hold cells (so a keyframe costs its own cells, not the largest
frame's pad), an empty map is filled on the host, and in "transform" mode each frame at a new capacity
runs `move_step` once on padding. Only a remap that outgrows the map (the transform's splats spread a
stored voxel over 8) compiles the grown capacity's programs.
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
from jaxmap.imt.latent_store import COMPACT, LatentStore, RowBatch
from jaxmap.imt.keyframe_store import KeyframeStore, RemapOptions, moved_keyframes
from jaxmap.imt.interpolation import splat_trilinear

log = logging.getLogger("jaxmap")

FRAME_SLOTS = 8          # keyframe slots of a frame's batch (one used): the padded slot count of an encode
MOVE_ROWS = 8192         # stored voxels per `move_step` call (8 splats each; one compiled shape)


@dataclasses.dataclass(frozen=True)
class ImtStatic:
    """What fixes the compiled programs besides array shapes (hashable; a jit static argument)."""

    voxel_size: float          # metres
    min_points: int            # voxels fed by fewer points of a keyframe are dropped
    cells_per_voxel: int       # pooling of a frame's points before encoding (0 = every point)
    remap: str = "reencode"    # "reencode" (keyframes keep pooled cells) | "transform" (latent local maps)
    jacobian_sign: float = -1.0  # transform: the first-order term (see `interpolation.py`)
    splat_power: float = 2.0     # transform: sharpened trilinear splats

    @classmethod
    def from_config(cls, cfg) -> "ImtStatic":
        c = cfg.map
        return cls(float(c.voxel_size_m), int(c.min_points), int(c.cells_per_voxel), str(c.remap),
                   float(c.jacobian_sign), float(c.splat_power))

    def new_store(self):
        """An empty keyframe store of the kind `remap` needs."""
        return LatentStore() if self.remap == "transform" else KeyframeStore()


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
    return ImtState(lm.empty(static.voxel_size, cap, channels), jax.device_put(np.int32(0)))


@jax.jit
def count_active(m: lm.LatentMap) -> jax.Array:
    """[] int32 voxels of `m` with weight > 0 (on the device; for a map built outside `step`)."""
    return jnp.sum(m.weight > 0, dtype=jnp.int32)


def state_of(m: lm.LatentMap) -> ImtState:
    """The state of a map built elsewhere (a checkpoint, `local_maps`)."""
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


def _fuse(state: ImtState, b: lm.VoxelBatch, blocked: jax.Array):
    """Insert the voxels of `b` into the map's table and scatter its (signed) sums, unless `blocked` or the
    table is full; then nothing changes (the insert reverts itself, the scatter is masked)."""
    m = state.map
    keys = lm.voxel_keys(b.coords)
    live = b.valid & (b.weight != 0) & ~blocked
    limit = max(1, int(lm.MAX_LOAD * m.table.capacity))
    table, rows, map_over = hashing.insert(m.table, keys, live, row_capacity=limit)
    new = jax.lax.cond(map_over, _distinct_missing, lambda *a: jnp.zeros((), jnp.int32), m.table, keys, live)
    ok = ~blocked & ~map_over
    rows = jnp.where(ok, rows, -1)
    out = lm.scatter(lm.LatentMap(table, m.coords, m.latent_sum, m.weight, m.jac_sum, m.voxel_size), rows, b, 1.0)
    r = jnp.where(b.valid & (rows >= 0) & (b.weight != 0), rows, m.rows)
    active = state.active + _active_delta(m.weight, out.weight, r, m.rows)
    stats = StepStats(ok, blocked, map_over, new, table.count, active, jnp.sum(live, dtype=jnp.int32))
    return ImtState(out, active), stats


@functools.partial(jax.jit, static_argnums=(0, 4), donate_argnums=1)
def step(static: ImtStatic, state: ImtState, prior, batch: CellBatch, encode_capacity: int):
    """Encode + fuse of one batch of cells, one compiled program, the state donated.

    With `static.remap == "transform"` the encode also gives each voxel's translation Jacobian, and the
    latents are rounded to the store's float16 before they are fused, so that the store holds exactly
    what the map holds. A map that keeps Jacobians (a local map of `local_maps.encode_cells`) gets their
    sums too (a program of its own: the map's pytree differs). Returns (state, StepStats, local): local = (coords [R, 3], latent [R, C, 3] f16,
    jac [R, C, 3, 3] f16, weight [R]) of the batch's voxels (weight 0 = unused row) in that mode, else None.
    When `stats.ok` is False the state is unchanged: grow and call again."""
    latent = static.remap == "transform"
    with_jacobian = latent or state.map.jac_sum is not None   # a local map that keeps them (`local_maps`)
    coords, lat_sum, jac_sum, w, levels, _, enc_over = lm.encode_pairs(
        prior, batch.cells, batch.normals, batch.counts, batch.slot, jnp.float32(static.min_points),
        static.voxel_size, encode_capacity, with_jacobian)
    local = None
    if latent:
        lat16, jac16 = lm.mean_of(lat_sum, w).astype(COMPACT), lm.mean_of(jac_sum, w).astype(COMPACT)
        sw = w * batch.signs[jnp.maximum(levels, 0)]
        b = lm.VoxelBatch(coords, lat16.astype(jnp.float32), None, sw, sw != 0)
        local = (coords, lat16, jac16, w)
    else:
        b = lm.signed_batch(coords, lat_sum, w, levels, batch.signs, jac_sum)
    state, stats = _fuse(state, b, enc_over)
    return state, stats, local


@functools.partial(jax.jit, donate_argnums=0)
def fuse_step(state: ImtState, b: lm.VoxelBatch):
    """The step's fusion alone (eq. 11), for voxel records already encoded: a local map's rows or a batch
    (`local_maps.fuse` / `remove`; negative weights remove). One compiled program per batch size, the
    state donated; the batch's Jacobians are fused when the map keeps them. Returns (state, StepStats,
    None); when `stats.ok` is False the state is unchanged: grow and call again (`fuse_batch`)."""
    state, stats = _fuse(state, b, jnp.zeros((), bool))
    return state, stats, None


@functools.partial(jax.jit, static_argnums=0, donate_argnums=1)
def move_step(static: ImtStatic, state: ImtState, rows: RowBatch):
    """Fuse (sign +1) or remove (-1) stored local-map voxels placed by their keyframes' motions: the
    trilinear splats of `transform.splat_trilinear` (exact entries go in as stored), one compiled
    program, the state donated. Returns (state, StepStats, None)."""
    b = lm.VoxelBatch(rows.coords, rows.latent.astype(jnp.float32), rows.jac.astype(jnp.float32), rows.weight,
                      rows.weight > 0)
    s = splat_trilinear(b, rows.motion, static.voxel_size, static.jacobian_sign, static.splat_power, False,
                        rows.exact)
    sw = s.weight * jnp.repeat(rows.sign, 8)
    s = lm.VoxelBatch(s.coords, s.latent, None, sw, s.valid & (sw != 0))
    state, stats = _fuse(state, s, jnp.zeros((), bool))
    return state, stats, None


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


def _until_in(call, state: ImtState, more_scratch, log_growth: bool):
    """`call(state)` (a step) until its batch is in: the scratch table grows through `more_scratch()`, the
    map through `grow`. Returns (state, StepStats as numpy, local as numpy)."""
    while True:
        state, stats, local = call(state)
        stats, local = jax.device_get((stats, local))  # the one host read of a step
        if stats.ok:
            return state, stats, local
        if stats.encode_overflow:
            more_scratch()
            continue
        old = state.map.table.capacity
        new_cap = _grown_capacity(old, int(stats.map_rows), int(stats.new_voxels))
        if log_growth:
            log.info("latent map: growing %d -> %d slots (%d voxels + %d new)", old, new_cap, int(stats.map_rows),
                     int(stats.new_voxels))
        state = grow(state, new_cap)


def _encode_call(static: ImtStatic, prior, batch: CellBatch, hints: dict):
    """(call, more_scratch) for `_until_in`: `step` with the scratch size `hints` holds for the batch's
    padded cell count (recorded with the map's capacity: the shapes `apply_keyframes` reuses)."""
    n_pad = len(batch.counts)

    def call(s):
        hints[n_pad] = lm.encode_capacity(n_pad, hints)
        hints[("compiled", s.map.table.capacity, n_pad)] = True
        return step(static, s, prior, batch, hints[n_pad])

    def more_scratch():
        if 2 * hints[n_pad] > hashing.MAX_CAPACITY:
            raise hashing.CapacityError(f"encode: more than {hashing.MAX_CAPACITY // 2} voxels in one batch")
        hints[n_pad] *= 2

    return call, more_scratch


def run(static: ImtStatic, state: ImtState, prior, batch: CellBatch, hints: dict, log_growth: bool = True):
    """`step` until the batch is in, growing the scratch table (`hints`) or the map as its stats ask.
    Returns (state, StepStats as numpy, local as numpy or None)."""
    call, more_scratch = _encode_call(static, prior, batch, hints)
    return _until_in(call, state, more_scratch, log_growth)


def _dispatch_all(state: ImtState, items) -> ImtState:
    """Run the calls of `items` ((call, retry) pairs: `call(state)` is a step, `retry(state, stats)` puts
    its batch in after it did not go in) one after the other without waiting for their results, read all
    their stats once, and retry those whose batch did not go in, one by one. The map stores sums, so the
    order does not matter; and the host prepares the next batch while the last one runs."""
    pending = []
    for call, retry in items:
        state, stats, _ = call(state)
        pending.append((retry, stats))
    for (retry, _), stats in zip(pending, jax.device_get([p[1] for p in pending])):
        if not stats.ok:
            state = retry(state, stats)
    return state


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


def frame_pad(n: int, hints: dict) -> int:
    """Padded cell count of a frame of n cells: `latent_map.bucket`, but never below the largest one so far
    (kept in `hints`). Frames then compile one shape per map capacity instead of one per bucket, and the
    last capacity's shape holds every keyframe, so a remap (`apply_keyframes`) compiles nothing."""
    hints["frame_pad"] = max(lm.bucket(n), hints.get("frame_pad", 0))
    return hints["frame_pad"]


def integrate(static: ImtStatic, state: ImtState, store, prior, cells, pose, frame: int, hints: dict):
    """Keep a frame as a keyframe and fuse it, in one `step`.

    cells: `(centroids [M, 3], normals [M, 3], counts [M])` pooled on the world grid at `pose`
    (`latent_map.pool_cells`); pose: [4, 4] T_world_sensor. `KeyframeStore` (remap: reencode): the cells
    are stored in the keyframe's sensor frame and the step encodes them as `store.cells_at` gives them
    back, as `remap` will. `LatentStore` (remap: transform): the step's local map is stored.
    Returns (state, store with the keyframe appended, StepStats)."""
    n_pad = frame_pad(len(cells[2]), hints)
    if static.remap == "transform":
        pts, nrm, cnt = cells
        sg = np.ones(FRAME_SLOTS, np.float32)
        batch = CellBatch(lm.pad(pts, n_pad, np.float32), lm.pad(nrm, n_pad, np.float32),
                          lm.pad(cnt, n_pad, np.float32), np.zeros(n_pad, np.int32), sg)
        state, stats, local = run(static, state, prior, batch, hints)
        return _move_step_ready(static, state, hints), store.add(frame, *local, pose), stats
    store = store.add(frame, *cells, pose)
    k = len(store) - 1
    batch = cell_batch(store, [k], store.poses()[k:], [1.0], n_pad, FRAME_SLOTS)
    state, stats, _ = run(static, state, prior, batch, hints)
    return state, store, stats


def _move_step_ready(static: ImtStatic, state: ImtState, hints: dict) -> ImtState:
    """The state after `move_step` ran once on padding (nothing moves) at a map capacity it has not run at
    yet (recorded in `hints`): a remap of the map (`move_keyframes`) then compiles nothing, as the frames
    leave `step` compiled for `apply_keyframes`."""
    key = ("move_step", state.map.table.capacity)
    if key not in hints:
        hints[key] = True
        empty = [((3,), np.int32), ((state.map.channels, 3), COMPACT), ((state.map.channels, 3, 3), COMPACT),
                 ((), np.float32), ((), np.float32), ((3, 4), np.float32), ((), bool)]
        rows = RowBatch(*(lm.pad(np.zeros((0,) + shape, dt), MOVE_ROWS, dt) for shape, dt in empty))
        state, _, _ = move_step(static, state, rows)
    return state


def _groups(sizes: list[int], max_cells: int, max_slots: int):
    """Consecutive groups of keyframes of at most `max_cells` cells and `max_slots` keyframes."""
    start = 0
    while start < len(sizes):
        stop, total = start + 1, sizes[start]
        while stop < len(sizes) and stop - start < max_slots and total + sizes[stop] <= max_cells:
            total += sizes[stop]
            stop += 1
        yield slice(start, stop)
        start = stop


def apply_keyframes(static: ImtStatic, state: ImtState, store: KeyframeStore, prior, ids, poses, signs,
                    hints: dict) -> ImtState:
    """Fuse (sign +1) or remove (-1) the contributions of keyframes `ids` at `poses` by re-encoding their
    cells, with FRAME_SLOTS slots and padded to the cell counts the frames were padded to at this map
    capacity (`hints` records them): the frame program, already compiled, encodes them. Consecutive
    keyframes share a batch up to the largest of those counts; a batch whose records overflow the frames'
    scratch table is run again one keyframe at a time."""
    sizes = store.sizes(ids)
    cap = state.map.table.capacity
    pads = sorted(k[2] for k in hints if isinstance(k, tuple) and k[0] == "compiled" and k[1] == cap)

    def batch(sl: slice):
        # a keyframe larger than every frame padded at this capacity (fused before the map grew) compiles one shape
        n_pad = next((p for p in pads if p >= sum(sizes[sl])), lm.bucket(sum(sizes[sl])))
        call, more_scratch = _encode_call(static, prior, cell_batch(store, ids[sl], poses[sl], signs[sl], n_pad,
                                                                    FRAME_SLOTS), hints)

        def retry(s: ImtState, stats) -> ImtState:
            if stats.encode_overflow and sl.stop - sl.start > 1:
                # several keyframes hold more (voxel, keyframe) records than one frame: each alone, as the
                # frames were encoded, rather than a bigger scratch table (a compile); later remaps group fewer
                hints["remap_group_cells"] = min(hints.get("remap_group_cells", n_pad), sum(sizes[sl]) // 2)
                return _dispatch_all(s, (batch(slice(k, k + 1)) for k in range(sl.start, sl.stop)))
            return _until_in(call, s, more_scratch, False)[0]

        return call, retry

    group_cells = min(max(pads + [0]), hints.get("remap_group_cells", hashing.MAX_CAPACITY))
    return _dispatch_all(state, (batch(sl) for sl in _groups(sizes, group_cells, FRAME_SLOTS)))


def move_keyframes(static: ImtStatic, state: ImtState, store: LatentStore, ids, poses, signs) -> ImtState:
    """Fuse (sign +1) or remove (-1) the stored local maps of keyframes `ids` placed at `poses`, in calls
    of MOVE_ROWS stored voxels (a keyframe may span two calls: its voxels are independent)."""
    def calls():
        pending, n = [], 0
        for j in range(len(ids) + 1):
            if j < len(ids):
                pending.append(store.rows(ids[j:j + 1], poses[j:j + 1], signs[j:j + 1]))
                n += len(pending[-1].weight)
            while n >= MOVE_ROWS or (j == len(ids) and n > 0):
                rows = RowBatch(*(np.concatenate(col) for col in zip(*pending)))
                part = RowBatch(*(lm.pad(x[:MOVE_ROWS], MOVE_ROWS, x.dtype) for x in rows))
                pending = [RowBatch(*(x[MOVE_ROWS:] for x in rows))]
                n = len(pending[0].weight)
                call = lambda s, part=part: move_step(static, s, part)  # noqa: E731
                yield call, lambda s, stats, call=call: _until_in(call, s, _no_scratch, False)[0]

    return _dispatch_all(state, calls())


def _no_scratch():
    raise AssertionError("move_step and fuse_step have no scratch table")


def fuse_batch(state: ImtState, b: lm.VoxelBatch, log_growth: bool = True):
    """`fuse_step` until the batch is in, the map grown as its stats ask. Returns (state, StepStats as
    numpy)."""
    state, stats, _ = _until_in(lambda s: fuse_step(s, b), state, _no_scratch, log_growth)
    return state, stats


def remap(static: ImtStatic, state: ImtState, store, prior, new_poses, opts: RemapOptions = RemapOptions(),
          hints: dict | None = None):
    """Move every keyframe whose pose changed to its new pose ([K, 4, 4] T_world_sensor, K = len(store)).

    The moved keyframes' contributions at their fused poses are removed (-w) and added at the new poses
    (+w): re-encoded from their cells (`KeyframeStore`) or moved from their stored local maps
    (`LatentStore`, `move_keyframes`). When more than `opts.rebuild_fraction` of them moved, the map is
    rebuilt from every keyframe. Returns (state, new store whose `pose_fused` are the new poses, moved
    ids); the given store is left as it was."""
    hints = {} if hints is None else hints
    new_poses = np.asarray(new_poses, np.float64)
    if new_poses.shape != (len(store), 4, 4):
        raise ValueError(f"remap: expected {len(store)} poses [K,4,4], got shape {new_poses.shape}")
    if isinstance(store, LatentStore) != (static.remap == "transform"):
        raise ValueError(f"remap: a {type(store).__name__} cannot be remapped with remap = {static.remap!r}")
    changed = moved_keyframes(store, new_poses, opts)
    if not changed:
        return state, store, []
    rebuild = len(changed) > opts.rebuild_fraction * len(store)
    if rebuild:
        ids, poses = list(range(len(store))), new_poses
        signs = np.ones(len(ids), np.float32)
        state = init(static, state.map.table.capacity, state.map.channels)
    else:
        # removal and fusion of a keyframe side by side: its -w and +w land in one scatter
        ids = [k for k in changed for _ in (0, 1)]
        fused = store.poses()
        poses = np.stack([P for k in changed for P in (fused[k], new_poses[k])])
        signs = np.tile(np.array([-1.0, 1.0], np.float32), len(changed))
    if static.remap == "transform":
        state = move_keyframes(static, state, store, ids, poses, signs)
    else:
        state = apply_keyframes(static, state, store, prior, ids, poses, signs, hints)
    log.info("remap: %d of %d keyframes moved%s", len(changed), len(store),
             " (rebuilt from every keyframe)" if rebuild else "")
    return state, store.with_poses(changed, new_poses[changed]), changed
