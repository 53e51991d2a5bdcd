"""The evaluation protocol on points and meshes in memory (the package docstring, `jaxmap.metrics`,
describes it): culling, cropping, sampling, down-sampling, the metrics and their table.

numpy at import time only (scipy, trimesh and open3d lazily).
"""
from __future__ import annotations

import logging
import math
import os

import numpy as np

from jaxmap.errors import DataError
from jaxmap.metrics.culling import GtCuller, as_points, cull_gt, culled_or_fail, no_gt_left  # noqa: F401  (step 1)

log = logging.getLogger("jaxmap.metrics")

PROTOCOL = "shine"
PROTOCOLS = ("shine", "surface")  # "surface": shine + the extra field completion_surface_cm
METRIC_KEYS = (
    "accuracy_cm", "completion_cm", "chamfer_l1_cm", "completion_ratio", "precision", "f_score",
    "threshold_m", "n_pred", "n_gt", "protocol",
)
DOWN_SAMPLE_M = 0.02       # SHINE's down_sample_res: voxel of both point sets, and the z growth of the crop box
ACC_TRUNCATION_M = 0.2     # SHINE's truncation_acc (MaiCity): predicted points farther from GT are dropped
COMP_TRUNCATION_M = 2.0    # SHINE's truncation_com (MaiCity): GT -> prediction distances are clamped here
N_SAMPLES = 10_000_000     # SHINE's mesh_sample_point
SIGNED_MAX_M = 0.2         # signed error: predicted points whose nearest GT point is closer than this
# SHINE grows the crop box in z only. Outdoors the box's x/y sides are open ends of the GT and growing them
# changes nothing measurable; indoors they are the room's walls, and an exact box cuts away every predicted
# wall triangle a millimetre outside the GT wall (a good TSDF room mesh fell to 73 % completion ratio). So x and y
# are grown by the same 2 cm as z: the one deviation from SHINE's eval_mesh.
CROP_XY_GROW_M = 0.02
FLOOR_MAX_EDGE_M = 0.5     # the GT mesh is subdivided to this edge length before it is cropped as a prediction
OBSERVED_VOXEL_M = 0.05    # observed scan points are thinned to one per voxel of this size for culling
_CHUNK = 2_000_000         # samples generated / down-sampled per piece (bounded memory)


def _nn(tree_points: np.ndarray, query: np.ndarray, upper: float = np.inf):
    """(distance [N], index [N]) from each query point to its nearest tree point (inf / len(tree) beyond
    `upper` or when the tree is empty)."""
    from scipy.spatial import cKDTree

    if len(tree_points) == 0:
        return np.full(len(query), np.inf), np.zeros(len(query), np.int64)
    if len(query) == 0:
        return np.zeros(0), np.zeros(0, np.int64)
    return cKDTree(tree_points).query(query, k=1, distance_upper_bound=upper, workers=-1)


def _nn_dist(tree_points: np.ndarray, query: np.ndarray, upper: float = np.inf) -> np.ndarray:
    """Distance from each query point to its nearest tree point (inf beyond `upper`)."""
    return _nn(tree_points, query, upper)[0]


def mesh_distance(mesh, query: np.ndarray) -> np.ndarray | None:
    """Unsigned distance [N] from points [N,3] to a triangle mesh (trimesh.Trimesh), or None when
    open3d is not installed."""
    try:
        import open3d as o3d
    except ImportError:
        return None
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(mesh.faces, dtype=np.uint32)))
    q = o3d.core.Tensor(np.ascontiguousarray(query, dtype=np.float32))
    return scene.compute_distance(q).numpy().astype(np.float64)


def crop_box(gt: np.ndarray, z_grow_m: float = DOWN_SAMPLE_M,
             xy_grow_m: float = CROP_XY_GROW_M) -> tuple[np.ndarray, np.ndarray]:
    """The crop box: the axis-aligned bounding box of the GT points with z grown by z_grow_m (SHINE) and
    x, y by xy_grow_m (SHINE: 0; see CROP_XY_GROW_M) on both sides. Returns (lo [3], hi [3])."""
    grow = np.array([xy_grow_m, xy_grow_m, z_grow_m])
    return gt.min(axis=0) - grow, gt.max(axis=0) + grow


