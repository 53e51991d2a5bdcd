"""`jaxmap slam` with `n3_loop: submaps` (jaxmap.runs.slam_n3, jaxmap.n3.following): a loop correction
moves each submap as a rigid body by its frames' correction (not its inverse), each pass maps into
submaps of its own, and the frames of the submap being mapped that still moved against it are re-added."""
import numpy as np

from analytic_lidar import corridor_scan, pose_at
from jaxmap.config import SlamConfig, load_config
from jaxmap.n3 import scan
from jaxmap.n3.submap_mapper import SubmapMapper
from jaxmap.n3.following import FollowingMap, FollowRule, submap_pose

SMALL = ["train.iters=6", "train.nv=128", "train.np_per_voxel=8", "preprocess.max_range_m=10.0",
         "preprocess.vox_down_m=0.2", "window.initial_blocks=4096", "mesh.min_component_faces=0",
         "submaps.enabled=true", "submaps.length_m=6", "submaps.blend_m=3", "submaps.revisit=false"]


def _rigid(deg: float, t) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = t
    return T


def test_submap_pose_fits_the_frames_correction():
    rng = np.random.default_rng(0)
    local = np.stack([_rigid(rng.uniform(-30, 30), rng.uniform(-5, 5, 3)) for _ in range(6)])
    G = _rigid(40.0, [3.0, -1.0, 0.2])
    np.testing.assert_allclose(submap_pose(G @ local, local), G, atol=1e-12)
    # a correction that bends the frames a little: the rigid fit lies between the frames' own ones
    bent = np.stack([_rigid(0.5 * i, [0.01 * i, 0, 0]) @ G @ L for i, L in enumerate(local)])
    fit = submap_pose(bent, local)
    err = np.linalg.norm((fit @ local)[:, :3, 3] - bent[:, :3, 3], axis=1)
    assert err.max() < np.linalg.norm((G @ local)[:, :3, 3] - bent[:, :3, 3], axis=1).max() + 1e-9


def test_a_loop_moves_each_submap_by_its_correction_not_its_inverse(tmp_path):
    """20 frames of a corridor in submaps of 6 m driven; the 'pose graph' then turns the first submaps'
    frames by 25 degrees and shifts them, the last submap's frames by another correction, and bends two
    frames of the last submap 5 cm further. Each submap must take its correction (the wall mapped at
    y = 6 m reads 0 where the correction puts it, and not where its inverse would), every frame end at
    its new pose, and exactly the two bent frames be re-added (their old pairs removed)."""
    cfg = load_config("configs/city_slam.yaml", ["n3_loop=submaps", "n3_loop_min_move_m=0.02", "n3_track=false",
                                                 "n3_config=configs/city.yaml"], schema=SlamConfig)
    mcfg = load_config("configs/city.yaml", SMALL)
    frames = [(corridor_scan(1.0 * i, max_range=10.0), pose_at(1.0 * i)) for i in range(20)]
    m = SubmapMapper(mcfg, first_scan=frames[0], directory=str(tmp_path / "subs"))
    fm = FollowingMap(m, FollowRule.of(cfg))
    for i, (pts, pose) in enumerate(frames):
        p, n, _, img = scan.preprocess(pts, np.eye(4), m.cfg.preprocess, i, image=m.static.evidence)
        fm.add(scan.PreparedScan(p, n, img), pose)
        fm.settle()
    sub = np.asarray(fm.submap)
    assert len(set(sub)) >= 3 and np.all(np.diff(sub) >= 0), sub
    last = sub[-1]
    wall = np.stack([np.linspace(0.5, 18.5, 60), np.full(60, 6.0), np.full(60, 1.0)], 1)
    before, ok = m.sdf(wall)
    assert ok.all() and np.abs(before).max() < 0.1

    G = {k: _rigid(25.0, [2.0, -3.0, 0.1]) if k != last else _rigid(-10.0, [1.0, 0.5, 0.0]) for k in set(sub)}
    traj = np.stack([G[k] @ pose for k, (_, pose) in zip(sub, frames)])
    bent = [i for i in range(20) if sub[i] == last][:2]
    for i in bent:
        traj[i, 1, 3] += 0.05
    rec = fm.correct(traj)
    assert rec["queued"] == 2 and rec["left_beyond_elsewhere"] == 0 and rec["submaps_moved"] == len(set(sub)), rec
    assert fm.pending == bent
    for k in set(sub):
        idx = sub == k
        got = m.submaps.infos[k].pose @ fm.mapped_at[np.nonzero(idx)[0][0]]
        fit = submap_pose(traj[idx], np.stack([fm.mapped_at[i] for i in np.nonzero(idx)[0]]))
        np.testing.assert_allclose(m.submaps.infos[k].pose, fit, atol=1e-9)
        if k != last:  # a rigid correction: exact
            np.testing.assert_allclose(got, traj[np.nonzero(idx)[0][0]], atol=1e-9)
    # the wall where each submap's correction carries it (each point read where its own submap rules)
    owner = np.clip(np.searchsorted([frames[i][1][0, 3] for i in range(20)], wall[:, 0]) - 1, 0, 19)
    moved = np.stack([(G[sub[o]] @ np.append(w, 1.0))[:3] for o, w in zip(owner, wall)])
    inner = np.abs(wall[:, 0] - np.round(wall[:, 0] / 6.0) * 6.0) > 1.5  # away from the seams
    after, ok_after = m.sdf(moved[inner])
    assert ok_after.all() and np.abs(after).max() < 0.1, np.abs(after).max()
    wrong = np.stack([(np.linalg.inv(G[sub[o]]) @ np.append(w, 1.0))[:3] for o, w in zip(owner, wall)])
    s_wrong, ok_wrong = m.sdf(wrong[inner])
    assert (~ok_wrong).mean() > 0.3 or np.abs(s_wrong[ok_wrong]).mean() > 0.5
    # the two bent frames re-added, one after each frame: their old pairs gone, they sit at their poses
    removed, forget = [], m.forget_frames
    m.forget_frames = lambda fr: removed.append((list(fr), forget(fr))) or removed[-1][1]
    old_counts = [fm.counter[i] for i in bent]
    for _ in bent:
        fm.readd(1, traj)
    assert not fm.pending
    assert [r[0] for r in removed] == [[c] for c in old_counts] and all(r[1] > 0 for r in removed), removed
    for i in bent:
        np.testing.assert_allclose(m.submaps.infos[last].pose @ fm.mapped_at[i], traj[i], atol=1e-9)
        assert fm.submap[i] == last
    # a frame added again is on the submap's path once (appended again, it would lengthen the path driven)
    assert len(m.submaps.infos[last].path) == int(np.sum(sub == last))


