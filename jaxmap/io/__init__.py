"""Sequence and point-cloud I/O.

`open_sequence(path)` reads any of these layouts into a `Sequence` of `SensorFrame`s (kind in parentheses):

* KITTI odometry (LiDAR) ("kitti"): velodyne/*.bin|*.ply|*.pcd + poses.txt (camera-frame poses) + calib.txt
  (Tr); frame poses are LiDAR poses `inv(Tr) @ pose @ Tr` (SHINE-Mapping / N3-Mapping convention).
* depth camera ("depth"): depth/*.png (uint16 mm) + intrinsics.txt (fx fy cx cy) + poses.txt (T_world_camera).
* ROS bags ("rosbag"): a ROS 1 .bag, a ROS 2 bag directory (metadata.yaml + .db3/.mcap) or a bare .mcap/.db3;
  one frame per sensor_msgs/PointCloud2 message, poses from an Odometry/PoseStamped topic or a TUM file
  (`jaxmap.io.rosbag`).
* TUM RGB-D ("tum"): depth.txt + groundtruth.txt + depth/*.png (5000 per metre), Freiburg 1/2/3 intrinsics
  by directory name or intrinsics.txt (`jaxmap.io.tum`).
* Replica ("replica"): results/depth*.png + traj.txt (4x4 per line) + cam_params.json (`jaxmap.io.replica`).
* LAS/LAZ ("las"): one .las/.laz file (one frame, identity pose) or a directory of them + poses.txt
  (`jaxmap.io.las`).

Every `SensorFrame` holds sensor-frame points [N,3] float32, the pose [4,4] float64 T_world_sensor
(p_w = R p_s + t) and, for ROS bags and TUM RGB-D, the sensor timestamp in seconds (else None).
Bad input raises `jaxmap.errors.DataError` (or `PoseError`) naming the file.
"""
from __future__ import annotations

import logging
import os

from jaxmap.config import DATA_KINDS
from jaxmap.errors import DataError
from jaxmap.io.depth import (DepthSequence, backproject_depth, pixel_rays, read_depth_png, read_intrinsics,
                             write_depth_png, write_intrinsics)
from jaxmap.io.kitti import (SensorFrame, KittiSequence, Sequence, camera_poses_from_lidar, lidar_poses_from_camera,
                             read_calib, read_poses, select_frames, write_calib, write_poses)
from jaxmap.io.las import LasSequence, is_las_file, list_las, read_las
from jaxmap.io.ply_pieces import read_points_ply_chunks
from jaxmap.io.pointcloud import (read_mesh_ply, read_pcd, read_points_ply, read_scan, write_mesh_ply,
                                  write_points_ply, write_scan_bin)
from jaxmap.io.replica import ReplicaSequence, is_replica
from jaxmap.io.rosbag import RosbagSequence, describe, is_rosbag
from jaxmap.io.stamped import read_tum_trajectory
from jaxmap.io.tum import TumSequence, is_tum

log = logging.getLogger("jaxmap")

KINDS = DATA_KINDS  # data.kind; the config validates it at load

_LAYOUTS = ("the KITTI layout (velodyne/*.bin|*.ply|*.pcd + poses.txt [+ calib.txt]), the depth layout "
            "(depth/*.png + intrinsics.txt + poses.txt), a ROS bag (.bag, .mcap, .db3, or a ROS 2 bag directory "
            "with metadata.yaml), TUM RGB-D (depth.txt + groundtruth.txt + depth/), Replica (results/depth*.png + "
            "traj.txt + cam_params.json) or LAS/LAZ (a .las/.laz file, or a directory of them + poses.txt)")


