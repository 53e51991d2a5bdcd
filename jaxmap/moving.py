"""Moving objects of a sequence: cars, pedestrians, ... that are in the scans but never in the ground truth.

A sequence directory may describe them in ``moving_objects.json`` (beside poses.txt)::

    {"format": "jaxmap moving objects v1", "frames": F,
     "objects": [{"id": 0, "kind": "car", "size_xyz_m": [l, w, h],
                  "poses": [[x, y, z_base, yaw], ... one per frame, or null when absent that frame]}, ...]}

or, in older synthetic cities (``jaxmap synth city --pedestrians``), in ``pedestrians.json``::

    {"size_xyz_m": [l, w, h], "base_z_m": z, "frames": [[{"xy": [x, y], "yaw": a}, ...], ...]}

(one list of boxes per frame, kind "pedestrian"). When both files exist only moving_objects.json is read.

The box of an object at a frame, in the world frame (the frame of gt_points.ply and of the poses'
translations, metres): footprint centre (x, y), bottom z_base, top z_base + h, length l along the heading
yaw (radians about +z, from +x towards +y), width w across it. Both formats are read into one
:class:`MovingObjects`: a flat table of boxes [B] with their frame, object and kind.

This module imports numpy only (scipy lazily).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass

import numpy as np

from jaxmap.errors import DataError

FORMAT = "jaxmap moving objects v1"
FILE = "moving_objects.json"
PEDESTRIANS_FILE = "pedestrians.json"
_MAX_CANDIDATES = 4_000_000  # (point, box) pairs tested per piece in inside_boxes (bounded memory)


@dataclass(frozen=True)
class Boxes:
    """B oriented boxes (world frame, metres).

    params: [B,7] float64 (x, y, z_base, yaw, length, width, height): footprint centre, bottom, heading
            (radians about +z), extent along / across the heading, height.
    kind:   [B] int64, index into `kinds`.
    frame:  [B] int64, the frame number (position among all frames of the sequence) of each box.
    obj:    [B] int64, the object each box belongs to (moving_objects.json's id; pedestrians.json: the
            position in the frame's list).
    kinds:  the kind names.
    """
    params: np.ndarray
    kind: np.ndarray
    frame: np.ndarray
    obj: np.ndarray
    kinds: tuple

    def __len__(self) -> int:
        return len(self.params)

    def subset(self, mask) -> "Boxes":
        """The boxes selected by a [B] bool mask or an index array."""
        return Boxes(self.params[mask], self.kind[mask], self.frame[mask], self.obj[mask], self.kinds)

    def centres(self) -> np.ndarray:
        """[B,3] the boxes' centres (half height)."""
        p = self.params
        return np.stack([p[:, 0], p[:, 1], p[:, 2] + 0.5 * p[:, 6]], 1)


@dataclass(frozen=True)
class MovingObjects:
    """The moving objects of a sequence: path (the file read), n_frames (frames the file describes) and
    boxes (every object's box at every frame where it is present; sorted by frame)."""
    path: str
    n_frames: int
    boxes: Boxes

    @property
    def kinds(self) -> tuple:
        return self.boxes.kinds

    def boxes_at(self, frame: int) -> Boxes:
        """The boxes of frame number `frame` (position among all frames of the sequence, before any
        begin/end/every selection). A frame beyond the file's frames is a DataError."""
        frame = int(frame)
        if not 0 <= frame < self.n_frames:
            raise DataError(f"{self.path}: describes {self.n_frames} frames, but frame {frame} was asked for; "
                            "does the file belong to this sequence?")
        lo, hi = np.searchsorted(self.boxes.frame, [frame, frame + 1])
        return self.boxes.subset(slice(lo, hi))

    def boxes_of_frames(self, frames) -> Boxes:
        """The boxes of the given frame numbers (an iterable of ints), e.g. the frames a run mapped."""
        fr = np.asarray(list(frames), dtype=np.int64)
        if len(fr) and (fr.min() < 0 or fr.max() >= self.n_frames):
            raise DataError(f"{self.path}: describes {self.n_frames} frames, but frames up to {fr.max()} "
                            "were asked for; does the file belong to this sequence?")
        return self.boxes.subset(np.isin(self.boxes.frame, fr))


def _fail(path, what):
    raise DataError(f"{path}: malformed moving-objects file: {what}")


def _finite(x, n, path, where):
    if not isinstance(x, (list, tuple)) or len(x) != n:
        _fail(path, f"{where}: expected a list of {n} numbers, got {x!r:.80}")
    try:
        a = [float(v) for v in x]
    except (TypeError, ValueError):
        _fail(path, f"{where}: expected numbers, got {x!r:.80}")
    if not all(math.isfinite(v) for v in a):
        _fail(path, f"{where}: not finite: {x!r:.80}")
    return a


def _size(x, path, where):
    s = _finite(x, 3, path, where)
    if min(s) <= 0:
        _fail(path, f"{where}: sizes must be positive, got {x!r}")
    return s


def _read_v1(path, doc) -> MovingObjects:
    if doc.get("format") != FORMAT:
        _fail(path, f"'format' must be {FORMAT!r}, got {doc.get('format')!r}")
    n = doc.get("frames")
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        _fail(path, f"'frames' must be a non-negative integer, got {n!r}")
    objs = doc.get("objects")
    if not isinstance(objs, list):
        _fail(path, "'objects' must be a list")
    kinds: list[str] = []
    rows, kind, frame, obj = [], [], [], []
    for k, o in enumerate(objs):
        where = f"objects[{k}]"
        if not isinstance(o, dict):
            _fail(path, f"{where}: expected an object")
        oid = o.get("id", k)
        if not isinstance(oid, int) or isinstance(oid, bool):
            _fail(path, f"{where}: 'id' must be an integer, got {oid!r}")
        name = o.get("kind")
        if not isinstance(name, str) or not name:
            _fail(path, f"{where}: 'kind' must be a non-empty string, got {name!r}")
        size = _size(o.get("size_xyz_m"), path, f"{where}.size_xyz_m")
        poses = o.get("poses")
        if not isinstance(poses, list) or len(poses) != n:
            _fail(path, f"{where}.poses: expected a list of {n} entries (one per frame, null when absent), got "
                        f"{len(poses) if isinstance(poses, list) else type(poses).__name__}")
        if name not in kinds:
            kinds.append(name)
        ki = kinds.index(name)
        for i, p in enumerate(poses):
            if p is None:
                continue
            x, y, z, yaw = _finite(p, 4, path, f"{where}.poses[{i}]")
            rows.append([x, y, z, yaw, *size])
            kind.append(ki)
            frame.append(i)
            obj.append(oid)
    return _objects(path, n, rows, kind, frame, obj, kinds)


def _read_pedestrians(path, doc) -> MovingObjects:
    size = _size(doc.get("size_xyz_m"), path, "size_xyz_m")
    (z,) = _finite([doc.get("base_z_m")], 1, path, "base_z_m")
    frames = doc.get("frames")
    if not isinstance(frames, list):
        _fail(path, "'frames' must be a list (one list of boxes per frame)")
    rows, frame, obj = [], [], []
    for i, fr in enumerate(frames):
        if not isinstance(fr, list):
            _fail(path, f"frames[{i}]: expected a list of boxes")
        for j, b in enumerate(fr):
            if not isinstance(b, dict):
                _fail(path, f"frames[{i}][{j}]: expected {{'xy': [x, y], 'yaw': a}}")
            x, y = _finite(b.get("xy"), 2, path, f"frames[{i}][{j}].xy")
            (yaw,) = _finite([b.get("yaw")], 1, path, f"frames[{i}][{j}].yaw")
            rows.append([x, y, z, yaw, *size])
            frame.append(i)
            obj.append(j)
    return _objects(path, len(frames), rows, [0] * len(rows), frame, obj, ["pedestrian"])


def _objects(path, n, rows, kind, frame, obj, kinds) -> MovingObjects:
    params = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
    frame = np.asarray(frame, dtype=np.int64)
    order = np.argsort(frame, kind="stable")
    boxes = Boxes(params[order], np.asarray(kind, np.int64)[order], frame[order],
                  np.asarray(obj, np.int64)[order], tuple(kinds))
    return MovingObjects(path=path, n_frames=int(n), boxes=boxes)


def moving_objects_path(data_dir) -> str | None:
    """The file that describes a sequence's moving objects (moving_objects.json, else pedestrians.json),
    or None."""
    for name in (FILE, PEDESTRIANS_FILE):
        p = os.path.join(os.fspath(data_dir), name)
        if os.path.isfile(p):
            return p
    return None


def load_moving_objects(data_dir) -> MovingObjects | None:
    """The moving objects of a sequence directory (module docstring), or None when it has neither
    moving_objects.json nor pedestrians.json. A malformed file is a DataError naming it."""
    path = moving_objects_path(data_dir)
    if path is None:
        return None
    try:
        with open(path) as f:
            doc = json.load(f)
    except (OSError, ValueError) as e:
        raise DataError(f"{path}: could not read the moving-objects JSON ({type(e).__name__}: {e})") from None
    if not isinstance(doc, dict):
        _fail(path, "expected a JSON object at the top")
    return _read_v1(path, doc) if os.path.basename(path) == FILE else _read_pedestrians(path, doc)


def _footprint_half_extents(params: np.ndarray, inflate_m: float) -> np.ndarray:
    """[B,2] half extents in x and y of the axis-aligned bounding box of each (inflated) box."""
    c, s = np.abs(np.cos(params[:, 3])), np.abs(np.sin(params[:, 3]))
    hl, hw = 0.5 * params[:, 4] + inflate_m, 0.5 * params[:, 5] + inflate_m
    return np.stack([c * hl + s * hw, s * hl + c * hw], 1)


def inside_boxes(points, boxes: Boxes, inflate_m: float = 0.0, return_box: bool = False):
    """Which points lie inside at least one of the boxes, each grown by inflate_m on every side.

    points: [N,3] (world frame, metres); boxes: :class:`Boxes` [B]. Returns inside [N] bool, and with
    return_box=True also box [N] int64: for each inside point the box whose centre (half height) is the
    nearest among the boxes that contain it (-1 outside), to attribute a point to one object's kind.

    Vectorised: the points are bucketed on a 2-D grid (cells about the boxes' half width); every box
    gathers the points of the grid cells under its axis-aligned footprint (one searchsorted for all
    boxes), and all (point, box) candidate pairs are tested at once in the box's frame, in pieces of a
    few million pairs. No Python loop over points or boxes; the cost grows with the number of (point, box)
    pairs, i.e. with how much the boxes overlap (consecutive frames of one object do).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    inside = np.zeros(n, bool)
    best_box = np.full(n, -1, np.int64)
    if n == 0 or len(boxes) == 0:
        return (inside, best_box) if return_box else inside
    p = boxes.params
    half = _footprint_half_extents(p, inflate_m)
    z_lo, z_hi = p[:, 2] - inflate_m, p[:, 2] + p[:, 6] + inflate_m
    # prefilter: the points inside the bounding box of all boxes
    lo = np.array([(p[:, 0] - half[:, 0]).min(), (p[:, 1] - half[:, 1]).min(), z_lo.min()])
    hi = np.array([(p[:, 0] + half[:, 0]).max(), (p[:, 1] + half[:, 1]).max(), z_hi.max()])
    sel = np.flatnonzero(np.all((pts >= lo) & (pts <= hi), axis=1))
    if len(sel) == 0:
        return (inside, best_box) if return_box else inside
    q = pts[sel]
    order, rbox, start, length = _candidate_runs(q, p, half, lo[:2], inflate_m)
    if len(rbox) == 0:
        return (inside, best_box) if return_box else inside
    centre = boxes.centres()
    best_d = np.full(len(sel), np.inf)
    for j, b in _pairs_inside(q, p, inflate_m, z_lo, z_hi, order, rbox, start, length):
        if not return_box:
            inside[sel[j]] = True
            continue
        # the nearest centre per point without a sort: the running minimum, then the pairs that attain it
        # (a later piece that finds a nearer box overwrites; ties keep one of the tied boxes)
        dist = np.linalg.norm(q[j] - centre[b], axis=1)
        np.minimum.at(best_d, j, dist)
        hit = dist <= best_d[j]
        best_box[sel[j[hit]]] = b[hit]
    if not return_box:
        return inside
    inside = best_box >= 0
    return (inside, best_box) if return_box else inside


def _candidate_runs(q: np.ndarray, p: np.ndarray, half: np.ndarray, lo: np.ndarray, inflate_m: float):
    """The (point, box) candidate pairs of inside_boxes as runs of grid-sorted points.

    q: [M,3] points (world frame) inside the boxes' joint bounding box, whose x, y minimum is lo [2];
    p: [B,7] box params; half: [B,2] their footprints' half extents. Returns (order [M]: q's indices
    sorted by grid cell, rbox [R]: the box of each run, start [R] and length [R] > 0: each run's slice of
    `order`), one run per grid row under a box's footprint that holds points.
    """
    cell = float(np.clip(0.5 * np.median(np.minimum(p[:, 4], p[:, 5])) + inflate_m, 0.1, 2.0))
    ix = np.floor((q[:, 0] - lo[0]) / cell).astype(np.int64)
    iy = np.floor((q[:, 1] - lo[1]) / cell).astype(np.int64)
    ny = int(iy.max()) + 1
    key = ix * ny + iy
    order = np.argsort(key, kind="stable")
    skey = key[order]
    # each box: the grid rows ix0..ix1 of its footprint, each row a contiguous run of keys iy0..iy1
    bx0 = np.floor((p[:, 0] - half[:, 0] - lo[0]) / cell).astype(np.int64)
    bx1 = np.floor((p[:, 0] + half[:, 0] - lo[0]) / cell).astype(np.int64)
    by0 = np.clip(np.floor((p[:, 1] - half[:, 1] - lo[1]) / cell).astype(np.int64), 0, ny - 1)
    by1 = np.clip(np.floor((p[:, 1] + half[:, 1] - lo[1]) / cell).astype(np.int64), 0, ny - 1)
    nrow = bx1 - bx0 + 1
    rbox = np.repeat(np.arange(len(p)), nrow)
    rx = bx0[rbox] + (np.arange(len(rbox)) - np.repeat(np.cumsum(nrow) - nrow, nrow))
    start = np.searchsorted(skey, rx * ny + by0[rbox], side="left")
    end = np.searchsorted(skey, rx * ny + by1[rbox], side="right")
    length = end - start
    keep = length > 0
    return order, rbox[keep], start[keep], length[keep]


def _pairs_inside(q, p, inflate_m, z_lo, z_hi, order, rbox, start, length):
    """Test the candidate pairs of `_candidate_runs` in the boxes' frames, in pieces of at most
    _MAX_CANDIDATES pairs (a single run may exceed it); yields per piece (j, b), the pairs where point
    q[j] lies inside box b grown by inflate_m (z_lo, z_hi [B]: the grown boxes' bottom and top)."""
    cos, sin = np.cos(p[:, 3]), np.sin(p[:, 3])
    hl, hw = 0.5 * p[:, 4] + inflate_m, 0.5 * p[:, 5] + inflate_m
    cum = np.cumsum(length)
    cuts = np.searchsorted(cum, np.arange(_MAX_CANDIDATES, cum[-1], _MAX_CANDIDATES), side="left") + 1
    bounds = np.unique(np.r_[0, np.minimum(cuts, len(rbox)), len(rbox)])
    for r0, r1 in zip(bounds[:-1], bounds[1:]):
        ln = length[r0:r1]
        tot = int(ln.sum())
        b = np.repeat(rbox[r0:r1], ln)
        k = np.repeat(start[r0:r1] - (np.cumsum(ln) - ln), ln) + np.arange(tot)
        j = order[k]  # index into q
        d = q[j, :2] - p[b, :2]
        along = d[:, 0] * cos[b] + d[:, 1] * sin[b]
        across = -d[:, 0] * sin[b] + d[:, 1] * cos[b]
        z = q[j, 2]
        ok = (np.abs(along) <= hl[b]) & (np.abs(across) <= hw[b]) & (z >= z_lo[b]) & (z <= z_hi[b])
        j, b = j[ok], b[ok]
        if len(j):
            yield j, b


GHOST_INFLATE_M = 0.1   # the moving objects' boxes are grown by this for the ghost area and static observations
GHOST_STATIC_M = 0.15   # predicted surface closer than this to a GT point is static surface, not ghost
GHOST_MAX_EDGE_M = 0.05  # faces near the boxes are cut to edges <= this before their centroids are tested


def _split(tri: np.ndarray, max_edge_m: float, max_k: int = 3) -> np.ndarray:
    """Triangles [T,3,3] -> the same surface as congruent triangles [T',3,3]: each cut into k^2,
    k = min(max_k, ceil(longest edge / max_edge_m))."""
    e = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    k = np.clip(np.ceil(e / max_edge_m - 1e-9), 1, max_k).astype(np.int64)
    out = [tri[k == 1]]
    for kk in np.unique(k[k > 1]):
        t = tri[k == kk]
        i, j = np.meshgrid(np.arange(kk), np.arange(kk), indexing="ij")
        i, j = i.ravel(), j.ravel()
        up, dn = i + j <= kk - 1, i + j <= kk - 2
        uv = np.concatenate([np.stack([np.stack([i[up], j[up]], 1), np.stack([i[up] + 1, j[up]], 1),
                                       np.stack([i[up], j[up] + 1], 1)], 1),
                             np.stack([np.stack([i[dn] + 1, j[dn]], 1), np.stack([i[dn], j[dn] + 1], 1),
                                       np.stack([i[dn] + 1, j[dn] + 1], 1)], 1)]) / kk  # [kk^2, 3, 2]
        a, e1, e2 = t[:, None, None, 0], (t[:, 1] - t[:, 0])[:, None, None], (t[:, 2] - t[:, 0])[:, None, None]
        out.append((a + uv[None, ..., :1] * e1 + uv[None, ..., 1:] * e2).reshape(-1, 3, 3))
    return np.concatenate(out)


def ghost_area(vertices, faces, gt_points, boxes: Boxes, inflate_m: float = GHOST_INFLATE_M,
               static_m: float = GHOST_STATIC_M, max_edge_m: float = GHOST_MAX_EDGE_M) -> dict:
    """Area (m^2) of predicted surface in space that only moving objects occupied, per kind.

    vertices [V,3], faces [F,3]: the predicted mesh (world frame, whole, not cropped). gt_points [G,3]:
    all static GT points (world frame). boxes: the moving objects' boxes over the frames that count (their
    union is the space they occupied).

    A piece of surface counts when it is inside some box grown by inflate_m and farther than static_m from
    every GT point. Computed deterministically, coarse to fine: a triangle with bounding sphere (centre c,
    radius r) is dropped when c is outside every box grown by inflate_m + r or closer than static_m - r to
    the GT, taken whole when c is inside a box grown by inflate_m - r and farther than static_m + r from the
    GT, and otherwise cut into congruent triangles with edges a third as long, down to max_edge_m, where
    each small triangle counts with its whole area when its centroid passes both tests (the error is
    confined to a max_edge_m strip along the region's border). Each counted piece goes to the kind of the
    box (among those containing its centre) whose centre is nearest.

    Returns {kind: area for every kind of boxes.kinds, "total": sum}, rounded to 1e-4 m^2.
    """
    from scipy.spatial import cKDTree

    kinds = [str(k) for k in boxes.kinds]
    per = np.zeros(len(kinds))
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)

    def result():
        out = {k: round(float(a), 4) for k, a in zip(kinds, per)}
        out["total"] = round(float(per.sum()), 4)
        return out

    if len(boxes) == 0 or len(f) == 0:
        return result()
    gt = np.asarray(gt_points, dtype=np.float64).reshape(-1, 3)
    # only GT points near the grown boxes can be within static_m of a point inside them
    gt = gt[inside_boxes(gt, boxes, inflate_m + static_m)]
    tree = cKDTree(gt) if len(gt) else None
    tri = v[f]
    while True:
        box, area, todo = _ghost_step(tri, boxes, tree, inflate_m, static_m, max_edge_m)
        np.add.at(per, boxes.kind[box], area)
        if not len(todo):
            break
        tri = _split(todo, max_edge_m)
    return result()