def crop_mesh(vertices, faces, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """open3d's ``TriangleMesh.crop(AxisAlignedBoundingBox(lo, hi))``: keep the vertices inside the box
    (bounds inclusive) and the triangles whose three vertices are all kept; unreferenced vertices are
    dropped. Returns (vertices [V',3] float64, faces [F',3] int64)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    inside = np.all((v >= np.asarray(lo)) & (v <= np.asarray(hi)), axis=1)
    f = f[inside[f].all(axis=1)]
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


def _uniform_sample_chunks(vertices, faces, n: int, seed: int = 0, chunk: int = _CHUNK):
    """Yields the samples of :func:`sample_points_uniformly` in pieces of about `chunk` points."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        raise DataError("the mesh has zero faces: nothing to sample (did the method produce a surface?)")
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    del tri
    total = float(area.sum())
    if not total > 0:
        raise DataError("the mesh has zero surface area: nothing to sample")
    # open3d (0.20): each sample picks its triangle from a discrete distribution weighted by area, i.e.
    # multinomial counts per triangle
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(n, area / total)
    ends = np.cumsum(counts)
    cuts = np.searchsorted(ends, np.arange(chunk, n, chunk), side="left") + 1
    bounds = np.unique(np.r_[0, np.minimum(cuts, len(f)), len(f)])
    for f0, f1 in zip(bounds[:-1], bounds[1:]):
        fid = np.repeat(np.arange(f0, f1), counts[f0:f1])
        if len(fid) == 0:
            continue
        r1 = np.sqrt(rng.random(len(fid)))[:, None]
        r2 = rng.random(len(fid))[:, None]
        t = f[fid]
        yield (1.0 - r1) * v[t[:, 0]] + r1 * (1.0 - r2) * v[t[:, 1]] + r1 * r2 * v[t[:, 2]]


def sample_points_uniformly(vertices, faces, n: int, seed: int = 0) -> np.ndarray:
    """open3d's ``TriangleMesh.sample_points_uniformly(n)``: each sample's triangle drawn with probability
    proportional to its area (multinomial counts per triangle), placed with barycentric coordinates
    (1 - sqrt(r1), sqrt(r1) (1 - r2), sqrt(r1) r2), r1, r2 uniform. Deterministic for a seed (numpy's
    generator instead of open3d's). Returns [n,3] float64, grouped by triangle."""
    chunks = list(_uniform_sample_chunks(vertices, faces, n, seed))
    return np.concatenate(chunks) if chunks else np.zeros((0, 3))


def _voxel_keys(points: np.ndarray, origin: np.ndarray, voxel_m: float) -> np.ndarray:
    q = np.floor((points - origin) / voxel_m).astype(np.int64)
    if q.size and (q.min() < 0 or q.max() >= 1 << 21):
        raise DataError(f"voxel_down_sample: the points span more than {(1 << 21) * voxel_m:.0f} m")
    return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]


def voxel_down_sample(points, voxel_m: float, origin=None) -> np.ndarray:
    """open3d's ``PointCloud.voxel_down_sample(voxel_m)``: the mean of the points in each voxel of a grid
    anchored at the points' minimum bound minus half a voxel.

    points: [N,3], or an iterable of [n,3] pieces (then `origin`, the grid anchor, must be given).
    Returns [M,3] float64, one point per occupied voxel (ordered by voxel, not as open3d's hash map)."""
    if isinstance(points, np.ndarray) or origin is None:
        pieces = [as_points(points, "points")]
        if origin is None:
            if len(pieces[0]) == 0:
                return np.zeros((0, 3))
            origin = pieces[0].min(axis=0) - 0.5 * voxel_m
    else:
        pieces = points
    origin = np.asarray(origin, dtype=np.float64)
    keys, sums, counts = [], [], []
    for p in pieces:
        if len(p) == 0:
            continue
        uk, inv = np.unique(_voxel_keys(p, origin, voxel_m), return_inverse=True)
        inv = inv.reshape(-1)
        keys.append(uk)
        sums.append(np.stack([np.bincount(inv, weights=p[:, c], minlength=len(uk)) for c in range(3)], 1))
        counts.append(np.bincount(inv, minlength=len(uk)).astype(np.float64))
    if not keys:
        return np.zeros((0, 3))
    if len(keys) == 1:
        return sums[0] / counts[0][:, None]
    uk, inv = np.unique(np.concatenate(keys), return_inverse=True)
    inv = inv.reshape(-1)
    s = np.concatenate(sums)
    tot = np.stack([np.bincount(inv, weights=s[:, c], minlength=len(uk)) for c in range(3)], 1)
    return tot / np.bincount(inv, weights=np.concatenate(counts), minlength=len(uk))[:, None]


