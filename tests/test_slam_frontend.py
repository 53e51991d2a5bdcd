"""jaxmap.slam: ICP odometry, loop verification, pose graph (open3d convention), trajectory files, ATE,
and the streaming front end on the small synthetic room and city (with sensor noise)."""
import logging

import numpy as np
import pytest

pytest.importorskip("open3d")

from jaxmap.errors import DataError  # noqa: E402
from jaxmap.geometry import (make_pose, pose_change, random_rotation, rotation_from_axis_angle,  # noqa: E402
                             se3_inverse, yaw_rotation)
from jaxmap.io import open_sequence  # noqa: E402
from jaxmap.slam import (FrontEnd, FrontEndConfig, LoopConfig, Odometry, OdometryConfig, PoseGraph,  # noqa: E402
                         ate, find_candidates, icp, read_pose_snapshot, read_tum, verify, write_kitti,
                         write_tum)
from jaxmap.slam.odometry import Scan  # noqa: E402

ROOM_FRAMES = 30     # 12 degrees / 0.25 m per step around the room; the last frame is next to the first


def perturb(rng, trans_m, rot_deg):
    """A random rigid transform with the given translation norm and rotation angle."""
    t = rng.normal(size=3)
    return make_pose(rotation_from_axis_angle(rng.normal(size=3), np.radians(rot_deg)), t / np.linalg.norm(t) * trans_m)


def chain(T0, rels):
    poses = [np.asarray(T0, dtype=np.float64)]
    for R in rels:
        poses.append(poses[-1] @ R)
    return np.stack(poses)


@pytest.fixture(scope="module")
def noisy_room(tmp_path_factory):
    """A small room sequence (160 x 120 depth) of ROOM_FRAMES frames with 5 mm depth noise, closing a loop."""
    from jaxmap.synth.room import generate_room

    out = tmp_path_factory.mktemp("slam_room")
    generate_room(out, seed=0, small=True, n_frames=ROOM_FRAMES, noise_m=0.005)
    seq = open_sequence(out)
    return [f.points for f in seq], np.asarray(seq.poses)


@pytest.fixture(scope="module")
def noisy_city(tmp_path_factory):
    """The small city with 2 cm range noise, every 4th scan of its 10 Hz drive: 16 keyframes ~3.9 m and up
    to 28 deg apart around a block (the front end's hard case; at 10 Hz, 0.97 m and 7 deg, it is easy)."""
    from jaxmap.synth.city import generate_city

    out = tmp_path_factory.mktemp("slam_city")
    generate_city(out, seed=0, small=True, noise_m=0.02)
    seq = open_sequence(out, every_frame=4)
    return [f.points for f in seq], np.asarray(seq.poses)


# ------------------------------------------------------------------------------------------------
# pose graph
# ------------------------------------------------------------------------------------------------

def test_pose_graph_edge_convention_matches_open3d():
    """An edge (i, j, T_i^-1 T_j) holds two known poses in place, and pulls a displaced node back to its pose."""
    rng = np.random.default_rng(3)
    A = make_pose(random_rotation(rng), rng.normal(size=3))
    B = make_pose(random_rotation(rng), rng.normal(size=3) * 2)
    info = np.eye(6) * 100.0

    g = PoseGraph()
    g.add_node(A)
    g.add_node(B)
    g.add_odometry(0, 1, se3_inverse(A) @ B, info)
    poses = g.optimize(max_corr_m=0.1)
    assert np.abs(poses[0] - A).max() < 1e-9 and np.abs(poses[1] - B).max() < 1e-6

    # a displaced node 1 is brought back to B (node 0 is the fixed reference)
    g2 = PoseGraph()
    g2.add_node(A)
    g2.add_node(B @ perturb(rng, 0.3, 10.0))
    g2.add_odometry(0, 1, se3_inverse(A) @ B, info)
    poses = g2.optimize(max_corr_m=0.1)
    ang, dist = pose_change(poses[1], B)
    assert dist < 1e-4 and ang < 1e-4

    # the same check straight against open3d: PoseGraphEdge(source, target, X) is satisfied by
    # X = T_target^-1 @ T_source, and not by its inverse
    import open3d as o3d

    reg = o3d.pipelines.registration
    for X, ok in ((se3_inverse(A) @ B, True), (se3_inverse(B) @ A, False)):
        og = reg.PoseGraph()
        og.nodes.append(reg.PoseGraphNode(A))
        og.nodes.append(reg.PoseGraphNode(B @ perturb(rng, 0.2, 5.0)))
        og.edges.append(reg.PoseGraphEdge(1, 0, X, info, uncertain=False))
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        reg.global_optimization(og, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(),
                                reg.GlobalOptimizationOption(max_correspondence_distance=0.1, reference_node=0))
        assert (pose_change(np.asarray(og.nodes[1].pose), B)[1] < 1e-4) == ok


