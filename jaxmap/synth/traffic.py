"""Moving traffic for the synthetic city (`generate_city(traffic=N)`, `jaxmap synth city --traffic N`).

N moving objects, in the scans and never in the ground truth: about two thirds cars (boxes ~4.2 x 1.75 x
1.5 m) on the drive's lanes, the rest pedestrians (the pedestrian boxes, 0.5 x 0.4 x 1.75 m) on the
sidewalks. Time: the ego vehicle drives 10 m/s, so a frame lasts spacing / 10 m/s (0.1 s at the default's
~1 m spacing), and speeds are given in m/s:

* cars ahead: the ego's lane, same direction, 10.3-11.5 m/s, always >= 8 m ahead of the sensor;
* oncoming cars: the opposite lane, opposite direction, 7-11 m/s;
* overtaking cars: start 10-16 m behind the sensor in its lane at 11.7-11.9 m/s, swing out into the
  opposite lane while within ~10 m of it and back in ahead. At <= 12 m/s an overtake takes ~100 frames
  in the opposite lane, so it rarely fits between the oncoming cars: a car whose role does not fit is
  drawn as oncoming, then as ahead, instead (and a small preset's lanes are too narrow to pass side
  by side: there oncoming cars give way to the cars ahead);
* pedestrians, 1.3-1.5 m/s: around the central block's sidewalk (both directions, on two lines ~0.5 m
  apart, between the trees and the lots), along the outer sidewalks facing the drive (back and forth),
  and (grid) across the side streets at the drive's corners (no traffic there), pausing on the sidewalk
  between crossings. The suburb layout has no crossings (its one road is the drive's).

Lanes keep clear of the parked cars (the grid: 1.1 m from the curb, ~1.85 m wide) and of each other
side by side; every candidate object is checked at every frame against the parked cars, the sensor
(a car in the sensor's lane stays >= 8 m from it) and the objects already placed, and redrawn (up to
60 times, then left out) when it overlaps one. Randomness: `SeedSequence([seed, 606])` only, so the
static scene and the files of the same seed without traffic do not change.

The result is a list of dicts: kind ("car" / "pedestrian"), size (l, w, h), poses [F,4] (x, y, z_base,
yaw) in the world frame, written as `moving_objects.json` ("jaxmap moving objects v1").
"""
from __future__ import annotations

import numpy as np

from jaxmap.synth import common as C

TAG = 606
EGO_MPS = 10.0
PED_SIZE = (0.5, 0.4, 1.75)
CAR_TRIES = PED_TRIES = 60
SAME_LANE_GAP_M = 8.0


# ------------------------------------------------------------------------------------------------
# geometry helpers
# ------------------------------------------------------------------------------------------------


def rect_corners(xy, yaw, size):
    """Corners [F,4,2] of rectangles centred at xy [F,2], length size[0] along yaw [F], width size[1]."""
    xy = np.asarray(xy, dtype=np.float64)
    yaw = np.asarray(yaw, dtype=np.float64)
    u = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    v = np.stack([-u[..., 1], u[..., 0]], -1)
    hl, hw = size[0] / 2, size[1] / 2
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
    return xy[..., None, :] + signs[:, 0, None] * hl * u[..., None, :] + signs[:, 1, None] * hw * v[..., None, :]


def polys_overlap(a, b) -> np.ndarray:
    """Separating-axis test of convex polygons a [F,na,2] and b [F,nb,2] (or [nb,2]): overlap mask [F]."""
    a = np.asarray(a, dtype=np.float64)
    b = np.broadcast_to(np.asarray(b, dtype=np.float64), (len(a),) + np.shape(b)[-2:])
    out = np.ones(len(a), bool)
    for P in (a, b):
        e = np.roll(P, -1, axis=1) - P
        axes = np.stack([-e[..., 1], e[..., 0]], -1)  # [F,n,2]
        pa = np.einsum("fkd,fnd->fkn", axes, a)
        pb = np.einsum("fkd,fnd->fkn", axes, b)
        sep = (pa.max(2) < pb.min(2)) | (pb.max(2) < pa.min(2))
        out &= ~sep.any(1)
    return out


def footprints_of(scene, kind: str):
    """Convex footprints [4,2] (minimum-area bounding rectangles of the xy vertices) of scene objects."""
    out = []
    for (v, _), k in zip(scene.parts, scene.kinds):
        if k != kind:
            continue
        xy = np.asarray(v)[:, :2]
        best = None
        for i in range(len(xy)):  # the car's edges include its axis direction; try each direction
            d = xy[(i + 1) % len(xy)] - xy[i]
            n = np.linalg.norm(d)
            if n < 1e-6:
                continue
            u = d / n
            w = np.array([-u[1], u[0]])
            a, b = xy @ u, xy @ w
            area = (a.max() - a.min()) * (b.max() - b.min())
            if best is None or area < best[0] - 1e-9:
                best = (area, u, w, a.min(), a.max(), b.min(), b.max())
        _, u, w, a0, a1, b0, b1 = best
        out.append(np.array([a0 * u + b0 * w, a1 * u + b0 * w, a1 * u + b1 * w, a0 * u + b1 * w]))
    return out


