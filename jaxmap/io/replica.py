"""Replica sequences as rendered for NICE-SLAM / Co-SLAM / Neural-RGBD-style pipelines.

Layout (e.g. Replica/room0/)::

    results/depth*.png   uint16 depth, `scale` units per metre (Replica: 6553.5), one per frame, sorted by
                         name (digit runs compared as numbers); results/frame*.jpg (colour) are not used
    traj.txt             one line per frame: 16 numbers, row-major 4x4 T_world_camera (OpenCV camera frame:
                         x right, y down, z forward)
    cam_params.json      {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}, in the sequence directory or
                         its parent (the Replica download keeps one Replica/cam_params.json for all scenes)
"""
from __future__ import annotations

import json
import logging
import os

import numpy as np

from jaxmap.errors import DataError
from jaxmap.io.depth import backproject_depth, read_depth_png
from jaxmap.io.kitti import Sequence, read_pose_lines
from jaxmap.io.pointcloud import natural_key

log = logging.getLogger("jaxmap")

CAM_KEYS = ("w", "h", "fx", "fy", "cx", "cy", "scale")


def is_replica(data_dir) -> bool:
    """A directory with a results/ subdirectory (depth*.png; traj.txt is checked when it is opened)."""
    return os.path.isdir(os.path.join(os.fspath(data_dir), "results"))


def find_cam_params(data_dir) -> str:
    """Path of cam_params.json in data_dir or its parent; DataError naming both places when missing."""
    data_dir = os.path.abspath(os.fspath(data_dir))
    here = os.path.join(data_dir, "cam_params.json")
    for p in (here, os.path.join(os.path.dirname(data_dir), "cam_params.json")):
        if os.path.isfile(p):
            return p
    raise DataError(f"{here}: missing (also not in the parent directory); a Replica sequence needs "
                    'cam_params.json = {"camera": {"w": .., "h": .., "fx": .., "fy": .., "cx": .., "cy": .., '
                    '"scale": depth units per metre}}')


def read_cam_params(path) -> dict:
    """cam_params.json -> {"w", "h", "fx", "fy", "cx", "cy", "scale"} floats; DataError naming the file."""
    path = os.fspath(path)
    try:
        with open(path) as f:
            doc = json.load(f)
    except (OSError, ValueError) as e:
        raise DataError(f"{path}: not valid JSON ({e}); expected {{\"camera\": {{\"w\", \"h\", \"fx\", \"fy\", "
                        "\"cx\", \"cy\", \"scale\"}}") from None
    cam = doc.get("camera") if isinstance(doc, dict) else None
    if not isinstance(cam, dict):
        raise DataError(f"{path}: no \"camera\" object; expected {{\"camera\": {{\"w\", \"h\", \"fx\", \"fy\", "
                        "\"cx\", \"cy\", \"scale\"}}")
    missing = [k for k in CAM_KEYS if k not in cam]
    if missing:
        raise DataError(f"{path}: \"camera\" lacks {', '.join(missing)}; it needs {', '.join(CAM_KEYS)} "
                        "(scale = depth units per metre, 6553.5 for Replica)")
    try:
        out = {k: float(cam[k]) for k in CAM_KEYS}
    except (TypeError, ValueError):
        raise DataError(f"{path}: \"camera\" values must be numbers, got {cam}") from None
    if not all(np.isfinite(v) for v in out.values()) or min(out["fx"], out["fy"], out["scale"]) <= 0:
        raise DataError(f"{path}: fx, fy and scale must be positive and finite, got {out}")
    return out


def read_traj(path) -> np.ndarray:
    """traj.txt: 16 numbers (row-major 4x4 T_world_camera) per line -> [M,4,4] float64."""
    return read_pose_lines(path, 16, "row-major 4x4 T_world_camera",
                           "missing; a Replica sequence needs traj.txt with one line of 16 numbers "
                           "(row-major 4x4 T_world_camera) per depth image")


class ReplicaSequence(Sequence):
    """A Replica sequence (see the module docstring): camera-frame points, T_world_camera poses.

    Extra attributes: depth_paths, intrinsics (fx, fy, cx, cy), depth_scale, image_size (w, h),
    cam_params_path.
    """

    kind = "replica"

    def __init__(self, data_dir, begin_frame: int = 0, end_frame: int = -1, every_frame: int = 1):
        data_dir = os.fspath(data_dir)
        if not os.path.isdir(data_dir):
            raise DataError(f"{data_dir}: sequence directory not found; check the path (data.path / --data)")
        res = os.path.join(data_dir, "results")
        if not os.path.isdir(res):
            raise DataError(f"{data_dir}: no results/ directory; a Replica sequence needs results/depth*.png + "
                            "traj.txt + cam_params.json")
        names = sorted((n for n in os.listdir(res) if n.lower().startswith("depth") and n.lower().endswith(".png")),
                       key=natural_key)
        if not names:
            raise DataError(f"{res}: no depth*.png images; expected uint16 depth images named depth000000.png, ...")
        self.depth_paths = [os.path.join(res, n) for n in names]
        self.cam_params_path = find_cam_params(data_dir)
        cam = read_cam_params(self.cam_params_path)
        self.intrinsics = (cam["fx"], cam["fy"], cam["cx"], cam["cy"])
        self.depth_scale = cam["scale"]
        self.image_size = (int(cam["w"]), int(cam["h"]))
        traj_path = os.path.join(data_dir, "traj.txt")
        poses = read_traj(traj_path)
        if len(poses) < len(names):
            raise DataError(f"{traj_path}: {len(poses)} poses for {len(names)} depth images in {res}; traj.txt "
                            "needs one line of 16 numbers per image")
        if len(poses) > len(names):
            log.warning("%s: %d poses for %d depth images; using the first %d poses", traj_path, len(poses),
                        len(names), len(names))
        super().__init__(data_dir, len(names), poses[:len(names)], begin_frame, end_frame, every_frame)

    def _depth_m(self, index: int) -> np.ndarray:
        raw = read_depth_png(self.depth_paths[index])
        w, h = self.image_size
        if raw.shape != (h, w):
            raise DataError(f"{self.depth_paths[index]}: image is {raw.shape[1]} x {raw.shape[0]} but "
                            f"{self.cam_params_path} says w={w}, h={h}; use the cam_params.json of this dataset")
        return raw.astype(np.float64) / self.depth_scale

    def read_depth(self, index: int) -> np.ndarray:
        """Metric depth [H,W] float32 (0 = no return) of frame number `index` (not the selection index)."""
        return self._depth_m(index).astype(np.float32)

    def _read_points(self, index: int) -> np.ndarray:
        return backproject_depth(self._depth_m(index), *self.intrinsics)
