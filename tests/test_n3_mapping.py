"""N3 mapping end to end: bounded memory, resume == uninterrupted, mesh quality, run directory."""
import json

import numpy as np

from analytic_lidar import corridor_scan, pose_at
from jaxmap.config import load_config
from jaxmap.n3.mapper import N3Mapper

SMALL = ["train.iters=8", "train.nv=128", "train.np_per_voxel=8", "preprocess.max_range_m=10.0",
         "preprocess.vox_down_m=0.2", "window.initial_blocks=4096", "mesh.min_component_faces=0"]


def _mapper(extra=()):
    return N3Mapper(load_config("configs/city.yaml", SMALL + list(extra)))


def test_store_stays_bounded_on_a_long_straight_trajectory():
    """Voxel window: the store stops growing once the window is full; replay keeps growing."""
    sizes = {}
    for mode in ("voxel", "replay"):
        m = _mapper([f"window.mode={mode}", "train.iters=1"])
        pairs = []
        for i in range(24):  # 24 frames x 3 m = 72 m, window radius 10 m
            pairs.append(m.add_frame(corridor_scan(3.0 * i, max_range=10.0), pose_at(3.0 * i))["store_pairs"])
        sizes[mode] = pairs
    v, r = sizes["voxel"], sizes["replay"]
    assert max(v[12:]) <= 1.1 * max(v[6:12])          # flat once full (window ~ 7 frames long)
    assert r[-1] > 2.5 * v[-1]                        # the replay ablation grows with the sequence
    assert r[-1] > 1.8 * r[11]


def test_resume_equals_uninterrupted(tmp_path):
    frames = [(corridor_scan(1.5 * i, max_range=10.0), pose_at(1.5 * i)) for i in range(6)]
    a = _mapper()
    for pts, pose in frames:
        a.add_frame(pts, pose)
    b = _mapper()
    for pts, pose in frames[:3]:
        b.add_frame(pts, pose)
    b.save(str(tmp_path / "ckpt"))
    c = N3Mapper.load(str(tmp_path / "ckpt"))
    for pts, pose in frames[3:]:
        c.add_frame(pts, pose)
    q = np.random.default_rng(0).uniform([0, -6, 0], [8, 6, 2], size=(2000, 3))
    sa, va = a.sdf(q)
    sc, vc = c.sdf(q)
    np.testing.assert_array_equal(va, vc)
    np.testing.assert_array_equal(sa, sc)
    np.testing.assert_array_equal(np.asarray(a.state.feature_table), np.asarray(c.state.feature_table))
    np.testing.assert_array_equal(np.asarray(a.state.feature_opt.moments), np.asarray(c.state.feature_opt.moments))


def test_corridor_sdf_is_accurate_near_the_surfaces():
    """After a few frames, the SDF near the ground and walls is within 3 cm of the truth."""
    # sigma 0.1 spreads samples over the 2-20 cm band queried here; the city default (0.05) meshes
    # better but supervises that band less, and |grad| drifts ~30 % from 1 there (see configs/city.yaml).
    m = _mapper(["train.iters=40", "train.nv=512", "sampling.sigma_m=0.1"])
    for i in range(5):
        m.add_frame(corridor_scan(1.0 * i, beams=32, steps=512, max_range=10.0), pose_at(1.0 * i))
    rng = np.random.default_rng(1)
    q = np.concatenate([
        np.stack([rng.uniform(3, 7, 500), rng.uniform(-3, 3, 500), rng.uniform(0.02, 0.2, 500)], 1),
        np.stack([rng.uniform(2, 6, 500), rng.uniform(5.8, 5.98, 500), rng.uniform(0.5, 1.5, 500)], 1)])
    true = np.minimum(q[:, 2], 6.0 - np.abs(q[:, 1]))
    s, v = m.sdf(q)
    assert v.mean() > 0.9
    err = np.abs(s - true)[v]
    assert np.median(err) < 0.03, np.median(err)
    _, g = m.sdf_grad(q[:500])
    assert np.median(np.abs(np.linalg.norm(g, axis=1) - 1.0)) < 0.2  # roughly an SDF, not just a sign


