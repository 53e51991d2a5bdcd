"""Evaluation of a mesh file against a sequence directory: its ground truth and observed region read
from disk, the protocol (`jaxmap.metrics.protocol`) applied, the protocol floor cached beside the data.
"""
from __future__ import annotations

import logging
import math
import os

import numpy as np

from jaxmap import hostmem, moving
from jaxmap.errors import DataError
from jaxmap.frame_loop import Frame, Prefetcher, Progress, run_frames
from jaxmap.geometry import transform_points
from jaxmap.io import open_sequence
from jaxmap.metrics.culling import GtCuller, no_gt_left
from jaxmap.metrics.protocol import (
    load_mesh,
    signed_error_by_class,
    mesh_arrays,
    evaluate_culled,
    surface_fields,
    subdivide_mesh,
    PROTOCOL,
    PROTOCOLS,
    DOWN_SAMPLE_M,
    ACC_TRUNCATION_M,
    COMP_TRUNCATION_M,
    N_SAMPLES,
    OBSERVED_VOXEL_M,
)

log = logging.getLogger("jaxmap.metrics")


def voxel_thin(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Keep one point (the first) per voxel of size voxel_m. points [N,3] -> [N',3], same dtype."""
    if len(points) == 0:
        return points
    q = np.floor(points / voxel_m).astype(np.int64)
    q -= q.min(axis=0)
    span = q.max(axis=0) + 1
    if np.prod(span.astype(np.float64)) < 2**62:
        key = (q[:, 0] * span[1] + q[:, 1]) * span[2] + q[:, 2]
        _, idx = np.unique(key, return_index=True)
    else:
        _, idx = np.unique(q, axis=0, return_index=True)
    return points[np.sort(idx)]

def observed_points_of(data_dir, voxel_m: float = OBSERVED_VOXEL_M, max_frames: int | None = None,
                       progress: bool = False, begin_frame: int = 0, end_frame: int = -1,
                       every_frame: int = 1, min_range_m: float = 0.0, max_range_m: float = -1.0,
                       exclude_moving: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """All scan points of a sequence in the world frame, thinned to one per voxel_m voxel, and the sensor
    positions (pose translations of every frame). Returns (observed [O,3] float64, sensors [S,3] float64).

    max_frames: use at most this many frames, evenly spaced, for the observed points (all frames'
    positions are still returned). begin_frame/end_frame/every_frame: the frames a run mapped.
    min_range_m/max_range_m (> 0): keep only scan points in that range of their sensor, i.e. what a
    mapper that crops its input saw (GT seen only from farther away cannot be reconstructed by it).
    exclude_moving: when the sequence has moving objects (:func:`jaxmap.moving.load_moving_objects`), the
    scan points of frame i inside frame i's boxes (grown by jaxmap.moving.GHOST_INFLATE_M) are left out:
    the observed region comes from static hits only (the boxes are indexed by the real frame number).
    """
    objects = moving.load_moving_objects(data_dir) if exclude_moving else None
    sel = dict(begin_frame=begin_frame, end_frame=end_frame)
    seq = open_sequence(data_dir, every_frame=every_frame, **sel)
    poses = np.asarray(seq.poses, dtype=np.float64)
    sensors = poses[:, :3, 3].copy()
    if max_frames is not None and max_frames > 0 and len(seq) > max_frames:
        step = int(math.ceil(len(seq) / max_frames))
        seq = open_sequence(data_dir, every_frame=every_frame * step, **sel)
    chunks: list[np.ndarray] = []

    def step(frame: Frame):
        pts = np.asarray(frame.points, dtype=np.float64)
        if max_range_m > 0 or min_range_m > 0:
            r = np.linalg.norm(pts, axis=1)
            pts = pts[(r >= min_range_m) & ((r <= max_range_m) | (max_range_m <= 0))]
        if len(pts) == 0:
            return {}, None
        w = transform_points(np.asarray(frame.pose, dtype=np.float64), pts)
        if objects is not None:
            w = w[~moving.inside_boxes(w, objects.boxes_at(frame.index), moving.GHOST_INFLATE_M)]
        if len(w):
            chunks.append(voxel_thin(w, voxel_m))
            if len(chunks) > 1 and sum(len(c) for c in chunks) > 4_000_000:
                chunks[:] = [voxel_thin(np.concatenate(chunks, axis=0), voxel_m)]
        return {}, None

    run_frames(Prefetcher(seq, 0, len(seq)), step, total=len(seq), progress=Progress("observed points", progress))
    if not chunks:
        raise DataError(f"{data_dir}: the sequence has no scan points, so nothing was observed")
    obs = voxel_thin(np.concatenate(chunks, axis=0), voxel_m)
    return obs, sensors


def read_gt(data_dir) -> dict:
    """The ground truth of a sequence directory: {"points" [G,3] float64, "normals" [G,3] or None,
    "classes" [G] uint8 or None, "class_names" list or None, "mesh" path of gt_mesh.ply or None}.

    Class names come from meta.json ("gt": {"classes": [...]}), as `jaxmap synth` writes them. (A run's
    evaluation reads only the points the protocol keeps: `read_gt_culled`.)"""
    from jaxmap.io import read_points_ply

    gt_path = _gt_path(data_dir)
    pts, nrm, cls = read_points_ply(gt_path, return_normals=True, return_classes=True)
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3 or len(pts) == 0:
        raise DataError(f"{gt_path}: expected a non-empty point cloud, got shape {pts.shape}")
    return {"points": pts[:, :3], "normals": nrm, "classes": cls, **_gt_extras(data_dir, cls is not None)}


GT_CHUNK = 2_000_000  # GT points read and culled at a time (`read_gt_culled`)


def read_gt_culled(data_dir, culler, ghost_boxes=None, chunk: int = GT_CHUNK) -> dict:
    """The GT points that step 1 of the protocol keeps (`culler`: a `protocol.GtCuller`), read from
    gt_points.ply in pieces of `chunk` points, so that memory holds those, not the file (a long drive's
    GT is ~75 M points, 5 GB once read whole). Returns read_gt's fields for the kept points ("points"
    [G',3] float64, "normals", "classes"; "class_names", "mesh"), the file's point count ("count"), and
    "near_moving": with `ghost_boxes` (jaxmap.moving.Boxes) every GT point inside a box grown by the ghost
    test's reach (`moving.ghost_area` reads no GT point farther away), else None."""
    from jaxmap.io import read_points_ply_chunks

    gt_path = _gt_path(data_dir)
    reach = moving.GHOST_INFLATE_M + moving.GHOST_STATIC_M + 1e-3
    kept: dict[str, list] = {"points": [], "normals": [], "classes": [], "near": []}
    count, has_n, has_c = 0, False, False
    for pts, nrm, cls in read_points_ply_chunks(gt_path, chunk):
        p = pts.astype(np.float64)
        keep = np.flatnonzero(culler.keep(p))
        kept["points"].append(p[keep])
        has_n, has_c = nrm is not None, cls is not None
        if has_n:
            kept["normals"].append(nrm[keep])
        if has_c:
            kept["classes"].append(cls[keep])
        if ghost_boxes is not None:
            kept["near"].append(p[moving.inside_boxes(p, ghost_boxes, reach)])
        count += len(p)
    if count == 0:
        raise DataError(f"{gt_path}: expected a non-empty point cloud, got no points")

    def joined(name, width):
        return np.concatenate(kept[name]) if kept[name] else np.zeros((0, width))

    return {"points": joined("points", 3),
            "normals": joined("normals", 3).astype(np.float32) if has_n else None,
            "classes": np.concatenate(kept["classes"]) if has_c else None,
            "near_moving": joined("near", 3) if ghost_boxes is not None else None, "count": count,
            **_gt_extras(data_dir, has_c)}


def _gt_path(data_dir) -> str:
    """data_dir/gt_points.ply, or a DataError that says what is missing."""
    data_dir = os.fspath(data_dir)
    gt_path = os.path.join(data_dir, "gt_points.ply")
    if not os.path.isdir(data_dir):
        raise DataError(f"data directory not found: {data_dir}")
    if not os.path.isfile(gt_path):
        raise DataError(f"{data_dir}: no gt_points.ply (ground-truth surface points); "
                        "`jaxmap synth` writes one, or convert the dataset's GT cloud to PLY")
    return gt_path


def _gt_extras(data_dir, has_classes: bool) -> dict:
    """{"class_names" (meta.json's "gt": {"classes"}, when the points have classes), "mesh" (gt_mesh.ply)}."""
    import json

    data_dir = os.fspath(data_dir)
    names = None
    meta_path = os.path.join(data_dir, "meta.json")
    if has_classes and os.path.isfile(meta_path):
        with open(meta_path) as f:
            names = (json.load(f).get("gt") or {}).get("classes")
    mesh = os.path.join(data_dir, "gt_mesh.ply")
    return {"class_names": names, "mesh": mesh if os.path.isfile(mesh) else None}


def evaluate_mesh_file(mesh_path, data_dir, threshold_m: float = 0.1, cull_distance_m: float = 0.3,
                       eval_radius_m: float = -1.0, n_samples: int = N_SAMPLES,
                       max_frames_for_culling: int | None = None, begin_frame: int = 0, end_frame: int = -1,
                       every_frame: int = 1, min_range_m: float = 0.0, max_range_m: float = -1.0,
                       floor: bool = False, protocol: str = PROTOCOL, seed: int = 0, ghost: bool = True) -> dict:
    """Metrics of a mesh file against a sequence directory's ground truth (what `jaxmap eval` prints).

    Reads the mesh (PLY/OBJ/... via trimesh), ``data_dir/gt_points.ply`` (GT surface points, world frame,
    with normals and classes when `jaxmap synth` wrote it) and every scan of the sequence (observed
    points = scan points in the world frame, thinned to 5 cm; sensor positions = pose translations), and
    applies the protocol (module docstring). begin/end/every_frame select the frames whose scans count as
    observed (those a run mapped); min/max_range_m crop them as the mapper did.

    Returns the dict of METRIC_KEYS (+ n_pred_far, n_pred_samples), plus "signed_error_cm" (per GT class,
    :func:`signed_error_by_class`) when the GT has classes, "completion_surface_cm" with
    protocol="surface", and with floor=True "floor": the same protocol with ``gt_mesh.ply`` as the
    prediction (:func:`protocol_floor`; left out with a warning when the data has no GT mesh).

    When the sequence has moving objects (moving_objects.json or pedestrians.json, :mod:`jaxmap.moving`),
    the observed points come from static hits only (:func:`observed_points_of`), and with ghost=True the
    result has "ghost_area_m2" {kind: m^2, ..., "total": m^2}: the area of the whole predicted mesh (not
    cropped) inside the union of the boxes of the selected frames grown by 0.1 m and farther than 0.15 m
    from every GT point (:func:`jaxmap.moving.ghost_area`); the floor gets one too (~0 for a sound GT).
    """
    if protocol not in PROTOCOLS:
        raise DataError(f"unknown protocol {protocol!r}; choose from {', '.join(PROTOCOLS)}")
    data_dir = os.fspath(data_dir)
    if not os.path.isfile(mesh_path):
        raise DataError(f"mesh file not found: {mesh_path}")
    _gt_path(data_dir)  # (the missing file is named before anything is read)
    v, f = mesh_arrays(_mesh_of(os.fspath(mesh_path)))  # (the arrays only: trimesh's object holds ~2x more)
    observed, sensors = observed_points_of(data_dir, max_frames=max_frames_for_culling, begin_frame=begin_frame,
                                           end_frame=end_frame, every_frame=every_frame,
                                           min_range_m=min_range_m, max_range_m=max_range_m)
    ghost_boxes = _ghost_boxes(data_dir, begin_frame, end_frame, every_frame) if ghost else None
    gtd = _kept_gt(data_dir, observed, sensors, cull_distance_m, eval_radius_m, ghost_boxes)
    del observed
    gt = gtd["points"]
    kw = dict(threshold_m=threshold_m, n_samples=n_samples, seed=seed, down_sample_m=DOWN_SAMPLE_M,
              acc_truncation_m=ACC_TRUNCATION_M, comp_truncation_m=COMP_TRUNCATION_M)
    m, pred = evaluate_culled(v, f, gt, **kw)
    if protocol == "surface":
        m.update(surface_fields(v, f, gt, COMP_TRUNCATION_M, DOWN_SAMPLE_M))
    if ghost_boxes is not None:
        m["ghost_area_m2"] = moving.ghost_area(v, f, gtd["near_moving"], ghost_boxes)
    has_classes = gtd["classes"] is not None and gtd["normals"] is not None and gtd["class_names"]
    if has_classes:
        m["signed_error_cm"] = signed_error_by_class(pred, gt, gtd["normals"], gtd["classes"], gtd["class_names"])
    del pred, v, f
    if floor:
        if gtd["mesh"] is None:
            log.warning("%s has no gt_mesh.ply: no protocol floor", data_dir)
        else:
            selection = dict(cull_distance_m=cull_distance_m, eval_radius_m=eval_radius_m,
                             max_frames_for_culling=max_frames_for_culling, begin_frame=begin_frame,
                             end_frame=end_frame, every_frame=every_frame, min_range_m=min_range_m,
                             max_range_m=max_range_m)
            m["floor"] = _floor_metrics(data_dir, gtd, kw, ghost_boxes, has_classes, selection)
    return m


def _kept_gt(data_dir: str, observed, sensors, cull_distance_m: float, eval_radius_m: float, ghost_boxes) -> dict:
    """`read_gt_culled` of the run's observed points [O,3] and sensor positions [S,3], logged; a DataError
    when no GT point is kept."""
    gtd = read_gt_culled(data_dir, GtCuller(observed_points=observed, cull_distance_m=cull_distance_m,
                                            sensor_positions=sensors, eval_radius_m=eval_radius_m), ghost_boxes)
    log.info("eval: %d GT points (%d kept), %d observed points (5 cm), %d sensor positions",
             gtd["count"], len(gtd["points"]), len(observed), len(sensors))
    hostmem.trim()  # (the pieces' heap back to the system before the protocol's own peak)
    if len(gtd["points"]) == 0:
        raise DataError(no_gt_left(cull_distance_m, eval_radius_m))
    return gtd


def _mesh_of(mesh_path: str):
    """The (existing) mesh file as a trimesh.Trimesh with faces, or a DataError."""
    mesh = load_mesh(mesh_path)
    if len(mesh.faces) == 0:
        raise DataError(f"{mesh_path}: the mesh has zero faces (and {len(mesh.vertices)} vertices); "
                        "there is no surface to evaluate")
    return mesh


def _floor_metrics(data_dir: str, gtd: dict, kw: dict, ghost_boxes, has_classes, selection: dict) -> dict:
    """The protocol with the subdivided GT mesh as the prediction (cached beside the data): the same
    fields as the run's metrics. gtd: `read_gt_culled`'s."""
    key = _floor_key(data_dir, gtd, kw, **selection, ghost=ghost_boxes is not None)
    fm = _floor_cache(data_dir).get(key)
    if fm is None:
        gt = gtd["points"]
        fv, ff = subdivide_mesh(*mesh_arrays(gtd["mesh"]))
        fm, fpred = evaluate_culled(fv, ff, gt, **kw)
        if ghost_boxes is not None:
            fm["ghost_area_m2"] = moving.ghost_area(fv, ff, gtd["near_moving"], ghost_boxes)
        if has_classes:
            fm["signed_error_cm"] = signed_error_by_class(fpred, gt, gtd["normals"], gtd["classes"],
                                                          gtd["class_names"])
        _floor_cache_put(data_dir, key, fm)
    return fm


FLOOR_CACHE = ".jaxmap_floor_cache.json"


def _ghost_boxes(data_dir: str, begin_frame: int, end_frame: int, every_frame: int):
    """The moving objects' boxes of the selected frames (real frame numbers), or None when the sequence
    has no moving objects."""
    from jaxmap.io import open_sequence

    objects = moving.load_moving_objects(data_dir)
    if objects is None:
        return None
    seq = open_sequence(data_dir, begin_frame=begin_frame, end_frame=end_frame, every_frame=every_frame)
    return objects.boxes_of_frames(int(i) for i in seq.indices)

def _floor_key(data_dir: str, gtd: dict, kw: dict, **selection) -> str:
    """What the floor depends on: the GT files (size and mtime), the scans' directory listing time and
    every protocol setting. The floor of a scene costs a full evaluation (minutes at 10M samples) and
    is the same for every run of that scene, so it is cached next to the data."""
    import hashlib
    import json

    files = [os.path.join(data_dir, "gt_points.ply"), gtd["mesh"], os.path.join(data_dir, "poses.txt"),
             moving.moving_objects_path(data_dir)]  # (moving objects: static-only observations, ghost area)
    stat = [(os.path.basename(f), os.path.getsize(f), os.path.getmtime(f)) for f in files if f and os.path.isfile(f)]
    blob = json.dumps({"files": stat, "kw": kw, "sel": selection, "protocol": PROTOCOL}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def _floor_cache(data_dir: str) -> dict:
    import json

    try:
        with open(os.path.join(data_dir, FLOOR_CACHE)) as f:
            return json.load(f)
    except (OSError, ValueError):
        return {}


def _floor_cache_put(data_dir: str, key: str, floor_metrics: dict) -> None:
    """Best effort: a read-only data directory just means the floor is recomputed next time."""
    import json

    cache = _floor_cache(data_dir)
    cache[key] = floor_metrics
    tmp = os.path.join(data_dir, f"{FLOOR_CACHE}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w") as f:
            json.dump(cache, f)
        os.replace(tmp, os.path.join(data_dir, FLOOR_CACHE))
    except OSError as e:
        log.debug("floor cache not written in %s (%s)", data_dir, e)
