"""Reconstruction metrics with the culling protocol of N3-Mapping, section IV-A (README: Evaluation protocol).

Protocol, all in the world frame, metres in and centimetres / percent out:

1. The prediction is a set of points sampled uniformly (area-weighted) on the predicted mesh
   (:func:`sample_mesh`, deterministic for a seed).
2. GT is culled to the observed region: GT points farther than ``cull_distance_m`` from every observed
   scan point are dropped (the map cannot know what no scan saw).
3. If ``eval_radius_m > 0``, GT points farther than that from every sensor position are dropped too
   ("evaluate within the 20 m the mapper sees" when scans are cropped to 20 m).
4. The prediction is cropped to the axis-aligned bounding box of the culled GT, grown by the threshold.
5. Accuracy = mean distance pred -> GT, Completion = mean distance GT -> pred, Chamfer-L1 = their mean
   (all cm); Precision = % of pred within the threshold of GT, Completion ratio = % of GT within the
   threshold of pred, F-score = 2 P R / (P + R) with R = completion ratio (all %).

Distances are surface to surface where the meshes are known: Accuracy measures each predicted sample
against the GT *mesh* and Completion each GT point against the predicted *mesh* (open3d's BVH
distance query). Point-to-point nearest neighbours between two samplings would add a floor of about
half the sample spacing (about 5 cm for GT points at 100 per m^2, above the 2 cm that N3 reports);
they are the fallback when a mesh is not given or open3d is missing (scipy cKDTree, all cores).
This module imports numpy at import time only (scipy, trimesh and open3d lazily), so it runs on
machines without open3d.
"""
from __future__ import annotations

import logging
import math
import os

import numpy as np

from jaxmap.errors import DataError

log = logging.getLogger(__name__)

METRIC_KEYS = (
    "accuracy_cm", "completion_cm", "chamfer_l1_cm", "completion_ratio", "precision", "f_score",
    "threshold_m", "n_pred", "n_gt",
)
OBSERVED_VOXEL_M = 0.05  # observed scan points are thinned to one per voxel of this size for culling


def _as_points(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise DataError(f"{name}: expected an array of shape [N,3], got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise DataError(f"{name}: contains NaN or inf")
    return a


def _nn_dist(tree_points: np.ndarray, query: np.ndarray, upper: float = np.inf) -> np.ndarray:
    """Distance from each query point to its nearest tree point (inf beyond `upper`)."""
    from scipy.spatial import cKDTree

    if len(tree_points) == 0:
        return np.full(len(query), np.inf)
    d, _ = cKDTree(tree_points).query(query, k=1, distance_upper_bound=upper, workers=-1)
    return d


def mesh_distance(mesh, query: np.ndarray) -> np.ndarray | None:
    """Unsigned distance [N] from points [N,3] to a triangle mesh (trimesh.Trimesh), or None when
    open3d is not installed (the caller then falls back to point sets)."""
    try:
        import open3d as o3d
    except ImportError:
        return None
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(mesh.faces, dtype=np.uint32)))
    q = o3d.core.Tensor(np.ascontiguousarray(query, dtype=np.float32))
    return scene.compute_distance(q).numpy().astype(np.float64)


def cull_gt(gt_points, *, observed_points=None, cull_distance_m: float = 0.3, sensor_positions=None,
            eval_radius_m: float = -1.0) -> np.ndarray:
    """Steps 2-3 of the protocol. gt_points [G,3] -> the kept GT points [G',3] (float64, world frame)."""
    gt = _as_points(gt_points, "gt_points")
    if observed_points is not None:
        obs = _as_points(observed_points, "observed_points")
        if len(obs) == 0:
            raise DataError("observed_points is empty: nothing was observed, so all GT would be culled")
        d = _nn_dist(obs, gt, upper=cull_distance_m * (1 + 1e-9) + 1e-12)
        gt = gt[d <= cull_distance_m]
    if eval_radius_m is not None and eval_radius_m > 0:
        if sensor_positions is None:
            raise DataError("eval_radius_m > 0 needs sensor_positions (the pose translations)")
        sp = _as_points(sensor_positions, "sensor_positions")
        d = _nn_dist(sp, gt, upper=eval_radius_m * (1 + 1e-9) + 1e-12)
        gt = gt[d <= eval_radius_m]
    return gt


