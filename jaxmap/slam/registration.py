"""Scan registration with open3d: point-to-plane (or point-to-point) ICP, a coarse-to-fine pass over two
prepared scans, and a global registration (FPFH + RANSAC) for when there is no initial guess.

Used by the frame-to-frame odometry (`jaxmap.slam.odometry`), by KISS-ICP's first step
(`jaxmap.slam.kiss`) and by the loop verification (`jaxmap.slam.loops`). T always maps source points
into the target frame (T_target_source). open3d is imported inside the functions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxmap.geometry import orthonormalize
from jaxmap.slam.odometry_common import OdometryConfig, Scan, quiet_open3d, to_o3d


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
