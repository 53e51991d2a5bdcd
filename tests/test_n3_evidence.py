"""Free-space evidence that persists (`jaxmap.n3.evidence`): what moved leaves no surface, also after it
left the training window; what stays (a car that parks, a wall seen only at grazing incidence) is kept."""
import logging
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from analytic_lidar import boxes_scan, pose_at
from jaxmap import range_image as ri
from jaxmap.config import load_config
from jaxmap.n3 import evidence, window
from jaxmap.n3.mapper import N3Mapper

SMALL = ["train.iters=10", "train.nv=256", "train.np_per_voxel=8", "preprocess.max_range_m=12.0",
         "preprocess.vox_down_m=0.1", "window.initial_blocks=4096", "mesh.min_component_faces=0"]
LEAVES = (4.0, 6.0, -4.5, -2.5, 0.0, 1.5)   # parked beside the path; drives off once the sensor is 12.5 m past
SPOT = (14.0, 16.0, 2.5, 4.5, 0.0, 1.5)     # a parking spot ahead: a car leaves it at frame 15, another parks
                                            # there at frame 25 (the sensor 1.5 m before it) and stays
GRAZING = (28.0, 40.0, 1.9, 2.0, 0.0, 1.0)  # a low wall along the drive, ahead: only ever seen at grazing incidence
FRAMES, STEP = 50, 0.5


def _drive(extra):
    """The sensor drives 24.5 m along the hall's axis (crop 12 m: the training window is 12 m wide) past
    the box that leaves; the box leaves once its voxels are out of the window, and the sensor looks back
    through its place for 13 more frames. Returns (mapper, face centres [F, 3] of its mesh)."""
    m = N3Mapper(load_config("configs/city.yaml", SMALL + list(extra)))
    for i in range(FRAMES):
        x = STEP * i
        boxes = [GRAZING] + ([LEAVES] if x < 18.25 else []) + ([SPOT] if i < 15 or i >= 25 else [])
        m.add_frame(boxes_scan((x, 0, 1.7), boxes, beams=64), pose_at(x))
    mesh = m.mesh(0.1)
    return m, np.asarray(mesh.vertices)[np.asarray(mesh.faces)].mean(1)


def _faces_in(c, box, z_min):
    x0, x1, y0, y1, _, z1 = box
    return int(np.sum(np.all((c > [x0 - 0.1, y0 - 0.1, z_min]) & (c < [x1 + 0.1, y1 + 0.1, z1 + 0.1]), axis=1)))


@pytest.fixture(scope="module")
def with_evidence():
    return _drive([])


@pytest.fixture(scope="module")
def without_evidence():
    return _drive(["evidence.enabled=false", "preprocess.veil_m=0"])


def test_a_car_that_left_after_its_voxels_left_the_window_leaves_no_surface(with_evidence, without_evidence):
    """Measured (10 iterations a frame): with the evidence 0 faces of the box that left above its lowest
    voxel layer (z > 0.45 m; the layer on the ground stays unseen: every footprint through it also holds
    rays that end on the ground before it); without it, the issue-21 rule (ray samples carve only the
    window's pairs) leaves the box whole: 1,000+ faces."""
    m, c = with_evidence
    assert _faces_in(c, LEAVES, 0.45) <= 10, _faces_in(c, LEAVES, 0.45)
    assert sum(t["voxels_void"] > 0 for t in m.timings) > 0
    assert all(t["voxels_untested"] == 0 for t in m.timings)   # the record counts them; here all are tested
    _, c_off = without_evidence
    assert _faces_in(c_off, LEAVES, 0.45) > 500, _faces_in(c_off, LEAVES, 0.45)


