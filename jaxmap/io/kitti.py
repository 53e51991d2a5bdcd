"""KITTI odometry layout (as read by SHINE-Mapping / N3-Mapping) and the `SensorFrame`/`Sequence` types.

Layout of a sequence directory::

    velodyne/*.bin|*.ply|*.pcd   one scan per frame, sensor (LiDAR) frame, sorted by name
    poses.txt                    one line per scan: 12 numbers, row-major 3x4 [R|t], CAMERA-frame poses
    calib.txt                    optional; a line "Tr: <12 numbers>" = T_cam_velo (other lines ignored)
    gt_points.ply, gt_mesh.ply   optional ground truth (world frame)

The LiDAR pose of frame i (world <- LiDAR, `p_w = R p_s + t`) is `inv(Tr) @ pose_i @ Tr`, exactly as
SHINE-Mapping and N3-Mapping compute it; without calib.txt, Tr = identity.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from jaxmap.errors import DataError
from jaxmap.geometry import validate_pose
from jaxmap.io.pointcloud import is_scan_file, natural_key, read_scan

log = logging.getLogger("jaxmap")

_identity_logged: set[str] = set()


@dataclass(frozen=True, eq=False)
class SensorFrame:
    """One frame of a sequence.

    index:  frame number in the sequence (position among all scans/images, before selection; for ROS bags
            and TUM RGB-D, among the clouds/images that got a pose)
    points: [N,3] float32 in the SENSOR frame, all finite (NaN/inf dropped on read)
    pose:   [4,4] float64 T_world_sensor (p_w = R p_s + t)
    timestamp: sensor time in seconds (float64) where the format records one (ROS bags, TUM RGB-D),
            else None (KITTI, depth, Replica, LAS layouts)
    """
    index: int
    points: np.ndarray
    pose: np.ndarray
    timestamp: float | None = None


class Sequence:
    """A selection of frames of a sequence directory (base of KittiSequence and DepthSequence).

    Attributes:
      data_dir:  the directory (or file, for a ROS bag / single LAS file) (str)
      kind:      "kitti", "depth", "rosbag", "tum", "replica" or "las"
      indices:   [M] int, frame numbers of the selected frames
      poses:     [M,4,4] float64 world <- sensor poses of the selected frames (read-only array)
      timestamps: [M] float64 sensor times (s) of the selected frames, or None if the format has none
      gt_points_path, gt_mesh_path: data_dir/gt_points.ply and gt_mesh.ply, or None if absent
    `len(seq)` is M; iterating reads one frame at a time (lazy); `seq.frame(i)` (or `seq[i]`) is the i-th
    selected frame. A frame with no points, or only points at the sensor origin (an all-zero scan), is
    returned as read, with a warning naming its file.
    """

    kind = "base"

    def __init__(self, data_dir, n_total: int, poses_all: np.ndarray, begin_frame: int, end_frame: int,
                 every_frame: int, timestamps_all: np.ndarray | None = None):
        self.data_dir = os.fspath(data_dir)
        self.n_total = int(n_total)
        self.begin_frame, self.end_frame, self.every_frame = begin_frame, end_frame, every_frame
        self.indices = select_frames(self.n_total, begin_frame, end_frame, every_frame, self.data_dir)
        poses = np.ascontiguousarray(poses_all[self.indices], dtype=np.float64)
        poses.setflags(write=False)
        self.poses = poses
        self.timestamps = None
        if timestamps_all is not None:
            ts = np.ascontiguousarray(np.asarray(timestamps_all, dtype=np.float64)[self.indices])
            ts.setflags(write=False)
            self.timestamps = ts
        gp = os.path.join(self.data_dir, "gt_points.ply")
        gm = os.path.join(self.data_dir, "gt_mesh.ply")
        self.gt_points_path = gp if os.path.isfile(gp) else None
        self.gt_mesh_path = gm if os.path.isfile(gm) else None

    def __len__(self) -> int:
        return len(self.indices)

    def __iter__(self) -> Iterator[SensorFrame]:
        for i in range(len(self)):
            yield self.frame(i)

    def frame(self, i: int) -> SensorFrame:
        """The i-th selected frame (negative i counts from the end)."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for a sequence of {n} selected frames")
        i = i % n
        idx = int(self.indices[i])
        stamp = None if self.timestamps is None else float(self.timestamps[i])
        points = self._read_points(idx)
        if not points.any():  # no points, or all exactly at the origin: nothing to map
            what = "no points" if len(points) == 0 else f"all {len(points)} points at the sensor origin (0, 0, 0)"
            log.warning("%s: empty scan (%s): frame %d adds nothing to the map", self.source(idx), what, idx)
        return SensorFrame(index=idx, points=points, pose=np.array(self.poses[i]), timestamp=stamp)

    def __getitem__(self, i: int) -> SensorFrame:
        """`seq[i]` = `seq.frame(i)`: the i-th selected frame (an int; negative counts from the end)."""
        if not isinstance(i, (int, np.integer)) or isinstance(i, bool):
            raise TypeError(f"sequence indices are ints (the i-th selected frame), not {type(i).__name__}")
        return self.frame(int(i))

    def source(self, index: int) -> str:
        """The file frame number `index` is read from (for messages): its scan or image, else the sequence."""
        for attr in ("scan_paths", "depth_paths"):
            paths = getattr(self, attr, None)
            if paths is not None and 0 <= index < len(paths):
                return paths[index]
        return f"{self.data_dir} (frame {index})"

    def _read_points(self, index: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({self.data_dir!r}, {len(self)} of {self.n_total} frames, "
                f"begin={self.begin_frame}, end={self.end_frame}, every={self.every_frame})")


def select_frames(n_total: int, begin_frame: int = 0, end_frame: int = -1, every_frame: int = 1,
                  where: str = "sequence") -> np.ndarray:
    """Frame numbers range(begin, end, every); end is exclusive, -1 means "to the end".

    An end past the last frame is clamped (with a warning). Raises DataError for an empty or invalid
    selection."""
    begin_frame, end_frame, every_frame = int(begin_frame), int(end_frame), int(every_frame)
    if every_frame < 1:
        raise DataError(f"{where}: every_frame must be >= 1, got {every_frame}")
    if begin_frame < 0:
        raise DataError(f"{where}: begin_frame must be >= 0, got {begin_frame}")
    end = n_total if end_frame < 0 else end_frame
    if end > n_total:
        log.warning("%s: end_frame %d is past the last frame; using all %d frames", where, end_frame, n_total)
        end = n_total
    if begin_frame >= end:
        raise DataError(f"{where}: no frames selected: begin_frame={begin_frame}, end_frame={end_frame} "
                        f"(exclusive, -1 = end), sequence has {n_total} frames")
    return np.arange(begin_frame, end, every_frame, dtype=np.int64)


# ------------------------------------------------------------------------------------------------
# poses and calibration
# ------------------------------------------------------------------------------------------------


def read_pose_lines(path, n_numbers: int, layout: str, missing: str) -> np.ndarray:
    """Poses [M,4,4] float64 of a text file with one row-major matrix of `n_numbers` (12: [R|t], 16:
    4x4) per line; blank lines skipped. DataError naming the file (and the line) when it is missing
    (`missing` says what to write), a line has another count (`layout` names the expected one) or a
    non-number; PoseError for a non-rigid matrix."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DataError(f"{path}: {missing}")
    poses = []
    with open(path) as f:
        for lineno, line in enumerate(f, start=1):
            words = line.split()
            if not words:
                continue
            if len(words) != n_numbers:
                raise DataError(f"{path} line {lineno}: expected {n_numbers} numbers ({layout}), "
                                f"found {len(words)}; fix or remove that line")
            try:
                vals = np.asarray([float(w) for w in words], np.float64)
            except ValueError:
                raise DataError(f"{path} line {lineno}: not a number in {line.strip()!r}") from None
            T = np.eye(4)
            T[: n_numbers // 4, :] = vals.reshape(-1, 4)
            validate_pose(T, where=f"{path} line {lineno}")
            poses.append(T)
    return np.stack(poses) if poses else np.zeros((0, 4, 4))


def read_poses(path) -> np.ndarray:
    """Read a KITTI pose file: one pose per line, 12 numbers = row-major 3x4 [R|t].

    Returns [M,4,4] float64 exactly as written (no calibration applied). Blank lines are skipped.
    Raises DataError for a missing file or a line without 12 numbers (naming the line), and PoseError
    (a DataError) for a non-rigid matrix (naming file and line).
    """
    return read_pose_lines(path, 12, "row-major 3x4 [R|t]",
                           "pose file not found; write one line of 12 numbers (row-major 3x4 [R|t]) per scan")


def _fmt(x: float) -> str:
    return repr(float(x))  # shortest string that round-trips the float64 exactly


def read_poses_for(poses_path: str, n_items: int, what: str, item_dir: str, need: str) -> np.ndarray:
    """Poses [n_items,4,4] from `poses_path` for a sequence of `n_items` `what` (scans, depth images).

    A missing file or fewer lines than items is a DataError naming the file and `need` (what the
    layout expects); extra lines are ignored with a warning.
    """
    if not os.path.isfile(poses_path):
        raise DataError(f"{poses_path}: missing; {need}")
    poses = read_poses(poses_path)
    if len(poses) < n_items:
        raise DataError(f"{poses_path}: {len(poses)} poses for {n_items} {what} in {item_dir}; "
                        f"poses.txt needs one line per {what[:-1]}")
    if len(poses) > n_items:
        log.warning("%s: %d poses for %d %s; using the first %d poses", poses_path, len(poses), n_items, what,
                    n_items)
    return poses[:n_items]


def write_poses(path, poses) -> None:
    """Write poses [M,4,4] (or [M,3,4]) as KITTI lines of 12 numbers; float64 values round-trip exactly."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise DataError(f"{path}: poses must have shape [M,4,4] or [M,3,4], got {poses.shape}")
    d = os.path.dirname(os.fspath(path))
    if d:
        os.makedirs(d, exist_ok=True)
    with open(os.fspath(path), "w") as f:
        for T in poses:
            f.write(" ".join(_fmt(v) for v in T[:3, :].reshape(-1)) + "\n")


_TR_KEYS = ("Tr", "Tr_velo_to_cam", "Tr_velo_cam")


def read_calib(path) -> np.ndarray:
    """Read `Tr` (T_cam_velo, [4,4] float64) from a KITTI calib.txt ("Tr: 12 numbers").

    Other lines (P0..P3, ...) are ignored. Raises DataError if there is no Tr line or it has not
    12 numbers, PoseError if Tr is not rigid."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DataError(f"{path}: calibration file not found")
    with open(path) as f:
        for lineno, line in enumerate(f, start=1):
            key, sep, rest = line.partition(":")
            if not sep or key.strip() not in _TR_KEYS:
                continue
            words = rest.split()
            if len(words) != 12:
                raise DataError(f"{path} line {lineno}: 'Tr:' needs 12 numbers (row-major 3x4), found {len(words)}")
            try:
                vals = np.asarray([float(w) for w in words], dtype=np.float64)
            except ValueError:
                raise DataError(f"{path} line {lineno}: not a number in {line.strip()!r}") from None
            T = np.eye(4)
            T[:3, :] = vals.reshape(3, 4)
            validate_pose(T, where=f"{path} line {lineno} (Tr)")
            return T
    raise DataError(f"{path}: no 'Tr:' line (12 numbers, LiDAR -> camera); add it or delete calib.txt "
                    "to use the identity")


def write_calib(path, Tr) -> None:
    """Write a calib.txt with one line "Tr: <12 numbers>" (float64 values round-trip exactly)."""
    Tr = np.asarray(Tr, dtype=np.float64)
    if Tr.shape not in ((4, 4), (3, 4)):
        raise DataError(f"{path}: Tr must be 4x4 or 3x4, got {Tr.shape}")
    d = os.path.dirname(os.fspath(path))
    if d:
        os.makedirs(d, exist_ok=True)
    with open(os.fspath(path), "w") as f:
        f.write("Tr: " + " ".join(_fmt(v) for v in Tr[:3, :].reshape(-1)) + "\n")


def lidar_poses_from_camera(poses_cam: np.ndarray, Tr: np.ndarray) -> np.ndarray:
    """SHINE/N3 convention: T_world_lidar = inv(Tr) @ T_cam_pose @ Tr. [M,4,4] -> [M,4,4]."""
    # a general inverse, not SE3.inverse: KITTI's Tr is rigid only to its printed digits, and SHINE/N3 do this
    return np.linalg.inv(Tr) @ poses_cam @ Tr


def camera_poses_from_lidar(poses_lidar: np.ndarray, Tr: np.ndarray) -> np.ndarray:
    """Inverse of `lidar_poses_from_camera`: pose_cam = Tr @ T_world_lidar @ inv(Tr)."""
    return Tr @ poses_lidar @ np.linalg.inv(Tr)


# ------------------------------------------------------------------------------------------------
# the sequence
# ------------------------------------------------------------------------------------------------


def list_scans(scan_dir: str) -> list[str]:
    """Scan files (*.bin, *.ply, *.pcd) in scan_dir sorted by name (digit runs compared as numbers)."""
    names = [n for n in os.listdir(scan_dir) if is_scan_file(n) and os.path.isfile(os.path.join(scan_dir, n))]
    return [os.path.join(scan_dir, n) for n in sorted(names, key=natural_key)]


class KittiSequence(Sequence):
    """A KITTI-layout LiDAR sequence (see the module docstring). Frames hold LiDAR-frame points and
    LiDAR poses `inv(Tr) @ pose_cam @ Tr`.

    Extra attributes: scan_paths (all scans, sorted), Tr ([4,4] T_cam_velo, identity without calib.txt),
    poses_cam ([M,4,4] the selected lines of poses.txt as written).
    """

    thread_safe_frames = True  # each frame is its own file: frames may be read from several threads

    kind = "kitti"

    def __init__(self, data_dir, begin_frame: int = 0, end_frame: int = -1, every_frame: int = 1):
        data_dir = os.fspath(data_dir)
        if not os.path.isdir(data_dir):
            raise DataError(f"{data_dir}: sequence directory not found; check the path (data.path / --data)")
        scan_dir = os.path.join(data_dir, "velodyne")
        if not os.path.isdir(scan_dir):
            raise DataError(f"{data_dir}: no velodyne/ directory; a KITTI sequence needs velodyne/*.bin|*.ply|*.pcd "
                            "+ poses.txt (+ calib.txt)")
        scans = list_scans(scan_dir)
        if not scans:
            raise DataError(f"{scan_dir}: no scans found; expected files *.bin (KITTI float32 x,y,z,i), "
                            "*.ply or *.pcd")
        poses_cam = read_poses_for(os.path.join(data_dir, "poses.txt"), len(scans), "scans", scan_dir,
                                   "a KITTI sequence needs poses.txt with one line of 12 numbers (row-major 3x4) "
                                   "per scan")
        calib_path = os.path.join(data_dir, "calib.txt")
        if os.path.isfile(calib_path):
            Tr = read_calib(calib_path)
        else:
            Tr = np.eye(4)
            if data_dir not in _identity_logged:
                _identity_logged.add(data_dir)
                log.info("%s: no calib.txt; using Tr = identity (poses.txt taken as LiDAR poses)", data_dir)
        self.Tr = Tr
        self.scan_paths = scans
        lidar = lidar_poses_from_camera(poses_cam, Tr)
        super().__init__(data_dir, len(scans), lidar, begin_frame, end_frame, every_frame)
        self.poses_cam = poses_cam[self.indices]

    def _read_points(self, index: int) -> np.ndarray:
        return read_scan(self.scan_paths[index])