def test_pose_graph_loop_corrects_drifting_odometry():
    """A 20-node circle with biased, noisy odometry and one correct loop edge is pulled back to the truth."""
    rng = np.random.default_rng(0)
    n, radius = 20, 5.0
    gt = np.stack([make_pose(yaw_rotation(2 * np.pi * i / n + np.pi / 2),
                             [radius * np.cos(2 * np.pi * i / n), radius * np.sin(2 * np.pi * i / n), 0.0])
                   for i in range(n)])
    info = 1000.0 * np.diag([5.0, 5.0, 5.0, 1.0, 1.0, 1.0])       # like ICP's: ~n_corr * [|p|^2 I, I]
    rels = []
    g = PoseGraph()
    for i in range(1, n):
        true_rel = se3_inverse(gt[i - 1]) @ gt[i]
        # 0.5 degree yaw bias per step (drift) plus 2 cm / 0.2 degree noise
        drift = make_pose(yaw_rotation(np.radians(0.5)), [0.0, 0.0, 0.0]) @ perturb(rng, 0.02, 0.2)
        rels.append(true_rel @ drift)
    odo = chain(gt[0], rels)
    for T in odo:
        g.add_node(T)
    for i in range(1, n):
        g.add_odometry(i - 1, i, rels[i - 1], info)
    g.add_loop(0, n - 1, se3_inverse(gt[0]) @ gt[n - 1], info)
    # the loop disagrees with the chain by ~1 m / 10 deg: max_corr_m (the tolerated disagreement) is 2 m
    opt = g.optimize(max_corr_m=2.0)

    before, after = ate(odo, gt)["rmse_m"], ate(opt, gt)["rmse_m"]
    assert before > 0.5                      # the chain has drifted
    assert after < 0.1 and after < 0.2 * before
    assert g.loop_confidence[len(g.edges) - 1] > 0.25          # the loop edge was kept, not pruned
    assert pose_change(opt[0], gt[0])[1] < 1e-9                # reference node fixed
    # the loop edge is now (nearly) satisfied
    assert g.edge_errors()[-1][1] < 0.05


def test_isotropic_information_keeps_each_blocks_scale_and_drops_the_cross_terms(noisy_room):
    """ICP's information of two room views has strong rotation-translation cross terms (points metres
    from the sensor); `isotropic_information` keeps the mean eigenvalue of each block and nothing else."""
    from jaxmap.slam.frontend import isotropic_information
    pts, gt = noisy_room
    cfg = OdometryConfig()
    a, b = Scan(pts[0], cfg), Scan(pts[1], cfg)
    info = icp(b.points, b.normals, a.points, a.normals, se3_inverse(gt[0]) @ gt[1], 0.06).information
    cross = np.abs(info[:3, 3:]).max() / np.sqrt(np.abs(np.diag(info)[:3]).max() * np.abs(np.diag(info)[3:]).max())
    assert cross > 0.1                                           # ICP's is coupled
    iso = isotropic_information(info)
    assert np.allclose(iso, np.diag(np.diag(iso))) and np.all(np.diag(iso) > 0)
    assert np.isclose(np.trace(iso[:3, :3]), np.trace(info[:3, :3]))
    assert np.isclose(np.trace(iso[3:, 3:]), np.trace(info[3:, 3:]))
    assert np.allclose(iso[:3, :3], iso[0, 0] * np.eye(3)) and np.allclose(iso[3:, 3:], iso[3, 3] * np.eye(3))


