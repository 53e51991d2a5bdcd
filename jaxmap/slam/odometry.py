"""Scan-to-scan odometry: point-to-plane ICP (open3d) with a constant-velocity motion prior.

Frames and conventions: scans are [N,3] float32 in their SENSOR frame; poses are [4,4] float64
T_world_sensor (p_w = R p_s + t). A relative transform `rel` from frame i-1 to frame i is
T_{i-1,i} = T_w_{i-1}^-1 @ T_w_i: it maps points of the newer scan into the older scan's frame, which
is exactly what ICP with source = newer scan and target = older scan estimates.

open3d is imported inside the functions, so `import jaxmap` (and the mapping core) works without it.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from jaxmap.config import ConfigError
from jaxmap.config.slam import ODOMETRY_METHODS
from jaxmap.frame_loop import Frame, Prefetcher, Progress, run_frames
from jaxmap.geometry import compose, orthonormalize, pose_change
from jaxmap.slam.kiss import KissOdometry
# The config, prepared scan, step result and open3d helpers live in odometry_common (KISS-ICP shares them);
# they are imported from here too.
from jaxmap.slam.odometry_common import (OdometryConfig, OdomStep, Scan, prepare_scan, quiet_open3d,  # noqa: F401
                                        to_o3d)

log = logging.getLogger("jaxmap")


@dataclass(frozen=True)
class IcpResult:
    """Result of one ICP registration.

    T:            [4,4] float64, maps source points into the target frame (T_target_source)
    fitness:      fraction of source points with a correspondence within max_corr_m
    inlier_rmse:  RMSE (m) of the point-to-point distances of those correspondences
    n_corr:       number of correspondences
    information:  [6,6] float64 information matrix of T (open3d order: rotation, then translation)
    """
    T: np.ndarray
    fitness: float
    inlier_rmse: float
    n_corr: int
    information: np.ndarray


def icp(source_pts, source_normals, target_pts, target_normals, init, max_corr_m: float, max_iter: int = 30,
        point_to_plane: bool = True) -> IcpResult:
    """Register a source scan to a target scan with open3d's ICP.

    source_pts, target_pts: [N,3] / [M,3] float, each in its own sensor frame.
    source_normals: [N,3] or None (unused by the point-to-plane error); target_normals: [M,3] unit
    normals, required when point_to_plane. init: [4,4] initial guess of T_target_source.
    max_corr_m: correspondence distance (m). Returns an IcpResult (T maps source into target frame).
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    src, tgt = to_o3d(source_pts, source_normals), to_o3d(target_pts, target_normals)
    if point_to_plane:
        if target_normals is None:
            raise ValueError("icp: point_to_plane=True needs target_normals")
        est = reg.TransformationEstimationPointToPlane()
    else:
        est = reg.TransformationEstimationPointToPoint()
    with quiet_open3d():
        res = reg.registration_icp(src, tgt, float(max_corr_m), np.asarray(init, dtype=np.float64), est,
                                   reg.ICPConvergenceCriteria(max_iteration=int(max_iter)))
        T = orthonormalize(np.array(res.transformation, dtype=np.float64))
        info = np.array(reg.get_information_matrix_from_point_clouds(src, tgt, float(max_corr_m), T))
    return IcpResult(T=T, fitness=float(res.fitness), inlier_rmse=float(res.inlier_rmse),
                     n_corr=int(len(res.correspondence_set)), information=info)


def register(source: Scan, target: Scan, init: np.ndarray, cfg: OdometryConfig) -> IcpResult:
    """Coarse-to-fine point-to-plane ICP of two prepared scans; T maps source into the target frame."""
    T = np.asarray(init, dtype=np.float64)
    if cfg.coarse_factor > 1:
        T = icp(source.coarse_points, source.coarse_normals, target.coarse_points, target.coarse_normals, T,
                cfg.max_corr_m * cfg.coarse_factor, cfg.max_iter).T
    return icp(source.points, source.normals, target.points, target.normals, T, cfg.max_corr_m, cfg.max_iter)


