"""Moving traffic for the synthetic city (`generate_city(traffic=N, parking=True)`, `jaxmap synth city
--traffic N --parking`).

N moving objects, in the scans and never in the ground truth: about two thirds cars (boxes ~4.2 x 1.75 x
1.5 m) on the drive's lanes, the rest pedestrians (the pedestrian boxes, 0.5 x 0.4 x 1.75 m). Time: the
ego vehicle drives 10 m/s, so a frame lasts spacing / 10 m/s (0.1 s at the default's ~1 m spacing), and
speeds are given in m/s. The cars take turns at the roles ahead, oncoming, overtaking, oncoming:

* ahead: the ego's lane, same direction, ~10-11 m/s (the speed swinging by up to 0.8 m/s over 8-16 s),
  always >= 8 m ahead of the sensor: a car the sensor follows;
* oncoming: the opposite lane, opposite direction, ~7.5-11.5 m/s, the speed swinging likewise. On the
  grid they drive straight along one of the drive's four streets, across the city, timed to meet the
  sensor on it (coming from and going to 55 m beyond the city, out of its range); on the suburb's ring
  they drive the ring backwards;
* overtaking: follows the sensor in its lane 12-20 m behind at its speed, then speeds up (2-2.5 m/s^2)
  to 15-17 m/s, changes into the opposite lane (over 20 m) once within 16 m of the sensor, passes,
  changes back >= 12 m ahead of it and slows to 11-12.5 m/s. On the grid the overtaking cars are placed
  first, then the cars ahead, then the oncoming ones (on the ring: ahead, oncoming, overtaking, as an
  overtaking car sweeping the ring's opposite lane meets any car driving it backwards); a role that does
  not fit (60 draws) falls back to ahead, then oncoming (a small preset's lanes are too narrow to pass
  side by side: there oncoming cars give way to the cars ahead);
* pedestrians, 1.3-1.5 m/s, take turns at: crossing the drive's street mid-block ahead of the sensor
  (in the middle of the road 2.5-4.5 s before the sensor passes; where no crossing fits, just after it
  passed), walking around the central block's sidewalk (both directions, on two lines ~0.5 m apart),
  crossing the side streets at the drive's corners (grid, no traffic there), and walking along the
  outer sidewalks facing the drive (back and forth). The crossings pause 2-6 s on the sidewalk.

With `parking`, two more cars (before the N, from their own seed sequence), on free places by a curb of
the drive's street (1.1 m from the curb, like the static parked cars), the side with the free place:

* "leaving": parked at frame 0, drives off while the sensor approaches (12-30 m before it passes, 28-40 m
  on the sensor's side, where it pulls out ahead of it): from rest at 1.5-2.5 m/s^2 to 8-11 m/s, out of
  its place over 10 m, into the lane of its side (the sensor's lane, or the opposite one against the
  sensor's direction). It is never in the ground truth; its box is listed at every frame.
* "parking": drives in the lane of its side at 8-11 m/s, brakes at 1.5-2.5 m/s^2 and pulls into its
  place over its last 10 m, standing still there 15-35 m before the sensor passes, and stays. The ground
  truth is the static world at the END of the sequence, so it is in gt_mesh.ply / gt_points.ply at its
  place (its own class, "parked_car"); its box is listed only at the frames while it moves.

Every car moves like a car: its position is the integral of a speed with |acceleration| <= 2.5 m/s^2,
along a lateral offset from the path that changes smoothly with distance (a half cosine over 20 m for a
lane change, 10 m for parking), so it turns on radii >= 5 m (the corners' lanes included) and its yaw
is its direction of travel (also when it stands). Every candidate object is checked at every frame
against the static parked cars, the sensor (a car, or a pedestrian on the road, in the sensor's line
stays >= 8 m from it) and the objects already placed, and redrawn (up to 60 times, then left out, or
given another role) when it overlaps one. Randomness: `SeedSequence([seed, 606])` (traffic) and
`[seed, 607]` (parking) only, so the static scene and the files of the same seed without them do not
change.

The result is a list of dicts: kind ("car" / "pedestrian"), role (ahead, oncoming, overtaking,
leaving, parking; pedestrians: drive_crossing, loop, crossing, sidewalk), size (l, w, h), poses [F,4]
(x, y, z_base, yaw) in the world frame, listed [F] bool (the frames whose box goes to the file, where
the object moves), written as `moving_objects.json` ("jaxmap moving objects v1", with each object's role).
"""
from __future__ import annotations

import numpy as np

from jaxmap.synth import common as C