def protocol_metrics(pred_ds, gt_ds, threshold_m: float = 0.1, acc_truncation_m: float = ACC_TRUNCATION_M,
                     comp_truncation_m: float = COMP_TRUNCATION_M) -> dict:
    """Step 4 of the protocol on the down-sampled point sets: pred_ds [P,3], gt_ds [G,3] -> the dict of
    METRIC_KEYS plus n_pred_far (predicted points dropped as >= acc_truncation_m from GT) and, beside the
    protocol (which cannot see what it drops: floaters, ghost surfaces), pred_far_share = the dropped
    points' share of pred_ds (%), precision_all = % of ALL of pred_ds closer than threshold_m to the GT
    (far points count as misses) and f_score_all = 2 P_all R / (P_all + R). Without far points
    precision_all == precision and f_score_all == f_score.

    n_pred counts the predicted points that entered Accuracy / Precision, n_gt the GT points. No
    predicted point (or none within acc_truncation_m) gives an infinite accuracy and zero precision."""
    if not threshold_m > 0:
        raise DataError(f"threshold_m must be positive, got {threshold_m}")
    pred = as_points(pred_ds, "pred_points")
    gt = as_points(gt_ds, "gt_points")
    d_p = _nn_dist(gt, pred)                  # pred -> nearest GT (accuracy, precision)
    near = d_p < acc_truncation_m
    n_hit_all = int(np.sum(d_p < threshold_m))  # every predicted point, no drop (precision_all)
    d_p = d_p[near]
    d_r = np.minimum(_nn_dist(pred, gt), comp_truncation_m)  # GT -> nearest pred (completion, recall)
    acc = float(d_p.mean()) * 100.0 if len(d_p) else math.inf
    comp = float(d_r.mean()) * 100.0 if len(d_r) else math.inf
    precision = float(np.mean(d_p < threshold_m)) * 100.0 if len(d_p) else 0.0
    recall = float(np.mean(d_r < threshold_m)) * 100.0 if len(d_r) else 0.0
    f = 2.0 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    # beside the protocol: the far points it drops (floaters, ghost surfaces) counted as misses
    n_far = int(len(near) - near.sum())
    far_share = 100.0 * n_far / len(pred) if len(pred) else 0.0
    precision_all = 100.0 * n_hit_all / len(pred) if len(pred) else 0.0
    f_all = 2.0 * precision_all * recall / (precision_all + recall) if precision_all + recall > 0 else 0.0
    if len(pred) == 0:
        log.warning("no predicted point inside the GT bounding box; accuracy is infinite")
    return {
        "accuracy_cm": round(acc, 4),
        "completion_cm": round(comp, 4),
        "chamfer_l1_cm": round(0.5 * (acc + comp), 4),
        "completion_ratio": round(recall, 3),
        "precision": round(precision, 3),
        "f_score": round(f, 3),
        "threshold_m": float(threshold_m),
        "n_pred": int(near.sum()),
        "n_gt": int(len(gt)),
        "protocol": PROTOCOL,
        "n_pred_far": n_far,
        "pred_far_share": round(far_share, 3),
        "precision_all": round(precision_all, 3),
        "f_score_all": round(f_all, 3),
    }


def evaluate(pred_points, gt_points, *, threshold_m: float = 0.1, observed_points=None,
             cull_distance_m: float = 0.3, sensor_positions=None, eval_radius_m: float = -1.0,
             down_sample_m: float = DOWN_SAMPLE_M, acc_truncation_m: float = ACC_TRUNCATION_M,
             comp_truncation_m: float = COMP_TRUNCATION_M) -> dict:
    """The protocol on a predicted point set (e.g. samples of a mesh): cull the GT, crop the prediction
    points to the GT box (z grown by down_sample_m), voxel-down-sample both, then :func:`protocol_metrics`.

    Args:
      pred_points: [P,3] points on the predicted surface (world frame, metres).
      gt_points: [G,3] GT surface points (world frame).
      threshold_m: distance threshold of precision / completion ratio / F-score.
      observed_points: [O,3] scan points in the world frame, or None for no culling.
      cull_distance_m: GT points farther than this from every observed point are dropped.
      sensor_positions: [S,3] sensor positions in the world frame (needed when eval_radius_m > 0).
      eval_radius_m: > 0 keeps only GT within this distance of some sensor position.
      down_sample_m: voxel of the down-sampling (0: none).

    Returns: dict with the keys of METRIC_KEYS (+ n_pred_far); see :func:`protocol_metrics`.
    """
    pred = as_points(pred_points, "pred_points")
    gt, _ = culled_or_fail(gt_points, cull_distance_m, eval_radius_m, observed_points=observed_points,
                            sensor_positions=sensor_positions)
    lo, hi = crop_box(gt, down_sample_m)
    pred = pred[np.all((pred >= lo) & (pred <= hi), axis=1)]
    if down_sample_m > 0:
        pred, gt = voxel_down_sample(pred, down_sample_m), voxel_down_sample(gt, down_sample_m)
    return protocol_metrics(pred, gt, threshold_m, acc_truncation_m, comp_truncation_m)


