"""Free-space evidence that persists: per leaf voxel, how many frames saw it free since it was last hit.

DUFOMap's idea on the N3 map's voxels. Every frame tests the allocated leaf voxels within
`evidence.max_range_m` of the sensor (the window's and those that left it) against the scan's range
image (`jaxmap.range_image`, built from the whole raw scan, not the training crop), those whose own pixel
lets them be free (`may_be_free`, one lookup: about a fifth of them) with their whole footprint:

  seen free  every return whose ray passes through the voxel lies beyond the voxel's far side by
             `margin` (pose and range error): the sensor looked through the whole voxel. Its footprint
             (`range_image.footprint_nearest`): in azimuth the columns within asin(r_v / d) of the
             centre's direction plus half a column (d its distance, r_v the half-diagonal), in elevation
             the sensor's own beams that bracket that angle. A footprint without any return (the sky,
             nothing within range) says nothing; a dropout under a return blocks
             (`range_image.dropouts_block`); one reaching beyond the field of view is never free.
  hit        a scan point of this frame lies in the voxel.

`free_run` counts the frames that saw the voxel free since its last hit (a hit resets it), and a voxel
with `free_run >= void_frames` is *void*: something was there and left (a car, a pedestrian), or was
never there (a mixed pixel's veil). Then (`jaxmap.n3.integrate`):
  - scan points that land in a void voxel get no training samples: they are on something that moves
    (their hit still resets the voxel, so a car that parks is trained from its second frame on);
  - the pairs stored in a voxel when it turns void are raised to at least `margin` (no surface closer
    than that was seen from any ray through it): the field there turns positive;
  - the map's queries and its mesh are invalid in void voxels (`jaxmap.n3.query`), also after the voxel
    left the training window: the evidence is per voxel row, and lives as long as the map.

The footprint test never frees a voxel that holds or touches a surface a ray saw: the surface's own
return, or a neighbouring pixel's, lies within the voxel or the margin. A wall seen at grazing incidence
is hit by the beams below the one that passes over it, and those are in the footprint.
"""
from __future__ import annotations

import math

import flax.struct
import jax
import jax.numpy as jnp

from jaxmap import range_image as ri
from jaxmap.grid.compaction import nonzero_fixed, nonzero_from

RUN_CAP = 1 << 14          # free_run saturates here (int32; a voxel seen free for ever stays void)
RAISE_PER_FRAME = 4096     # voxels whose pairs are raised per frame (the rest next frame: `raised` says)
TESTED_PER_FRAME = 1 << 16  # voxels tested against a frame's range image at most (those within
                            # `evidence.max_range_m` that `may_be_free` lets through: 18-31 k of 105-122 k on
                            # the city and the traffic street; when more are, a different part of them each frame)


@flax.struct.dataclass
class Evidence:
    free_run: jax.Array   # [V] int32 frames that saw the voxel free since its last hit
    raised: jax.Array     # [V] bool its stored pairs were raised once it turned void (cleared by a hit)


def create(n_voxel_rows: int) -> Evidence:
    return Evidence(free_run=jnp.zeros((n_voxel_rows,), jnp.int32), raised=jnp.zeros((n_voxel_rows,), bool))


def grow(ev: Evidence, n_voxel_rows: int) -> Evidence:
    """More voxel rows, contents kept (outside jit)."""
    extra = n_voxel_rows - ev.free_run.shape[0]
    if extra <= 0:
        return ev
    return Evidence(free_run=jnp.concatenate([ev.free_run, jnp.zeros((extra,), jnp.int32)]),
                    raised=jnp.concatenate([ev.raised, jnp.zeros((extra,), bool)]))


def void(ev: Evidence, void_frames: int) -> jax.Array:
    """[V] bool: voxels seen free in at least `void_frames` frames since their last hit."""
    return ev.free_run >= void_frames


def candidates(voxel_coord, n_voxels, leaf: float, sensor, max_range: float, offset, maybe=True):
    """The voxel rows a frame tests: those within max_range of the sensor (map frame) that `maybe` ([V]
    bool, `may_be_free`) lets through, at most TESTED_PER_FRAME of them, starting at row `offset` (a traced
    int; the caller rotates it, so that when more voxels are in range every one is tested every few frames).
    Returns (rows [T] int32 (V: none), [] bool more voxels were in range than tested)."""
    v = voxel_coord.shape[0]
    d = (voxel_coord.astype(jnp.float32) + 0.5) * leaf - sensor
    near = (jnp.sum(d * d, axis=1) <= max_range * max_range) & (jnp.arange(v, dtype=jnp.int32) < n_voxels) & maybe
    size = min(TESTED_PER_FRAME, v)
    return nonzero_from(near, size, offset), jnp.sum(near, dtype=jnp.int32) > size


