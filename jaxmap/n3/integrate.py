"""Putting one scan into the N3 map: sample the frame's training pairs, allocate leaf voxels and their
corner feature rows (fixed-capacity hash tables), store the pairs in their voxels' blocks, slide the
window and let the frame's free space carve the pairs it contradicts (`window.carve`: what moved
away is erased), then count the frame's free-space evidence (`jaxmap.n3.evidence.update`). Pure functions,
traced inside the frame program (`jaxmap.n3.frame.step`).

Capacities are fixed inside jit. Nothing is dropped when one runs out: `integrate` is all or
nothing for the pair store, hash inserts revert themselves on overflow, corner allocation is a
queue worked off `new_voxels_per_pass` voxels at a time, and `FrameStats.ok` is False until the
frame is fully in; the host then grows what the stats name and runs the frame again.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp

from jaxmap.grid import features as gfeat
from jaxmap.grid import hashing
from jaxmap.grid.compaction import nonzero_from
from jaxmap.n3 import evidence as n3evidence
from jaxmap.n3 import pool, window
from jaxmap.n3.query import query, voxel_rows
from jaxmap.n3.sampling import Samples, sample_frame
from jaxmap.n3.scan_batch import ScanBatch
from jaxmap.n3.state import N3State, N3Static


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
    points_void: jax.Array      # [] int32 scan points dropped as lying in void voxels (free-space evidence)
    voxels_free: jax.Array      # [] int32 voxels this frame saw free
    voxels_void: jax.Array      # [] int32 void voxels after the frame
    voxels_raised: jax.Array    # [] int32 voxels whose stored pairs were raised this frame (they turned void)
    rays_left: jax.Array        # [] int32 usable ray samples beyond `carve_samples` (not used this frame)
    voxels_untested: jax.Array  # [] int32 voxels the evidence did not test this frame though in range (beyond
                                # its TESTED_PER_FRAME: a different part of them each frame, `evidence.candidates`)
    kept: jax.Array             # [N] bool the scan points that got training samples


@functools.partial(jax.named_call, name="screen")
def filter_moved_points(static: N3Static, state: N3State, scan: ScanBatch) -> tuple[ScanBatch, jax.Array]:
    """PIN-SLAM's dynamic filter: a scan point where the map, as trained so far, is confidently free
    (SDF above `point_filter` in a voxel whose block holds at least Nt pairs: only voxels near
    surfaces are allocated, so this is space the map once held as surface, or next to one, and later
    saw free) is something that moved in, or an artifact (a mixed pixel between a foreground and a
    background): it gets no samples, so it neither draws a surface nor marks its voxel as hit (which
    would shield it from carving). Returns (scan with those points invalid, [] int32 points dropped)."""
    sdf, q_ok = query(static, state, scan.points)
    pslot = window.block_of(state.store, voxel_rows(static, state, scan.points))
    trained = (pslot >= 0) & (state.store.count[jnp.maximum(pslot, 0)] >= max(static.nt, 1))
    # (once the decoder is frozen: before that the field is still finding its shape)
    mature = state.frame >= static.freeze_after_frame
    drop = scan.valid & q_ok & trained & (sdf > static.point_filter) & mature
    return scan._replace(valid=scan.valid & ~drop), jnp.sum(drop, dtype=jnp.int32)


@functools.partial(jax.named_call, name="screen")
def drop_void_points(static: N3Static, state: N3State, scan: ScanBatch):
    """Scan points that land in void voxels (`jaxmap.n3.evidence`: seen free since their last hit) get no
    samples: they are on something that moves, or a sensor artifact. Returns (scan with those points
    invalid, [N] int32 voxel row of every scan point (-1: none yet), [] int32 points dropped)."""
    rows = jnp.where(scan.valid, voxel_rows(static, state, scan.points), -1)
    is_void = n3evidence.void(state.evidence, static.void_frames)
    drop = (rows >= 0) & is_void[jnp.maximum(rows, 0)]
    return scan._replace(valid=scan.valid & ~drop), rows, jnp.sum(drop, dtype=jnp.int32)


@functools.partial(jax.named_call, name="allocate")
def allocate_voxels(static: N3Static, state: N3State, vkeys, valid, vox):
    """Leaf voxels where near-surface samples land (all feature levels at once).
    vkeys: [n, ns + nf, 4] voxel keys of the samples; valid: [n, ns + nf]; vox: [n * (ns + nf), 3].
    Returns (voxel table, surface samples' rows [n * ns], overflow [], new voxels [], voxel_coord [V, 3])."""
    n, ns = vkeys.shape[0], static.n_surface
    v_rows_cap = state.voxel_coord.shape[0]
    v_limit = min(int(static.max_load * state.voxels.capacity), v_rows_cap)
    voxels, surf_rows, v_over, n_new_v, _ = hashing.insert_counted(
        state.voxels, vkeys[:, :ns].reshape(-1, 4), valid[:, :ns].reshape(-1), hashing.DEFAULT_MAX_PROBES, v_limit)
    surf_vox = vox.reshape(n, vkeys.shape[1], 3)[:, :ns].reshape(-1, 3)
    voxel_coord = state.voxel_coord.at[jnp.where(surf_rows >= 0, surf_rows, v_rows_cap)].set(surf_vox, mode="drop")
    return voxels, surf_rows, v_over, n_new_v, voxel_coord


@functools.partial(jax.named_call, name="allocate")
def allocate_voxel_corners(static: N3Static, state: N3State, voxels: hashing.HashTable, voxel_coord):
    """Corner rows for up to `new_voxels_per_pass` voxels that have none yet (a queue: rows are handed
    out in order, so those voxels are rows [voxels_with_corners, count)).
    Returns (corner table, voxel_corner_rows [V, L*8], voxels_with_corners [], pending [], overflow [],
    new rows [])."""
    v_rows_cap = state.voxel_coord.shape[0]
    k = static.new_voxels_per_pass
    done = state.voxels_with_corners
    pend = done + jnp.arange(k, dtype=jnp.int32)
    pend_ok = pend < voxels.count
    c_limit = min(int(static.max_load * state.corners.capacity), state.feature_table.shape[0])
    corners, crows, c_over, n_new_c = gfeat.allocate_corners(
        state.corners, voxel_coord[jnp.minimum(pend, v_rows_cap - 1)], static.levels, pend_ok, c_limit)
    wrote = pend_ok & ~c_over
    voxel_corner_rows = state.voxel_corner_rows.at[jnp.where(wrote, pend, v_rows_cap)].set(crows, mode="drop")
    done = done + jnp.sum(wrote, dtype=jnp.int32)
    return corners, voxel_corner_rows, done, voxels.count - done, c_over, n_new_c


@functools.partial(jax.named_call, name="pairs")
def free_sample_rows(static: N3Static, state: N3State, voxels: hashing.HashTable, vkeys, valid, surf_rows):
    """Voxel rows of the free-space samples. They train where their leaf voxel has features; elsewhere
    they would only train the decoder's empty-space output (counted in the stats, not silently lost).
    Returns (rows [n, nf], usable [n, nf], ray samples that carve [n, n_ray], ray samples in an
    allocated voxel [n, n_ray])."""
    n, ns, nf = vkeys.shape[0], static.n_surface, vkeys.shape[1] - static.n_surface
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
    return free_rows, free_ok, ray_ok, ray_any


@flax.struct.dataclass
class FramePairs:
    """A frame's training pairs as the store takes them: every near-surface and band sample ([n, ns + nb]
    flattened, point by point), then at most `carve_samples` usable ray samples, compacted (most ray samples
    land in no allocated voxel, or in one a frame hit lately: a few hundred of 350,000 are usable on a
    static street, a few thousand with traffic; the store would sort them all)."""

    rows: jax.Array      # [M] int32 voxel row of each pair (-1: none), M = n * (ns + nb) + B
    vox: jax.Array       # [M, 3] int32 leaf voxel of each pair
    samples: Samples     # [M] the pairs' points, labels, surface flags
    rays_left: jax.Array # [] int32 usable ray samples beyond the budget (a different part of the scan next frame)
    budget: int = flax.struct.field(pytree_node=False, default=0)  # B: the ray samples are the last B

    @property
    def ray(self) -> slice:
        m = self.rows.shape[0]
        return slice(m - self.budget, m)


@functools.partial(jax.named_call, name="pairs")
def frame_pairs(static: N3Static, samples: Samples, vox, valid, surf_rows, free, key) -> FramePairs:
    """The pairs of a frame (`FramePairs`) from its samples ([n * (ns + nf)], `sample_frame`'s order), their
    leaf voxels vox [n * (ns + nf), 3], valid [n, ns + nf], the surface samples' rows [n * ns] and
    `free_sample_rows`'s (rows, usable, ray_ok, ray_any)."""
    n, ns, nb, nr = valid.shape[0], static.n_surface, static.n_free, static.n_ray
    k = ns + nb
    free_rows, free_ok, ray_ok, _ = free
    rows = jnp.concatenate([jnp.where(valid[:, :ns], surf_rows.reshape(n, ns), -1),
                            jnp.where(free_ok[:, :nb], free_rows[:, :nb], -1)], axis=1).reshape(-1)

    def part(x, lo, hi):
        return x.reshape((n, k + nr) + x.shape[1:])[:, lo:hi].reshape((-1,) + x.shape[1:])

    arrays = [vox, samples.points, samples.labels, samples.surface, samples.valid]
    out = [part(x, 0, k) for x in arrays]
    budget = min(static.carve_samples, n * nr)
    rays_left = jnp.zeros((), jnp.int32)
    if budget:
        # at most `budget` of them, in scan order from a random start: over frames every part of the scan is used
        start = jax.random.randint(jax.random.fold_in(key, 4), (), 0, n * nr)
        pick = nonzero_from(ray_ok.reshape(-1), budget, start)
        real = pick < n * nr
        at = jnp.minimum(pick, n * nr - 1)
        rows = jnp.concatenate([rows, jnp.where(real, free_rows[:, nb:].reshape(-1)[at], -1)])
        out = [jnp.concatenate([o, part(x, k, k + nr)[at]]) for o, x in zip(out, arrays)]
        rays_left = jnp.sum(ray_ok, dtype=jnp.int32) - jnp.sum(real, dtype=jnp.int32)
    vox, pts, labels, surface, ok = out
    return FramePairs(rows, vox, Samples(pts, labels, surface, ok), rays_left, budget)


@functools.partial(jax.named_call, name="carve")
def carve_store(static: N3Static, state: N3State, store: window.PairStore, pairs: FramePairs, ray_any, free_rows,
                samples: Samples, stored, key):
    """Let the frame's usable ray samples (`FramePairs`) change the stored pairs they contradict
    (`window.carve`), once the frame's pairs are stored (stored: [] bool); with `carve_sign` also every ray
    sample in an allocated voxel (ray_any [n, n_ray], free_rows [n, nf], samples: the frame's). Returns
    (store, [] int32 pairs changed)."""
    r = pairs.ray
    rows = pairs.rows[r]
    store, carved = window.carve(
        store, rows, pairs.samples.points[r], pairs.samples.labels[r], (rows >= 0) & stored, state.frame,
        jax.random.fold_in(key, 2), margin=static.carve_margin, max_samples=static.carve_samples,
        quiet_frames=static.ray_quiet, rule=static.carve_rule)
    if static.carve_sign:
        # The one thing every ray sample is sure of is its sign: the ray passed through it, so it
        # is outside every object, f(y) > 0, and f(x) > -|x - y| nearby. A pair stored deeper
        # inside than that is gone, whatever hit the voxel lately (no quiet rule needed).
        n = free_rows.shape[0]
        ns, nf = static.n_surface, free_rows.shape[1]
        pts = samples.points.reshape(n, ns + nf, 3)[:, ns + static.n_free:].reshape(-1, 3)
        store, signed = window.carve(
            store, jnp.where(ray_any, free_rows[:, static.n_free:], -1).reshape(-1), pts,
            jnp.zeros((pts.shape[0],), jnp.float32), ray_any.reshape(-1) & stored, state.frame,
            jax.random.fold_in(key, 3), margin=static.carve_margin, max_samples=static.carve_samples,
            quiet_frames=-1, rule="raise")
        carved = carved + signed
    return store, carved


def store_pairs(static: N3Static, state: N3State, pairs: FramePairs, samples: Samples, allowed, center, key, free):
    """The frame's pairs (`FramePairs`) into the pair store (sliding the window around `center` and
    carving), or the flat pool of the replay / keyframe ablations. samples: the frame's own
    (`sample_frame`); free: `free_sample_rows`'s (rows, usable, ray_ok, ray_any).
    Returns (store, pool, ok [], needed [], free blocks [], pairs held [], carved [])."""
    carved = jnp.zeros((), jnp.int32)
    p = pairs.samples
    if static.uses_pool:  # the replay / keyframe ablations: the frame's pairs go to the flat pool
        new_pool, pst = pool.update(state.pool, pairs.rows, p.points, p.labels, p.surface,
                                    state.frame, allowed, keyframes=static.keyframes)
        zero = jnp.zeros((), jnp.int32)
        return state.store, new_pool, pst.ok, pst.needed, zero, new_pool.n, carved
    store, ids, n_win, sst = jax.named_call(window.update, name="store")(
        state.store, pairs.rows, pairs.vox, p.points, p.labels, p.surface, state.frame, center, allowed,
        jax.random.fold_in(key, 1), radius_vox=static.radius_vox, policy=static.block_policy,
        pairs_per_frame=static.pairs_per_frame)
    store = store.replace(window_ids=jnp.where(sst.ok, ids, state.store.window_ids),
                          window_n=jnp.where(sst.ok, n_win, state.store.window_n))
    if static.carve and static.n_ray:
        free_rows, _, _, ray_any = free
        store, carved = carve_store(static, state, store, pairs, ray_any, free_rows, samples, sst.ok, key)
    return store, None, sst.ok, sst.blocks_needed, sst.blocks_free, window.total_pairs(store), carved


def integrate(static: N3Static, state: N3State, scan: ScanBatch, key, fits=True) -> tuple[N3State, FrameStats]:
    """Put one scan into the map (one pass; see the module docstring for `ok` and retries).
    fits: [] bool, False when the preprocessed scan did not fit its rows (nothing is stored)."""
    fits = jnp.asarray(fits, bool)
    scan = scan._replace(valid=scan.valid & fits)
    n = scan.points.shape[0]
    ns, nf = static.n_surface, static.n_free + static.n_ray   # nf: free samples of both kinds
    n_filtered = jnp.zeros((), jnp.int32)
    if static.point_filter > 0:
        scan, n_filtered = filter_moved_points(static, state, scan)
    point_rows = n_void = None
    if static.evidence:
        scan, point_rows, n_void = drop_void_points(static, state, scan)
    elif static.evidence_requested:
        n3evidence.warn_without_layout(static)
    samples = jax.named_call(sample_frame, name="sample")(key, scan.points, scan.normals, scan.valid, scan.sensor, label_mode=static.label_mode,
                           trunc=static.trunc, sigma=static.sigma, n_surface=ns, n_free=static.n_free,
                           free_band=static.free_band, free_label=static.free_label,
                           free_label_mode=static.free_label_mode, n_ray=static.n_ray,
                           min_range=static.free_min_range)
    vox = gfeat.leaf_voxel(samples.points, static.leaf)                           # [N*(ns+nf), 3]
    vkeys = jnp.concatenate([vox, jnp.zeros_like(vox[:, :1])], -1).reshape(n, ns + nf, 4)
    valid = samples.valid.reshape(n, ns + nf)
    voxels, surf_rows, v_over, n_new_v, voxel_coord = allocate_voxels(static, state, vkeys, valid, vox)
    corners, voxel_corner_rows, done, pending, c_over, n_new_c = allocate_voxel_corners(
        static, state, voxels, voxel_coord)
    free = free_sample_rows(static, state, voxels, vkeys, valid, surf_rows)
    free_rows = free[0]
    frame = frame_pairs(static, samples, vox, valid, surf_rows, free, key)
    allowed = ~v_over & ~c_over & (pending == 0) & fits
    center = gfeat.leaf_voxel(scan.sensor[None], static.leaf)[0]
    store, new_pool, ok, needed, free_blocks, pairs, carved = store_pairs(
        static, state, frame, samples, allowed, center, key, free)
    zero = jnp.zeros((), jnp.int32)
    ev, counts = state.evidence, n3evidence.Counts(zero, zero, zero)
    if static.evidence:
        ev, store, counts = n3evidence.update(static, state.evidence, store, scan, point_rows, voxel_coord,
                                              voxels.count, state.frame, ok)
    state = state.replace(voxels=voxels, corners=corners, voxel_coord=voxel_coord,
                          voxel_corner_rows=voxel_corner_rows, voxels_with_corners=done, store=store, pool=new_pool,
                          evidence=ev)
    n_void_voxels = (jnp.sum(n3evidence.void(ev, static.void_frames), dtype=jnp.int32) if static.evidence
                     else zero)
    stats = FrameStats(
        ok=ok, voxel_overflow=v_over, corner_overflow=c_over, store_overflow=allowed & ~ok,
        pending_corners=pending, voxels=voxels.count, feature_rows=corners.count, new_voxels=n_new_v,
        new_feature_rows=n_new_c, blocks_needed=needed, blocks_free=free_blocks, window_blocks=store.window_n,
        store_pairs=pairs, free_dropped=jnp.sum(valid[:, ns:] & (free_rows < 0), dtype=jnp.int32),
        carved=carved, points_filtered=n_filtered, scan_points=jnp.sum(scan.valid, dtype=jnp.int32),
        scan_overflow=~fits, points_void=zero if n_void is None else n_void, voxels_free=counts.free,
        voxels_void=n_void_voxels, voxels_raised=counts.raised, rays_left=frame.rays_left,
        voxels_untested=counts.untested, kept=scan.valid,
    )
    return state, stats
