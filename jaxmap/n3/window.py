"""Voxel-oriented training-pair store and its sliding window (N3 paper, section III-C1).

Each leaf voxel that holds training pairs owns one *block* of `P` pairs. Blocks live in `S` fixed
slots; a voxel row (dense id from the voxel hash table) maps to its slot. The window is the cube of
voxels within `radius` of the current sensor; blocks that leave it are released, so memory is
bounded by the window, not by the sequence length.

What a block keeps (`window.block_policy`), so that a voxel is supervised from the viewpoints that
saw it while it was in the window (the point of the voxel-oriented window):
  reservoir  a uniform sample of all the pairs the voxel received since it entered the window
             (Algorithm R, vectorised per frame), each frame offering at most `pairs_per_frame`
             pairs, evenly spread over the frame's pairs in that voxel. Near the sensor a voxel gets
             15-38 pairs a frame; a ring buffer of 64 would hold only the last 2-4 of the ~40
             frames that see it.                                                      [default]
  ring       the newest P pairs (oldest overwritten); the pre-reservoir store (ablation).

The paper's data-replay ablations (`window.mode` replay / keyframe) do not use blocks: see `pool`.
"""
from __future__ import annotations

from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp

from jaxmap.grid.compaction import nonzero_fixed, nonzero_from, prefix_sum

BLOCK_POLICIES = ("reservoir", "ring")
CARVE_RULES = ("replace", "raise")


@flax.struct.dataclass
class PairStore:
    pairs: jax.Array          # [S, P, 4] float32: x, y, z (map frame), label
    surface: jax.Array        # [S, P] bool: pair lies in the truncation band (eikonal term)
    frame: jax.Array          # [S, P] int32: frame that produced the pair (-1 = never written)
    count: jax.Array          # [S] int32: valid pairs in the block (<= P)
    received: jax.Array       # [S] int32: pairs offered to the block since it was assigned (after the
                              #   per-frame quota); the ring's write position is `received % P`
    frames_seen: jax.Array    # [S] int32: frames that offered pairs to the block since it was assigned
    last_hit: jax.Array       # [S] int32: the last frame whose near-surface samples reached the block
                              #   (-1: none); free space carves only blocks no recent frame hit
    voxel_of_slot: jax.Array  # [S] int32: voxel row owning the slot, -1 = free
    coord: jax.Array          # [S, 3] int32: leaf-voxel coordinate of the block
    slot_of_voxel: jax.Array  # [V] int32: slot of each voxel row, -1 = none
    window_ids: jax.Array     # [S] int32: the window's blocks that hold pairs, `window_ids[:window_n]`
    window_n: jax.Array       # [] int32  (as of the last `update`; what training samples from)

    @property
    def n_slots(self) -> int:
        return self.pairs.shape[0]

    @property
    def block_size(self) -> int:
        return self.pairs.shape[1]


def create(n_slots: int, pairs_per_voxel: int, n_voxel_rows: int) -> PairStore:
    s, p = n_slots, pairs_per_voxel
    return PairStore(
        pairs=jnp.zeros((s, p, 4), jnp.float32),
        surface=jnp.zeros((s, p), bool),
        frame=jnp.full((s, p), -1, jnp.int32),
        count=jnp.zeros((s,), jnp.int32),
        received=jnp.zeros((s,), jnp.int32),
        frames_seen=jnp.zeros((s,), jnp.int32),
        last_hit=jnp.full((s,), -1, jnp.int32),
        voxel_of_slot=jnp.full((s,), -1, jnp.int32),
        coord=jnp.zeros((s, 3), jnp.int32),
        slot_of_voxel=jnp.full((n_voxel_rows,), -1, jnp.int32),
        window_ids=jnp.zeros((s,), jnp.int32),
        window_n=jnp.zeros((), jnp.int32),
    )


