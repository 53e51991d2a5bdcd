"""SLAM front end (geometry only): ICP or KISS-ICP odometry, loop closure, pose graph, trajectory files,
ATE and RPE.

Registration and pose-graph optimisation use open3d, imported inside the functions that need it, so
importing this package (and the mapping core) works without open3d. Poses are [4,4] float64
T_world_sensor; scans [N,3] float32 in the sensor frame.

    from jaxmap.slam import FrontEnd, FrontEndConfig
    fe = FrontEnd(FrontEndConfig.lidar(), initial_pose=seq.poses[0])
    for frame in seq:
        result = fe.add_frame(frame.points)
    poses = fe.trajectory()
"""
from jaxmap.config.slam import FrontEndConfig, LoopConfig, OdometryConfig
from jaxmap.slam.frontend import FrameResult, FrontEnd
from jaxmap.slam.loops import LoopResult, find_candidates, verify
from jaxmap.slam.odometry import IcpResult, Odometry, OdomStep, icp, make_odometry
from jaxmap.slam.posegraph import PoseGraph
from jaxmap.slam.trajectory import ate, read_pose_snapshot, read_tum, rpe, write_kitti, write_tum

__all__ = [
    "FrontEnd", "FrontEndConfig", "FrameResult", "LoopConfig", "LoopResult", "find_candidates", "verify",
    "Odometry", "OdometryConfig", "OdomStep", "IcpResult", "icp", "make_odometry", "PoseGraph", "ate", "rpe",
    "read_pose_snapshot", "read_tum", "write_kitti", "write_tum",
]