TAG = 606
PARKING_TAG = 607
EGO_MPS = 10.0
PED_SIZE = (0.5, 0.4, 1.75)
CAR_TRIES = PED_TRIES = 60
SAME_LANE_GAP_M = 8.0
CAR_GROW = (0.3, 0.04)        # a car's footprint grown (length, width) in the overlap tests
MAX_ACCEL = 2.5               # m/s^2, speeding up and braking
LANE_CHANGE_M = 20.0          # a lane change blends the lateral offset over this distance
PARK_MANOEUVRE_M = 10.0       # ... pulling out of / into a parking place
PARK_FROM_CURB_M = 1.1        # a parked car's centre line from the curb (the static parked cars')
STEP_M = 0.05                 # the path's table and the trajectories' arc-length resolution
ROLES = ("ahead", "oncoming", "overtaking", "oncoming")
FALLBACK = {"overtaking": ("ahead", "oncoming"), "ahead": ("oncoming",), "oncoming": ("ahead",)}
# the oncoming cars drive straight streets where the layout has them (grid): an overtaking car fits between
# them and goes first; on a ring (suburb) they drive it backwards and go before it (it rarely fits then)
PLACING_ORDER = {True: ("overtaking", "ahead", "oncoming"), False: ("ahead", "oncoming", "overtaking")}


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
    """Separating-axis test of convex polygons a [F,na,2] and b [F,nb,2] (or [nb,2]): overlap mask [F]
    (False where a polygon is absent: not finite)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.broadcast_to(np.asarray(b, dtype=np.float64), (len(a),) + np.shape(b)[-2:])
    out = np.isfinite(a).all(axis=(1, 2)) & np.isfinite(b).all(axis=(1, 2))
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


class StreetLine:
    """A straight street's centre line through p0 and p1 (world x, y), directed from p0 to p1 and
    extended beyond both (arc length s from p0, negative before it): `point(s, d)` as PathTable's."""

    def __init__(self, p0, p1):
        self.p0 = np.asarray(p0, dtype=np.float64)
        d = np.asarray(p1, dtype=np.float64) - self.p0
        self.length = float(np.linalg.norm(d))
        self.u = d / self.length

    def point(self, s, d):
        s, d = np.broadcast_arrays(np.asarray(s, dtype=np.float64), np.asarray(d, dtype=np.float64))
        x = self.p0[0] + s * self.u[0] + d * self.u[1]
        y = self.p0[1] + s * self.u[1] - d * self.u[0]
        return x, y, np.full(s.shape, np.arctan2(self.u[1], self.u[0]))

    def along(self, xy) -> np.ndarray:
        """Arc lengths [N] of the points xy [N,2] projected onto the line."""
        return (np.asarray(xy, dtype=np.float64) - self.p0) @ self.u

    def across(self, xy) -> np.ndarray:
        """Offsets [N] of the points xy [N,2] right of the line."""
        return (np.asarray(xy, dtype=np.float64) - self.p0) @ np.array([self.u[1], -self.u[0]])


class PathTable:
    """A closed reference path (LoopPath / CurvePath: `at(s)`, `length`) tabulated every STEP_M metres, for
    vectorised points beside it: arc lengths s [...] wrap around the loop."""

    def __init__(self, path, step: float = STEP_M):
        self.length = L = float(path.length)
        n = int(np.ceil(L / step))
        self.s = np.linspace(0.0, L, n + 1)
        xy_yaw = np.array([path.at(v) for v in self.s[:-1]], dtype=np.float64)
        xy_yaw = np.vstack([xy_yaw, xy_yaw[:1]])  # closed: s = L is s = 0
        self.x, self.y = xy_yaw[:, 0], xy_yaw[:, 1]
        self.yaw = np.unwrap(xy_yaw[:, 2])

    def at(self, s):
        """(x, y, yaw) arrays at arc lengths s."""
        s = np.mod(np.asarray(s, dtype=np.float64), self.length)
        return np.interp(s, self.s, self.x), np.interp(s, self.s, self.y), np.interp(s, self.s, self.yaw)

    def point(self, s, d):
        """(x, y, path yaw) of the points d metres right of the path at arc lengths s (broadcast)."""
        x, y, yaw = self.at(s)
        return x + d * np.sin(yaw), y - d * np.cos(yaw), yaw

    def right(self, s):
        """Unit vectors [..., 2] to the right of the path at arc lengths s."""
        _, _, yaw = self.at(s)
        return np.stack([np.sin(yaw), -np.cos(yaw)], -1)

    def rel(self, s, s_ref):
        """Arc length from s_ref to s, wrapped into [-L/2, L/2)."""
        return (np.asarray(s) - s_ref + self.length / 2) % self.length - self.length / 2


# ------------------------------------------------------------------------------------------------
# car-like motion: a speed along a smooth lateral offset from the path
# ------------------------------------------------------------------------------------------------


