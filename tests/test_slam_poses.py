"""Poses that jaxmap composes, integrates or optimises stay on SE(3); a pose it made that left SE(3)
is named as its own, and a failure mid-run keeps the map and names the frame; a loop closure remaps
the map (skipping it fails)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from jaxmap.config import DataConfig
from jaxmap.errors import JaxmapError
from jaxmap.geometry import PoseError, compose, make_pose, orthonormalize, random_rotation, validate_pose


def _off_so3(rng, scale=1e-4):
    """A rigid transform whose rotation block is off SO(3) by ~scale, like a float32 or LM result."""
    T = make_pose(random_rotation(rng), rng.normal(size=3) * 0.1)
    T[:3, :3] += scale * rng.normal(size=(3, 3))
    return T


def _orth_err(T):
    R = np.asarray(T)[..., :3, :3]
    return float(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max())


def test_orthonormalize_is_the_nearest_rotation_and_keeps_exact_ones():
    rng = np.random.default_rng(0)
    T = make_pose(random_rotation(rng), np.array([1.0, -2.0, 0.5]))
    np.testing.assert_allclose(orthonormalize(T), T, atol=1e-14)
    bad = _off_so3(rng, 1e-2)
    good = orthonormalize(bad)
    assert _orth_err(good) < 1e-14 and np.linalg.det(good[:3, :3]) > 0
    np.testing.assert_array_equal(good[:3, 3], bad[:3, 3])
    # nearest in Frobenius norm: no other rotation nearby is closer
    from jaxmap.geometry import rotation_from_axis_angle

    for _ in range(20):
        other = good[:3, :3] @ rotation_from_axis_angle(rng.normal(size=3), 1e-3)
        assert np.linalg.norm(other - bad[:3, :3]) >= np.linalg.norm(good[:3, :3] - bad[:3, :3])
    batch = orthonormalize(np.stack([bad, bad]))
    assert batch.shape == (2, 4, 4) and _orth_err(batch) < 1e-14


def test_10000_chained_compositions_stay_orthonormal():
    rng = np.random.default_rng(1)
    rels = [_off_so3(rng, 1e-6) for _ in range(100)]
    T_raw, T = np.eye(4), np.eye(4)
    for i in range(10_000):
        T_raw = T_raw @ rels[i % 100]
        T = compose(T, rels[i % 100])
    assert _orth_err(T) < 1e-6
    assert _orth_err(T_raw) > 1e-4          # without re-orthonormalisation the chain leaves SO(3)


def test_odometry_chain_corrections_and_pose_graph_stay_on_se3(monkeypatch):
    pytest.importorskip("open3d")
    from jaxmap.slam import odometry as odo_mod
    from jaxmap.slam.odometry import IcpResult, Odometry, OdometryConfig
    from jaxmap.slam.posegraph import PoseGraph

    from jaxmap.geometry import rotation_from_axis_angle

    rng = np.random.default_rng(2)
    odo = Odometry(OdometryConfig(min_points=1), np.eye(4))
    for _ in range(10_000):                 # pose-graph corrections, each slightly off SO(3)
        C = make_pose(rotation_from_axis_angle(rng.normal(size=3), 1e-3), rng.normal(size=3) * 1e-3)
        C[:3, :3] += 1e-6 * rng.normal(size=(3, 3))
        odo.correct(C)
    assert _orth_err(odo.pose) < 1e-6
    # ICP steps: the registration result is off SO(3) (as open3d's can be); the chained pose is not
    rel = _off_so3(rng, 1e-5)
    monkeypatch.setattr(odo_mod, "register", lambda *a, **k: IcpResult(rel.copy(), 1.0, 0.001, 100, np.eye(6)))
    pts = rng.uniform(-1, 1, (200, 3)).astype(np.float32) + np.array([0, 0, 3], np.float32)
    odo = Odometry(OdometryConfig(min_points=1), np.eye(4))
    for _ in range(300):
        step = odo.step(pts)
    assert step.ok and _orth_err(step.pose) < 1e-6
    # the pose graph's nodes after open3d's optimisation
    g = PoseGraph()
    for k in range(30):
        g.add_node(_off_so3(rng, 1e-3))
        if k:
            g.add_odometry(k - 1, k, _off_so3(rng, 1e-3), np.eye(6))
    g.add_loop(0, 29, _off_so3(rng, 1e-3), np.eye(6))
    poses = g.optimize(0.5)
    assert _orth_err(poses) < 1e-9


def test_a_pose_jaxmap_made_is_not_blamed_on_a_pose_file():
    bad = _off_so3(np.random.default_rng(3), 1e-2)
    with pytest.raises(PoseError, match="12 numbers"):
        validate_pose(bad, "pose of frame 3")                                  # the user's file
    with pytest.raises(PoseError) as e:
        validate_pose(bad, "pose of frame 3", source="jaxmap's SLAM front end")
    assert "from jaxmap's SLAM front end" in str(e.value) and "12 numbers" not in str(e.value)
    validate_pose(orthonormalize(bad), "pose of frame 3")                      # fixed where it is produced


def test_a_failure_mid_run_saves_the_map_and_names_the_frame(small_room, tmp_path, monkeypatch):
    pytest.importorskip("open3d")
    from jaxmap.imt.mapper import ImtMapper
    from jaxmap.slam import frontend
    from jaxmap.config import SlamConfig
    from jaxmap.runs.slam import run_slam

    real = frontend.FrontEnd.add_frame

    def failing(self, points_s, **kw):
        if len(self.frame_ref) == 3:
            raise RuntimeError("simulated ICP crash")
        return real(self, points_s, **kw)

    monkeypatch.setattr(frontend.FrontEnd, "add_frame", failing)
    cfg = SlamConfig(data=DataConfig(path=str(small_room), every_frame=1), mesh_at_loops=False,
                     preprocess=dataclasses.replace(SlamConfig().preprocess, vox_down_m=0.04),
                     output=str(tmp_path / "run"))
    with pytest.raises(JaxmapError, match=r"failed at frame 3: RuntimeError: simulated ICP crash.*3 keyframes"):
        run_slam(cfg, cfg.output, progress=False, evaluate=False)
    assert len(ImtMapper.load(str(tmp_path / "run" / "checkpoint")).store) == 3


def test_the_map_is_remapped_at_a_loop_closure(small_room, tmp_path, monkeypatch):
    """A scripted front end fuses drifted poses and then reports a loop with the true poses: the final
    map must match the true-pose map (it does not if `jaxmap slam` skips the remap)."""
    from jaxmap.geometry import rotation_from_axis_angle
    from jaxmap.imt.mapper import ImtMapper
    from jaxmap.io import open_sequence
    from jaxmap.runs.slam_imt import ImtSlamStep
    from jaxmap.slam.frontend import FrameResult
    from jaxmap.config import SlamConfig

    seq = open_sequence(str(small_room))
    gt = np.asarray(seq.poses)[:6]
    drift = np.asarray([make_pose(rotation_from_axis_angle(np.array([0.3, -0.2, 1.0]), np.deg2rad(2.0 * k)),
                                  np.array([0.04, -0.03, 0.02]) * k) @ P for k, P in enumerate(gt)])

    class Loop:
        fitness, rmse = 0.9, 0.01

    class ScriptedFrontEnd:
        def __init__(self, cfg, initial_pose=None):
            self.n, self.loops = 0, []
            self.odometry = type("O", (), {"velocity": np.eye(4)})()

        def add_frame(self, points_s, refine=None, scan=None):
            k, self.n = self.n, self.n + 1
            closing = k == len(gt) - 1
            poses = gt[:k + 1] if closing else drift[:k + 1]
            return FrameResult(k, poses[k], True, k, Loop() if closing else None, closing, poses, True,
                               {"odometry_s": 0.0, "loop_s": 0.0, "optimize_s": 0.0})

        def trajectory(self):
            return gt[:self.n]

    monkeypatch.setattr("jaxmap.runs.slam_imt.FrontEnd", ScriptedFrontEnd)
    cfg = SlamConfig(data=DataConfig(path=str(small_room), every_frame=1, end_frame=len(gt)), mesh_at_loops=False,
                     output=str(tmp_path / "run"))
    mapper = ImtMapper(cfg.imt())
    step = ImtSlamStep(cfg, gt[0])
    step.attach(mapper, total=len(gt))
    for i in range(len(gt)):
        step.submit(step.load_frame(seq, i))
    out = step.results(seq)
    assert len(out["loops"]) == 1 and out["loops"][0]["keyframes_moved"] == len(gt) - 2   # 0 never drifted, 5 not yet
    ref, drifted = ImtMapper(cfg.imt()), ImtMapper(cfg.imt())
    for i in range(len(gt)):
        ref.add_frame(seq.frame(i).points, gt[i])
        drifted.add_frame(seq.frame(i).points, drift[i])
    probe = np.concatenate([seq.frame(i).points @ gt[i][:3, :3].T + gt[i][:3, 3] for i in range(len(gt))])[::50]
    s_ref, _, v_ref = ref.sdf(probe)

    def err(m):
        s, _, v = m.sdf(probe)
        return float(np.mean(np.where(v & v_ref, np.abs(s - s_ref), 0.05)))

    # the remapped keyframes' cells were pooled on the grid of their drifted poses, so the re-encoded
    # map differs from the true-pose map by the pooling's quadrature (~1 mm), not by the drift (cm)
    assert err(mapper) < 2e-3 and err(mapper) < 0.1 * err(drifted), (err(mapper), err(drifted))
