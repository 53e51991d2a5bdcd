"""Voxel-oriented training-pair store and its sliding window (N3 paper, section III-C1).

Each leaf voxel that holds training pairs owns one *block*: a ring buffer of `P` pairs (oldest
overwritten, counts kept), so a voxel keeps supervision from every viewpoint that saw it. Blocks
live in `S` fixed slots; a voxel row (dense id from the voxel hash table) maps to its slot.
The window is the cube of voxels within `radius` of the current sensor; blocks that leave it are
released, so memory is bounded by the window, not by the sequence length.

Ablations (`window.mode`): `replay` never releases (all past frames stay), `keyframe` keeps only
pairs of the last N frames.
"""
from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

WINDOW_MODES = ("voxel", "replay", "keyframe")


@flax.struct.dataclass
class PairStore:
    pairs: jax.Array          # [S, P, 4] float32: x, y, z (map frame), label
    surface: jax.Array        # [S, P] bool: pair lies in the truncation band (eikonal term)
    frame: jax.Array          # [S, P] int32: frame that produced the pair (-1 = never written)
    count: jax.Array          # [S] int32: valid pairs in the block (<= P)
    head: jax.Array           # [S] int32: next ring-buffer write position
    voxel_of_slot: jax.Array  # [S] int32: voxel row owning the slot, -1 = free
    coord: jax.Array          # [S, 3] int32: leaf-voxel coordinate of the block
    last_frame: jax.Array     # [S] int32: last frame that wrote into the block
    slot_of_voxel: jax.Array  # [V] int32: slot of each voxel row, -1 = none

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
        head=jnp.zeros((s,), jnp.int32),
        voxel_of_slot=jnp.full((s,), -1, jnp.int32),
        coord=jnp.zeros((s, 3), jnp.int32),
        last_frame=jnp.full((s,), -1, jnp.int32),
        slot_of_voxel=jnp.full((n_voxel_rows,), -1, jnp.int32),
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
        head=put(fresh.head, store.head), voxel_of_slot=put(fresh.voxel_of_slot, store.voxel_of_slot),
        coord=put(fresh.coord, store.coord), last_frame=put(fresh.last_frame, store.last_frame),
        slot_of_voxel=put(fresh.slot_of_voxel, store.slot_of_voxel),
    ) if (s_new, v_new) != (s_old, v_old) else store


def in_window(store: PairStore, center_vox, radius_vox: int, *, mode: str, frame, keyframes: int):
    """[S] bool: slots inside the current window (and in use)."""
    used = store.voxel_of_slot >= 0
    if mode == "voxel":
        inside = jnp.all(jnp.abs(store.coord - center_vox) <= radius_vox, axis=-1)
    elif mode == "replay":
        inside = jnp.ones_like(used)
    elif mode == "keyframe":
        inside = store.last_frame > frame - keyframes
    else:
        raise ValueError(f"window.mode must be one of {WINDOW_MODES}, got {mode!r}")
    return used & inside


def release(store: PairStore, keep) -> PairStore:
    """Free the slots where `keep` is False. keep: [S] bool."""
    drop = (store.voxel_of_slot >= 0) & ~keep
    v = store.slot_of_voxel.shape[0]
    vox = jnp.where(drop, store.voxel_of_slot, v)   # out of range -> dropped by the scatter
    return store.replace(
        slot_of_voxel=store.slot_of_voxel.at[vox].set(-1, mode="drop"),
        voxel_of_slot=jnp.where(drop, -1, store.voxel_of_slot),
        count=jnp.where(drop, 0, store.count),
        head=jnp.where(drop, 0, store.head),
        frame=jnp.where(drop[:, None], -1, store.frame),
        last_frame=jnp.where(drop, -1, store.last_frame),
    )


def assign_slots(store: PairStore, voxel_rows, coords):
    """Give every voxel row without a block a free slot.

    voxel_rows: [M] int32 (-1 = no voxel, ignored); coords: [M,3] int32 leaf-voxel coordinates.
    Returns (store, slots [M] int32 (-1 where voxel_rows is -1), overflow [] bool). On overflow
    the store is returned unchanged in the overflowing part; the caller grows and retries.
    """
    v = store.slot_of_voxel.shape[0]
    m = voxel_rows.shape[0]
    ok = voxel_rows >= 0
    rows_or_oob = jnp.where(ok, voxel_rows, v)
    touched = jnp.zeros((v,), bool).at[rows_or_oob].set(True, mode="drop")
    need = touched & (store.slot_of_voxel < 0)
    coord_of_row = jnp.zeros((v, 3), jnp.int32).at[rows_or_oob].set(coords, mode="drop")
    k = min(m, v)
    need_rows = jnp.nonzero(need, size=k, fill_value=v)[0]                    # [k]
    free_slots = jnp.nonzero(store.voxel_of_slot < 0, size=k, fill_value=store.n_slots)[0]
    n_need = need.sum()
    n_free = (store.voxel_of_slot < 0).sum()
    overflow = n_need > n_free
    pair_ok = (need_rows < v) & (free_slots < store.n_slots)
    nr = jnp.where(pair_ok, need_rows, v)
    fs = jnp.where(pair_ok, free_slots, store.n_slots)
    store = store.replace(
        slot_of_voxel=store.slot_of_voxel.at[nr].set(fs.astype(jnp.int32), mode="drop"),
        voxel_of_slot=store.voxel_of_slot.at[fs].set(nr.astype(jnp.int32), mode="drop"),
        coord=store.coord.at[fs].set(coord_of_row[jnp.minimum(nr, v - 1)], mode="drop"),
        count=store.count.at[fs].set(0, mode="drop"),
        head=store.head.at[fs].set(0, mode="drop"),
    )
    slots = jnp.where(ok, store.slot_of_voxel[jnp.minimum(rows_or_oob, v - 1)], -1)
    return store, slots, overflow


def write_pairs(store: PairStore, slots, points, labels, surface, frame) -> PairStore:
    """Append pairs to their blocks' ring buffers (only the newest P of a block survive).

    slots: [M] int32 (-1 = skip); points: [M,3]; labels: [M]; surface: [M] bool; frame: [] int32.
    """
    s, p = store.n_slots, store.block_size
    m = slots.shape[0]
    key = jnp.where(slots >= 0, slots, s)
    order = jnp.argsort(key, stable=True)
    ks = key[order]
    idx = jnp.arange(m)
    first = jnp.concatenate([jnp.ones((1,), bool), ks[1:] != ks[:-1]])
    start = jax.lax.cummax(jnp.where(first, idx, 0))
    rank = idx - start                                             # position within the slot's run
    n_in = jnp.zeros((s + 1,), jnp.int32).at[ks].add(1)[:s]        # pairs arriving per slot
    ks_c = jnp.minimum(ks, s - 1)
    keep = (ks < s) & (rank >= n_in[ks_c] - p)
    pos = (store.head[ks_c] + rank) % p
    tgt = jnp.where(keep, ks, s)
    row = jnp.concatenate([points[order], labels[order, None]], axis=-1)
    return store.replace(
        pairs=store.pairs.at[tgt, pos].set(row, mode="drop"),
        surface=store.surface.at[tgt, pos].set(surface[order], mode="drop"),
        frame=store.frame.at[tgt, pos].set(frame, mode="drop"),
        head=(store.head + n_in) % p,
        count=jnp.minimum(store.count + n_in, p),
        last_frame=jnp.where(n_in > 0, frame, store.last_frame),
    )


def total_pairs(store: PairStore):
    """[] int32: pairs held by the store (what the memory bound is about)."""
    return store.count.sum()
