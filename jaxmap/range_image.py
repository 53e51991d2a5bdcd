"""A spinning LiDAR's scan as its organised range image: rows by elevation, columns by azimuth.

    layout = estimate_layout(points_s)              # once, from the first raw scan (sensor frame)
    row, col, rng, inside = pixels(points_s, layout) # numpy or jax.numpy (xp=jnp)
    image = min_range_image(points_s, layout)        # [H, W] float32, inf where no return
    keep = veil_keep(points_s, layout, tol_m=0.15)   # mixed pixels and isolated returns dropped

No ring field is needed: a spinning LiDAR fires each beam at a fixed elevation, so the elevations of one
scan fall into as many tight clusters as it has beams, and its azimuth steps are regular. The layout is
read off those (`estimate_layout`): the sensor's beam table (each cluster's centre), one row per beam
(a return belongs to the nearest beam: row boundaries halfway between neighbouring beams, however
unevenly the sensor spaces them: KITTI's HDL-64E has two blocks 0.33 and 0.5 deg apart, a VLP-32C
beams 0.33 deg apart at the horizon and up to 9 deg apart below), and one column per azimuth step.
Neighbours (and the free-space evidence's footprints, `jaxmap.n3.evidence`) are counted in beams, never in
a uniform angle. A sensor without beams (a depth camera, a solid-state LiDAR) gets a uniform spherical grid
at its angular sampling. Pixels with several returns keep the nearest (`min`); pixels without a return
are `inf`: nothing is known there.

Everything is in the sensor frame (x forward, z up): elevation = atan2(z, |xy|), azimuth = atan2(y, x).
The functions take `xp` (numpy or jax.numpy) where both sides need them: the host preprocesses with
numpy, the frame program (`preprocess.device`, the N3 map's free-space evidence) with jax.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

BEAM_GAP_RAD = math.radians(0.08)   # elevations further apart than this are different beams
MIN_RANGE_M = 0.5                    # returns nearer than this say nothing of the layout (the ego vehicle)
MAX_ROWS, MAX_COLS = 512, 4096


@dataclasses.dataclass(frozen=True)
class Layout:
    """The pixel grid of a range image (hashable: a static argument of compiled programs).

    rows, cols: image size; cols span the full turn, column c covering azimuths [az0 + c w, az0 + (c+1) w)
    (mod 2 pi), w = 2 pi / cols: az0 puts the first scan's azimuth steps at the columns' centres.
    beams: a spinning LiDAR's beam table, the elevations (radians, ascending) of its `rows` beams: row r
    holds the elevations nearer to beam r than to its neighbours (the outer rows reach half their gap
    beyond the outer beams). Empty for a uniform grid (a sensor without beams): row r covers
    [elev0 + r elev_step, elev0 + (r+1) elev_step). elev0 / elev_step: with beams, the lower edge of
    row 0 and the median gap between neighbouring beams (the scale of the footprint windows).
    """

    rows: int
    cols: int
    elev0: float
    elev_step: float
    az0: float = -math.pi
    beams: tuple = ()

    @property
    def col_step(self) -> float:
        return 2.0 * math.pi / self.cols

    @property
    def edges(self) -> tuple:
        """The rows' elevation boundaries (radians, [rows + 1], ascending)."""
        if not self.beams:
            return tuple(self.elev0 + r * self.elev_step for r in range(self.rows + 1))
        b = self.beams
        mid = tuple(0.5 * (lo + hi) for lo, hi in zip(b[:-1], b[1:]))
        first = b[0] - 0.5 * (b[1] - b[0]) if len(b) > 1 else b[0] - 0.5 * self.elev_step
        last = b[-1] + 0.5 * (b[-1] - b[-2]) if len(b) > 1 else b[0] + 0.5 * self.elev_step
        return (first,) + mid + (last,)

    def describe(self) -> str:
        e = self.edges
        kind = (f"{self.rows} beams {min(self.gaps_deg()):.3f}-{max(self.gaps_deg()):.3f} deg apart"
                if len(self.beams) > 1 else f"rows {math.degrees(self.elev_step):.3f} deg")
        return (f"{self.rows} x {self.cols} pixels, elevation {math.degrees(e[0]):.2f} to {math.degrees(e[-1]):.2f} "
                f"deg ({kind}, columns {math.degrees(self.col_step):.3f} deg)")

    def gaps_deg(self) -> list:
        """The gaps between neighbouring beams (degrees; [rows - 1])."""
        return [math.degrees(hi - lo) for lo, hi in zip(self.beams[:-1], self.beams[1:])]


