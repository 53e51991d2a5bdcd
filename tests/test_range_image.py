"""The scan's range image (`jaxmap.range_image`): the layout read off a raw scan, the nearest return per
pixel, and the veil filter that drops mixed pixels and isolated returns."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmap import range_image as ri
from jaxmap.synth.city import beam_directions

BEAMS, STEPS = 32, 512


def _scan(t_of_dirs, beams=BEAMS, steps=STEPS):
    """Points [N, 3] of a LiDAR at the origin whose ray d travels t_of_dirs(d) (inf: no return)."""
    d = beam_directions(beams, steps)
    t = t_of_dirs(d)
    ok = np.isfinite(t)
    return (d[ok] * t[ok, None]).astype(np.float32), d, t


def _two_walls(d, near_x=6.0, near_y=(-1.0, 1.0), far_x=12.0):
    """A wall x = far_x behind a narrower wall x = near_x spanning near_y (both 10 m tall), and the ground
    1.7 m below the sensor."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[:, 2] < -1e-6, -1.7 / d[:, 2], np.inf)
        tf = np.where(d[:, 0] > 1e-6, far_x / d[:, 0], np.inf)
        tn = np.where(d[:, 0] > 1e-6, near_x / d[:, 0], np.inf)
        yn = tn * d[:, 1]
        tn = np.where((yn >= near_y[0]) & (yn <= near_y[1]), tn, np.inf)
    return np.minimum(t, np.minimum(tf, tn))


def test_layout_is_read_off_the_beams_and_azimuth_steps():
    """A 32 x 512 LiDAR (beams from -25 to +2 degrees) gives 32 rows of its beam spacing and 512 columns,
    every return lands in its own beam's row and azimuth step's column, and one pixel holds one return."""
    pts, d, t = _scan(_two_walls)
    lay = ri.estimate_layout(pts)
    assert (lay.rows, lay.cols) == (BEAMS, STEPS)
    assert math.isclose(math.degrees(lay.elev_step), 27.0 / (BEAMS - 1), rel_tol=1e-3)
    row, col, rng, inside = ri.pixels(pts, lay)
    ok = np.isfinite(t)
    beam = np.repeat(np.arange(BEAMS), STEPS)[ok]
    step = np.tile(np.arange(STEPS), BEAMS)[ok]
    assert inside.all() and np.array_equal(row, beam)
    # columns are the azimuth steps up to a fixed rotation (column 0 starts at -pi)
    assert len(np.unique((col - step) % STEPS)) == 1
    img = ri.min_range_image(pts, lay)
    assert np.isfinite(img).sum() == len(pts)
    np.testing.assert_allclose(img[row, col], rng, rtol=1e-6)
    # the same on the device
    img_j = ri.min_range_image_jax(jnp.asarray(pts), jnp.ones(len(pts), bool), lay)
    np.testing.assert_array_equal(np.asarray(img_j), img)


def test_layout_of_a_sensor_without_beams_is_a_uniform_grid_at_its_sampling():
    """40,000 returns in random directions (no beams): a uniform grid whose step, on both axes, is the median
    angle between a return and its nearest neighbour (brute force here: 0.0043 rad, 1,437 columns), whose
    rows span every return, and whose pixels hold about one return each (measured 1.12 per occupied pixel;
    a grid twice as coarse holds ~4, four times as coarse ~16, and its footprints blur what a pixel saw)."""
    rng = np.random.default_rng(0)
    u = rng.normal(size=(40000, 3))
    u[:, 2] = np.abs(u[:, 2]) * 0.3
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    lay = ri.estimate_layout(u * 10.0)
    assert not lay.beams
    sub = u[:1000]
    ang = np.arccos(np.clip(sub @ u.T, -1.0, 1.0))
    ang[np.arange(len(sub)), np.arange(len(sub))] = np.inf
    nn = float(np.median(ang.min(axis=1)))
    assert abs(lay.elev_step / nn - 1) < 0.1 and abs(lay.col_step / nn - 1) < 0.1, (lay.elev_step, lay.col_step, nn)
    assert lay.cols <= ri.MAX_COLS
    row, col, _, inside = ri.pixels((u * 10.0).astype(np.float32), lay)
    assert inside.all()
    per_pixel = np.bincount(row * lay.cols + col)
    assert per_pixel[per_pixel > 0].mean() < 1.3, per_pixel[per_pixel > 0].mean()
    with pytest.raises(ValueError, match="too small"):
        ri.estimate_layout(u[:50] * 10.0)


def _mixed(pts_d_t, p=1.0, seed=0, jump=0.3):
    """The scan with the synthetic city's mixed pixels: a return whose azimuth neighbour (same beam) lies
    more than `jump` away gets a range uniform between the two, with probability p. Returns (points,
    is_mixed [N] bool, gap [N]: the mixed return's distance to the nearer of the two surfaces)."""
    _, d, t = pts_d_t
    G = t.reshape(BEAMS, STEPS).copy()
    ok = np.isfinite(G)
    rng = np.random.default_rng(seed)
    best, other = np.zeros(G.shape), G.copy()
    for shift in (1, -1):
        Gn, okn = np.roll(G, shift, axis=1), np.roll(ok, shift, axis=1)
        diff = np.where(ok & okn, np.abs(np.where(okn, Gn, 0) - np.where(ok, G, 0)), 0.0)
        take = diff > best
        best, other = np.where(take, diff, best), np.where(take, Gn, other)
    mix = (best > jump) & (rng.random(G.shape) < p)
    lo, hi = np.minimum(G, other), np.maximum(G, other)
    w = rng.uniform(0.0, 1.0, G.shape)
    with np.errstate(invalid="ignore"):
        G = np.where(mix, lo + w * (hi - lo), G)
        gap = np.where(mix, np.minimum(G - lo, hi - G), 0.0)
    t2 = G.reshape(-1)
    keep = np.isfinite(t2)
    return (d[keep] * t2[keep, None]).astype(np.float32), mix.reshape(-1)[keep], gap.reshape(-1)[keep]


