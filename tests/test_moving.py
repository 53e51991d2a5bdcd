"""jaxmap.moving and what `jaxmap eval` does with moving objects: the reader of moving_objects.json /
pedestrians.json, inside_boxes against a brute-force reference, the ghost area on meshes with known answers,
and static-only observations (a scan's hits inside its own frame's boxes are not observations)."""
import json

import numpy as np
import pytest
import trimesh

from jaxmap.errors import DataError
from jaxmap.moving import Boxes, ghost_area, inside_boxes, load_moving_objects

CAR = (4.5, 1.8, 1.5)


def write_objects(d, objects, frames):
    doc = {"format": "jaxmap moving objects v1", "frames": frames, "objects": objects}
    (d / "moving_objects.json").write_text(json.dumps(doc))
    return d / "moving_objects.json"


def car_track(frames=11, yaw=0.3, x0=-5.0, step=1.0):
    """A car driving along its heading (yaw) through the origin, one pose per frame."""
    t = x0 + step * np.arange(frames)
    return [[float(s * np.cos(yaw)), float(s * np.sin(yaw)), 0.0, yaw] for s in t]


def box_mesh(size, x, y, z_base, yaw):
    m = trimesh.creation.box(extents=size)
    m.apply_transform(trimesh.transformations.rotation_matrix(yaw, [0, 0, 1]))
    m.apply_translation((x, y, z_base + size[2] / 2))
    return m


def road_points(half=15.0, step=0.04):
    g = np.arange(-half, half + 1e-9, step)
    x, y = np.meshgrid(g, g, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)


def random_boxes(rng, n):
    params = np.column_stack([rng.uniform(-5, 5, (n, 2)), rng.uniform(-1, 1, n), rng.uniform(-np.pi, np.pi, n),
                              rng.uniform(0.3, 4.5, n), rng.uniform(0.3, 2.0, n), rng.uniform(0.5, 2.0, n)])
    return Boxes(params, rng.integers(0, 2, n), np.arange(n), np.arange(n), ("car", "pedestrian"))


def brute_inside(points, params, inflate):
    """[B,N] bool: point n inside box b grown by inflate, one box at a time in its own frame."""
    out = []
    for x, y, z0, yaw, ln, w, h in params:
        R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        loc = (points[:, :2] - [x, y]) @ R  # world -> box frame: R^T (p - c)
        out.append((np.abs(loc[:, 0]) <= ln / 2 + inflate) & (np.abs(loc[:, 1]) <= w / 2 + inflate)
                   & (points[:, 2] >= z0 - inflate) & (points[:, 2] <= z0 + h + inflate))
    return np.array(out)


def test_inside_boxes_matches_brute_force():
    rng = np.random.default_rng(0)
    boxes = random_boxes(rng, 60)
    pts = rng.uniform([-8, -8, -2], [8, 8, 4], (60_000, 3))
    centres = boxes.centres()
    for inflate in (0.0, 0.1, 0.5):
        ref = brute_inside(pts, boxes.params, inflate)
        ins, which = inside_boxes(pts, boxes, inflate, return_box=True)
        np.testing.assert_array_equal(ins, ref.any(0))
        assert 1000 < ins.sum() < len(pts) - 1000  # a real mix of inside and outside
        assert np.array_equal(which >= 0, ins)
        # the chosen box contains the point and has the nearest centre among those that do
        i = np.flatnonzero(ins)
        assert ref[which[i], i].all()
        d = np.linalg.norm(pts[None, i] - centres[:, None], axis=2)
        d[~ref[:, i]] = np.inf
        np.testing.assert_allclose(d[which[i], np.arange(len(i))], d.min(0))
    assert not inside_boxes(pts, boxes.subset(np.zeros(60, bool))).any()
    assert inside_boxes(np.zeros((0, 3)), boxes).shape == (0,)


