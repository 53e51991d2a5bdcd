"""Shared helpers of the synthetic scenes: triangle-mesh primitives, a deterministic surface sampler,
a ray-casting wrapper (open3d, imported lazily) and small file utilities.

Meshes are plain numpy pairs (vertices [V,3] float64, faces [F,3] int64) with counter-clockwise winding
seen from outside, so face normals point out of solids (or into a room built with `flip`).
"""
from __future__ import annotations

import hashlib
import json
import os

import numpy as np

from jaxmap.errors import DataError

# ------------------------------------------------------------------------------------------------
# mesh assembly
# ------------------------------------------------------------------------------------------------


class MeshBuilder:
    """Accumulates triangle meshes; `build()` -> (vertices [V,3] float64, faces [F,3] int64)."""

    def __init__(self):
        self._v: list[np.ndarray] = []
        self._f: list[np.ndarray] = []
        self._n = 0

    def add(self, mesh) -> None:
        v, f = mesh
        v = np.asarray(v, dtype=np.float64)
        f = np.asarray(f, dtype=np.int64)
        self._v.append(v)
        self._f.append(f + self._n)
        self._n += len(v)

    def build(self):
        if not self._v:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        return np.concatenate(self._v), np.concatenate(self._f)

    def __len__(self):
        return sum(len(f) for f in self._f)


def transform_mesh(mesh, R=None, t=None):
    """Apply x -> R x + t to a mesh (R must be a proper rotation or a positive scaling)."""
    v, f = mesh
    v = np.asarray(v, dtype=np.float64)
    if R is not None:
        v = v @ np.asarray(R, dtype=np.float64).T
    if t is not None:
        v = v + np.asarray(t, dtype=np.float64)
    return v, f


def flip(mesh):
    """Reverse the winding (normals point the other way), e.g. a box seen from inside."""
    v, f = mesh
    return v, np.asarray(f)[:, ::-1].copy()


def polygon_area2(poly: np.ndarray) -> float:
    """Twice the signed area of a polygon [N, 2] (xy): positive when its vertices run counter-clockwise."""
    x, y = poly[:, 0], poly[:, 1]
    return float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def triangulate_polygon(poly) -> np.ndarray:
    """Ear clipping of a simple polygon [n,2] given counter-clockwise -> triangles [n-2,3] (CCW)."""
    poly = np.asarray(poly, dtype=np.float64)
    n = len(poly)
    if polygon_area2(poly) <= 0:
        raise ValueError("polygon must be counter-clockwise")
    idx = list(range(n))
    tris = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(idx) > 3:
        guard += 1
        if guard > 10 * n * n:
            raise ValueError("ear clipping failed; polygon not simple")
        m = len(idx)
        for k in range(m):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % m]
            a, b, c = poly[i0], poly[i1], poly[i2]
            if cross(a, b, c) <= 1e-12:
                continue  # reflex or degenerate corner
            inside = False
            for j in idx:
                if j in (i0, i1, i2):
                    continue
                p = poly[j]
                if cross(a, b, p) >= 0 and cross(b, c, p) >= 0 and cross(c, a, p) >= 0:
                    inside = True
                    break
            if not inside:
                tris.append((i0, i1, i2))
                idx.pop(k)
                break
    tris.append(tuple(idx))
    return np.asarray(tris, dtype=np.int64)


def prism(poly, z0: float, z1: float, bottom: bool = True, top: bool = True):
    """Vertical prism over a simple CCW polygon [n,2] from z0 to z1 (outward normals).

    `bottom=False` omits the bottom cap (objects standing on the ground: that face is never seen and
    would only add hidden surface to the ground truth)."""
    poly = np.asarray(poly, dtype=np.float64)
    if polygon_area2(poly) < 0:
        poly = poly[::-1]
    n = len(poly)
    lo = np.c_[poly, np.full(n, z0)]
    hi = np.c_[poly, np.full(n, z1)]
    v = np.concatenate([lo, hi])
    i = np.arange(n)
    j = (i + 1) % n
    faces = [np.stack([i, j, n + j], 1), np.stack([i, n + j, n + i], 1)]
    if top or bottom:
        cap = triangulate_polygon(poly)
        if top:
            faces.append(cap + n)
        if bottom:
            faces.append(cap[:, ::-1])
    return v, np.concatenate(faces)


