"""jaxmap.metrics: the N3/SHINE evaluation protocol (docs/evaluation.md) on scenes with known answers, checked against a
literal implementation written here (numpy brute force) and against open3d's own crop / sampling /
down-sampling."""
import json
import os

import numpy as np
import pytest
import trimesh

from jaxmap.errors import DataError
from jaxmap.metrics import (METRIC_KEYS, crop_box, crop_mesh, evaluate, evaluate_mesh, evaluate_mesh_file, protocol_floor,
                            sample_mesh, sample_points_uniformly, signed_error_by_class, voxel_down_sample)


def ground_with_box(size=2.0, box=(0.5, 0.5, 0.5)):
    """A one-sided square ground at z=0 with a closed box standing on it (world frame, metres)."""
    h = size / 2
    ground = trimesh.Trimesh([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], [[0, 1, 2], [0, 2, 3]])
    b = trimesh.creation.box(extents=box)
    b.apply_translation((0.3, 0.2, box[2] / 2))
    return trimesh.util.concatenate([ground, b])


# ------------------------------------------------------------------------------------------------
# a literal implementation of SHINE-Mapping's eval_mesh (MaiCity settings), as plainly as possible
# ------------------------------------------------------------------------------------------------


def literal_down_sample(points, voxel):
    """open3d's voxel_down_sample: grid anchored at min bound - voxel / 2, the mean of each voxel."""
    origin = points.min(0) - voxel / 2
    acc = {}
    for p in points:
        k = tuple(int(v) for v in np.floor((p - origin) / voxel))
        s, n = acc.get(k, (np.zeros(3), 0))
        acc[k] = (s + p, n + 1)
    return np.array([s / n for s, n in acc.values()])


def literal_protocol(pred, gt, threshold, acc_trunc=0.2, comp_trunc=2.0, voxel=0.02, crop=True):
    """pred, gt: point sets (GT already culled). Crop pred to the GT box (z +- voxel), down-sample both,
    brute-force nearest neighbours, SHINE's truncations."""
    if crop:  # (SHINE grows z only; jaxmap grows x and y by the same voxel: metrics.CROP_XY_GROW_M)
        lo, hi = gt.min(0) - [voxel, voxel, voxel], gt.max(0) + [voxel, voxel, voxel]
        pred = pred[np.all((pred >= lo) & (pred <= hi), axis=1)]
    pred, gt = literal_down_sample(pred, voxel), literal_down_sample(gt, voxel)
    dist_p = np.full(len(pred), np.inf)  # each predicted point -> nearest GT point
    dist_r = np.full(len(gt), np.inf)    # each GT point -> nearest predicted point
    for a in range(0, len(pred), 256):   # the full distance matrix, 256 rows at a time
        d = np.sqrt(((pred[a:a + 256, None, :] - gt[None, :, :]) ** 2).sum(-1))
        dist_p[a:a + 256] = d.min(1)
        dist_r = np.minimum(dist_r, d.min(0))
    dist_p = dist_p[dist_p < acc_trunc]                                 # nn_correspondance(ignore_outlier=True)
    dist_r = np.where(dist_r < comp_trunc, dist_r, comp_trunc)          # nn_correspondance(ignore_outlier=False)
    acc, comp = 100 * dist_p.mean(), 100 * dist_r.mean()
    precision = 100 * np.mean(dist_p < threshold)
    recall = 100 * np.mean(dist_r < threshold)
    return {"accuracy_cm": acc, "completion_cm": comp, "chamfer_l1_cm": (acc + comp) / 2, "precision": precision,
            "completion_ratio": recall, "f_score": 2 * precision * recall / (precision + recall),
            "n_pred": len(dist_p), "n_gt": len(gt)}


