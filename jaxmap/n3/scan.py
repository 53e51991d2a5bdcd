"""Host side of a frame: how a map starts, and a scan checked, preprocessed, moved to the map frame and
padded to a bucket.

`MapStart` settles a map from its config and its first frame before anything is compiled (the range-image
layout, the map frame, the host or the device path); every way into an N3 map starts from one. Its
`prepare` is the one place a scan takes the host path (crop, downsample, PCA normals; numpy/scipy, ~0.2 s a
city scan on 2 cores) or the device path (only checked: the frame program preprocesses), and `batch_of`
the one place it becomes the frame program's batch. `jaxmap map` prepares the next frames in the frame
loop's prefetch thread (`jaxmap.frame_loop.Prefetcher`), off the critical path (numpy and scipy's k-d
tree release the GIL), and then, in order, pads each scan, moves it to the map frame and uploads it
(`Uploader`).
"""
from __future__ import annotations

import dataclasses
import logging

import jax
import numpy as np

from jaxmap.errors import DataError
from jaxmap.geometry import SE3, validate_pose
from jaxmap.n3.routing import Place, Route
from jaxmap.n3.scan_batch import RawScan, ScanBatch
from jaxmap.n3.state import N3Static, origin_vox_for
from jaxmap.preprocess import drop_veil, layout_of, preprocess_points, with_layout
from jaxmap.preprocess_device import resolve
from jaxmap.range_image import min_range_image
from jaxmap.sizes import bucket_for  # noqa: F401  (re-exported: the frame loops pad with scan.bucket_for)

log = logging.getLogger("jaxmap")


def clean_points(points_s, frame: int) -> np.ndarray:
    """[N, 3] float32 without NaN/inf rows; a clear error for a wrong shape."""
    points_s = np.asarray(points_s, np.float32)
    if points_s.ndim != 2 or points_s.shape[1] != 3:
        raise DataError(f"frame {frame}: points must be an [N, 3] array, got shape {points_s.shape}")
    finite = np.all(np.isfinite(points_s), axis=1)
    if not finite.all():
        log.warning("frame %d: dropped %d NaN/inf points", frame, int((~finite).sum()))
        points_s = points_s[finite]
    return points_s


def check_frame(points_s, pose, frame: int):
    """(points [N, 3] float32 without NaN/inf rows, pose [4, 4] float64), checked: all a frame needs
    on the host when the frame program preprocesses it (`preprocess.device`)."""
    pose = np.asarray(pose, np.float64)
    validate_pose(pose, where=f"pose of frame {frame}")
    return clean_points(points_s, frame), pose


def preprocess(points_s, pose, cfg_preprocess, frame: int, image: bool = False):
    """(points [M, 3], normals [M, 3]) sensor frame, the pose [4, 4] float64, checked, and with `image` the
    whole scan's range image [H, W] float32 (the free-space evidence's; its layout is cfg_preprocess's),
    else None. Mixed pixels and isolated returns are dropped from the points (`preprocess.veil_m`), not
    from the image: there they still block the free-space test (they say something may be there; gone,
    the rays beside a depth edge would free the voxels of the edge whose returns they replaced)."""
    points_s, pose = check_frame(points_s, pose, frame)
    # one range image a scan: the veil's neighbours and the evidence's footprints read the same one
    layout = layout_of(cfg_preprocess)
    img = min_range_image(points_s, layout) if (image or cfg_preprocess.veil_m > 0) and layout is not None else None
    raw = drop_veil(points_s, cfg_preprocess, img)
    pts, nrm = preprocess_points(raw, cfg_preprocess)
    return pts, nrm, pose, img if image else None


def needs_layout(cfg) -> bool:
    """Whether a MapConfig still has to read its range-image layout off a scan (veil filter, free-space
    evidence or range-image normals on, `preprocess.image_rows` 0)."""
    p = cfg.preprocess
    return (cfg.evidence.enabled or p.veil_m > 0 or p.normals == "range_image") and p.image_rows == 0


def resolve_layout(cfg, points_s, frame: int = 0):
    """cfg (a MapConfig) with the range-image layout of raw scan points_s [N, 3] (sensor frame) when it has
    none yet (`needs_layout`), logged; the layout then holds for every scan of the run."""
    if not needs_layout(cfg):
        return cfg
    pts = clean_points(points_s, frame)
    try:
        pre = with_layout(cfg.preprocess, pts)
    except ValueError as e:
        raise DataError(f"frame {frame}: {e}; set preprocess.image_rows/image_cols/image_elev0_deg/"
                        "image_elev_step_deg by hand, or turn evidence.enabled and preprocess.veil_m off") from None
    log.info("range image of the scans: %s (read off frame %d)", layout_of(pre).describe(), frame)
    return dataclasses.replace(cfg, preprocess=pre)