def grow(store: PairStore, n_slots: int | None = None, n_voxel_rows: int | None = None) -> PairStore:
    """Bigger capacities, contents kept (outside jit)."""
    s_old, v_old = store.n_slots, store.slot_of_voxel.shape[0]
    s_new, v_new = n_slots or s_old, n_voxel_rows or v_old
    fresh = create(s_new, store.block_size, v_new)

    def put(new, old):
        return new.at[: old.shape[0]].set(old)

    return fresh.replace(
        pairs=put(fresh.pairs, store.pairs), surface=put(fresh.surface, store.surface),
        frame=put(fresh.frame, store.frame), count=put(fresh.count, store.count),
        received=put(fresh.received, store.received), frames_seen=put(fresh.frames_seen, store.frames_seen),
        last_hit=put(fresh.last_hit, store.last_hit),
        voxel_of_slot=put(fresh.voxel_of_slot, store.voxel_of_slot),
        coord=put(fresh.coord, store.coord),
        slot_of_voxel=put(fresh.slot_of_voxel, store.slot_of_voxel),
        window_ids=put(fresh.window_ids, store.window_ids), window_n=store.window_n,
    ) if (s_new, v_new) != (s_old, v_old) else store


def in_window(store: PairStore, center_vox, radius_vox: int):
    """[S] bool: slots in use inside the window, the cube of half-width radius_vox around center_vox."""
    # A range test, not |coord - center| <= r: XLA's GPU backend (jax 0.11.2, H100) miscompiles
    # `all(abs(int32 difference) <= r, axis=-1)` on large arrays (15 % of random rows wrong;
    # tests/test_n3_core.py checks this formulation against numpy on whatever backend runs it).
    lo, hi = center_vox - radius_vox, center_vox + radius_vox
    inside = jnp.all((store.coord >= lo) & (store.coord <= hi), axis=-1)
    return (store.voxel_of_slot >= 0) & inside


class StoreStats(NamedTuple):
    """What `update` reports to the host (a few scalars)."""

    ok: jax.Array             # [] bool: the update was applied (False: nothing changed; grow and retry)
    blocks_needed: jax.Array  # [] int32: voxels of the batch that needed a new block
    blocks_free: jax.Array    # [] int32: free blocks once the window had slid


