"""DynamicMap's point scores (jaxmap.metrics.dynamic): SA = static points kept / static points, DA = dynamic
points removed / dynamic points, of the points a run trained on, on a hand-made frame and through a whole
`jaxmap map` run (metrics.json, `jaxmap eval`, the suite table)."""
import json
import types

import numpy as np
import pytest

from jaxmap.metrics.dynamic import PointScores, dynamic_labels, format_scores, scores_of_run
from jaxmap.moving import Boxes, load_moving_objects

CAR = (4.0, 2.0, 1.5)  # length, width, height


def car_box(x=10.0, y=0.0, z=0.0, yaw=0.0):
    return Boxes(np.array([[x, y, z, yaw, *CAR]]), np.zeros(1, np.int64), np.zeros(1, np.int64),
                 np.zeros(1, np.int64), ("car",))


def sensor_pose(yaw=np.pi / 2, t=(1.0, -2.0, 1.7)):
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def test_labels_and_scores_of_a_hand_made_frame():
    """A car box 4 x 2 x 1.5 m at (10, 0), the points given in the world and moved into a rotated sensor
    frame. The labels: inside grown by 0.1 m on the sides and on top, the road under and beside the car
    static. A 0.2 m inflation, or one that also grows the box downwards (the ground under the car
    dynamic), or boxes not moved into the sensor frame, fail; so do swapped SA and DA."""
    world = np.array([
        [9.0, 1.05, 0.8],    # 5 cm beyond the car's side: dynamic (within 0.1 m)
        [11.9, -0.5, 1.58],  # 8 cm over its roof: dynamic
        [10.0, 0.0, 0.7],    # inside: dynamic
        [8.1, 0.0, 0.3],     # its rear, 10 cm in from its end: dynamic
        [9.0, 1.15, 0.8],    # 15 cm beyond its side: static (a 0.2 m inflation would take it)
        [10.0, 0.0, 1.65],   # 15 cm over its roof: static
        [10.0, 0.3, 0.02],   # the road under it: static (a box grown downwards would take it)
        [9.5, 1.05, 0.05],   # the road beside it, within 0.1 m of its side: static
        [20.0, 0.0, 0.8],    # far away: static
        [7.95, 0.0, 0.05],   # the road behind it: static
    ])
    expected = np.array([1, 1, 1, 1, 0, 0, 0, 0, 0, 0], bool)
    T = sensor_pose()
    points_s = (world - T[:3, 3]) @ T[:3, :3]  # world -> sensor frame: R^T (p - t)
    labels = dynamic_labels(points_s, T, car_box())
    np.testing.assert_array_equal(labels, expected)
    assert not dynamic_labels(points_s, np.eye(4), car_box()).any()  # (the pose is applied)
    # 6 static points, 5 kept -> SA 83.33 %; 4 dynamic, 3 removed -> DA 75 %
    kept = np.array([1, 0, 0, 0, 1, 1, 1, 0, 1, 1], bool)
    sc = PointScores()
    sc.add(labels, kept)
    sc.add(labels[:0], None)  # an empty frame counts as a frame and nothing else
    r = sc.result()
    assert (r["static_points"], r["static_kept"], r["dynamic_points"], r["dynamic_removed"]) == (6, 5, 4, 3)
    assert r["sa_percent"] == pytest.approx(500 / 6) and r["da_percent"] == pytest.approx(75.0)
    assert r["frames"] == 2 and r["inflate_m"] == 0.1 and r["ground_m"] == 0.1
    everything = PointScores()
    everything.add(labels)  # a mapper that does not say what it trained on kept everything
    assert everything.result()["sa_percent"] == 100.0 and everything.result()["da_percent"] == 0.0
    with pytest.raises(ValueError, match="same points"):
        sc.add(labels, kept[:3])
    line = format_scores(r)
    assert "SA 83.33 %" in line and "DA 75.00 %" in line