def handmade_case(rng):
    """GT: a 2 m x 1.5 m ground and a 1.5 m x 1 m wall, a jittered 2.5 cm grid;
    pred: the ground 3 cm high, the wall 6 cm off, a missing corner, a far blob (> 0.2 m: dropped) and a few
    points outside the GT box (cropped)."""
    gx, gy = np.meshgrid(np.arange(0, 2.0, 0.025), np.arange(0, 1.5, 0.025), indexing="ij")
    ground = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    wx, wz = np.meshgrid(np.arange(0, 1.5, 0.025), np.arange(0.025, 1.0, 0.025), indexing="ij")
    wall = np.stack([wx.ravel(), np.full(wx.size, 1.5), wz.ravel()], 1)
    gt = np.concatenate([ground, wall]) + rng.normal(0, 0.002, (len(ground) + len(wall), 3))
    pg = ground[(ground[:, 0] < 1.6) | (ground[:, 1] < 1.0)] + [0.003, 0.004, 0.03]
    pw = wall + [0.0, -0.06, 0.0]
    blob = rng.uniform([0.5, 0.5, 0.4], [0.8, 0.8, 0.6], (300, 3))
    outside = rng.uniform([3.0, 0, 0], [4.0, 1, 1], (200, 3))
    return np.concatenate([pg, pw, blob, outside]), gt


def test_keys_and_types():
    gt = np.random.default_rng(0).random((1000, 3))
    m = evaluate(gt, gt)
    assert tuple(m)[:len(METRIC_KEYS)] == METRIC_KEYS and m["protocol"] == "shine"
    assert isinstance(m["n_pred"], int) and isinstance(m["n_gt"], int)
    json.dumps(m)


def test_evaluate_reproduces_a_literal_implementation():
    pred, gt = handmade_case(np.random.default_rng(0))
    for thr in (0.05, 0.1):
        m = evaluate(pred, gt, threshold_m=thr)
        ref = literal_protocol(pred, gt, thr)
        for k, v in ref.items():
            assert m[k] == pytest.approx(v, abs=2e-3), (k, m[k], v)
    # the case exercises every branch: dropped far points, clamped-free misses, threshold splits
    m = evaluate(pred, gt, threshold_m=0.05)
    assert m["n_pred_far"] > 250 and 2.5 < m["accuracy_cm"] < 4.5 and 0 < m["precision"] < 100
    assert m["completion_ratio"] < 99 and m["completion_cm"] > m["accuracy_cm"]
    # SHINE's completion clamps at 2 m: a prediction far away from everything reads 200 cm, not infinity
    far = evaluate(gt + [0, -0.5, 0.5], gt, threshold_m=0.1, down_sample_m=0.0)
    assert far["n_pred"] == 0 and far["accuracy_cm"] == float("inf")


