"""An indoor room seen by a pinhole depth camera, with exact ground truth.

The room (world frame: z up, floor at z = 0) is a 6 m x 5 m x 3 m box seen from inside (normals point
into the room), furnished with a table on thin legs, a chair with thin legs and back slats, a cabinet,
a sofa (L-shaped profile), a floor-to-ceiling pillar, a bin (cylinders), a ball (sphere), a floor lamp
(thin pole + spherical shade) and a wall shelf. A depth camera (default 320 x 240, fx = fy = 250)
circles the room once on an ellipse, looking mostly inward and a little ahead and down; the last frame
is one step before the first, so the trajectory closes a loop. Written in the depth layout:

    depth/000000.png   uint16 depth (z along the optical axis) in millimetres, 0 = no return
    intrinsics.txt     "fx fy cx cy"
    poses.txt          12 numbers a line, T_world_camera (camera: x right, y down, z forward)
    gt_mesh.ply        triangle mesh of the room and furniture (world frame)
    gt_points.ply      dense uniform samples of it (+ normals, + a uchar class per point: ROOM_CLASSES),
                       hidden surfaces removed (7000 per m^2, small 5000: the whole room is observed)
    meta.json          stats and parameters (deterministic: no timings)

Everything is deterministic from `seed` (furniture placement jitter, sizes, noise).
"""
from __future__ import annotations

import logging
import os
import time

import numpy as np

from jaxmap.io.depth import pixel_rays, write_depth_png, write_intrinsics
from jaxmap.io.kitti import write_poses
from jaxmap.io.pointcloud import write_mesh_ply, write_points_ply
from jaxmap.synth import common as C

log = logging.getLogger("jaxmap")

ROOM = (6.0, 5.0, 3.0)       # x, y, z size (m); the room spans [-3,3] x [-2.5,2.5] x [0,3]
MAX_DEPTH = 10.0             # m
DEPTH_SCALE = 1000.0         # png units per metre (millimetres)
DEFAULT_FRAMES = 120
SMALL_FRAMES = 10
GT_DENSITY = 7000.0          # samples per m^2 (one per ~1.4 cm^2)
SMALL_GT_DENSITY = 5000.0    # one per 2 cm^2
# per-point GT classes (uint8 index into ROOM_CLASSES); the "walls" box splits into floor / wall / ceiling
ROOM_CLASSES = ("floor", "wall", "ceiling", "table", "chair", "cabinet", "sofa", "pillar", "bin", "ball", "lamp",
                "shelf")
_KIND_CLASS = {"table": 3, "table_leg": 3, "chair": 4, "cabinet": 5, "sofa": 6, "pillar": 7, "bin": 8, "ball": 9,
               "lamp_pole": 10, "lamp_shade": 10, "shelf": 11, "books": 11}