def _blend(u):
    """0 -> 1 as a half cosine over u in [0, 1] (zero slope at both ends)."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(u, 0.0, 1.0))


def lateral_profile(d0: float, moves=()):
    """d(x): the offset (m, right of the path) after x metres of path: d0, then for each (x_start, d_to,
    length) of `moves` a half-cosine change to d_to over `length` metres (curvature <= pi^2 |change| /
    (2 length^2) on a straight path)."""
    def d(x):
        x = np.asarray(x, dtype=np.float64)
        out, prev = np.full(x.shape, float(d0)), float(d0)
        for x0, d_to, length in moves:
            out = out + (d_to - prev) * _blend((x - x0) / length)
            prev = d_to
        return out
    return d


def drive(table, s0: float, sign: float, travelled, lateral, backwards: bool = False):
    """Poses [F,4] (x, y, 0, yaw) and path distances [F] of a car on the path `table` (a PathTable or a
    StreetLine: `point(s, d)`) that has driven travelled[i] metres (its
    own distance, monotonic in i) from arc length s0 at frame i, along the path's direction (sign +1) or
    against it (-1), lateral(x) metres right of the path after x metres of path. yaw: the trajectory's
    tangent (its direction of travel, also standing still); backwards=True: the car drives towards
    decreasing `travelled` (a car built back from where it stops)."""
    travelled = np.asarray(travelled, dtype=np.float64)
    span = 2.0 * float(travelled.max()) + 10.0  # (the inside of a turn: less path than car distance)
    x = np.arange(0.0, span + STEP_M, STEP_M)
    px, py, _ = table.point(s0 + sign * x, lateral(x))
    u = np.r_[0.0, np.cumsum(np.hypot(np.diff(px), np.diff(py)))]
    xk = np.interp(travelled, u, x)
    cx, cy, _ = table.point(s0 + sign * xk, lateral(xk))
    eps = 0.25
    ax, ay, _ = table.point(s0 + sign * (xk - eps), lateral(xk - eps))
    bx, by, _ = table.point(s0 + sign * (xk + eps), lateral(xk + eps))
    yaw = np.arctan2(by - ay, bx - ax) + (np.pi if backwards else 0.0)
    poses = np.stack([cx, cy, np.zeros_like(cx), (yaw + np.pi) % (2 * np.pi) - np.pi], 1)
    return poses, xk


def cruise(t, v: float, amp: float, period: float, phase: float):
    """Distance (m) driven by times t at the speed v + amp sin(2 pi t / period + phase) (|acceleration| <=
    2 pi amp / period)."""
    w = 2 * np.pi / period
    return v * t + amp / w * (np.cos(phase) - np.cos(w * np.asarray(t) + phase))


def from_rest(t, t0: float, accel: float, v: float):
    """Distance driven by times t by a car standing until t0, then speeding up at `accel` to v."""
    tau = np.clip(np.asarray(t, dtype=np.float64) - t0, 0.0, None)
    ta = v / accel
    return np.where(tau <= ta, 0.5 * accel * tau ** 2, 0.5 * v * ta + v * (tau - ta))


def to_rest(t, t1: float, brake: float, v: float):
    """Distance still to drive at times t by a car at v that brakes at `brake` to stand still at t1."""
    return from_rest(-np.asarray(t, dtype=np.float64), -t1, brake, v)


def speed_steps(v0: float, targets, accel: float, dt: float) -> np.ndarray:
    """Distances [F] driven at frames 0.. by a car at v0 that follows the target speeds [F], changing
    speed by at most accel * dt a frame."""
    v = np.empty(len(targets))
    cur = v0
    for i, tgt in enumerate(targets):
        cur += float(np.clip(tgt - cur, -accel * dt, accel * dt))
        v[i] = cur
    return np.r_[0.0, np.cumsum(v[:-1] * dt)]


# ------------------------------------------------------------------------------------------------
# the street: curbs, parking places and crossings along the drive
# ------------------------------------------------------------------------------------------------


def curb_distance(table: PathTable, s, side: float, curb_z, max_m: float = 9.0, step: float = 0.02):
    """Distance (m) from the path at arc lengths s [S] to the first raised ground (curb_z > 0) on its
    right (side +1) or left (-1); inf where there is none within max_m."""
    s = np.asarray(s, dtype=np.float64)
    x, y, _ = table.at(s)
    r = table.right(s) * side
    dist = np.arange(0.0, max_m, step)
    pts = np.stack([x, y], -1)[:, None, :] + dist[None, :, None] * r[:, None, :]
    up = (curb_z(pts.reshape(-1, 2)) > 0).reshape(len(s), len(dist))
    first = np.argmax(up, axis=1)
    return np.where(up.any(axis=1), dist[first], np.inf)


def _straight_curb(c: np.ndarray, k: int, tol: float) -> np.ndarray:
    """[S] the curb distances c [S] (every grid step of the loop) stay within tol over +-k grid steps."""
    ok = np.isfinite(c)
    cf = np.where(ok, c, 0.0)
    for j in range(1, k + 1):
        for sh in (j, -j):
            ok &= np.roll(ok, sh) & (np.abs(np.roll(cf, sh) - cf) <= tol)
    return ok


def parking_places(table: PathTable, curb_z, lanes, parked, step: float = 0.5):
    """Free parking places by the curbs of the drive's street: (s [P] arc length, side [P] +1 right / -1
    left, d [P] offset right of the path) where a 4.4 m x 1.8 m car, heading along the path 1.1 m from
    the curb (measured across the path), stands on the road (by 0.1 m) with the curb alongside its whole
    length (within 0.45 m of its curb side: no intersection, no corner), clear of the static parked cars
    (by 0.5 m along, 0.15 m across) and beside both traffic lanes' widest cars."""
    s = np.arange(0.0, table.length, step)
    out = []
    for side in (1.0, -1.0):
        c = curb_distance(table, s, side, curb_z)
        d = side * (np.where(np.isfinite(c), c, 0.0) - PARK_FROM_CURB_M)
        ok = np.isfinite(c)
        for lane in lanes:  # the largest moving car in either lane passes beside it
            ok &= np.abs(d - lane) >= 1.8 + CAR_GROW[1]
        x, y, yaw = table.point(s, d)
        xy = np.stack([x, y], -1)
        road = rect_corners(xy, yaw, (4.4 + 0.2, 1.8 + 0.2)).reshape(-1, 2)
        ok &= (curb_z(road) <= 0).reshape(len(s), 4).all(1)
        # (rect_corners: corners 0, 1 on the left of the heading, 2, 3 on its right)
        kerb = rect_corners(xy, yaw, (4.4, 1.8 + 0.9))[:, [2, 3] if side > 0 else [0, 1]].reshape(-1, 2)
        ok &= (curb_z(kerb) > 0).reshape(len(s), 2).all(1)
        idx = np.flatnonzero(ok)
        if len(idx) and len(parked):
            foot = rect_corners(xy[idx], yaw[idx], (4.4 + 1.0, 1.8 + 0.3))
            clear = np.ones(len(idx), bool)
            for fp in parked:
                clear &= ~polys_overlap(foot, fp)
            idx = idx[clear]
        out += [(s[i], side, d[i]) for i in idx]
    if not out:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    a = np.array(out)
    return a[:, 0], a[:, 1], a[:, 2]