def test_a_car_that_parks_where_the_map_saw_free_space_is_kept(with_evidence):
    """A car leaves its spot and another parks there 10 frames later: the spot's voxels are void by then,
    so the second car's first scan lands in void voxels and is not trained on, but its hits reset them:
    from its next frame on it is mapped, and it ends up meshed (measured ~1,900 faces above 0.45 m)."""
    m, c = with_evidence
    assert m.timings[25]["points_void"] > 50, m.timings[25]["points_void"]
    assert all(t["points_void"] < 0.2 * m.timings[25]["points_void"] for t in m.timings[27:]), \
        [t["points_void"] for t in m.timings[25:]]
    assert _faces_in(c, SPOT, 0.45) > 800, _faces_in(c, SPOT, 0.45)


def test_static_surfaces_seen_at_grazing_incidence_are_never_void(with_evidence):
    """No voxel that holds or touches the ground, the hall's walls or the low wall seen only at grazing
    incidence (10-35 degrees) for 50 frames turns void, and the low wall's SDF is valid and near zero on
    its face."""
    m, _ = with_evidence
    st = m.state
    n = int(st.voxels.count)
    lo = np.asarray(st.voxel_coord[:n]) * 0.2 + m.origin          # voxel min corner, world frame
    hi = lo + 0.2
    eps = 1e-6
    touches = (lo[:, 2] <= eps) & (hi[:, 2] >= -eps)                                     # the ground z = 0
    touches |= (np.abs(lo[:, 1]) <= 6 + eps) & (np.abs(hi[:, 1]) >= 6 - eps)           # walls y = +-6
    g = GRAZING
    touches |= np.all((lo <= [g[1] + eps, g[3] + eps, g[5] + eps]) & (hi >= [g[0] - eps, g[2] - eps, -eps]), axis=1)
    void = evidence.void(st.evidence, m.static.void_frames)[:n]
    assert touches.sum() > 5000
    assert not np.asarray(void)[touches].any(), lo[np.asarray(void) & touches][:10]
    q = np.array([[x, 1.9, z] for x in np.arange(28.2, 35.0, 0.4) for z in (0.3, 0.6)])
    sdf, valid = m.sdf(q)
    assert valid.mean() >= 0.85 and np.abs(sdf[valid]).mean() < 0.06, (valid.mean(), sdf)


def test_footprint_rule_frees_the_air_and_never_the_ground_at_grazing_incidence():
    """`seen_free` on its own, the sensor at 20 positions along the hall: the voxels touching the ground
    (seen at grazing incidence up to 20 m) are never free; the air voxels 0.8-1.0 m up that the scan looks
    through are (>= 80 % of those 3-20 m away). A footprint of the centre's pixel alone (the nearest beam at
    its direction, no window) frees ground voxels: the window and the bracketing beams are what keep them."""
    ij = np.stack(np.meshgrid(np.arange(-20, 120), np.arange(-25, 25), indexing="ij"), -1).reshape(-1, 2)
    ground = np.concatenate([ij, np.zeros((len(ij), 1), int)], 1)                      # cubes [0, 0.2] in z
    air = np.concatenate([ij, np.full((len(ij), 1), 4)], 1)                             # cubes [0.8, 1.0]
    coords = jnp.asarray(np.concatenate([ground, air]), jnp.int32)
    lay = ri.estimate_layout(boxes_scan((0, 0, 1.7), beams=64))
    n_g = len(ground)
    centres = (np.asarray(coords[n_g:]) + 0.5) * 0.2
    ground_free = ground_free_one = air_free = air_seen = 0
    for x in np.arange(0.0, 20.0, 1.0):
        pts = boxes_scan((x, 0, 1.7), beams=64)
        padded = np.zeros((64 * 512, 3), np.float32)
        padded[:len(pts)] = pts
        valid = np.arange(len(padded)) < len(pts)
        f = np.asarray(_free(coords, padded, valid, lay, False, np.float32(x)))
        ground_free += f[:n_g].sum()
        ground_free_one += np.asarray(_free(coords, padded, valid, lay, True, np.float32(x)))[:n_g].sum()
        d = np.linalg.norm(centres - [x, 0, 1.7], axis=1)
        look = (d < 20) & (d > 3) & (np.abs(centres[:, 1]) < 4)
        air_seen += look.sum()
        air_free += f[n_g:][look].sum()
    assert ground_free == 0, ground_free
    assert air_free >= 0.8 * air_seen, (air_free, air_seen)
    assert ground_free_one > 0