def test_isotropic_edge_information_lets_the_loop_correct_the_drifting_room():
    """The pose graph the front end built on the drifting Kinect-noise room (every 6th frame of the
    300-frame room of `jaxmap bench slam --only drift`: 49 odometry edges and 3 loop edges with open3d's ICP
    information, the odometry poses and the true ones; tests/fixtures). With that information as is, the
    optimised trajectory is no better than odometry (the cross terms absorb the loop's correction); with
    `isotropic_information` the ATE drops by more than half."""
    import os

    from jaxmap.slam.frontend import isotropic_information

    g = np.load(os.path.join(os.path.dirname(__file__), "fixtures", "kinect_room_pose_graph.npz"))
    odo, truth = g["odometry"], g["truth"]

    def optimised(info_of):
        graph = PoseGraph()
        for P in odo:
            graph.add_node(P)
        for (i, j), T, info, loop in zip(g["edge_ij"], g["edge_T"], g["edge_info"], g["edge_loop"]):
            (graph.add_loop if loop else graph.add_odometry)(int(i), int(j), T, info_of(info))
        return ate(graph.optimize(max_corr_m=0.5), truth)["rmse_m"]

    before = ate(odo, truth)["rmse_m"]
    coupled, iso = optimised(lambda I: I), optimised(isotropic_information)
    # measured: odometry 12.9 cm, open3d's information 13.3 cm, isotropic 5.9 cm
    assert before > 0.10
    assert coupled > 0.8 * before
    assert iso < 0.5 * before and iso < 0.6 * coupled


# ------------------------------------------------------------------------------------------------
# ICP and odometry
# ------------------------------------------------------------------------------------------------

def test_icp_recovers_relative_pose_between_room_views(noisy_room):
    """Two consecutive noisy room views (12 deg, 0.25 m apart): ICP from a 5 cm / 2 deg off guess is within
    1 cm / 0.5 deg of the true relative pose, with a sane fitness and a symmetric PSD information matrix."""
    pts, gt = noisy_room
    cfg = OdometryConfig()
    rng = np.random.default_rng(1)
    for i in (5, 17):
        src, tgt = Scan(pts[i + 1], cfg), Scan(pts[i], cfg)
        true_T = se3_inverse(gt[i]) @ gt[i + 1]            # maps frame i+1 (source) into frame i (target)
        init = true_T @ perturb(rng, 0.05, 2.0)
        res = icp(src.points, src.normals, tgt.points, tgt.normals, init, max_corr_m=0.15)
        ang, dist = pose_change(true_T, res.T)
        assert dist < 0.01 and np.degrees(ang) < 0.5, (i, dist, np.degrees(ang))
        assert res.fitness > 0.7 and res.n_corr > 1000 and res.inlier_rmse < 0.05
        assert np.allclose(res.information, res.information.T) and np.linalg.eigvalsh(res.information)[0] > 0


def test_odometry_failure_keeps_constant_velocity(noisy_room, caplog):
    """A scan with too few points is not registered: a warning names the frame, the motion prior is kept."""
    pts, gt = noisy_room
    odo = Odometry(OdometryConfig(), initial_pose=gt[0])
    odo.step(pts[0])
    s1 = odo.step(pts[1])
    assert s1.ok and pose_change(s1.pose, gt[1])[1] < 0.01
    with caplog.at_level(logging.WARNING, logger="jaxmap"):
        s2 = odo.step(pts[2][:20])
    assert not s2.ok
    assert np.allclose(s2.rel, s1.rel) and np.allclose(s2.pose, s1.pose @ s1.rel)
    assert any("frame 2" in r.getMessage() and "constant-velocity" in r.getMessage() for r in caplog.records)