def _yaw(R_yaw):
    c, s = np.cos(R_yaw), np.sin(R_yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def build_room(seed: int):
    """The static room: (vertices [V,3], faces [F,3], object id per face [F], kinds, hidden tests)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 401]))
    j = lambda s=0.08: rng.uniform(-s, s)  # noqa: E731  position jitter
    hx, hy, hz = ROOM[0] / 2, ROOM[1] / 2, ROOM[2]
    parts, kinds, hidden = [], [], []

    def add(mesh, kind):
        parts.append(mesh)
        kinds.append(kind)
        return len(parts) - 1

    # walls, floor and ceiling, seen from inside
    add(C.flip(C.box([-hx, -hy, 0.0], [hx, hy, hz])), "walls")

    # table: top + 4 thin legs
    tx, ty = 0.3 + j(), 0.0 + j()
    tl, tw, th = rng.uniform(1.3, 1.5), rng.uniform(0.75, 0.85), rng.uniform(0.72, 0.76)
    add(C.box([tx - tl / 2, ty - tw / 2, th], [tx + tl / 2, ty + tw / 2, th + 0.04]), "table")
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = tx + sx * (tl / 2 - 0.06), ty + sy * (tw / 2 - 0.06)
            add(C.box([cx - 0.025, cy - 0.025, 0.0], [cx + 0.025, cy + 0.025, th], bottom=False), "table_leg")

    # chair (local frame: seat centred at the origin, back at -x), facing the table
    chair = C.MeshBuilder()
    seat_h = 0.45
    chair.add(C.box([-0.22, -0.22, seat_h - 0.04], [0.22, 0.22, seat_h]))
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * 0.19, sy * 0.19
            chair.add(C.box([cx - 0.015, cy - 0.015, 0.0], [cx + 0.015, cy + 0.015, seat_h - 0.04], bottom=False))
    for k in range(4):  # back slats on the seat's back edge, then a top bar
        cy = -0.165 + k * 0.11
        chair.add(C.box([-0.22, cy - 0.015, seat_h], [-0.20, cy + 0.015, seat_h + 0.42], bottom=False))
    chair.add(C.box([-0.22, -0.22, seat_h + 0.42], [-0.19, 0.22, seat_h + 0.48]))
    chair_xy = (tx - tl / 2 - 0.45 + j(0.04), ty + j(0.1))
    add(C.transform_mesh(chair.build(), _yaw(j(0.25)), (chair_xy[0], chair_xy[1], 0.0)), "chair")

    # cabinet, 2 cm off the +x wall
    cy0 = -1.8 + j()
    add(C.box([hx - 0.62, cy0 - 0.5, 0.0], [hx - 0.02, cy0 + 0.5, rng.uniform(1.7, 1.9)], bottom=False), "cabinet")

    # sofa along the -y wall: an L profile (seat + back) extruded along x
    prof = np.array([[0.0, 0.0], [0.85, 0.0], [0.85, 0.45], [0.2, 0.45], [0.2, 0.85], [0.0, 0.85]])
    sofa_len = rng.uniform(1.8, 2.1)
    add(C.extrude_profile(prof, sofa_len, (j(0.15), -hy + 0.03, 0.0), np.pi / 2), "sofa")

    # floor-to-ceiling pillar and a bin (cylinders)
    add(C.cylinder(-2.2 + j(), 1.8 + j(), 0.15, 0.0, hz, n=32, bottom=False, top=False), "pillar")
    add(C.cylinder(-2.5 + j(), -2.0 + j(), rng.uniform(0.18, 0.22), 0.0, rng.uniform(0.45, 0.6), n=32,
                   bottom=False), "bin")

    # a ball on the floor
    r_ball = rng.uniform(0.2, 0.27)
    add(C.ellipsoid((1.3 + j(), 1.85 + j(), r_ball), (r_ball,) * 3, subdivisions=3), "ball")

    # floor lamp: thin pole entering a spherical shade
    lx, ly = -2.5 + j(), -0.5 + j()
    pole_top = rng.uniform(1.45, 1.6)
    add(C.cylinder(lx, ly, 0.015, 0.0, pole_top, n=12, bottom=False, top=False), "lamp_pole")
    shade_c = (lx, ly, pole_top + 0.12)
    add(C.ellipsoid(shade_c, (0.15, 0.15, 0.15), subdivisions=3), "lamp_shade")
    lamp_pole = len(parts) - 2
    hidden.append((lamp_pole, lambda p, c=np.asarray(shade_c): (((p - c) / (0.15 * 0.97)) ** 2).sum(1) < 1.0))

    # wall shelf on the +y wall (1 cm off it) with a row of thin boards standing on it
    sx0 = j(0.3)
    add(C.box([sx0 - 0.6, hy - 0.26, 1.5], [sx0 + 0.6, hy - 0.01, 1.53]), "shelf")
    for k in range(6):
        bx = sx0 - 0.5 + k * 0.07
        add(C.box([bx, hy - 0.22, 1.53], [bx + 0.02, hy - 0.04, 1.53 + rng.uniform(0.18, 0.26)], bottom=False),
            "books")

    # hidden surfaces: the floor under solids standing on it (and the ceiling above the pillar), the
    # sofa's bottom face lying on the floor
    walls = 0
    for i, k in enumerate(kinds):
        lo, hi = parts[i][0].min(0), parts[i][0].max(0)
        if k in ("cabinet", "sofa"):
            hidden.append((walls, lambda p, lo=lo, hi=hi: (p[:, 2] < 1e-6) & np.all(
                (p[:, :2] > lo[:2] + 1e-6) & (p[:, :2] < hi[:2] - 1e-6), axis=1)))
        if k in ("pillar", "bin"):
            c, r = (lo[:2] + hi[:2]) / 2, (hi[0] - lo[0]) / 2 * np.cos(np.pi / 32) - 1e-6
            hidden.append((walls, lambda p, c=c, r=r, top=hi[2]: ((p[:, 2] < 1e-6) | (p[:, 2] > top - 1e-6))
                           & (((p[:, :2] - c) ** 2).sum(1) < r * r)))
        if k == "sofa":
            hidden.append((i, lambda p: p[:, 2] < 1e-6))

    mb = C.MeshBuilder()
    obj = []
    for i, m in enumerate(parts):
        mb.add(m)
        obj.append(np.full(len(m[1]), i, np.int32))
    v, f = mb.build()
    return v, f, np.concatenate(obj), kinds, hidden


def camera_poses(n_frames: int) -> np.ndarray:
    """[n,4,4] T_world_camera on an ellipse around the room centre, one closed loop.

    Camera frame: x right, y down, z forward. The view direction points inward, turned 0.6 rad
    towards the direction of travel, pitched down ~14 degrees; height 1.3-1.5 m."""
    poses = []
    for i in range(n_frames):
        th = 2 * np.pi * i / n_frames
        pos = np.array([1.7 * np.cos(th), 1.2 * np.sin(th), 1.4 + 0.1 * np.sin(2 * th)])
        yaw = th + np.pi - 0.6
        pitch = -0.25 + 0.08 * np.sin(3 * th)
        fwd = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        T = np.eye(4)
        T[:3, :3] = np.stack([right, down, fwd], 1)
        T[:3, 3] = pos
        poses.append(T)
    return np.stack(poses)


def generate_room(out_dir, *, seed: int = 0, small: bool = False, n_frames: int | None = None,
                  noise_m: float = 0.0, width: int | None = None, height: int | None = None) -> dict:
    """Write a synthetic depth-camera sequence (depth layout, see the module docstring) into out_dir.

    seed: furniture jitter and noise are deterministic from it.
    small: 160 x 120 images and 10 frames (default 320 x 240, 120 frames).
    n_frames: frames evenly spaced over the one closed loop.  noise_m: std of Gaussian depth noise (m).
    width, height: image size in pixels; fx = fy = 250 * width / 320, principal point at the centre.
    Returns the stats written to meta.json, plus "elapsed_s" (not written, so files stay deterministic).
    """
    t_start = time.perf_counter()
    W = int(width or (160 if small else 320))
    H = int(height or (120 if small else 240))
    n_frames = int(n_frames or (SMALL_FRAMES if small else DEFAULT_FRAMES))
    if n_frames < 1 or W < 1 or H < 1:
        raise ValueError("n_frames, width and height must be >= 1")
    fx = fy = 250.0 * W / 320.0
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
    out_dir = os.fspath(out_dir)
    depth_dir = C.prepare_out_dir(out_dir, "depth", ".png")

    V, F, obj, kinds, hidden = build_room(seed)
    T_wc = camera_poses(n_frames)
    caster = C.Raycaster(V, F)
    rays_c = pixel_rays(W, H, fx, fy, cx, cy)  # z = 1, so the hit parameter is the depth z
    counts = []
    for i in range(n_frames):
        R, o = T_wc[i, :3, :3], T_wc[i, :3, 3]
        z, _ = caster.cast(o, rays_c @ R.T)
        valid = np.isfinite(z) & (z <= MAX_DEPTH)
        if noise_m > 0:
            rng = np.random.default_rng(np.random.SeedSequence([seed, 503, i]))
            z = z + rng.normal(0.0, noise_m, size=z.shape)
        mm = np.where(valid, np.clip(np.round(np.where(valid, z, 0.0) * DEPTH_SCALE), 1, 65535), 0)
        write_depth_png(os.path.join(depth_dir, f"{i:06d}.png"), mm.astype(np.uint16).reshape(H, W))
        counts.append(int(np.count_nonzero(mm)))
    write_intrinsics(os.path.join(out_dir, "intrinsics.txt"), fx, fy, cx, cy)
    write_poses(os.path.join(out_dir, "poses.txt"), T_wc)

    write_mesh_ply(os.path.join(out_dir, "gt_mesh.ply"), V, F)
    density = SMALL_GT_DENSITY if small else GT_DENSITY
    pts, nrm, fid = C.sample_surface(V, F, density, seed=seed * 7919 + 13, return_faces=True)
    keep = np.ones(len(pts), bool)
    for oid, inside in hidden:
        sel = np.flatnonzero(obj[fid] == oid)
        keep[sel[inside(pts[sel])]] = False
    pts, nrm, fid = pts[keep].astype(np.float32), nrm[keep], fid[keep]
    cls = np.array([_KIND_CLASS.get(k, 255) for k in kinds], dtype=np.uint8)[obj[fid]]
    box = cls == 255  # the room's own faces (normals point into the room)
    cls[box & (nrm[:, 2] > 0.5)] = 0
    cls[box & (nrm[:, 2] < -0.5)] = 2
    cls[box & (np.abs(nrm[:, 2]) <= 0.5)] = 1
    write_points_ply(os.path.join(out_dir, "gt_points.ply"), pts, nrm, cls)

    kind_counts = {}
    for k in kinds:
        kind_counts[k] = kind_counts.get(k, 0) + 1
    step = np.linalg.norm(T_wc[1 % n_frames, :3, 3] - T_wc[0, :3, 3]) if n_frames > 1 else 0.0
    meta = {
        "scene": "room", "seed": int(seed), "small": bool(small), "frames": n_frames,
        "points_per_frame": C.points_stats(counts),
        "extent": {"min": C.rounded(V.min(0), 3), "max": C.rounded(V.max(0), 3)},
        "room_size_m": list(ROOM),
        "sensor": {"type": "depth", "width": W, "height": H, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
                   "depth_scale": DEPTH_SCALE, "max_depth_m": MAX_DEPTH, "noise_m": float(noise_m)},
        "trajectory": {"closed_loop": True, "frame_step_m": round(float(step), 4)},
        "objects": kind_counts,
        "gt": {"mesh_triangles": int(len(F)), "points": int(len(pts)), "density_per_m2": density,
               "surface_area_m2": round(float(C.mesh_area(V, F).sum()), 3), "classes": list(ROOM_CLASSES),
               "class_points": {c: int(n) for c, n in zip(ROOM_CLASSES, np.bincount(cls, minlength=len(ROOM_CLASSES)))}},
    }
    C.write_json(os.path.join(out_dir, "meta.json"), meta)
    elapsed = time.perf_counter() - t_start
    log.info("synth room: %d frames of %dx%d, %.0f points/frame, %d GT points -> %s (%.1f s)", n_frames, W, H,
             meta["points_per_frame"]["mean"], len(pts), out_dir, elapsed)
    return dict(meta, elapsed_s=round(elapsed, 2), out_dir=out_dir)