@jax.jit(static_argnums=(3, 4))
def _free(coords, pts, valid, lay, one_pixel, x):
    img = ri.min_range_image_jax(pts, valid, lay)
    sensor = jnp.stack([x, jnp.float32(0.0), jnp.float32(1.7)])
    if one_pixel:  # the planted defect: the footprint is the nearest beam's pixel at the centre's direction
        p_s = (coords.astype(jnp.float32) + 0.5) * 0.2 - sensor
        row, col, dist, inside = ri.pixels(p_s, lay, jnp)
        half = 0.2 * 3 ** 0.5 / 2
        return inside & (dist > 1.5) & (img[row, col] > dist + half + 0.1) & jnp.isfinite(img[row, col])
    levels = evidence.footprint_levels(img, lay, jnp)
    return evidence.seen_free(coords, 0.2, levels, lay, jnp.eye(3, dtype=jnp.float32), sensor, 0.1, 1.5)


def test_dropouts_never_free_the_ground():
    """A LiDAR loses returns at grazing incidence and on dark surfaces. With the empty pixels under a return
    filled from their column (`evidence.dropouts_block`, the rule) no ground voxel is seen free, both when
    half the ground returns beyond 8 m are lost at random (the air above is still seen free: measured 65 %
    of it, 100 % without dropouts) and when every ground return beyond 10 m is (a dark road). With every
    empty pixel taken as the sky, the rays of the end walls, which went farther, free the dark road's voxels."""
    ij = np.stack(np.meshgrid(np.arange(-20, 120), np.arange(-25, 25), indexing="ij"), -1).reshape(-1, 2)
    ground = np.concatenate([ij, np.zeros((len(ij), 1), int)], 1)
    air = np.concatenate([ij, np.full((len(ij), 1), 4)], 1)
    coords = jnp.asarray(np.concatenate([ground, air]), jnp.int32)
    lay = ri.estimate_layout(boxes_scan((0, 0, 1.7), beams=64))
    n_g = len(ground)
    centres = (np.asarray(coords[n_g:]) + 0.5) * 0.2
    rng = np.random.default_rng(0)
    counts = np.zeros((2, 2), int)  # [random, dark road] x [rule, sky]: ground voxels seen free
    air_free = air_seen = 0
    for x in np.arange(0.0, 20.0, 2.0):
        for case in (0, 1):
            pts = boxes_scan((x, 0, 1.7), beams=64)
            far = (pts[:, 2] < -1.65) & (np.linalg.norm(pts[:, :2], axis=1) > (8.0, 10.0)[case])
            pts = pts[~(far & (rng.random(len(pts)) < 0.5))] if case == 0 else pts[~far]
            padded = np.zeros((64 * 512, 3), np.float32)
            padded[:len(pts)] = pts
            valid = np.arange(len(padded)) < len(pts)
            for mode in (0, 1):
                f = np.asarray(_free_with_dropouts(coords, padded, valid, lay, mode == 0, np.float32(x)))
                counts[case, mode] += f[:n_g].sum()
                if case == 0 and mode == 0:
                    d = np.linalg.norm(centres - [x, 0, 1.7], axis=1)
                    look = (d < 20) & (d > 3) & (np.abs(centres[:, 1]) < 4)
                    air_seen += look.sum()
                    air_free += f[n_g:][look].sum()
    assert counts[0, 0] == 0 and counts[1, 0] == 0, counts
    assert air_free >= 0.5 * air_seen, (air_free, air_seen)
    assert counts[1, 1] > 0, counts


@jax.jit(static_argnums=(3, 4))
def _free_with_dropouts(coords, pts, valid, lay, block, x):
    img = ri.min_range_image_jax(pts, valid, lay)
    levels = evidence.footprint_levels(evidence.dropouts_block(img, lay, jnp) if block else img, lay, jnp)
    sensor = jnp.stack([x, jnp.float32(0.0), jnp.float32(1.7)])
    return evidence.seen_free(coords, 0.2, levels, lay, jnp.eye(3, dtype=jnp.float32), sensor, 0.1, 1.5)