def rect(x0, y0, x1, y1) -> np.ndarray:
    """Axis-aligned rectangle as a CCW polygon [4,2]."""
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def box(lo, hi, bottom: bool = True, top: bool = True):
    """Axis-aligned box from corner lo [3] to hi [3]."""
    return prism(rect(lo[0], lo[1], hi[0], hi[1]), lo[2], hi[2], bottom=bottom, top=top)


def oriented_box(center_xy, size_xy, yaw, z0, z1, bottom=True, top=True):
    """Box with footprint size_xy centred at center_xy, rotated by yaw about z, from z0 to z1."""
    hx, hy = size_xy[0] / 2, size_xy[1] / 2
    c, s = np.cos(yaw), np.sin(yaw)
    poly = rect(-hx, -hy, hx, hy) @ np.array([[c, s], [-s, c]]) + np.asarray(center_xy)
    return prism(poly, z0, z1, bottom=bottom, top=top)


def circle(cx, cy, r, n=32, phase=0.0) -> np.ndarray:
    a = phase + 2 * np.pi * np.arange(n) / n
    return np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], 1)


def ellipse(cx, cy, rx, ry, n=48) -> np.ndarray:
    a = 2 * np.pi * np.arange(n) / n
    return np.stack([cx + rx * np.cos(a), cy + ry * np.sin(a)], 1)


def rounded_rect(x0, y0, x1, y1, r, n_corner=8) -> np.ndarray:
    """CCW rectangle with quarter-circle corners of radius r (curved facades)."""
    r = min(r, (x1 - x0) / 2 - 1e-6, (y1 - y0) / 2 - 1e-6)
    pts = []
    for (cx, cy, a0) in ((x1 - r, y0 + r, -np.pi / 2), (x1 - r, y1 - r, 0.0), (x0 + r, y1 - r, np.pi / 2),
                         (x0 + r, y0 + r, np.pi)):
        a = a0 + np.linspace(0, np.pi / 2, n_corner + 1)
        pts.append(np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], 1))
    return np.concatenate(pts)


def cylinder(cx, cy, r, z0, z1, n=24, bottom=True, top=True):
    """Vertical cylinder (an n-gon prism)."""
    return prism(circle(cx, cy, r, n), z0, z1, bottom=bottom, top=top)


def _frame_from_axis(axis) -> np.ndarray:
    """A proper rotation whose third column is the unit vector `axis`."""
    z = np.asarray(axis, dtype=np.float64)
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], 1)


