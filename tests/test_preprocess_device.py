"""Scan preprocessing on the device (`jaxmap.preprocess_device`, `preprocess.device`) against its numpy
reference (`jaxmap.preprocess`): the same kept points, normals within 5 degrees on 99 % of them, and
the frame program that runs it maps what the host path maps."""
import jax
import numpy as np
import pytest

from analytic_lidar import corridor_scan, hall_scan, pose_at
from jaxmap import preprocess as ref
from jaxmap import preprocess_device as dev
from jaxmap.config import load_config
from jaxmap.io import open_sequence
from jaxmap.n3 import scan
from jaxmap.n3.mapper import N3Mapper


def _angles_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def _device(points, cfg, pad=4096):
    """Device preprocessing of sensor-frame points [N, 3] padded with `pad` invalid rows of garbage."""
    n = len(points)
    padded = np.concatenate([points, np.random.default_rng(0).normal(0, 5, (pad, 3))]).astype(np.float32)
    valid = np.arange(n + pad) < n
    f = jax.jit(lambda p, v: dev.preprocess_scan(p, v, cfg, n + pad))
    pts, nrm, ok, kept = (np.asarray(x) for x in f(padded, valid))
    return pts[ok], nrm[ok], int(kept)


@pytest.mark.parametrize("normals", ["grid", "cube_knn"])
def test_device_preprocessing_keeps_the_reference_points_and_its_normals(small_city, normals):
    # without the veil filter, which the frame program applies after this step (tests/test_range_image.py)
    cfg = load_config("configs/city.yaml", [f"preprocess.normals={normals}", "preprocess.veil_m=0.0"]).preprocess
    seq = open_sequence(str(small_city))
    for i in (0, 7):
        raw = np.asarray(seq.frame(i).points, np.float32)
        want_p, want_n = ref.preprocess_scan(raw, cfg)
        got_p, got_n, kept = _device(raw, cfg)
        assert kept == len(want_p) and len(want_p) > 1000
        np.testing.assert_array_equal(got_p, want_p)       # the same points, in the same order
        ang = _angles_deg(got_n, want_n)                   # oriented alike: no abs()
        assert np.mean(ang < 5.0) >= 0.99, np.percentile(ang, [50, 99])


def test_voxel_downsample_picks_the_same_point_of_two_equidistant_ones():
    # Two points per voxel are equidistant from their mean: float rounding must not choose; both
    # implementations keep the lower index. A third point at the mean wins in both.
    rng = np.random.default_rng(1)
    cells = rng.choice(600**3, 500, replace=False)                     # 500 distinct voxels
    base = (np.stack(np.unravel_index(cells, (600, 600, 600)), 1) - 300) * 0.05 + 0.025
    d = rng.uniform(-0.02, 0.02, (500, 3))
    pts = np.concatenate([base + d, base - d]).astype(np.float32)
    keep = np.asarray(jax.jit(lambda p, v: dev.voxel_keep(p, v, 0.05))(pts, np.ones(len(pts), bool)))
    np.testing.assert_array_equal(pts[keep], ref.voxel_downsample(pts, 0.05))
    assert keep[:500].all() and not keep[500:].any()
    three = np.concatenate([pts, base.astype(np.float32)])
    keep3 = np.asarray(jax.jit(lambda p, v: dev.voxel_keep(p, v, 0.05))(three, np.ones(len(three), bool)))
    assert keep3[1000:].all() and keep3.sum() == 500
    np.testing.assert_array_equal(three[keep3], ref.voxel_downsample(three, 0.05))


