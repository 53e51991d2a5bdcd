"""TUM RGB-D benchmark sequences (https://cvg.cit.tum.de/data/datasets/rgbd-dataset) as depth sequences.

Layout of a sequence directory (as downloaded, e.g. rgbd_dataset_freiburg1_xyz/)::

    depth.txt        '# ...' comments, then one line 'timestamp depth/<timestamp>.png' per depth image
    groundtruth.txt  '# ...' comments, then 'timestamp tx ty tz qx qy qz qw' (T_world_camera, Hamilton, w last)
    depth/*.png      uint16 depth, 5000 units per metre (0 = no return)
    rgb.txt, rgb/    colour images (not used: jaxmap maps geometry)
    intrinsics.txt   optional 'fx fy cx cy [depth units per metre]' (default scale 5000); overrides the
                     Freiburg 1/2/3 intrinsics chosen from the directory name (..._freiburg1_... -> fr1)

Each depth image is matched to the ground-truth pose NEAREST in time, if within `time_tolerance`
(default 0.02 s, as TUM's associate.py); depth images without one are skipped and counted in a warning,
and a sequence where none matches is an error. Frame numbers (`SensorFrame.index`, begin/end/every_frame)
count the matched depth images; `SensorFrame.timestamp` is the depth image's timestamp. Points are
back-projected with `jaxmap.io.depth.backproject_depth` (the images are taken as undistorted, as the
TUM tools do).
"""
from __future__ import annotations

import logging
import os
import re

import numpy as np

from jaxmap.errors import DataError
from jaxmap.io.depth import backproject_depth, read_depth_png, read_intrinsics
from jaxmap.io.kitti import Sequence
from jaxmap.io.stamped import poses_at_times, read_tum_trajectory

log = logging.getLogger("jaxmap")

TIME_TOLERANCE_S = 0.02
DEPTH_SCALE = 5000.0
# (fx, fy, cx, cy) of the Freiburg cameras, from the TUM RGB-D "file formats" page
FREIBURG_INTRINSICS = {
    1: (517.3, 516.5, 318.6, 255.3),
    2: (520.9, 521.0, 325.1, 249.7),
    3: (535.4, 539.2, 320.1, 247.6),
}


def is_tum(data_dir) -> bool:
    """A directory with depth.txt (and no poses.txt, which would make it the plain depth layout)."""
    data_dir = os.fspath(data_dir)
    return (os.path.isfile(os.path.join(data_dir, "depth.txt"))
            and not os.path.isfile(os.path.join(data_dir, "poses.txt")))


