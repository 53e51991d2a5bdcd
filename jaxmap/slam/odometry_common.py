"""What both odometries share (the ICP one in `jaxmap.slam.odometry`, KISS-ICP in `jaxmap.slam.kiss`): their
config, the scan prepared for registration, the per-frame result, and open3d helpers.

Frames and conventions: scans are [N,3] float32 in their SENSOR frame; poses are [4,4] float64
T_world_sensor (p_w = R p_s + t). open3d is imported inside the functions, so importing this works
without it.
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from jaxmap.config.slam import OdometryConfig
from jaxmap.preprocess import crop, estimate_normals, voxel_downsample


@contextmanager
def quiet_open3d():
    """Silence open3d's console messages below errors inside the block (restored afterwards)."""
    import open3d as o3d

    level = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    try:
        yield
    finally:
        o3d.utility.set_verbosity_level(level)


def to_o3d(points: np.ndarray, normals: np.ndarray | None = None):
    """An open3d PointCloud from points [N,3] (and normals [N,3]), any float dtype, any frame."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return pc


def odometry_points(points_s: np.ndarray, cfg: OdometryConfig, voxel_m: float | None = None, crop_range: bool = True):
    """Range crop, voxel downsample and PCA normals of a scan.

    points_s: [N,3] float32, sensor frame -> (points [M,3] float32, normals [M,3] float32), sensor frame.
    voxel_m: overrides cfg.voxel_m. crop_range: apply cfg.min_range_m / max_range_m.
    """
    pts = np.asarray(points_s, dtype=np.float32)
    if crop_range:
        pts = crop(pts, cfg.min_range_m, cfg.max_range_m, -np.inf, np.inf)
    pts = voxel_downsample(pts, cfg.voxel_m if voxel_m is None else voxel_m)
    normals, _ = estimate_normals(pts, cfg.normals_k)
    return pts, normals


class Scan:
    """A scan prepared for registration: fine and (optionally) coarse levels, sensor frame.

    points/normals: [M,3] float32 at cfg.voxel_m; coarse_points/coarse_normals at
    cfg.voxel_m * cfg.coarse_factor (the same arrays when coarse_factor <= 1).
    """

    def __init__(self, points_s: np.ndarray, cfg: OdometryConfig):
        self.points, self.normals = odometry_points(points_s, cfg)
        if cfg.coarse_factor > 1:
            self.coarse_points, self.coarse_normals = odometry_points(self.points, cfg, cfg.voxel_m * cfg.coarse_factor,
                                                                   crop_range=False)
        else:
            self.coarse_points, self.coarse_normals = self.points, self.normals

    def __len__(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class OdomStep:
    """Result of `Odometry.step` for one frame.

    pose:        [4,4] float64 T_world_sensor estimate of this frame
    rel:         [4,4] float64 T_{prev,this} (maps this frame's points into the previous frame);
                 identity for the first frame
    fitness, rmse: of the ICP (fitness 1, rmse 0 for the first frame; the failed ICP's values otherwise)
    ok:          False when ICP failed and the constant-velocity prior was kept
    information: [6,6] float64 information of `rel` (ICP's; a weak identity when ok is False)
    """
    pose: np.ndarray
    rel: np.ndarray
    fitness: float
    rmse: float
    ok: bool
    information: np.ndarray