def test_building_blocks_match_open3d():
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(1)
    # voxel_down_sample: the same voxel means as open3d (order aside)
    pts = rng.uniform(-1, 1, (20000, 3)) * [3, 2, 0.5]
    ref = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(0.05).points)
    ours = voxel_down_sample(pts, 0.05)
    assert ours.shape == ref.shape
    np.testing.assert_allclose(ours[np.lexsort(ours.T)], ref[np.lexsort(ref.T)], atol=1e-12)
    # crop: the same triangles (all three vertices in the box, bounds inclusive)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    lo, hi = np.array([-0.6, -2, -0.3]), np.array([2, 0.4, 0.7])
    o = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices), o3d.utility.Vector3iVector(mesh.faces))
    oc = o.crop(o3d.geometry.AxisAlignedBoundingBox(lo, hi))
    v, f = crop_mesh(mesh.vertices, mesh.faces, lo, hi)
    assert len(f) == len(oc.triangles) > 100
    assert trimesh.Trimesh(v, f).area == pytest.approx(oc.get_surface_area(), rel=1e-9)
    # sample_points_uniformly: open3d's per-triangle shares (area-weighted draws), uniform inside
    tris = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [7, 0, 0], [5, 3, 0], [10, 0, 0], [10.5, 0, 0],
                            [10, 0.3, 0]], [[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    n = 100_001
    s = sample_points_uniformly(tris.vertices, tris.faces, n, seed=3)
    o = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(tris.vertices), o3d.utility.Vector3iVector(tris.faces))
    so = np.asarray(o.sample_points_uniformly(n).points)
    assert len(s) == len(so) == n
    count = lambda p: [int(np.sum(p[:, 0] < 2.5)), int(np.sum((p[:, 0] > 2.5) & (p[:, 0] < 8))), int(np.sum(p[:, 0] > 8))]  # noqa: E731
    share = np.array([0.5, 3.0, 0.075]) / 3.575  # triangle areas / total
    for c in (count(s), count(so)):  # both within 5 standard deviations of the multinomial expectation
        assert np.all(np.abs(np.array(c) - n * share) < 5 * np.sqrt(n * share * (1 - share))), c
    np.testing.assert_allclose(s[s[:, 0] < 2.5].mean(0), [1 / 3, 1 / 3, 0], atol=0.01)  # uniform: the centroid


def test_evaluate_mesh_reproduces_open3d_pipeline():
    """The whole mesh path (crop, sample, down-sample) against open3d's own calls + the literal metrics."""
    o3d = pytest.importorskip("open3d")
    scene = ground_with_box(size=2.0, box=(0.5, 0.5, 0.5))
    scene = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(scene.vertices, scene.faces, 0.1))
    rng = np.random.default_rng(2)
    gt = sample_mesh(scene, 12_000, seed=1)
    gt = gt[gt[:, 0] < 0.8]  # the GT box leaves part of the mesh out: the crop matters
    pred = scene.copy()
    pred.apply_translation((0.0, 0.0, -0.015))
    m = evaluate_mesh(pred, gt, n_samples=50_000, threshold_m=0.05)
    lo, hi = gt.min(0) - 0.02, gt.max(0) + 0.02
    o = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(pred.vertices), o3d.utility.Vector3iVector(pred.faces))
    o = o.crop(o3d.geometry.AxisAlignedBoundingBox(lo, hi))
    samples = np.asarray(o.sample_points_uniformly(50_000).points)
    # (open3d samples points differently; the literal metrics on them agree within sampling noise)
    ref = literal_protocol(samples[rng.permutation(len(samples))], gt, 0.05, crop=False)
    for k in ("accuracy_cm", "completion_cm", "chamfer_l1_cm"):
        assert m[k] == pytest.approx(ref[k], rel=0.03), (k, m[k], ref[k])
    for k in ("precision", "completion_ratio", "f_score"):
        assert m[k] == pytest.approx(ref[k], abs=1.0), (k, m[k], ref[k])


def test_floor_is_below_a_3cm_offset():
    """The protocol floor (GT mesh as the prediction) against dense GT points is ~1 cm here; a mesh 3 cm off
    reads ~3 cm more. (Fine subdivision: the crop drops the triangles crossing the GT box, here the whole
    ground's rim.)"""
    scene = ground_with_box(size=4.0, box=(1.0, 1.0, 0.6))
    gt = sample_mesh(scene, 4 * 18 * 1000, seed=1)  # ~1000 per m^2
    floor = protocol_floor(scene, gt, n_samples=400_000, threshold_m=0.1, max_edge_m=0.05)
    off = scene.copy()
    off.apply_translation((0.0, 0.0, 0.03))
    m = evaluate_mesh(off, gt, n_samples=400_000, threshold_m=0.1)
    assert floor["chamfer_l1_cm"] < 2.0 and floor["f_score"] > 99.0, floor
    assert m["chamfer_l1_cm"] > floor["chamfer_l1_cm"] + 1.5, (m, floor)
    m5 = evaluate_mesh(off, gt, n_samples=400_000, threshold_m=0.02)
    assert m5["precision"] < 50.0


def test_signed_error_per_class():
    """GT: ground (class 0, normal up) and a box (class 1, outward normals); the prediction is the ground
    2 cm low and the box as it is."""
    scene = ground_with_box(size=4.0, box=(1.0, 1.0, 0.6))
    gt, fid = trimesh.sample.sample_surface(scene, 40_000, seed=1)
    nrm = scene.face_normals[fid]
    cls = (fid >= 2).astype(np.uint8)  # faces 0-1: the ground
    ground = trimesh.Trimesh(scene.vertices, scene.faces[:2])
    box = trimesh.Trimesh(scene.vertices, scene.faces[2:])
    ground.apply_translation((0, 0, -0.02))
    pred = np.concatenate([sample_mesh(ground, 200_000, seed=2), sample_mesh(box, 50_000, seed=3)])
    pred = voxel_down_sample(pred, 0.02)
    se = signed_error_by_class(pred, gt, nrm, cls, ["road", "box"])
    assert se["road"]["mean_cm"] == pytest.approx(-2.0, abs=0.3) and se["road"]["median_cm"] == pytest.approx(-2.0, abs=0.3)
    assert abs(se["box"]["mean_cm"]) < 0.3 and se["road"]["n"] > 1000 and se["box"]["n"] > 1000
    lifted = signed_error_by_class(pred + [0, 0, 0.05], gt, nrm, cls, ["road", "box"])
    assert lifted["road"]["mean_cm"] == pytest.approx(3.0, abs=0.3)