def test_inside_boxes_on_many_boxes_and_points():
    
    rng = np.random.default_rng(1)
    n = 2000
    params = np.column_stack([rng.uniform(-100, 100, (n, 2)), np.zeros(n), rng.uniform(-np.pi, np.pi, n),
                              np.full(n, 4.5), np.full(n, 1.8), np.full(n, 1.5)])
    boxes = Boxes(params, np.zeros(n, np.int64), np.arange(n), np.arange(n), ("car",))
    pts = rng.uniform([-100, -100, -1], [100, 100, 3], (1_000_000, 3))
    ins = inside_boxes(pts, boxes, 0.1)  # (the candidate pieces of 2000 boxes x 1 M points, bounded memory)
    sub = rng.choice(len(pts), 20_000, replace=False)
    np.testing.assert_array_equal(ins[sub], brute_inside(pts[sub], params, 0.1).any(0))


def test_load_moving_objects_formats_and_errors(tmp_path):
    assert load_moving_objects(tmp_path) is None
    poses = car_track(5)
    poses[2] = None
    write_objects(tmp_path, [{"id": 7, "kind": "car", "size_xyz_m": list(CAR), "poses": poses},
                             {"id": 8, "kind": "pedestrian", "size_xyz_m": [0.5, 0.4, 1.75],
                              "poses": [[1, 2, 0.15, 0.0]] * 5}], 5)
    mo = load_moving_objects(tmp_path)
    assert mo.n_frames == 5 and mo.kinds == ("car", "pedestrian") and len(mo.boxes) == 9
    b = mo.boxes_at(2)
    assert len(b) == 1 and b.obj[0] == 8 and mo.kinds[b.kind[0]] == "pedestrian"
    np.testing.assert_allclose(mo.boxes_at(3).params[0], [*poses[3], *CAR])
    assert len(mo.boxes_of_frames([0, 1])) == 4
    with pytest.raises(DataError, match="moving_objects.json"):
        mo.boxes_at(5)
    # the older pedestrians.json of `jaxmap synth city --pedestrians`
    d = tmp_path / "old"
    d.mkdir()
    (d / "pedestrians.json").write_text(json.dumps({"size_xyz_m": [0.5, 0.4, 1.75], "base_z_m": 0.15, "frames": [
        [{"xy": [1.0, 2.0], "yaw": 0.5}, {"xy": [3.0, 4.0], "yaw": 0.0}], [{"xy": [1.1, 2.0], "yaw": 0.5}]]}))
    old = load_moving_objects(d)
    assert old.kinds == ("pedestrian",) and old.n_frames == 2 and len(old.boxes_at(0)) == 2
    np.testing.assert_allclose(old.boxes_at(1).params[0], [1.1, 2.0, 0.15, 0.5, 0.5, 0.4, 1.75])
    # malformed files: a DataError naming the file
    bad = [
        "{not json",
        json.dumps({"format": "something else", "frames": 1, "objects": []}),
        json.dumps({"format": "jaxmap moving objects v1", "frames": 2,
                    "objects": [{"id": 0, "kind": "car", "size_xyz_m": list(CAR), "poses": [[0, 0, 0, 0]]}]}),
        json.dumps({"format": "jaxmap moving objects v1", "frames": 1,
                    "objects": [{"id": 0, "kind": "car", "size_xyz_m": [4, -1, 1], "poses": [[0, 0, 0, 0]]}]}),
        json.dumps({"format": "jaxmap moving objects v1", "frames": 1,
                    "objects": [{"id": 0, "kind": "car", "size_xyz_m": list(CAR), "poses": [[0, 0, 0]]}]}),
        json.dumps({"format": "jaxmap moving objects v1", "frames": 1,
                    "objects": [{"id": 0, "size_xyz_m": list(CAR), "poses": [[0, 0, 0, 0]]}]}),
        json.dumps([1, 2]),
    ]
    for text in bad:
        (tmp_path / "moving_objects.json").write_text(text)
        with pytest.raises(DataError, match="moving_objects.json"):
            load_moving_objects(tmp_path)
    (d / "pedestrians.json").write_text(json.dumps({"size_xyz_m": [0.5, 0.4], "base_z_m": 0, "frames": []}))
    with pytest.raises(DataError, match="pedestrians.json"):
        load_moving_objects(d)


def ghost_scene(tmp_path):
    """A 30 m road (GT points, z = 0), a car driving through the origin at yaw 0.3 (frames 0-10, x from -5 to
    5 along its heading) and a pedestrian standing at (8, -8)."""
    write_objects(tmp_path, [{"id": 0, "kind": "car", "size_xyz_m": list(CAR), "poses": car_track()},
                             {"id": 1, "kind": "pedestrian", "size_xyz_m": [0.5, 0.4, 1.75],
                              "poses": [[8.0, -8.0, 0.0, 0.0]] * 11}], 11)
    return load_moving_objects(tmp_path), road_points()