# ------------------------------------------------------------------------------------------------
# loop closure
# ------------------------------------------------------------------------------------------------

def test_find_candidates_matches_brute_force():
    rng = np.random.default_rng(5)
    K = 60
    steps = [make_pose(yaw_rotation(rng.normal() * 0.3), [rng.uniform(0.2, 0.6), 0, 0]) for _ in range(K - 1)]
    kp = chain(np.eye(4), steps)
    for cfg in (LoopConfig(radius_m=1.5, min_gap=10, max_candidates=100),
                LoopConfig(radius_m=3.0, min_gap=5, max_candidates=3),
                LoopConfig(radius_m=0.0, min_gap=1, max_candidates=100)):
        for cur in range(0, K, 7):
            pose = kp[cur] @ make_pose(np.eye(3), rng.normal(size=3) * 0.3)
            got = find_candidates(kp, cur, pose, cfg)
            brute = []
            for j in range(K):
                d = np.linalg.norm(kp[j, :3, 3] - pose[:3, 3])
                if cur - j >= cfg.min_gap and d <= cfg.radius_m:
                    brute.append((d, j))
            assert got == [j for _, j in sorted(brute)][: cfg.max_candidates]
            assert all(cur - j >= cfg.min_gap for j in got)


def test_verify_rejects_false_loops_and_accepts_true_revisits(noisy_room, noisy_city):
    """Scans from different places, claimed to be at the same pose, are rejected (their overlap alone
    would pass: box room seen from opposite sides, parallel streets); true revisits from a drifted guess
    are accepted with an accurate relative pose."""
    rng = np.random.default_rng(2)
    cases = [("room", noisy_room, OdometryConfig(), LoopConfig(), [(0, 15), (4, 19), (22, 7)], (ROOM_FRAMES - 1, 0),
              (0.05, 2.0), (0.02, 0.5)),
             ("city", noisy_city, OdometryConfig.lidar(), LoopConfig.lidar(), [(0, 8), (3, 12), (10, 6)], (15, 0),
              (0.5, 2.0), (0.15, 0.5))]
    for name, (pts, gt), ocfg, lcfg, false_pairs, (i, j), drift, tol in cases:
        scans = {k: Scan(pts[k], ocfg) for k in {a for p in false_pairs for a in p} | {i, j}}
        for a, b in false_pairs:
            assert np.linalg.norm(gt[a][:3, 3] - gt[b][:3, 3]) > 2.0        # really different places
            res = verify(scans[a].points, scans[a].normals, scans[b].points, scans[b].normals, np.eye(4), lcfg)
            assert not res.accepted, (name, a, b, res.reason)
        true_T = se3_inverse(gt[j]) @ gt[i]
        res = verify(scans[i].points, scans[i].normals, scans[j].points, scans[j].normals,
                     true_T @ perturb(rng, *drift), lcfg)
        assert res.accepted, (name, res.reason)
        ang, dist = pose_change(true_T, res.T_rel)
        assert dist < tol[0] and np.degrees(ang) < tol[1], (name, dist, np.degrees(ang))
        assert res.conflict <= lcfg.max_conflict and res.fitness >= lcfg.min_fitness


# ------------------------------------------------------------------------------------------------
# trajectory files and ATE
# ------------------------------------------------------------------------------------------------

def random_trajectory(n, seed):
    rng = np.random.default_rng(seed)
    return np.stack([make_pose(random_rotation(rng), rng.normal(size=3) * 10) for _ in range(n)])