def drive_crossings(table: PathTable, curb_z, obstacles, step: float = 1.0, onto_m: float = 0.8):
    """Segments (p0 [2], p1 [2], s) across the drive's street, right sidewalk to left sidewalk (onto_m
    metres beyond each curb), where both curbs run straight for +-2 m and the walkers' corridor (0.5 m
    wide, 0.3 m margin) is clear of the obstacles (footprints [4,2]: parked cars, poles, trunks)."""
    s = np.arange(0.0, table.length, step)
    cr, cl = curb_distance(table, s, 1.0, curb_z), curb_distance(table, s, -1.0, curb_z)
    ok = _straight_curb(cr, 2, 0.1) & _straight_curb(cl, 2, 0.1)
    x, y, yaw = table.at(s)
    r = table.right(s)
    out = []
    for i in np.flatnonzero(ok):
        q = np.array([x[i], y[i]])
        p0, p1 = q + r[i] * (cr[i] + onto_m), q - r[i] * (cl[i] + onto_m)
        mid = 0.5 * (p0 + p1)
        corridor = rect_corners(mid[None], np.array([np.arctan2(*(p1 - p0)[::-1])]),
                                (float(np.linalg.norm(p1 - p0)) + 0.6, 0.5 + 0.6))
        if any(polys_overlap(corridor, fp)[0] for fp in obstacles):
            continue
        out.append((p0, p1, float(s[i])))
    return out


# ------------------------------------------------------------------------------------------------
# the plan
# ------------------------------------------------------------------------------------------------