def test_a_run_counts_the_points_it_trained_on(small_parking_city, tmp_path, monkeypatch, capsys):
    """`jaxmap map` on the small city with the parking cars (frames 8, 10, 12, 14: positions differ from
    the sequence's frame numbers), with a mapper that trains on all but every 7th point: metrics.json's
    "dynamic_points" equal the counts of the prepared points labelled here by brute force against each
    frame's own boxes (a run that used the position, not the frame number, or ignored "kept", fails), the
    map sense's kept and removed by the void voxels of the run's final map (some of the car that left
    are: a map sense that ignored them fails);
    `jaxmap eval` prints them for that data and not for another; the suite table shows them."""
    from jaxmap.bench import n3_suite
    from jaxmap.cli import main
    from jaxmap.config import load_config
    from jaxmap.frame_loop import SubmitSteps
    from jaxmap.io import open_sequence
    from jaxmap.metrics import format_metrics
    from jaxmap.metrics.dynamic import voxel_keys
    from jaxmap.n3.scan import MapStart
    from jaxmap.n3.submap_mapper import load_map

    real_init = SubmitSteps.__init__

    def six_of_seven(self, mapper, on_finished=None):  # the run's scores see each frame as if the map trained
        real_init(self, mapper,                         # on 6 of its 7 points (the map itself is untouched)
                  lambda frame, record, kept: on_finished(frame, record, np.arange(len(kept)) % 7 != 0))

    monkeypatch.setattr(SubmitSteps, "__init__", six_of_seven)
    sel = ["--set", "data.begin_frame=8", "--set", "data.end_frame=16", "--set", "data.every_frame=2"]
    out = tmp_path / "run"
    assert main(["map", "configs/city.yaml", "--data", str(small_parking_city), "--out", str(out), "--no-progress",
                 "--set", "train.iters=3", "--set", "train.nv=64", "--set", "eval.n_samples=20000",
                 "--set", "mesh.resolution_m=0.2"] + sel) == 0
    got = json.loads((out / "metrics.json").read_text())["dynamic_points"]
    # the reference: the same prepared points, each frame's boxes by its frame number, tested one by one
    cfg = load_config("configs/city.yaml", [f"data.path={small_parking_city}", "data.begin_frame=8",
                                            "data.end_frame=16", "data.every_frame=2"])
    seq = open_sequence(small_parking_city, begin_frame=8, end_frame=16, every_frame=2)
    objects = load_moving_objects(small_parking_city)
    final = load_map(out / "checkpoint")  # the run's final map: which of its voxels are void
    void = voxel_keys(final.void_voxels())
    counts, by_map = np.zeros(4, int), np.zeros(4, int)
    for i in range(len(seq)):
        raw = seq.frame(i)
        ready, pose = MapStart.of(cfg).prepare(raw.points, raw.pose, i)
        fr = types.SimpleNamespace(points=ready.points, pose=pose, index=raw.index)
        w = fr.points.astype(np.float64) @ fr.pose[:3, :3].T + fr.pose[:3, 3]
        dyn = np.zeros(len(w), bool)
        for x, y, z, yaw, ln, wd, h in objects.boxes_at(fr.index).params:
            d = w[:, :2] - (x, y)
            a, b = d @ (np.cos(yaw), np.sin(yaw)), d @ (-np.sin(yaw), np.cos(yaw))
            dyn |= (np.abs(a) <= ln / 2 + 0.1) & (np.abs(b) <= wd / 2 + 0.1) & (w[:, 2] >= z + 0.1) \
                & (w[:, 2] <= z + h + 0.1)
        kept = np.arange(len(w)) % 7 != 0
        counts += [(~dyn).sum(), (~dyn & kept).sum(), dyn.sum(), (dyn & ~kept).sum()]
        gone = np.isin(voxel_keys(final.voxel_coords(fr.points, fr.pose)), void)  # its voxel is void at the end
        by_map += [(~dyn).sum(), (~dyn & ~gone).sum(), dyn.sum(), (dyn & gone).sum()]
    assert counts[2] > 100  # (the cars are in these frames)
    assert by_map[3] > 0  # (the car driving to its parking place: the map voided where frame 8 saw it)
    tr = got["trained"]  # the trained-on sense: the points the mapper trained on
    assert [tr["static_points"], tr["static_kept"], tr["dynamic_points"], tr["dynamic_removed"]] == list(counts)
    assert got["frames"] == 4 and tr["sa_percent"] == pytest.approx(100 * counts[1] / counts[0])
    # the headline is the map's sense (a point is removed when its voxel is void in the final map): the
    # same points, kept or removed by the final map's void voxels, not by what was trained on
    assert got["sense"] == "map"
    assert [got["static_points"], got["static_kept"], got["dynamic_points"], got["dynamic_removed"]] == list(by_map)
    # `jaxmap eval` shows the run's scores beside its metrics, for the data the run mapped only
    capsys.readouterr()
    assert main(["eval", str(out / "mesh.ply"), "--gt", str(small_parking_city), "--samples", "20000",
                 "--no-floor"]) == 0
    printed = capsys.readouterr().out
    assert f"SA {got['sa_percent']:.2f} % ({got['static_kept']} of {got['static_points']} static kept)" in printed
    assert "ghost surface" in printed
    assert scores_of_run(out / "mesh.ply", tmp_path) is None
    m = {"accuracy_cm": 1.0, "completion_cm": 1.0, "chamfer_l1_cm": 1.0, "completion_ratio": 1.0, "f_score": 1.0}
    assert "dynamic points" not in format_metrics(m)
    # the suite table: SA / DA columns and on the traffic city's line
    row = {k: 1.0 for k in n3_suite.KEYS}
    n3_suite.print_suite("jaxmap", {"grid_s1_hdl64": row, "grid_s1_hdl64_traffic": row}, {}, {},
                         {"grid_s1_hdl64_traffic": {"dynamic_points": got}})
    printed = capsys.readouterr().out
    assert "SA %" in printed and f"SA {got['sa_percent']:.2f} %, DA {got['da_percent']:.2f} %" in printed


def test_map_sense_counts_the_points_whose_voxels_the_final_map_holds():
    """The map sense (DynamicMap's, of the output map): a point is removed when its leaf voxel is void at
    the end, whatever happened in its frame. Two frames, four voxels; the second voxel turns void."""
    from jaxmap.metrics.dynamic import voxel_keys

    vox = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [-3, 5, 7]])
    sc = PointScores()
    # frame 1: a static point in voxel 0, two dynamic ones in voxel 1 (trained on), one static in voxel 3
    sc.add(np.array([False, True, True, False]), None, voxel_keys(vox[[0, 1, 1, 3]]))
    # frame 2: a dynamic point in voxel 2 (not trained on: it fell in void), a static one in voxel 1
    sc.add(np.array([True, False]), np.array([False, True]), voxel_keys(vox[[2, 1]]))
    r = sc.result(voxel_keys(vox[[1, 2]]))
    assert r["sense"] == "map"
    assert (r["static_points"], r["static_kept"], r["dynamic_points"], r["dynamic_removed"]) == (3, 2, 3, 3)
    assert r["trained"]["dynamic_removed"] == 1 and r["trained"]["static_kept"] == 3
    assert "of the final map" in format_scores(r) and "trained on: SA 100.00 %, DA 33.33 %" in format_scores(r)
    assert sc.result()["sense"] == "trained"   # no map: the trained sense alone
