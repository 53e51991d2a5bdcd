"""N3 building blocks against hand-computed values and slow references."""
import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.n3 import hierarchical, window
from jaxmap.n3.loss import bce_loss, eikonal_loss, sdf_and_grad
from jaxmap.n3.sampling import sample_frame
from jaxmap.preprocess import estimate_normals, voxel_downsample

KW = dict(trunc=0.3, sigma=0.1, n_surface=4, n_free=2, free_band=1.0, free_label=0.3)


def _samples(points, normals, origin, mode, seed=0):
    n = len(points)
    return sample_frame(jax.random.PRNGKey(seed), jnp.asarray(points, jnp.float32), jnp.asarray(normals, jnp.float32),
                        jnp.ones(n, bool), jnp.asarray(origin, jnp.float32), label_mode=mode, **KW)


def test_normal_labels_equal_true_sdf_on_a_plane_and_projective_overestimates_at_grazing():
    # Ground plane z=0 seen from a sensor at height 1.7 m; far points are seen at grazing angles.
    xs = np.linspace(3, 30, 200)
    pts = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (len(xs), 1))
    origin = np.array([0.0, 0.0, 1.7])
    s = _samples(pts, nrm, origin, "normal")
    surf = np.asarray(s.surface)
    true_sdf = np.asarray(s.points)[:, 2]
    np.testing.assert_allclose(np.asarray(s.labels)[surf], true_sdf[surf], atol=1e-5)
    p = _samples(pts, nrm, origin, "projective")
    lab, true_p = np.asarray(p.labels)[surf], np.asarray(p.points)[surf, 2]
    # |projective label| >= |true distance|, strictly larger by the factor 1/sin(incidence).
    assert np.all(np.abs(lab) >= np.abs(true_p) - 1e-5)
    far = np.repeat(xs > 20, KW["n_surface"] + KW["n_free"])[surf] & (np.abs(lab) > 0.05)
    assert np.median(np.abs(lab[far]) / np.abs(true_p[far])) > 5.0
    c = _samples(pts, nrm, origin, "corrected")
    np.testing.assert_allclose(np.asarray(c.labels)[surf], np.asarray(c.points)[surf, 2], atol=1e-5)


def test_labels_on_a_sphere():
    # Sphere of radius 2 at the origin, sensor at (6,0,0): normal labels are exact (x = p + d n stays
    # radial); projective labels differ from the true SDF off the line of sight.
    rng = np.random.default_rng(0)
    v = rng.normal(size=(500, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v[:, 0] > 0.3]
    pts, nrm, origin = 2.0 * v, v, np.array([6.0, 0, 0])
    s = _samples(pts, nrm, origin, "normal")
    surf = np.asarray(s.surface)
    true = np.linalg.norm(np.asarray(s.points), axis=1) - 2.0
    np.testing.assert_allclose(np.asarray(s.labels)[surf], true[surf], atol=1e-5)
    p = _samples(pts, nrm, origin, "projective")
    true_p = np.linalg.norm(np.asarray(p.points), axis=1) - 2.0
    err = np.abs(np.asarray(p.labels)[surf] - true_p[surf])
    assert err.max() > 0.01  # would be ~0 if projective sampling were the same as normal sampling


def test_free_samples_lie_on_the_ray_before_the_band():
    pts = np.array([[10.0, 0, 0], [0, 5.0, 0]])
    s = _samples(pts, -pts / np.linalg.norm(pts, axis=1, keepdims=True), np.zeros(3), "normal")
    free = ~np.asarray(s.surface)
    fp = np.asarray(s.points)[free]
    d = np.linalg.norm(fp, axis=1)
    owner = np.repeat(np.arange(2), 6)[free]
    dist = np.linalg.norm(pts, axis=1)[owner]
    assert np.all(d <= dist - 0.3 + 1e-5) and np.all(d >= dist - 1.3 - 1e-5)
    cross = np.linalg.norm(np.cross(fp, pts[owner]), axis=1)
    assert np.all(cross < 1e-4)
    np.testing.assert_allclose(np.asarray(s.labels)[free], 0.3)


def test_eikonal_is_zero_for_an_exact_sdf_and_not_for_a_scaled_one():
    pts = jax.random.normal(jax.random.PRNGKey(0), (256, 3)) * 3 + 0.1
    mask = jnp.ones(256, bool)
    _, g = sdf_and_grad(lambda p: jnp.linalg.norm(p, axis=-1) - 1.0, pts)
    assert float(eikonal_loss(g, mask)) < 1e-8
    _, g2 = sdf_and_grad(lambda p: 2 * (jnp.linalg.norm(p, axis=-1) - 1.0), pts)
    assert abs(float(eikonal_loss(g2, mask)) - 1.0) < 1e-4


def test_bce_is_zero_at_the_label_and_positive_elsewhere():
    lab = jnp.linspace(-0.3, 0.3, 50)
    m = jnp.ones(50, bool)
    assert abs(float(bce_loss(lab, lab, 0.1, m))) < 1e-6
    assert float(bce_loss(lab + 0.05, lab, 0.1, m)) > 1e-3


def test_normals_face_the_sensor_and_are_exact_on_a_plane():
    rng = np.random.default_rng(1)
    xy = rng.uniform(-10, 10, size=(2000, 2))
    pts = np.concatenate([xy, np.full((2000, 1), -1.7)], 1).astype(np.float32)
    n, _ = estimate_normals(pts, 20)
    np.testing.assert_allclose(n, np.tile([0, 0, 1.0], (2000, 1)), atol=1e-4)


def test_voxel_downsample_keeps_one_point_per_voxel():
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 1, size=(5000, 3)).astype(np.float32)
    d = voxel_downsample(pts, 0.25)
    keys = np.floor(d / 0.25)
    assert len(np.unique(keys, axis=0)) == len(d) == 64