class _Planner:
    """The shared state of one plan: the path, the sensor's frames and the objects placed so far."""

    def __init__(self, path, ego_s, spacing, parked):
        self.table = PathTable(path)
        self.ego_s = np.asarray(ego_s, dtype=np.float64)
        self.F = len(self.ego_s)
        self.dt = spacing / EGO_MPS
        self.t = np.arange(self.F) * self.dt
        self.spacing = spacing
        ex, ey, eyaw = self.table.at(self.ego_s)
        self.ego = np.stack([ex, ey, eyaw], 1)  # [F,3] x, y, yaw of the sensor
        self.parked = list(parked)
        self.placed = []  # grown footprints [F,4,2] of the objects placed

    def ok(self, corners) -> bool:
        """The grown footprints [F,4,2] overlap no static parked car and no object placed at any frame."""
        return not any(polys_overlap(corners, pc).any() for pc in self.placed) and \
            not any(polys_overlap(corners, fp).any() for fp in self.parked)

    def clear_of_sensor(self, poses, size, line_half_width, frames=True) -> bool:
        """The object never holds the sensor (its box grown by 15 cm), and is never within
        SAME_LANE_GAP_M of it while in its line (laterally within line_half_width) at the frames
        selected by `frames` ([F] bool, default all)."""
        rel_xy = poses[:, :2] - self.ego[:, :2]
        c, s = np.cos(self.ego[:, 2]), np.sin(self.ego[:, 2])
        fwd = rel_xy[:, 0] * c + rel_xy[:, 1] * s
        lat = -rel_xy[:, 0] * s + rel_xy[:, 1] * c
        if np.any(frames & (np.abs(lat) < line_half_width) & (np.abs(fwd) < SAME_LANE_GAP_M)):
            return False
        along = rel_xy[:, 0] * np.cos(poses[:, 3]) + rel_xy[:, 1] * np.sin(poses[:, 3])
        across = -rel_xy[:, 0] * np.sin(poses[:, 3]) + rel_xy[:, 1] * np.cos(poses[:, 3])
        return not np.any((np.abs(along) < size[0] / 2 + 0.15) & (np.abs(across) < size[1] / 2 + 0.15))

    def place_car(self, role, size, poses, listed=None) -> dict | None:
        """The car as an object when it fits (sensor and overlaps), else None. The sensor's line counts
        only while the car moves (a parked car stands by the curb, not in a lane: the sensor's line
        sweeps across it in the corners)."""
        step = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1) > 1e-6
        if not self.clear_of_sensor(poses, size, size[1] / 2 + 0.1, frames=np.r_[step, False] | np.r_[False, step]):
            return None
        corners = rect_corners(poses[:, :2], poses[:, 3], (size[0] + CAR_GROW[0], size[1] + CAR_GROW[1]))
        if not self.ok(corners):
            return None
        self.placed.append(corners)
        return {"kind": "car", "role": role, "size": size, "poses": poses,
                "listed": np.ones(self.F, bool) if listed is None else listed}

    def sensor_reaches(self, s) -> float:
        """The frame (fractional) at which the sensor passes arc length s (the first pass from frame 0)."""
        return float(((s - self.ego_s[0]) % self.table.length) / self.spacing)


def _car_size(rng):
    return (float(rng.uniform(4.0, 4.4)), float(rng.uniform(1.7, 1.8)), float(rng.uniform(1.4, 1.6)))