def detect_kind(path) -> str:
    """The kind of the sequence at `path` (see the module docstring), else DataError listing the layouts.

    Files: .bag/.mcap/.db3 -> "rosbag", .las/.laz -> "las". Directories, first match: velodyne/ -> "kitti",
    metadata.yaml -> "rosbag", depth.txt (without poses.txt) -> "tum", depth/ -> "depth", results/ ->
    "replica", *.las|*.laz files -> "las".
    """
    path = os.fspath(path)
    if os.path.isfile(path):
        if is_rosbag(path):
            return "rosbag"
        if is_las_file(path):
            return "las"
        raise DataError(f"{path}: unknown sequence file type {os.path.splitext(path)[1]!r}; expected a ROS bag "
                        "(.bag, .mcap, .db3) or a .las/.laz file, or a sequence directory")
    if not os.path.isdir(path):
        raise DataError(f"{path}: sequence directory or file not found; check the path (data.path / --data)")
    if os.path.isdir(os.path.join(path, "velodyne")):
        return "kitti"
    if is_rosbag(path):
        return "rosbag"
    if is_tum(path):
        return "tum"
    if os.path.isdir(os.path.join(path, "depth")):
        return "depth"
    if is_replica(path):
        return "replica"
    if list_las(path):
        return "las"
    raise DataError(f"{path}: not a sequence directory: expected {_LAYOUTS}")


def open_sequence(data_dir, kind: str = "auto", begin_frame: int = 0, end_frame: int = -1,
                  every_frame: int = 1, *, topic: str = "", pose_topic: str = "", pose_file: str = "",
                  time_tolerance: float | None = None) -> Sequence:
    """Open a sequence (directory, or a bag / LAS file); select frames range(begin_frame, end_frame, every_frame).

    kind: "auto" (detect from the layout, see `detect_kind`), "kitti", "depth", "rosbag", "tum", "replica"
    or "las". end_frame is exclusive, -1 = to the end. Frames are read lazily one at a time.
    ROS bags only: topic (the PointCloud2 topic; "" = the bag's only one), pose_topic, pose_file (a TUM
    trajectory) - see `jaxmap.io.rosbag`. time_tolerance (s): how far a pose's time may be from a frame's,
    for ROS bags (default 0.1, interpolating) and TUM RGB-D (default 0.02, nearest ground-truth pose).
    """
    if kind not in KINDS:
        raise DataError(f"{os.fspath(data_dir)}: unknown sequence kind {kind!r} (data.kind); use one of "
                        + ", ".join(repr(k) for k in KINDS))
    if kind == "auto":
        kind = detect_kind(data_dir)
    if kind != "rosbag" and (topic or pose_topic or pose_file):
        log.warning("%s: topic/pose_topic/pose_file (data.topic) only apply to ROS bags; ignored for kind %r",
                    os.fspath(data_dir), kind)
    sel = (begin_frame, end_frame, every_frame)
    if kind == "kitti":
        return KittiSequence(data_dir, *sel)
    if kind == "depth":
        return DepthSequence(data_dir, *sel)
    if kind == "rosbag":
        return RosbagSequence(data_dir, *sel, topic=topic, pose_topic=pose_topic, pose_file=pose_file,
                              time_tolerance=time_tolerance)
    if kind == "tum":
        return TumSequence(data_dir, *sel, time_tolerance=time_tolerance)
    if kind == "replica":
        return ReplicaSequence(data_dir, *sel)
    return LasSequence(data_dir, *sel)


__all__ = [
    "SensorFrame", "Sequence", "KittiSequence", "DepthSequence", "RosbagSequence", "TumSequence", "ReplicaSequence",
    "LasSequence", "KINDS", "open_sequence", "detect_kind", "describe", "select_frames", "read_las",
    "read_tum_trajectory",
    "read_scan", "write_scan_bin", "read_pcd", "read_points_ply", "read_points_ply_chunks", "write_points_ply", "read_mesh_ply",
    "write_mesh_ply", "read_poses", "write_poses", "read_calib", "write_calib", "lidar_poses_from_camera",
    "camera_poses_from_lidar", "read_intrinsics", "write_intrinsics", "read_depth_png", "write_depth_png",
    "backproject_depth", "pixel_rays",
]
