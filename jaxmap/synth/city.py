"""A MaiCity-like synthetic street scene with a ray-cast LiDAR and exact ground truth.

The scene (world frame: z up, road surface at z = 0) is a grid of streets around city blocks raised by a
curb; blocks hold buildings (flat box facades, rounded and cylindrical facades), a park lot behind a
fence of thin slats and one behind a thin railing; sidewalks hold trees (trunk + ellipsoid crown),
poles and traffic signs (thin plates); cars are parked along the curbs. Optional pedestrians (boxes)
walk around the central block (long: the first block on the drive's left) and are NOT part of the
ground truth.

A vehicle drives one closed loop around the central block (right lane, counter-clockwise) with a
LiDAR at 1.73 m. With long=True the city is a larger grid (6 N-S x 5 E-W streets, 256 m x 200 m) and the
vehicle drives a ~1.1 km serpentine through it instead (right lane, every E-W street once, joined at
alternate ends; not closed), ~1.09 m per frame, so the area seen grows about linearly with the frames
(long-drive memory benchmarks). long with length_km=X drives about X km through the same city: the
serpentine, then loops around groups of blocks (LONG_LOOPS) that run back over streets already driven and
pass the same intersections again, like KITTI's sequence 00 (`long_route`, `route_revisits`). Every
preset drives like a car's LiDAR at 10 Hz (`jaxmap.synth.drive`): frames ~1 m apart at a constant speed,
turns of at least 8 m radius, at most ~7.3 deg of heading change between two scans (meta.json
"trajectory": "motion" holds the figures of the frames written; fewer --frames than the preset's spread
over a loop turn faster). Written in the KITTI odometry layout, with
the SHINE/N3 pose convention:

    velodyne/000000.bin ...  float32 x,y,z,intensity in the LiDAR frame (x forward, y left, z up)
    calib.txt                "Tr:" = T_cam_velo (KITTI's typical velo->cam matrix, orthonormalised)
    poses.txt                camera-frame poses P_i, such that inv(Tr) @ P_i @ Tr = T_world_lidar_i
    gt_mesh.ply              triangle mesh of the static scene (world frame)
    gt_points.ply            uniform samples of it at 1000 per m^2 within 1 m of an observation (+ normals,
                             + a uchar class per point: CITY_CLASSES), hidden surfaces removed
    meta.json                stats and parameters (deterministic: no timings)
    pedestrians.json         (only with pedestrians=True) per-frame pedestrian boxes
    moving_objects.json      (only with traffic > 0 or parking) per-frame boxes of the moving objects:
                             {"format": "jaxmap moving objects v1", "frames": F, "objects": [{"id", "kind":
                             "car" | "pedestrian", "role", "size_xyz_m": [l, w, h], "poses": [[x, y, z_base,
                             yaw] or null per frame]}]}: centre (x, y) in the world frame, bottom z_base, top
                             z_base + h, length l along yaw (radians about +z), width w across; 4 decimals

Traffic (traffic=N, `jaxmap.synth.traffic`): N moving boxes in the scans, never in the ground truth: ~2/3
cars, taking turns at driving ahead of the sensor in its lane (>= 8 m away), oncoming (grid: straight along
the drive's streets, meeting the sensor there) and overtaking it (up to 17 m/s with the ego at 10 m/s, a
frame = spacing / 10 m/s, 0.1 s at the default's ~1 m), moving like cars (|acceleration| <= 2.5 m/s^2,
turning radius >= 5 m, yaw along the motion); the rest pedestrians (1.3-1.5 m/s) crossing the drive's
street ahead of the sensor, on the sidewalks and (grid) across the side streets. parking=True adds a
parked car that drives off mid-sequence and one that parks mid-sequence: the ground truth is the static
world at the end, so the car that parked is in it (class "parked_car", the ground under it cut away) and
listed in moving_objects.json only while it moves; the car that left is listed at every frame it is in
the scans. Grid (default, small) and suburb layouts; not with long.

Real-sensor artifacts (realistic=..., each switchable; "all" = every one), applied on the organised
beams x azimuth grid of each frame before the invalid rays are dropped:
    mixed         mixed pixels: where a return's range differs from its azimuth neighbour's (same beam) by
                  more than MIXED_JUMP_M (0.3 m), with probability MIXED_P (0.5) the return gets a range
                  uniform between the foreground and the background range
    dropout       lost returns: at grazing incidence with probability clip(1 - |cos| / 0.2, 0, 1) * 0.8 and on
                  dark surfaces (reflectivity < 0.15: seeded per object, ~60 % of the cars, ~20 % of the
                  facades) with probability 0.5 + 0.4 * range / 50 m; the intensity written becomes
                  reflectivity * (0.3 + 0.7 |cos|)
    outliers      1 in OUTLIER_RATE (2000) returns gets a range uniform in [0.5 m, 50 m] along its ray
    beam_offsets  a constant range offset per beam, N(0, 1 cm), fixed for the sequence
noise_m adds its Gaussian noise after them, as without them. Every option draws from its own seed
sequence, so a sequence without them is unchanged.

Everything is deterministic from `seed`.
"""
from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass

import numpy as np

from jaxmap.io.kitti import camera_poses_from_lidar, write_calib, write_poses
from jaxmap.io.pointcloud import write_mesh_ply, write_points_ply, write_scan_bin
from jaxmap.synth import common as C
from jaxmap.synth.drive import drive_stats
from jaxmap.synth import beams as beam_patterns
from jaxmap.synth import suburb
from jaxmap.synth import traffic as traffic_mod
from jaxmap.synth.streets import CURB_H, TILE, Scene, add_pole, add_tree, car_mesh, inside_convex

log = logging.getLogger("jaxmap")

