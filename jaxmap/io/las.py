"""LAS / LAZ point clouds (through `laspy`; LAZ needs its `lazrs` backend: pip install 'laspy[lazrs]').

Two layouts:

* a single `.las`/`.laz` file: one frame, identity pose (the points are already in the world frame);
* a directory of `.las`/`.laz` scans (sorted by name, digit runs compared as numbers) + `poses.txt`
  with one line of 12 numbers (row-major 3x4 T_world_sensor, no calibration) per scan.

Points are the real coordinates `X * scale + offset` of the file (laspy's x, y, z), cast to float32.
float32 keeps ~1 cm only up to ~1e5 m, so files in georeferenced coordinates (UTM, ...) get a warning:
shift them near the origin first (e.g. `pdal translate in.las out.las -f transformation ...`).
"""
from __future__ import annotations

import logging
import os

import numpy as np

from jaxmap.errors import DataError
from jaxmap.io.kitti import Sequence, read_poses_for
from jaxmap.io.pointcloud import drop_nonfinite, natural_key

log = logging.getLogger("jaxmap")

LAS_EXTENSIONS = (".las", ".laz")
LARGE_COORD_M = 1e5


def is_las_file(path) -> bool:
    return os.path.splitext(os.fspath(path))[1].lower() in LAS_EXTENSIONS


def list_las(data_dir) -> list[str]:
    """The .las/.laz files of a directory sorted by name (digit runs compared as numbers)."""
    data_dir = os.fspath(data_dir)
    names = [n for n in os.listdir(data_dir) if is_las_file(n) and os.path.isfile(os.path.join(data_dir, n))]
    return [os.path.join(data_dir, n) for n in sorted(names, key=natural_key)]


def read_las(path) -> np.ndarray:
    """x, y, z of a LAS/LAZ file (scale and offset applied) -> [N,3] float32, non-finite points dropped.
    DataError naming the file if it is missing or unreadable, or if LAZ has no decompression backend."""
    import laspy

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DataError(f"{path}: file not found; check the path")
    try:
        las = laspy.read(path)
    except laspy.LaspyException as e:
        msg = str(e)
        if "backend" in msg.lower() or ("laz" in msg.lower() and path.lower().endswith(".laz")):
            raise DataError(f"{path}: cannot decompress LAZ ({msg}); pip install 'laspy[lazrs]'") from None
        raise DataError(f"{path}: not a readable LAS/LAZ file ({msg}); re-export it") from None
    except Exception as e:  # laspy/lazrs raise several types (struct.error, ValueError, ...) for corrupt files
        raise DataError(f"{path}: not a readable LAS/LAZ file ({type(e).__name__}: {e}); the file is truncated "
                        "or not LAS; re-export it") from None
    xyz = np.stack([np.asarray(las.x, np.float64), np.asarray(las.y, np.float64), np.asarray(las.z, np.float64)],
                   axis=1)
    if xyz.size and np.nanmax(np.abs(xyz)) > LARGE_COORD_M:
        log.warning("%s: coordinates up to %.3g m lose precision as float32 (~%.2g m steps); shift the cloud "
                    "near the origin first", path, float(np.nanmax(np.abs(xyz))),
                    float(np.spacing(np.float32(np.nanmax(np.abs(xyz))))))
    return drop_nonfinite(np.ascontiguousarray(xyz, dtype=np.float32), path)


class LasSequence(Sequence):
    """A LAS/LAZ file or directory (see the module docstring).

    Extra attributes: scan_paths (all scans, sorted).
    """

    kind = "las"

    def __init__(self, path, begin_frame: int = 0, end_frame: int = -1, every_frame: int = 1):
        path = os.fspath(path)
        if os.path.isfile(path):
            if not is_las_file(path):
                raise DataError(f"{path}: not a .las/.laz file")
            self.scan_paths = [path]
            super().__init__(path, 1, np.eye(4)[None], begin_frame, end_frame, every_frame)
            here = os.path.dirname(os.path.abspath(path))
            gp, gm = os.path.join(here, "gt_points.ply"), os.path.join(here, "gt_mesh.ply")
            self.gt_points_path = gp if os.path.isfile(gp) else None
            self.gt_mesh_path = gm if os.path.isfile(gm) else None
            return
        if not os.path.isdir(path):
            raise DataError(f"{path}: LAS file or directory not found; check the path (data.path / --data)")
        scans = list_las(path)
        if not scans:
            raise DataError(f"{path}: no .las/.laz files; a LAS sequence is a directory of scans + poses.txt, or "
                            "a single .las/.laz file")
        self.scan_paths = scans
        poses = read_poses_for(os.path.join(path, "poses.txt"), len(scans), "scans", path,
                               "a directory of LAS/LAZ scans needs poses.txt with one line of 12 numbers (row-major "
                               "3x4 T_world_sensor) per scan; a single .las file needs none")
        super().__init__(path, len(scans), poses, begin_frame, end_frame, every_frame)

    def _read_points(self, index: int) -> np.ndarray:
        return read_las(self.scan_paths[index])
