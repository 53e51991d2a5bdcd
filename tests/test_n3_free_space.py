"""Free space that carves (N3 section III-B, Fig. 10), the loss's sign and sharpness, the frozen
decoder, and free samples that land where the map has no voxel."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from analytic_lidar import corridor_scan, hall_scan, pose_at
from jaxmap.config import load_config
from jaxmap.n3 import core, scan, window
from jaxmap.n3.loss import bce_loss
from jaxmap.n3.mapper import N3Mapper
from jaxmap.n3.sampling import sample_frame

SMALL = ["train.iters=20", "train.nv=256", "train.np_per_voxel=8", "preprocess.max_range_m=12.0",
         "preprocess.vox_down_m=0.1", "window.initial_blocks=4096", "mesh.min_component_faces=0"]
# Every free-space and carving key these tests depend on, set here rather than taken from configs/city.yaml's
# defaults (which may change): the measured counts and bounds below belong to these values.
FREE_SPACE = ["sampling.free_sample_n=3", "sampling.free_band_m=1.0", "sampling.free_ray_n=6",
              "sampling.free_ray_quiet_frames=10", "sampling.free_label_m=-1.0", "sampling.free_label_mode=projected",
              "sampling.free_point_filter_m=0.0", "window.carve=true", "window.carve_margin_m=0.05",
              "window.carve_samples=16384", "window.carve_rule=replace", "window.carve_sign=false",
              "evidence.enabled=false", "preprocess.veil_m=0.0"]  # the rays and carving alone (issue 21)
BOX = (4.0, 6.0, -1.0, 1.0, 1.5)  # x0, x1, y0, y1, height: a car-sized box 6 m ahead of the sensor


def _hall_with_a_box_that_leaves(extra, frames_with=5, frames_without=21):
    """The sensor rolls towards the hall's end wall; the box stands in front of it for the first
    frames, then is gone while the rays to the end wall keep crossing its place."""
    m = N3Mapper(load_config("configs/city.yaml", SMALL + FREE_SPACE + list(extra)))
    for i in range(frames_with + frames_without):
        x = -2.0 + 0.1 * i
        m.add_frame(hall_scan((x, 0, 1.7), box=BOX if i < frames_with else None), pose_at(x))
    rng = np.random.default_rng(0)
    q = np.stack([rng.uniform(4.0, 4.6, 2000), rng.uniform(-0.8, 0.8, 2000), rng.uniform(0.4, 1.3, 2000)], 1)
    sdf, valid = m.sdf(q)
    mesh = m.mesh(0.1)
    c = np.asarray(mesh.vertices)[np.asarray(mesh.faces)].mean(1)
    # the box's place, its front face x = 4 with 20 cm in front of it (a ghost face learned a few cm
    # off must not fall out of the count), above the ground and inside its sides
    in_box = np.all((c > [3.8, -0.9, 0.25]) & (c < [6.0, 0.9, 1.4]), axis=1)
    return m, sdf[valid], int(in_box.sum())


# Faces left in the box's place. The count is chaotic: any change of the float rounding moves it.
# Measured (26 frames, 20 iterations) over train.seed 0-4, the box moved by 1 mm along x, y, z, the scan
# rounded to 1 mm or moved by 1 float32 ulp, each under XLA_FLAGS none, --xla_cpu_enable_fast_math=true
# or false, --xla_cpu_max_isa=AVX2 (no AVX-512) and both: carving 0-32 faces (87 runs; 0 on most, 16 on
# issue 35's AMD EPYC), no carving (window.carve=false) 171-580 (27 runs; 94-564 in 57 runs counting
# from x = 4 on), the pre-issue rule (sampling.free_ray_n=0) 690-722 (3 runs; 465-649 from x = 4 on,
# 33 runs). The bound sits ~2.3x from both sides.
GHOST_FACES = 75


def test_free_space_along_the_ray_erases_a_box_that_left_and_keeps_the_walls():
    """Carving erases the box: at most GHOST_FACES faces are left in its place (measured 0-32; see above)
    and most SDF samples on its old front face are > 5 cm (measured 95.4-100 %). Without carving the
    same samples leave 171-580 faces; the pre-issue rule (free samples only in the last metre before the
    band, `sampling.free_ray_n=0`) 690-722 faces and SDF < 5 cm on 87-95 % of the samples."""
    m, sdf, faces_in_box = _hall_with_a_box_that_leaves([])
    assert faces_in_box <= GHOST_FACES, faces_in_box
    assert np.mean(sdf > 0.05) > 0.9, np.mean(sdf > 0.05)
    assert sum(t["carved"] for t in m.timings) > 0
    # the static hall is still there: the end wall x = 9 and the ground under the box's place (measured
    # within 4.5 cm of the true SDF over the runs above; an erased wall reads up to the free label, 0.3 m)
    q = np.array([[8.95, y, z] for y in np.linspace(-3, 3, 7) for z in (0.5, 1.0, 1.5)]
                 + [[x, y, 0.0] for x in (4.5, 5.0, 5.5) for y in (-0.5, 0.0, 0.5)])
    s, v = m.sdf(q)
    assert v.all() and np.all(np.abs(s - np.r_[np.full(21, 0.05), np.zeros(9)]) < 0.09), s

    # the wrong rules leave the ghost, so the bound above separates them: this scene tests something
    _, _, faces_no_carve = _hall_with_a_box_that_leaves(["window.carve=false"])
    assert faces_no_carve > GHOST_FACES, faces_no_carve  # the ray samples alone do not finish the job
    _, sdf_band, faces_band = _hall_with_a_box_that_leaves(["sampling.free_ray_n=0", "window.carve=false"])
    assert faces_band > GHOST_FACES, faces_band
    assert np.mean(sdf_band > 0.05) < 0.5, np.mean(sdf_band > 0.05)


def test_carve_replaces_only_contradicted_pairs_of_earlier_frames():
    store = window.create(4, 8, 16)
    pairs = np.zeros((4, 8, 4), np.float32)
    # block 0 (voxel row 3): a surface pair at the origin (label 0), a pair 10 cm away that is
    # consistent with free space at y (label 0.25 >= 0.3 - 0.1 - margin), and a contradicted pair
    # written by the current frame (kept: this frame's own observations do not carve each other).
    pairs[0, 0] = [0.0, 0.0, 0.0, 0.0]
    pairs[0, 1] = [0.15, 0.0, 0.0, 0.25]
    pairs[0, 2] = [0.0, 0.02, 0.0, 0.0]
    frame = np.full((4, 8), -1, np.int32)
    frame[0, :3] = [1, 1, 7]
    store = store.replace(pairs=jnp.asarray(pairs), frame=jnp.asarray(frame),
                          count=jnp.asarray([3, 0, 0, 0], jnp.int32),
                          voxel_of_slot=jnp.asarray([3, -1, -1, -1], jnp.int32),
                          slot_of_voxel=jnp.full((16,), -1, jnp.int32).at[3].set(0))
    y = jnp.asarray([[0.05, 0.0, 0.0], [0.05, 0.0, 0.0], [9.0, 9.0, 9.0]], jnp.float32)
    lab = jnp.asarray([0.3, 0.3, 0.3], jnp.float32)
    new, n = window.carve(store, jnp.asarray([3, -1, 5], jnp.int32), y, lab, jnp.ones(3, bool), jnp.int32(7),
                          jax.random.PRNGKey(0), margin=0.05, max_samples=8)
    assert int(n) == 1
    p = np.asarray(new.pairs)
    np.testing.assert_allclose(p[0, 0], [0.05, 0.0, 0.0, 0.3])            # replaced by the free sample
    assert not bool(new.surface[0, 0]) and int(new.frame[0, 0]) == 7
    np.testing.assert_array_equal(p[0, 1:3], pairs[0, 1:3])                # consistent / same frame: kept
    np.testing.assert_array_equal(np.asarray(new.count), [3, 0, 0, 0])
    # a block that a frame hit within the last quiet_frames frames is not carved (a static surface is
    # hit again and again; what moved away is not)
    hit = store.replace(last_hit=jnp.asarray([5, -1, -1, -1], jnp.int32))
    _, n_recent = window.carve(hit, jnp.asarray([3, -1, 5], jnp.int32), y, lab, jnp.ones(3, bool), jnp.int32(7),
                               jax.random.PRNGKey(0), margin=0.05, max_samples=8, quiet_frames=2)
    _, n_quiet = window.carve(hit, jnp.asarray([3, -1, 5], jnp.int32), y, lab, jnp.ones(3, bool), jnp.int32(7),
                              jax.random.PRNGKey(0), margin=0.05, max_samples=8, quiet_frames=1)
    assert int(n_recent) == 0 and int(n_quiet) == 1


def test_bce_sign_and_sharpness_against_the_formula():
    """L = BCE(sigmoid(f / beta), sigmoid(s / beta)) minus its floor, from the formula in float64:
    a swapped label sign or another beta gives other values, and the gradient pulls f towards s."""
    f = np.array([0.1, -0.05, 0.2, 0.0])
    s = np.array([-0.1, -0.05, 0.05, 0.3])
    beta = 0.1

    def ref(f, s, beta):
        sig = lambda x: 1.0 / (1.0 + np.exp(-x))  # noqa: E731
        t, p = sig(s / beta), sig(f / beta)
        per = -(t * np.log(p) + (1 - t) * np.log(1 - p))
        floor = -(t * np.log(t) + (1 - t) * np.log(1 - t))
        return np.mean(per - floor)

    m = jnp.ones(4, bool)
    got = float(bce_loss(jnp.asarray(f, jnp.float32), jnp.asarray(s, jnp.float32), beta, m))
    assert abs(got - ref(f, s, beta)) < 1e-5
    # the formula with the label sign swapped or beta doubled is far outside the 1e-5 above
    assert abs(ref(f, -s, beta) - got) > 0.02 and abs(ref(f, s, 2 * beta) - got) > 0.02
    g = jax.grad(lambda x: bce_loss(x, jnp.asarray(s, jnp.float32), beta, m))(jnp.asarray(f, jnp.float32))
    assert np.all(np.sign(np.asarray(g))[[0, 2, 3]] == np.sign(f - s)[[0, 2, 3]]) and abs(float(g[1])) < 1e-6


def test_eikonal_term_counts_only_pairs_the_config_puts_in_the_band():
    from jaxmap.n3 import field, hierarchical
    from jaxmap.n3.decoder import init_decoder

    _, dec = init_decoder(jax.random.PRNGKey(0), 8, 32, 2)
    rng = np.random.default_rng(0)
    feats = jnp.asarray(rng.normal(0, 0.5, (4, 24, 8)), jnp.float32)
    vox = jnp.asarray(rng.integers(-5, 5, (4, 3)), jnp.int32)
    pts = (vox[:, None, :] + jnp.asarray(rng.uniform(0.1, 0.9, (4, 6, 3)), jnp.float32)) * 0.2

    def loss(surface, weight_e):
        b = hierarchical.Batch(points=pts, labels=jnp.zeros((4, 6)), surface=surface,
                               mask=jnp.ones((4, 6), bool), voxel_rows=jnp.zeros((4,), jnp.int32), coords=vox)
        return field.n3_loss(feats, dec, b, vox, 0.1, weight_e, leaf=0.2, levels=3)

    none = jnp.zeros((4, 6), bool)
    half = jnp.arange(6)[None].repeat(4, 0) < 3
    total, (bce, eik) = loss(half, 0.5)
    assert float(eik) > 0.1 and abs(float(total) - float(bce) - 0.5 * float(eik)) < 1e-5
    assert float(loss(none, 0.5)[1][1]) == 0.0                      # free pairs: no eikonal term
    assert abs(float(loss(half, 0.0)[0]) - float(bce)) < 1e-6       # weight_e = 0: BCE alone


def test_decoder_stays_frozen_after_the_freeze_frame():
    m = N3Mapper(load_config("configs/city.yaml", SMALL + ["train.freeze_after_frame=2", "train.iters=4"]))
    seen = []
    for i in range(5):
        m.add_frame(corridor_scan(1.0 * i, max_range=10.0), pose_at(1.0 * i))
        seen.append([np.asarray(x).copy() for x in jax.tree_util.tree_leaves(m.state.decoder)])
    moved = lambda a, b: any(not np.array_equal(x, y) for x, y in zip(a, b))  # noqa: E731
    assert moved(seen[0], seen[1])                     # frame 1 (< 2) trains the decoder
    assert not moved(seen[1], seen[2]) and not moved(seen[1], seen[4])   # frames 2.. do not
    assert m.timings[-1]["loss"] > 0 and moved([np.asarray(m.state.feature_table)], [np.zeros(1)])


@pytest.mark.parametrize("extra", [[], ["sampling.free_ray_n=0", "window.carve=false"]])
def test_free_samples_outside_allocated_voxels_are_dropped_and_counted(extra):
    """FrameStats.free_dropped equals the free samples (recomputed with the frame's key) whose leaf
    voxel the map does not hold; no stored free pair lies outside an allocated voxel."""
    cfg = load_config("configs/city.yaml", SMALL + FREE_SPACE + list(extra))
    static = core.N3Static.from_config(cfg)
    state = core.init_state(static, cfg, core.capacities_for(static, cfg))
    pts, nrm, pose = scan.preprocess(corridor_scan(0.0, max_range=10.0), pose_at(0.0), cfg.preprocess, 0)[:3]
    state = core.set_origin(static, state, pose[:3, 3])
    batch = scan.to_batch(pts, nrm, pose, core.origin_world(static, state), scan.bucket_for(len(pts)))
    key = jax.random.PRNGKey(3)
    state, fs = jax.jit(lambda st, b, k: core.integrate(static, st, b, k))(state, batch, key)
    assert bool(fs.ok)
    smp = sample_frame(key, batch.points, batch.normals, batch.valid, batch.sensor, label_mode=static.label_mode,
                       trunc=static.trunc, sigma=static.sigma, n_surface=static.n_surface, n_free=static.n_free,
                       free_band=static.free_band, free_label=static.free_label,
                       free_label_mode=static.free_label_mode, n_ray=static.n_ray, min_range=static.free_min_range)
    held = {tuple(c) for c in np.asarray(state.voxel_coord)[: int(fs.voxels)]}
    free = np.asarray(smp.valid & ~smp.surface)
    vox = np.floor(np.asarray(smp.points)[free] / static.leaf).astype(int)
    outside = sum(tuple(v) not in held for v in vox)
    assert outside > 0 and int(fs.free_dropped) == outside
    st = state.store
    used = np.arange(st.block_size)[None] < np.asarray(st.count)[:, None]
    stored_free = used & ~np.asarray(st.surface)
    sv = np.floor(np.asarray(st.pairs)[..., :3][stored_free] / static.leaf).astype(int)
    assert len(sv) > 0 and all(tuple(v) in held for v in sv)


def test_points_where_the_map_is_confidently_free_get_no_samples():
    """PIN-SLAM's dynamic filter (`sampling.free_point_filter_m`): a box stands in the hall, leaves and is
    carved; when it comes back (a second car in the same lane), its points fall where the map learned
    free space and get no samples. The hall's own points are kept all along."""
    m = N3Mapper(load_config("configs/city.yaml", SMALL + FREE_SPACE + ["sampling.free_point_filter_m=0.1",
                                                                         "train.freeze_after_frame=10"]))
    for i in range(27):
        x = -2.0 + 0.1 * i
        box = BOX if i < 5 or i == 26 else None
        info = m.add_frame(hall_scan((x, 0, 1.7), box=box), pose_at(x))
        if box is None:
            # a static scene keeps its points: all but a few on the ground next to the walls (a concave
            # corner, where the field is learned ~0.1 m too high: measured at most 0.16-0.34 % of the
            # points over train.seed 0-2, the box moved by 1 mm and XLA's fast math / AVX2 code)
            assert info["points_filtered"] <= 0.01 * info["points"], info
    pts, _, _ = scan.preprocess(hall_scan((x, 0, 1.7), box=BOX), pose_at(x), m.cfg.preprocess, 26)[:3]
    w = pts + [x, 0.0, 1.7]
    on_box = int(np.sum(np.all((w > [3.95, -1.05, -0.05]) & (w < [6.05, 1.05, 1.55]), axis=1)))
    # measured 56-78 % of the box's points filtered over those runs; without the filter, none
    assert on_box > 100 and 0.25 * on_box <= info["points_filtered"] <= on_box + 0.01 * info["points"], \
        (info, on_box)
