"""`jaxmap bench slam --suite`: `jaxmap slam` on streets scanned like real sensors, each against the map
that `jaxmap map` builds from the same scans with the true poses.

Five 130-frame streets with a loop (closed at frame ~120), each a `jaxmap synth city` of its own:

    city_hdl64              the default city's layout (seed 0), KITTI's two-block HDL-64E (no table of
                            the README reports it)
    grid_s2_hdl64_noise2cm  street grid, seed 2, HDL-64E, 2 cm range noise
    suburb_s3               the suburb layout, seed 3, 64 uniform beams
    grid_s4_b32             street grid, seed 4, 32 uniform beams
    grid_s5_vlp32           street grid, seed 5, a VLP-32C's beam table

Per street and variant (`--only NAME`: a name for the row, the `--set`s its settings; default `jaxmap`,
the shipped `city_slam`), each in its own process: `jaxmap slam city_slam` and, once per street,
`jaxmap map city` (the true-pose map). The row: ATE, its horizontal part, the trajectory's height error (mean, lowest) and
tilt error (mean, deg) that ATE's rigid fit hides, the map's C-L1 (standard protocol at 10 cm) and its
ratio to the true-pose map's, F-score, the map's mean signed error on road and sidewalk (cm), the
main-thread seconds of the loop corrections, and seconds a frame (wall, compiling included) against
the true-pose run's. Beside them the offline map: `jaxmap map city` over the same scans at the SLAM
run's final poses (`offline_street`), its C-L1 and ratio, which splits the online map's loss into what
the poses cost and what mapping while they moved cost. Mean and worst over the streets; everything to
OUT/slam_suite.json.
"""
from __future__ import annotations

import json
import os

import numpy as np

from jaxmap.bench.n3_suite import SUITE

# the default city's layout with the HDL-64E, and four of `jaxmap bench n3 --suite`'s clean cities
STREETS = {"city_hdl64": dict(seed=0, beams="hdl64"),
           **{name: SUITE[name] for name in ("grid_s2_hdl64_noise2cm", "suburb_s3", "grid_s4_b32", "grid_s5_vlp32")}}


def streets(root: str, only=None) -> dict:
    """{name: directory} of the streets under root (those in `only`, default all), synthesized where
    missing."""
    from jaxmap.bench import synthesized

    return synthesized(root, STREETS, only, what="streets")


def offline_street(data: str, slam_dir: str, out: str) -> str:
    """The street `data` with its poses replaced by the SLAM run's final trajectory (slam_dir's
    trajectory_kitti.txt, LiDAR poses in the world) in directory `out` (scans, calibration, ground
    truth and meta linked, not copied); returns out. KITTI's poses.txt holds camera poses."""
    from jaxmap.io import open_sequence
    from jaxmap.io.kitti import camera_poses_from_lidar, write_poses
    from jaxmap.slam.trajectory import read_pose_snapshot

    T = read_pose_snapshot(os.path.join(slam_dir, "trajectory_kitti.txt"))
    Tr = open_sequence(data).Tr   # (the identity without calib.txt)
    os.makedirs(out, exist_ok=True)
    for name in os.listdir(data):
        link = os.path.join(out, name)
        if name != "poses.txt" and not os.path.lexists(link):
            os.symlink(os.path.abspath(os.path.join(data, name)), link)
    write_poses(os.path.join(out, "poses.txt"), camera_poses_from_lidar(T, Tr))
    return out


def street_row(data: str, slam_dir: str, true: dict, offline: dict | None = None) -> dict:
    """One street's row from the SLAM run's directory, the true-pose run's summary and the offline run's
    (`offline_street`; None: not run)."""
    from jaxmap.io import open_sequence
    from jaxmap.slam.trajectory import ate, axis_errors, read_pose_snapshot

    gt = np.asarray(open_sequence(data).poses, np.float64)
    T = read_pose_snapshot(os.path.join(slam_dir, "trajectory_kitti.txt"))
    a, ax = ate(T, gt[:len(T)]), axis_errors(T, gt[:len(T)])
    with open(os.path.join(slam_dir, "metrics.json")) as f:
        m = json.load(f)
    with open(os.path.join(slam_dir, "slam.json")) as f:
        s = json.load(f)
    nan = float("nan")
    se, true_se = m.get("signed_error_cm", {}), true["metrics"].get("signed_error_cm", {})
    loops = [lp.get("map_s", 0.0) for lp in s.get("loops") or []]
    per_frame, true_per_frame = float(s.get("wall_s_per_frame", nan)), float(true.get("wall_s_per_frame", nan))
    true_cl1 = true["metrics"]["chamfer_l1_cm"]
    off_cl1 = offline["metrics"]["chamfer_l1_cm"] if offline else nan
    return {"ate_cm": 100 * a["rmse_m"], "xy_cm": 100 * ax["xy_rmse_m"], "dz_mean_cm": 100 * ax["dz_mean_m"],
            "dz_min_cm": 100 * ax["dz_min_m"],
            "tilt_deg": ax["tilt_mean_deg"], "chamfer_l1_cm": m["chamfer_l1_cm"], "f_score": m["f_score"],
            "true_chamfer_l1_cm": true_cl1, "ratio": m["chamfer_l1_cm"] / true_cl1,
            "offline_chamfer_l1_cm": off_cl1, "offline_ratio": off_cl1 / true_cl1,
            "road_cm": se.get("road", {}).get("mean_cm", nan),
            "sidewalk_cm": se.get("sidewalk", {}).get("mean_cm", nan),
            "true_road_cm": true_se.get("road", {}).get("mean_cm", nan),
            "loop_s": float(s.get("loop_map_s", 0.0)), "loop_max_s": float(max(loops, default=0.0)),
            "s_per_frame": per_frame, "true_s_per_frame": true_per_frame, "time_ratio": per_frame / true_per_frame}