def test_grid_normals_are_the_planes_normals_facing_the_sensor():
    # A hall's ground, walls and ends: away from the edges where two planes meet, every normal is its
    # plane's, oriented towards the sensor (a wrong moment shift or orientation fails this).
    sensor = np.array([1.0, 0.5, 1.7])
    p_s = hall_scan(sensor, max_range=12.0)
    cfg = load_config("configs/city.yaml", ["preprocess.normals=grid", "preprocess.max_range_m=12"]).preprocess
    p_s = ref.voxel_downsample(ref.crop(p_s, 1.0, 12.0, -10, 30), 0.05)
    n_dev = np.asarray(jax.jit(lambda p, v: dev.grid_normals(p, v, cell=0.15, levels=3, k=20, max_range=12.0)[0])(
        p_s, np.ones(len(p_s), bool)))
    w = p_s + sensor
    true = np.zeros_like(w)
    true[:, 2] = 1.0                                                   # ground
    side = np.abs(np.abs(w[:, 1]) - 6.0) < 1e-3
    true[side] = np.stack([np.zeros(side.sum()), -np.sign(w[side, 1]), np.zeros(side.sum())], 1)
    end = np.abs(np.abs(w[:, 0]) - 9.0) < 1e-3
    true[end] = np.stack([-np.sign(w[end, 0]), np.zeros(end.sum()), np.zeros(end.sum())], 1)
    # more than 1.3 m (the coarsest cube's half-width plus a cell) from every edge between planes
    far = (np.minimum(6.0 - np.abs(w[:, 1]), 9.0 - np.abs(w[:, 0])) > 1.3) | (~side & ~end & (w[:, 2] < 0.01)
                                                                            & (np.abs(w[:, 1]) < 4.7)
                                                                            & (np.abs(w[:, 0]) < 7.7))
    far &= (w[:, 2] > 1.3) | (w[:, 2] < 0.01)
    assert far.sum() > 2000
    ang = _angles_deg(n_dev[far], true[far])
    assert np.max(ang) < 2.0, np.percentile(ang, [50, 99, 100])
    n_ref, _ = ref.grid_normals(p_s, 0.15, 3, 20)
    assert np.mean(_angles_deg(n_dev, n_ref) < 5.0) >= 0.99
    # cube_knn: the 20 nearest of the cube's points, as close to scipy's k nearest neighbours as the cap
    # allows (whole-cube PCA blurs the edges where two planes meet; the nearest 20 mostly do not).
    n_knn = np.asarray(jax.jit(lambda p, v: dev.grid_normals(p, v, cell=0.15, levels=3, k=20, max_range=12.0,
                                                             knn_cap=ref.CUBE_KNN_CAP)[0])(
        p_s, np.ones(len(p_s), bool)))
    assert np.max(_angles_deg(n_knn[far], true[far])) < 2.0
    scipy_knn, _ = ref.estimate_normals(p_s, 20)
    edge = ~far
    err_cube = _angles_deg(n_dev[edge], true[edge])
    err_knn = _angles_deg(n_knn[edge], true[edge])
    assert np.mean(err_knn) < 0.6 * np.mean(err_cube)
    assert np.mean(np.abs(np.sum(n_knn * scipy_knn, 1)) > np.cos(np.radians(5))) >= 0.9


def test_smallest_eigenvector_equals_eigh():
    rng = np.random.default_rng(2)
    q, _ = np.linalg.qr(rng.normal(size=(2000, 3, 3)))
    lam = np.sort(rng.uniform(1e-6, 1e-2, (2000, 3)), axis=1)
    lam[:, 1:] += 1e-3                                                # a simple smallest eigenvalue
    cov = (q * lam[:, None, :]) @ q.transpose(0, 2, 1)
    v = np.asarray(jax.jit(dev.smallest_eigenvector)(cov.astype(np.float32)))
    want = np.linalg.eigh(cov)[1][:, :, 0]
    assert np.max(np.degrees(np.arccos(np.clip(np.abs(np.sum(v * want, 1)), 0, 1)))) < 0.5


SMALL = ["train.iters=6", "train.nv=128", "train.np_per_voxel=8", "preprocess.max_range_m=10.0",
         "preprocess.vox_down_m=0.1", "window.initial_blocks=4096", "mesh.min_component_faces=0",
         "preprocess.normals=cube_knn"]


