"""Odometry-like drift added to a sequence's poses: what a map built from a SLAM system's poses before a
loop closure looks like (`jaxmap bench imt`, notebooks/04_remapping)."""
from __future__ import annotations

import numpy as np

from jaxmap.geometry import make_pose, rotation_from_axis_angle


def drift_poses(poses: np.ndarray, rot_deg: float = 2.0, trans_m: float = 0.10) -> np.ndarray:
    """Poses with an error that grows linearly to `rot_deg` (about a tilted axis) and `trans_m` at the
    last frame, applied in the world frame about the first camera: a slow odometry drift."""
    n = len(poses)
    axis = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    direction = np.array([1.0, 0.6, -0.2]) / np.linalg.norm([1.0, 0.6, -0.2])
    c = poses[0][:3, 3]
    out = []
    for k, P in enumerate(poses):
        a = k / max(n - 1, 1)
        R = rotation_from_axis_angle(axis, np.deg2rad(rot_deg) * a)
        E = make_pose(R, c - R @ c + trans_m * a * direction)
        out.append(E @ P)
    return np.asarray(out)