# ---- the voxel-oriented store against a slow Python reference ----

def _reference_store(batches, P):
    ref = {}
    for slots, vals in batches:
        for s, v in zip(slots, vals):
            if s >= 0:
                ref.setdefault(s, []).append(v)
    return {s: vs[-P:] for s, vs in ref.items()}


def test_write_pairs_keeps_the_newest_P_per_block_like_a_python_reference():
    rng = np.random.default_rng(3)
    S, P = 16, 5
    st = window.create(S, P, 64)
    batches = []
    write = jax.jit(window.write_pairs)
    for f in range(6):
        m = 40
        slots = rng.integers(-1, S, size=m).astype(np.int32)
        vals = rng.normal(size=m).astype(np.float32)
        pts = np.tile(vals[:, None], (1, 3))
        st = write(st, jnp.asarray(slots), jnp.asarray(pts), jnp.asarray(vals), jnp.ones(m, bool), jnp.int32(f))
        batches.append((slots, vals))
    ref = _reference_store(batches, P)
    for s in range(S):
        got = sorted(np.asarray(st.pairs[s, : int(st.count[s]), 3]).tolist())
        assert got == sorted(ref.get(s, [])), s


def test_assign_slots_gives_each_voxel_one_block_and_reports_overflow():
    st = window.create(4, 8, 32)
    rows = jnp.asarray([3, 3, 7, -1, 9, 7], jnp.int32)
    coords = jnp.stack([rows, rows, rows], 1)
    st, slots, over = window.assign_slots(st, rows, coords)
    slots = np.asarray(slots)
    assert not bool(over)
    assert slots[0] == slots[1] and slots[2] == slots[5] and slots[3] == -1
    assert len({slots[0], slots[2], slots[4]}) == 3
    st, slots2, over = window.assign_slots(st, jnp.asarray([11, 12, 3], jnp.int32), jnp.zeros((3, 3), jnp.int32))
    assert bool(over)  # 2 new voxels, 1 free slot: reported, never silently dropped


def test_window_releases_blocks_that_leave_the_cube():
    st = window.create(8, 4, 16)
    rows = jnp.arange(4, dtype=jnp.int32)
    coords = jnp.asarray([[0, 0, 0], [5, 0, 0], [50, 0, 0], [-50, 0, 0]], jnp.int32)
    st, slots, _ = window.assign_slots(st, rows, coords)
    keep = window.in_window(st, jnp.asarray([0, 0, 0]), 10, mode="voxel", frame=0, keyframes=0)
    st = window.release(st, keep)
    assert np.asarray(st.slot_of_voxel)[:4].tolist()[2:] == [-1, -1]
    assert (np.asarray(st.voxel_of_slot) >= 0).sum() == 2