def test_trajectory_files_round_trip_and_errors(tmp_path):
    poses = random_trajectory(7, 0)
    ts = np.arange(7) * 0.1 + 1e9
    write_tum(tmp_path / "t.txt", ts, poses)
    ts2, p2 = read_tum(tmp_path / "t.txt")
    assert np.array_equal(ts2, ts) and np.abs(p2 - poses).max() < 1e-12
    assert np.abs(read_pose_snapshot(tmp_path / "t.txt", n_expected=7) - poses).max() < 1e-12
    write_kitti(tmp_path / "k.txt", poses)
    assert np.array_equal(read_pose_snapshot(tmp_path / "k.txt"), poses)

    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3 4 5 6 7\n")                             # 7 columns: neither format
    with pytest.raises(DataError, match="bad.txt.*7 numbers per line"):
        read_pose_snapshot(bad)
    lines = (tmp_path / "k.txt").read_text().splitlines()
    words = lines[3].split()
    words[3] = "nan"
    bad.write_text("\n".join(lines[:3] + [" ".join(words)] + lines[4:]) + "\n")
    with pytest.raises(DataError, match="bad.txt line 4: NaN"):
        read_pose_snapshot(bad)
    bad.write_text("\n".join(lines[:2] + ["1 2 3"] + lines[2:]) + "\n")
    with pytest.raises(DataError, match="bad.txt line 3"):
        read_pose_snapshot(bad)
    with pytest.raises(DataError, match="k.txt: 7 poses, expected 8"):
        read_pose_snapshot(tmp_path / "k.txt", n_expected=8)
    with pytest.raises(DataError, match="missing.txt"):
        read_pose_snapshot(tmp_path / "missing.txt")
    words = lines[0].split()
    words[0] = "5.0"                                              # R[0,0] = 5: not a rotation
    bad.write_text("\n".join([" ".join(words)] + lines[1:]) + "\n")
    with pytest.raises(DataError, match="bad.txt line 1"):
        read_pose_snapshot(bad)


def test_ate_properties():
    gt = random_trajectory(12, 1)
    zero = ate(gt, gt)
    assert zero["rmse_m"] < 1e-12 and zero["max_m"] < 1e-12 and zero["rot_rmse_deg"] < 1e-4

    rng = np.random.default_rng(4)
    S = make_pose(random_rotation(rng), rng.normal(size=3) * 5)
    moved = S @ gt
    assert ate(moved, gt)["rmse_m"] > 1.0
    aligned = ate(moved, gt, align="se3")
    assert aligned["rmse_m"] < 1e-9 and aligned["rot_rmse_deg"] < 1e-4

    offset = gt.copy()
    offset[:, :3, 3] += [0.3, 0.4, 0.0]                          # a constant 0.5 m world offset
    r = ate(offset, gt)
    assert r["rmse_m"] == pytest.approx(0.5) and r["mean_m"] == pytest.approx(0.5) and r["max_m"] == pytest.approx(0.5)
    # half the frames off by 0.5 m: rmse sqrt(0.125), mean 0.25
    half = gt.copy()
    half[::2, :3, 3] += [0.0, 0.0, 0.5]
    r = ate(half, gt)
    assert r["rmse_m"] == pytest.approx(np.sqrt(0.125)) and r["mean_m"] == pytest.approx(0.25)
    with pytest.raises(ValueError):
        ate(gt, gt, align="sim3")


# ------------------------------------------------------------------------------------------------
# the front end
# ------------------------------------------------------------------------------------------------

def odometry_chain(fe):
    """The odometry-only trajectory of keyframes: the chain of the graph's odometry edges."""
    rels = [T for i, j, T, _, loop in fe.graph.edges if not loop]
    return chain(fe.trajectory()[0], rels)