def test_ghost_area_of_a_ghost_car(tmp_path):
    mo, road = ghost_scene(tmp_path)
    boxes = mo.boxes
    yaw = 0.3
    # the car left as a ghost where it was at frame 7 (2 m along its heading): its surface above 0.15 m
    # of the road is ghost; the bottom face and a 15 cm strip of the sides are within 0.15 m of the road GT
    ghost = box_mesh(CAR, 2 * np.cos(yaw), 2 * np.sin(yaw), 0.0, yaw)
    ghost = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(ghost.vertices, ghost.faces, 0.5))
    ln, w, h = CAR
    expected = ln * w + 2 * (ln + w) * (h - 0.15)
    g = ghost_area(ghost.vertices, ghost.faces, road, boxes)
    assert g["car"] == pytest.approx(expected, rel=0.03) and g["pedestrian"] == 0.0
    assert g["total"] == pytest.approx(g["car"])
    # with no static GT near it, the whole box surface
    far_gt = road + [0, 0, -10.0]
    assert ghost_area(ghost.vertices, ghost.faces, far_gt, boxes)["car"] == pytest.approx(ghost.area, rel=0.03)
    # the same box where no object ever was: no ghost
    elsewhere = box_mesh(CAR, -8.0, 8.0, 0.0, yaw)
    assert ghost_area(elsewhere.vertices, elsewhere.faces, road, boxes)["total"] == 0.0
    # the road itself as predicted surface (one big quad through every box): within 0.15 m of the GT
    plane = trimesh.Trimesh([[-15, -15, 0.02], [15, -15, 0.02], [15, 15, 0.02], [-15, 15, 0.02]], [[0, 1, 2], [0, 2, 3]])
    assert ghost_area(plane.vertices, plane.faces, road, boxes)["total"] < 0.01
    # a pedestrian ghost beside it
    ped = box_mesh((0.5, 0.4, 1.75), 8.0, -8.0, 0.0, 0.0)
    both = trimesh.util.concatenate([ghost, ped, plane])
    g2 = ghost_area(both.vertices, both.faces, road, boxes)
    assert g2["car"] == pytest.approx(g["car"], abs=0.01)
    assert g2["pedestrian"] == pytest.approx(0.5 * 0.4 + 2 * 0.9 * 1.6, rel=0.03)
    # deterministic
    assert ghost_area(both.vertices, both.faces, road, boxes) == g2


def write_sequence(d, frames_world, sensor_xy):
    """A KITTI sequence (no calib: poses are the LiDAR poses): frame i's scan is frames_world[i] (world
    frame) seen from a sensor at (sensor_xy[i], 1.5)."""
    from jaxmap.io import write_poses, write_scan_bin

    (d / "velodyne").mkdir(parents=True)
    poses = []
    for i, (pts, xy) in enumerate(zip(frames_world, sensor_xy)):
        T = np.eye(4)
        T[:3, 3] = [xy[0], xy[1], 1.5]
        poses.append(T)
        write_scan_bin(d / "velodyne" / f"{i:06d}.bin", np.asarray(pts) - T[:3, 3])
    write_poses(d / "poses.txt", np.array(poses))