def test_hierarchical_sampler_matches_algorithm_1():
    """Every drawn pair comes from a window block; blocks under Nt give Np//3 valid pairs."""
    S, P = 6, 32
    st = window.create(S, P, 16)
    rows = jnp.arange(S, dtype=jnp.int32)
    st, slots, _ = window.assign_slots(st, rows, jnp.zeros((S, 3), jnp.int32))
    counts = [30, 3, 12, 0, 9, 20]
    pts, lab, sl = [], [], []
    for s, c in enumerate(counts):
        for j in range(c):
            pts.append([s, j, 0]); lab.append(s * 100 + j); sl.append(int(slots[s]))
    st = window.write_pairs(st, jnp.asarray(sl, jnp.int32), jnp.asarray(pts, jnp.float32),
                            jnp.asarray(lab, jnp.float32), jnp.ones(len(lab), bool), jnp.int32(0))
    inside = jnp.asarray([True, True, False, True, True, True])  # slot 2 outside the window
    ids, n = hierarchical.window_slots(inside & (st.count > 0))
    b = hierarchical.sample_hierarchical(jax.random.PRNGKey(0), st, ids, n, nv=4000, np_=9, nt=10)
    slots_b, mask, labels = np.asarray(b.slots), np.asarray(b.mask), np.asarray(b.labels)
    assert set(slots_b.tolist()) == {0, 1, 4, 5}  # window blocks with pairs, and all of them
    for s in {0, 1, 4, 5}:
        per = mask[slots_b == s].sum(1)
        assert np.all(per == (9 if counts[s] >= 10 else 3))
        lab = labels[slots_b == s][mask[slots_b == s]]
        assert np.all((lab >= s * 100) & (lab < s * 100 + counts[s]))
    # Stage 1 is uniform over voxels, not over pairs: block 1 (3 pairs) is drawn as often as block 0 (30).
    freq = np.bincount(slots_b, minlength=S)[[0, 1, 4, 5]] / 4000
    np.testing.assert_allclose(freq, 0.25, atol=0.04)
    u = hierarchical.sample_uniform(jax.random.PRNGKey(1), st, ids, n, batch=20000)
    share0 = (np.asarray(u.slots) == 0).mean()
    assert abs(share0 - 30 / 62) < 0.03  # uniform over pairs: block 0 holds 30 of the 62 window pairs


def test_sparse_adam_equals_dense_adam_on_touched_rows_and_leaves_others():
    import optax

    from jaxmap.n3.mapper import VALUE, _pack, sparse_adam

    rng = np.random.default_rng(4)
    R, D = 12, 3
    init = jnp.asarray(rng.normal(size=(R, D)), jnp.float32)
    packed, cnt = _pack(init), jnp.zeros((), jnp.int32)
    tx = optax.adam(0.01)
    dense, st = init, tx.init(init)
    touched = np.arange(8)  # rows 8..11 are never touched
    for step in range(3):
        rows = rng.choice(touched, size=20).astype(np.int32)
        rows[:8] = touched  # every touched row appears at least once per step: dense == lazy there
        rows[-2:] = -1      # padding
        g = rng.normal(size=(20, D)).astype(np.float32)
        packed, cnt = sparse_adam(packed, cnt, jnp.asarray(rows), jnp.asarray(g), lr=0.01)
        gd = np.zeros((R, D), np.float32)
        np.add.at(gd, rows[rows >= 0], g[rows >= 0])
        upd, st = tx.update(jnp.asarray(gd), st, dense)
        dense = optax.apply_updates(dense, upd)
    np.testing.assert_allclose(np.asarray(packed[:8, VALUE]), np.asarray(dense)[:8], rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(packed[8:, VALUE]), np.asarray(init)[8:])
    np.testing.assert_array_equal(np.asarray(packed[:, 3]), 0.0)  # accumulator cleared


def test_analytic_weight_gradients_equal_autodiff():
    from jaxmap.grid import features as gf

    rng = np.random.default_rng(5)
    vox = rng.integers(-20, 20, size=(64, 3)).astype(np.int32)
    pts = ((vox + rng.uniform(0.01, 0.99, size=(64, 3))) * 0.2).astype(np.float32)
    w, dw = gf.corner_weights_and_grad(jnp.asarray(pts), jnp.asarray(vox), 0.2, 3)
    np.testing.assert_allclose(w, gf.corner_weights(jnp.asarray(pts), jnp.asarray(vox), 0.2, 3), rtol=1e-5, atol=1e-6)
    jac = jax.vmap(jax.jacfwd(lambda p, v: gf.corner_weights(p[None], v[None], 0.2, 3)[0]))(
        jnp.asarray(pts), jnp.asarray(vox))
    np.testing.assert_allclose(dw, jac, rtol=1e-4, atol=1e-4)


def test_explicit_mlp_gradient_equals_autodiff_and_so_does_its_parameter_gradient():
    from jaxmap.n3.decoder import init_decoder, mlp_with_input_grad

    module, params = init_decoder(jax.random.PRNGKey(0), 8, 32, 2)
    f = jax.random.normal(jax.random.PRNGKey(1), (100, 8))
    sdf, g = mlp_with_input_grad(params, f)
    np.testing.assert_allclose(sdf, module.apply(params, f), rtol=1e-5, atol=1e-6)
    g_ref = jax.vmap(jax.grad(lambda x: module.apply(params, x[None])[0]))(f)
    np.testing.assert_allclose(g, g_ref, rtol=1e-5, atol=1e-6)
    # The eikonal-style second-order parameter gradient agrees too.
    def eik(p, explicit):
        gg = mlp_with_input_grad(p, f)[1] if explicit else jax.vmap(jax.grad(lambda x: module.apply(p, x[None])[0]))(f)
        return jnp.sum(jnp.sum(gg**2, -1))
    a, b = jax.grad(eik)(params, True), jax.grad(eik)(params, False)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5)