def test_culling_to_observed_region():
    # GT: a 20 m x 20 m ground; the scans cover the 3 m x 3 m square around the origin and the map
    # (prediction) the 4 m x 4 m one. Culled to 30 cm around the scan points (a 3.6 m square, inside the
    # prediction), completion is tiny and the ratio ~100 %; unculled, the unobserved 98 % dominates.
    big = trimesh.Trimesh([[-2, -2, 0], [18, -2, 0], [18, 18, 0], [-2, 18, 0]], [[0, 1, 2], [0, 2, 3]])
    small = trimesh.Trimesh([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], [[0, 1, 2], [0, 2, 3]])
    small = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(small.vertices, small.faces, 0.05))  # (crop)
    seen = trimesh.Trimesh([[-1.5, -1.5, 0], [1.5, -1.5, 0], [1.5, 1.5, 0], [-1.5, 1.5, 0]], [[0, 1, 2], [0, 2, 3]])
    gt = sample_mesh(big, 400_000, seed=1)
    scans = sample_mesh(seen, 20_000, seed=5)
    raw = evaluate_mesh(small, gt, n_samples=200_000)
    culled = evaluate_mesh(small, gt, n_samples=200_000, observed_points=scans, cull_distance_m=0.3)
    assert raw["completion_cm"] > 100.0  # (clamped at 2 m per point)
    assert raw["completion_ratio"] < 10.0
    assert culled["completion_cm"] < 2.0
    assert culled["completion_ratio"] > 99.0
    # eval radius: keep GT within 1.5 m of the sensor positions (one sensor at the origin).
    r = evaluate_mesh(small, gt, n_samples=200_000, observed_points=scans, sensor_positions=[[0, 0, 1.0]],
                      eval_radius_m=1.5)
    assert r["n_gt"] < culled["n_gt"] / 2
    with pytest.raises(DataError, match="sensor_positions"):
        evaluate_mesh(small, gt, n_samples=1000, eval_radius_m=1.5)


def test_empty_prediction_gives_infinite_accuracy():
    gt = np.random.default_rng(0).random((100, 3))
    m = evaluate(np.zeros((0, 3)), gt)
    assert m["accuracy_cm"] == float("inf") and m["f_score"] == 0.0 and m["n_pred"] == 0
    assert m["completion_cm"] == pytest.approx(200.0)


def test_sample_mesh_is_deterministic_and_area_weighted():
    mesh = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 2, 0], [5, 0, 0], [8, 0, 0], [5, 2, 0]], [[0, 1, 2], [3, 4, 5]])
    a = sample_mesh(mesh, 40_000, seed=3)
    assert np.array_equal(a, sample_mesh(mesh, 40_000, seed=3)) and not np.array_equal(a, sample_mesh(mesh, 40_000, seed=4))
    assert np.mean(a[:, 0] < 2.5) == pytest.approx(0.25, abs=0.01)
    b = sample_points_uniformly(mesh.vertices, mesh.faces, 40_000, seed=3)
    assert np.array_equal(b, sample_points_uniformly(mesh.vertices, mesh.faces, 40_000, seed=3))
    assert np.mean(b[:, 0] < 2.5) == pytest.approx(0.25, abs=0.01)
    with pytest.raises(DataError, match="zero faces"):
        sample_mesh(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)), 10)


def test_evaluate_mesh_file_errors(tmp_path):
    with pytest.raises(DataError, match="not found"):
        evaluate_mesh_file(tmp_path / "missing.ply", tmp_path)
    empty = tmp_path / "empty.ply"
    empty.write_bytes(trimesh.Trimesh(np.zeros((3, 3)), np.zeros((0, 3), int)).export(file_type="ply"))
    os.makedirs(tmp_path / "seq", exist_ok=True)
    with pytest.raises(DataError, match="gt_points.ply"):
        evaluate_mesh_file(empty, tmp_path / "seq")
    from jaxmap.io import write_points_ply

    write_points_ply(tmp_path / "seq" / "gt_points.ply", np.zeros((10, 3), np.float32))
    with pytest.raises(DataError, match="zero faces"):
        evaluate_mesh_file(empty, tmp_path / "seq")
    with pytest.raises(DataError, match="protocol"):
        evaluate_mesh_file(empty, tmp_path / "seq", protocol="chamfer")


