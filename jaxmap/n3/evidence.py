"""Free-space evidence that persists: per leaf voxel, how many frames saw it free since it was last hit.

DUFOMap's idea on the N3 map's voxels. Every frame tests the allocated leaf voxels within
`evidence.max_range_m` of the sensor (the window's and those that left it) against the scan's range
image (`jaxmap.range_image`, built from the whole raw scan, not the training crop), those whose own pixel
lets them be free (`may_be_free`, one lookup: about a fifth of them) with their whole footprint:

  seen free  every return whose ray passes through the voxel lies beyond the voxel's far side by
             `margin` (pose and range error): the sensor looked through the whole voxel. Its footprint
             (`footprint_nearest`): in azimuth the columns within asin(r_v / d) of the centre's direction
             plus half a column (d its distance, r_v the half-diagonal), in elevation the sensor's own
             beams that bracket that angle; one reaching beyond the field of view is never free. Empty
             pixels: one with a return above it in its column is a dropout (a dark or wet surface,
             grazing incidence) and blocks, taking the nearest return within DROPOUT_ROWS rows of it in
             its column, range 0 when there is none (`dropouts_block`); one with nothing above it (the
             sky, nothing within range) stays empty: it frees nothing by itself (a footprint without any
             return is never free) and blocks nothing (a footprint's nearest is that of its returns).
  hit        a scan point of this frame lies in the voxel.

`free_run` counts the frames that saw the voxel free since its last hit (a hit resets it), and a voxel
with `free_run >= void_frames` is *void*: something was there and left (a car, a pedestrian), or was
never there (a mixed pixel's veil). Then (`update`, in the frame program; `jaxmap.n3.integrate`):
  - scan points that land in a void voxel get no training samples: they are on something that moves
    (their hit still resets the voxel, so a car that parks is trained from its second frame on);
  - the pairs stored in a voxel when it turns void are raised to at least `margin` (no surface closer
    than that was seen from any ray through it): the field there turns positive (`raise_void_pairs`);
  - the map's queries and its mesh are invalid in void voxels (`jaxmap.n3.query`), also after the voxel
    left the training window: the evidence is per voxel row, and lives as long as the map.

The footprint test never frees a voxel that holds or touches a surface a ray saw: the surface's own
return, or a neighbouring pixel's, lies within the voxel or the margin. A wall seen at grazing incidence
is hit by the beams below the one that passes over it, and those are in the footprint.
"""
from __future__ import annotations

import functools
import logging
import math
from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from jaxmap import range_image as ri
from jaxmap.grid.compaction import nonzero_fixed, nonzero_from
from jaxmap.n3 import window

log = logging.getLogger(__name__)

RUN_CAP = 1 << 14          # free_run saturates here (int32; a voxel seen free for ever stays void)
RAISE_PER_FRAME = 4096     # voxels whose pairs are raised per frame (the rest next frame: `raised` says)
TESTED_PER_FRAME = 1 << 16  # voxels tested against a frame's range image at most (those within
                            # `evidence.max_range_m` that `may_be_free` lets through: 18-31 k of 105-122 k on
                            # the city and the traffic street; when more are, a different part of them each frame,
                            # and the frame's `Counts.untested` says how many waited)


@flax.struct.dataclass
class Evidence:
    free_run: jax.Array   # [V] int32 frames that saw the voxel free since its last hit
    raised: jax.Array     # [V] bool its stored pairs were raised once it turned void (cleared by a hit)


class Counts(NamedTuple):
    """A frame's evidence in numbers (its `FrameStats`)."""

    free: jax.Array       # [] int32 voxels seen free (and not hit)
    raised: jax.Array     # [] int32 voxels whose stored pairs were raised (they turned void)
    untested: jax.Array   # [] int32 voxels in range that `may_be_free` let through beyond TESTED_PER_FRAME
                          # (not tested this frame: the next frames test them, `candidates`)


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