def load_mesh(mesh, where: str = "mesh"):
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
    """Sample n points uniformly (area-weighted, independent draws) on a triangle mesh.

    Args:
      mesh: trimesh.Trimesh or a path to a mesh file.
      n: number of points.
      seed: the same seed and mesh give the same points.

    Returns: [n,3] float64 points in the mesh's frame.
    """
    m = load_mesh(mesh)
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


def signed_error_by_class(pred_points, gt_points, gt_normals, gt_classes, class_names,
                          max_dist_m: float = SIGNED_MAX_M) -> dict:
    """Mean signed surface error per GT class: {class name: {"mean_cm", "median_cm", "n"}}.

    For each predicted point p (after crop and down-sampling) whose nearest GT point g is closer than
    max_dist_m, the signed distance is dot(p - g, n_g) with n_g the GT normal (pointing out of solids /
    up from the ground: positive = the predicted surface lies outside / above the true one); the values
    are grouped by g's class. Classes that no predicted point reaches are left out."""
    pred = as_points(pred_points, "pred_points")
    gt = as_points(gt_points, "gt_points")
    nrm = np.asarray(gt_normals, dtype=np.float64)
    cls = np.asarray(gt_classes).astype(np.int64)
    if nrm.shape != gt.shape or cls.shape != (len(gt),):
        raise DataError(f"signed error: GT normals {nrm.shape} / classes {cls.shape} do not match GT {gt.shape}")
    d, i = _nn(gt, pred, upper=max_dist_m)
    ok = d < max_dist_m
    i = i[ok]
    s = np.einsum("ij,ij->i", pred[ok] - gt[i], nrm[i])
    c = cls[i]
    out = {}
    for k, name in enumerate(class_names):
        sk = s[c == k]
        if len(sk):
            out[str(name)] = {"mean_cm": round(float(sk.mean()) * 100, 3),
                              "median_cm": round(float(np.median(sk)) * 100, 3), "n": int(len(sk))}
    return out


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    m = load_mesh(mesh)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64).reshape(-1, 3)


def evaluate_culled(vertices, faces, gt, *, threshold_m, n_samples, seed, down_sample_m, acc_truncation_m,
                     comp_truncation_m):
    """Steps 2-4 on an already culled GT [G,3]: (metrics, predicted points after crop and down-sampling)."""
    lo, hi = crop_box(gt, down_sample_m)
    v, f = crop_mesh(vertices, faces, lo, hi)
    if len(f) == 0:
        pred = np.zeros((0, 3))
    else:
        pieces = _uniform_sample_chunks(v, f, int(n_samples), seed)
        if down_sample_m > 0:
            pred = voxel_down_sample(pieces, down_sample_m, origin=v.min(axis=0) - 0.5 * down_sample_m)
        else:
            pred = np.concatenate(list(pieces))
    gt_ds = voxel_down_sample(gt, down_sample_m) if down_sample_m > 0 else gt
    m = protocol_metrics(pred, gt_ds, threshold_m, acc_truncation_m, comp_truncation_m)
    m["n_pred_samples"] = int(n_samples) if len(f) else 0
    return m, pred


def evaluate_mesh(mesh, gt_points, *, n_samples: int = N_SAMPLES, seed: int = 0, threshold_m: float = 0.1,
                  observed_points=None, cull_distance_m: float = 0.3, sensor_positions=None,
                  eval_radius_m: float = -1.0, down_sample_m: float = DOWN_SAMPLE_M,
                  acc_truncation_m: float = ACC_TRUNCATION_M, comp_truncation_m: float = COMP_TRUNCATION_M,
                  protocol: str = PROTOCOL) -> dict:
    """The protocol on a predicted mesh (trimesh.Trimesh or a path): cull the GT, crop the mesh to the GT
    box, sample n_samples points, down-sample, compare (see the module docstring and :func:`evaluate`).

    An empty mesh (no faces, or none inside the box) gives the metrics of an empty prediction. With
    protocol="surface" the result also has completion_surface_cm (kept GT points -> the cropped mesh,
    exact, clamped at comp_truncation_m; needs open3d). Nothing is measured against the GT mesh."""
    if protocol not in PROTOCOLS:
        raise DataError(f"unknown protocol {protocol!r}; choose from {', '.join(PROTOCOLS)}")
    v, f = mesh_arrays(mesh)
    gt, _ = culled_or_fail(gt_points, cull_distance_m, eval_radius_m, observed_points=observed_points,
                            sensor_positions=sensor_positions)
    m, _ = evaluate_culled(v, f, gt, threshold_m=threshold_m, n_samples=n_samples, seed=seed,
                            down_sample_m=down_sample_m, acc_truncation_m=acc_truncation_m,
                            comp_truncation_m=comp_truncation_m)
    if protocol == "surface":
        m.update(surface_fields(v, f, gt, comp_truncation_m, down_sample_m))
    return m