def test_small_city_maps_to_a_mesh_close_to_ground_truth(small_city, tmp_path, monkeypatch):
    """The whole `jaxmap map` run on the small synthetic city (every 4th scan of its 10 Hz drive: 16 frames
    ~3.9 m apart): run directory layout and quality.

    The bounds separate N3's normal-guided labels from the projective ones: with the standard protocol
    (floor here C-L1 3.72 cm, F 95.5 %) this run scores C-L1 6.7 cm / F 80.9 % with `normal` labels and
    25.2 cm / 58.1 % with `sampling.label_mode=projective` (measured, same settings; on the drive before
    issue 25, 15 frames 4.7 m apart: 7.2 cm / 78.4 % and 44.9 cm / 28.0 %)."""
    from jaxmap.cli import main

    out = tmp_path / "run"
    rc = main(["map", "configs/city.yaml", "--data", str(small_city), "--out", str(out), "--no-progress",
               "--set", "data.every_frame=4", "--set", "train.iters=20", "--set", "train.nv=512",
               "--set", "eval.n_samples=200000"])
    assert rc == 0
    for f in ("config.yaml", "mesh.ply", "metrics.json", "timing.json", "run.json"):
        assert (out / f).exists(), f
    m = json.loads((out / "metrics.json").read_text())
    assert m["chamfer_l1_cm"] < 9.5, m
    assert m["f_score"] > 74.0, m
    assert m["floor"]["chamfer_l1_cm"] < m["chamfer_l1_cm"], m
    # Regression of the allocation: the voxels and corner rows allocated are integers that depend only
    # on where the samples fall. On the small city before issue 25 (15 frames) this run matched the
    # engine before its rewrite as pure functions (jaxmap 0.1, commit 13ce444) to one voxel (67681 leaf
    # voxels, 164385 corner rows; with the packages of 2026-11, jax 0.10.2, scipy 1.17.1, numpy 2.4.6,
    # the engine at the commit before issue 21 allocated 67680). The figures below are the same engine's
    # (unchanged by issue 25) on the 10 Hz drive's every 4th scan. On the earlier drive another random
    # stream of the near-surface samples gave the same count, so the check pins the allocation itself:
    # one key lost or allocated twice per frame would move it by ~15 voxels and ~40 rows. The veil filter
    # (issue 30) drops the mixed pixels at depth edges before allocation: 66011-66013 voxels and
    # 157775-157787 rows over runs with and without a warm compile cache (the programs XLA builds differ
    # in their last float bits; without the veil, veil_m=0: 66082 and 158173, the figures before it). On
    # the sensor's beam table, with the prediction across beams in inverse range (issue 38), it drops
    # fewer true returns: 66062 voxels and 157901 rows, cold and warm (same run: C-L1 7.01 / F 79.6 %;
    # before it 7.08 / 80.6 %).
    frames = json.loads((out / "timing.json").read_text())["frames"]
    assert abs(frames[-1]["leaf_voxels"] - 66062) <= 6 and abs(frames[-1]["feature_rows"] - 157901) <= 24, frames[-1]
    # Re-extract a mesh from the checkpoint at another resolution (a relative run path, as users type it).
    monkeypatch.chdir(tmp_path)
    assert main(["mesh", "run", "--res", "0.2"]) == 0
    assert (out / "mesh_0.2.ply").exists()


def test_ctrl_c_leaves_a_checkpoint_and_resume_finishes_the_same_map(small_city, tmp_path, monkeypatch):
    """KeyboardInterrupt during frame 2 -> checkpoint of frames 0-1; `--resume` gives the same map as
    an uninterrupted run."""
    from jaxmap.cli import main
    from jaxmap.frame_loop import SubmitSteps

    args = ["--no-progress", "--no-mesh", "--data", str(small_city), "--set", "data.end_frame=4", "--set",
            "train.iters=3", "--set", "train.nv=64"]
    assert main(["map", "configs/city.yaml", "--out", str(tmp_path / "full")] + args) == 0

    real = SubmitSteps.submit  # where the frame loop hands each frame to the map
    submitted = []

    def interrupt_at_2(self, *a, **kw):  # Ctrl-C as frame 2 is handed to the map (frames 0-1 in flight)
        if len(submitted) == 2:
            raise KeyboardInterrupt
        submitted.append(1)
        return real(self, *a, **kw)

    monkeypatch.setattr(SubmitSteps, "submit", interrupt_at_2)
    assert main(["map", "configs/city.yaml", "--out", str(tmp_path / "cut")] + args) == 130
    meta = json.loads((tmp_path / "cut" / "checkpoint" / "2" / "meta.json").read_text())
    assert meta["frame"] == 2
    monkeypatch.setattr(SubmitSteps, "submit", real)
    assert main(["map", "--resume", str(tmp_path / "cut"), "--no-progress", "--no-mesh"]) == 0
    a = N3Mapper.load(str(tmp_path / "full" / "checkpoint"))
    b = N3Mapper.load(str(tmp_path / "cut" / "checkpoint"))
    assert int(b.state.frame) == 4
    np.testing.assert_array_equal(np.asarray(a.state.feature_table), np.asarray(b.state.feature_table))


def test_a_finished_run_is_evaluated_without_its_map(small_city, tmp_path, monkeypatch):
    """`finish_run` writes the mesh, then releases the map's arrays (what the end of a run held beside the
    ground truth it reads) and only then evaluates the mesh file: the evaluation finds the map gone, and the
    records stay for timing.json."""
    from jaxmap import finish
    from jaxmap.io import open_sequence

    m = _mapper([f"data.path={small_city}", "eval.n_samples=50000"])
    seq = open_sequence(str(small_city))
    for i in range(4):
        m.add_frame(seq[i].points, seq[i].pose)
    seen = []
    real = finish.evaluate_run_mesh
    monkeypatch.setattr(finish, "evaluate_run_mesh",
                        lambda path, cfg, **kw: seen.append(m.state is None) or real(path, cfg, **kw))
    out = finish.finish_run(m, m.cfg, str(tmp_path))
    assert seen == [True] and m.state is None
    assert out["faces"] > 0 and out["metrics"] == json.load(open(tmp_path / "metrics.json"))
    assert len(json.load(open(tmp_path / "timing.json"))["frames"]) == 4