def evaluate(pred_points, gt_points, *, threshold_m: float = 0.1, observed_points=None,
             cull_distance_m: float = 0.3, sensor_positions=None, eval_radius_m: float = -1.0,
             pred_mesh=None, gt_mesh=None) -> dict:
    """Reconstruction metrics of predicted surface points against GT surface points.

    Args:
      pred_points: [P,3] points sampled on the predicted surface (world frame, metres).
      gt_points: [G,3] GT surface points (world frame).
      threshold_m: distance threshold of precision / completion ratio / F-score.
      observed_points: [O,3] scan points in the world frame, or None for no culling.
      cull_distance_m: GT points farther than this from every observed point are dropped.
      sensor_positions: [S,3] sensor positions in the world frame (needed when eval_radius_m > 0).
      eval_radius_m: > 0 keeps only GT within this distance of some sensor position.
      pred_mesh: the predicted trimesh, when known: Completion is then GT point -> predicted surface.
      gt_mesh: the GT trimesh, when known: Accuracy is then predicted sample -> GT surface.

    Returns:
      dict with exactly the keys of METRIC_KEYS: accuracy_cm, completion_cm, chamfer_l1_cm (cm, 4
      decimals), completion_ratio, precision, f_score (%, 3 decimals), threshold_m, n_pred and n_gt
      (points that entered the metrics, after culling and cropping). A prediction with no point inside
      the GT box gives infinite distances and zero ratios rather than an error, so a failed method still
      gets a row in a benchmark table.
    """
    if not threshold_m > 0:
        raise DataError(f"threshold_m must be positive, got {threshold_m}")
    pred = _as_points(pred_points, "pred_points")
    gt = cull_gt(gt_points, observed_points=observed_points, cull_distance_m=cull_distance_m,
                 sensor_positions=sensor_positions, eval_radius_m=eval_radius_m)
    if len(gt) == 0:
        raise DataError(
            "no GT point is left after culling (cull distance "
            f"{cull_distance_m} m, eval radius {eval_radius_m} m): do the GT and the scans share a frame?"
        )
    lo = gt.min(axis=0) - threshold_m
    hi = gt.max(axis=0) + threshold_m
    pred = pred[np.all((pred >= lo) & (pred <= hi), axis=1)]
    if len(pred) == 0:
        log.warning("no predicted point inside the GT bounding box; metrics are infinite / zero")
        return {
            "accuracy_cm": math.inf, "completion_cm": math.inf, "chamfer_l1_cm": math.inf,
            "completion_ratio": 0.0, "precision": 0.0, "f_score": 0.0,
            "threshold_m": float(threshold_m), "n_pred": 0, "n_gt": int(len(gt)),
        }
    d_pred = mesh_distance(gt_mesh, pred) if gt_mesh is not None else None     # accuracy: pred -> GT
    if d_pred is None:
        d_pred = _nn_dist(gt, pred)
    d_gt = mesh_distance(pred_mesh, gt) if pred_mesh is not None else None     # completion: GT -> pred
    if d_gt is None:
        d_gt = _nn_dist(pred, gt)
    acc = float(d_pred.mean()) * 100.0
    comp = float(d_gt.mean()) * 100.0
    precision = float(np.mean(d_pred < threshold_m)) * 100.0
    recall = float(np.mean(d_gt < threshold_m)) * 100.0
    f = 2.0 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "accuracy_cm": round(acc, 4),
        "completion_cm": round(comp, 4),
        "chamfer_l1_cm": round(0.5 * (acc + comp), 4),
        "completion_ratio": round(recall, 3),
        "precision": round(precision, 3),
        "f_score": round(f, 3),
        "threshold_m": float(threshold_m),
        "n_pred": int(len(pred)),
        "n_gt": int(len(gt)),
    }