def _moving_car(pl: _Planner, role: str, rng, lane_same: float, lane_opposite: float, through) -> dict | None:
    """One draw of a car in the role ahead / oncoming / overtaking; None when it does not fit. through:
    (StreetLine directed against the drive, offset of its lane right of it) pairs, [] where the oncoming
    cars drive the loop."""
    size = _car_size(rng)
    t, L = pl.t, pl.table.length
    if role in ("ahead", "oncoming"):
        amp, period, phase = rng.uniform(0.2, 0.8), rng.uniform(8.0, 16.0), rng.uniform(0.0, 2 * np.pi)
        if role == "ahead":
            v = rng.uniform(10.0, 11.0)
            s0 = pl.ego_s[0] + rng.uniform(SAME_LANE_GAP_M + 2.0, max(SAME_LANE_GAP_M + 4.0, 0.4 * L))
            table, sign, lane = pl.table, 1.0, lane_same
        elif through:  # straight along a street of the drive, meeting the sensor there
            v = rng.uniform(7.5, 11.5)
            line, lane = through[int(rng.integers(len(through)))]
            travelled = cruise(t, v, amp, period, phase)
            on_street = np.flatnonzero(np.abs(line.across(pl.ego[:, :2]) + lane) < 3.0)
            k_meet = int(rng.choice(on_street)) if len(on_street) else int(rng.integers(pl.F))
            s0 = line.along(pl.ego[k_meet:k_meet + 1, :2])[0] - travelled[k_meet] + rng.uniform(-10.0, 10.0)
            poses, x = drive(line, s0, 1.0, travelled, lateral_profile(lane))
            poses[(s0 + x < 0.0) | (s0 + x > line.length)] = np.nan  # (beyond the sensor's range)
            return pl.place_car(role, size, poses)
        else:
            v, table, sign, lane = rng.uniform(7.5, 11.5), pl.table, -1.0, lane_opposite
            s0 = rng.uniform(0.0, L)
        poses, _ = drive(table, s0, sign, cruise(t, v, amp, period, phase), lateral_profile(lane))
        return pl.place_car(role, size, poses)
    # overtaking: follow at the sensor's speed, speed up, pull out within 16 m of the sensor, pass in the
    # opposite lane, pull in >= 12 m ahead of it, slow down
    gap0, accel = rng.uniform(12.0, 20.0), rng.uniform(2.0, MAX_ACCEL)
    v_pass, v_after = rng.uniform(15.0, 17.0), rng.uniform(11.0, 12.5)
    k0 = int(rng.integers(0, max(1, pl.F - 60)))
    s0 = pl.ego_s[0] - gap0
    frames = np.arange(pl.F)
    targets = np.where(frames < k0, EGO_MPS, v_pass)
    travelled = speed_steps(EGO_MPS, targets, accel, pl.dt)
    _, x = drive(pl.table, s0, 1.0, travelled, lateral_profile(lane_same))
    close = np.flatnonzero((frames >= k0) & (pl.table.rel(s0 + x, pl.ego_s) >= -16.0))
    if not len(close):
        return None
    out = [(x[close[0]], lane_opposite, LANE_CHANGE_M)]
    _, x = drive(pl.table, s0, 1.0, travelled, lateral_profile(lane_same, out))
    ahead = np.flatnonzero((frames > close[0]) & (pl.table.rel(s0 + x, pl.ego_s) >= SAME_LANE_GAP_M + 4.0))
    if not len(ahead):
        return None  # (the pass would not end within the sequence)
    k_in = int(ahead[0])
    travelled = speed_steps(EGO_MPS, np.where(np.arange(pl.F) >= k_in, v_after, targets), accel, pl.dt)
    poses, _ = drive(pl.table, s0, 1.0, travelled,
                     lateral_profile(lane_same, out + [(x[k_in], lane_same, LANE_CHANGE_M)]))
    return pl.place_car(role, size, poses)


def _parking_car(pl: _Planner, role: str, rng, places, lanes, taken, through) -> dict | None:
    """One draw of the car that leaves its parking place ("leaving") or parks ("parking"); None when it
    does not fit. places: (s, side, d) arrays of `parking_places`; taken: (s, side) of the places already
    used; through: `_moving_car`'s. A car by the right curb drives the drive's loop in the sensor's lane
    (leaving: 28-40 m ahead of the sensor, or 10-20 m behind it, slower than it); one by the left curb
    drives a through street in the opposite lane (where there is one: else the loop backwards)."""
    s_all, side_all, d_all = places
    reach = np.array([pl.sensor_reaches(s) for s in s_all]) if len(s_all) else np.zeros(0)
    lead = (rng.uniform(12.0, 30.0) if role == "leaving" else rng.uniform(15.0, 35.0)) / pl.spacing
    free = np.ones(len(s_all), bool)
    for s0, side0 in taken:  # (one car's place is not the other's)
        free &= (side_all != side0) | (np.abs(pl.table.rel(s_all, s0)) > 6.0)
    if role == "leaving":  # parked for >= 5 frames, its place seen free for >= 5 frames
        fits = free & (reach - lead >= 5) & (reach <= pl.F - 5)
    else:  # moving for a quarter of the sequence, then parked before the sensor passes
        fits = free & (reach - lead >= pl.F / 4) & (reach <= pl.F - 3)
    idx = np.flatnonzero(fits)
    if not len(idx):
        return None
    j = int(rng.choice(idx))
    s_place, side, d_place = float(s_all[j]), float(side_all[j]), float(d_all[j])
    size = _car_size(rng)
    v, accel = rng.uniform(8.0, 11.0), rng.uniform(1.5, MAX_ACCEL)
    street, s_street, sign, lane = pl.table, s_place, side, (lanes[0] if side > 0 else lanes[1])
    if side < 0:  # the through street this curb lines, if any
        x, y, _ = pl.table.point(s_place, d_place)
        for line, line_lane in through:
            across = float(line.across(np.array([[x, y]]))[0])
            if abs(across - line_lane - (lanes[1] - d_place)) < 0.5:
                street, s_street, sign, lane, d_place = line, float(line.along(np.array([[x, y]]))[0]), 1.0, \
                    line_lane, across
                break
    if role == "leaving" and side > 0:
        if rng.random() < 0.5:  # pulling out ahead of the sensor
            lead = rng.uniform(28.0, 40.0) / pl.spacing
        else:  # pulling out behind it and following it, slower
            lead, v = -rng.uniform(10.0, 20.0) / pl.spacing, rng.uniform(8.0, 9.5)
        if not 5 <= reach[j] - lead <= pl.F - 5:
            return None
    t_event = (reach[j] - lead) * pl.dt
    if role == "leaving" and t_event + np.sqrt(2 * (size[0] + 1.0) / accel) + 1.0 > pl.t[-1]:
        return None  # (out of its place, by its length and 1 m, >= 1 s before the end)
    manoeuvre = lateral_profile(d_place, [(0.0, lane, PARK_MANOEUVRE_M)])
    if role == "leaving":
        poses, x = drive(street, s_street, sign, from_rest(pl.t, t_event, accel, v), manoeuvre)
        listed = None
    else:
        remaining = to_rest(pl.t, t_event, accel, v)
        poses, x = drive(street, s_street, -sign, remaining, manoeuvre, backwards=True)
        listed = remaining > 0
    if street is not pl.table:  # (absent beyond the street's ends: out of the sensor's range)
        s_car = s_street + (x if role == "leaving" else -x)
        poses[(s_car < 0.0) | (s_car > street.length)] = np.nan
    car = pl.place_car(role, size, poses, listed)
    if car is not None:
        car["place"] = (s_place, side)
        car["event_frame"] = int(np.ceil(t_event / pl.dt - 1e-9))
    return car


