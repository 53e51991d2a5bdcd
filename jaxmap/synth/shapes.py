"""Local surface patches with exact signed distances, for training the equivariant prior.

Everything is in voxel units (voxel size 1). A *scene* is a union of primitives with exact SDFs
(planes, spheres, boxes, capped cylinders and cones, tori, convex and concave corners and edges of
large boxes, thin slabs), each with its own rotation and translation; the scene may be turned inside
out (a room around a box is the complement of a box). A *patch* (one training example) is one voxel
whose cell the surface crosses:

* `points [N, 3]`, `normals [N, 3]`: surface samples of the voxel's 2x2x2-voxel neighbourhood,
  relative to the voxel centre (so in `[-1, 1]^3`), with unit outward normals (gradient of the SDF);
  sampled about uniformly by area; `mask [N]` marks the valid ones (counts vary per voxel, padding
  repeats valid points).
* `queries [Q, 3]` in `[-1, 1]^3` (most near the surface, some uniform) and `sdf [Q]`, their signed
  distances (positive outside / in free space).

SDF exactness: each primitive's SDF is exact (Inigo Quilez's formulas); the union is the min of them,
which is exact outside the shapes and on the surface, and a lower bound of the depth inside where two
primitives overlap. Turning a scene inside out negates it (exact). No noise is added here: the
trainer adds point and normal noise on the fly.

numpy only (float64 inside, float32 out). `make_dataset` is deterministic given its seed.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from jaxmap.geometry import random_rotation

BIG = 50.0  # half-size of the "infinite" boxes used for corners, edges and slabs

KINDS = ("plane", "sphere", "box", "cylinder", "cone", "torus", "corner", "edge", "slab")
KIND_WEIGHTS = (0.12, 0.13, 0.12, 0.10, 0.07, 0.08, 0.13, 0.13, 0.12)


# ---------------------------------------------------------------------------------------------
# Primitive SDFs, in the primitive's own frame. x: [M, 3] float64 -> [M].
# ---------------------------------------------------------------------------------------------


def sdf_plane(x):
    """Half-space z <= 0 (normal +z)."""
    return x[:, 2]


def sdf_sphere(x, r):
    return np.linalg.norm(x, axis=1) - r


def sdf_box(x, b):
    """Axis-aligned box of half-sizes b [3] centred at the origin."""
    q = np.abs(x) - b
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside


def sdf_cylinder(x, r, h):
    """Capped cylinder along z, radius r, half-height h."""
    d = np.stack([np.linalg.norm(x[:, :2], axis=1) - r, np.abs(x[:, 2]) - h], axis=1)
    return np.minimum(d.max(axis=1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=1)


def sdf_cone(x, h, r1, r2):
    """Capped cone along z, half-height h, radius r1 at z=-h and r2 at z=+h (exact)."""
    qx = np.linalg.norm(x[:, :2], axis=1)
    qy = x[:, 2]
    k1 = np.array([r2, h])
    k2 = np.array([r2 - r1, 2.0 * h])
    ca_x = qx - np.minimum(qx, np.where(qy < 0.0, r1, r2))
    ca_y = np.abs(qy) - h
    q = np.stack([qx, qy], axis=1)
    t = np.clip(((k1 - q) @ k2) / (k2 @ k2), 0.0, 1.0)
    cb = q - k1 + k2 * t[:, None]
    s = np.where((cb[:, 0] < 0.0) & (ca_y < 0.0), -1.0, 1.0)
    return s * np.sqrt(np.minimum(ca_x**2 + ca_y**2, (cb**2).sum(axis=1)))


def sdf_torus(x, big_r, small_r):
    """Torus around the z axis."""
    qx = np.linalg.norm(x[:, :2], axis=1) - big_r
    return np.sqrt(qx**2 + x[:, 2] ** 2) - small_r


@dataclass
class Primitive:
    """One primitive: `kind`, parameters, pose (`x_local = R^T (x - t)`), and sign (-1 = complement)."""

    kind: str
    params: dict
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sign: float = 1.0

    def local_sdf(self, xl):
        k, p = self.kind, self.params
        if k == "plane":
            return sdf_plane(xl)
        if k == "sphere":
            return sdf_sphere(xl, p["r"])
        if k in ("box", "corner", "edge", "slab"):
            return sdf_box(xl - p["c"], p["b"])
        if k == "cylinder":
            return sdf_cylinder(xl, p["r"], p["h"])
        if k == "cone":
            return sdf_cone(xl, p["h"], p["r1"], p["r2"])
        if k == "torus":
            return sdf_torus(xl, p["R"], p["r"])
        raise ValueError(k)

    def sdf(self, x):
        return self.sign * self.local_sdf((x - self.t) @ self.R)

    def anchor(self, rng, n):
        """Points [n, 3] (scene frame) near the interesting part of the surface, to place voxels at."""
        k, p = self.kind, self.params
        if k == "plane":
            xl = rng.uniform(-1.0, 1.0, (n, 3))
        elif k == "sphere":
            d = rng.normal(size=(n, 3))
            xl = d / np.linalg.norm(d, axis=1, keepdims=True) * p["r"]
        elif k == "box":
            xl = rng.uniform(-1.0, 1.0, (n, 3)) * (p["b"] + 0.3)
        elif k == "cylinder":
            xl = rng.uniform(-1.0, 1.0, (n, 3)) * np.array([p["r"] + 0.3, p["r"] + 0.3, p["h"] + 0.3])
        elif k == "cone":
            r = max(p["r1"], p["r2"]) + 0.3
            xl = rng.uniform(-1.0, 1.0, (n, 3)) * np.array([r, r, p["h"] + 0.3])
        elif k == "torus":
            r = p["R"] + p["r"] + 0.3
            xl = rng.uniform(-1.0, 1.0, (n, 3)) * np.array([r, r, p["r"] + 0.3])
        else:  # corner, edge, slab: the feature is at the origin of the local frame
            xl = rng.uniform(-0.8, 0.8, (n, 3))
        return xl @ self.R.T + self.t


def random_primitive(rng: np.random.Generator, kind: str | None = None) -> Primitive:
    """A random primitive of `kind` (or of a random kind) with a uniformly random orientation."""
    if kind is None:
        kind = KINDS[rng.choice(len(KINDS), p=np.asarray(KIND_WEIGHTS) / np.sum(KIND_WEIGHTS))]
    logu = lambda lo, hi: float(np.exp(rng.uniform(np.log(lo), np.log(hi))))  # noqa: E731
    sign = 1.0
    if kind == "plane":
        params = {}
    elif kind == "sphere":
        params = {"r": logu(0.4, 8.0)}
        sign = -1.0 if rng.random() < 0.2 else 1.0  # spherical cavities too
    elif kind == "box":
        params = {"c": np.zeros(3), "b": np.array([logu(0.25, 5.0) for _ in range(3)])}
    elif kind == "cylinder":
        params = {"r": logu(0.3, 5.0), "h": logu(0.3, 5.0)}
        sign = -1.0 if rng.random() < 0.15 else 1.0
    elif kind == "cone":
        r1 = rng.uniform(0.3, 4.0)
        params = {"h": rng.uniform(0.5, 4.0), "r1": r1, "r2": rng.uniform(0.0, 0.8 * r1)}
    elif kind == "torus":
        big = rng.uniform(1.0, 5.0)
        params = {"R": big, "r": rng.uniform(0.2, min(big - 0.1, 2.0))}
    elif kind == "corner":  # box corner at the origin, box in the negative octant
        params = {"c": -np.full(3, BIG), "b": np.full(3, BIG)}
        sign = -1.0 if rng.random() < 0.5 else 1.0  # concave (room) corners as often as convex ones
    elif kind == "edge":  # box edge along z through the origin
        params = {"c": np.array([-BIG, -BIG, 0.0]), "b": np.full(3, BIG)}
        sign = -1.0 if rng.random() < 0.5 else 1.0
    elif kind == "slab":  # thin plate |z| <= th, ending at x = e
        th = rng.uniform(0.05, 0.5)
        e = rng.uniform(-1.0, 3.0)
        params = {"c": np.array([e - BIG, 0.0, 0.0]), "b": np.array([BIG, BIG, th])}
    else:
        raise ValueError(f"unknown primitive kind {kind!r}; known: {KINDS}")
    return Primitive(kind, params, R=random_rotation(rng), t=np.zeros(3), sign=sign)


@dataclass
class Scene:
    """Union of primitives (min of their SDFs), optionally turned inside out (`sign = -1`)."""

    prims: list
    sign: float = 1.0

    def sdf(self, x):
        x = np.asarray(x, dtype=np.float64)
        d = self.prims[0].sdf(x)
        for p in self.prims[1:]:
            d = np.minimum(d, p.sdf(x))
        return self.sign * d

    def grad(self, x, h=1e-5):
        """Central-difference gradient [M, 3] (float64; exact to ~1e-9 away from creases)."""
        g = np.empty_like(x)
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            g[:, i] = (self.sdf(x + e) - self.sdf(x - e)) / (2.0 * h)
        return g

    def project(self, x, iters=3):
        """Move points onto the zero level set (x -= d grad d). Returns (points, |sdf| after)."""
        for _ in range(iters):
            d = self.sdf(x)
            g = self.grad(x)
            g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
            x = x - d[:, None] * g
        return x, np.abs(self.sdf(x))


def random_scene(rng: np.random.Generator, kind: str | None = None, union_prob: float = 0.35) -> Scene:
    """A primary primitive plus, with probability `union_prob`, one or two small primitives whose
    surfaces pass near the primary's anchor region."""
    prims = [random_primitive(rng, kind)]
    if rng.random() < union_prob:
        anchor = prims[0].anchor(rng, 1)[0]
        for _ in range(rng.integers(1, 3)):
            q = random_primitive(rng, KINDS[rng.choice([1, 2, 3, 4, 5])])
            s = q.anchor(rng, 1)[0]
            q.t = anchor + rng.uniform(-1.0, 1.0, 3) - s
            prims.append(q)
    sign = -1.0 if rng.random() < 0.15 else 1.0
    return Scene(prims, sign)