# KITTI odometry sequence 00 velo->cam Tr (before orthonormalisation).
KITTI_TR = np.array([
    [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
    [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
    [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
    [0.0, 0.0, 0.0, 1.0]])


def kitti_tr() -> np.ndarray:
    """KITTI's typical T_cam_velo with its rotation orthonormalised (SVD), [4,4] float64."""
    U, _, Vt = np.linalg.svd(KITTI_TR[:3, :3])
    T = KITTI_TR.copy()
    T[:3, :3] = U @ Vt
    return T


@dataclass(frozen=True)
class CityPreset:
    half_extent: float      # scene spans [-h, h]^2 (m)
    street_x: float         # N-S streets at x = +-street_x (centre lines)
    street_y: float         # E-W streets at y = +-street_y
    road_width: float
    sidewalk: float         # sidewalk width inside each block (m)
    lane_offset: float      # vehicle path offset from the street centre line, outward (right lane)
    corner_radius: float
    frames: int
    beams: int
    azimuth_steps: int
    gt_density: float       # GT samples per m^2
    tree_from_curb: float
    ped_from_curb: float
    pedestrians: int
    # Larger grids (the long preset); the defaults keep the 3 x 3-block layout of the loop presets.
    streets_x: tuple = ()   # N-S street centre lines (x, increasing); () = (-street_x, street_x)
    streets_y: tuple = ()   # E-W street centre lines (y, increasing); () = (-street_y, street_y)
    half_extent_y: float = 0.0  # scene spans [-half_extent, half_extent] x [-half_extent_y, ...]; 0 = square
    parks: tuple = ()       # (i, j) block indices (x-major, from -x/-y) holding the park lots; () = central

    def street_lines(self):
        """(x centre lines of the N-S streets, y centre lines of the E-W streets), increasing."""
        return (tuple(self.streets_x) or (-self.street_x, self.street_x),
                tuple(self.streets_y) or (-self.street_y, self.street_y))


# The drives are a car's at 10 Hz (`jaxmap.synth.drive`): frames ~1 m apart (~10 m/s) at a constant speed, and
# corner radii of 8-8.5 m, so the heading turns at most 7.3 deg between two scans (the loop presets: <= 7).
DEFAULT = CityPreset(half_extent=50.0, street_x=20.0, street_y=14.0, road_width=8.0, sidewalk=4.0,
                     lane_offset=0.5, corner_radius=8.5, frames=130, beams=64, azimuth_steps=1024,
                     gt_density=1000.0, tree_from_curb=1.3, ped_from_curb=2.4, pedestrians=8)
# The small loop (~62 m, mostly corner: the sides' straights are 5 m and 1 m long) in 64 frames ~0.97 m apart.
SMALL = CityPreset(half_extent=20.0, street_x=10.0, street_y=8.0, road_width=7.0, sidewalk=2.0,
                   lane_offset=0.5, corner_radius=8.0, frames=64, beams=32, azimuth_steps=512,
                   gt_density=1000.0, tree_from_curb=0.9, ped_from_curb=1.5, pedestrians=4)
# The long drive: the DEFAULT's streets, sidewalks and sensor on a 7 x 6-block grid (N-S streets 40 m apart,
# E-W streets 36 m apart, outer blocks 24 m deep); the route (`long_route`) is ~1115 m and `frames` puts
# the frames ~1.09 m apart (street_x / street_y, the loop presets' streets, are unused). Parks in a few
# scattered blocks, so fences and railings keep showing up along the drive.
LONG = CityPreset(half_extent=128.0, street_x=0.0, street_y=0.0, road_width=8.0, sidewalk=4.0,
                  lane_offset=0.5, corner_radius=8.5, frames=1025, beams=64, azimuth_steps=1024,
                  gt_density=1000.0, tree_from_curb=1.3, ped_from_curb=2.4, pedestrians=8,
                  streets_x=(-100.0, -60.0, -20.0, 20.0, 60.0, 100.0), streets_y=(-72.0, -36.0, 0.0, 36.0, 72.0),
                  half_extent_y=100.0, parks=((1, 1), (4, 1), (2, 3), (5, 2), (3, 4)))

SENSOR_H = 1.73          # LiDAR height above the road (KITTI)
MAX_RANGE = 50.0
# Ground truth: GT points are kept within GT_NEAR_M of an observation (a static-scene hit of any frame,
# the hits thinned to one per OBS_VOXEL_M voxel); each carries one of CITY_CLASSES (uint8 index).
GT_NEAR_M = 1.0
OBS_VOXEL_M = 0.1
CITY_CLASSES = ("road", "sidewalk", "curb", "building", "car", "vegetation", "pole", "fence")
_KIND_CLASS = {"building": 3, "house": 3, "car": 4, "trunk": 5, "crown": 5, "hedge": 5, "pole": 6, "sign": 6,
               "fence": 7, "railing": 7, "parked_car": 8}  # "ground": road / sidewalk / curb by its normal and height
PARKED_CAR_CLASS = "parked_car"  # class 8, after CITY_CLASSES, only in a city with parking: the car that parked
LAYOUTS = ("grid", "suburb")
REALISTIC = ("mixed", "dropout", "outliers", "beam_offsets")
MIXED_JUMP_M = 0.3
MIXED_P = 0.5
GRAZING_COS = 0.2
GRAZING_P = 0.8
DARK_REFLECTIVITY = 0.15
OUTLIER_RATE = 2000
BEAM_OFFSET_STD_M = 0.01


def realistic_modes(realistic) -> tuple:
    """The artifacts asked for, in REALISTIC order: "all" / True = all; a comma list or a sequence of names."""
    if realistic is True:
        return REALISTIC
    if not realistic:
        return ()
    names = [n.strip() for n in realistic.split(",")] if isinstance(realistic, str) else [str(n) for n in realistic]
    names = [n for n in names if n]
    if "all" in names:
        return REALISTIC
    bad = [n for n in names if n not in REALISTIC]
    if bad:
        raise ValueError(f"unknown realistic option(s) {', '.join(bad)}; choose from all, {', '.join(REALISTIC)}")
    return tuple(n for n in REALISTIC if n in names)


def _reflectivity(kinds, seed: int, tag: int = 505) -> np.ndarray:
    """A seeded reflectivity in (0, 1] per scene object (dark < DARK_REFLECTIVITY: ~60 % of the cars, ~20 %
    of the facades)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, tag]))
    r = np.empty(len(kinds))
    for k, kind in enumerate(kinds):
        u, a = rng.random(), rng.uniform(0.04, 0.12)
        if kind == "car":
            r[k] = a if u < 0.6 else rng.uniform(0.3, 0.9)
        elif kind in ("building", "house"):
            r[k] = a if u < 0.2 else rng.uniform(0.25, 0.9)
        elif kind == "ground":
            r[k] = rng.uniform(0.2, 0.35)
        else:
            r[k] = rng.uniform(0.25, 0.7)
    return r


def _sensor_artifacts(t, cos_abs, refl, beams: int, azimuth_steps: int, modes, seed: int, i: int):
    """The range-changing artifacts of `modes` (mixed, dropout, outliers) on the organised beam-major grid
    t [beams*azimuth_steps] (inf: no return); lost returns become inf."""
    t = t.copy()
    ok = np.isfinite(t) & (t <= MAX_RANGE)
    if "mixed" in modes:
        rng = np.random.default_rng(np.random.SeedSequence([seed, 511, i]))
        G, okg = t.reshape(beams, azimuth_steps), ok.reshape(beams, azimuth_steps)
        best, other = np.zeros(G.shape), G.copy()
        for shift in (1, -1):  # the azimuth neighbours (the scan wraps around)
            Gn, okn = np.roll(G, shift, axis=1), np.roll(okg, shift, axis=1)
            diff = np.where(okg & okn, np.abs(np.where(okn, Gn, 0.0) - np.where(okg, G, 0.0)), 0.0)
            take = diff > best
            best, other = np.where(take, diff, best), np.where(take, Gn, other)
        u, w = rng.random(G.shape), rng.random(G.shape)
        mix = (best > MIXED_JUMP_M) & (u < MIXED_P)
        lo, hi = np.minimum(G[mix], other[mix]), np.maximum(G[mix], other[mix])
        G = G.copy()
        G[mix] = lo + w[mix] * (hi - lo)
        t = G.reshape(-1)
    if "dropout" in modes:
        rng = np.random.default_rng(np.random.SeedSequence([seed, 512, i]))
        p_graze = np.clip(1.0 - cos_abs / GRAZING_COS, 0.0, 1.0) * GRAZING_P
        rng_frac = np.clip(np.where(ok, t, 0.0) / MAX_RANGE, 0.0, 1.0)
        p_dark = np.where(refl < DARK_REFLECTIVITY, 0.5 + 0.4 * rng_frac, 0.0)
        drop = ok & (rng.random(len(t)) < 1.0 - (1.0 - p_graze) * (1.0 - p_dark))
        t[drop] = np.inf
        ok &= ~drop
    if "outliers" in modes:
        rng = np.random.default_rng(np.random.SeedSequence([seed, 513, i]))
        out = ok & (rng.random(len(t)) < 1.0 / OUTLIER_RATE)
        t[out] = rng.uniform(0.5, MAX_RANGE, size=int(out.sum()))
    return t


# ------------------------------------------------------------------------------------------------
# the closed vehicle path: a rounded rectangle, counter-clockwise, parametrised by arc length
# ------------------------------------------------------------------------------------------------


class LoopPath:
    """Rounded rectangle |x| <= hx, |y| <= hy with corner radius r; starts at (0, -hy) heading +x."""

    def __init__(self, hx: float, hy: float, r: float):
        self.hx, self.hy, self.r = hx, hy, r
        sx, sy = 2 * (hx - r), 2 * (hy - r)
        arc = np.pi * r / 2
        # segments: (kind, length, data)
        self.segs = [
            ("line", sx / 2, (np.array([0.0, -hy]), 0.0)),
            ("arc", arc, (np.array([hx - r, -hy + r]), -np.pi / 2)),
            ("line", sy, (np.array([hx, -hy + r]), np.pi / 2)),
            ("arc", arc, (np.array([hx - r, hy - r]), 0.0)),
            ("line", sx, (np.array([hx - r, hy]), np.pi)),
            ("arc", arc, (np.array([-hx + r, hy - r]), np.pi / 2)),
            ("line", sy, (np.array([-hx, hy - r]), -np.pi / 2)),
            ("arc", arc, (np.array([-hx + r, -hy + r]), np.pi)),
            ("line", sx / 2, (np.array([-hx + r, -hy]), 0.0)),
        ]
        self.length = float(sum(s[1] for s in self.segs))

    def at(self, s: float):
        """(x, y, yaw) at arc length s (mod the loop length)."""
        s = float(s) % self.length
        for kind, length, data in self.segs:
            if s <= length + 1e-12:
                if kind == "line":
                    p0, yaw = data
                    return p0[0] + s * np.cos(yaw), p0[1] + s * np.sin(yaw), yaw
                c, a0 = data
                a = a0 + s / self.r
                return c[0] + self.r * np.cos(a), c[1] + self.r * np.sin(a), a + np.pi / 2
            s -= length
        raise AssertionError  # pragma: no cover

    def samples(self, step: float = 0.25) -> np.ndarray:
        n = int(np.ceil(self.length / step))
        return np.array([self.at(i * self.length / n)[:2] for i in range(n)])


class RoutePath:
    """An open drive through the street grid, parametrised by arc length like LoopPath.

    waypoints: [n,2] intersection centres (world x, y) visited in order, consecutive legs axis-aligned and
    each turn 90 degrees. The vehicle keeps `lane_offset` right of the street centre line (right lane) and
    turns on a quarter circle of radius r tangent to both lanes (left and right turns alike). Starts at
    the first waypoint's lane point heading along the first leg, ends at the last one's."""

    def __init__(self, waypoints, lane_offset: float, r: float):
        W = np.asarray(waypoints, dtype=np.float64)
        d = np.diff(W, axis=0)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        right = np.stack([d[:, 1], -d[:, 0]], 1)
        self.waypoints, self.r = W, r
        # corners: (tangent point in, tangent point out, arc centre, start angle, +1 left / -1 right)
        corners = []
        for k in range(1, len(W) - 1):
            turn = d[k - 1, 0] * d[k, 1] - d[k - 1, 1] * d[k, 0]
            if abs(abs(turn) - 1.0) > 1e-9:
                raise ValueError("route legs must meet at right angles")
            q = W[k] + lane_offset * (right[k - 1] + right[k])  # where the two lane lines cross
            t_in, t_out = q - r * d[k - 1], q + r * d[k]
            c = t_in - turn * r * right[k - 1]  # the centre lies on the inside of the turn
            a0 = float(np.arctan2(*(t_in - c)[::-1]))
            corners.append((t_in, t_out, c, a0, float(np.sign(turn))))
        start = W[0] + lane_offset * right[0]
        end = W[-1] + lane_offset * right[-1]
        # segments: ("line", length, (p0, yaw)) or ("arc", length, (centre, a0, sign))
        self.segs = []
        p = start
        for k, (t_in, t_out, c, a0, sign) in enumerate(corners):
            self.segs.append(("line", float(np.linalg.norm(t_in - p)), (p, float(np.arctan2(d[k, 1], d[k, 0])))))
            self.segs.append(("arc", np.pi * r / 2, (c, a0, sign)))
            p = t_out
        self.segs.append(("line", float(np.linalg.norm(end - p)), (p, float(np.arctan2(d[-1, 1], d[-1, 0])))))
        if any(s[0] == "line" and s[1] < 0 for s in self.segs):
            raise ValueError("route legs shorter than the corner radius")
        self.length = float(sum(s[1] for s in self.segs))

    def at(self, s: float):
        """(x, y, yaw) at arc length s, clamped to [0, length]."""
        s = min(max(float(s), 0.0), self.length)
        for kind, length, data in self.segs:
            if s <= length + 1e-12:
                if kind == "line":
                    p0, yaw = data
                    return p0[0] + s * np.cos(yaw), p0[1] + s * np.sin(yaw), yaw
                c, a0, sign = data
                a = a0 + sign * s / self.r
                return c[0] + self.r * np.cos(a), c[1] + self.r * np.sin(a), a + sign * np.pi / 2
            s -= length
        kind, length, data = self.segs[-1]  # s within 1e-12 past the end (rounding)
        p0, yaw = data
        return p0[0] + length * np.cos(yaw), p0[1] + length * np.sin(yaw), yaw

    def samples(self, step: float = 0.25) -> np.ndarray:
        """[n+1,2] points every ~step metres from start to end."""
        n = int(np.ceil(self.length / step))
        return np.array([self.at(i * self.length / n)[:2] for i in range(n + 1)])


def _snake_waypoints(P: CityPreset) -> np.ndarray:
    """Intersections of a serpentine over the grid [n,2]: every E-W street once, from the southmost up,
    alternately eastward and westward, joined by one block of the outermost N-S street at alternate
    ends (so apart from crossing intersections the drive never repeats a street)."""
    xs, ys = P.street_lines()
    pts = []
    for j, y in enumerate(ys):
        a, b = (xs[0], xs[-1]) if j % 2 == 0 else (xs[-1], xs[0])
        pts += [(a, y), (b, y)]
    return np.array(pts)


# The long drive past the serpentine (`long_route(length_m=...)`, `jaxmap synth city --long --length-km X`):
# loops around groups of blocks, like KITTI's sequence 00, which passes the same intersections again. Each
# loop is a rectangle of blocks (i0, i1, j0, j1: indices of its N-S and E-W streets in P.street_lines())
# driven once around, clockwise ("cw", right turns) or counter-clockwise; it is entered where the drive
# reaches it soonest and left where it was entered. The list repeats with the directions reversed (the
# streets driven the other way) until the length is reached.
LONG_LOOPS = (
    (3, 5, 2, 4, "cw"),    # the serpentine's last blocks, back down the east edge
    (1, 3, 1, 3, "ccw"),   # the centre
    (0, 2, 2, 4, "cw"),    # the north-west
    (2, 4, 0, 2, "ccw"),   # the south, over the first streets of the serpentine
    (0, 5, 0, 4, "cw"),    # the whole city's edge
    (1, 4, 2, 3, "ccw"),   # a row of three blocks north of the centre
)
_HEADINGS = ((1, 0), (0, 1), (-1, 0), (0, -1))  # grid steps (node indices): east, north, west, south
_TURN_COST_M = 10.0  # the transits between the loops prefer going straight on


def _heading_of(a, b) -> int:
    return _HEADINGS.index((int(np.sign(b[0] - a[0])), int(np.sign(b[1] - a[1]))))


def _transits(P: CityPreset, node, heading: int):
    """Shortest drives (Dijkstra; metres plus _TURN_COST_M a turn) from `node` (i, j) arrived at with
    `heading` over the grid's intersections, never turning back: (cost, previous state) per state (i, j,
    heading arrived with)."""
    import heapq

    xs, ys = P.street_lines()
    start = (*node, heading)
    dist, prev, heap = {start: 0.0}, {}, [(0.0, start)]
    while heap:
        d, (i, j, h) = heapq.heappop(heap)
        if d > dist[(i, j, h)]:
            continue
        for h2, (di, dj) in enumerate(_HEADINGS):
            i2, j2 = i + di, j + dj
            if h2 == (h + 2) % 4 or not (0 <= i2 < len(xs) and 0 <= j2 < len(ys)):
                continue  # no U-turns; inside the grid
            d2 = d + abs(xs[i2] - xs[i]) + abs(ys[j2] - ys[j]) + (_TURN_COST_M if h2 != h else 0.0)
            if d2 < dist.get((i2, j2, h2), np.inf):
                dist[(i2, j2, h2)], prev[(i2, j2, h2)] = d2, (i, j, h)
                heapq.heappush(heap, (d2, (i2, j2, h2)))
    return dist, prev


def _loop_cycle(i0: int, i1: int, j0: int, j1: int, way: str) -> list:
    """The intersections around a rectangle of blocks in driving order (closed: the first follows the last)."""
    ccw = ([(i, j0) for i in range(i0, i1)] + [(i1, j) for j in range(j0, j1)]
           + [(i, j1) for i in range(i1, i0, -1)] + [(i0, j) for j in range(j1, j0, -1)])
    return ccw if way == "ccw" else [ccw[0]] + ccw[:0:-1]


def _loop_nodes(P: CityPreset, length_m: float) -> list:
    """The intersections (i, j) the long drive passes, in order, until it is at least length_m long (or
    further): the serpentine, then LONG_LOOPS, each reached by the shortest transit."""
    xs, ys = P.street_lines()
    nodes = []
    for j in range(len(ys)):
        row = range(len(xs)) if j % 2 == 0 else range(len(xs) - 1, -1, -1)
        nodes += [(i, j) for i in row]

    def length(ns):
        W = _turns_only(np.array([(xs[i], ys[j]) for i, j in ns], dtype=np.float64))
        return RoutePath(W, P.lane_offset, P.corner_radius).length

    k = 0
    while length(nodes) < length_m:
        i0, i1, j0, j1, way = LONG_LOOPS[k % len(LONG_LOOPS)]
        if (k // len(LONG_LOOPS)) % 2:
            way = "cw" if way == "ccw" else "ccw"
        k += 1
        cyc = _loop_cycle(i0, i1, j0, j1, way)
        n = len(cyc)
        dist, prev = _transits(P, nodes[-1], _heading_of(nodes[-2], nodes[-1]))
        entries = [(dist.get((*cyc[(e + 1) % n], _heading_of(cyc[e], cyc[(e + 1) % n])), np.inf), e)
                   for e in range(n)]
        _, e = min(entries)
        state, way_in = (*cyc[(e + 1) % n], _heading_of(cyc[e], cyc[(e + 1) % n])), []
        while state in prev:  # the transit, ending with the loop's first leg
            way_in.append(state[:2])
            state = prev[state]
        nodes += way_in[::-1] + [cyc[(e + m) % n] for m in range(2, n + 1)]
    return nodes


def _turns_only(W: np.ndarray) -> np.ndarray:
    """Waypoints [n,2] without the points where a drive goes straight on (RoutePath's corners all turn)."""
    a, b = W[1:-1] - W[:-2], W[2:] - W[1:-1]
    turn = np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]) > 1e-9
    return W[np.r_[True, turn, True]] if len(W) > 2 else W


def long_waypoints(P: CityPreset | None = None, length_m: float | None = None) -> np.ndarray:
    """The long drive's waypoints [n,2] (RoutePath's): the serpentine (`_snake_waypoints`) alone, or with
    length_m the serpentine and then LONG_LOOPS, cut to length_m: the last leg shortened so the route is
    length_m long (or, where length_m falls in a corner, the route ends before that corner, < 5 m short)."""
    P = P or LONG
    if length_m is None:
        return _snake_waypoints(P)
    if not length_m > 0:
        raise ValueError(f"the long drive's length must be > 0 m, not {length_m:g}")
    xs, ys = P.street_lines()
    nodes = _loop_nodes(P, length_m)
    pts = np.array([(xs[i], ys[j]) for i, j in nodes], dtype=np.float64)
    # the fewest intersections that reach length_m (the length grows with every one)
    lo, hi = 1, len(pts) - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if RoutePath(_turns_only(pts[:mid + 1]), P.lane_offset, P.corner_radius).length >= length_m:
            hi = mid
        else:
            lo = mid + 1
    W = _turns_only(pts[:lo + 1])
    route = RoutePath(W, P.lane_offset, P.corner_radius)
    excess, last = route.length - length_m, route.segs[-1][1]
    if excess <= last:
        d = (W[-1] - W[-2]) / np.linalg.norm(W[-1] - W[-2])
        W[-1] = W[-1] - excess * d
    elif len(W) > 2:
        W = W[:-1]  # length_m falls in the last corner: end before it
    return W


def long_route(P: CityPreset | None = None, length_m: float | None = None) -> RoutePath:
    """The long preset's drive (a RoutePath over `long_waypoints`): the ~1115 m serpentine, or with
    length_m a drive of that length that goes on with loops over streets already driven."""
    P = P or LONG
    return RoutePath(long_waypoints(P, length_m), P.lane_offset, P.corner_radius)


def route_revisits(route, P: CityPreset | None = None, step: float = 1.0, gap_m: float = 60.0) -> dict:
    """How much of a drive passes again where it has been: {"intersections": the grid intersections it
    passes, "intersections_passed_again": those it passes more than once, "max_passes": the most passes of
    one, "revisited_m": metres driven within 1.5 m of the drive at least gap_m earlier (either lane)}. A
    pass: a run of the route's points (every `step` m) within road_width / 2 + 1 m of the crossing's centre."""
    from scipy.spatial import cKDTree

    P = P or LONG
    n = max(int(np.ceil(route.length / step)), 1)
    s = np.arange(n + 1) * (route.length / n)
    xy = np.array([route.at(v)[:2] for v in s])
    xs, ys = P.street_lines()
    passes = []
    for x in xs:
        for y in ys:
            near = np.flatnonzero(np.hypot(xy[:, 0] - x, xy[:, 1] - y) < P.road_width / 2 + 1.0)
            passes.append(0 if len(near) == 0 else 1 + int(np.count_nonzero(np.diff(near) > 1)))
    passes = np.array(passes)
    again = np.zeros(len(xy), bool)
    for a, b in cKDTree(xy).query_pairs(1.5):
        if abs(s[b] - s[a]) >= gap_m:
            again[max(a, b)] = True
    return {"intersections": int((passes > 0).sum()), "intersections_passed_again": int((passes > 1).sum()),
            "max_passes": int(passes.max()), "revisited_m": round(float(again.sum()) * route.length / n, 1)}


def long_drive(n_frames: int | None = None, P: CityPreset | None = None, length_km: float | None = None):
    """Frames of the long drive without building the city: (route, T_world_lidar [n,4,4], spacing (m)).

    The preset's `frames` span the whole route (spacing = length / (frames - 1), ~1.09 m). Fewer frames
    keep that spacing and stop early (the first n frames of the same drive), more are spread over the
    whole route at a smaller spacing. length_km: a drive of about that length (`long_route`), its frames
    at the preset's spacing (3.7 km: 3400 frames); the frames before the serpentine's last corner are the
    serpentine's."""
    P = P or LONG
    if length_km is None:
        route = long_route(P)
        n_frames = int(n_frames or P.frames)
        spacing = route.length / (max(n_frames, P.frames) - 1)
        return route, _poses_at(route, [i * spacing for i in range(n_frames)]), spacing
    base = long_route(P).length / (P.frames - 1)
    route = long_route(P, max(round(float(length_km) * 1000.0 / base), 1) * base)
    full = int(np.floor(route.length / base + 1e-6)) + 1
    n_frames = int(n_frames or full)
    spacing = base if n_frames <= full else route.length / (n_frames - 1)
    return route, _poses_at(route, [i * spacing for i in range(n_frames)]), spacing


def lidar_poses(path: LoopPath, n_frames: int) -> np.ndarray:
    """[n,4,4] T_world_lidar evenly spaced over one loop (frame n would coincide with frame 0)."""
    return _poses_at(path, [i * path.length / n_frames for i in range(n_frames)])


def preset(small: bool = False, long: bool = False, layout: str = "grid"):
    """The preset generate_city uses: a CityPreset (grid: DEFAULT / SMALL / LONG) or a suburb.SuburbPreset."""
    if layout == "suburb":
        return suburb.SMALL if small else suburb.DEFAULT
    return LONG if long else SMALL if small else DEFAULT


def preset_drive(P, n_frames: int | None = None, layout: str = "grid", long: bool = False,
                 length_km: float | None = None):
    """The sensor's drive of a preset without building its scene: (path, T_world_lidar [n,4,4], spacing (m)).

    P: a CityPreset or SuburbPreset (`preset`); n_frames: default P.frames. The loops (grid, suburb) spread
    the frames evenly over one loop; long: `long_drive` (the city depends on the whole route, never on
    n_frames: a short run sees the same scene), with length_km a drive of about that length (default
    frames: the route's at the preset's spacing)."""
    if long and length_km is not None:
        return long_drive(n_frames, P, length_km)
    n_frames = int(n_frames or P.frames)
    if long:
        return long_drive(n_frames, P)
    if layout == "suburb":
        path = suburb.ring_path(P)
    else:
        path = LoopPath(P.street_x + P.lane_offset, P.street_y + P.lane_offset, P.corner_radius)
    return path, lidar_poses(path, n_frames), path.length / n_frames


def _poses_at(path, arclengths) -> np.ndarray:
    """[n,4,4] T_world_lidar at the given arc lengths (m) of a LoopPath / RoutePath."""
    poses = []
    for s in arclengths:
        x, y, yaw = path.at(s)
        pitch = 0.005 * np.sin(2 * np.pi * s / 23.0)  # a gently rocking vehicle (radians)
        roll = 0.004 * np.sin(2 * np.pi * s / 17.0)
        cy, sy_ = np.cos(yaw), np.sin(yaw)
        cp, sp = np.cos(pitch), np.sin(pitch)
        cr, sr = np.cos(roll), np.sin(roll)
        Rz = np.array([[cy, -sy_, 0], [sy_, cy, 0], [0, 0, 1]])
        Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        T = np.eye(4)
        T[:3, :3] = Rz @ Ry @ Rx
        T[:3, 3] = (x, y, SENSOR_H)
        poses.append(T)
    return np.stack(poses)


def beam_directions(beams, azimuth_steps: int) -> np.ndarray:
    """Unit ray directions in the LiDAR frame, beam-major: [beams*azimuth_steps, 3] float64. beams: the
    beams' elevations in degrees [B] (`jaxmap.synth.beams`), or a count of uniform beams."""
    if np.ndim(beams) == 0:
        beams = beam_patterns.elevations_deg("uniform", int(beams))
    el = np.deg2rad(np.asarray(beams, np.float64))
    az = 2 * np.pi * np.arange(azimuth_steps) / azimuth_steps
    el, az = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# ------------------------------------------------------------------------------------------------
# the static scene
# ------------------------------------------------------------------------------------------------


def _intervals(P: CityPreset):
    """Cell bounds along x and y: [-h, s0 - w, s0 + w, s1 - w, ..., h]; even cells are blocks, odd ones roads."""
    w = P.road_width / 2
    xs, ys = P.street_lines()
    hx, hy = P.half_extent, P.half_extent_y or P.half_extent
    xb = [-hx] + [b for s in xs for b in (s - w, s + w)] + [hx]
    yb = [-hy] + [b for s in ys for b in (s - w, s + w)] + [hy]
    return xb, yb


def _ground(P: CityPreset):
    """Road cells at z = 0, block cells raised to CURB_H, vertical curb faces between them."""
    xb, yb = _intervals(P)
    ncx, ncy = len(xb) - 1, len(yb) - 1  # cells
    hgt = lambda i, j: CURB_H if (i % 2 == 0 and j % 2 == 0) else 0.0  # noqa: E731
    mb = C.MeshBuilder()
    for i in range(ncx):
        for j in range(ncy):
            # tiles of <= 2 m keep triangles well shaped (float32 closest-point queries stay accurate)
            xs = np.linspace(xb[i], xb[i + 1], int(np.ceil((xb[i + 1] - xb[i]) / TILE)) + 1)
            ys = np.linspace(yb[j], yb[j + 1], int(np.ceil((yb[j + 1] - yb[j]) / TILE)) + 1)
            gx, gy = np.meshgrid(xs, ys, indexing="ij")
            v = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, hgt(i, j))], 1)
            nx, ny = len(xs), len(ys)
            a = (np.arange(nx - 1)[:, None] * ny + np.arange(ny - 1)[None, :]).ravel()
            f = np.concatenate([np.stack([a, a + ny, a + ny + 1], 1), np.stack([a, a + ny + 1, a + 1], 1)])
            mb.add((v, f))
    for i in range(ncx):
        for j in range(ncy):
            if hgt(i, j) == 0.0:
                continue
            # curb faces of this block towards lower neighbours (outward normals)
            x0, x1, y0, y1 = xb[i], xb[i + 1], yb[j], yb[j + 1]
            sides = []
            if i > 0:
                sides.append(((x0, y1), (x0, y0)))
            if i < ncx - 1:
                sides.append(((x1, y0), (x1, y1)))
            if j > 0:
                sides.append(((x0, y0), (x1, y0)))
            if j < ncy - 1:
                sides.append(((x1, y1), (x0, y1)))
            for (ax, ay), (bx, by) in sides:
                n = int(np.ceil(np.hypot(bx - ax, by - ay) / TILE))
                for k in range(n):
                    p0 = np.array([ax + (bx - ax) * k / n, ay + (by - ay) * k / n])
                    p1 = np.array([ax + (bx - ax) * (k + 1) / n, ay + (by - ay) * (k + 1) / n])
                    mb.add((np.array([[*p0, 0.0], [*p1, 0.0], [*p1, CURB_H], [*p0, CURB_H]]),
                            np.array([[0, 1, 2], [0, 2, 3]])))
    return mb.build()


