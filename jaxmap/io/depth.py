"""Depth-camera sequences: depth images -> camera-frame points.

Layout of a sequence directory::

    depth/*.png      uint16 depth in millimetres (0 = no return), one image per frame, sorted by name
    intrinsics.txt   one line "fx fy cx cy" (pixels); an optional 5th number is the depth scale in
                     units per metre (default 1000, i.e. millimetres; TUM RGB-D uses 5000)
    poses.txt        one line per image: 12 numbers, row-major 3x4 T_world_camera (no calib)
    gt_points.ply, gt_mesh.ply   optional ground truth (world frame)

Camera frame: x right, y down, z forward. Pixel (u, v) = (column, row) with depth z back-projects to
`((u - cx) z / fx, (v - cy) z / fy, z)`; pixel centres are at integer coordinates.
"""
from __future__ import annotations

import logging
import os

import numpy as np

from jaxmap.errors import DataError
from jaxmap.io.kitti import Sequence, read_poses_for
from jaxmap.io.pointcloud import makedirs_for, natural_key

log = logging.getLogger("jaxmap")


def read_intrinsics(path, default_scale: float = 1000.0):
    """Read intrinsics.txt -> (fx, fy, cx, cy, depth_scale) floats; without a 5th number depth_scale is
    `default_scale` (1000 = millimetres; the TUM RGB-D reader passes 5000)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DataError(f"{path}: missing; a depth sequence needs intrinsics.txt with one line 'fx fy cx cy'")
    with open(path) as f:
        lines = [ln for ln in f.read().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise DataError(f"{path}: empty; write one line 'fx fy cx cy' (pixels)")
    words = lines[0].split()
    try:
        vals = [float(w) for w in words]
    except ValueError:
        raise DataError(f"{path}: not a number in {lines[0]!r}; expected 'fx fy cx cy'") from None
    if len(vals) not in (4, 5):
        raise DataError(f"{path}: expected 4 numbers 'fx fy cx cy' (optionally a 5th: depth units per metre), "
                        f"found {len(vals)}")
    fx, fy, cx, cy = vals[:4]
    scale = vals[4] if len(vals) == 5 else float(default_scale)
    if not (fx > 0 and fy > 0 and scale > 0 and np.isfinite(vals).all()):
        raise DataError(f"{path}: fx, fy and the depth scale must be positive and finite, got {vals}")
    return fx, fy, cx, cy, scale


def write_intrinsics(path, fx, fy, cx, cy) -> None:
    """Write intrinsics.txt: one line 'fx fy cx cy' (exact float64 round trip)."""
    makedirs_for(path)
    with open(os.fspath(path), "w") as f:
        f.write(" ".join(repr(float(v)) for v in (fx, fy, cx, cy)) + "\n")


def read_depth_png(path) -> np.ndarray:
    """Read a 16-bit single-channel PNG -> [H,W] uint16 (raw units, e.g. millimetres)."""
    from PIL import Image

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DataError(f"{path}: depth image not found")
    try:
        with Image.open(path) as im:
            mode = im.mode
            arr = np.array(im)
    except Exception as e:  # PIL raises several types for corrupt files
        raise DataError(f"{path}: unreadable depth image ({e}); expected a 16-bit PNG") from None
    if arr.ndim != 2 or mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise DataError(f"{path}: depth PNG must be single-channel 16-bit (uint16 millimetres), got PIL mode "
                        f"{mode!r} with shape {arr.shape}; save depth as uint16, not 8-bit or colour")
    if arr.dtype != np.uint16:
        if arr.size and (arr.min() < 0 or arr.max() > 65535):
            raise DataError(f"{path}: depth values outside the uint16 range")
        arr = arr.astype(np.uint16)
    return arr


def write_depth_png(path, depth_u16) -> None:
    """Write [H,W] uint16 depth as a 16-bit grayscale PNG (deterministic bytes)."""
    from PIL import Image

    depth_u16 = np.asarray(depth_u16)
    if depth_u16.ndim != 2 or depth_u16.dtype != np.uint16:
        raise DataError(f"{path}: depth must be [H,W] uint16, got {depth_u16.shape} {depth_u16.dtype}")
    makedirs_for(path)
    Image.fromarray(np.ascontiguousarray(depth_u16)).save(os.fspath(path), format="PNG")


def check_depth_size(path: str, shape: tuple, intrinsics: tuple, source: str, first: tuple | None = None) -> None:
    """DataError when a depth image of `shape` [H, W] does not fit the intrinsics (fx, fy, cx, cy) read
    from `source`: their principal point must lie in the central half of the image (intrinsics made for
    another resolution put it near an edge or outside), and every image must have the size `first`
    ([H, W] of the sequence's first image read, if given)."""
    h, w = int(shape[0]), int(shape[1])
    if first is not None and (h, w) != tuple(first):
        raise DataError(f"{path}: {w} x {h} pixels, but the sequence's other depth images are {first[1]} x "
                        f"{first[0]}; all depth images of a sequence must have one size (and its intrinsics)")
    cx, cy = float(intrinsics[2]), float(intrinsics[3])
    if not (0.25 * w <= cx <= 0.75 * w and 0.25 * h <= cy <= 0.75 * h):
        raise DataError(f"{path}: {w} x {h} pixels, but {source} puts the principal point at (cx, cy) = "
                        f"({cx:g}, {cy:g}), which fits an image of about {2 * cx:.0f} x {2 * cy:.0f}: the intrinsics "
                        f"are for another image size; scale fx fy cx cy to {w} x {h} or use the images they belong to")


def pixel_rays(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Camera-frame ray directions with z = 1 for every pixel, row-major: [H*W,3] float64."""
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    return np.stack([(u.reshape(-1) - cx) / fx, (v.reshape(-1) - cy) / fy, np.ones(width * height)], axis=1)


def backproject_depth(depth_m: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Back-project valid pixels (finite depth > 0) of [H,W] metric depth -> [N,3] float32 camera-frame
    points (x right, y down, z forward), in row-major pixel order."""
    depth_m = np.asarray(depth_m, dtype=np.float64)
    H, W = depth_m.shape
    z = depth_m.reshape(-1)
    valid = np.isfinite(z) & (z > 0)
    rays = pixel_rays(W, H, fx, fy, cx, cy)[valid]
    return (rays * z[valid, None]).astype(np.float32)


class DepthSequence(Sequence):
    """A depth-camera sequence (see the module docstring). Frames hold camera-frame points of the valid
    pixels and T_world_camera poses.

    Extra attributes: depth_paths, intrinsics (fx, fy, cx, cy), depth_scale (units per metre).
    """

    thread_safe_frames = True  # each frame is its own file: frames may be read from several threads

    kind = "depth"

    def __init__(self, data_dir, begin_frame: int = 0, end_frame: int = -1, every_frame: int = 1):
        data_dir = os.fspath(data_dir)
        if not os.path.isdir(data_dir):
            raise DataError(f"{data_dir}: sequence directory not found; check the path (data.path / --data)")
        depth_dir = os.path.join(data_dir, "depth")
        if not os.path.isdir(depth_dir):
            raise DataError(f"{data_dir}: no depth/ directory; a depth sequence needs depth/*.png (uint16 mm) "
                            "+ intrinsics.txt + poses.txt")
        names = sorted((n for n in os.listdir(depth_dir) if n.lower().endswith(".png")), key=natural_key)
        if not names:
            raise DataError(f"{depth_dir}: no depth images found; expected *.png (uint16, millimetres, 0 = no return)")
        self.depth_paths = [os.path.join(depth_dir, n) for n in names]
        fx, fy, cx, cy, scale = read_intrinsics(os.path.join(data_dir, "intrinsics.txt"))
        self.intrinsics = (fx, fy, cx, cy)
        self.depth_scale = scale
        poses = read_poses_for(os.path.join(data_dir, "poses.txt"), len(names), "depth images", depth_dir,
                               "a depth sequence needs poses.txt with one line of 12 numbers "
                               "(row-major 3x4 T_world_camera) per image")
        super().__init__(data_dir, len(names), poses, begin_frame, end_frame, every_frame)

    def _read_raw(self, index: int) -> np.ndarray:
        """The uint16 image of frame number `index`, checked against the intrinsics and the first image."""
        path = self.depth_paths[index]
        raw = read_depth_png(path)
        check_depth_size(path, raw.shape, self.intrinsics, os.path.join(self.data_dir, "intrinsics.txt"),
                         getattr(self, "_image_shape", None))
        self._image_shape = raw.shape
        return raw

    def read_depth(self, index: int) -> np.ndarray:
        """Metric depth [H,W] float32 (0 = no return) of frame number `index` (not the selection index)."""
        raw = self._read_raw(index)
        return (raw.astype(np.float64) / self.depth_scale).astype(np.float32)

    def _read_points(self, index: int) -> np.ndarray:
        raw = self._read_raw(index)
        fx, fy, cx, cy = self.intrinsics
        return backproject_depth(raw.astype(np.float64) / self.depth_scale, fx, fy, cx, cy)