# -------------------------------------------------------------------------------------------------
# footprints: the nearest return within a window around each pixel of the range image
# -------------------------------------------------------------------------------------------------

FOOTPRINTS = (1, 2, 3, 4, 6, 8, 11, 16, 23, 32)   # window half-widths, in pixels of the coarser axis


def footprint_windows(layout: ri.Layout) -> tuple:
    """((rows, cols) half-widths in pixels, ...) of the footprint levels: level j spans at least
    FOOTPRINTS[j] * s radians on both axes, s the larger of the row and column steps."""
    s = max(layout.elev_step, layout.col_step)
    return tuple((int(math.ceil(k * s / layout.elev_step - 1e-6)), int(math.ceil(k * s / layout.col_step - 1e-6)))
                 for k in FOOTPRINTS)


def _window_min(img, k: int, axis: int, xp):
    """min over [c - k, c + k] along `axis` (columns wrap; rows are padded by the caller) by a sparse
    table: two overlapping windows of 2^p cells."""
    d = (1, 0) if axis == 0 else (0, 1)
    length = 2 * k + 1
    table = img
    p = 0
    while (2 << p) <= length:
        table = xp.minimum(table, ri.neighbour(table, (1 << p) * d[0], (1 << p) * d[1], xp))
        p += 1
    a = -k
    b = k - (1 << p) + 1
    return xp.minimum(ri.neighbour(table, a * d[0], a * d[1], xp), ri.neighbour(table, b * d[0], b * d[1], xp))


DROPOUT_ROWS = 2   # a dropout takes the nearest return this many rows above or below it in its column


def dropouts_block(image, layout: ri.Layout, xp=np):
    """The range image [rows, cols] with its dropouts filled for the free-space test. An empty pixel with a
    return anywhere above it in its column is a dropout (a dark or wet surface, grazing incidence): the
    ray above it met something, so this one, pointing lower, met something too, not free space. It takes
    the nearest return within DROPOUT_ROWS rows of it in its column (the rays just above and below met the
    surface it lost), range 0 (blocking) when there is none. An empty pixel with nothing above it (the
    sky, or nothing within range along an open street: the rays that free the voxels a car left) stays
    inf. Without this the rays beside a lost return, which went farther, free the voxel it would have
    hit: the ground and dark cars of the suite's artifact city lose their voxels."""
    finite = xp.isfinite(image)
    above = xp.cumsum(finite[::-1].astype(xp.int32), axis=0)[::-1] - finite.astype(xp.int32) > 0
    near = _window_min(image, DROPOUT_ROWS, 0, xp)
    fill = xp.where(xp.isfinite(near), near, xp.zeros((), image.dtype))
    return xp.where(above & ~finite, fill, image)


def min_pool_levels(image, layout: ri.Layout, xp=np):
    """[len(FOOTPRINTS), rows, cols]: level j holds at each pixel the nearest return within its window
    (`footprint_windows`). Columns wrap around (a full turn); rows beyond the image count as a return at
    range 0 (outside the sensor's field of view nothing is seen, so a window reaching there is never free)."""
    wins = footprint_windows(layout)
    pad = max(kr for kr, _ in wins) + 1
    rows = image.shape[0]
    unseen = xp.zeros((pad, image.shape[1]), image.dtype)
    padded = xp.concatenate([unseen, image, unseen])
    out = []
    for kr, kc in wins:
        by_rows = _window_min(padded, kr, 0, xp)[pad:pad + rows]
        out.append(_window_min(by_rows, kc, 1, xp))
    return xp.stack(out)


def level_for(half_angle, layout: ri.Layout, xp=np):
    """Index into FOOTPRINTS of the smallest window whose every ray lies within `half_angle` radians of a
    direction, plus half a pixel (where the direction falls in its pixel); len(FOOTPRINTS) when none
    (a uniform grid's footprints, `min_pool_levels`)."""
    s = max(layout.elev_step, layout.col_step)
    need = half_angle / s + 0.5
    radii = xp.asarray(FOOTPRINTS, xp.float32)
    return xp.sum(need[..., None] > radii, axis=-1).astype(xp.int32)


