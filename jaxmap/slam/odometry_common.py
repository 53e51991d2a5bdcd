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


@dataclass(frozen=True)
class OdometryConfig:
    """Odometry parameters. Defaults suit the indoor depth camera (room: 0.2-10 m ranges, mm noise):
    3 cm voxels and correspondences within 2 voxels. Measured on the 40-frame room with 5 mm noise:
    3 cm / 6 cm gives 0.4 cm ATE at ~0.2 s per frame (2 CPU cores); 5 cm / 10 cm 0.8 cm at ~0.1 s;
    a wider correspondence distance (3 voxels) is faster to converge but biased: 2x the drift.

    For a street LiDAR (the city, 50 m range, cm noise) use `OdometryConfig.lidar()`: voxel 0.3 m,
    correspondences within 0.6 m (1.5 m in the coarse stage), fitness >= 0.5, RMSE <= 0.4 m (the
    point-to-point RMSE of a correct match of sparse beams is already ~0.25 m, so fitness is the real
    test). On the small city (4.7 m between scans, 2 cm noise): 8.5 cm ATE over the 70 m loop; 0.2 m
    voxels give 5 cm at twice the time; 0.2-0.5 m voxels are the sensible range for 32-64 beams.

    method:         "icp": this module's frame-to-frame point-to-plane ICP (open3d), the default; "kiss_icp":
                    KISS-ICP (Vizzo et al., RA-L 2023; `pip install kiss-icp`), point-to-point ICP against a
                    voxel-hashed local map with an adaptive threshold (`jaxmap.slam.kiss`). Both give the
                    same OdomStep; the scans kept for loop closure are prepared with the fields below either way
    kiss_voxel_m:   kiss_icp only: voxel size of its local map (m); 0 = max_range_m / 100 as KISS-ICP does
    voxel_m:        downsampling voxel (m) of the scans fed to ICP (and to the loop verification)
    max_corr_m:     ICP correspondence distance of the fine stage (m); about 2 voxels
    coarse_factor:  a first ICP stage runs with voxel and max_corr scaled by this (1 = single stage);  # a first ICP stage runs with voxel and max_corr scaled by this (1 = one stage)
                    it widens the basin of convergence when the motion prior is off
    retry_below_fitness: when ICP from the motion prior reaches a lower fitness, a global registration
                    (FPFH + RANSAC, then ICP) is tried too and the better-fitting result kept; 0 disables.
                    It rescues sharp turns and the first step, where constant velocity is a poor guess
    min_fitness:    ICP result rejected below this fraction of matched source points
    max_rmse_m:     ICP result rejected above this inlier RMSE (m)
    max_iter:       ICP iterations per stage
    normals_k:      neighbours for the PCA normals
    min_points:     fewer downsampled points than this -> the frame is not registered
    min_range_m, max_range_m: range crop of the input scan (m)
    """
    method: str = "icp"                 # "icp" (open3d point-to-plane, frame to frame) or "kiss_icp" (KISS-ICP, frame to local map)
    kiss_voxel_m: float = 0.0           # kiss_icp: voxel (m) of its local map; 0 = max_range_m / 100 (KISS-ICP's default)
    voxel_m: float = 0.03               # downsampling voxel (m) of the scans fed to ICP
    max_corr_m: float = 0.06            # ICP correspondence distance of the fine stage (m); about 2 voxels
    coarse_factor: float = 2.5          # a first ICP stage runs with voxel and max_corr scaled by this (1 = one stage)
    retry_below_fitness: float = 0.8    # below this fitness a global registration (FPFH + RANSAC) is tried too; 0 = never
    min_fitness: float = 0.5            # ICP rejected below this fraction of matched source points
    max_rmse_m: float = 0.04            # ICP rejected above this inlier RMSE (m)
    max_iter: int = 30                  # ICP iterations per stage
    normals_k: int = 15                 # neighbours for the PCA normals
    min_points: int = 100               # fewer downsampled points than this: the frame is not registered
    min_range_m: float = 0.1            # range crop of the input scan (m), near
    max_range_m: float = 10.0           # range crop of the input scan (m), far

    @classmethod
    def lidar(cls, **overrides) -> "OdometryConfig":
        """Settings for a street LiDAR (see the class docstring); keyword arguments override them."""
        base = dict(voxel_m=0.3, max_corr_m=0.6, coarse_factor=2.5, retry_below_fitness=0.8, min_fitness=0.5,
                    max_rmse_m=0.4, normals_k=15, min_range_m=2.0, max_range_m=50.0)
        base.update(overrides)
        return cls(**base)


def prepare_scan(points_s: np.ndarray, cfg: OdometryConfig, voxel_m: float | None = None, crop_range: bool = True):
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
        self.points, self.normals = prepare_scan(points_s, cfg)
        if cfg.coarse_factor > 1:
            self.coarse_points, self.coarse_normals = prepare_scan(self.points, cfg, cfg.voxel_m * cfg.coarse_factor,
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