def read_file_list(path) -> tuple[np.ndarray, list[str]]:
    """TUM 'timestamp filename' list (rgb.txt, depth.txt) -> (timestamps [N] float64, filenames)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DataError(f"{path}: missing; a TUM RGB-D sequence needs depth.txt (one line 'timestamp "
                        "depth/<name>.png' per image) + groundtruth.txt + depth/*.png")
    stamps, names = [], []
    with open(path) as f:
        for lineno, line in enumerate(f, start=1):
            words = line.split()
            if not words or words[0].startswith("#"):
                continue
            if len(words) < 2:
                raise DataError(f"{path} line {lineno}: expected 'timestamp filename', found {line.strip()!r}")
            try:
                stamps.append(float(words[0]))
            except ValueError:
                raise DataError(f"{path} line {lineno}: timestamp {words[0]!r} is not a number") from None
            names.append(words[1])
    if not names:
        raise DataError(f"{path}: no image lines; expected 'timestamp depth/<name>.png' per depth image")
    return np.asarray(stamps, np.float64), names


def tum_intrinsics(data_dir) -> tuple[float, float, float, float, float, str]:
    """(fx, fy, cx, cy, depth_scale, source): intrinsics.txt if present, else Freiburg 1/2/3 by the
    directory name. DataError naming the directory when neither."""
    data_dir = os.fspath(data_dir)
    ipath = os.path.join(data_dir, "intrinsics.txt")
    if os.path.isfile(ipath):
        return (*read_intrinsics(ipath, default_scale=DEPTH_SCALE), ipath)
    m = re.search(r"freiburg([123])", os.path.basename(os.path.normpath(os.path.abspath(data_dir))))
    if m:
        cam = int(m.group(1))
        return (*FREIBURG_INTRINSICS[cam], DEPTH_SCALE, f"Freiburg {cam} (from the directory name)")
    raise DataError(f"{data_dir}: unknown TUM camera: the directory name has no 'freiburg1|2|3' and there is no "
                    f"{ipath}; write one line 'fx fy cx cy' (pixels) there, or keep the dataset's directory name "
                    "(e.g. rgbd_dataset_freiburg1_xyz)")


class TumSequence(Sequence):
    """A TUM RGB-D sequence (see the module docstring): camera-frame points, T_world_camera poses.

    Extra attributes: depth_paths (matched images, all), intrinsics (fx, fy, cx, cy), depth_scale,
    intrinsics_source, time_tolerance, n_skipped (depth images without a pose within the tolerance),
    pose_dt ([M] s, time between each selected image and its pose).
    """

    kind = "tum"

    def __init__(self, data_dir, begin_frame: int = 0, end_frame: int = -1, every_frame: int = 1,
                 time_tolerance: float | None = None):
        data_dir = os.fspath(data_dir)
        if not os.path.isdir(data_dir):
            raise DataError(f"{data_dir}: sequence directory not found; check the path (data.path / --data)")
        self.time_tolerance = TIME_TOLERANCE_S if time_tolerance is None else float(time_tolerance)
        t_depth, names = read_file_list(os.path.join(data_dir, "depth.txt"))
        gt_path = os.path.join(data_dir, "groundtruth.txt")
        if not os.path.isfile(gt_path):
            raise DataError(f"{gt_path}: missing; jaxmap needs the ground-truth poses of a TUM sequence "
                            "(lines 'timestamp tx ty tz qx qy qz qw'); sequences without ground truth cannot be mapped")
        t_gt, P_gt = read_tum_trajectory(gt_path, what="TUM ground truth")
        fx, fy, cx, cy, scale, src = tum_intrinsics(data_dir)
        self.intrinsics, self.depth_scale, self.intrinsics_source = (fx, fy, cx, cy), scale, src
        ok, T, dt = poses_at_times(t_depth, t_gt, P_gt, self.time_tolerance, interpolate=False)
        self.n_skipped = int((~ok).sum())
        if not ok.any():
            raise DataError(f"{gt_path}: no ground-truth pose within {self.time_tolerance} s of any of the "
                            f"{len(names)} depth images in depth.txt (depth {t_depth.min():.3f} .. {t_depth.max():.3f} "
                            f"s, ground truth {t_gt.min():.3f} .. {t_gt.max():.3f} s); check that the files belong "
                            "to the same sequence")
        if self.n_skipped:
            log.warning("%s: skipped %d of %d depth images with no ground-truth pose within %g s", data_dir,
                        self.n_skipped, len(names), self.time_tolerance)
        keep = np.flatnonzero(ok)
        self.depth_paths = [os.path.join(data_dir, names[k]) for k in keep]
        super().__init__(data_dir, len(keep), T[ok], begin_frame, end_frame, every_frame,
                         timestamps_all=t_depth[ok])
        self.pose_dt = dt[ok][self.indices]

    def read_depth(self, index: int) -> np.ndarray:
        """Metric depth [H,W] float32 (0 = no return) of frame number `index` (not the selection index)."""
        raw = read_depth_png(self.depth_paths[index])
        return (raw.astype(np.float64) / self.depth_scale).astype(np.float32)

    def _read_points(self, index: int) -> np.ndarray:
        raw = read_depth_png(self.depth_paths[index])
        return backproject_depth(raw.astype(np.float64) / self.depth_scale, *self.intrinsics)