def empty_image(layout) -> np.ndarray:
    """A range image with no return (a frame whose image is unknown: it says nothing free)."""
    return np.full((layout.rows, layout.cols), np.inf, np.float32)


def to_raw(points_s: np.ndarray, pose: np.ndarray, origin_w: np.ndarray, bucket: int) -> RawScan:
    """Sensor-frame points [N, 3] -> a RawScan padded to `bucket` rows, with the pose in the map
    frame (the translation relative to the map origin in float64, rounded once)."""
    n = len(points_s)
    out = np.zeros((bucket, 3), np.float32)
    out[:n] = points_s
    T_w_s = SE3.from_matrix(pose)
    return RawScan(out, np.arange(bucket) < n, T_w_s.rotation().matrix.astype(np.float32),
                   (T_w_s.translation() - origin_w).astype(np.float32))


def to_batch(points_s: np.ndarray, normals_s: np.ndarray, pose: np.ndarray, origin_w: np.ndarray,
             bucket: int, image: np.ndarray | None = None) -> ScanBatch:
    """Sensor-frame points/normals [M, 3] -> a ScanBatch in the map frame padded to `bucket` rows.

    The rigid transform is done in float64 and rounded once, so map-frame coordinates are as
    precise as float32 allows however far the scene is from the world origin. Padding rows sit one
    metre from the sensor, valid = False. image: the scan's range image (free-space evidence), carried
    with the sensor's rotation R_map_sensor; None: neither.
    """
    T_w_s = SE3.from_matrix(pose)
    # T_map_sensor: the map frame is the world frame shifted by origin_w (subtracted in float64 first)
    T_m_s = SE3.from_rotation_and_translation(T_w_s.rotation(), T_w_s.translation() - origin_w)
    pts = T_m_s.apply(points_s.astype(np.float64)).astype(np.float32)
    nrm = T_m_s.rotation().astype(np.float32).apply(normals_s).astype(np.float32)  # float32 matmul
    sensor = T_m_s.translation().astype(np.float32)
    n = len(pts)
    out_p = np.empty((bucket, 3), np.float32)
    out_n = np.empty((bucket, 3), np.float32)
    out_p[:n], out_n[:n] = pts, nrm
    out_p[n:], out_n[n:] = sensor + 1.0, (0.0, 0.0, 1.0)
    rot = T_m_s.rotation().matrix.astype(np.float32) if image is not None else None
    return ScanBatch(out_p, out_n, np.arange(bucket) < n, sensor, rot, image)