def plan(n: int, seed: int, path, ego_s, spacing: float, *, lane_same: float, lane_opposite: float,
         parked, ped_paths, ped_loops, crossings, curb_z, ped_loop_lat=(0.0, 0.0), parking: bool = False,
         obstacles=(), through_streets=()) -> list:
    """The moving objects (see the module docstring).

    path: the ego's closed path; ego_s [F] its arc length per frame; spacing: metres per frame (frame time
    spacing / EGO_MPS). lane_same / lane_opposite: lane centres as offsets right of the ego's path (m).
    parked: footprints [4,2] of the static parked cars. ped_loops: closed paths for the walkers around a
    block (`at`, `length`), walked on the lines ped_loop_lat (offsets right of the path: one per
    direction); ped_paths: open sidewalk segments (p0 [2], p1 [2]) walked back and forth; crossings:
    segments (p0, p1) across side streets, crossed with pauses; curb_z(xy [F,2]) -> ground height [F]
    (0 on the road, > 0 on sidewalks and blocks). parking: add the leaving and the parking car first.
    obstacles: footprints [4,2] of poles and trunks (the drive crossings keep clear of them).
    through_streets: (p0 [2], p1 [2], lane) for straight streets the drive follows for a while: the
    centre line directed against the drive there, from where a car comes into the sensor's range to
    where it leaves it (absent beyond), and the lane's offset right of it (the drive's opposite lane).
    The oncoming cars drive them straight through, meeting the sensor on them, instead of driving the
    drive's loop backwards (on a loop an overtaking car could never pass between them)."""
    pl = _Planner(path, ego_s, spacing, parked)
    through = [(StreetLine(p0, p1), lane) for p0, p1, lane in through_streets]
    objects = []
    if parking:
        rng = np.random.default_rng(np.random.SeedSequence([seed, PARKING_TAG]))
        places = parking_places(pl.table, curb_z, (lane_same, lane_opposite), parked)
        taken = []
        for role in ("leaving", "parking"):
            for _ in range(CAR_TRIES):
                car = _parking_car(pl, role, rng, places, (lane_same, lane_opposite), taken, through)
                if car is not None:
                    objects.append(car)
                    taken.append(car["place"])
                    break
            else:
                raise ValueError(f"no free parking place along the drive fits the {role} car; try another seed")
    rng = np.random.default_rng(np.random.SeedSequence([seed, TAG]))
    n_cars = int(round(2 * n / 3))
    roles = [ROLES[k % len(ROLES)] for k in range(n_cars)]
    for want in sorted(roles, key=PLACING_ORDER[bool(through)].index):
        for role in (want,) + FALLBACK[want]:
            car = next((c for c in (_moving_car(pl, role, rng, lane_same, lane_opposite, through)
                                    for _ in range(CAR_TRIES)) if c is not None), None)
            if car is not None:
                objects.append(car)
                break
    objects += _pedestrians(pl, n - n_cars, rng, ped_paths, ped_loops, crossings, curb_z, ped_loop_lat,
                            drive_crossings(pl.table, curb_z, list(parked) + list(obstacles)))
    return objects