def assert_same_run(ref, cut, frames: int):
    """The SLAM runs in directories ref and cut made the same trajectory (to 1e-9 m: KISS-ICP's own
    run-to-run noise is 1e-15) and the same map (SDF at points of the road around the drive, the sensor
    1.73 m above it, to 1e-5 m). Returns their maps."""
    from jaxmap.n3.submap_mapper import load_map

    a, b = (np.loadtxt(r / "trajectory_kitti.txt") for r in (ref, cut))
    assert a.shape == b.shape == (frames, 12)
    np.testing.assert_allclose(b, a, atol=1e-9)
    ma, mb = load_map(str(ref / "checkpoint")), load_map(str(cut / "checkpoint"))
    rng = np.random.default_rng(0)
    q = a[:, [3, 7, 11]][rng.integers(0, frames, 2000)] + np.c_[rng.uniform(-4, 4, (2000, 2)),
                                                                rng.uniform(-2.0, -1.4, 2000)]
    (sa, va), (sb, vb) = ma.sdf(q), mb.sdf(q)
    np.testing.assert_array_equal(va, vb)
    assert va.mean() > 0.5
    np.testing.assert_allclose(sb[vb], sa[va], atol=1e-5)
    return ma, mb


def test_slam_stopped_by_ctrl_c_and_resumed_gives_the_run_without_the_stop(small_noisy_city, tmp_path, monkeypatch,
                                                                          capsys):
    """`jaxmap slam --no-mesh` on submaps (tracking on), stopped by SIGINT after frame 8 of 16, then
    `--resume`d: the same trajectory (to 1e-9 m: KISS-ICP's own run-to-run noise is 1e-15) and the same map
    (SDF at points along the drive to 1e-5 m) as the run without the stop; `jaxmap mesh` meshes it. Without
    the front end's state (a fresh KISS-ICP, a new pose graph) the trajectory jumps by centimetres; without
    the map's, tracking and the map differ."""
    import json
    import os
    import signal

    from jaxmap.cli import main
    from jaxmap.runs import slam_n3 as n3slam

    sets = [f"--set={s}" for s in ("n3.train.iters=10", "n3.train.nv=256", "data.end_frame=16", "n3_loop=submaps",
                                   "n3_submap_m=6")]
    base = ["slam", "city_slam", "--data", str(small_noisy_city), "--no-progress", "--no-mesh", *sets]
    ref, cut = tmp_path / "ref", tmp_path / "cut"
    assert main([*base, "--out", str(ref)]) == 0
    step = n3slam.N3SlamStep.submit

    def stop_after_8(self, frame):
        out = step(self, frame)
        if frame.position == 8:
            os.kill(os.getpid(), signal.SIGINT)
        return out

    monkeypatch.setattr(n3slam.N3SlamStep, "submit", stop_after_8)
    assert main([*base, "--out", str(cut)]) == 130
    assert f"jaxmap slam --resume {cut}" in capsys.readouterr().err
    assert json.loads((cut / "run.json").read_text())["status"] == "interrupted"
    monkeypatch.setattr(n3slam.N3SlamStep, "submit", step)
    assert main(["slam", "--resume", str(cut), "--no-progress", "--no-mesh"]) == 0
    ma, mb = assert_same_run(ref, cut, 16)
    assert len(ma.submaps.infos) == len(mb.submaps.infos) >= 2
    assert not (ref / "mesh.ply").exists() and not (ref / "metrics.json").exists()   # --no-mesh
    assert main(["mesh", str(cut), "--res", "0.2"]) == 0 and (cut / "mesh_0.2.ply").stat().st_size > 10_000
    ja, jb = (json.loads((r / "slam.json").read_text()) for r in (ref, cut))
    assert ja["frames"] == jb["frames"] == 16 and ja["tracked_ok"] == jb["tracked_ok"]