def test_observed_points_exclude_hits_inside_the_same_frames_boxes(tmp_path):
    from jaxmap.metrics import observed_points_of

    # the object: a 4 m x 2 m x 1.5 m box at A = (0, 0) in frame 0, at B = (10, 0) in frame 1, absent in frame 2
    write_objects(tmp_path, [{"id": 0, "kind": "car", "size_xyz_m": [4.0, 2.0, 1.5],
                              "poses": [[0.0, 0.0, 0.0, 0.0], [10.0, 0.0, 0.0, 0.0], None]}], 3)
    ground = road_points(half=3.0, step=0.5) + [5.0, 6.0, 0.0]  # static hits away from both boxes
    a0 = np.array([[0.5, 0.2, 1.0]])    # frame 0, inside its own box at A: a hit on the car
    b0 = np.array([[10.5, 0.3, 1.0]])   # frame 0, where the car is at frame 1: static then
    b1 = np.array([[9.5, -0.3, 1.0]])   # frame 1, inside its own box at B
    a1 = np.array([[-0.5, -0.4, 0.8]])  # frame 1, where the car was at frame 0
    a2 = np.array([[1.5, 0.9, 1.2]])    # frame 2: no car
    edge = np.array([[2.05, 0.0, 1.0]])  # frame 0, 5 cm outside the box: inside the 0.1 m inflation
    write_sequence(tmp_path, [np.concatenate([ground, a0, b0, edge]), np.concatenate([ground, b1, a1]),
                              np.concatenate([ground, a2])], [(0, -5), (5, -5), (10, -5)])

    def has(obs, p):
        return bool(np.any(np.linalg.norm(obs - p, axis=1) < 1e-4))

    obs, sensors = observed_points_of(tmp_path, voxel_m=0.01)
    assert len(sensors) == 3 and has(obs, ground[0])
    assert not has(obs, a0) and not has(obs, b1) and not has(obs, edge)
    assert has(obs, b0) and has(obs, a1) and has(obs, a2)
    # the selection indexes the boxes by the real frame number (frame 1 is the car at B)
    obs, _ = observed_points_of(tmp_path, voxel_m=0.01, begin_frame=1)
    assert not has(obs, b1) and has(obs, a1) and has(obs, a2) and not has(obs, b0)
    # without the exclusion every hit is an observation
    obs, _ = observed_points_of(tmp_path, voxel_m=0.01, exclude_moving=False)
    assert all(has(obs, p) for p in (a0, b0, b1, a1, a2, edge))


def test_eval_file_reports_ghost_area_and_floor(tmp_path, capsys):
    """`jaxmap eval` on a sequence with a moving car: the mesh with the car's ghost gets the car's area above
    0.15 m of the road, the GT mesh as prediction (the floor) ~0; the figures are printed."""
    from jaxmap.cli import main
    from jaxmap.io import write_mesh_ply, write_points_ply

    yaw = 0.3
    write_objects(tmp_path, [{"id": 0, "kind": "car", "size_xyz_m": list(CAR), "poses": car_track(3, step=5.0)}], 3)
    road = road_points(half=10.0, step=0.04)
    write_points_ply(tmp_path / "gt_points.ply", road.astype(np.float32))
    quad = trimesh.Trimesh([[-10, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]], [[0, 1, 2], [0, 2, 3]])
    write_mesh_ply(tmp_path / "gt_mesh.ply", quad.vertices, quad.faces)
    # scans: the road around the sensors, and the car's roof at its pose of each frame
    scans = []
    for x, y, _, _ in car_track(3, step=5.0):
        roof = trimesh.sample.sample_surface(box_mesh(CAR, x, y, 0.0, yaw), 500, seed=1)[0]
        scans.append(np.concatenate([road[::7], roof]))
    write_sequence(tmp_path, scans, [(0, -4)] * 3)
    ghost = box_mesh(CAR, 0.0, 0.0, 0.0, yaw)  # the car at frame 1 (x = 0)
    pred = trimesh.util.concatenate([quad, ghost])
    trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(pred.vertices, pred.faces, 0.5)).export(tmp_path / "pred.ply")
    assert main(["eval", str(tmp_path / "pred.ply"), "--gt", str(tmp_path), "--samples", "300000"]) == 0
    out = capsys.readouterr().out
    m = json.loads(out.strip().splitlines()[-1])
    ln, w, h = CAR
    assert m["ghost_area_m2"]["car"] == pytest.approx(ln * w + 2 * (ln + w) * (h - 0.15), rel=0.03)
    assert m["floor"]["ghost_area_m2"]["total"] < 0.01
    assert "ghost surface (m^2): car" in out and "P all %" in out
    assert m["floor"]["pred_far_share"] == 0.0 and m["floor"]["precision_all"] == m["floor"]["precision"]
    assert main(["eval", str(tmp_path / "pred.ply"), "--gt", str(tmp_path), "--samples", "100000", "--no-floor",
                 "--no-ghost"]) == 0
    assert "ghost_area_m2" not in json.loads(capsys.readouterr().out.strip().splitlines()[-1])