def ranks_within_slot(slots, n_slots: int):
    """Rank of each item among the earlier items of the same slot, and the count per slot.

    slots: [M] int32 in [0, n_slots] (n_slots = no slot). Returns (rank [M] int32, n_in [n_slots]).
    Equal to a stable argsort by slot, without one: XLA's CPU sort of an index payload costs ~4x a
    sort of bare uint32 keys, so the items are cut into chunks small enough that
    `slot << b | index_in_chunk` fits 32 bits, each chunk's packed keys are sorted alone (ranks
    within the chunk from run starts), and a per-chunk histogram adds the counts of earlier chunks.
    """
    m = slots.shape[0]
    slot_bits = int(n_slots).bit_length()
    if slot_bits > 20:  # chunks would get too small: sort with a payload instead
        order = jnp.argsort(slots, stable=True)
        ks = slots[order]
        i = jnp.arange(m, dtype=jnp.int32)
        first = jnp.concatenate([jnp.ones((1,), bool), ks[1:] != ks[:-1]])
        r = i - jax.lax.cummax(jnp.where(first, i, 0))
        n_in = jnp.zeros((n_slots + 1,), jnp.int32).at[slots].add(1)[:n_slots]
        return jnp.zeros((m,), jnp.int32).at[order].set(r), n_in
    b = 32 - slot_bits
    c = min(1 << b, m)
    n_chunks = -(-m // c)
    pad = n_chunks * c - m
    sl = jnp.concatenate([slots, jnp.full((pad,), n_slots, slots.dtype)]).reshape(n_chunks, c)
    local = jnp.arange(c, dtype=jnp.uint32)
    keys = jnp.sort((sl.astype(jnp.uint32) << b) | local, axis=-1)              # [n_chunks, c]
    ks = (keys >> b).astype(jnp.int32)
    low = jnp.uint32((1 << b) - 1)
    at = (keys & low).astype(jnp.int32)                                         # index within the chunk
    # Position in the sorted chunk minus the start of the slot's run (a binary search; XLA's CPU
    # cumulative max/sum lower to slow reduce-windows).
    start = jax.vmap(jnp.searchsorted)(keys, keys & ~low)
    r_sorted = jnp.arange(c, dtype=jnp.int32) - start.astype(jnp.int32)
    chunk = jnp.arange(n_chunks, dtype=jnp.int32)[:, None]
    hist = jnp.zeros((n_chunks, n_slots + 1), jnp.int32).at[chunk, sl].add(1)   # [n_chunks, S+1]
    before = [jnp.zeros((n_slots + 1,), jnp.int32)]                             # earlier chunks' counts
    for j in range(n_chunks - 1):
        before.append(before[-1] + hist[j])
    r_sorted = r_sorted + jnp.stack(before)[chunk, ks]
    rank = jnp.zeros((n_chunks, c), jnp.int32).at[chunk, at].set(r_sorted).reshape(-1)[:m]
    return rank, hist.sum(0)[:n_slots]


class _Blocks(NamedTuple):
    """The store's per-block arrays once the window slid and the batch's voxels got their blocks."""

    slot_of_voxel: jax.Array  # [V] int32
    voxel_of_slot: jax.Array  # [S] int32
    coord: jax.Array          # [S, 3] int32
    count: jax.Array          # [S] int32
    received: jax.Array       # [S] int32
    frames_seen: jax.Array    # [S] int32
    last_hit: jax.Array       # [S] int32


def assign_blocks(store: PairStore, voxel_rows, coords, center_vox, allowed, radius_vox: int):
    """Slide the window and give a block to every voxel of the batch that has none (all or nothing).
    Returns (_Blocks, slot [M] int32 of each pair (S: none), ok [], blocks needed [], blocks free [])."""
    s = store.n_slots
    v = store.slot_of_voxel.shape[0]
    m = voxel_rows.shape[0]
    idx = jnp.arange(m, dtype=jnp.int32)

    keep = in_window(store, center_vox, radius_vox)
    released = (store.voxel_of_slot >= 0) & ~keep                              # [S]
    free = (store.voxel_of_slot < 0) | released                                # [S] once slid

    real = voxel_rows >= 0
    row = jnp.where(real, voxel_rows, v)                                       # v: out of range
    # The first pair of each voxel (a scatter-min of pair indices) speaks for the voxel.
    first = real & (jnp.full((v,), m, jnp.int32).at[row].min(idx, mode="drop")[jnp.minimum(row, v - 1)] == idx)
    cur = store.slot_of_voxel[jnp.minimum(row, v - 1)]                         # block held now
    has = real & (cur >= 0) & ~released[jnp.maximum(cur, 0)]
    need = first & ~has
    n_need = jnp.sum(need, dtype=jnp.int32)
    n_free = jnp.sum(free, dtype=jnp.int32)
    ok = jnp.asarray(allowed, bool) & (n_need <= n_free)

    # Slide: free the blocks that left the window (their pairs are never read again: count = 0).
    drop = released & ok
    slot_of_voxel = store.slot_of_voxel.at[jnp.where(drop, store.voxel_of_slot, v)].set(-1, mode="drop")
    voxel_of_slot = jnp.where(drop, -1, store.voxel_of_slot)
    count = jnp.where(drop, 0, store.count)
    received = jnp.where(drop, 0, store.received)
    frames_seen = jnp.where(drop, 0, store.frames_seen)
    last_hit = jnp.where(drop, -1, store.last_hit)
    # Assign: voxels needing a block take the free blocks in order of voxel row (deterministic, and
    # the order of the pre-refactor store).
    k = min(m, s)
    free_list = nonzero_fixed(free, k, s)                                       # [k]
    needv = jnp.zeros((v + 1,), jnp.int32).at[row].max(need.astype(jnp.int32))[:v]
    rank_v = prefix_sum(needv) - 1
    new_slot = free_list[jnp.clip(rank_v[jnp.minimum(row, v - 1)], 0, k - 1)]
    take = need & ok
    tgt_slot = jnp.where(take, new_slot, s)
    blocks = _Blocks(
        slot_of_voxel=slot_of_voxel.at[jnp.where(take, row, v)].set(new_slot, mode="drop"),
        voxel_of_slot=voxel_of_slot.at[tgt_slot].set(voxel_rows, mode="drop"),
        coord=store.coord.at[tgt_slot].set(coords, mode="drop"),
        count=count.at[tgt_slot].set(0, mode="drop"),
        received=received.at[tgt_slot].set(0, mode="drop"),
        frames_seen=frames_seen.at[tgt_slot].set(0, mode="drop"),
        last_hit=last_hit.at[tgt_slot].set(-1, mode="drop"))
    slot = jnp.where(real & ok, blocks.slot_of_voxel[jnp.minimum(row, v - 1)], s)    # [M] s: skip
    return blocks, slot, ok, n_need, n_free


def frame_quota(slot, rank, n_in, ss, q: int, s: int):
    """The per-frame quota: of the n pairs a frame brings to a block keep q evenly spaced ones;
    the kept ones are renumbered 0..q-1 (rank r is kept where floor((r+1) q / n) steps up).
    Returns (slot [M] (s: not kept), rank [M], n_in [S])."""
    n_s = jnp.maximum(n_in[ss], 1)
    few = n_s <= q
    k_hi = ((rank + 1) * q) // n_s
    kept = few | (k_hi > (rank * q) // n_s)
    return jnp.where(kept, slot, s), jnp.where(few, rank, k_hi - 1), jnp.minimum(n_in, q)


def block_positions(policy: str, key, slot, rank, n_in, i, ss, s: int, p: int):
    """Where in its block each pair goes under `policy`: (block [M] (s: nowhere), position [M]).
    i: [M] the pair's index in its block's stream of pairs."""
    if policy == "ring":
        # The r-th of n pairs goes to position (received + r) % P; the newest P survive.
        return jnp.where((slot < s) & (rank >= n_in[ss] - p), slot, s), i % p
    if policy == "reservoir":
        # Algorithm R: the i-th pair fills position i while the block has room, else replaces a
        # uniform position j in [0, i] if j < P. Pairs of one frame that draw the same position
        # resolve as a sequential pass would: the later one wins (a scatter-max of the rank).
        j = jnp.floor(jax.random.uniform(key, i.shape) * (i + 1).astype(jnp.float32)).astype(jnp.int32)
        pos = jnp.where(i < p, i, jnp.minimum(j, i))
        cand = jnp.where((slot < s) & (pos < p), slot, s)
        pos = jnp.minimum(pos, p - 1)
        winner = jnp.full((s, p), -1, jnp.int32).at[cand, pos].max(rank, mode="drop")
        return jnp.where((cand < s) & (winner[jnp.minimum(cand, s - 1), pos] == rank), cand, s), pos
    raise ValueError(f"window.block_policy must be one of {BLOCK_POLICIES}, got {policy!r}")


def update(store: PairStore, voxel_rows, coords, points, labels, surface, frame, center_vox, allowed=True,
           key=None, *, radius_vox: int, policy: str = "ring",
           pairs_per_frame: int = 0):
    """Slide the window, give a block to every voxel of the batch that has none, append the pairs.

    voxel_rows: [M] int32 voxel row of each pair (-1 = drop the pair); coords: [M, 3] int32 leaf-voxel
    coordinates; points: [M, 3] float32 map frame; labels: [M]; surface: [M] bool; frame: [] int32;
    center_vox: [3] int32 leaf voxel of the sensor; allowed: [] bool, False makes it a no-op.

    All or nothing: if more voxels need a block than there are free blocks after the slide, or
    `allowed` is False, the store comes back unchanged with `ok = False` (the caller grows the store
    outside jit and retries; no pair is ever dropped for capacity). What a block keeps is `policy`
    (module docstring): "ring", the newest P pairs (within a frame, later pairs of the batch are
    newer); "reservoir", a uniform sample of the pairs offered (key: PRNG key of the draws).
    pairs_per_frame > 0: a voxel is offered at most that many of a frame's pairs (evenly spaced in
    batch order); 0 = all.

    Returns (store, ids [S] int32, n [] int32: the window blocks that hold pairs, `ids[:n]`, StoreStats).
    """
    s, p = store.n_slots, store.block_size
    b, slot, ok, n_need, n_free = assign_blocks(store, voxel_rows, coords, center_vox, allowed, radius_vox)
    # (before the per-frame quota: every near-surface sample of the frame marks its block as hit)
    last_hit = b.last_hit.at[jnp.where(surface, slot, s)].set(frame, mode="drop")
    rank, n_in = ranks_within_slot(slot, s)
    ss = jnp.minimum(slot, s - 1)
    if pairs_per_frame > 0:
        slot, rank, n_in = frame_quota(slot, rank, n_in, ss, pairs_per_frame, s)
    i = b.received[ss] + rank                                                  # index in the block's stream
    tgt, pos = block_positions(policy, key, slot, rank, n_in, i, ss, s, p)
    store = store.replace(
        pairs=store.pairs.at[tgt, pos].set(jnp.concatenate([points, labels[:, None]], -1), mode="drop"),
        surface=store.surface.at[tgt, pos].set(surface, mode="drop"),
        frame=store.frame.at[tgt, pos].set(frame, mode="drop"),
        received=b.received + n_in,
        frames_seen=b.frames_seen + (n_in > 0),
        last_hit=last_hit,
        count=jnp.minimum(b.count + n_in, p),
        voxel_of_slot=b.voxel_of_slot, slot_of_voxel=b.slot_of_voxel, coord=b.coord,
    )
    inside = in_window(store, center_vox, radius_vox)
    ids, n = window_slots(inside & (store.count > 0))
    return store, ids, n, StoreStats(ok, n_need, n_free)


def block_of(store: PairStore, voxel_rows):
    """The store slot (block) of each voxel row: voxel_rows [M] int32 (-1: no voxel) -> [M] int32, -1
    where the voxel has no block (or there is no voxel)."""
    v = store.slot_of_voxel.shape[0]
    return jnp.where(voxel_rows >= 0, store.slot_of_voxel[jnp.clip(voxel_rows, 0, v - 1)], -1)


def raise_labels(store: PairStore, voxel_rows, floor: float) -> PairStore:
    """The store with the labels of the pairs held for voxel_rows [C] int32 (outside [0, V): none) raised to
    at least `floor`; a pair raised leaves the eikonal term (`surface` cleared: it is no surface sample any
    more). The free-space evidence's rule for voxels that turned void (`jaxmap.n3.evidence.raise_void_pairs`)."""
    v, s = store.slot_of_voxel.shape[0], store.n_slots
    slot = block_of(store, jnp.where(voxel_rows < v, voxel_rows, -1))
    tgt = jnp.where(slot >= 0, slot, s)
    pairs = store.pairs[jnp.minimum(tgt, s - 1)]                                 # [C, P, 4]
    lab = pairs[..., 3]
    low = lab < floor
    pairs = pairs.at[..., 3].set(jnp.maximum(lab, floor))
    surf = store.surface[jnp.minimum(tgt, s - 1)] & ~low
    return store.replace(pairs=store.pairs.at[tgt].set(pairs, mode="drop"),
                         surface=store.surface.at[tgt].set(surf, mode="drop"))


def window_slots(in_window):
    """Compact list of window slots. in_window: [S] bool -> (ids [S] int32, n [] int32): `ids[:n]`."""
    return nonzero_fixed(in_window, in_window.shape[0], 0), in_window.sum().astype(jnp.int32)


def frames_held_fraction(store: PairStore, ids, n, min_frames: int = 1):
    """Median over the window's blocks `ids[:n]` observed by at least `min_frames` frames of (distinct
    frames among the pairs a block holds) / (frames that offered it pairs since it entered the
    window): 1.0 = every viewpoint kept. (Most window voxels are seen by few frames, so the median
    over all is 1.0 for any policy; min_frames=10 shows what a policy keeps of well-observed voxels.)"""
    held = jnp.arange(store.block_size)[None, :] < store.count[ids][:, None]
    b = jnp.where(held, store.frame[ids], -1)                                  # [S, P]
    srt = jnp.sort(b, axis=1)
    distinct = jnp.sum((srt >= 0) & jnp.concatenate([jnp.ones_like(srt[:, :1], bool), srt[:, 1:] != srt[:, :-1]], 1),
                       axis=1)
    frac = distinct / jnp.maximum(store.frames_seen[ids], 1)
    frac = jnp.where((jnp.arange(ids.shape[0]) < n) & (store.frames_seen[ids] >= min_frames), frac, jnp.nan)
    return jnp.nanmedian(frac)


def forget_frames(store: PairStore, drop):
    """The store without the pairs of the frames `drop` [F] bool names (indexed by the frame number the
    pairs carry; frames >= F are kept): each block's other pairs move to its front, in order. A block
    that lost pairs restarts its stream at its count (so the reservoir fills the room first). The
    window list is left as it is: a block left empty trains nothing (count 0).
    Returns (store, [] int32 pairs removed)."""
    p, f_max = store.block_size, drop.shape[0]
    held = jnp.arange(p)[None, :] < store.count[:, None]                       # [S, P]
    f = store.frame
    gone = held & (f >= 0) & (f < f_max) & drop[jnp.clip(f, 0, f_max - 1)]
    keep = held & ~gone
    order = jnp.argsort(~keep, axis=1, stable=True)                            # kept pairs first, in order
    pairs = jnp.take_along_axis(store.pairs, order[..., None], axis=1)
    count = jnp.sum(keep, axis=1, dtype=jnp.int32)
    lost = jnp.any(gone, axis=1)
    return store.replace(pairs=pairs, surface=jnp.take_along_axis(store.surface, order, axis=1),
                         frame=jnp.take_along_axis(store.frame, order, axis=1), count=count,
                         received=jnp.where(lost, count, store.received)), jnp.sum(gone, dtype=jnp.int32)


def total_pairs(store: PairStore):
    """[] int32: pairs held by the store (what the memory bound is about)."""
    return store.count.sum()


def carve(store: PairStore, voxel_rows, points, labels, use, frame, key, *, margin: float, max_samples: int,
          quiet_frames: int = 0, rule: str = "replace"):
    """Free space replaces the stored pairs it contradicts (what moved away is erased, N3 Fig. 10).

    A free-space sample y with an honest label l_y (a lower bound of its distance to every surface)
    says f(y) >= l_y, so a 1-Lipschitz SDF has f(x) >= l_y - |x - y| everywhere. A pair (x, l) stored
    by an earlier frame in y's block with l < l_y - |x - y| - margin cannot hold any more: the surface
    it described is gone (a car that drove on). `rule` "replace": each sample replaces the most
    contradicted such pair of its block with itself (a free-space pair of this frame); "raise": every
    contradicted pair keeps its place and its label rises to the bound, l_y - |x - y| - margin (the
    largest over the frame's samples), no longer a surface pair. Pairs of the current frame are never
    changed. True surfaces are safe as long as free labels are honest (`sampling.free_label_mode`
    projected, ray samples in voxels the frame hit dropped), `margin` covering the range noise; and
    a ray's label is only honest about its own hit (a ray to a far wall that passes 10 cm above the
    road claims tr), so blocks that a frame hit within the last `quiet_frames` frames are not carved:
    a static surface is hit again and again, what moved away is not.

    voxel_rows: [M] int32 (-1: none); points: [M, 3] float32 map frame; labels: [M]; use: [M] bool;
    frame: [] int32; key: PRNG key. At most `max_samples` of the usable samples carve per frame (a
    fixed-size gather of [max_samples, P] pairs): those from a random start on, in scan order, so
    that over frames every part of the scan carves.
    Returns (store, [] int32 pairs changed).
    """
    s, p = store.n_slots, store.block_size
    slot = jnp.where(use, block_of(store, voxel_rows), -1)
    quiet = (store.last_hit[jnp.maximum(slot, 0)] < frame - quiet_frames)
    slot = jnp.where(quiet, slot, -1)
    total = slot.shape[0]
    m = min(max_samples, total)
    pick = nonzero_from(slot >= 0, m, jax.random.randint(key, (), 0, total))  # [m], total: none
    real = pick < total
    pick = jnp.minimum(pick, total - 1)
    sl = jnp.where(real, slot[pick], 0)
    y, ly = points[pick], labels[pick]                                         # [m, 3], [m]
    blk = store.pairs[sl]                                                      # [m, P, 4]
    d = jnp.linalg.norm(blk[..., :3] - y[:, None], axis=-1)                    # [m, P]
    held = (jnp.arange(p)[None] < store.count[sl][:, None]) & (store.frame[sl] < frame)
    excess = jnp.where(held, (ly[:, None] - d - margin) - blk[..., 3], 0.0)    # > 0: contradicted
    if rule == "raise":
        # every contradicted pair's label rises to the bound (the largest over this frame's samples)
        bad = real[:, None] & (excess > 0)                                     # [m, P]
        tgt = jnp.where(bad, sl[:, None], s)
        cols = jnp.broadcast_to(jnp.arange(p)[None], bad.shape)
        new = store.replace(
            pairs=store.pairs.at[tgt, cols, 3].max(ly[:, None] - d - margin, mode="drop"),
            surface=store.surface.at[tgt, cols].set(False, mode="drop"),
        )
        return new, jnp.sum(bad, dtype=jnp.int32)
    if rule != "replace":
        raise ValueError(f"window.carve_rule must be one of {CARVE_RULES}, got {rule!r}")
    j = jnp.argmax(excess, axis=1)
    hit = real & (jnp.take_along_axis(excess, j[:, None], 1)[:, 0] > 0)
    tgt = jnp.where(hit, sl, s)
    new = store.replace(
        pairs=store.pairs.at[tgt, j].set(jnp.concatenate([y, ly[:, None]], -1), mode="drop"),
        surface=store.surface.at[tgt, j].set(False, mode="drop"),
        frame=store.frame.at[tgt, j].set(frame, mode="drop"),
    )
    return new, jnp.sum(hit, dtype=jnp.int32)