def test_veil_filter_drops_mixed_pixels_between_two_walls_and_keeps_the_walls():
    """Mixed pixels at both edges of a near wall in front of a far one (and where its foot meets the ground):
    the veil test drops >= 95 % of those farther than 0.5 m from both surfaces (nearer ones, on a grazing
    surface where neighbouring returns differ by more than 0.3 m, lie on that surface), and
    keeps >= 99.5 % of the true returns of both walls and the ground. Dropping every return that differs from a neighbour by more
    than 0.3 m (a plain jump test) would drop the near wall's edges and the far wall beside them: it fails
    the second bound."""
    clean = _scan(_two_walls)
    pts, is_mixed, gap = _mixed(clean)
    lay = ri.estimate_layout(clean[0])
    keep = ri.veil_keep(pts, lay, tol_m=0.15)
    veil = is_mixed & (gap > 0.5)
    assert veil.sum() > 50
    assert keep[veil].mean() <= 0.05, keep[veil].mean()
    assert keep[~is_mixed].mean() >= 0.995, keep[~is_mixed].mean()
    # the plain jump test the bound rules out
    img = ri.min_range_image(pts, lay)
    row, col, rng, _ = ri.pixels(pts, lay)
    jumpy = np.zeros(len(pts), bool)
    for dc in (-1, 1):
        nb = np.roll(img, -dc, axis=1)[row, col]
        jumpy |= np.isfinite(nb) & (np.abs(nb - rng) > 0.3)
    assert (~jumpy)[~is_mixed].mean() < 0.995
    # the device's filter is the host's
    keep_j = jax.jit(lambda p: ri.veil_keep(p, lay, 0.15, valid=jnp.ones(p.shape[0], bool), xp=jnp))(pts)
    np.testing.assert_array_equal(np.asarray(keep_j), keep)


def _corridor(d):
    """Ranges [R] of directions d [R, 3]: the ground 1.7 m below and walls 3 m to both sides, up to 40 m."""
    with np.errstate(divide="ignore"):
        t = np.where(d[:, 2] < -1e-6, -1.7 / d[:, 2], np.inf)
        t = np.minimum(t, np.where(np.abs(d[:, 1]) > 1e-6, 3.0 / np.abs(d[:, 1]), np.inf))
    return np.where(t < 40.0, t, np.inf)


def test_veil_filter_keeps_grazing_surfaces_and_drops_isolated_returns():
    """A wall along the drive seen at grazing incidence (ranges rising steadily along each beam) and 2 cm
    range noise: >= 99.5 % kept. Returns moved to random ranges (the synthetic LiDAR's outliers) are
    dropped (>= 90 %)."""
    pts, d, t = _scan(_corridor)
    rng = np.random.default_rng(3)
    r = np.linalg.norm(pts, axis=1)
    noisy = pts * ((r + rng.normal(0, 0.02, len(r))) / r)[:, None]
    lay = ri.estimate_layout(pts)
    assert ri.veil_keep(noisy.astype(np.float32), lay, 0.15).mean() >= 0.995
    out = rng.random(len(pts)) < 0.01
    far = noisy.copy()
    far[out] = (pts[out] / r[out, None] * rng.uniform(0.5, 40.0, (out.sum(), 1))).astype(np.float32)
    # (a random range within the tolerance of the true one is no outlier)
    real = out & (np.abs(np.linalg.norm(far, axis=1) - r) > 0.5)
    keep = ri.veil_keep(far.astype(np.float32), lay, 0.15)
    assert keep[real].mean() <= 0.1, keep[real].mean()
    assert keep[~out].mean() >= 0.99


def test_veil_filter_keeps_a_grazing_surface_that_lost_most_of_its_returns():
    """The corridor at grazing incidence with 2 cm noise, and 70 % of the returns beyond 10 m lost (a real
    LiDAR's dropouts there): >= 85 % of the returns left are kept (measured 88.9 %), as the first returns past
    the lost ones predict them (`GAP_PIXELS`); with only the direct neighbours (GAP_PIXELS = 1: 77.8 %) fewer are."""
    pts, d, t = _scan(_corridor)
    rng = np.random.default_rng(5)
    r = np.linalg.norm(pts, axis=1)
    noisy = (pts * ((r + rng.normal(0, 0.02, len(r))) / r)[:, None]).astype(np.float32)
    lay = ri.estimate_layout(pts)
    left = noisy[~((r > 10.0) & (rng.random(len(r)) < 0.7))]
    far = np.linalg.norm(left, axis=1) > 10.0
    kept = ri.veil_keep(left, lay, 0.15)
    assert kept[far].mean() >= 0.85, kept[far].mean()
    try:
        gap, ri.GAP_PIXELS = ri.GAP_PIXELS, 1
        assert ri.veil_keep(left, lay, 0.15)[far].mean() < kept[far].mean() - 0.05
    finally:
        ri.GAP_PIXELS = gap
