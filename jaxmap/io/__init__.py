"""Sequence and point-cloud I/O.

`open_sequence(data_dir)` reads either layout into a `Sequence` of `Frame`s:

* KITTI odometry (LiDAR): velodyne/*.bin|*.ply|*.pcd + poses.txt (camera-frame poses) + calib.txt (Tr);
  frame poses are LiDAR poses `inv(Tr) @ pose @ Tr` (SHINE-Mapping / N3-Mapping convention).
* depth camera: depth/*.png (uint16 mm) + intrinsics.txt (fx fy cx cy) + poses.txt (T_world_camera).

Every `Frame` holds sensor-frame points [N,3] float32 and the pose [4,4] float64 T_world_sensor
(p_w = R p_s + t). Bad input raises `jaxmap.errors.DataError` (or `PoseError`) naming the file.
"""
from __future__ import annotations

import os

from jaxmap.errors import DataError
from jaxmap.io.depth import (DepthSequence, backproject_depth, pixel_rays, read_depth_png, read_intrinsics,
                             write_depth_png, write_intrinsics)
from jaxmap.io.kitti import (Frame, KittiSequence, Sequence, camera_poses_from_lidar, lidar_poses_from_camera,
                             read_calib, read_poses, select_frames, write_calib, write_poses)
from jaxmap.io.pointcloud import (read_mesh_ply, read_pcd, read_points_ply, read_scan, write_mesh_ply,
                                  write_points_ply, write_scan_bin)


def detect_kind(data_dir) -> str:
    """"kitti" if data_dir/velodyne exists, "depth" if data_dir/depth exists, else DataError."""
    data_dir = os.fspath(data_dir)
    if not os.path.isdir(data_dir):
        raise DataError(f"{data_dir}: sequence directory not found; check the path (data.path / --data)")
    if os.path.isdir(os.path.join(data_dir, "velodyne")):
        return "kitti"
    if os.path.isdir(os.path.join(data_dir, "depth")):
        return "depth"
    raise DataError(f"{data_dir}: not a sequence directory: expected either the KITTI layout "
                    "(velodyne/*.bin|*.ply|*.pcd + poses.txt [+ calib.txt]) or the depth layout "
                    "(depth/*.png + intrinsics.txt + poses.txt)")


def open_sequence(data_dir, kind: str = "auto", begin_frame: int = 0, end_frame: int = -1,
                  every_frame: int = 1) -> Sequence:
    """Open a sequence directory; select frames range(begin_frame, end_frame, every_frame).

    kind: "auto" (detect from the layout), "kitti" or "depth". end_frame is exclusive, -1 = to the end.
    Returns a KittiSequence or DepthSequence; frames are read lazily one at a time.
    """
    if kind == "auto":
        kind = detect_kind(data_dir)
    if kind == "kitti":
        return KittiSequence(data_dir, begin_frame, end_frame, every_frame)
    if kind == "depth":
        return DepthSequence(data_dir, begin_frame, end_frame, every_frame)
    raise DataError(f"{os.fspath(data_dir)}: unknown sequence kind {kind!r}; use 'auto', 'kitti' or 'depth'")


__all__ = [
    "Frame", "Sequence", "KittiSequence", "DepthSequence", "open_sequence", "detect_kind", "select_frames",
    "read_scan", "write_scan_bin", "read_pcd", "read_points_ply", "write_points_ply", "read_mesh_ply",
    "write_mesh_ply", "read_poses", "write_poses", "read_calib", "write_calib", "lidar_poses_from_camera",
    "camera_poses_from_lidar", "read_intrinsics", "write_intrinsics", "read_depth_png", "write_depth_png",
    "backproject_depth", "pixel_rays",
]