# ---------------------------------------------------------------------------------------------
# Patches
# ---------------------------------------------------------------------------------------------


def voxel_centres(scene: Scene, rng: np.random.Generator, k: int) -> np.ndarray:
    """k voxel centres [k', 3] (k' <= k) whose cell contains a point of the scene surface."""
    seeds = np.concatenate([p.anchor(rng, k) for p in scene.prims])[rng.permutation(k * len(scene.prims))[:k]]
    s, err = scene.project(seeds)
    s = s[err < 1e-6]
    return s + rng.uniform(-0.5, 0.5, s.shape)


def surface_samples(scene: Scene, centres: np.ndarray, rng: np.random.Generator, n_cand: int,
                    shell: float = 0.04):
    """Surface points and unit normals in the 2x2x2 neighbourhood of each centre.

    Thin-shell sampling: candidates uniform in each cube, those within `shell` of the surface are
    projected onto it (area-uniform up to O(shell * curvature)). Returns a list (one per centre) of
    `(points [m, 3], normals [m, 3])` relative to the centre.
    """
    k = len(centres)
    cand = rng.uniform(-1.0, 1.0, (k, n_cand, 3)) + centres[:, None, :]
    flat = cand.reshape(-1, 3)
    owner = np.repeat(np.arange(k), n_cand)
    d = scene.sdf(flat)
    keep = np.abs(d) < shell
    pts, own = flat[keep], owner[keep]
    pts, err = scene.project(pts, iters=2)
    rel = pts - centres[own]
    ok = (err < 1e-6) & (np.abs(rel).max(axis=1) <= 1.0)
    pts, rel, own = pts[ok], rel[ok], own[ok]
    g = scene.grad(pts)
    nrm = np.linalg.norm(g, axis=1, keepdims=True)
    ok = nrm[:, 0] > 0.5  # drop points exactly on creases where the gradient is undefined
    normals = g[ok] / nrm[ok]
    rel, own = rel[ok], own[ok]
    return [(rel[own == i], normals[own == i]) for i in range(k)]