def _load_mesh(mesh, where: str = "mesh"):
    import trimesh

    if isinstance(mesh, trimesh.Trimesh):
        return mesh
    path = os.fspath(mesh)
    if not os.path.isfile(path):
        raise DataError(f"mesh file not found: {path}")
    try:
        m = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for malformed files
        raise DataError(f"{path}: could not read a triangle mesh ({type(e).__name__}: {e})") from None
    if not isinstance(m, trimesh.Trimesh):
        raise DataError(f"{path}: not a triangle mesh")
    return m


def sample_mesh(mesh, n: int, seed: int = 0) -> np.ndarray:
    """Sample n points uniformly (area-weighted) on a triangle mesh.

    Args:
      mesh: trimesh.Trimesh or a path to a mesh file.
      n: number of points.
      seed: the same seed and mesh give the same points.

    Returns: [n,3] float64 points in the mesh's frame.
    """
    m = _load_mesh(mesh)
    faces = np.asarray(m.faces)
    if len(faces) == 0:
        raise DataError("the mesh has zero faces: nothing to sample (did the method produce a surface?)")
    tri = np.asarray(m.vertices, dtype=np.float64)[faces]  # [F,3,3]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = area.sum()
    if not total > 0:
        raise DataError("the mesh has zero surface area: nothing to sample")
    rng = np.random.default_rng(seed)
    cdf = np.cumsum(area)
    face = np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right")
    face = np.minimum(face, len(faces) - 1)
    u = rng.random((n, 2))
    flip = u.sum(axis=1) > 1.0  # reflect into the triangle: uniform barycentric coordinates
    u[flip] = 1.0 - u[flip]
    t = tri[face]
    return t[:, 0] + u[:, :1] * (t[:, 1] - t[:, 0]) + u[:, 1:] * (t[:, 2] - t[:, 0])


def evaluate_mesh(mesh, gt_points, *, n_samples: int = 1_000_000, seed: int = 0, **kw) -> dict:
    """evaluate(sample_mesh(mesh, n_samples, seed), gt_points, pred_mesh=mesh, **kw); see :func:`evaluate`.

    An empty mesh (no faces) gives the metrics of an empty prediction (infinite distances, zero ratios).
    """
    m = _load_mesh(mesh)
    if len(m.faces) == 0:
        return evaluate(np.zeros((0, 3)), gt_points, **kw)
    return evaluate(sample_mesh(m, n_samples, seed), gt_points, pred_mesh=m, **kw)


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
                       every_frame: int = 1, min_range_m: float = 0.0,
                       max_range_m: float = -1.0) -> tuple[np.ndarray, np.ndarray]:
    """All scan points of a sequence in the world frame, thinned to one per voxel_m voxel, and the sensor
    positions (pose translations of every frame). Returns (observed [O,3] float64, sensors [S,3] float64).

    max_frames: use at most this many frames, evenly spaced, for the observed points (all frames'
    positions are still returned). begin_frame/end_frame/every_frame: the frames a run mapped.
    min_range_m/max_range_m (> 0): keep only scan points in that range of their sensor, i.e. what a
    mapper that crops its input saw (GT seen only from farther away cannot be reconstructed by it).
    """
    from jaxmap.geometry import transform_points
    from jaxmap.io import open_sequence

    sel = dict(begin_frame=begin_frame, end_frame=end_frame)
    seq = open_sequence(data_dir, every_frame=every_frame, **sel)
    poses = np.asarray(seq.poses, dtype=np.float64)
    sensors = poses[:, :3, 3].copy()
    if max_frames is not None and max_frames > 0 and len(seq) > max_frames:
        step = int(math.ceil(len(seq) / max_frames))
        seq = open_sequence(data_dir, every_frame=every_frame * step, **sel)
    chunks: list[np.ndarray] = []
    pending = 0
    frames = seq
    if progress:
        from tqdm import tqdm

        frames = tqdm(seq, total=len(seq), desc="observed points", unit="frame")
    for frame in frames:
        pts = np.asarray(frame.points, dtype=np.float64)
        if max_range_m > 0 or min_range_m > 0:
            r = np.linalg.norm(pts, axis=1)
            pts = pts[(r >= min_range_m) & ((r <= max_range_m) | (max_range_m <= 0))]
        if len(pts) == 0:
            continue
        w = transform_points(np.asarray(frame.pose, dtype=np.float64), pts)
        chunks.append(voxel_thin(w, voxel_m))
        pending += len(chunks[-1])
        if len(chunks) > 1 and pending > 4_000_000:
            chunks = [voxel_thin(np.concatenate(chunks, axis=0), voxel_m)]
            pending = len(chunks[0])
    if not chunks:
        raise DataError(f"{data_dir}: the sequence has no scan points, so nothing was observed")
    obs = voxel_thin(np.concatenate(chunks, axis=0), voxel_m)
    return obs, sensors