def test_frame_program_maps_what_the_host_path_maps_and_grows_the_scan_rows():
    frames = [(corridor_scan(1.5 * i, max_range=10.0), pose_at(1.5 * i)) for i in range(4)]
    host = N3Mapper(load_config("configs/city.yaml", SMALL + ["preprocess.device=false"]))
    on_dev = N3Mapper(load_config("configs/city.yaml", SMALL + ["preprocess.device=true"]))
    short = N3Mapper(load_config("configs/city.yaml", SMALL + ["preprocess.device=true"]))
    short._headroom["scan_rows"] = 256         # too few: the first frame must grow them and run again
    for i, (pts, pose) in enumerate(frames):
        want = len(scan.preprocess(pts, pose, host.cfg.preprocess, i)[0])
        a, b, c = host.add_frame(pts, pose), on_dev.add_frame(pts, pose), short.add_frame(pts, pose)
        assert a["points"] == b["points"] == c["points"] == want
        assert c["passes"] == (2 if i == 0 else 1) and b["passes"] == 1
    # The device's float32 normals differ from the host's float64 ones in the last bits: the maps agree
    # to a voxel or two, and the run that grew its rows is the run that had them from the start.
    assert abs(b["leaf_voxels"] - a["leaf_voxels"]) <= 0.01 * a["leaf_voxels"]
    assert abs(b["loss"] - a["loss"]) <= 0.05 * a["loss"]
    for x, y in zip(jax.tree_util.tree_leaves(on_dev.state), jax.tree_util.tree_leaves(short.state)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_auto_preprocesses_on_the_device_on_a_gpu_only_and_true_alone_works(caplog):
    """`preprocess.device: auto` (the default) is the device on a GPU or TPU backend and the host on a
    CPU; on the device `normals: knn` (the host's k-d tree) becomes cube_knn, and outlier removal (host
    only) keeps auto on the host. `preprocess.device=true` alone is a valid config that maps on the
    device (it used to be an error asking for `normals`). A resolver that ignored the backend, or left
    knn normals to a frame program that cannot run them, fails here."""
    from jaxmap.n3.state import N3Static

    auto = load_config("configs/city.yaml").preprocess
    assert auto.device == "auto" and auto.normals == "knn"
    caplog.set_level("INFO", logger="jaxmap")
    assert dev.resolve(auto, backend="cpu").device == "false"
    on_gpu = dev.resolve(auto, backend="gpu")
    assert (on_gpu.device, on_gpu.normals) == ("true", "cube_knn")
    assert "preprocessing on the device (jax backend gpu" in caplog.text and "cube_knn" in caplog.text
    with_mad = load_config("configs/city.yaml", ["preprocess.outlier_mad=6"]).preprocess
    assert dev.resolve(with_mad, backend="gpu").device == "false"
    grid = load_config("configs/city.yaml", ["preprocess.normals=grid"]).preprocess
    assert dev.resolve(grid, backend="tpu").normals == "grid"          # a device method is kept
    forced = load_config("configs/city.yaml", ["preprocess.device=true"])  # no error
    assert forced.preprocess.device == "true"
    static = N3Static.from_config(forced)
    assert static.preprocess is not None and static.preprocess.normals == "cube_knn"
    assert N3Static.from_config(load_config("configs/city.yaml")).preprocess is None  # this CPU: the host
    assert load_config("configs/city.yaml", ["preprocess.device=false"]).preprocess.device == "false"


def test_range_image_normals_are_the_planes_normals_and_the_device_computes_the_reference():
    """`normals: range_image`: in a closed hall (ground, four walls, a box), seen by a 32-beam LiDAR, the
    normals from each point's range-image neighbours are the true plane normals (within 5 deg, facing
    the sensor) on as many of the downsampled points as the host's k nearest neighbours over the whole
    scan (92.0 % against 91.1 %; the rest are where planes meet), and the device's (float32,
    `lax.top_k`) are the float64 reference's within 1 deg on 99 %. Every pixel of the window instead of
    its k nearest returns in space (87.6 %), or normals facing away from the sensor, fail here."""
    from jaxmap.range_image import estimate_layout

    box = (2.0, 3.5, -1.0, 1.0, 1.0)
    raw = hall_scan((-3.0, 0.5, 1.7), box=box)
    layout = estimate_layout(raw)
    pts = ref.voxel_downsample(raw, 0.1)
    nrm, cnt = ref.range_image_normals(pts, raw, layout, 20)
    w = pts + np.array([-3.0, 0.5, 1.7], np.float32)                  # world frame (axes as the sensor's)
    x0, x1, y0, y1, h = box
    true = np.full_like(w, np.nan)
    true[np.abs(w[:, 2]) < 1e-3] = (0, 0, 1)
    on_side = np.abs(np.abs(w[:, 1]) - 6.0) < 1e-3
    true[on_side] = np.c_[np.zeros(on_side.sum()), -np.sign(w[on_side, 1]), np.zeros(on_side.sum())]
    on_end = np.abs(np.abs(w[:, 0]) - 9.0) < 1e-3
    true[on_end] = np.c_[-np.sign(w[on_end, 0]), np.zeros(on_end.sum()), np.zeros(on_end.sum())]
    on_front = (np.abs(w[:, 0] - x0) < 1e-3) & (w[:, 2] < h - 0.05)   # the box's face towards the sensor
    true[on_front] = (-1, 0, 0)
    known = np.isfinite(true[:, 0])
    assert known.sum() > 0.8 * len(w)
    ang = _angles_deg(nrm[known], true[known])
    knn = _angles_deg(ref.estimate_normals(pts, 20)[0][known], true[known])
    assert np.mean(ang < 5.0) >= max(np.mean(knn < 5.0), 0.9), (np.mean(ang < 5.0), np.mean(knn < 5.0))

    n = len(pts)
    pad = 256
    pts_p = np.concatenate([pts, np.zeros((pad, 3), np.float32)])
    raw_p = np.concatenate([raw, np.zeros((pad, 3), np.float32)]).astype(np.float32)
    f = jax.jit(lambda p, v, r, rv: dev.range_image_normals(p, v, r, rv, layout, 20))
    d_nrm, d_cnt = (np.asarray(x) for x in f(pts_p, np.arange(n + pad) < n, raw_p, np.arange(len(raw_p)) < len(raw)))
    agree = _angles_deg(d_nrm[:n], nrm)
    assert np.mean(agree < 1.0) >= 0.99, np.percentile(agree, [50, 99, 99.9])
    assert np.all(d_cnt[n:] == 0)