def surface_fields(v, f, gt, comp_truncation_m, down_sample_m) -> dict:
    import trimesh

    vc, fc = crop_mesh(v, f, *crop_box(gt, down_sample_m))
    if len(fc) == 0:
        return {"completion_surface_cm": round(comp_truncation_m * 100, 4)}
    d = mesh_distance(trimesh.Trimesh(vc, fc, process=False), gt)
    if d is None:
        log.warning("open3d is not installed: no completion_surface_cm")
        return {}
    return {"completion_surface_cm": round(float(np.minimum(d, comp_truncation_m).mean()) * 100, 4)}


def subdivide_mesh(vertices, faces, max_edge_m: float = FLOOR_MAX_EDGE_M) -> tuple[np.ndarray, np.ndarray]:
    """The same surface with every edge at most max_edge_m long (trimesh's subdivide_to_size)."""
    import trimesh

    v, f = trimesh.remesh.subdivide_to_size(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                                            max_edge=max_edge_m, max_iter=64)
    return np.asarray(v, np.float64), np.asarray(f, np.int64)


def protocol_floor(gt_mesh, gt_points, max_edge_m: float = FLOOR_MAX_EDGE_M, **kw) -> dict:
    """The protocol floor: :func:`evaluate_mesh` with the GT mesh itself as the prediction (same culling,
    cropping, sampling and down-sampling; keyword arguments as evaluate_mesh). The GT mesh is first
    subdivided to edges <= max_edge_m, so that the crop (which keeps whole triangles) does not drop a
    20 m facade triangle that crosses the box; the surface is unchanged (only a strip narrower than
    max_edge_m along the box's sides is lost, as for any mesh)."""
    v, f = mesh_arrays(gt_mesh)
    import trimesh

    return evaluate_mesh(trimesh.Trimesh(*subdivide_mesh(v, f, max_edge_m), process=False), gt_points, **kw)


def format_metrics(m: dict, name: str = "mesh") -> str:
    """A small table of a metrics dict of :func:`evaluate_mesh_file`: the floor row first (when
    present), then the mesh (the protocol's figures, then pred_far_share, precision_all and f_score_all),
    the ghost area per kind (when the sequence has moving objects), the run's SA / DA of the points it
    trained on ("dynamic_points", `jaxmap.metrics.dynamic`, when present), then the signed error per class (cm,
    mean / median / points). Older dicts without the extra keys print nan there."""
    head = f"{'':<8}{'Acc cm':>8}{'Comp cm':>8}{'C-L1 cm':>8}{'CR %':>8}{'F %':>8}" \
           f"{'far %':>8}{'P all %':>9}{'F all %':>9}   (protocol {m.get('protocol')}, " \
           f"threshold {m.get('threshold_m')} m; far / all: beside the protocol, far points not dropped)"
    rows = [head]
    na = float("nan")
    for label, r in (("floor", m.get("floor")), (name, m)):
        if r:
            rows.append(f"{label:<8}{r['accuracy_cm']:>8.2f}{r['completion_cm']:>8.2f}{r['chamfer_l1_cm']:>8.2f}"
                        f"{r['completion_ratio']:>8.2f}{r['f_score']:>8.2f}{r.get('pred_far_share', na):>8.2f}"
                        f"{r.get('precision_all', na):>9.2f}{r.get('f_score_all', na):>9.2f}")
    for label, r in ((name, m), ("floor", m.get("floor"))):
        g = (r or {}).get("ghost_area_m2")
        if g:
            parts = ", ".join(f"{k} {v:.2f}" for k, v in g.items())
            rows.append(f"ghost surface (m^2){'' if label == name else ', floor'}: {parts} (predicted surface "
                        "inside space only moving objects occupied, > 0.15 m from the static GT)")
    if m.get("dynamic_points"):
        from jaxmap.metrics.dynamic import format_scores

        rows.append(format_scores(m["dynamic_points"]))
    se = m.get("signed_error_cm")
    if se:
        rows.append("signed error per class (cm, + = outside / above the GT surface): " + ", ".join(
            f"{k} {v['mean_cm']:+.2f} (median {v['median_cm']:+.2f}, n {v['n']})" for k, v in se.items()))
    return "\n".join(rows)
