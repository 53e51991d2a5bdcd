"""Loop closure: candidate keyframes near the current pose estimate, verified by ICP with sanity checks.

A loop candidate is accepted only when ICP from the (drifted) pose estimate
  * converges with enough overlap in BOTH directions (source->target and target->source fitness),
  * leaves a small inlier RMSE,
  * corrects the initial guess by a plausible amount (bounded translation and rotation): a
    registration that has to move the scan by metres to "fit" is an aliased match, not a revisit,
  * is well constrained: the point-to-plane normal equations have no weak translation direction
    (two walls and a floor "match" anywhere along their shared edge),
  * and is free-space consistent both ways: few points of one scan lie in front of the surface the
    other scan saw along the same ray (the sensor saw through them). Overlap alone cannot tell two
    similar places apart (a box room seen from opposite sides, two straight streets with buildings);
    their differences show up as points in the other scan's free space.
open3d is imported inside the functions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxmap.config.slam import LoopConfig
from jaxmap.geometry import SE3, pose_change, se3_inverse
from jaxmap.slam.odometry import icp, to_o3d


@dataclass(frozen=True)
class LoopResult:
    """Outcome of verifying one loop candidate.

    accepted:    True when every check passed
    T_rel:       [4,4] float64 ICP estimate of T_target_source (maps source points into the target frame)
    fitness:     min(forward, backward) overlap at max_corr_m / 2
    rmse:        inlier RMSE (m) at max_corr_m / 2
    conflict:    max(forward, backward) fraction of points in the other scan's free space
    constraint:  smallest translation eigenvalue of the normalised point-to-plane normal matrix
    information: [6,6] float64 information of T_rel (open3d order)
    reason:      "accepted" or which check failed, with the numbers
    """
    accepted: bool
    T_rel: np.ndarray
    fitness: float
    rmse: float
    information: np.ndarray
    reason: str
    conflict: float = float("nan")
    constraint: float = float("nan")


def find_candidates(keyframe_poses, current_index: int, current_pose, cfg: LoopConfig) -> list[int]:
    """Keyframes that may close a loop with keyframe `current_index`.

    keyframe_poses: [K,4,4] T_world_keyframe estimates (K may include the current keyframe).
    current_pose: [4,4] estimate of the current keyframe. Returns the indices j with
    j <= current_index - min_gap and |t_j - t_current| <= radius_m, nearest first, at most max_candidates.
    """
    kp = np.asarray(keyframe_poses, dtype=np.float64).reshape(-1, 4, 4)
    last = min(int(current_index) - int(cfg.min_gap), len(kp) - 1)
    if last < 0:
        return []
    d = np.linalg.norm(kp[: last + 1, :3, 3] - np.asarray(current_pose)[:3, 3], axis=1)
    idx = np.flatnonzero(d <= cfg.radius_m)
    idx = idx[np.argsort(d[idx], kind="stable")]
    return [int(i) for i in idx[: cfg.max_candidates]]


def _range_bins(points: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray]:
    """Spherical range-image bin key and range of points [N,3] (sensor at the origin); res in radians."""
    r = np.linalg.norm(points, axis=1)
    az = np.arctan2(points[:, 1], points[:, 0]) + np.pi
    el = np.arcsin(np.clip(points[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0)) + np.pi / 2
    n_el = int(np.ceil(np.pi / res)) + 1
    return np.floor(az / res).astype(np.int64) * n_el + np.floor(el / res).astype(np.int64), r


def free_space_conflict(points_a, points_b, T_b_a, margin_m: float, res_deg: float = 1.0) -> float:
    """Fraction of the points of scan a that lie in the free space seen by scan b.

    points_a, points_b: [N,3] / [M,3], each in its own sensor frame (sensor at the origin); T_b_a: [4,4]
    maps a's points into b's frame. A point of a (in b's frame) conflicts when it is more than
    margin_m + 10 % of its range in front of b's nearest return in the same angular bin (res_deg wide).
    Points whose direction b has no return in are not counted. Returns 0 when none can be tested.
    """
    res = np.radians(res_deg)
    pa = SE3.from_matrix(np.asarray(T_b_a, np.float64)).apply(np.asarray(points_a, np.float64))
    kb, rb = _range_bins(np.asarray(points_b, np.float64), res)
    keys, inv = np.unique(kb, return_inverse=True)
    rmin = np.full(len(keys), np.inf)
    np.minimum.at(rmin, inv.reshape(-1), rb)
    ka, ra = _range_bins(pa, res)
    pos = np.clip(np.searchsorted(keys, ka), 0, len(keys) - 1)
    seen = keys[pos] == ka
    if not np.any(seen):
        return 0.0
    return float(np.mean(ra[seen] < rmin[pos[seen]] * 0.9 - margin_m))


def translation_constraint(source_pts, target_pts, target_normals, T, max_corr_m: float) -> float:
    """Smallest eigenvalue of the translation block of the point-to-plane normal matrix, per correspondence.

    Correspondences: nearest target point of each transformed source point within max_corr_m. The block
    is mean(n n^T) of the matched target normals: near 0 when the matched surfaces leave a direction free.
    """
    from scipy.spatial import cKDTree

    ps = SE3.from_matrix(np.asarray(T, np.float64)).apply(np.asarray(source_pts, np.float64))
    d, idx = cKDTree(np.asarray(target_pts, np.float64)).query(ps, distance_upper_bound=max_corr_m)
    n = np.asarray(target_normals, np.float64)[idx[np.isfinite(d)]]
    if len(n) < 3:
        return 0.0
    return float(np.linalg.eigvalsh(n.T @ n / len(n))[0])


def verify(source_pts, source_normals, target_pts, target_normals, init, cfg: LoopConfig) -> LoopResult:
    """Verify a loop candidate by three-stage point-to-plane ICP and consistency checks.

    ICP runs at max_corr_m, max_corr_m / 2 and fine_corr_m; the checks (overlap both ways, RMSE,
    constraint, free space) are made at max_corr_m / 2 on the final transform.

    source_*: [N,3] points and unit normals of the current keyframe (its sensor frame);
    target_*: [M,3] of the candidate keyframe (its sensor frame); init: [4,4] guess of
    T_target_source from the pose estimates (T_w_target^-1 @ T_w_source). Returns a LoopResult.
    """
    import open3d as o3d

    init = np.asarray(init, dtype=np.float64)
    if min(len(source_pts), len(target_pts)) < 10:
        return LoopResult(False, init, 0.0, np.inf, np.zeros((6, 6)), "too few points")
    check_corr = 0.5 * cfg.max_corr_m
    T = init
    for corr in (cfg.max_corr_m, check_corr, cfg.fine_corr_m):
        res = icp(source_pts, source_normals, target_pts, target_normals, T, corr, cfg.max_iter)
        T = res.T
    reg = o3d.pipelines.registration
    src, tgt = to_o3d(source_pts), to_o3d(target_pts)
    fwd = reg.evaluate_registration(src, tgt, check_corr, T)
    back = reg.evaluate_registration(tgt, src, check_corr, se3_inverse(T))
    fitness, rmse = min(fwd.fitness, back.fitness), fwd.inlier_rmse
    ang, dist = pose_change(init, T)
    ang = float(np.degrees(ang))
    constraint = translation_constraint(source_pts, target_pts, target_normals, T, check_corr)
    conflict = max(free_space_conflict(source_pts, target_pts, T, cfg.free_space_margin_m, cfg.free_space_res_deg),
                   free_space_conflict(target_pts, source_pts, se3_inverse(T), cfg.free_space_margin_m,
                                       cfg.free_space_res_deg))
    if len(fwd.correspondence_set) == 0 or not np.all(np.isfinite(T)):
        reason = "ICP found no correspondences"
    elif dist > cfg.max_correction_m or ang > cfg.max_correction_deg:
        reason = (f"correction too large: {dist:.3f} m / {ang:.1f} deg "
                  f"(max {cfg.max_correction_m} m / {cfg.max_correction_deg} deg)")
    elif fitness < cfg.min_fitness:
        reason = (f"low overlap: fitness {fwd.fitness:.3f} forward, {back.fitness:.3f} backward "
                  f"(min {cfg.min_fitness})")
    elif rmse > cfg.max_rmse_m:
        reason = f"high RMSE: {rmse:.4f} m (max {cfg.max_rmse_m} m)"
    elif constraint < cfg.min_constraint:
        reason = f"under-constrained: translation eigenvalue {constraint:.4f} (min {cfg.min_constraint})"
    elif conflict > cfg.max_conflict:
        reason = f"free-space conflict: {conflict:.3f} of the points (max {cfg.max_conflict})"
    else:
        reason = "accepted"
    return LoopResult(reason == "accepted", T, fitness, rmse, res.information, reason, conflict, constraint)
