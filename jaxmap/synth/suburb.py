"""The second city layout (`generate_city(layout="suburb")`, `jaxmap synth city --layout suburb`).

A curved ring boulevard through a suburb: the road (8 m wide, z = 0) follows a closed, smooth,
non-circular curve r(theta) = R0 (1 + 0.12 cos 2 theta + 0.03 sin(3 theta + 0.5)) around a park; the
ground on both sides is raised by the curb (CURB_H). Outside the ring stand two rows of detached houses
with gabled roofs (some behind a low picket fence), with trees between them and parked cars along the
outer curb; the inner park holds trees, street lamps and a round pavilion. The vehicle drives the ring
once counter-clockwise, 0.5 m outward of the centre line, with the grid city's LiDAR (same sensor, same
files, same classes). Everything is deterministic from the seed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxmap.synth import common as C
from jaxmap.synth.streets import CURB_H, TILE, Scene, add_pole, add_tree, car_mesh, inside_convex


@dataclass(frozen=True)
class SuburbPreset:
    r0: float               # mean radius of the road's centre line (m)
    road_width: float
    lane_offset: float      # vehicle path, outward of the centre line
    outer: float            # raised ground beyond the road's outer edge (m)
    house_rows: tuple       # distances of the house rows' front facades from the outer curb (m)
    house_spacing: float    # arc length between house centres along the first row (m)
    frames: int
    beams: int
    azimuth_steps: int
    gt_density: float
    pedestrians: int


DEFAULT = SuburbPreset(r0=21.0, road_width=8.0, lane_offset=0.5, outer=42.0, house_rows=(5.0, 24.0),
                       house_spacing=15.0, frames=130, beams=64, azimuth_steps=1024, gt_density=1000.0,
                       pedestrians=8)
SMALL = SuburbPreset(r0=11.0, road_width=7.0, lane_offset=0.5, outer=16.0, house_rows=(4.5,),
                     house_spacing=14.0, frames=72, beams=32, azimuth_steps=512, gt_density=1000.0,
                     pedestrians=4)


def _radius(P: SuburbPreset, th):
    th = np.asarray(th, dtype=np.float64)
    return P.r0 * (1.0 + 0.12 * np.cos(2 * th) + 0.03 * np.sin(3 * th + 0.5))  # convex, egg-shaped


def _polar(r, th):
    return np.stack([r * np.cos(th), r * np.sin(th)], -1)


class CurvePath:
    """A closed polar curve r = base(theta) + offset, counter-clockwise, parametrised by arc length
    (as LoopPath: `at(s)` -> (x, y, yaw), `length`, `samples(step)`)."""

    def __init__(self, P: SuburbPreset, offset: float, n: int = 20000):
        th = 2 * np.pi * np.arange(n + 1) / n
        xy = _polar(_radius(P, th) + offset, th)
        seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        self._s = np.r_[0.0, np.cumsum(seg)]
        self._xy = xy
        self.length = float(self._s[-1])

    def at(self, s: float):
        s = float(s) % self.length
        k = int(np.clip(np.searchsorted(self._s, s, side="right") - 1, 0, len(self._s) - 2))
        u = (s - self._s[k]) / max(self._s[k + 1] - self._s[k], 1e-12)
        p = self._xy[k] + u * (self._xy[k + 1] - self._xy[k])
        d = self._xy[k + 1] - self._xy[k]
        return float(p[0]), float(p[1]), float(np.arctan2(d[1], d[0]))

    def samples(self, step: float = 0.25) -> np.ndarray:
        n = int(np.ceil(self.length / step))
        return np.array([self.at(i * self.length / n)[:2] for i in range(n)])


def ring_path(P: SuburbPreset) -> CurvePath:
    """The drive: the road's centre line moved lane_offset outward (the right lane, counter-clockwise)."""
    return CurvePath(P, P.lane_offset)


def ground_height(P: SuburbPreset):
    """ground_z(xy [N,2]) -> [N]: 0 on the ring road (radially within road_width / 2 of its centre line),
    CURB_H elsewhere (the park inside, the raised ground outside)."""
    w = P.road_width / 2

    def ground_z(xy):
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        r, th = np.hypot(xy[:, 0], xy[:, 1]), np.arctan2(xy[:, 1], xy[:, 0])
        return np.where(np.abs(r - _radius(P, th)) < w, 0.0, CURB_H)
    return ground_z