def _ghost_step(tri: np.ndarray, boxes: Boxes, tree, inflate_m: float, static_m: float, max_edge_m: float):
    """One coarse-to-fine pass of ghost_area over triangles [T,3,3] (world frame; tree: the cKDTree of the
    GT points near the boxes, or None). Returns (box [S]: the box each surely counted triangle goes to,
    area [S]: its area, todo [T',3,3]: the undecided triangles that can still be cut)."""
    cen = tri.mean(axis=1)
    rad = np.linalg.norm(tri - cen[:, None, :], axis=2).max(axis=1)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    final = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1) <= max_edge_m * (1 + 1e-9)
    slack = np.where(final, 0.0, rad)  # final triangles: decided by their centroid alone
    # outside every grown box (radii bucketed geometrically: inside_boxes takes one inflation)
    maybe = np.zeros(len(tri), bool)
    rest = np.ones(len(tri), bool)
    bound = 0.05
    while rest.any():
        sel = rest & ((slack <= bound) | (bound > 50.0))
        if sel.any():
            maybe[sel] = inside_boxes(cen[sel], boxes, inflate_m + bound)
        rest &= ~sel
        bound *= 3.0
    tri, cen, slack, area, final = tri[maybe], cen[maybe], slack[maybe], area[maybe], final[maybe]
    if tree is not None and len(tri):
        d, _ = tree.query(cen, k=1, distance_upper_bound=static_m + slack.max() + 1e-9, workers=-1)
    else:
        d = np.full(len(tri), np.inf)
    keep = ~(d <= static_m - slack) if len(tri) else np.zeros(0, bool)  # not surely near the GT
    far = d > static_m + slack                                            # surely far from it
    tri, cen, slack, area, final, far = tri[keep], cen[keep], slack[keep], area[keep], final[keep], far[keep]
    # surely inside a box: inside one shrunk by the radius (final ones: the centroid inside one grown box)
    ins, box = inside_boxes(cen, boxes, inflate_m, return_box=True)
    sure = ins & far & (final | (slack <= 0))
    if (~final).any():
        cand = np.flatnonzero(~final & far & ins)
        for r in np.unique(np.ceil(slack[cand] / 0.02) * 0.02):  # shrink in 2 cm buckets (conservative)
            c = cand[np.ceil(slack[cand] / 0.02) * 0.02 == r]
            if r < inflate_m + 0.5 * boxes.params[:, 4:7].min():  # (else no box is left)
                sure[c] = inside_boxes(cen[c], boxes, inflate_m - r)
    todo = ~sure & ~final
    return box[sure], area[sure], tri[todo]