def cylinder_between(p0, p1, r, n=16, caps=True):
    """Cylinder of radius r with its axis from p0 to p1 (any direction)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = float(np.linalg.norm(p1 - p0))
    return transform_mesh(cylinder(0.0, 0.0, r, 0.0, length, n=n, bottom=caps, top=caps),
                          _frame_from_axis(p1 - p0), p0)


def extrude_profile(profile_xz, width, center, yaw):
    """Extrude a CCW side profile (x along the object, z up) [n,2] across its width (along local y),
    then rotate by yaw about z and move to center [3]. Used for car bodies."""
    v, f = prism(profile_xz, -width / 2, width / 2)
    # (u, v, w) -> (u, -w, v): a proper rotation about x, keeps the winding outward
    v = np.stack([v[:, 0], -v[:, 2], v[:, 1]], 1)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return transform_mesh((v, f), R, center)


def icosphere(subdivisions: int = 2):
    """Unit icosphere (vertices on the unit sphere, outward CCW faces), deterministic."""
    t = (1.0 + 5 ** 0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
                  [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                  [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        mid = (v[uniq[:, 0]] + v[uniq[:, 1]]) / 2
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)  # midpoints of edges (01, 12, 20) per face
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate([np.stack([a, m01, m20], 1), np.stack([b, m12, m01], 1),
                            np.stack([c, m20, m12], 1), np.stack([m01, m12, m20], 1)])
        v = np.concatenate([v, mid])
    return v, f


def ellipsoid(center, radii, subdivisions=2):
    v, f = icosphere(subdivisions)
    return v * np.asarray(radii, dtype=np.float64) + np.asarray(center, dtype=np.float64), f


def mesh_area(vertices, faces) -> np.ndarray:
    """Per-face areas [F]."""
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def face_normals(vertices, faces) -> np.ndarray:
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    n = np.cross(b - a, c - a)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def sample_surface(vertices, faces, density_per_m2: float, seed: int, return_faces: bool = False):
    """Deterministic uniform surface samples: ~density_per_m2 points per square metre.

    Each face gets floor(area * density) samples plus one more with probability equal to the
    fractional part, placed uniformly (reflected barycentric coordinates); all randomness comes from
    `np.random.default_rng(seed)`. Returns (points [N,3] float64, normals [N,3] float32 face normals)
    and, with return_faces=True, the face index of every sample [N]."""
    rng = np.random.default_rng(seed)
    v = np.asarray(vertices, dtype=np.float64)
    area = mesh_area(v, faces)
    expected = area * density_per_m2
    counts = np.floor(expected).astype(np.int64)
    counts += rng.random(len(faces)) < (expected - counts)
    fid = np.repeat(np.arange(len(faces)), counts)
    r1 = rng.random(len(fid))
    r2 = rng.random(len(fid))
    flipm = r1 + r2 > 1
    r1[flipm], r2[flipm] = 1 - r1[flipm], 1 - r2[flipm]
    a, b, c = v[faces[fid, 0]], v[faces[fid, 1]], v[faces[fid, 2]]
    pts = a + r1[:, None] * (b - a) + r2[:, None] * (c - a)
    nrm = face_normals(v, faces)[fid].astype(np.float32)
    if return_faces:
        return pts, nrm, fid
    return pts, nrm


# ------------------------------------------------------------------------------------------------
# ray casting
# ------------------------------------------------------------------------------------------------


class Raycaster:
    """Wraps `open3d.t.geometry.RaycastingScene` over one triangle mesh (float32 inside open3d).

    `cast(origins [N,3], dirs [N,3])` -> (t [N] float64, normals [N,3] float32): hit parameter along
    `dirs` (hit = origin + t * dir, so t is a distance only for unit dirs), inf where the ray misses.
    """

    def __init__(self, vertices, faces):
        import open3d as o3d

        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.empty = len(faces) == 0
        if not self.empty:
            self.scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                                     o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))

    def cast(self, origins, dirs, return_ids: bool = False):
        """With return_ids=True also the hit triangle's index per ray [N] int64 (-1 where the ray misses)."""
        n = len(dirs)
        if self.empty:
            out = np.full(n, np.inf), np.zeros((n, 3), np.float32)
            return out + (np.full(n, -1, np.int64),) if return_ids else out
        rays = np.concatenate([np.broadcast_to(origins, dirs.shape), dirs], axis=1).astype(np.float32)
        ans = self.scene.cast_rays(self._o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        if not return_ids:
            return t, ans["primitive_normals"].numpy()
        ids = ans["primitive_ids"].numpy().astype(np.int64)
        ids[~np.isfinite(t) | (ids >= 2 ** 32 - 1)] = -1
        return t, ans["primitive_normals"].numpy(), ids


def point_triangle_distance(points, a, b, c) -> np.ndarray:
    """Exact float64 distance [N] from points [N,3] to triangles (a, b, c) [N,3] each (Ericson's
    closest-point-on-triangle, vectorised)."""
    p, a, b, c = (np.asarray(x, dtype=np.float64) for x in (points, a, b, c))
    dot = lambda x, y: np.einsum("ij,ij->i", x, y)  # noqa: E731
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        q = a + ab * v[:, None] + ac * w[:, None]  # interior
        # edge regions
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    q = np.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[:, None], b + (c - b) * t_bc[:, None], q)
    q = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[:, None], a + ac * t_ac[:, None], q)
    q = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[:, None], a + ab * t_ab[:, None], q)
    # vertex regions
    q = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
    return np.linalg.norm(p - q, axis=1)