def _ground(P: SuburbPreset):
    """Polar grid: the inner park (raised), the road (z = 0), the outer ground (raised), and the two curb
    faces; tiles of at most ~TILE m; normals up (ground) or towards the road (curbs)."""
    w = P.road_width / 2
    r_out = float(_radius(P, np.linspace(0, 2 * np.pi, 720)).max()) + w + P.outer
    n_th = int(np.ceil(2 * np.pi * r_out / TILE))
    th = 2 * np.pi * np.arange(n_th) / n_th
    rc = _radius(P, th)
    mb = C.MeshBuilder()

    def band(u0, u1, z, n_rad, rel):
        """Quads between radii (rc + u0) and (rc + u1) (or fractions of rc when rel), n_rad rows."""
        fr = np.linspace(0.0, 1.0, n_rad + 1)
        if rel:
            radii = np.outer(fr, rc * u1)  # from the centre (fr = 0) out to rc * u1
        else:
            radii = (rc + u0)[None, :] + np.outer(fr, np.full(n_th, u1 - u0))
        xy = _polar(radii, th[None, :]).reshape(-1, 2)
        v = np.c_[xy, np.full(len(xy), z)]
        i = np.arange(n_rad)[:, None] * n_th
        j = np.arange(n_th)[None, :]
        a, b = (i + j).ravel(), (i + (j + 1) % n_th).ravel()
        c, d = a + n_th, b + n_th
        f = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
        return v, f

    inner_frac = (rc - w) / rc
    mb.add(_orient_up(band(0, inner_frac, CURB_H, int(np.ceil((rc - w).max() / TILE)), rel=True)))
    mb.add(_orient_up(band(-w, w, 0.0, int(np.ceil(2 * w / TILE)), rel=False)))
    mb.add(_orient_up(band(w, w + P.outer, CURB_H, int(np.ceil(P.outer / TILE)), rel=False)))
    # curb faces: inner edge faces outward (+radial), outer edge faces inward
    for u, sign in ((-w, 1.0), (w, -1.0)):
        xy = _polar(rc + u, th)
        nxt = np.roll(np.arange(n_th), -1)
        v = np.concatenate([np.c_[xy, np.zeros(n_th)], np.c_[xy, np.full(n_th, CURB_H)]])
        i = np.arange(n_th)
        f = np.concatenate([np.stack([i, nxt, nxt + n_th], 1), np.stack([i, nxt + n_th, i + n_th], 1)])
        nrm = C.face_normals(v, f)
        radial = _polar(np.ones(n_th), th + np.pi / n_th)
        flip = np.einsum("ij,ij->i", nrm[:, :2], np.concatenate([radial, radial])) * sign < 0
        f[flip] = f[flip][:, ::-1]
        mb.add((v, f))
    return mb.build()


def _orient_up(mesh):
    v, f = mesh
    f = np.asarray(f).copy()
    down = C.face_normals(v, f)[:, 2] < 0
    f[down] = f[down][:, ::-1]
    area = C.mesh_area(v, f)
    return v, f[area > 1e-9]  # (the fan's degenerate triangles at the centre)