def test_small_city_floor_and_signed_error(small_city, tmp_path, capsys):
    """Integration with jaxmap.io and the synthetic city: the GT mesh lowered by 2 cm, evaluated from files
    with the floor. Scans, GT points and GT mesh share one world frame (a wrong frame: metres), the floor
    is near the figures of a MaiCity-like city, and the signed error reads -2 cm on road and sidewalk."""
    from jaxmap.cli import main
    from jaxmap.io import read_mesh_ply
    from jaxmap.metrics import subdivide_mesh

    V, F = read_mesh_ply(small_city / "gt_mesh.ply")
    v, f = subdivide_mesh(V, F)
    low = tmp_path / "low.ply"
    trimesh.Trimesh(v - [0, 0, 0.02], f, process=False).export(low)
    assert main(["eval", str(low), "--gt", str(small_city), "--radius", "20", "--samples", "500000",
                 "--max-range", "20"]) == 0
    out = capsys.readouterr().out
    assert "floor" in out and "signed error" in out
    m = json.loads(out.strip().splitlines()[-1])
    fl = m["floor"]
    assert m["protocol"] == fl["protocol"] == "shine" and m["n_gt"] == fl["n_gt"] > 100_000
    assert fl["chamfer_l1_cm"] < 3.0 and fl["completion_ratio"] > 97.0 and fl["f_score"] > 96.0, fl
    assert m["chamfer_l1_cm"] > fl["chamfer_l1_cm"] + 0.5
    for c in ("road", "sidewalk"):
        assert m["signed_error_cm"][c]["mean_cm"] == pytest.approx(-2.0, abs=0.3), m["signed_error_cm"]
        assert abs(fl["signed_error_cm"][c]["mean_cm"]) < 0.3, fl["signed_error_cm"]
    assert set(m["signed_error_cm"]) >= {"road", "sidewalk", "building", "car"}


def test_far_share_and_precision_without_the_drop():
    """A floater > 0.2 m from the GT is invisible to the protocol's accuracy and precision; pred_far_share is
    its share of the down-sampled predicted points and precision_all / f_score_all count it as misses."""
    from jaxmap.metrics import format_metrics

    rng = np.random.default_rng(3)
    _, gt = handmade_case(rng)
    pred = gt + rng.normal(0, 0.01, gt.shape)
    clean = evaluate(pred, gt, threshold_m=0.05)
    assert clean["n_pred_far"] == 0 and clean["pred_far_share"] == 0.0
    assert clean["precision_all"] == clean["precision"] and clean["f_score_all"] == clean["f_score"]
    # a 30 cm x 30 cm x 20 cm blob floating in the middle of the GT box, > 0.3 m from the ground and the wall
    floater = rng.uniform([0.8, 0.5, 0.35], [1.1, 0.8, 0.55], (1000, 3))
    both = np.concatenate([pred, floater])
    m = evaluate(both, gt, threshold_m=0.05)
    lo, hi = crop_box(gt)
    ds = voxel_down_sample(both[np.all((both >= lo) & (both <= hi), axis=1)], 0.02)  # evaluate's crop and grid
    in_floater = (ds[:, 2] > 0.3) & (ds[:, 1] < 1.3)  # (the wall stands at y = 1.5)
    share = 100 * np.mean(in_floater)
    assert 1.0 < share < 30.0
    assert m["pred_far_share"] == pytest.approx(share, abs=1e-3)
    assert m["n_pred_far"] == int(np.sum(in_floater))
    # the protocol's own figures do not move; the ones without the drop do
    for k in ("accuracy_cm", "precision", "f_score", "completion_ratio"):
        assert m[k] == pytest.approx(clean[k], abs=0.05), k
    assert m["precision_all"] < m["precision"] - 1.0 and m["f_score_all"] < m["f_score"]
    assert m["precision_all"] == pytest.approx(m["precision"] * (1 - share / 100), abs=1e-2)
    r = m["completion_ratio"]
    assert m["f_score_all"] == pytest.approx(2 * m["precision_all"] * r / (m["precision_all"] + r), abs=1e-2)
    out = format_metrics(dict(m, floor=clean))
    assert "far %" in out and "P all %" in out and "F all %" in out
    row = out.splitlines()[2].split()
    assert row[0] == "mesh" and float(row[6]) == pytest.approx(m["pred_far_share"], abs=0.01)
    assert float(row[7]) == pytest.approx(m["precision_all"], abs=0.01)
    assert "ghost surface" not in out
    g = format_metrics(dict(m, ghost_area_m2={"car": 3.25, "pedestrian": 0.5, "total": 3.75}))
    assert "ghost surface (m^2): car 3.25, pedestrian 0.50, total 3.75" in g