def test_frontend_room_closes_loop_and_reduces_error(noisy_room):
    pts, gt = noisy_room
    fe = FrontEnd(FrontEndConfig(), initial_pose=gt[0])
    results = [fe.add_frame(p) for p in pts]
    assert all(r.is_keyframe and r.odometry_ok for r in results)          # keyframe_every=1, no ICP failure
    assert [r.keyframe_id for r in results] == list(range(ROOM_FRAMES))

    # odometry alone drifts a little; bounded
    odo = odometry_chain(fe)
    ate_odo = ate(odo, gt)
    assert ate_odo["max_m"] < 0.05

    # the loop (last frames back to the first) is found and optimised
    assert fe.loops and all(c <= 2 and k >= ROOM_FRAMES - 4 for c, k in fe.loops)
    first = next(i for i, r in enumerate(results) if r.optimized)
    assert results[first].loop.accepted
    before = results[first - 1].keyframe_poses
    after = results[first].keyframe_poses
    assert len(after) == len(before) + 1 and np.abs(after[:-1] - before).max() > 1e-4   # old keyframes moved
    assert pose_change(after[0], gt[0])[1] < 1e-9                                       # reference fixed

    # every edge carries the per-block isotropic information (the default), not open3d's cross terms
    for _, _, _, info, _ in fe.graph.edges:
        assert np.all(info[:3, 3:] == 0) and np.allclose(info, np.diag(np.diag(info)))

    traj = fe.trajectory()
    assert traj.shape == (ROOM_FRAMES, 4, 4) and np.allclose(traj, fe.keyframe_poses())
    ate_opt = ate(traj, gt)
    # measured: odometry 0.84 cm RMSE / 1.26 cm max -> 0.33 / 0.64 cm after the loop closure
    assert ate_opt["rmse_m"] < 0.7 * ate_odo["rmse_m"] and ate_opt["max_m"] < ate_odo["max_m"]
    assert ate_opt["max_m"] < 0.02
    # the pose reported after the optimisation is the optimised keyframe pose, and tracking went on from it
    assert np.allclose(results[first].pose, after[-1])
    if first + 1 < ROOM_FRAMES:
        assert pose_change(results[first + 1].pose, gt[first + 1])[1] < 0.03


def test_frontend_sparse_keyframes_move_non_keyframes(noisy_room):
    """keyframe_every=3: non-keyframes are stored relative to their keyframe and move with it."""
    pts, gt = noisy_room
    fe = FrontEnd(FrontEndConfig(keyframe_every=3), initial_pose=gt[0])
    results = [fe.add_frame(p) for p in pts[:8]]
    assert [r.is_keyframe for r in results] == [True, False, False, True, False, False, True, False]
    assert [r.keyframe_id for r in results] == [0, -1, -1, 1, -1, -1, 2, -1]
    assert len(fe.graph.edges) == 2                   # keyframe-to-keyframe odometry edges
    traj = fe.trajectory()
    assert ate(traj, gt[:8])["max_m"] < 0.02
    # moving keyframe 1 moves frames 3, 4, 5 rigidly with it and nothing else
    D = make_pose(yaw_rotation(0.1), [0.2, 0.0, 0.0])
    fe.graph.poses[1] = D @ fe.graph.poses[1]
    moved = fe.trajectory()
    assert np.allclose(moved[3:6], D @ traj[3:6]) and np.allclose(moved[:3], traj[:3])
    assert np.allclose(moved[6:], traj[6:])


def test_frontend_city_closes_loop(noisy_city):
    """Small noisy city, every 4th scan: 3.9 m and up to 28 deg between keyframes; the loop is closed and
    takes 40 % off the error."""
    pts, gt = noisy_city
    # jaxmap's ICP (the LiDAR default, KISS-ICP, predicts each motion from the last one: not for keyframes)
    fe = FrontEnd(FrontEndConfig.lidar(odometry=OdometryConfig.lidar(method="icp")), initial_pose=gt[0])
    results = [fe.add_frame(p) for p in pts]
    assert all(r.odometry_ok for r in results)
    ate_odo, ate_opt = ate(odometry_chain(fe), gt), ate(fe.trajectory(), gt)
    assert ate_odo["max_m"] < 1.0                     # < 1.6 % of the 62 m loop
    assert fe.loops and any(r.optimized for r in results)
    assert ate_opt["rmse_m"] < 0.6 * ate_odo["rmse_m"]
    assert all(set(r.timings) == {"odometry_s", "loop_s", "optimize_s", "level_s"} for r in results)