@dataclasses.dataclass(frozen=True, eq=False)
class PreparedScan:
    """A scan made ready on the host for an N3 map (`MapStart.prepare`), sensor frame: points [M, 3]
    float32 (preprocessed; with `preprocess.device` only checked), normals [M, 3] float32 (None with
    `preprocess.device`: the frame program estimates them), image [H, W] float32 the whole scan's range
    image (the free-space evidence's; None when it is off)."""

    points: np.ndarray
    normals: np.ndarray | None = None
    image: np.ndarray | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class MapStart:
    """How an N3 map starts, settled before anything is compiled or allocated.

    cfg: the MapConfig with its preprocessing's place decided (`preprocess_device.resolve`) and the
    range-image layout read off the first scan (`resolve_layout`); static: its `N3Static`; anchor: [3]
    float64 the first frame's sensor position in the world (None until a first pose is known), which
    places the map frame (`origin_vox`: snapped to the coarsest voxel) and a map of submaps' first one.
    `jaxmap map`, mapping at given poses, SLAM and `N3Mapper` itself start a map from one (`MapStart.of`,
    then `N3Mapper(start=...)`), and prepare its scans with it."""

    cfg: object
    static: N3Static
    anchor: np.ndarray | None = None

    @classmethod
    def of(cls, cfg, points_s=None, pose=None, frame: int = 0) -> "MapStart":
        """The start of a map of `cfg` (a MapConfig) whose first frame is the raw scan points_s [N, 3]
        (sensor frame) at pose [4, 4] T_world_sensor; either may be None (not known yet)."""
        cfg = dataclasses.replace(cfg, preprocess=resolve(cfg.preprocess))
        if points_s is not None:
            cfg = resolve_layout(cfg, points_s, frame)
        static = N3Static.from_config(cfg)
        if pose is not None:
            validate_pose(pose, "pose of frame 0")
            pose = np.asarray(pose, np.float64)[:3, 3]
        return cls(cfg, static, pose)

    @property
    def origin_vox(self) -> np.ndarray | None:
        """[3] int32 the map frame's origin in leaf voxels (`state.origin_vox_for`; None: no first pose yet)."""
        return None if self.anchor is None else origin_vox_for(self.static, self.anchor)

    @property
    def origin(self) -> np.ndarray | None:
        """[3] float64 world position of the map frame (None: no first pose yet)."""
        return None if self.anchor is None else self.origin_vox * self.static.leaf

    @property
    def device(self) -> bool:
        """Whether the frame program preprocesses the scans (`preprocess.device`)."""
        return self.static.preprocess is not None

    def prepare(self, points_s, pose, frame: int) -> tuple[PreparedScan, np.ndarray]:
        """(the scan points_s [N, 3] made ready for the map, pose [4, 4] float64 checked) of frame `frame`."""
        if self.device:
            pts, pose = check_frame(points_s, pose, frame)
            return PreparedScan(pts), pose
        pts, nrm, pose, img = preprocess(points_s, pose, self.cfg.preprocess, frame, image=self.static.evidence)
        return PreparedScan(pts, nrm, img), pose

    def batch(self, scan: PreparedScan, pose, origin_w, bucket: int):
        """The frame program's batch of a prepared scan at pose, in the map frame at origin_w [3], `bucket`
        rows. With the evidence on and no image, an image with no return: the frame sees nothing free."""
        image = scan.image
        if self.static.evidence and not self.device and image is None:
            image = empty_image(self.static.image)
        return batch_of(scan.points, scan.normals, image, pose, origin_w, bucket, self.device)

    def first_batch(self, scan: PreparedScan, pose):
        """The batch of the map's first frame, a prepared scan at pose [4, 4] (the start's own, placed: the
        map frame is known), in its own bucket: what the frame program compiles from."""
        return self.batch(scan, pose, self.origin, bucket_for(len(scan.points)))

    def uploader(self, bucket: int = 0) -> "Uploader":
        """The frame loop's last reading stage for this map (`Uploader`), at its origin (the world's before
        a first pose is known); with submaps.enabled it routes the frames to their submaps (`routing.Route`)."""
        route = Route.first(self.static, self.cfg.submaps, self.anchor) if self.cfg.submaps.enabled else None
        return Uploader(np.zeros(3) if self.anchor is None else self.origin, self.device, bucket, route)


def batch_of(points_s, normals_s, image, pose, origin_w, bucket: int, raw: bool):
    """A prepared scan (sensor frame) as the frame program takes it: a RawScan the program preprocesses
    (`raw`, `preprocess.device`) or a ScanBatch, padded to `bucket` rows, in the map frame at origin_w."""
    if raw:
        return to_raw(points_s, pose, origin_w, bucket)
    return to_batch(points_s, normals_s, pose, origin_w, bucket, image)


class Uploader:
    """The last stage of reading ahead (`frame_loop.Prefetcher(then=...)`, one thread, frames in order):
    a prepared frame's scan padded to its bucket (the one of the scans before it while it fits:
    `bucket_for`), in its map frame, put on the device as the frame's `batch` (a ScanBatch with the
    frame's range image if it has one, or with `raw` a RawScan the frame program preprocesses), with
    where it is mapped (`Frame.place`, a `routing.Place`). The map frame is the one at origin_w [3]
    float64, or with a `route` (a map of submaps) the frame of the submap the route sends the frame to:
    this thread alone decides it, so every batch is made in the frame it is mapped in. `bucket`: the
    bucket so far."""

    def __init__(self, origin_w: np.ndarray, raw: bool, bucket: int = 0, route: Route | None = None):
        self.origin_w, self.raw, self.bucket, self.route = np.asarray(origin_w, np.float64), raw, bucket, route

    def __call__(self, frame):
        self.bucket = bucket_for(len(frame.points), self.bucket)
        place = Place(self.origin_w) if self.route is None else self.route(np.asarray(frame.pose)[:3, 3])
        batch = batch_of(frame.points, frame.normals, frame.image, frame.pose, place.origin_w, self.bucket, self.raw)
        return dataclasses.replace(frame, batch=jax.device_put(batch), place=place)
