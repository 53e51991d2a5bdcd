"""N3 building blocks against hand-computed values and slow references."""
import jax
import jax.numpy as jnp
import numpy as np

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


# The store, the hierarchical sampler and sparse Adam are tested in test_n3_core.py.


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


def _free_labels_and_truth(pts, nrm, origin, true_dist, mode):
    n = len(pts)
    s = sample_frame(jax.random.PRNGKey(1), jnp.asarray(pts, jnp.float32), jnp.asarray(nrm, jnp.float32),
                     jnp.ones(n, bool), jnp.asarray(origin, jnp.float32), label_mode="normal",
                     **dict(KW, n_free=8), free_label_mode=mode)
    free = ~np.asarray(s.surface)
    return np.asarray(s.labels)[free], true_dist(np.asarray(s.points, np.float64)[free])


def test_free_space_labels_never_exceed_the_true_distance_to_a_plane_or_a_sphere():
    """Free samples a metre before a grazing hit pass centimetres above the ground: their label must
    not claim the truncation distance. `projected` labels stay <= the true distance to a plane (equal
    there, up to tr) and to a sphere seen from outside; the paper's flat label exceeds it."""
    origin = np.array([0.0, 0.0, 1.73])
    xs = np.linspace(3, 20, 300)
    ground = np.stack([xs, 0.3 * np.sin(xs), np.zeros_like(xs)], 1)
    up = np.tile([0.0, 0.0, 1.0], (len(xs), 1))
    lab, true = _free_labels_and_truth(ground, up, origin, lambda p: p[:, 2], "projected")
    assert np.all(lab <= true + 1e-5)
    np.testing.assert_allclose(lab, np.minimum(true, 0.3), atol=1e-4)
    flat, true_f = _free_labels_and_truth(ground, up, origin, lambda p: p[:, 2], "truncation")
    assert np.mean(flat > true_f + 0.05) > 0.3  # the flat rule lies by > 5 cm for many samples

    rng = np.random.default_rng(2)
    v = rng.normal(size=(800, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    sensor = np.array([6.0, 0.0, 0.0])
    v = v[(v @ sensor) / 6.0 > 0.35]  # the side of a radius-2 sphere that the sensor sees
    sphere = lambda p: np.linalg.norm(p, axis=1) - 2.0  # noqa: E731
    lab, true = _free_labels_and_truth(2.0 * v, v, sensor, sphere, "projected")
    assert np.all(lab <= true + 1e-5) and np.all(lab > 0)
    flat, true_f = _free_labels_and_truth(2.0 * v, v, sensor, sphere, "truncation")
    assert np.any(flat > true_f + 0.02)


def test_outlier_removal_drops_stray_returns_between_surfaces_and_keeps_the_surfaces():
    """preprocess.remove_outliers: a wall and a ground plane seen from the sensor keep their points;
    returns scattered in the free space between them (mixed pixels, stray ranges) are dropped."""
    from jaxmap.preprocess import remove_outliers

    rng = np.random.default_rng(3)
    ground = np.stack([rng.uniform(2, 15, 6000), rng.uniform(-6, 6, 6000), np.full(6000, -1.7)], 1)
    wall = np.stack([np.full(3000, 12.0), rng.uniform(-6, 6, 3000), rng.uniform(-1.7, 3, 3000)], 1)
    stray = np.stack([rng.uniform(4, 11, 40), rng.uniform(-5, 5, 40), rng.uniform(-0.5, 2.5, 40)], 1)
    pts = np.concatenate([ground, wall, stray]).astype(np.float32)
    kept = remove_outliers(pts, 20, 6.0)
    keys = {tuple(p) for p in kept}
    assert sum(tuple(p) in keys for p in stray) <= 4                      # >= 90 % of the strays gone
    # the surfaces stay, but not whole: 2.8 % of these random-spaced points go too (measured), which
    # is why the filter is off by default (on the realistic suite city it cost 2 cm of completion)
    assert sum(tuple(p) in keys for p in pts[:9000]) >= 0.95 * 9000
    np.testing.assert_array_equal(remove_outliers(pts, 20, 0.0), pts)      # 0 = off
