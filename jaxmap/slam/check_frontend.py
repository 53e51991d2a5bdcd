"""Check the SLAM front end on synthetic sequences: odometry alone vs front end with loop closure.

    python -m jaxmap.slam.check_frontend [--scene room|city|both] [--frames N] [--noise M] [--out DIR]

Generates the sequence (room: `generate_room(small=True, n_frames=40, noise_m=0.005)`; city:
`generate_city(small=True, noise_m=0.02)`, 64 frames 0.97 m apart at 10 Hz), runs the front end's
odometry alone (`make_odometry`: ICP on the room, KISS-ICP on the city) and the `FrontEnd`, and prints the ATE of both against the ground truth, the loops found, the per-frame
timings, and a false-loop check (two different places must be rejected by `loops.verify`).
"""
from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time

import numpy as np

from jaxmap.geometry import se3_inverse
from jaxmap.io import open_sequence
from jaxmap.slam.frontend import FrontEnd, FrontEndConfig
from jaxmap.slam.loops import verify
from jaxmap.slam.odometry import Scan, make_odometry
from jaxmap.slam.trajectory import ate


def run_scene(scene: str, out_dir: str, frames: int | None, noise: float | None) -> dict:
    """Generate `scene` into out_dir, run odometry and the front end; returns the figures."""
    if scene == "room":
        from jaxmap.synth.room import generate_room

        generate_room(out_dir, small=True, n_frames=frames or 40, noise_m=0.005 if noise is None else noise)
        cfg = FrontEndConfig()
    else:
        from jaxmap.synth.city import generate_city

        generate_city(out_dir, small=True, n_frames=frames, noise_m=0.02 if noise is None else noise)
        cfg = FrontEndConfig.lidar()
    seq = open_sequence(out_dir)
    frames_pts = [f.points for f in seq]
    gt = np.asarray(seq.poses)

    odo = make_odometry(cfg.odometry, gt[0])
    t0 = time.perf_counter()
    odo_poses = np.stack([odo.step(p).pose for p in frames_pts])
    odo_s = (time.perf_counter() - t0) / len(frames_pts)

    fe = FrontEnd(cfg, gt[0])
    t0 = time.perf_counter()
    results = [fe.add_frame(p) for p in frames_pts]
    fe_s = (time.perf_counter() - t0) / len(frames_pts)
    traj = fe.trajectory()

    # false loop: frame 0 against the frame farthest along the loop, claimed to be at the same pose
    far = len(frames_pts) // 2
    a, b = Scan(frames_pts[0], cfg.odometry), Scan(frames_pts[far], cfg.odometry)
    false = verify(a.points, a.normals, b.points, b.normals, np.eye(4), cfg.loops)
    # true revisit: frame 0 against the last frame (next to it), from the ground-truth relative pose
    c = Scan(frames_pts[-1], cfg.odometry)
    true = verify(a.points, a.normals, c.points, c.normals, se3_inverse(gt[-1]) @ gt[0], cfg.loops)
    return {
        "scene": scene, "frames": len(frames_pts),
        "odometry_s_per_frame": odo_s, "frontend_s_per_frame": fe_s,
        "ate_odometry": ate(odo_poses, gt), "ate_frontend": ate(traj, gt),
        "ate_odometry_se3": ate(odo_poses, gt, "se3"), "ate_frontend_se3": ate(traj, gt, "se3"),
        "loops": list(fe.loops), "optimizations": sum(r.optimized for r in results),
        "odometry_failures": sum(not r.odometry_ok for r in results),
        "false_loop": (false.accepted, false.reason), "true_revisit": (true.accepted, true.reason),
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=("room", "city", "both"), default="both")
    ap.add_argument("--frames", type=int, default=None, help="frames per sequence (default: room 40, city 64)")
    ap.add_argument("--noise", type=float, default=None, help="sensor noise (m) (default: room 0.005, city 0.02)")
    ap.add_argument("--out", default=None, help="where to write the sequences (default: a temporary dir)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    scenes = ("room", "city") if args.scene == "both" else (args.scene,)
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            out = os.path.join(args.out or tmp, scene)
            r = run_scene(scene, out, args.frames, args.noise)
            print(f"== {scene}: {r['frames']} frames")
            print(f"   time per frame: odometry {1000 * r['odometry_s_per_frame']:.0f} ms, "
                  f"front end {1000 * r['frontend_s_per_frame']:.0f} ms")
            for key in ("ate_odometry", "ate_frontend", "ate_odometry_se3", "ate_frontend_se3"):
                a = r[key]
                print(f"   {key:18s} rmse {100 * a['rmse_m']:.2f} cm, max {100 * a['max_m']:.2f} cm, "
                      f"rot rmse {a['rot_rmse_deg']:.3f} deg")
            print(f"   loops (keyframe pairs) {r['loops']}, optimisations {r['optimizations']}, "
                  f"odometry failures {r['odometry_failures']}")
            print(f"   false loop accepted: {r['false_loop'][0]} ({r['false_loop'][1]})")
            print(f"   true revisit accepted: {r['true_revisit'][0]} ({r['true_revisit'][1]})")


if __name__ == "__main__":
    main()