def _walk_segment(p0, p1, v: float, pause_m: float, phase_m: float, F: int):
    """Poses [F,4] of a walker going back and forth between p0 and p1 at v metres a frame, pausing
    pause_m / v frames at each end (half a pause on either side of a turn), phase_m metres into its
    period (the period: 2 (|p1 - p0| + pause_m) metres, a pause counted as distance at v)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    seg = float(np.linalg.norm(p1 - p0))
    u = (p1 - p0) / seg
    half = seg + pause_m
    q = (phase_m + v * np.arange(F)) % (2 * half)
    back = q >= half
    q = np.where(back, q - half, q)
    a = np.clip(q - pause_m / 2, 0.0, seg)
    a = np.where(back, seg - a, a)
    xy = p0 + a[:, None] * u
    yaw = np.arctan2(u[1], u[0]) + np.where(back, np.pi, 0.0)
    return np.stack([xy[:, 0], xy[:, 1], np.zeros(F), yaw], 1)


def _pedestrians(pl: _Planner, n: int, rng, ped_paths, ped_loops, crossings, curb_z, ped_loop_lat, drive_x):
    groups = [[("drive_crossing", p) for p in drive_x], [("loop", p) for p in ped_loops],
              [("crossing", p) for p in crossings], [("sidewalk", p) for p in ped_paths]]
    groups = [g for g in groups if g]
    if not groups or n <= 0:
        return []
    sources = []  # round robin over the groups (then over each group's paths)
    for r in range(max(len(g) for g in groups)):
        sources += [g[r % len(g)] for g in groups]
    F, dt, objects = pl.F, pl.dt, []
    for k in range(n):
        src, data = sources[k % len(sources)]
        for _ in range(PED_TRIES):
            v = rng.uniform(1.3, 1.5) * dt
            if src == "drive_crossing":  # any of the drive's crossings, timed against the sensor
                p0, p1, s_c = drive_x[int(rng.integers(len(drive_x)))]
                if rng.random() < 0.5:
                    p0, p1 = p1, p0
                pause = rng.uniform(2.0, 6.0) * v / dt
                seg = float(np.linalg.norm(np.asarray(p1) - p0))
                k_mid = pl.sensor_reaches(s_c) - rng.uniform(2.5, 4.5) / dt  # mid-road before the sensor passes
                if k_mid < 1:
                    k_mid = pl.sensor_reaches(s_c) + rng.uniform(1.5, 3.0) / dt  # (or just after)
                poses = _walk_segment(p0, p1, v, pause, pause / 2 + seg / 2 - v * k_mid, F)
            elif src == "loop":
                sign = 1.0 if rng.random() < 0.5 else -1.0
                s0 = rng.uniform(0.0, data.length)
                lat = ped_loop_lat[0] if sign > 0 else ped_loop_lat[1]
                walk, s = _Lanes(data), s0
                poses = np.zeros((F, 4))
                for i in range(F):
                    x, y, yaw = walk.point(s, lat)
                    poses[i] = (x, y, 0.0, yaw if sign > 0 else yaw + np.pi)
                    s += sign * walk.advance(s, lat, v, sign)
            else:
                pause = 0.0 if src == "sidewalk" else rng.uniform(2.0, 6.0) * v / dt
                seg = float(np.linalg.norm(np.asarray(data[1], float) - data[0]))
                poses = _walk_segment(data[0], data[1], v, pause, rng.uniform(0.0, 2 * (seg + pause)), F)
            foot = rect_corners(poses[:, :2], poses[:, 3], PED_SIZE[:2]).reshape(-1, 2)
            poses[:, 2] = curb_z(foot).reshape(F, 4).max(1)  # (stepping up a curb: on it at once)
            corners = rect_corners(poses[:, :2], poses[:, 3], (PED_SIZE[0] + 0.1, PED_SIZE[1] + 0.1))
            if np.any(np.linalg.norm(poses[:, :2] - pl.ego[:, :2], axis=1) < 2.0):
                continue
            # on the road in front of (or behind) the sensor's car, 1.8 m wide: >= 8 m from it
            if not pl.clear_of_sensor(poses, PED_SIZE, 0.9 + 0.25 + 0.1, frames=poses[:, 2] <= 0.0):
                continue
            if not pl.ok(corners):
                continue
            pl.placed.append(corners)
            poses[:, 3] = (poses[:, 3] + np.pi) % (2 * np.pi) - np.pi
            objects.append({"kind": "pedestrian", "role": src, "size": PED_SIZE, "poses": poses,
                            "listed": np.ones(F, bool)})
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
    """moving_objects.json: each object's box at the frames it is listed at (null elsewhere)."""
    out = []
    for k, o in enumerate(objects):
        listed = o.get("listed", np.ones(n_frames, bool))
        poses = [None if not (ok and np.isfinite(p[0])) else C.rounded(p, 4) for p, ok in zip(o["poses"], listed)]
        out.append({"id": k, "kind": o["kind"], "role": o["role"], "size_xyz_m": C.rounded(o["size"], 4),
                    "poses": poses})
    return {"format": "jaxmap moving objects v1", "frames": int(n_frames), "objects": out}