COLUMNS = (("ATE cm", "ate_cm", "7.2f"), ("xy cm", "xy_cm", "6.2f"), ("dz mean", "dz_mean_cm", "+8.2f"), ("dz min", "dz_min_cm", "+7.2f"),
           ("tilt deg", "tilt_deg", "9.3f"), ("C-L1 cm", "chamfer_l1_cm", "8.2f"),
           ("true", "true_chamfer_l1_cm", "6.2f"),
           ("ratio", "ratio", "6.2f"), ("offline", "offline_chamfer_l1_cm", "8.2f"),
           ("off ratio", "offline_ratio", "9.2f"), ("F %", "f_score", "7.2f"), ("road", "road_cm", "+6.2f"),
           ("true road", "true_road_cm", "+10.2f"), ("sidewalk", "sidewalk_cm", "+9.2f"), ("loop s", "loop_s", "7.1f"),
           ("max loop s", "loop_max_s", "11.1f"), ("s/frame", "s_per_frame", "8.2f"), ("x true", "time_ratio", "7.2f"))


def print_rows(variant: str, rows: dict) -> None:
    """The table: one row per street, then the mean and the worst (the largest in size; the F-score's
    lowest)."""
    width = [int(f.lstrip("+").split(".")[0]) for _, _, f in COLUMNS]
    head = f"{'street (' + variant + ')':<26}" + "".join(f" {h:>{w}}" for (h, _, _), w in zip(COLUMNS, width))
    print(head)
    print("-" * len(head))

    def line(name, r):
        return f"{name:<26}" + "".join(" " + format(r[k], f) for _, k, f in COLUMNS)

    for name, r in rows.items():
        print(line(name, r))
    if len(rows) > 1:
        keys = [k for _, k, _ in COLUMNS]
        mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in keys}
        worst = {k: float(min(r[k] for r in rows.values()) if k == "f_score" else
                          max((r[k] for r in rows.values()), key=abs)) for k in keys}
        print(line(f"mean ({len(rows)})", mean))
        print(line(f"worst ({len(rows)})", worst))


def main_suite(args) -> int:
    """`jaxmap bench slam --suite [--only NAME] [--cities A,B] [--set K=V ...]`."""
    from jaxmap.bench import command_summary

    root = args.data if args.data not in (None, "data/room_noisy") else "data/slam_suite"
    only = [c.strip() for c in args.cities.split(",")] if getattr(args, "cities", None) else None
    data = streets(root, only)
    name = args.only or "jaxmap"
    sets = [a for o in (args.overrides or []) for a in ("--set", o)]
    out = args.out
    os.makedirs(out, exist_ok=True)
    cache = os.path.join(out, "xla_cache")
    path = os.path.join(out, "slam_suite.json")
    results = {}
    if os.path.isfile(path):
        with open(path) as f:
            results = json.load(f)
    rows = results.get(name, {})
    for street, d in data.items():
        true_dir, slam_dir = os.path.join(out, "true", street), os.path.join(out, name, street)
        true = results.get("true", {}).get(street)
        if true is None:   # the true-pose map, once per street (every variant is compared with it)
            print(f"[bench] slam suite: {street}, the true poses", flush=True)
            true = command_summary(["map", "city", "--data", d, "--out", true_dir, "--no-progress", "--overwrite"],
                                   cache)
            results.setdefault("true", {})[street] = true
        print(f"[bench] slam suite {name}: {street}", flush=True)
        command_summary(["slam", "city_slam", "--data", d, "--out", slam_dir, "--no-progress", "--overwrite", *sets],
                        cache)
        print(f"[bench] slam suite {name}: {street}, mapped again at the final poses", flush=True)
        offline = command_summary(["map", "city", "--data", offline_street(d, slam_dir, slam_dir + "_poses"),
                                   "--out", slam_dir + "_offline", "--no-progress", "--overwrite"], cache)
        rows[street] = street_row(d, slam_dir, true, offline)
        results[name] = rows
        with open(path, "w") as f:   # after every street: a stopped suite keeps what it measured
            json.dump(results, f, indent=1)
    print()
    print_rows(name, {s: rows[s] for s in STREETS if s in rows})
    print(f"\n[bench] written to {path}")
    return 0