@dataclass(frozen=True)
class PatchSpec:
    """What one example holds (voxel units)."""

    n_points: int = 64          # padded point count N
    min_points: int = 16        # fewer surface samples than this in the neighbourhood: voxel skipped
    n_queries: int = 128        # Q
    near_frac: float = 0.8      # share of queries near the surface (rest uniform in [-1, 1]^3)
    near_sigma: float = 0.25    # std of the offset along the normal of near-surface queries
    n_cand: int = 3000          # candidates per voxel for thin-shell surface sampling
    random_count: bool = True   # valid point count uniform in [min_points, n_points] (else all N)


def patch_from_samples(scene: Scene, centre, pts, nrm, rng, spec: PatchSpec):
    """One example from a voxel centre and its surface samples; None if too few samples."""
    m = len(pts)
    if m < spec.min_points or np.sum(np.abs(pts).max(axis=1) <= 0.5) < 3:
        return None
    n_valid = int(rng.integers(spec.min_points, spec.n_points + 1)) if spec.random_count else spec.n_points
    idx = rng.choice(m, size=n_valid, replace=m < n_valid)
    idx = np.concatenate([idx, idx[rng.integers(0, n_valid, spec.n_points - n_valid)]])
    mask = np.arange(spec.n_points) < n_valid
    n_near = int(round(spec.near_frac * spec.n_queries))
    j = rng.integers(0, m, n_near)
    near = pts[j] + nrm[j] * rng.normal(0.0, spec.near_sigma, (n_near, 1)) + rng.normal(0.0, 0.05, (n_near, 3))
    uni = rng.uniform(-1.0, 1.0, (spec.n_queries - n_near, 3))
    q = np.clip(np.concatenate([near, uni]), -1.0, 1.0)
    sdf = scene.sdf(q + centre)
    return {
        "points": pts[idx].astype(np.float32),
        "normals": nrm[idx].astype(np.float32),
        "mask": mask,
        "queries": q.astype(np.float32),
        "sdf": sdf.astype(np.float32),
    }


