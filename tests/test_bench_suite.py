"""`jaxmap bench n3 --suite` bookkeeping: rows merge city by city, twins compare, subsets print; `jaxmap bench
slam --suite`'s rows."""
import json

import pytest

from jaxmap.bench import n3_suite as S


def _summary(c_l1, ghost=None, far=2.0):
    m = {k: 1.0 for k in S.KEYS}
    m.update(chamfer_l1_cm=c_l1, pred_far_share=far, precision_all=90.0, f_score_all=91.0)
    if ghost is not None:
        m["ghost_area_m2"] = {"car": ghost, "total": ghost}
    return {"metrics": m, "store_frames_held": 1.0}


def test_rows_are_recorded_city_by_city_and_twins_compare(tmp_path, capsys):
    path = str(tmp_path / "suite.json")
    S._record(path, "jaxmap", "grid_s1_hdl64_traffic", _summary(3.1, ghost=20.0, far=5.0))  # a traffic-only run first
    v = S._record(path, "jaxmap", "grid_s1_hdl64", _summary(3.0))
    assert list(v["rows"]) == ["grid_s1_hdl64", "grid_s1_hdl64_traffic"]           # suite order, nothing lost
    assert v["mean"]["chamfer_l1_cm"] == 3.0                            # the clean cities only
    S._record(path, "band_only", "grid_s1_hdl64", _summary(2.9))
    saved = json.load(open(path))
    assert set(saved) == {"jaxmap", "band_only"} and saved["jaxmap"]["rows"]["grid_s1_hdl64"]["chamfer_l1_cm"] == 3.0
    S.print_suite("jaxmap", v["rows"], v["floors"], v["signed_error_cm"], v["beyond_protocol"])
    out = capsys.readouterr().out
    assert "grid_s1_hdl64_traffic / grid_s1_hdl64: C-L1 3.10 / 3.00 cm (x1.033), far 5.00 / 2.00 %" in out
    assert "ghost m2: car 20.0, total 20.0" in out and "mean (1 clean)" in out
    assert S.summarize({"grid_s1_hdl64_traffic": v["rows"]["grid_s1_hdl64_traffic"]}, S.CLEAN) == {"mean": {}, "worst": {}}


def test_a_traffic_city_from_an_older_generator_is_made_again(tmp_path):
    """The suite's traffic city asks for the parking cars: a directory whose meta.json says its traffic
    has no roles (before issue 30) or no parking cars is synthesized again, one that has them is kept."""
    kw = S.SUITE["grid_s1_hdl64_traffic"]
    assert kw.get("parking")
    d = tmp_path / "c"
    d.mkdir()
    for traffic, older in (({"cars": 5, "pedestrians": 3}, True), ({"cars": 5, "roles": {}}, True),
                           ({"cars": 7, "roles": {}, "parking": {}}, False)):
        (d / "meta.json").write_text(json.dumps({"traffic": traffic}))
        assert S._older_traffic(str(d), kw) == older, traffic
    assert not S._older_traffic(str(d), S.SUITE["grid_s1_hdl64"])


def test_a_slam_street_row_reads_the_run_and_compares_it_with_the_true_pose_map(small_city, tmp_path, capsys):
    """`jaxmap bench slam --suite`'s row from a run's files: a trajectory 2 cm high and tilted 0.1 deg
    reads as such, the ratio is SLAM's C-L1 over the true-pose map's, the loop seconds are summed and their
    largest kept; the table's worst row takes the largest size, the lowest F-score."""
    import numpy as np

    from jaxmap.bench import slam_suite
    from jaxmap.io import open_sequence
    from jaxmap.slam.level import rotvec_matrix

    gt = np.asarray(open_sequence(str(small_city)).poses, np.float64)
    est = gt.copy()
    est[:, 2, 3] += 0.02
    est[:, :3, :3] = rotvec_matrix(np.radians([0.1, 0, 0])) @ est[:, :3, :3]
    run = tmp_path / "run"
    run.mkdir()
    np.savetxt(run / "trajectory_kitti.txt", est[:, :3].reshape(len(est), 12))
    road = {"road": {"mean_cm": 2.1}, "sidewalk": {"mean_cm": -0.4}}
    (run / "metrics.json").write_text(json.dumps({"chamfer_l1_cm": 3.3, "f_score": 90.0, "signed_error_cm": road}))
    (run / "slam.json").write_text(json.dumps({"loop_map_s": 7.0, "loops": [{"map_s": 5.0}, {"map_s": 2.0}],
                                              "wall_s_per_frame": 1.2}))
    true = {"metrics": {"chamfer_l1_cm": 3.0, "signed_error_cm": {"road": {"mean_cm": 0.3}}}, "wall_s_per_frame": 0.8}
    r = slam_suite.street_row(str(small_city), str(run), true, {"metrics": {"chamfer_l1_cm": 3.15}})
    assert r["offline_ratio"] == pytest.approx(1.05)
    assert r["dz_mean_cm"] == pytest.approx(2.0) and r["dz_min_cm"] == pytest.approx(2.0)
    assert r["tilt_deg"] == pytest.approx(0.1, abs=1e-6) and r["ratio"] == pytest.approx(1.1)
    assert (r["road_cm"], r["true_road_cm"], r["loop_s"], r["loop_max_s"]) == (2.1, 0.3, 7.0, 5.0)
    other = dict(r, ratio=1.3, f_score=95.0, dz_mean_cm=-3.0)
    slam_suite.print_rows("x", {"a": r, "b": other})
    worst = [line for line in capsys.readouterr().out.splitlines() if line.startswith("worst")][0].split()
    assert worst[4] == "-3.00" and worst[9] == "1.30" and worst[12] == "90.00"   # dz mean, ratio, F


def test_the_offline_street_is_the_street_at_the_slam_poses(small_city, tmp_path):
    """The offline map's sequence: the same scans (linked), and poses that read back as the SLAM run's
    LiDAR trajectory through the street's non-identity calibration (camera poses in poses.txt)."""
    import numpy as np

    from jaxmap.bench import slam_suite
    from jaxmap.io import open_sequence
    from jaxmap.slam.level import rotvec_matrix

    seq = open_sequence(str(small_city))
    est = np.asarray(seq.poses, np.float64).copy()
    est[:, :3, 3] += [0.05, -0.02, 0.03]
    est[:, :3, :3] = rotvec_matrix(np.radians([0.2, -0.1, 1.0])) @ est[:, :3, :3]
    run = tmp_path / "run"
    run.mkdir()
    np.savetxt(run / "trajectory_kitti.txt", est[:, :3].reshape(len(est), 12))
    off = open_sequence(slam_suite.offline_street(str(small_city), str(run), str(tmp_path / "off")))
    assert np.allclose(off.poses, est, atol=1e-9)
    assert np.array_equal(off[3].points, seq[3].points)