def test_ground_truth_read_in_pieces_keeps_what_culling_it_whole_keeps(tmp_path):
    """`read_gt_culled` (a run's evaluation: the GT file read and culled piece by piece) keeps exactly the
    points, normals and classes that `cull_gt` of the whole file keeps, and the GT it keeps for the ghost
    test gives the ghost area that all of the GT gives: a mesh wall inside a car's grown box, 12 cm from a
    GT wall 20 cm outside the box (static surface), counts as ghost if those GT points are left out."""
    from jaxmap.io import write_points_ply
    from jaxmap.metrics import cull_gt, read_gt
    from jaxmap.metrics.protocol import GtCuller
    from jaxmap.metrics.sequence import read_gt_culled
    from jaxmap.moving import Boxes, ghost_area

    rng = np.random.default_rng(0)
    g = np.arange(0.0, 1.5001, 0.05)
    wall = np.stack(np.meshgrid([3.2], np.arange(1.0, 3.0001, 0.05), g, indexing="ij"), -1).reshape(-1, 3)
    gt = np.concatenate([rng.uniform(-10, 10, (5000, 3)), wall]).astype(np.float32)
    nrm = rng.normal(size=gt.shape).astype(np.float32)
    cls = rng.integers(0, 8, len(gt)).astype(np.uint8)
    write_points_ply(tmp_path / "gt_points.ply", gt, nrm, cls)
    observed, sensors = rng.uniform(-6, 6, (400, 3)), np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    cull = dict(observed_points=observed, cull_distance_m=1.0, sensor_positions=sensors, eval_radius_m=8.0)
    car = Boxes(params=np.array([[2.0, 2.0, 0.0, 0.0, 2.0, 1.0, 1.5]]), kind=np.zeros(1, np.int64),
                frame=np.zeros(1, np.int64), obj=np.zeros(1, np.int64), kinds=("car",))
    got = read_gt_culled(tmp_path, GtCuller(**cull), car, chunk=333)
    whole = read_gt(tmp_path)
    kept, idx = cull_gt(whole["points"], return_index=True, **cull)
    assert got["count"] == len(gt) and 100 < len(kept) < len(gt) // 2, len(kept)
    np.testing.assert_array_equal(got["points"], kept)
    np.testing.assert_array_equal(got["normals"], whole["normals"][idx])
    np.testing.assert_array_equal(got["classes"], whole["classes"][idx])
    # the mesh: a ghost roof inside the box (1.6 x 0.8 m) and a wall 12 cm in front of the GT wall
    v = np.array([[1.2, 1.6, 0.9], [2.8, 1.6, 0.9], [2.8, 2.4, 0.9], [1.2, 2.4, 0.9],
                  [3.08, 1.6, 0.2], [3.08, 2.4, 0.2], [3.08, 2.4, 1.2], [3.08, 1.6, 1.2]])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    all_gt = ghost_area(v, f, whole["points"], car)["total"]
    assert 1.1 < all_gt < 1.3, all_gt  # the roof (1.28 m2, less where a random GT point is within 15 cm)
    assert ghost_area(v, f, got["near_moving"], car)["total"] == all_gt
    assert ghost_area(v, f, got["near_moving"][got["near_moving"][:, 0] < 3.1], car)["total"] > all_gt + 0.5