def _blocks(P: CityPreset):
    """Blocks as (x0, x1, y0, y1, street sides {'-x','+x','-y','+y'}, has_parks), x-major order.

    has_parks: the block is in P.parks (default: the central block): its lots include park lots and it
    holds at least two lots along its long side."""
    xb, yb = _intervals(P)
    nx, ny = len(xb) - 1, len(yb) - 1
    parks = set(P.parks) or {(((nx + 1) // 2 - 1) // 2, ((ny + 1) // 2 - 1) // 2)}  # the central block
    out = []
    for i in range(0, nx, 2):
        for j in range(0, ny, 2):
            sides = set()
            if i > 0:
                sides.add("-x")
            if i < nx - 1:
                sides.add("+x")
            if j > 0:
                sides.add("-y")
            if j < ny - 1:
                sides.add("+y")
            out.append((xb[i], xb[i + 1], yb[j], yb[j + 1], sides, (i // 2, j // 2) in parks))
    return out


def _split(lo: float, hi: float, n: int, rng, gap=(1.5, 3.0)):
    """Split [lo, hi] into n intervals separated by random gaps."""
    if n <= 1:
        return [(lo, hi)]
    gaps = rng.uniform(*gap, size=n - 1)
    usable = hi - lo - gaps.sum()
    w = rng.uniform(0.7, 1.3, size=n)
    w = w / w.sum() * usable
    out, x = [], lo
    for k in range(n):
        out.append((x, x + w[k]))
        x += w[k] + (gaps[k] if k < n - 1 else 0)
    return out


def _street_edges(x0, x1, y0, y1, sides):
    """Curb lines of a block: (start [2], end [2], inward unit normal [2]) per street side."""
    edges = []
    if "-y" in sides:
        edges.append((np.array([x0, y0]), np.array([x1, y0]), np.array([0.0, 1.0])))
    if "+y" in sides:
        edges.append((np.array([x1, y1]), np.array([x0, y1]), np.array([0.0, -1.0])))
    if "-x" in sides:
        edges.append((np.array([x0, y1]), np.array([x0, y0]), np.array([1.0, 0.0])))
    if "+x" in sides:
        edges.append((np.array([x1, y0]), np.array([x1, y1]), np.array([-1.0, 0.0])))
    return edges


HALF_CAR = 0.9  # the moving cars (traffic) are <= 1.8 m wide


def traffic_lanes(P: CityPreset) -> tuple:
    """The grid's traffic lane centres as offsets right of the drive (m): (same direction, opposite). The
    parked cars' inner edge lies 1.1 + 0.925 m from the curb; the lanes keep 2.5 cm from it."""
    w = P.road_width / 2
    b = w - 1.1 - 0.925 - 0.025
    return b - HALF_CAR - P.lane_offset, -(b - HALF_CAR) - P.lane_offset


def _lane_samples(P: CityPreset, path, step: float):
    """Both traffic lanes every ~step metres: (centres [n,2], the largest moving car there [n,4,2]: 4.4 m x
    1.8 m, grown as the traffic planner grows it, by 0.3 m and 0.04 m)."""
    n = int(np.ceil(path.length / step))
    xy, yaw = [], []
    for d in traffic_lanes(P):
        for k in range(n + 1):
            x, y, a = path.at(k * path.length / n)
            xy.append((x + d * np.sin(a), y - d * np.cos(a)))
            yaw.append(a)
    xy = np.array(xy)
    return xy, traffic_mod.rect_corners(xy, np.array(yaw), (4.4 + 0.3, 2 * HALF_CAR + 0.04))


def build_city(P: CityPreset, seed: int, path):
    """The static scene: (vertices [V,3], faces [F,3], object id per face [F], Scene).

    path: the LoopPath / RoutePath driven; parked cars on it are left out."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 101]))
    scene = Scene()
    gid = scene.add(_ground(P), "ground")
    traj = path.samples(0.25)
    lanes = _lane_samples(P, path, 0.25)
    S = P.sidewalk

    def clear_of_path(poly, margin):
        # reject objects whose footprint (expanded by margin) contains a trajectory sample
        lo, hi = poly.min(0) - margin, poly.max(0) + margin
        return not np.any(np.all((traj >= lo) & (traj <= hi), axis=1))

    def clear_of_lanes(poly):
        # ... or overlaps the largest moving car anywhere along a traffic lane (the corners cut across the
        # intersections; on the straights the parked cars clear the lanes by 0.5 cm). Parked cars lie
        # along the streets: their footprint is the vertices' axis-aligned box.
        lo, hi = poly.min(0), poly.max(0)
        near = np.linalg.norm(lanes[0] - (lo + hi) / 2, axis=1) < 6.0
        box = np.array([lo, (hi[0], lo[1]), hi, (lo[0], hi[1])])
        return not traffic_mod.polys_overlap(lanes[1][near], box).any()

    for (x0, x1, y0, y1, sides, central) in _blocks(P):  # central: a block with park lots
        # ---- lots and buildings
        ix0 = x0 + (S if "-x" in sides else 0.5)
        ix1 = x1 - (S if "+x" in sides else 0.5)
        iy0 = y0 + (S if "-y" in sides else 0.5)
        iy1 = y1 - (S if "+y" in sides else 0.5)
        lx, ly = ix1 - ix0, iy1 - iy0
        along_x = lx >= ly
        long_len, short_len = (lx, ly) if along_x else (ly, lx)
        n_long = max(2 if central else 1, int(round(long_len / rng.uniform(6.5, 10.0))))
        n_short = 2 if short_len >= 16.0 else 1
        long_iv = _split(ix0 if along_x else iy0, ix1 if along_x else iy1, n_long, rng)
        short_iv = _split(iy0 if along_x else ix0, iy1 if along_x else ix1, n_short, rng)
        park = {}
        if central:
            for r in range(n_short):
                park[(int(rng.integers(n_long)), r)] = r
        for a, (l0, l1) in enumerate(long_iv):
            for b, (s0, s1) in enumerate(short_iv):
                lot = (l0, l1, s0, s1) if along_x else (s0, s1, l0, l1)
                if (a, b) in park:
                    _park(scene, lot, b, n_short, rng, along_x)
                    continue
                _building(scene, gid, lot, rng)
        # ---- trees, poles and signs along the curbs; parked cars on the road
        for p0, p1, nrm in _street_edges(x0, x1, y0, y1, sides):
            edge = p1 - p0
            length = float(np.linalg.norm(edge))
            u = edge / length
            s = rng.uniform(3.0, 6.0)
            k = 0
            while s < length - 3.0:
                xy = p0 + s * u + nrm * P.tree_from_curb
                add_tree(scene, xy, rng, max_r=min(1.8, S - P.tree_from_curb - 0.3), z0=CURB_H)
                gap = rng.uniform(8.0, 12.0)
                if k % 2 == 0 and s + gap / 2 < length - 3.0:
                    pxy = p0 + (s + gap / 2) * u + nrm * 0.4
                    add_pole(scene, pxy, u, rng)
                s += gap
                k += 1
            s = rng.uniform(1.0, 3.0)
            while s < length - 1.0 - 4.8:
                if rng.random() < 0.7:
                    mesh, L, W = car_mesh(p0 + (s + 2.4) * u - nrm * 1.1, float(np.arctan2(u[1], u[0]))
                                      + (np.pi if rng.random() < 0.5 else 0.0), rng)
                    if clear_of_path(mesh[0][:, :2], 0.6) and clear_of_lanes(mesh[0][:, :2]):
                        scene.add(mesh, "car")
                    s += 4.8 + rng.uniform(1.0, 3.0)
                else:
                    s += rng.uniform(3.0, 8.0)
    v, f, obj = scene.build()
    return v, f, obj, scene


def _building(scene: Scene, gid: int, lot, rng):
    x0, x1, y0, y1 = lot
    sb = rng.uniform(0.0, min(1.0, 0.12 * min(x1 - x0, y1 - y0)), size=4)  # setbacks
    x0, x1, y0, y1 = x0 + sb[0], x1 - sb[1], y0 + sb[2], y1 - sb[3]
    w, h = x1 - x0, y1 - y0
    if w < 2.0 or h < 2.0:
        return
    height = rng.uniform(6.0, 22.0)
    kind = rng.choice(["box", "rounded", "round"], p=[0.55, 0.25, 0.2])
    if kind == "round" and max(w, h) / min(w, h) > 2.0:
        kind = "rounded"
    if kind == "box":
        poly = C.rect(x0, y0, x1, y1)
    elif kind == "rounded":
        poly = C.rounded_rect(x0, y0, x1, y1, rng.uniform(0.25, 0.45) * min(w, h), n_corner=10)
    else:
        poly = C.ellipse((x0 + x1) / 2, (y0 + y1) / 2, w / 2, h / 2, n=64)
    scene.add(C.prism(poly, CURB_H, CURB_H + height, bottom=False, top=True), "building")
    scene.hidden.append((gid, inside_convex(poly, CURB_H - 0.01, CURB_H + height)))


def _park(scene: Scene, lot, row: int, n_rows: int, rng, along_x: bool):
    """An open lot with a tree, a fence of thin slats on its first street side and a railing on the other."""
    x0, x1, y0, y1 = lot
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    r = min(x1 - x0, y1 - y0) / 2 - 0.6
    if r > 0.8:
        add_tree(scene, (cx, cy), rng, max_r=min(r, 2.5), z0=CURB_H)
    # the lot's street sides: its low edge (-y, or -x) gets the fence, its high edge the railing
    lines = []
    if along_x:
        if row == 0:
            lines.append(("fence", (x0, y0), (x1, y0)))
        if row == n_rows - 1:
            lines.append(("rail", (x1, y1), (x0, y1)))
    else:
        if row == 0:
            lines.append(("fence", (x0, y1), (x0, y0)))
        if row == n_rows - 1:
            lines.append(("rail", (x1, y0), (x1, y1)))
    for kind, a, b in lines:
        a, b = np.asarray(a, float), np.asarray(b, float)
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        yaw = float(np.arctan2(u[1], u[0]))
        if kind == "fence":
            n = int((length - 0.1) // 0.12)
            for k in range(n):
                c = a + u * (0.1 + k * 0.12)
                scene.add(C.oriented_box(c, (0.05, 0.03), yaw, CURB_H, CURB_H + 1.2, bottom=False), "fence")
            mid = a + u * (0.1 + (n - 1) * 0.06)
            scene.add(C.oriented_box(mid, ((n - 1) * 0.12 + 0.05, 0.04), yaw, CURB_H + 1.2, CURB_H + 1.26),
                      "fence")
        else:
            n = max(2, int(length // 1.5) + 1)
            rr = 0.03
            for k in range(n):
                c = a + u * (0.15 + k * (length - 0.3) / (n - 1))
                scene.add(C.cylinder(c[0], c[1], rr, CURB_H, CURB_H + 1.0 - rr, n=12, bottom=False, top=True),
                          "railing")
            p0 = np.r_[a + u * 0.1, CURB_H + 1.0]
            p1 = np.r_[b - u * 0.1, CURB_H + 1.0]
            scene.add(C.cylinder_between(p0, p1, rr, n=12), "railing")


# ------------------------------------------------------------------------------------------------
# pedestrians (dynamic; not in the ground truth)
# ------------------------------------------------------------------------------------------------


def _pedestrian_boxes(P: CityPreset, seed: int, n_frames: int, step: float, block=None):
    """Per frame a list of (center_xy, yaw) for P.pedestrians boxes walking around a block's sidewalk:
    `block` (x0, x1, y0, y1), default the central block (centred on the origin)."""
    d = P.ped_from_curb
    if block is None:
        xb, yb = _intervals(P)
        hx, hy = xb[3] - d, yb[3] - d
    else:
        x0, x1, y0, y1 = block
        hx, hy = (x1 - x0) / 2 - d, (y1 - y0) / 2 - d
    square = LoopPath(hx, hy, 1e-3)
    shift = None if block is None else ((x0 + x1) / 2, (y0 + y1) / 2)
    return C.walkers(square, P.pedestrians, seed, 202, n_frames, step, shift)


def _pedestrian_mesh(peds):
    mb = C.MeshBuilder()
    for (x, y), yaw in peds:
        mb.add(C.oriented_box((x, y), (0.5, 0.4), yaw, CURB_H, CURB_H + 1.75, bottom=False))
    return mb.build()


# ------------------------------------------------------------------------------------------------
# the generator
# ------------------------------------------------------------------------------------------------


def generate_city(out_dir, *, seed: int = 0, small: bool = False, n_frames: int | None = None,
                  noise_m: float = 0.0, beams: int | str | None = None, azimuth_steps: int | None = None,
                  pedestrians: bool = False, long: bool = False, layout: str = "grid", traffic: int = 0,
                  realistic: str | tuple = (), lane_shift_m: float = 0.0, start_m: float = 0.0,
                  parking: bool = False, length_km: float | None = None) -> dict:
    """Write a synthetic LiDAR sequence (KITTI layout, see the module docstring) into out_dir.

    seed: everything (layout, sizes, noise) is deterministic from it.
    small: 40 m x 40 m scene, 64 frames 0.97 m apart, 32 x 512 beams (seconds); default 100 m x 100 m,
           130 frames 0.96 m apart, 64 x 1024 beams.
    long: 256 m x 200 m city, a 1115 m serpentine drive (not closed), 1025 frames 1.09 m apart, the
          default's 64 x 1024 beams and GT density (1 GB of scans; see `long_drive`).
    length_km: (long only) a drive of about that many km through the same city instead: the serpentine,
          then loops around groups of blocks over streets already driven, passing its intersections again
          (LONG_LOOPS, like KITTI's sequence 00), frames 1.09 m apart (3.7 km: 3400 frames, ~3.4 GB of
          scans, written one frame at a time); meta.json "trajectory" records its "length_km" and
          "revisits" (`route_revisits`). The scene differs from the serpentine's only where the longer route
          clears parked cars off its corners.
    n_frames: frames evenly spaced over the one closed loop (default per preset); with long, the first
              n_frames of the drive at the preset's 1.09 m (spread over the whole route if more; default
              1025, with length_km the route's frames).
    noise_m: std of Gaussian range noise (m).
    beams: the LiDAR's beams (default per preset): a count of uniform beams from -25 to +2 deg, or a real
           sensor's table by name (`jaxmap.synth.beams`: "hdl64", KITTI's two-block HDL-64E with per-beam
           jitter; "vlp32", a VLP-32C, dense near the horizon and sparse below); azimuth_steps: per turn
           (default per preset, or the named sensor's).
    pedestrians: add boxes walking around the central block (long: around the first block on the left
                 of the drive) (in the scans, not in the ground truth).
    layout: "grid" (the street grid above, the default) or "suburb" (`jaxmap.synth.suburb`: a curved
            ring boulevard with detached houses, ~130 m non-rectangular loop; with small, a smaller ring).
    traffic: N moving objects (~2/3 cars on the lanes, the rest pedestrians; `jaxmap.synth.traffic`) in the
             scans, never in the ground truth; written to moving_objects.json (grid and suburb, not long).
    parking: two more cars (also with traffic=0): one parked at the start that drives off mid-sequence
             (never in the ground truth, listed in moving_objects.json at every frame) and one that parks
             mid-sequence and stays (in the ground truth at its place, GT class "parked_car"; listed only
             while it moves): the ground truth is the static world at the end of the sequence.
    realistic: real-sensor artifacts, "all" or any of REALISTIC ("mixed,dropout,outliers,beam_offsets"; see
               the module docstring).
    lane_shift_m, start_m: a second drive through the same city (grid and small loops, not long or suburb):
               the vehicle drives the loop shifted outward by lane_shift_m (negative: towards the street's
               centre line; the corner radius changes with it) and starts start_m metres along it; the scene
               (parked cars included) is the one of the unshifted drive, so a map of one drive localises the
               other (`jaxmap localize`).
    The GT points (gt_points.ply) are samples at gt_density (1000 per m^2) of the static surfaces within
    1 m of an observation (any frame's scan, without noise or pedestrians), hidden surfaces removed, with
    normals and a class per point (CITY_CLASSES, names in meta.json "gt": "classes").
    Returns the stats written to meta.json, plus "elapsed_s" (not written, so files stay deterministic).
    """
    t_start = time.perf_counter()
    if small and long:
        raise ValueError("small and long are different presets; pick one")
    if layout not in LAYOUTS:
        raise ValueError(f"unknown city layout {layout!r}; choose from {', '.join(LAYOUTS)}")
    if layout != "grid" and long:
        raise ValueError("long is a grid preset; it does not combine with another layout")
    traffic = int(traffic)
    if traffic < 0:
        raise ValueError("traffic must be >= 0")
    if (traffic or parking) and long:
        raise ValueError("traffic and parking are not available with long (the grid and suburb loops only)")
    if length_km is not None:
        if not long:
            raise ValueError("length_km is the long drive's length; it needs long")
        length_km = float(length_km)
        if not (np.isfinite(length_km) and length_km > 0):
            raise ValueError(f"length_km must be a positive number of km, not {length_km:g}")
    if (traffic or parking) and (lane_shift_m or start_m):
        raise ValueError("traffic and parking follow the first drive's lanes; they do not combine with "
                         "lane_shift_m / start_m")
    modes = realistic_modes(realistic)
    P = preset(small, long, layout)
    if length_km is not None and not n_frames:  # (by default the route's frames, at the preset's spacing)
        n_frames = len(long_drive(None, P, length_km)[1])
    n_frames = int(n_frames or P.frames)
    pattern, count = beam_patterns.parse(beams)
    elev_deg = beam_patterns.elevations_deg(pattern, count or (P.beams if pattern == "uniform" else None), seed)
    beams = len(elev_deg)
    azimuth_steps = int(azimuth_steps or beam_patterns.AZIMUTH_STEPS.get(pattern, P.azimuth_steps))
    if n_frames < 1 or azimuth_steps < 1:
        raise ValueError("n_frames, beams and azimuth_steps must be >= 1")
    out_dir = os.fspath(out_dir)
    scan_dir = C.prepare_out_dir(out_dir, "velodyne", ".bin")

    path, T_wl, spacing = preset_drive(P, n_frames, layout=layout, long=long, length_km=length_km)
    ped_block = None
    if long:
        xb, yb = _intervals(P)
        ped_block = (xb[2], xb[3], yb[2], yb[3])  # left of the first leg, passed again on the second run
    V, F, obj, scene = suburb.build_suburb(P, seed, path) if layout == "suburb" else build_city(P, seed, path)
    if lane_shift_m or start_m:
        if long or layout != "grid":
            raise ValueError("lane_shift_m and start_m are for the grid loop (default and small presets)")
        if P.corner_radius + lane_shift_m <= 0.5:
            raise ValueError(f"lane_shift_m {lane_shift_m:g} leaves no corner (radius {P.corner_radius:g} m)")
        path = LoopPath(path.hx + lane_shift_m, path.hy + lane_shift_m, P.corner_radius + lane_shift_m)
        T_wl = _poses_at(path, [start_m + i * path.length / n_frames for i in range(n_frames)])
        spacing = path.length / n_frames
    Tr = kitti_tr()

    # ---- scans
    caster = C.Raycaster(V, F)
    dirs_s = beam_directions(elev_deg, azimuth_steps)
    if pedestrians and layout == "suburb":
        peds = suburb.pedestrian_boxes(P, seed, n_frames, 0.15 * spacing)
    else:
        peds = _pedestrian_boxes(P, seed, n_frames, 0.15 * spacing, ped_block) if pedestrians else None
    movers = _traffic_plan(P, layout, seed, traffic, path, scene, n_frames, spacing, parking) \
        if traffic or parking else []
    parker = next((k for k, o in enumerate(movers) if o["role"] == "parking"), None)
    refl_static = _reflectivity(scene.kinds, seed) if "dropout" in modes else None
    if movers and refl_static is not None:
        refl_movers = _reflectivity([o["kind"] for o in movers], seed, 506)
    if "beam_offsets" in modes:
        beam_off = np.random.default_rng(np.random.SeedSequence([seed, 514])).normal(0.0, BEAM_OFFSET_STD_M, beams)
        ray_beam = np.repeat(np.arange(beams), azimuth_steps)
    counts, moving_points = [], 0
    observed = _ObservedPoints(OBS_VOXEL_M)
    for i in range(n_frames):
        R, o = T_wl[i, :3, :3], T_wl[i, :3, 3]
        dirs_w = dirs_s @ R.T
        if refl_static is not None:
            t, nrm, pid = caster.cast(o, dirs_w, return_ids=True)
            refl = np.where(pid >= 0, refl_static[obj[np.maximum(pid, 0)]], 1.0)
        else:
            t, nrm = caster.cast(o, dirs_w)
        hit = np.isfinite(t) & (t <= MAX_RANGE)  # the static scene, noise free: what the GT must cover
        observed.add(o + dirs_w[hit] * t[hit, None])
        if peds is not None:
            tp, nrm_p = C.Raycaster(*_pedestrian_mesh(peds[i])).cast(o, dirs_w)
            closer = tp < t
            t = np.where(closer, tp, t)
            nrm = np.where(closer[:, None], nrm_p, nrm)
            if refl_static is not None:
                refl = np.where(closer, 0.5, refl)
        if movers:
            mv, mf, owner = traffic_mod.frame_mesh(movers, i)
            tm, nrm_m, pid_m = C.Raycaster(mv, mf).cast(o, dirs_w, return_ids=True)
            on_mover = tm < t
            if parker is not None and not movers[parker]["listed"][i]:  # parked: the end's static world
                on_parked = on_mover & (owner[np.maximum(pid_m, 0)] == parker) & (tm <= MAX_RANGE)
                observed.add(o + dirs_w[on_parked] * tm[on_parked, None])
            t = np.where(on_mover, tm, t)
            nrm = np.where(on_mover[:, None], nrm_m, nrm)
            if refl_static is not None:
                refl = np.where(on_mover, refl_movers[owner[np.maximum(pid_m, 0)]], refl)
        if modes:
            cos_abs = np.abs(np.einsum("ij,ij->i", nrm.astype(np.float64), dirs_w))
            t = _sensor_artifacts(t, cos_abs, refl if refl_static is not None else None, beams, azimuth_steps,
                                  modes, seed, i)
        valid = np.isfinite(t) & (t <= MAX_RANGE)
        t = t[valid]
        if "beam_offsets" in modes:
            t = np.maximum(t + beam_off[ray_beam[valid]], 0.0)
        if noise_m > 0:
            rng = np.random.default_rng(np.random.SeedSequence([seed, 303, i]))
            t = np.maximum(t + rng.normal(0.0, noise_m, size=t.shape), 0.0)
        pts = dirs_s[valid] * t[:, None]
        inten = np.abs(np.einsum("ij,ij->i", nrm[valid].astype(np.float64), dirs_w[valid]))
        if refl_static is not None:
            inten = refl[valid] * (0.3 + 0.7 * inten)
        write_scan_bin(os.path.join(scan_dir, f"{i:06d}.bin"), pts, np.clip(inten, 0.0, 1.0))
        counts.append(len(pts))
        if movers:
            moving_points += int(on_mover[valid].sum())
        if long and (i + 1) % 100 == 0:
            log.info("synth city: %d/%d frames (%.0f s)", i + 1, n_frames, time.perf_counter() - t_start)
    write_calib(os.path.join(out_dir, "calib.txt"), Tr)
    write_poses(os.path.join(out_dir, "poses.txt"), camera_poses_from_lidar(T_wl, Tr))
    ped_file = os.path.join(out_dir, "pedestrians.json")
    if peds is not None:
        with open(ped_file, "w") as f:
            json.dump({"size_xyz_m": [0.5, 0.4, 1.75], "base_z_m": CURB_H,
                       "frames": [[{"xy": C.rounded(p, 4), "yaw": round(float(y), 5)} for p, y in fr]
                                  for fr in peds]}, f)
    elif os.path.exists(ped_file):
        os.remove(ped_file)
    mov_file = os.path.join(out_dir, "moving_objects.json")
    if movers:
        with open(mov_file, "w") as f:
            json.dump(traffic_mod.to_json(movers, n_frames), f)
    elif os.path.exists(mov_file):
        os.remove(mov_file)

    # ---- ground truth: the static world at the end of the sequence (with the car that parked)
    classes = CITY_CLASSES
    if parker is not None:
        V, F, obj = _add_parked_car(scene, movers[parker])
        classes = CITY_CLASSES + (PARKED_CAR_CLASS,)
    write_mesh_ply(os.path.join(out_dir, "gt_mesh.ply"), V, F)
    # sampled in pieces of ~2M points (bounded memory), only faces that come within 1 m of an observation
    gt_pts, gt_nrm, gt_cls = _gt_points(V, F, obj, scene, P.gt_density, seed, observed.points())
    write_points_ply(os.path.join(out_dir, "gt_points.ply"), gt_pts, gt_nrm, gt_cls)

    kinds = {}
    for k in scene.kinds:
        kinds[k] = kinds.get(k, 0) + 1
    meta = {
        "scene": "city", "layout": layout, "seed": int(seed), "small": bool(small), "frames": n_frames,
        "points_per_frame": C.points_stats(counts),
        "extent": {"min": C.rounded(V.min(0), 3), "max": C.rounded(V.max(0), 3)},
        "sensor": {"type": "lidar", "beams": beams, "azimuth_steps": azimuth_steps, "beam_pattern": pattern,
                   "elevation_deg": [round(float(elev_deg[0]), 4), round(float(elev_deg[-1]), 4)],
                   "beam_elevations_deg": C.rounded(elev_deg, 4), "max_range_m": MAX_RANGE, "height_m": SENSOR_H,
                   "noise_m": float(noise_m)},
        "trajectory": ({"route_length_m": round(path.length, 3), "frame_spacing_m": round(spacing, 4),
                        "driven_length_m": round(spacing * (n_frames - 1), 3), "closed_loop": False,
                        "waypoints": C.rounded(_snake_waypoints(P) if length_km is None else path.waypoints, 3),
                        **({"length_km": length_km, "revisits": route_revisits(path, P)} if length_km is not None
                           else {})} if long else
                       {"loop_length_m": round(path.length, 3), "frame_spacing_m": round(spacing, 4),
                        "closed_loop": True, **({"lane_shift_m": float(lane_shift_m), "start_m": float(start_m)}
                                                if lane_shift_m or start_m else {})}) | {"motion": drive_stats(T_wl, closed=not long)},
        "calib_Tr": C.rounded(Tr[:3].reshape(-1), 12),
        "objects": kinds, "pedestrians": (P.pedestrians if pedestrians else 0),
        "gt": {"mesh_triangles": int(len(F)), "points": int(len(gt_pts)),
               "density_per_m2": P.gt_density, "surface_area_m2": round(float(C.mesh_area(V, F).sum()), 2),
               "near_observation_m": GT_NEAR_M, "classes": list(classes),
               "class_points": {c: int(n) for c, n in zip(classes, np.bincount(gt_cls, minlength=len(classes)))}},
    }
    if long:
        meta["long"] = True
    if movers:
        n_cars = sum(o["kind"] == "car" for o in movers)
        roles = {}
        for o in movers:
            roles[o["role"]] = roles.get(o["role"], 0) + 1
        meta["traffic"] = {"cars": n_cars, "pedestrians": len(movers) - n_cars, "roles": roles}
        if parking:
            meta["traffic"]["parking"] = _parking_meta(movers)
        meta["moving_points_share"] = round(moving_points / max(sum(counts), 1), 5)
    if modes:
        meta["sensor"]["realistic"] = list(modes)
    C.write_json(os.path.join(out_dir, "meta.json"), meta)
    elapsed = time.perf_counter() - t_start
    log.info("synth city (%s): %d frames, %.0f points/frame, %d GT points -> %s (%.1f s)", layout, n_frames,
             meta["points_per_frame"]["mean"], len(gt_pts), out_dir, elapsed)
    return dict(meta, elapsed_s=round(elapsed, 2), out_dir=out_dir)


def _traffic_plan(P, layout: str, seed: int, n: int, path, scene, n_frames: int, spacing: float,
                  parking: bool = False) -> list:
    """The moving objects of generate_city(traffic=n, parking=...) (`jaxmap.synth.traffic.plan` on this
    layout's lanes, curbs and sidewalks)."""
    parked = traffic_mod.footprints_of(scene, "car")
    obstacles = [fp for k in ("pole", "trunk", "sign") for fp in traffic_mod.footprints_of(scene, k)]
    ego_s = np.arange(n_frames) * spacing
    half_car = HALF_CAR
    if layout == "suburb":
        w = P.road_width / 2
        b = w - 1.1 - 0.925 - 0.025  # the parked cars' inner edge (outer curb), a margin
        # a straight car on the curved lane bulges towards the parked cars by its (grown) half length's
        # sagitta at the ring's sharpest bend (0.19 m on the default ring, 0.36 m on the small one)
        table = traffic_mod.PathTable(path)
        bend = float(np.abs(np.diff(table.yaw) / np.diff(table.s)).max())
        lane_same, lane_opp = b - half_car - (0.5 * (4.4 + 0.3)) ** 2 * bend / 2 - 0.03, -w + 1.5 + half_car
        loops, sides, crossings, through = [suburb.CurvePath(P, w + 1.3)], [], [], []
        curb_z = suburb.ground_height(P)
    else:
        w = P.road_width / 2
        lane_same, lane_opp = (d + P.lane_offset for d in traffic_lanes(P))  # (parked cars on both curbs)
        xb, yb = _intervals(P)
        d = P.ped_from_curb
        loops = [LoopPath(xb[3] - d, yb[3] - d, 0.5)]  # (corners rounder than the walkers' 0.35 m offsets)
        sides = [((xb[4] + d, yb[2] + d), (xb[4] + d, yb[3] - d)), ((xb[1] - d, yb[3] - d), (xb[1] - d, yb[2] + d)),
                 ((xb[3] - d, yb[4] + d), (xb[2] + d, yb[4] + d)), ((xb[2] + d, yb[1] - d), (xb[3] - d, yb[1] - d))]
        e = w + min(d, 1.5)
        crossings = []
        for sx in (1.0, -1.0):
            for sy in (1.0, -1.0):
                cx, cy = sx * P.street_x, sy * P.street_y
                crossings.append(((cx - e, sy * (P.street_y + w + 0.5)), (cx + e, sy * (P.street_y + w + 0.5))))
                crossings.append(((sx * (P.street_x + w + 0.5), cy - e), (sx * (P.street_x + w + 0.5), cy + e)))

        # the four streets of the loop, straight across the city and 55 m beyond it (cars come and go out
        # of the sensor's range), directed against the counter-clockwise drive; their lane: the drive's
        # opposite lane
        X, Y = xb[-1] + 55.0, yb[-1] + 55.0
        sx, sy = P.street_x, P.street_y
        through = [(p0, p1, -lane_opp) for p0, p1 in (((X, -sy), (-X, -sy)), ((sx, Y), (sx, -Y)),
                                                     ((-X, sy), (X, sy)), ((-sx, -Y), (-sx, Y)))]

        def curb_z(xy):
            i = np.searchsorted(xb, xy[:, 0]) - 1
            j = np.searchsorted(yb, xy[:, 1]) - 1
            return np.where((i % 2 == 0) & (j % 2 == 0), CURB_H, 0.0)
    off = P.lane_offset
    if layout == "suburb":
        lat = (0.35, -0.35)  # (the loop runs counter-clockwise around the ring: right = outward)
    else:  # the central block's walkers: two lines between the trees' trunks and the lots (right = to the curb)
        near = P.tree_from_curb + 0.4
        far = min(near + 0.5, P.sidewalk - 0.23)
        lat = (P.ped_from_curb - near, P.ped_from_curb - far)
    return traffic_mod.plan(n, seed, path, ego_s, spacing, lane_same=lane_same - off, lane_opposite=lane_opp - off,
                            parked=parked, ped_paths=sides, ped_loops=loops, crossings=crossings, curb_z=curb_z,
                            ped_loop_lat=lat, parking=parking, obstacles=obstacles, through_streets=through)


def traffic_of(seed: int = 0, traffic: int = 0, *, small: bool = False, layout: str = "grid",
               n_frames: int | None = None, parking: bool = False):
    """The moving objects generate_city(seed, small, layout, n_frames, traffic, parking) puts in the scans,
    without casting a scan: (objects (`jaxmap.synth.traffic.plan`), T_world_lidar [F,4,4], spacing (m))."""
    P = preset(small, False, layout)
    path, T_wl, spacing = preset_drive(P, n_frames, layout=layout)
    scene = (suburb.build_suburb(P, seed, path) if layout == "suburb" else build_city(P, seed, path))[3]
    return _traffic_plan(P, layout, seed, traffic, path, scene, len(T_wl), spacing, parking), T_wl, spacing


def _parking_meta(movers) -> dict:
    """meta.json's "traffic": "parking": per parking car its id in moving_objects.json, its place (x, y,
    yaw; world frame) and the frame it departs at / is parked from."""
    out = {}
    for k, o in enumerate(movers):
        if o["role"] == "leaving":
            out["leaving"] = {"id": k, "place_xy_yaw": C.rounded(o["poses"][0][[0, 1, 3]], 4),
                              "departs_at_frame": o["event_frame"]}
        elif o["role"] == "parking":
            out["parking"] = {"id": k, "place_xy_yaw": C.rounded(o["poses"][-1][[0, 1, 3]], 4),
                              "parked_from_frame": o["event_frame"]}
    return out


def _add_parked_car(scene: Scene, car: dict):
    """The static scene with the car that parked (its box at its last pose, kind "parked_car"; the ground
    cut away under it, as nothing sees it there): (vertices [V,3], faces [F,3], object id per face [F]).
    Changes `scene` (object 0 is the ground)."""
    x, y, z, yaw = car["poses"][-1]
    l, w, h = car["size"]
    box = C.oriented_box((x, y), (l, w), yaw, z, z + h, bottom=False)
    scene.parts[0] = _outside_footprint(scene.parts[0], box[0][:4, :2])
    scene.add(box, PARKED_CAR_CLASS)
    return scene.build()


def _outside_footprint(mesh, footprint):
    """The part of a surface (vertices [V,3], faces [F,3]) outside the vertical prism over a convex
    footprint [n,2]: its faces near the footprint cut along the footprint's sides
    (`trimesh.intersections.slice_faces_plane`), the pieces inside dropped."""
    from trimesh.intersections import slice_faces_plane

    v, f = np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1])
    poly = np.asarray(footprint, dtype=np.float64)
    if C.polygon_area2(poly) < 0:
        poly = poly[::-1]  # counter-clockwise: the right of each side is outside
    tri = v[f]
    lo, hi = poly.min(0), poly.max(0)
    near = np.all((tri[..., :2].max(1) >= lo) & (tri[..., :2].min(1) <= hi), axis=1)
    pieces, rest = [(v, f[~near])], (v, f[near])
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        normal, origin = np.array([b[1] - a[1], a[0] - b[0], 0.0]), np.array([a[0], a[1], 0.0])
        pieces.append(slice_faces_plane(*rest, normal, origin)[:2])
        rest = slice_faces_plane(*rest, -normal, origin)[:2]
    mb = C.MeshBuilder()
    for pv, pf in pieces:
        if len(pf):
            used, inv = np.unique(pf, return_inverse=True)
            mb.add((pv[used], inv.reshape(pf.shape)))
    return mb.build()


class _ObservedPoints:
    """World-frame scan points of all frames, thinned to one per voxel (bounded memory). The chunks are
    thinned together once those added since the last time outnumber the points kept then (and 4 M): each
    point is thinned again a bounded number of times on average, however long the drive (thinning the
    whole set every frame once it passed 4 M points made a 3.7 km drive's synthesis quadratic). The first
    point of each voxel is kept whatever the schedule, so the result does not depend on it."""

    def __init__(self, voxel_m: float):
        from jaxmap.metrics import voxel_thin

        self.voxel_m, self._thin = voxel_m, voxel_thin
        self.chunks, self.pending, self.kept = [], 0, 0

    def add(self, pts: np.ndarray) -> None:
        if len(pts) == 0:
            return
        self.chunks.append(self._thin(pts, self.voxel_m))
        self.pending += len(self.chunks[-1])
        if len(self.chunks) > 1 and self.pending > max(4_000_000, self.kept):
            self.chunks = [self._thin(np.concatenate(self.chunks), self.voxel_m)]
            self.kept, self.pending = len(self.chunks[0]), 0

    def points(self) -> np.ndarray:
        if not self.chunks:
            return np.zeros((0, 3))
        return self._thin(np.concatenate(self.chunks), self.voxel_m)


def _gt_points(V, F, obj, scene: Scene, density: float, seed: int, observed: np.ndarray,
               chunk: int = 2_000_000):
    """Uniform samples of the static mesh within GT_NEAR_M of an observed point, hidden samples (inside
    other solids) removed: (points [N,3] float32, normals [N,3] float32, classes [N] uint8), world frame.

    Only faces whose bounding sphere comes within GT_NEAR_M of an observation are sampled, in runs of
    consecutive faces holding ~chunk expected samples each, with their own seeds (bounded memory)."""
    from scipy.spatial import cKDTree

    empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.uint8))
    if len(observed) == 0:
        return empty
    tree = cKDTree(observed)
    tri = V[F]
    centre = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)
    d, _ = tree.query(centre, distance_upper_bound=float(radius.max()) + GT_NEAR_M, workers=-1)
    cand = np.flatnonzero(d <= radius + GT_NEAR_M)
    if len(cand) == 0:
        return empty

    def near(p):
        return tree.query(p, distance_upper_bound=GT_NEAR_M, workers=-1)[0] <= GT_NEAR_M

    obj_class = np.array([_KIND_CLASS.get(k, 255) for k in scene.kinds], dtype=np.uint8)
    expected = np.cumsum(C.mesh_area(V, F[cand]) * density)
    cuts = np.searchsorted(expected, np.arange(chunk, expected[-1], chunk))
    bounds = np.unique(np.r_[0, cuts, len(cand)])
    pts, nrm, cls = [], [], []
    for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        sub_seed = int(np.random.SeedSequence([seed, 404, k]).generate_state(1)[0])
        p, n, c = _visible_samples(V, F[cand[a:b]], obj[cand[a:b]], scene, density, sub_seed, near, obj_class)
        pts.append(p)
        nrm.append(n)
        cls.append(c)
    return np.concatenate(pts), np.concatenate(nrm), np.concatenate(cls)


def _visible_samples(V, F, obj, scene: Scene, density: float, seed: int, near=None, obj_class=None):
    """Samples of faces F [n,3] (object ids obj [n], non-decreasing) that pass near(points) (when given)
    and the hidden-tests of their objects: (points [N,3] float32, normals [N,3] float32, classes [N]
    uint8: obj_class of the object, or for the ground road / sidewalk / curb by normal and height)."""
    pts, nrm, fid = C.sample_surface(V, F, density, seed=seed, return_faces=True)
    if near is not None and len(pts):
        ok = near(pts)
        pts, nrm, fid = pts[ok], nrm[ok], fid[ok]
    # faces are grouped by object (in Scene order) and samples by face: each object's samples are one run
    sample_obj = obj[fid]
    keep = np.ones(len(pts), bool)
    by_x = {}  # object id -> (order of its samples by x, their sorted x)
    oids = np.array([oid for oid, _ in scene.hidden], dtype=sample_obj.dtype)  # (same dtype: no array copies)
    runs = zip(np.searchsorted(sample_obj, oids, "left"), np.searchsorted(sample_obj, oids, "right"))
    for (oid, inside), (a, b) in zip(scene.hidden, runs):
        if a == b:
            continue
        x_range = getattr(inside, "x_range", None)
        if x_range is not None and b - a > 10_000:
            # a large object (the ground, tested under every building): test only its samples within the
            # solid's x range (the same result; the long city has ~220 buildings over ~5M ground samples)
            if oid not in by_x:
                order = np.argsort(pts[a:b, 0], kind="stable")
                by_x[oid] = (order, pts[a:b, 0][order])
            order, xs = by_x[oid]
            sel = a + order[np.searchsorted(xs, x_range[0], "left"):np.searchsorted(xs, x_range[1], "right")]
        else:
            sel = np.arange(a, b)
        keep[sel[inside(pts[sel])]] = False
    pts, nrm, sample_obj = pts[keep], nrm[keep], sample_obj[keep]
    if obj_class is None:
        obj_class = np.array([_KIND_CLASS.get(k, 255) for k in scene.kinds], dtype=np.uint8)
    cls = obj_class[sample_obj]
    ground = cls == 255
    up = nrm[:, 2] > 0.5
    cls[ground & up & (pts[:, 2] < 0.5 * CURB_H)] = 0          # road
    cls[ground & up & (pts[:, 2] >= 0.5 * CURB_H)] = 1         # sidewalk (and the raised blocks / lots)
    cls[ground & ~up] = 2                                      # curb faces
    return pts.astype(np.float32), nrm, cls