def _house(scene: Scene, gid: int, centre, yaw: float, rng, fence: bool):
    """A detached house: a gabled prism (ridge across the facade) standing on the raised ground, its
    front facade facing the road (yaw = direction from the house to the road)."""
    width = rng.uniform(8.0, 12.0)   # along the facade
    depth = rng.uniform(7.0, 9.5)    # towards the road
    eaves = rng.uniform(3.0, 6.5)
    ridge = rng.uniform(1.8, 3.2)
    prof = np.array([[-depth / 2, 0.0], [depth / 2, 0.0], [depth / 2, eaves], [0.0, eaves + ridge],
                     [-depth / 2, eaves]])
    mesh = C.extrude_profile(prof, width, (centre[0], centre[1], CURB_H), yaw)
    hid = scene.add(mesh, "house")
    foot = C.oriented_box(centre, (depth, width), yaw, 0.0, 1.0)[0][:4, :2]
    scene.hidden.append((gid, inside_convex(foot, CURB_H - 0.01, CURB_H + eaves + ridge)))
    scene.hidden.append((hid, lambda p: p[:, 2] < CURB_H + 1e-6))  # its bottom face, on the ground
    if fence:
        u = np.array([np.cos(yaw), np.sin(yaw)])        # towards the road
        t = np.array([-u[1], u[0]])                     # along the facade
        front = np.asarray(centre) + u * (depth / 2 + rng.uniform(1.5, 2.5))
        half = width / 2 + 1.0
        n = int(2 * half // 0.12)
        fyaw = float(np.arctan2(t[1], t[0]))
        for k in range(n):
            c = front + t * (-half + 0.06 + k * 0.12)
            scene.add(C.oriented_box(c, (0.05, 0.03), fyaw, CURB_H, CURB_H + 0.9, bottom=False), "fence")
        scene.add(C.oriented_box(front, (2 * half, 0.04), fyaw, CURB_H + 0.9, CURB_H + 0.96), "fence")


def build_suburb(P: SuburbPreset, seed: int, path: CurvePath):
    """The static scene: (vertices [V,3], faces [F,3], object id per face [F], Scene)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 111]))
    scene = Scene()
    gid = scene.add(_ground(P), "ground")
    traj = path.samples(0.25)
    w = P.road_width / 2

    def frame_at(s, offset):
        """Point at arc length s of the centre line moved by `offset` outward, and the outward normal."""
        x, y, yaw = centre_line.at(s)
        n = np.array([np.sin(yaw), -np.cos(yaw)])  # right of a counter-clockwise travel = outward
        return np.array([x, y]) + offset * n, n, yaw

    centre_line = CurvePath(P, 0.0)
    L = centre_line.length

    def clear_of_path(poly, margin):
        # every footprint vertex farther than margin from the drive (a car is convex, the drive outside it)
        d = np.linalg.norm(poly[:, None, :] - traj[None, :, :], axis=2)
        return bool(d.min() > margin)

    # houses in rows outside the ring, facing the road; trees between the first row's houses
    placed = []
    for row, front in enumerate(P.house_rows):
        n_h = int(L * (1.0 + (w + front + 4.25) / P.r0) // P.house_spacing)  # ~house_spacing apart in the row
        s0 = rng.uniform(0, L / n_h)
        for k in range(n_h):
            s = (s0 + k * L / n_h + rng.uniform(-1.0, 1.0)) % L
            depth_guess = 8.5
            p, n, _ = frame_at(s, w + front + depth_guess / 2)
            yaw = float(np.arctan2(-n[1], -n[0]))
            fence = row == 0 and rng.random() < 0.5
            if any(np.linalg.norm(p - q) < 13.0 for q in placed):  # (never on the convex ring; a guard)
                continue
            placed.append(p)
            _house(scene, gid, p, yaw, rng, fence=fence)
            if row == 0:
                tp, _, _ = frame_at((s + 0.5 * L / n_h) % L, w + 2.2)
                add_tree(scene, tp, rng, max_r=rng.uniform(1.2, 1.6), z0=CURB_H)
    # the inner park: a ring of trees and lamps along the inner curb, a pavilion in the middle
    s = rng.uniform(0, 5)
    k = 0
    while s < L - 4:
        p, n, yaw = frame_at(s, -w - 2.0)
        if k % 3 == 2:
            add_pole(scene, frame_at(s, -w - 0.5)[0], np.array([np.cos(yaw), np.sin(yaw)]), rng)
        else:
            add_tree(scene, p, rng, max_r=1.4, z0=CURB_H)
        s += rng.uniform(7.0, 10.0)
        k += 1
    pr = 0.15 * P.r0
    poly = C.circle(0.0, 0.0, pr, n=48)
    h = rng.uniform(6.0, 9.0)
    scene.add(C.prism(poly, CURB_H, CURB_H + h, bottom=False, top=True), "building")
    scene.hidden.append((gid, inside_convex(poly, CURB_H - 0.01, CURB_H + h)))
    # cars parked along the outer curb (on the road), clear of the drive
    s = rng.uniform(1.0, 4.0)
    while s < L - 6.0:
        if rng.random() < 0.6:
            p, n, yaw = frame_at(s + 2.4, w - 1.1)
            mesh, _, _ = car_mesh(p, yaw + (np.pi if rng.random() < 0.5 else 0.0), rng)
            if clear_of_path(mesh[0][:, :2], 0.6):
                scene.add(mesh, "car")
            s += 4.8 + rng.uniform(1.5, 4.0)
        else:
            s += rng.uniform(4.0, 10.0)
    v, f, obj = scene.build()
    return v, f, obj, scene


def pedestrian_boxes(P: SuburbPreset, seed: int, n_frames: int, step: float):
    """Per frame a list of (center_xy, yaw): pedestrians walking along the outer sidewalk."""
    path = CurvePath(P, P.road_width / 2 + 1.5)
    return C.walkers(path, P.pedestrians, seed, 212, n_frames, step)