def global_register(source: Scan, target: Scan, cfg: OdometryConfig, seed: int = 0) -> IcpResult:
    """Registration without an initial guess: FPFH features + RANSAC (open3d) on the coarse level,
    refined by `register`. Deterministic for a given seed. T maps source into the target frame."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    voxel = cfg.voxel_m * max(cfg.coarse_factor, 1.0)
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    src, tgt = to_o3d(source.coarse_points, source.coarse_normals), to_o3d(target.coarse_points, target.coarse_normals)
    f_src, f_tgt = reg.compute_fpfh_feature(src, param), reg.compute_fpfh_feature(tgt, param)
    dist = 1.5 * voxel
    o3d.utility.random.seed(seed)
    with quiet_open3d():
        ransac = reg.registration_ransac_based_on_feature_matching(
            src, tgt, f_src, f_tgt, True, dist, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
    return register(source, target, np.array(ransac.transformation), cfg)


class Odometry:
    """Streaming frame-to-frame point-to-plane ICP odometry with a constant-velocity prior.

    Each new scan is registered to the previous scan, initialised with the previous relative motion
    (constant velocity); a poor fit triggers a global registration (see OdometryConfig).
    Frame-to-frame (not frame-to-local-map) keeps it simple; its drift on the synthetic data is small
    (about 3 cm over the 40-frame room loop, 0.3 m over the 70 m city loop) and the loop closure
    removes much of it.

    Usage: `odo = Odometry(cfg, initial_pose)`, then `odo.step(points_s)` per frame in order.
    After a pose-graph correction, `odo.correct(T_corr)` moves the current pose (T_world <- T_corr @ T_world).
    """

    def __init__(self, cfg: OdometryConfig | None = None, initial_pose: np.ndarray | None = None):
        self.cfg = cfg or OdometryConfig()
        self.pose = np.eye(4) if initial_pose is None else np.array(initial_pose, dtype=np.float64)
        self.velocity = np.eye(4)        # T_{i-1,i} of the last step, the motion prior
        self.prev: Scan | None = None    # the previous prepared scan (the ICP target)
        self.last: Scan | None = None    # the prepared scan of the last step (same as prev after step)
        self.n_frames = 0

    def step(self, points_s: np.ndarray) -> OdomStep:
        """Register the next scan. points_s: [N,3] float32, sensor frame. Returns an OdomStep."""
        cfg = self.cfg
        scan = Scan(points_s, cfg)
        frame = self.n_frames
        self.n_frames += 1
        self.last = scan
        if self.prev is None:
            self.prev = scan
            return OdomStep(self.pose.copy(), np.eye(4), 1.0, 0.0, True, np.eye(6))
        prior = self.velocity
        if len(scan) < cfg.min_points or len(self.prev) < cfg.min_points:
            log.warning("odometry frame %d: too few points for ICP (%d and %d after downsampling, need %d); "
                        "keeping the constant-velocity motion", frame, len(scan), len(self.prev), cfg.min_points)
            res, ok = None, False
        else:
            res = register(scan, self.prev, prior, cfg)
            if res.fitness < cfg.retry_below_fitness:
                alt = global_register(scan, self.prev, cfg)
                if alt.fitness > res.fitness:
                    log.debug("odometry frame %d: global registration beat the motion prior (fitness %.3f > %.3f)",
                              frame, alt.fitness, res.fitness)
                    res = alt
            ok = res.fitness >= cfg.min_fitness and res.inlier_rmse <= cfg.max_rmse_m
            if not ok:
                ang, dist = pose_change(prior, res.T)
                log.warning("odometry frame %d: ICP failed (fitness %.3f < %.2f or RMSE %.4f m > %.4f m; "
                            "correction %.3f m / %.2f deg); keeping the constant-velocity motion", frame,
                            res.fitness, cfg.min_fitness, res.inlier_rmse, cfg.max_rmse_m, dist, np.degrees(ang))
        rel = res.T if ok else prior.copy()
        self.velocity = rel
        self.pose = compose(self.pose, rel)   # re-orthonormalised: chained products drift off SO(3) otherwise
        self.prev = scan
        return OdomStep(self.pose.copy(), rel.copy(), res.fitness if res else 0.0, res.inlier_rmse if res else np.inf,
                        ok, res.information if ok else np.eye(6))

    def correct(self, T_corr: np.ndarray) -> None:
        """Apply a world-frame correction (e.g. from a pose-graph optimisation): pose <- T_corr @ pose.

        The velocity (a relative motion) is unchanged, so tracking continues smoothly from the new pose."""
        self.pose = compose(T_corr, self.pose)




def make_odometry(cfg: OdometryConfig | None = None, initial_pose: np.ndarray | None = None):
    """The odometry `cfg.method` names: `Odometry` ("icp") or `jaxmap.slam.kiss.KissOdometry` ("kiss_icp").

    Both have step(points_s) -> OdomStep, correct(T_corr), and the attributes pose, velocity, last (the
    prepared Scan of the last step), n_frames. ConfigError for an unknown method."""
    cfg = cfg or OdometryConfig()
    if cfg.method == "icp":
        return Odometry(cfg, initial_pose)
    if cfg.method == "kiss_icp":
        return KissOdometry(cfg, initial_pose)
    raise ConfigError(f"frontend.odometry.method: unknown odometry {cfg.method!r}; use one of "
                      + ", ".join(repr(m) for m in ODOMETRY_METHODS))


def odometry_trajectory(seq, cfg: OdometryConfig, progress: bool = False) -> tuple[np.ndarray, float]:
    """Run the odometry `cfg.method` names over every frame of `seq` from its first pose.

    Returns (poses [N,4,4] float64, median seconds per frame after the first)."""
    odo = make_odometry(cfg, np.asarray(seq.poses[0], dtype=np.float64))
    poses, times = [], []

    def step(frame: Frame):
        t0 = time.perf_counter()
        poses.append(odo.step(frame.points).pose)
        times.append(time.perf_counter() - t0)
        return {}, poses[-1]

    run_frames(Prefetcher(seq, 0, len(seq)), step, total=len(seq),
               progress=Progress(f"odometry ({cfg.method})", progress))
    return np.stack(poses), float(np.median(times[1:])) if len(times) > 1 else float(times[0])