def test_min_pool_levels_are_the_nearest_return_within_their_window():
    """Every footprint level against a brute-force window minimum: columns wrap, rows beyond the image
    count as unseen (range 0), so a window reaching past the field of view is never free."""
    rng = np.random.default_rng(1)
    lay = ri.Layout(rows=12, cols=40, elev0=-0.2, elev_step=0.02, az0=-math.pi)   # rows 0.02, cols 0.157 rad
    img = rng.uniform(1, 50, (12, 40)).astype(np.float32)
    img[rng.random(img.shape) < 0.2] = np.inf
    lv = np.asarray(jax.jit(lambda x: evidence.min_pool_levels(x, lay, jnp))(img))
    wins = evidence.footprint_windows(lay)
    assert wins[0] == (8, 1) and len(lv) == len(evidence.FOOTPRINTS)
    for j, (kr, kc) in enumerate(wins[:5]):
        ref = np.full_like(img, np.inf)
        for dr in range(-kr, kr + 1):
            for dc in range(-kc, kc + 1):
                sh = np.roll(img, -dc, axis=1)
                r = np.arange(12) + dr
                inside = (r >= 0) & (r < 12)
                sh = np.where(inside[:, None], sh[np.where(inside, r, 0)], 0.0)
                ref = np.minimum(ref, sh)
        np.testing.assert_array_equal(lv[j], ref, err_msg=f"level {kr} x {kc}")
    np.testing.assert_array_equal(evidence.min_pool_levels(img, lay)[3], lv[3])  # numpy and jax agree
    # the level a half-angle needs: its window covers it plus half a pixel on both axes
    half = np.array([0.0, 0.1, 0.3, 1.0], np.float32)
    j = evidence.level_for(half, lay)
    s = max(lay.elev_step, lay.col_step)
    for h, jj in zip(half, j):
        assert evidence.FOOTPRINTS[jj] * s >= h + 0.5 * s and (jj == 0 or evidence.FOOTPRINTS[jj - 1] * s < h + 0.5 * s)