def _powers(n: int) -> int:
    """How many spans 2^p (p = 0, 1, ...) a sparse table over n cells holds: the largest is at most n."""
    return int(n).bit_length()


def footprint_levels(image, layout: ri.Layout, xp=np):
    """The range image [rows, cols] ready for `footprint_nearest`: a uniform grid's `min_pool_levels`
    [L, rows, cols]; with a beam table a sparse table [P, Q, rows, cols]: at [p, q, r, c] the nearest
    return in the 2^p rows (beams) from r and the 2^q columns from c (wrapping). Any window of beams and
    columns is then four overlapping lookups, so a footprint takes exactly the beams that bracket it
    (Q: up to the widest column window, `footprint_windows`)."""
    if not layout.beams:
        return min_pool_levels(image, layout, xp)
    widest = 2 * footprint_windows(layout)[-1][1] + 1
    by_cols = [image]
    for q in range(1, _powers(min(widest, layout.cols))):
        by_cols.append(xp.minimum(by_cols[-1], ri.neighbour(by_cols[-1], 0, 1 << (q - 1), xp)))
    out = []
    for t in by_cols:
        tables = [t]
        for p in range(1, _powers(layout.rows)):
            t = xp.minimum(t, ri.neighbour(t, 1 << (p - 1), 0, xp))
            tables.append(t)
        out.append(xp.stack(tables))
    return xp.stack(out, axis=1)


def _floor_log2(n, powers: int, xp):
    """[N] int32 floor(log2 n) of spans n [N] >= 1 (at most 2^powers - 1)."""
    return sum((n >= (1 << k)).astype(xp.int32) for k in range(1, powers))