SLOW_SLAM = """
import sys, time
from jaxmap.runs import slam_n3 as n3slam
real = n3slam.N3SlamStep.submit
def slow(self, frame):
    out = real(self, frame)
    time.sleep(0.4)  # leaves time to kill the run between its checkpoints
    return out
n3slam.N3SlamStep.submit = slow
from jaxmap.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_slam_killed_by_sigkill_resumes_from_its_last_checkpoint(small_noisy_city, tmp_path):
    """`jaxmap slam` (the default map of submaps, tracking on) saves itself every `checkpoint_every` (4)
    frames; killed by SIGKILL after its first save (no handler runs: what a crash or the OOM killer does),
    `--resume` goes on from that save and ends with the trajectory (to 1e-9 m) and the map (SDF at points
    along the drive, to 1e-5 m) of the run that was never stopped. Without the periodic save there is no
    state to resume (`slam_state.pkl` missing: the run is lost); the scans for loop corrections come from
    `slam_scans/`, written a file a frame, not from the saved state."""
    import json
    import os
    import pickle
    import signal
    import subprocess
    import sys
    import time

    from jaxmap.cli import main
    from jaxmap.runs.slam_n3 import SCANS_DIR
    from jaxmap.runs.slam_step import STATE_FILE

    sets = [f"--set={s}" for s in ("n3.train.iters=10", "n3.train.nv=256", "data.end_frame=14", "checkpoint_every=4")]
    base = ["slam", "city_slam", "--data", str(small_noisy_city), "--no-progress", "--no-mesh", *sets]
    ref, cut = tmp_path / "ref", tmp_path / "cut"
    assert main([*base, "--out", str(ref)]) == 0
    proc = subprocess.Popen([sys.executable, "-c", SLOW_SLAM, *base, "--out", str(cut)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not (cut / STATE_FILE).exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < 600, "no SLAM checkpoint after 600 s"
        time.sleep(0.02)
    proc.kill()
    proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    saved = pickle.loads((cut / STATE_FILE).read_bytes())
    # a save every 4 frames finished, the frame then in flight (its map program dispatched) settled into it
    assert 4 <= saved["frames"] < 14 and saved["frames"] % 4 in (0, 1), saved["frames"]
    assert len(saved["step"].scans._held) == 0   # the state carries the scans' count, not the scans
    assert len(os.listdir(cut / SCANS_DIR)) >= saved["frames"]
    assert json.loads((cut / "run.json").read_text())["status"] == "running"   # nothing ran at the kill
    assert main(["slam", "--resume", str(cut), "--no-progress", "--no-mesh"]) == 0
    assert_same_run(ref, cut, 14)
