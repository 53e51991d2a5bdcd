"""Street furniture shared by the two city layouts (`jaxmap.synth.city`'s grid and `jaxmap.synth.suburb`'s
ring): the scene that collects object meshes, the 'inside' tests that drop hidden ground-truth samples,
and trees, parked cars and poles. World frame, metres, z up; the road is at z = 0 and the sidewalks at
CURB_H. Every random draw comes from the caller's `rng`, in a fixed order (the scenes are deterministic
from the seed).
"""
from __future__ import annotations

import numpy as np

from jaxmap.synth import common as C

CURB_H = 0.15            # sidewalk / block height above the road
TILE = 2.0               # ground and curb faces are split into tiles of at most this size (m)


class Scene:
    """Collects object meshes with ids and the 'inside' tests used to drop hidden GT samples."""

    def __init__(self):
        self.parts: list = []      # (vertices, faces)
        self.kinds: list[str] = []
        self.hidden: list = []     # (object id whose samples are tested, inside(points) -> mask)

    def add(self, mesh, kind: str) -> int:
        self.parts.append(mesh)
        self.kinds.append(kind)
        return len(self.parts) - 1

    def build(self):
        mb = C.MeshBuilder()
        obj = []
        for i, m in enumerate(self.parts):
            mb.add(m)
            obj.append(np.full(len(m[1]), i, np.int32))
        v, f = mb.build()
        return v, f, np.concatenate(obj)


def inside_convex(poly: np.ndarray, z0: float, z1: float, eps: float = 1e-6):
    """inside(points) for a vertical prism over a CCW convex polygon (strictly inside by eps)."""
    poly = np.asarray(poly, dtype=np.float64)
    if C.polygon_area2(poly) < 0:
        poly = poly[::-1]
    a = poly
    b = np.roll(poly, -1, axis=0)

    lo, hi = poly.min(0), poly.max(0)

    def inside(p):
        m = ((p[:, 2] > z0 - eps) & (p[:, 2] < z1 - eps) & (p[:, 0] > lo[0]) & (p[:, 0] < hi[0])
             & (p[:, 1] > lo[1]) & (p[:, 1] < hi[1]))
        idx = np.flatnonzero(m)
        q = p[idx]
        ok = np.ones(len(idx), bool)
        for ai, bi in zip(a, b):
            e = bi - ai
            ok &= e[0] * (q[:, 1] - ai[1]) - e[1] * (q[:, 0] - ai[0]) > eps
        m[idx] = ok
        return m
    inside.x_range = (lo[0], hi[0])  # no point outside it is inside (lets city's GT sampling skip the rest)
    return inside


def inside_ellipsoid(center, radii, shrink: float = 0.98):
    """inside(points [N, 3]) -> [N] bool for an axis-aligned ellipsoid (center [3], radii [3]) shrunk by `shrink`."""
    c = np.asarray(center)
    r = np.asarray(radii) * shrink  # the icosphere's facets lie slightly inside the ellipsoid

    def inside(p):
        return (((p - c) / r) ** 2).sum(1) < 1.0
    inside.x_range = (c[0] - r[0], c[0] + r[0])
    return inside


def add_tree(scene: Scene, xy, rng, max_r: float, z0: float):
    """A trunk standing on z0 at xy [2] with an ellipsoid crown of horizontal radius <= max_r (4 draws of rng);
    the crown hides the trunk's samples inside it."""
    r_trunk = rng.uniform(0.12, 0.18)
    trunk_h = rng.uniform(2.3, 3.0)
    rxy = rng.uniform(0.75, 1.0) * max_r
    rz = rng.uniform(1.0, 1.5) * rxy
    z_top = z0 + trunk_h
    center = (xy[0], xy[1], z_top + rz - 0.15)
    tid = scene.add(C.cylinder(xy[0], xy[1], r_trunk, z0, z_top, n=16, bottom=False, top=False), "trunk")
    scene.add(C.ellipsoid(center, (rxy, rxy, rz), subdivisions=3), "crown")
    scene.hidden.append((tid, inside_ellipsoid(center, (rxy, rxy, rz))))


def car_mesh(xy, yaw, rng):
    """A parked car on the road (z = 0) centred at xy [2], heading `yaw` (rad), 3 draws of rng.
    Returns ((vertices [V, 3], faces [F, 3]), length L, width W)."""
    L = rng.uniform(4.0, 4.8)
    H = rng.uniform(1.4, 1.6)
    W = rng.uniform(1.7, 1.85)
    prof = np.array([[0, 0.3], [L, 0.3], [L, 0.85], [0.78 * L, 1.0], [0.62 * L, H], [0.25 * L, H],
                     [0.08 * L, 1.0], [0, 0.95]])
    prof[:, 0] -= L / 2
    return C.extrude_profile(prof, W, (xy[0], xy[1], 0.0), yaw), L, W


def add_pole(scene: Scene, xy, street_dir, rng):
    """A pole on the sidewalk at xy [2], half of them with a sign facing along street_dir [2] (unit)."""
    r = 0.08
    top = CURB_H + rng.uniform(4.5, 7.0)
    scene.add(C.cylinder(xy[0], xy[1], r, CURB_H, top, n=16, bottom=False, top=True), "pole")
    if rng.random() < 0.5:  # a traffic sign: a 2 cm plate facing along the street, touching the pole
        c = np.asarray(xy) + street_dir * (r + 0.01)
        yaw = float(np.arctan2(street_dir[1], street_dir[0]))
        scene.add(C.oriented_box(c, (0.02, 0.6), yaw, CURB_H + 2.2, CURB_H + 2.8), "sign")