def closest_distance(vertices, faces, points, exact: bool = True, refine_above: float = 1e-5,
                     max_refine: int = 20000) -> np.ndarray:
    """Unsigned distance [N] of points [N,3] to a triangle mesh [V,3], [F,3].

    open3d's closest-point query runs in float32 and is off by up to a few mm near long thin
    triangles (and may pick a neighbour of the closest triangle). With exact=True the distance to the
    triangle open3d picks is recomputed in float64 - an exact upper bound of the true distance - and
    points where that bound exceeds `refine_above` (at most `max_refine` of them, the farthest first)
    are searched exactly over every triangle whose bounding box is within the bound. Returns float64."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
    q = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
    if not exact:
        return scene.compute_distance(q).numpy().astype(np.float64)
    points = np.asarray(points, dtype=np.float64)
    ids = scene.compute_closest_points(q)["primitive_ids"].numpy().astype(np.int64)
    tris = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    tri = tris[ids]
    d = point_triangle_distance(points, tri[:, 0], tri[:, 1], tri[:, 2])
    redo = np.flatnonzero(d > refine_above)
    redo = redo[np.argsort(-d[redo], kind="stable")[:max_refine]]
    if len(redo):
        lo, hi = tris.min(1), tris.max(1)
        for k in redo:
            p = points[k]
            box_d = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=1)
            cand = np.flatnonzero(box_d <= d[k])
            t = tris[cand]
            d[k] = min(d[k], point_triangle_distance(np.broadcast_to(p, (len(cand), 3)), t[:, 0], t[:, 1],
                                                     t[:, 2]).min())
    return d


# ------------------------------------------------------------------------------------------------
# files
# ------------------------------------------------------------------------------------------------


def prepare_out_dir(out_dir, sub: str, pattern_ext: str) -> str:
    """Create out_dir/sub; remove earlier generated files there (6-digit names with pattern_ext) so a
    re-run with fewer frames leaves no stale frames behind. Refuses a path that is a file."""
    out_dir = os.fspath(out_dir)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise DataError(f"{out_dir}: exists and is not a directory; pick another --out")
    d = os.path.join(out_dir, sub)
    os.makedirs(d, exist_ok=True)
    for name in os.listdir(d):
        stem, ext = os.path.splitext(name)
        if ext == pattern_ext and len(stem) == 6 and stem.isdigit():
            os.remove(os.path.join(d, name))
    return d


def write_json(path, obj) -> None:
    with open(path, "w") as f:
        json.dump(obj, f, indent=1, sort_keys=True)
        f.write("\n")


def points_stats(counts) -> dict:
    counts = np.asarray(counts)
    return {"mean": round(float(counts.mean()), 1), "min": int(counts.min()), "max": int(counts.max())}


def hash_tree(root) -> dict:
    """{relative path: sha256} of every file under root (for determinism checks)."""
    out = {}
    root = os.fspath(root)
    for dirpath, _, files in os.walk(root):
        for name in files:
            p = os.path.join(dirpath, name)
            with open(p, "rb") as f:
                out[os.path.relpath(p, root)] = hashlib.sha256(f.read()).hexdigest()
    return out


def rounded(x, nd=4):
    """Round floats (recursively in lists) for readable, stable JSON."""
    if isinstance(x, (list, tuple, np.ndarray)):
        return [rounded(v, nd) for v in x]
    return round(float(x), nd)


def walkers(path, n: int, seed, tag: int, n_frames: int, step: float, shift=None) -> list:
    """Per frame a list of (center_xy, yaw) of n pedestrians walking along `path` (an object with
    `.length` and `.at(s) -> (x, y, yaw)`), every other one the other way, `step` metres a frame, from
    seeded random starts (`SeedSequence([seed, tag])`); `shift` (dx, dy) moves them all."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, tag]))
    s0 = (np.arange(n) + rng.uniform(0.1, 0.9, n)) * path.length / n
    sign = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    frames = []
    for i in range(n_frames):
        peds = []
        for k in range(n):
            x, y, yaw = path.at(s0[k] + sign[k] * step * i)
            if shift is not None:  # (only then: adding 0.0 would turn a -0.0 into 0.0)
                x, y = x + shift[0], y + shift[1]
            peds.append(((x, y), yaw + (0.0 if sign[k] > 0 else np.pi)))
        frames.append(peds)
    return frames
