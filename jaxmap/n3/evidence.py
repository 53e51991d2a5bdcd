"""Free-space evidence that persists: per leaf voxel, how many frames saw it free since it was last hit.

DUFOMap's idea on the N3 map's voxels. Every frame tests every allocated leaf voxel against the scan's
range image (`jaxmap.range_image`, built from the whole raw scan, not the training crop):

  seen free  every return whose ray passes through the voxel (its footprint: the pixels within
             asin(r_v / d) of the centre's direction, d its distance, r_v the half-diagonal, plus half a
             pixel) lies beyond the voxel's far side by `margin` (pose and range error): the sensor looked
             through the whole voxel. A footprint without any return (sky, dropouts, beyond the sensor's
             range) says nothing; one reaching beyond the field of view is never free.
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
from jaxmap.grid.compaction import nonzero_fixed

RUN_CAP = 1 << 14          # free_run saturates here (int32; a voxel seen free for ever stays void)
RAISE_PER_FRAME = 4096     # voxels whose pairs are raised per frame (the rest next frame: `raised` says)


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


def seen_free(voxel_coord, n_voxels, leaf: float, levels, layout: ri.Layout, rotation, translation,
              margin: float, min_range: float):
    """[V] bool: voxels (rows < n_voxels, leaf-voxel coordinates [V, 3] int32 in the map frame) that this
    frame saw free. levels: `range_image.min_pool_levels` of the frame's range image [L, H, W];
    rotation [3, 3] R_map_sensor and translation [3] the sensor's pose in the map frame."""
    v = voxel_coord.shape[0]
    centre = (voxel_coord.astype(jnp.float32) + 0.5) * leaf - translation             # [V, 3] map frame
    # R^T c elementwise, not a matmul: a GPU's float32 matmul may round through TF32 (centimetres at 50 m)
    p_s = jnp.sum(centre[:, :, None] * rotation[None], axis=1)                        # [V, 3] sensor frame
    row, col, dist, inside = ri.pixels(p_s, layout, jnp)
    half = leaf * math.sqrt(3.0) / 2.0
    ang = jnp.arcsin(jnp.clip(half / jnp.maximum(dist, 1e-3), 0.0, 1.0))
    lv = ri.level_for(ang, layout, jnp)
    n_lv = len(ri.FOOTPRINTS)
    ok = inside & (lv < n_lv) & (dist > max(min_range, half + margin)) & (jnp.arange(v, dtype=jnp.int32) < n_voxels)
    nearest = levels[jnp.minimum(lv, n_lv - 1), row, col]   # [V]
    return ok & jnp.isfinite(nearest) & (nearest > dist + half + margin)


def observe(ev: Evidence, free, hit, apply) -> Evidence:
    """This frame's evidence: hit [V] bool resets, free [V] bool (and not hit) counts; apply [] bool (the
    frame went in: a failed pass changes nothing)."""
    run = jnp.where(hit, 0, jnp.where(free, jnp.minimum(ev.free_run + 1, RUN_CAP), ev.free_run))
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