def angles(points_s, xp=np):
    """(elevation [N], azimuth [N], range [N]) of sensor-frame points [N, 3]."""
    x, y, z = points_s[:, 0], points_s[:, 1], points_s[:, 2]
    horiz = xp.sqrt(x * x + y * y)
    return xp.arctan2(z, horiz), xp.arctan2(y, x), xp.sqrt(horiz * horiz + z * z)


def estimate_layout(points_s: np.ndarray) -> Layout:
    """The range-image layout of one raw scan (sensor frame, [N, 3]; the whole scan, before any crop or
    downsampling, as it left the sensor). ValueError when the scan has too few returns to tell."""
    p = np.asarray(points_s, np.float64).reshape(-1, 3)
    el, az, rng = angles(p)
    ok = np.isfinite(rng) & (rng > MIN_RANGE_M)
    el, az = el[ok], az[ok]
    if len(el) < 100:
        raise ValueError(f"a scan of {len(el)} returns beyond {MIN_RANGE_M} m is too small to read the "
                         "sensor's range-image layout from")
    order = np.argsort(el)
    e = el[order]
    cut = np.flatnonzero(np.diff(e) > BEAM_GAP_RAD) + 1
    starts, ends = np.r_[0, cut], np.r_[cut, len(e)]
    sizes = ends - starts
    # Beams hold a whole turn of returns; a cluster of a few points is a stray (an outlier, a mixed pixel).
    beams = sizes >= max(8, 0.05 * np.median(sizes))
    n_beams = int(beams.sum())
    beam_table = ()
    if 2 <= n_beams <= MAX_ROWS and n_beams >= 0.5 * len(sizes):
        centres = np.array([np.median(e[s:t]) for s, t in zip(starts[beams], ends[beams])])
        step = float(np.median(np.diff(centres)))
        rows = n_beams
        beam_table = tuple(float(c) for c in centres)
        lo = float(centres[0] - 0.5 * (centres[1] - centres[0]))
        # the azimuth step of the fullest beam: the median gap between its sorted azimuths
        s, t = starts[beams][np.argmax(sizes[beams])], ends[beams][np.argmax(sizes[beams])]
        a = np.sort(az[order[s:t]])
        gaps = np.diff(a)
        col_step = float(np.median(gaps[gaps > 1e-7])) if np.any(gaps > 1e-7) else 2 * math.pi / 1024
        phase_of = a
    else:
        # no beams: a uniform grid at the scan's angular sampling (the median angle to the nearest neighbour)
        from scipy.spatial import cKDTree

        u = p[ok] / np.linalg.norm(p[ok], axis=1, keepdims=True)
        sub = u[:: max(1, len(u) // 20000)]
        d, _ = cKDTree(u).query(sub, k=2)
        step = col_step = float(np.median(d[:, 1]))
        lo = float(e[0] - 0.5 * step)
        rows = int(math.ceil((e[-1] - e[0]) / step)) + 1
        phase_of = az[:0]
    cols = int(np.clip(round(2 * math.pi / max(col_step, 1e-6)), 16, MAX_COLS))
    if rows > MAX_ROWS:
        step = step * rows / MAX_ROWS
        rows = MAX_ROWS
    w = 2 * math.pi / cols
    # the azimuth steps' phase (a circular mean), so that they fall at the columns' centres, not on edges
    ang = (phase_of + math.pi) / w * 2 * math.pi
    phase = (math.atan2(np.sin(ang).mean(), np.cos(ang).mean()) / (2 * math.pi) * w) if len(ang) else 0.5 * w
    return Layout(rows=int(rows), cols=cols, elev0=lo, elev_step=float(step), az0=float(-math.pi + phase - 0.5 * w),
                  beams=beam_table)


def beam_layout(elevations, cols: int, az0: float = -math.pi) -> Layout:
    """The layout of a spinning LiDAR with the given beam elevations (radians, any order; >= 2 distinct)
    and `cols` azimuth steps a turn."""
    b = np.unique(np.asarray(elevations, np.float64))
    if len(b) < 2:
        raise ValueError("a beam table needs at least 2 distinct elevations")
    if len(b) > MAX_ROWS:
        raise ValueError(f"a beam table of {len(b)} beams is more than {MAX_ROWS}")
    return Layout(rows=len(b), cols=int(cols), elev0=float(b[0] - 0.5 * (b[1] - b[0])),
                  elev_step=float(np.median(np.diff(b))), az0=float(az0), beams=tuple(float(x) for x in b))


def rows_of(el, layout: Layout, xp):
    """(row [N] int32, inside [N] bool) of elevations [N] (radians): the nearest beam's row (boundaries
    halfway between beams), or the uniform grid's."""
    if layout.beams:
        e = layout.edges
        inner = xp.asarray(e[1:-1], el.dtype)
        row = xp.searchsorted(inner, el, side="right").astype(xp.int32)
        return row, (el >= e[0]) & (el < e[-1])
    rowf = xp.floor((el - layout.elev0) / layout.elev_step)
    return xp.clip(rowf, 0, layout.rows - 1).astype(xp.int32), (rowf >= 0) & (rowf < layout.rows)


def pixels(points_s, layout: Layout, xp=np):
    """(row [N] int32, col [N] int32, range [N] float32, inside [N] bool: the row is in the image) of
    sensor-frame points [N, 3]."""
    el, az, rng = angles(points_s, xp)
    row, inside = rows_of(el, layout, xp)
    col = xp.floor((az - layout.az0) / layout.col_step).astype(xp.int32) % layout.cols
    return row, col, rng.astype(xp.float32), inside


def min_range_image(points_s: np.ndarray, layout: Layout, valid: np.ndarray | None = None) -> np.ndarray:
    """[rows, cols] float32: the nearest return of each pixel, inf where none (numpy; host)."""
    row, col, rng, inside = pixels(np.asarray(points_s, np.float32), layout)
    ok = inside & np.isfinite(rng) & (rng > 0)
    if valid is not None:
        ok &= valid
    image = np.full(layout.rows * layout.cols, np.inf, np.float32)
    # the nearest of each pixel (an unbuffered minimum: numpy >= 1.25's ufunc.at is a fast loop, ~0.1 ms for
    # a 120k-return scan where sorting by pixel and range took 35 ms)
    np.minimum.at(image, row[ok].astype(np.int64) * layout.cols + col[ok], rng[ok])
    return image.reshape(layout.rows, layout.cols)


def min_range_image_jax(points_s, valid, layout: Layout):
    """`min_range_image` in jax (inside a compiled program): points_s [N, 3], valid [N] bool."""
    import jax.numpy as jnp

    row, col, rng, inside = pixels(points_s, layout, jnp)
    ok = valid & inside & jnp.isfinite(rng) & (rng > 0)
    flat = jnp.where(ok, row * layout.cols + col, layout.rows * layout.cols)
    image = jnp.full((layout.rows * layout.cols,), jnp.inf, jnp.float32).at[flat].min(rng, mode="drop")
    return image.reshape(layout.rows, layout.cols)


def neighbour(image, dr: int, dc: int, xp):
    """The image shifted so that out[r, c] = image[r + dr, c + dc]: columns wrap around (a full turn),
    rows beyond the image are inf."""
    out = xp.roll(image, -dc, axis=1) if dc else image
    if abs(dr) >= image.shape[0]:
        return xp.full(image.shape, np.inf, image.dtype)
    if dr:
        pad = xp.full((abs(dr), image.shape[1]), np.inf, image.dtype)
        out = xp.concatenate([out[dr:], pad]) if dr > 0 else xp.concatenate([pad, out[:dr]])
    return out


GAP_PIXELS = 6   # veil test: past dropped-out neighbours, the first returns this many pixels away predict a return


def row_elevations(layout: Layout) -> tuple:
    """Each row's elevation (radians, [rows]): its beam's, or the uniform row's centre."""
    if layout.beams:
        return layout.beams
    return tuple(layout.elev0 + (r + 0.5) * layout.elev_step for r in range(layout.rows))


def _offset_angle(layout: Layout, m: int, dr: int, dc: int, xp):
    """The angle (radians) from each pixel to the one m steps along (dr, dc): across the beams the
    difference of their elevations, however unevenly spaced ([rows, 1]; rows past the image take the
    last one's), along a beam m column steps (a scalar)."""
    if not dr:
        return m * dc * layout.col_step
    el = np.asarray(row_elevations(layout), np.float64)
    r = np.arange(layout.rows)
    return xp.asarray((el[np.clip(r + m * dr, 0, layout.rows - 1)] - el)[:, None], xp.float32)


def _inverse_line(a1, a2, t, xp):
    """The range at position t on the line through (0, a1) and (1, a2) in inverse range: a plane's inverse
    range is a linear function of the ray's direction, so along a column or a beam it is nearly linear in
    the angle (exact to the cosine's curvature), whatever the spacing and however the range itself curves
    (the ground's rings at range). inf where the line leaves the plane's side (a grazing plane's horizon)."""
    inv = 1.0 / a1 + (1.0 / a2 - 1.0 / a1) * t
    return xp.where(inv > 0, 1.0 / xp.where(inv > 0, inv, 1.0), xp.inf)


def _continuation(image, layout: Layout, dr: int, dc: int, xp):
    """[rows, cols]: the range each pixel's neighbour at (dr, dc) and the pixel beyond it predict there
    (inf: no neighbour). Along a beam their range line (2 a1 - a2: evenly spaced azimuths); across the
    beams their inverse ranges at the pixel's beam elevation; the neighbour's range when the pixel beyond
    it is empty."""
    a1, a2 = neighbour(image, dr, dc, xp), neighbour(image, 2 * dr, 2 * dc, xp)
    both = xp.isfinite(a1) & xp.isfinite(a2)
    if dc:
        line = 2.0 * a1 - xp.where(both, a2, 0.0)
    else:
        e1, e2 = _offset_angle(layout, 1, dr, dc, xp), _offset_angle(layout, 2, dr, dc, xp)
        step = xp.where(xp.abs(e2 - e1) > 0, e2 - e1, 1.0)
        line = _inverse_line(xp.where(both, a1, 1.0), xp.where(both, a2, 1.0), -e1 / step, xp)
    return xp.where(both, line, a1)


def _across_gap(image, raw, layout: Layout, dr: int, dc: int, xp):
    """[rows, cols], the veil test across dropouts: a surface seen at grazing incidence loses most of its
    returns, and those left lack a direct neighbour; the first returns on both sides past the lost ones
    (within GAP_PIXELS, along the beam (dc) or across the beams (dr)) predict it, by their inverse ranges
    at its angle between them, and along the beam one side alone does (its range: the ground's rings).
    Only where the sensor gave no return next to it (`raw`, the image before the veil): a mixed pixel has
    both direct neighbours, the surfaces it mixes, and one beside a mixed pixel dropped in the first pass
    is no gap. Returns the predicted range at each pixel (inf: none)."""
    def first_return(sign):
        found, ang = neighbour(image, sign * dr, sign * dc, xp), _offset_angle(layout, sign, dr, dc, xp)
        for j in range(2, GAP_PIXELS + 1):
            take = ~xp.isfinite(found)
            found = xp.where(take, neighbour(image, j * sign * dr, j * sign * dc, xp), found)
            ang = xp.where(take, _offset_angle(layout, j * sign, dr, dc, xp), ang)
        return found, ang

    (a_l, e_l), (a_r, e_r) = first_return(-1), first_return(1)
    gap = ~xp.isfinite(neighbour(raw, -dr, -dc, xp)) | ~xp.isfinite(neighbour(raw, dr, dc, xp))
    both = xp.isfinite(a_l) & xp.isfinite(a_r)
    span = xp.where(both, e_r - e_l, 1.0)
    t = xp.where(xp.abs(span) > 0, -e_l / xp.where(xp.abs(span) > 0, span, 1.0), 0.5)
    pred = xp.where(both, _inverse_line(xp.where(both, a_l, 1.0), xp.where(both, a_r, 1.0), t, xp),
                    xp.minimum(a_l, a_r) if dc else xp.inf)
    return xp.where(gap, pred, xp.inf)


def veil_keep(points_s, layout: Layout, tol_m: float, valid=None, xp=np, image=None):
    """[N] bool: the returns to keep once mixed pixels and isolated returns are dropped (the veil, or
    shadow-point, test of LiDAR pipelines, on the organised scan).

    A mixed pixel lies between a foreground and a background surface: along its beam it continues
    neither its left nor its right neighbours, and neither do the beams above and below it at its
    azimuth. A return on a real surface continues at least one side in at least one direction: the two
    pixels beyond a neighbour predict it within tol_m (`_continuation`: along a beam their range line,
    across the beams their inverse ranges extrapolated to its beam's elevation, since a plane's inverse
    range is linear in the direction; where the second pixel is empty, the neighbour's range), or, past
    dropouts, the first returns beyond them (`_across_gap`). Grazing surfaces (ranges rising steadily
    along the beam) pass; an isolated return (an outlier) has no neighbour that predicts it.

    points_s [N, 3] sensor frame (the whole raw scan: neighbours must not be cropped away); valid [N]
    bool or None; tol_m: a multiple of the range noise (0.15 m for 2 cm noise). The predictions are made
    per pixel from the image of each pixel's nearest return, and every return is tested against its
    pixel's (pixels holding several returns test each). image: that image of the `valid` returns
    [rows, cols], when the caller has built it (the free-space evidence reads the same one), else built here.
    """
    row, col, rng, inside = pixels(points_s, layout, xp)
    flat = row * layout.cols + col
    if valid is None:
        valid = xp.ones(points_s.shape[0], bool)

    def image_of(ok):
        return min_range_image(points_s, layout, ok) if xp is np else min_range_image_jax(points_s, ok, layout)

    def supported(image, raw):
        preds = [_continuation(image, layout, dr, dc, xp) for dr, dc in ((0, -1), (0, 1), (-1, 0), (1, 0))]
        preds += [_across_gap(image, raw, layout, 0, 1, xp), _across_gap(image, raw, layout, 1, 0, xp)]
        at = xp.stack(preds).reshape(len(preds), -1)[:, flat]                       # [6, N]
        ok = xp.any(xp.abs(rng[None] - at) <= tol_m, axis=0)
        # a return with no neighbour at all in its row and column says nothing against it (a lone beam hit)
        has_any = xp.zeros(image.shape, bool)
        for dr, dc in ((0, -1), (0, 1), (-1, 0), (1, 0)):
            has_any = has_any | xp.isfinite(neighbour(image, dr, dc, xp))
        return ok | ~has_any.reshape(-1)[flat] | ~inside

    # twice: a mixed pixel that a neighbouring mixed pixel happened to continue loses that support once
    # the neighbour is gone
    raw = image_of(valid) if image is None else image
    keep = valid & supported(raw, raw)
    return keep & supported(image_of(keep), raw)