def evaluate_mesh_file(mesh_path, data_dir, threshold_m: float = 0.1, cull_distance_m: float = 0.3,
                       eval_radius_m: float = -1.0, n_samples: int = 1_000_000,
                       max_frames_for_culling: int | None = None, begin_frame: int = 0, end_frame: int = -1,
                       every_frame: int = 1, min_range_m: float = 0.0, max_range_m: float = -1.0) -> dict:
    """Metrics of a mesh file against a sequence directory's ground truth (what `jaxmap eval` prints).

    Reads the mesh (PLY/OBJ/... via trimesh), ``data_dir/gt_points.ply`` (GT surface points, world frame)
    and every scan of the sequence (observed points = scan points in the world frame, thinned to 5 cm;
    sensor positions = pose translations), then calls :func:`evaluate_mesh`; with ``gt_mesh.ply``
    present, Accuracy is measured against that surface. begin/end/every_frame select the frames whose
    scans count as observed (those a run mapped); min/max_range_m crop them as the mapper did.
    """
    from jaxmap.io import read_points_ply

    mesh_path = os.fspath(mesh_path)
    data_dir = os.fspath(data_dir)
    if not os.path.isfile(mesh_path):
        raise DataError(f"mesh file not found: {mesh_path}")
    gt_path = os.path.join(data_dir, "gt_points.ply")
    if not os.path.isdir(data_dir):
        raise DataError(f"data directory not found: {data_dir}")
    if not os.path.isfile(gt_path):
        raise DataError(f"{data_dir}: no gt_points.ply (ground-truth surface points); "
                        "`jaxmap synth` writes one, or convert the dataset's GT cloud to PLY")
    mesh = _load_mesh(mesh_path)
    if len(mesh.faces) == 0:
        raise DataError(f"{mesh_path}: the mesh has zero faces (and {len(mesh.vertices)} vertices); "
                        "there is no surface to evaluate")
    gt = np.asarray(read_points_ply(gt_path), dtype=np.float64)
    if gt.ndim != 2 or gt.shape[1] < 3 or len(gt) == 0:
        raise DataError(f"{gt_path}: expected a non-empty point cloud, got shape {gt.shape}")
    gt = gt[:, :3]
    observed, sensors = observed_points_of(data_dir, max_frames=max_frames_for_culling, begin_frame=begin_frame,
                                           end_frame=end_frame, every_frame=every_frame,
                                           min_range_m=min_range_m, max_range_m=max_range_m)
    gt_mesh_path = os.path.join(data_dir, "gt_mesh.ply")
    gt_mesh = _load_mesh(gt_mesh_path) if os.path.isfile(gt_mesh_path) else None
    log.info("eval: %d GT points, %d observed points (5 cm), %d sensor positions",
             len(gt), len(observed), len(sensors))
    return evaluate_mesh(mesh, gt, n_samples=n_samples, threshold_m=threshold_m, observed_points=observed,
                         cull_distance_m=cull_distance_m, sensor_positions=sensors,
                         eval_radius_m=eval_radius_m, gt_mesh=gt_mesh)