def test_candidates_rotate_past_the_cap_until_every_voxel_in_range_is_tested():
    """More voxels in range (and let through by `may_be_free`) than a frame tests (cap 512 here,
    TESTED_PER_FRAME in the map): each frame tests `cap` of them, all in range, and counts the rest
    (`voxels_untested` in the frame's record); frame f starts at row f * cap, so frames 0 .. V / cap - 1
    test every one of them. Stuck at row 0, the same 512 would be tested every frame."""
    rng = np.random.default_rng(0)
    v, n, cap, leaf, radius = 8192, 7000, 512, 0.2, 15.0
    coord = rng.integers(-60, 60, (v, 3)).astype(np.int32)
    maybe = rng.random(v) < 0.7
    sensor = np.array([0.3, -0.2, 0.1], np.float32)
    d = (coord + 0.5) * leaf - sensor
    near = (np.sum(d * d, axis=1) <= radius * radius) & (np.arange(v) < n) & maybe
    assert near.sum() > 4 * cap
    pick = jax.jit(lambda f: evidence.candidates(jnp.asarray(coord), n, leaf, jnp.asarray(sensor), radius, f,
                                                 jnp.asarray(maybe), cap=cap))
    tested = np.zeros(v, bool)
    for f in range(v // cap):
        rows, untested = (np.asarray(x) for x in pick(jnp.int32(f)))
        assert len(np.unique(rows)) == cap and (rows < v).all() and near[rows].all()
        assert int(untested) == near.sum() - cap
        tested[rows] = True
    assert tested[near].all(), f"{(near & ~tested).sum()} of {near.sum()} voxels in range never tested"


def _void_store(v: int, p: int = 4):
    """A pair store of v voxel rows, each with a block (slots in a shuffled order) of p pairs labelled
    -0.2 .. 0.3 m, all surface samples."""
    rng = np.random.default_rng(1)
    store = window.create(v, p, v)
    slot = rng.permutation(v).astype(np.int32)
    pairs = rng.uniform(-1, 1, (v, p, 4)).astype(np.float32)
    pairs[..., 3] = rng.uniform(-0.2, 0.3, (v, p))
    return store.replace(pairs=jnp.asarray(pairs), surface=jnp.ones((v, p), bool), count=jnp.full((v,), p, jnp.int32),
                         slot_of_voxel=jnp.asarray(slot), voxel_of_slot=jnp.asarray(np.argsort(slot).astype(np.int32)))


def test_void_voxels_past_the_raise_cap_are_raised_on_the_next_frames():
    """More voxels turn void in a frame than RAISE_PER_FRAME (4,096): the first frame raises 4,096 of them,
    the next the rest, then none; every void voxel's pairs end at least `floor` (and out of the eikonal
    term where they were below it), the other voxels' pairs untouched, and a pass that did not go in
    (apply False) raises nothing."""
    cap, floor = evidence.RAISE_PER_FRAME, 0.1
    v = cap + 2000
    store0 = _void_store(v)
    is_void = np.random.default_rng(2).random(v) < 0.9                      # ~5,000 void voxels
    ev = evidence.create(v).replace(free_run=jnp.asarray(np.where(is_void, 3, 0), jnp.int32))
    step = jax.jit(lambda e, s, a: evidence.raise_void_pairs(e, s, 2, floor, a))
    _, same, none = step(ev, store0, jnp.bool_(False))
    assert int(none) == 0 and np.array_equal(np.asarray(same.pairs), np.asarray(store0.pairs))
    counts, store = [], store0
    for _ in range(3):
        ev, store, n = step(ev, store, jnp.bool_(True))
        counts.append(int(n))
    assert counts == [cap, int(is_void.sum()) - cap, 0], counts
    assert np.array_equal(np.asarray(ev.raised), is_void)
    slot = np.asarray(store0.slot_of_voxel)
    lab0, lab = np.asarray(store0.pairs)[slot, :, 3], np.asarray(store.pairs)[slot, :, 3]
    assert (lab[is_void] >= floor).all()
    np.testing.assert_array_equal(lab[is_void], np.maximum(lab0[is_void], floor))
    np.testing.assert_array_equal(np.asarray(store.surface)[slot][is_void], lab0[is_void] >= floor)
    np.testing.assert_array_equal(lab[~is_void], lab0[~is_void])


def test_evidence_without_a_range_image_layout_is_said_where_the_frame_program_is_built(caplog):
    """evidence.enabled with no range-image layout (preprocess.image_rows 0, no scan read yet): the static
    settings are built without a word (the layout may be read off the first scan a moment later), and the
    frame program built from them says that it maps without evidence, and how to set the layout."""
    from jaxmap.config import MapConfig
    from jaxmap.n3 import core, scan

    cfg = MapConfig()
    assert cfg.evidence.enabled and cfg.preprocess.image_rows == 0
    evidence.warn_without_layout.cache_clear()
    with caplog.at_level(logging.WARNING):
        static = core.N3Static.from_config(cfg)
    assert static.evidence_requested and not static.evidence and not caplog.records
    state = jax.eval_shape(lambda: core.init_state(static, cfg, core.capacities_for(static, cfg)))
    pts, nrm, pose = scan.preprocess(boxes_scan((0, 0, 1.7)), pose_at(0.0), cfg.preprocess, 0)[:3]
    batch = scan.to_batch(pts, nrm, pose, pose[:3, 3], scan.bucket_for(len(pts)))
    with caplog.at_level(logging.WARNING):
        jax.eval_shape(lambda s, b: core.integrate(static, s, b, jax.random.PRNGKey(0)), state, batch)
    said = [r.getMessage() for r in caplog.records if r.name == "jaxmap.n3.evidence"]
    assert len(said) == 1 and "without free-space evidence" in said[0] and "preprocess.image_rows" in said[0], said