def footprint_nearest(levels, layout: ri.Layout, points_s, half_size: float, xp=np):
    """The nearest return among the rays that pass a sphere of radius half_size around each of points_s
    [T, 3] (sensor frame): its footprint. Returns (nearest [T] float32 (inf: no return there), ok [T] bool:
    the footprint lies inside the image and a window covers it, distance [T] float32).

    levels: `footprint_levels` of the scan's image. Columns: the smallest window covering the sphere's
    angular radius plus half a pixel. Rows, with a beam table: the beams from the last one at or below the
    sphere to the first one at or above it (the beams that bracket it: with beams several degrees apart a
    small voxel lies between two of them, and a ray that passes beside it says nothing of it, while the
    beam below, which meets the ground before it, does), counted in beams whatever their spacing; a
    footprint whose bracket leaves the image is never ok. A uniform grid: `level_for`'s square window."""
    el, az, dist = ri.angles(points_s, xp)
    half_angle = xp.arcsin(xp.clip(half_size / xp.maximum(dist, 1e-3), 0.0, 1.0))
    col = xp.floor((az - layout.az0) / layout.col_step).astype(xp.int32) % layout.cols
    n_lv = len(FOOTPRINTS)
    if not layout.beams:
        row, inside = ri.rows_of(el, layout, xp)
        lv = level_for(half_angle, layout, xp)
        return levels[xp.minimum(lv, n_lv - 1), row, col], inside & (lv < n_lv), dist.astype(xp.float32)
    kc = xp.asarray([k for _, k in footprint_windows(layout)], xp.int32)
    lv = xp.sum((half_angle / layout.col_step + 0.5)[..., None] > kc, axis=-1).astype(xp.int32)
    beams = xp.asarray(layout.beams, el.dtype)
    lo = xp.searchsorted(beams, el - half_angle, side="right").astype(xp.int32) - 1   # last beam at or below
    hi = xp.searchsorted(beams, el + half_angle, side="left").astype(xp.int32)        # first beam at or above
    ok = (lv < n_lv) & (lo >= 0) & (hi < layout.rows)
    lo = xp.clip(lo, 0, layout.rows - 1)
    hi = xp.clip(hi, lo, layout.rows - 1)
    p = _floor_log2(hi - lo + 1, _powers(layout.rows), xp)
    top = hi + 1 - xp.left_shift(xp.ones_like(p), p)
    # the column window c +- k (at most the whole turn: a sparse table's two lookups cover any span <= cols)
    half_cols = xp.minimum(kc[xp.minimum(lv, n_lv - 1)], (layout.cols - 1) // 2)
    q = _floor_log2(2 * half_cols + 1, levels.shape[1], xp)
    left = (col - half_cols) % layout.cols
    right = (col + half_cols + 1 - xp.left_shift(xp.ones_like(q), q)) % layout.cols
    nearest = xp.minimum(xp.minimum(levels[p, q, lo, left], levels[p, q, lo, right]),
                         xp.minimum(levels[p, q, top, left], levels[p, q, top, right]))
    return nearest, ok, dist.astype(xp.float32)


def may_be_free(voxel_coord, leaf: float, blocked, layout: ri.Layout, rotation, translation, margin: float,
                min_range: float):
    """[V] bool: the voxels (leaf-voxel coordinates [V, 3] int32, map frame) `seen_free` may find free this
    frame, at a fraction of its cost: one pixel instead of a footprint. The pixel of the voxel's centre is
    in its footprint, so where that pixel's return (blocked: the range image with its dropouts blocking,
    `dropouts_block`) is not beyond the voxel's far side by `margin`, neither is the footprint's
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
    levels: `footprint_levels` of the frame's range image; rotation [3, 3] R_map_sensor and
    translation [3] the sensor's pose in the map frame."""
    centre = (voxel_coord.astype(jnp.float32) + 0.5) * leaf - translation             # [T, 3] map frame
    # R^T c elementwise, not a matmul: a GPU's float32 matmul may round through TF32 (centimetres at 50 m)
    p_s = jnp.sum(centre[:, :, None] * rotation[None], axis=1)                        # [T, 3] sensor frame
    half = leaf * math.sqrt(3.0) / 2.0
    nearest, ok, dist = footprint_nearest(levels, layout, p_s, half, jnp)
    ok = ok & (dist > max(min_range, half + margin))
    return ok & jnp.isfinite(nearest) & (nearest > dist + half + margin)


def candidates(voxel_coord, n_voxels, leaf: float, sensor, max_range: float, frame, maybe=True,
               cap: int = TESTED_PER_FRAME):
    """The voxel rows a frame tests: those within max_range of the sensor (map frame) that `maybe` ([V]
    bool, `may_be_free`) lets through, at most `cap` of them, counted from row (frame * cap) mod V (frame: a
    traced int): when more voxels are in range, the next frame starts where this one's rows would end, so
    every one is tested every few frames. Returns (rows [cap] int32 (V: none), [] int32 voxels in range and
    let through that this frame does not test)."""
    v = voxel_coord.shape[0]
    d = (voxel_coord.astype(jnp.float32) + 0.5) * leaf - sensor
    near = (jnp.sum(d * d, axis=1) <= max_range * max_range) & (jnp.arange(v, dtype=jnp.int32) < n_voxels) & maybe
    size = min(cap, v)
    offset = (frame * cap) % v
    return nonzero_from(near, size, offset), jnp.maximum(jnp.sum(near, dtype=jnp.int32) - size, 0)


def observe(ev: Evidence, rows, free, hit, apply) -> Evidence:
    """This frame's evidence: hit [V] bool resets, free [T] bool of voxel rows [T] (V: none; and not hit)
    counts; apply [] bool (the frame went in: a failed pass changes nothing)."""
    v = ev.free_run.shape[0]
    seen = jnp.zeros((v,), bool).at[jnp.where(free & apply, rows, v)].set(True, mode="drop")
    run = jnp.where(hit, 0, jnp.where(seen, jnp.minimum(ev.free_run + 1, RUN_CAP), ev.free_run))
    return Evidence(free_run=jnp.where(apply, run, ev.free_run), raised=ev.raised & ~(hit & apply))


def raise_void_pairs(ev: Evidence, store, void_frames: int, floor: float, apply, cap: int = RAISE_PER_FRAME):
    """Raise the labels of the pairs stored in voxels that turned void to at least `floor`
    (`window.raise_labels`): at most `cap` voxels a frame, the first in row order; `raised` remembers which
    are done, so the rest are raised on the next frames. Returns (evidence, store, [] int32 voxels raised)."""
    v = ev.free_run.shape[0]
    todo = void(ev, void_frames) & ~ev.raised & apply
    rows = nonzero_fixed(todo, cap, v)                                           # [C] (v: none)
    store = window.raise_labels(store, rows, floor)
    raised = ev.raised.at[jnp.where(rows < v, rows, v)].set(True, mode="drop")
    return ev.replace(raised=raised), store, jnp.sum(rows < v, dtype=jnp.int32)


@functools.partial(jax.named_call, name="evidence")
def update(static, ev: Evidence, store, scan, point_rows, voxel_coord, n_voxels, frame, ok):
    """A frame's free-space evidence, inside its program (static: the `N3Static`; scan: its `ScanBatch` with
    the whole scan's range image): the voxels its range image saw free count one more frame, the voxels its
    points hit (point_rows [N] int32 voxel rows, -1: none; those dropped as void too) start again; the pairs
    of voxels that turned void are raised (`raise_void_pairs`). Nothing changes when ok [] is False (the
    pass is retried). Returns (evidence, store, `Counts`)."""
    v = ev.free_run.shape[0]
    hit = jnp.zeros((v,), bool).at[jnp.where(point_rows >= 0, point_rows, v)].set(True, mode="drop")
    with jax.named_scope("image"):
        blocked = dropouts_block(scan.image, static.image, jnp)
        levels = footprint_levels(blocked, static.image, jnp)
    with jax.named_scope("candidates"):
        maybe = may_be_free(voxel_coord, static.leaf, blocked, static.image, scan.rotation, scan.sensor,
                            static.evidence_margin, static.free_min_range)
        rows, untested = candidates(voxel_coord, n_voxels, static.leaf, scan.sensor, static.evidence_range, frame,
                                    maybe)
    with jax.named_scope("test"):
        coords = voxel_coord[jnp.minimum(rows, v - 1)]
        free = (rows < v) & seen_free(coords, static.leaf, levels, static.image, scan.rotation, scan.sensor,
                                      static.evidence_margin, static.free_min_range)
    with jax.named_scope("observe"):
        ev = observe(ev, rows, free, hit, ok)
    n_raised = jnp.zeros((), jnp.int32)
    if static.raise_pairs and not static.uses_pool:
        with jax.named_scope("raise"):
            ev, store, n_raised = raise_void_pairs(ev, store, static.void_frames, static.evidence_margin, ok)
    n_free = jnp.sum(free & ~hit[jnp.minimum(rows, v - 1)], dtype=jnp.int32)
    return ev, store, Counts(free=n_free, raised=n_raised, untested=untested)


@functools.lru_cache(maxsize=None)
def warn_without_layout(static) -> None:
    """Say (once per `N3Static`, when its frame program is built) that evidence.enabled is on but the map
    runs without it: the scans' range-image layout was not known (`N3Static.evidence` is False)."""
    log.warning("evidence.enabled is true, but the scans' range-image layout is not known (preprocess.image_rows "
                "0): this frame program maps without free-space evidence. Let the mapper read the layout off the "
                "first raw scan (N3Mapper's first_scan, add_frame of raw points, jaxmap.n3.scan.resolve_layout), "
                "set preprocess.image_rows, image_cols, image_elev0_deg and image_elev_step_deg, or set "
                "evidence.enabled=false")