def may_be_free(voxel_coord, leaf: float, blocked, layout: ri.Layout, rotation, translation, margin: float,
                min_range: float):
    """[V] bool: the voxels (leaf-voxel coordinates [V, 3] int32, map frame) `seen_free` may find free this
    frame, at a fraction of its cost: one pixel instead of a footprint. The pixel of the voxel's centre is
    in its footprint, so where that pixel's return (blocked: the range image with its dropouts blocking,
    `range_image.dropouts_block`) is not beyond the voxel's far side by `margin`, neither is the footprint's
    nearest. A pixel without a return (inf) passes: the rest of the footprint may hold one. (A centimetre of
    slack: the two tests round their angles in different programs.)"""
    centre = (voxel_coord.astype(jnp.float32) + 0.5) * leaf - translation
    p_s = jnp.sum(centre[:, :, None] * rotation[None], axis=1)                        # (as `seen_free`)
    half = leaf * math.sqrt(3.0) / 2.0
    row, col, dist, inside = ri.pixels(p_s, layout, jnp)
    own = blocked[jnp.clip(row, 0, layout.rows - 1), col]
    return inside & (dist > max(min_range, half + margin) - 0.01) & (own > dist + half + margin - 0.01)


def seen_free(voxel_coord, leaf: float, levels, layout: ri.Layout, rotation, translation, margin: float,
              min_range: float):
    """[T] bool: which of the voxels (leaf-voxel coordinates [T, 3] int32, map frame) this frame saw free.
    levels: `range_image.footprint_levels` of the frame's range image; rotation [3, 3] R_map_sensor and
    translation [3] the sensor's pose in the map frame."""
    centre = (voxel_coord.astype(jnp.float32) + 0.5) * leaf - translation             # [T, 3] map frame
    # R^T c elementwise, not a matmul: a GPU's float32 matmul may round through TF32 (centimetres at 50 m)
    p_s = jnp.sum(centre[:, :, None] * rotation[None], axis=1)                        # [T, 3] sensor frame
    half = leaf * math.sqrt(3.0) / 2.0
    nearest, ok, dist = ri.footprint_nearest(levels, layout, p_s, half, jnp)
    ok = ok & (dist > max(min_range, half + margin))
    return ok & jnp.isfinite(nearest) & (nearest > dist + half + margin)


def observe(ev: Evidence, rows, free, hit, apply) -> Evidence:
    """This frame's evidence: hit [V] bool resets, free [T] bool of voxel rows [T] (V: none; and not hit)
    counts; apply [] bool (the frame went in: a failed pass changes nothing)."""
    v = ev.free_run.shape[0]
    seen = jnp.zeros((v,), bool).at[jnp.where(free & apply, rows, v)].set(True, mode="drop")
    run = jnp.where(hit, 0, jnp.where(seen, jnp.minimum(ev.free_run + 1, RUN_CAP), ev.free_run))
    return Evidence(free_run=jnp.where(apply, run, ev.free_run), raised=ev.raised & ~(hit & apply))


def raise_void_pairs(ev: Evidence, store, void_frames: int, floor: float, apply):
    """Raise the labels of the pairs stored in voxels that turned void (at most RAISE_PER_FRAME voxels a
    frame; `raised` remembers which are done) to at least `floor`; those pairs lose the eikonal term
    where they were raised (they are no surface sample any more). Returns (evidence, store, [] int32
    voxels raised)."""
    v = ev.free_run.shape[0]
    todo = void(ev, void_frames) & ~ev.raised & apply
    rows = nonzero_fixed(todo, RAISE_PER_FRAME, v)                               # [C] (v: none)
    slot = jnp.where(rows < v, store.slot_of_voxel[jnp.minimum(rows, v - 1)], -1)
    s = store.n_slots
    tgt = jnp.where(slot >= 0, slot, s)
    pairs = store.pairs[jnp.minimum(tgt, s - 1)]                                 # [C, P, 4]
    lab = pairs[..., 3]
    low = lab < floor
    pairs = pairs.at[..., 3].set(jnp.maximum(lab, floor))
    surf = store.surface[jnp.minimum(tgt, s - 1)] & ~low
    store = store.replace(pairs=store.pairs.at[tgt].set(pairs, mode="drop"),
                          surface=store.surface.at[tgt].set(surf, mode="drop"))
    raised = ev.raised.at[jnp.where(rows < v, rows, v)].set(True, mode="drop")
    return ev.replace(raised=raised), store, jnp.sum(rows < v, dtype=jnp.int32)