class _Lanes:
    """Points beside a reference path (LoopPath / CurvePath with `at(s)` and `length`), offset d metres to the
    right of its direction, moved at a given speed (the arc-length rate corrected for the offset)."""

    def __init__(self, path):
        self.path = path

    def point(self, s, d):
        x, y, yaw = self.path.at(s)
        return x + d * np.sin(yaw), y - d * np.cos(yaw), yaw

    def advance(self, s, d, step, sign=1.0):
        """The arc-length increment (>= 0, along sign) that moves the offset point by `step` metres (chord)."""
        p = np.array(self.point(s, d)[:2])
        ds = step
        for _ in range(4):
            q = np.array(self.point(s + sign * ds, d)[:2])
            ds *= step / max(np.linalg.norm(q - p), 1e-6)
        return ds


# ------------------------------------------------------------------------------------------------
# the plan
# ------------------------------------------------------------------------------------------------


def plan(n: int, seed: int, path, ego_s, spacing: float, *, lane_same: float, lane_opposite: float,
         parked, ped_paths, ped_loops, crossings, curb_z, ped_loop_lat=(0.0, 0.0)) -> list:
    """The moving objects (see the module docstring).

    path: the ego's path; ego_s [F] its arc length per frame; spacing: metres per frame (frame time
    spacing / EGO_MPS). lane_same / lane_opposite: lane centres as offsets right of the ego's path (m).
    parked: footprints [4,2] of the parked cars. ped_loops: closed paths for the walkers around a block
    (`at`, `length`), walked on the lines ped_loop_lat (offsets right of the path: one per direction);
    ped_paths: open sidewalk segments (p0 [2], p1 [2]) walked back and forth; crossings:
    segments (p0, p1) across a road, crossed with pauses; curb_z(xy [F,2]) -> z_base [F] of a pedestrian."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, TAG]))
    F = len(ego_s)
    dt = spacing / EGO_MPS
    lanes = _Lanes(path)
    L = path.length
    ego = np.array([lanes.point(s, 0.0) for s in ego_s])  # [F,3] x, y, yaw of the sensor
    n_cars = int(round(2 * n / 3))
    n_peds = n - n_cars
    placed = []  # (corners [F,4,2] inflated, ...)
    objects = []

    def ok(corners):
        for pc in placed:
            if polys_overlap(corners, pc).any():
                return False
        for fp in parked:
            if polys_overlap(corners, fp).any():
                return False
        return True

    # ---- cars
    kinds = ["ahead", "oncoming", "overtaking", "oncoming"]
    fallback = {"overtaking": ["oncoming", "ahead"], "oncoming": ["ahead"], "ahead": []}
    for k in range(n_cars):
        tries = [r for r in [kinds[k % len(kinds)]] + fallback[kinds[k % len(kinds)]] for _ in range(CAR_TRIES)]
        for role in tries:
            size = (float(rng.uniform(4.0, 4.4)), float(rng.uniform(1.7, 1.8)), float(rng.uniform(1.4, 1.6)))
            if role == "ahead":
                v = rng.uniform(10.3, 11.5) * dt
                s = ego_s[0] + rng.uniform(SAME_LANE_GAP_M + 4.0, 0.55 * L)
                sign, dfun = 1.0, (lambda rel: lane_same)
            elif role == "oncoming":
                v = rng.uniform(7.0, 11.0) * dt
                s = rng.uniform(0.0, L)
                sign, dfun = -1.0, (lambda rel: lane_opposite)
            else:
                v = rng.uniform(11.7, 11.9) * dt
                s = ego_s[0] - rng.uniform(10.0, 16.0)
                sign = 1.0

                def dfun(rel):  # swing out within ~10 m of the sensor (blend over 2 m either side)
                    w = np.clip((10.0 - abs(rel)) / 2.0, 0.0, 1.0)
                    return (1 - w) * lane_same + w * lane_opposite
            poses = np.zeros((F, 4))
            for i in range(F):
                rel = (s - ego_s[i] + L / 2) % L - L / 2
                d = dfun(rel)
                x, y, yaw = lanes.point(s, d)
                poses[i] = (x, y, 0.0, yaw if sign > 0 else yaw + np.pi)
                s += sign * lanes.advance(s, d, v, sign)
            corners = rect_corners(poses[:, :2], poses[:, 3], (size[0] + 0.3, size[1] + 0.04))
            # the sensor: outside every car; a car across its line (laterally within w/2 + 0.1 m) >= 8 m away
            rel_xy = poses[:, :2] - ego[:, :2]
            fwd = rel_xy[:, 0] * np.cos(ego[:, 2]) + rel_xy[:, 1] * np.sin(ego[:, 2])
            lat = -rel_xy[:, 0] * np.sin(ego[:, 2]) + rel_xy[:, 1] * np.cos(ego[:, 2])
            if np.any((np.abs(lat) < size[1] / 2 + 0.1) & (np.abs(fwd) < SAME_LANE_GAP_M)):
                continue
            along = rel_xy[:, 0] * np.cos(poses[:, 3]) + rel_xy[:, 1] * np.sin(poses[:, 3])
            across = -rel_xy[:, 0] * np.sin(poses[:, 3]) + rel_xy[:, 1] * np.cos(poses[:, 3])
            if np.any((np.abs(along) < size[0] / 2 + 0.15) & (np.abs(across) < size[1] / 2 + 0.15)):
                continue  # the sensor inside the car (grown by 15 cm)
            if not ok(corners):
                continue
            placed.append(corners)
            poses[:, 3] = (poses[:, 3] + np.pi) % (2 * np.pi) - np.pi
            objects.append({"kind": "car", "role": role, "size": size, "poses": poses})
            break

    # ---- pedestrians
    groups = [[("loop", p) for p in ped_loops], [("cross", p) for p in crossings], [("side", p) for p in ped_paths]]
    groups = [g for g in groups if g]
    sources = []  # round robin over the groups (then over each group's paths)
    for r in range(max(len(g) for g in groups)):
        sources += [g[r % len(g)] for g in groups]
    for k in range(n_peds):
        src, data = sources[k % len(sources)]
        for _ in range(PED_TRIES):
            v = rng.uniform(1.3, 1.5) * dt
            poses = np.zeros((F, 4))
            if src == "loop":
                sign = 1.0 if rng.random() < 0.5 else -1.0
                s0 = rng.uniform(0.0, data.length)
                lat = ped_loop_lat[0] if sign > 0 else ped_loop_lat[1]
                walk, s = _Lanes(data), s0
                for i in range(F):
                    x, y, yaw = walk.point(s, lat)
                    poses[i] = (x, y, 0.0, yaw if sign > 0 else yaw + np.pi)
                    s += sign * walk.advance(s, lat, v, sign)
            else:
                p0, p1 = np.asarray(data[0], float), np.asarray(data[1], float)
                seg = float(np.linalg.norm(p1 - p0))
                u = (p1 - p0) / seg
                pause = 0.0 if src == "side" else rng.uniform(2.0, 6.0)  # seconds at each end
                period = 2 * (seg + pause * v / dt)  # metres walked (a pause counts as distance at v)
                ph = rng.uniform(0.0, period)
                for i in range(F):
                    q = (ph + v * i) % period
                    half = period / 2
                    back = q >= half
                    q = q - half if back else q
                    a = np.clip(q - pause * v / dt / 2, 0.0, seg)  # pause half at each end
                    a = seg - a if back else a
                    xy = p0 + a * u
                    yaw = np.arctan2(u[1], u[0]) + (np.pi if back else 0.0)
                    poses[i] = (xy[0], xy[1], 0.0, yaw)
            foot = rect_corners(poses[:, :2], poses[:, 3], PED_SIZE[:2]).reshape(-1, 2)
            poses[:, 2] = curb_z(foot).reshape(F, 4).max(1)  # (stepping up a curb: on it at once)
            corners = rect_corners(poses[:, :2], poses[:, 3], (PED_SIZE[0] + 0.1, PED_SIZE[1] + 0.1))
            if np.any(np.linalg.norm(poses[:, :2] - ego[:, :2], axis=1) < 2.0):
                continue
            if not ok(corners):
                continue
            placed.append(corners)
            poses[:, 3] = (poses[:, 3] + np.pi) % (2 * np.pi) - np.pi
            objects.append({"kind": "pedestrian", "role": src, "size": PED_SIZE, "poses": poses})
            break
    return objects


def frame_mesh(objects, i: int):
    """Boxes of the objects at frame i: (vertices, faces, object index per face)."""
    mb = C.MeshBuilder()
    owner = []
    for k, o in enumerate(objects):
        x, y, z, yaw = o["poses"][i]
        if not np.isfinite(x):
            continue
        l, w, h = o["size"]
        m = C.oriented_box((x, y), (l, w), yaw, z, z + h, bottom=False)
        mb.add(m)
        owner.append(np.full(len(m[1]), k, np.int64))
    v, f = mb.build()
    return v, f, (np.concatenate(owner) if owner else np.zeros(0, np.int64))


def to_json(objects, n_frames: int) -> dict:
    out = []
    for k, o in enumerate(objects):
        poses = [None if not np.isfinite(p[0]) else C.rounded(p, 4) for p in o["poses"]]
        out.append({"id": k, "kind": o["kind"], "size_xyz_m": C.rounded(o["size"], 4), "poses": poses})
    return {"format": "jaxmap moving objects v1", "frames": int(n_frames), "objects": out}