def _stack(examples, kinds):
    out = {k: np.stack([e[k] for e in examples]) for k in examples[0]}
    out["kind"] = np.asarray(kinds, dtype=np.int32)
    return out


def make_dataset(n: int, seed: int, spec: PatchSpec = PatchSpec(), voxels_per_scene: int = 8,
                 kind: str | None = None, union_prob: float = 0.35, progress=None) -> dict:
    """`n` examples from random scenes. Returns a dict of stacked arrays:
    points/normals `[n, N, 3]` f32, mask `[n, N]` bool, queries `[n, Q, 3]` f32, sdf `[n, Q]` f32,
    kind `[n]` int32 (index into KINDS of the scene's primary primitive). Deterministic in `seed`.
    """
    rng = np.random.default_rng(seed)
    examples, kinds = [], []
    while len(examples) < n:
        scene = random_scene(rng, kind, union_prob)
        centres = voxel_centres(scene, rng, voxels_per_scene)
        if len(centres) == 0:
            continue
        for c, (pts, nrm) in zip(centres, surface_samples(scene, centres, rng, spec.n_cand)):
            ex = patch_from_samples(scene, c, pts, nrm, rng, spec)
            if ex is not None and len(examples) < n:
                examples.append(ex)
                kinds.append(KINDS.index(scene.prims[0].kind))
                if progress is not None:
                    progress(1)
    return _stack(examples, kinds)


# ---------------------------------------------------------------------------------------------
# Held-out test patches
# ---------------------------------------------------------------------------------------------

HELDOUT_PATCHES = ("plane", "sphere_r2", "box_corner")


def _fixed_scene(name: str, rng: np.random.Generator) -> Scene:
    R = random_rotation(rng)
    if name == "plane":
        return Scene([Primitive("plane", {}, R=R)])
    if name == "sphere_r2":
        return Scene([Primitive("sphere", {"r": 2.0}, R=R)])
    if name == "box_corner":
        return Scene([Primitive("corner", {"c": -np.full(3, BIG), "b": np.full(3, BIG)}, R=R)])
    raise ValueError(f"unknown test patch {name!r}; known: {HELDOUT_PATCHES}")


def heldout_patches(name: str, n: int = 16, seed: int = 12345, n_points: int = 64, n_queries: int = 512,
                 inner: bool = True) -> dict:
    """`n` held-out voxels of one named patch: a plane, a sphere of radius 2 voxels, or a convex box
    corner, each in a random orientation, with the voxel placed so that the surface crosses its cell
    (for the corner, the corner itself lies in the cell). Clean points and normals (all N valid).
    Queries are uniform in the voxel's own cell `[-0.5, 0.5]^3` when `inner` (what mesh extraction
    decodes), else in the whole neighbourhood `[-1, 1]^3`. Same dict layout as `make_dataset`.
    """
    rng = np.random.default_rng(seed)
    spec = PatchSpec(n_points=n_points, min_points=8, n_queries=n_queries, random_count=False)
    examples = []
    while len(examples) < n:
        scene = _fixed_scene(name, rng)
        if name == "box_corner":
            centre = rng.uniform(-0.5, 0.5, (1, 3))
        else:
            centre = voxel_centres(scene, rng, 1)
            if len(centre) == 0:
                continue
        (pts, nrm), = surface_samples(scene, centre, rng, spec.n_cand * 2)
        if len(pts) < spec.min_points:
            continue
        idx = rng.choice(len(pts), size=n_points, replace=len(pts) < n_points)
        lim = 0.5 if inner else 1.0
        q = rng.uniform(-lim, lim, (n_queries, 3))
        examples.append({
            "points": pts[idx].astype(np.float32),
            "normals": nrm[idx].astype(np.float32),
            "mask": np.ones(n_points, dtype=bool),
            "queries": q.astype(np.float32),
            "sdf": scene.sdf(q + centre[0]).astype(np.float32),
        })
    kind = {"plane": "plane", "sphere_r2": "sphere", "box_corner": "corner"}[name]
    return _stack(examples, [KINDS.index(kind)] * n)
