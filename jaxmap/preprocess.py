"""Scan preprocessing: range/height crop, voxel downsample, optional outlier removal, PCA normals
oriented to the sensor.

Pure numpy + scipy (no open3d), so the mapping core runs on machines that only have JAX.
All functions take and return sensor-frame arrays; the mapper moves them to the map frame.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def crop(points_s: np.ndarray, min_range: float, max_range: float, min_z: float, max_z: float) -> np.ndarray:
    """Keep points with min_range <= |p| <= max_range and min_z <= z <= max_z.

    points_s: [N,3] float32, sensor frame -> [M,3] float32.
    """
    r = np.linalg.norm(points_s, axis=1)
    keep = (r >= min_range) & (r <= max_range) & (points_s[:, 2] >= min_z) & (points_s[:, 2] <= max_z)
    return points_s[keep]


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per voxel of side `voxel`: the point closest to the voxel's mean (deterministic).

    points: [N,3] float32 -> [M,3] float32, M <= N; voxel <= 0 returns the input.
    """
    if voxel <= 0 or len(points) == 0:
        return points
    q = np.floor(points / voxel).astype(np.int64)
    q -= q.min(axis=0)
    span = q.max(axis=0) + 1
    # One int64 key per voxel: a 1-D unique is several times faster than np.unique(axis=0).
    keys = (q[:, 0] * span[1] + q[:, 1]) * span[2] + q[:, 2]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    means = np.stack([np.bincount(inverse, weights=points[:, d], minlength=len(counts)) for d in range(3)], 1)
    means /= counts[:, None]
    d = np.linalg.norm(points - means[inverse], axis=1)
    # Per voxel, the index of the smallest distance: sort by (voxel, distance), take firsts.
    order = np.lexsort((d, inverse))
    first = np.ones(len(order), bool)
    first[1:] = inverse[order][1:] != inverse[order][:-1]
    return points[np.sort(order[first])]


def remove_outliers(points_s: np.ndarray, k: int = 20, n_mad: float = 6.0) -> np.ndarray:
    """Statistical outlier removal for a spinning LiDAR (mixed pixels between a foreground and a
    background, stray returns): drop points whose mean distance to their k nearest neighbours,
    divided by their range (the beam spacing grows with range), exceeds the scan's median of that
    ratio by more than n_mad robust standard deviations (1.4826 MAD).

    points_s: [N,3] float32 sensor frame -> [M,3] float32, M <= N (order kept); n_mad <= 0 keeps all.
    """
    n = len(points_s)
    if n_mad <= 0 or n <= k:
        return points_s
    d, _ = cKDTree(points_s).query(points_s, k=k + 1, workers=-1)          # [N, k+1], self first
    spread = d[:, 1:].mean(axis=1) / np.maximum(np.linalg.norm(points_s, axis=1), 1.0)
    med = np.median(spread)
    mad = 1.4826 * np.median(np.abs(spread - med))
    return points_s[spread <= med + n_mad * max(mad, 1e-9)]


def estimate_normals(points_s: np.ndarray, k: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """PCA normals from the k nearest neighbours, oriented towards the sensor at the origin.

    points_s: [N,3] float32, sensor frame.
    Returns (normals [N,3] float32 unit, planarity [N] float32 in [0,1]: 1 - l_min / l_mid,
    low where the neighbourhood is degenerate, e.g. a single scan line).
    """
    n = len(points_s)
    if n == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0,), np.float32)
    k = int(min(k, n))
    tree = cKDTree(points_s)
    _, idx = tree.query(points_s, k=k, workers=-1)
    idx = idx.reshape(n, k)
    # Neighbourhoods relative to their query point keep float32 accurate (the scan spans ~100 m).
    nb = points_s[idx] - points_s[:, None, :]                # [N,k,3] float32
    c = nb - nb.mean(axis=1, keepdims=True)
    # The 6 distinct covariance entries as plain products: several times faster than an einsum.
    xx, yy, zz = (c[..., 0] ** 2).sum(1), (c[..., 1] ** 2).sum(1), (c[..., 2] ** 2).sum(1)
    xy, xz, yz = (c[..., 0] * c[..., 1]).sum(1), (c[..., 0] * c[..., 2]).sum(1), (c[..., 1] * c[..., 2]).sum(1)
    cov = np.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], axis=1).reshape(n, 3, 3) / k   # [N,3,3]
    evals, evecs = np.linalg.eigh(cov)                        # ascending
    normals = evecs[:, :, 0].astype(np.float64)
    # Orient towards the sensor (origin of the sensor frame): n . (0 - p) > 0.
    flip = np.einsum("ni,ni->n", normals, -points_s) < 0
    normals[flip] = -normals[flip]
    planarity = 1.0 - evals[:, 0] / np.maximum(evals[:, 1], 1e-12)
    return normals.astype(np.float32), planarity.astype(np.float32)


def preprocess_scan(points_s: np.ndarray, cfg) -> tuple[np.ndarray, np.ndarray]:
    """Crop, downsample and estimate normals. cfg: a PreprocessConfig.

    points_s: [N,3] float32 sensor frame -> (points [M,3] float32, normals [M,3] float32), sensor frame.
    """
    pts = crop(points_s, cfg.min_range_m, cfg.max_range_m, cfg.min_z_m, cfg.max_z_m)
    pts = voxel_downsample(pts, cfg.vox_down_m)
    if cfg.outlier_mad > 0:
        pts = remove_outliers(pts, cfg.normal_knn, cfg.outlier_mad)
    normals, _ = estimate_normals(pts, cfg.normal_knn)
    return pts.astype(np.float32), normals
