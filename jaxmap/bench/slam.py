"""`jaxmap bench slam`: loop closure end to end on the noisy synthetic room (default, data/room_noisy,
configs/room_slam.yaml) or, with `--data data/city_small_noisy` (any KITTI-layout directory), on the
small city with LiDAR noise (configs/city_slam.yaml), in one run.

Runs `jaxmap slam` (the config's odometry: ICP on the room, KISS-ICP on the city; loop verification,
open3d pose graph, remapping of the latent map at each loop), then builds the latent map of the same
frames with the ground-truth poses and with the odometry-only poses (all frames: where the SLAM run
keeps fewer keyframes, as on the city since issue 25, its map holds fewer scans than these two), and
prints side by side: the absolute trajectory error of odometry alone and of the optimised trajectory,
the reconstruction metrics (5 cm threshold) of the three maps, and per loop the optimisation and
remapping times. Before that, the odometry alone of both methods
(`frontend.odometry.method`: KISS-ICP and jaxmap's frame-to-frame ICP, same config otherwise) is run
over the sequence and their ATE / RPE / time per frame printed side by side. `--only odometry` stops
there; `--only slam` skips it.

Two more runs on an unseen 300-frame room (seed 1) with Kinect-like depth noise (std 0.002 z^2 m,
`kinect_noise`), made in data/room300_kinect when missing:
* `long` (`--only long`): `jaxmap slam` with the shipped config (every 2nd frame: 150 frames) must
  complete; its ATE, loops and map are printed.
* `drift` (`--only drift`): every 6th frame (a keyframe rate: ~13 cm and 7 deg apart), where the
  odometry drifts by decimetres before the loop; the ATE of odometry and of SLAM, and the maps built
  with the true poses, the odometry poses and the SLAM run's remapped map (ratio remapped / true).
With `map_kind: n3` (`--data` a city, configs/city_slam.yaml) the online N3 map is set against the N3
maps of the same frames with the true poses and with the odometry's, and what the ATE hides is printed
per trajectory: the height error (mean, min, max), the horizontal RMSE and the tilt error
(`jaxmap.slam.trajectory.axis_errors`), and per map the mean signed error of its road and sidewalk (a
trajectory a centimetre low maps the road that much low, and the standard protocol's crop cuts it).
Everything is written to OUT/bench.json.
"""
from __future__ import annotations

import json
import os

import numpy as np

from jaxmap.bench import print_map_table
from jaxmap.bench.n3 import print_signed_errors


def _bench_config(args, data: str, out: str):
    """The SlamConfig of the bench's scene (made if missing): LiDAR (KITTI layout) -> configs/city_slam.yaml,
    depth images -> configs/room_slam.yaml."""
    from jaxmap.bench import base_overrides
    from jaxmap.config import load_config, shipped_config_path
    from jaxmap.io import detect_kind
    from jaxmap.config import SlamConfig
    from jaxmap.synth.city import generate_city
    from jaxmap.synth.room import generate_room

    city = "city" in os.path.basename(os.path.normpath(data))
    if not os.path.isfile(os.path.join(data, "poses.txt")):
        if city:
            print(f"[bench] synthesizing the small city with 2 cm LiDAR range noise into {data}")
            generate_city(data, seed=0, small=True, noise_m=0.02)
        else:
            print(f"[bench] synthesizing the room with 5 mm depth noise into {data}")
            generate_room(data, seed=0, noise_m=0.005)
    config = shipped_config_path("city_slam.yaml" if detect_kind(data) == "kitti" else "room_slam.yaml")
    return load_config(config, base_overrides(args, data, os.path.join(out, "slam")), schema=SlamConfig)


def _write(out: str, name: str, res: dict) -> None:
    with open(os.path.join(out, name), "w") as f:
        json.dump(res, f, indent=1, default=lambda x: x.tolist() if hasattr(x, "tolist") else str(x))


def main(args) -> int:
    from jaxmap.frame_loop import open_run_sequence

    if getattr(args, "validation_suite", False):
        from jaxmap.bench.slam_suite import main_suite
        return main_suite(args)
    data, out = args.data, args.out
    os.makedirs(out, exist_ok=True)
    cfg = _bench_config(args, data, out)
    parts = {"odometry", "slam", "long", "drift"}
    only = {v.strip() for v in args.only.split(",")} if getattr(args, "only", None) else parts
    unknown = only - parts
    if unknown:
        raise SystemExit(f"jaxmap bench slam: --only takes {', '.join(sorted(parts))}, not {', '.join(sorted(unknown))}")
    if only & {"long", "drift"}:
        kinect = {}
        path = make_kinect_room()
        if "long" in only:
            kinect["long"] = run_on(path, 2, os.path.join(out, "long"), args, compare=False)
        if "drift" in only:
            kinect["drift"] = run_on(path, 6, os.path.join(out, "drift"), args, compare=True)
        _print_kinect(kinect)
        _write(out, "bench_kinect.json", kinect)
        only -= {"long", "drift"}
        if not only:
            return 0
    res_odo = None
    if "odometry" in only:
        res_odo = compare_odometry(cfg, open_run_sequence(cfg.imt()))
        _print_odometry(res_odo)
        if "slam" not in only:
            _write(out, "bench.json", {"odometry": res_odo})
            print(f"\n[bench] written to {os.path.join(out, 'bench.json')}")
            return 0
    res = (n3_slam_against_references if cfg.map_kind == "n3" else slam_against_references)(cfg, out)
    if res_odo is not None:
        res["odometry"] = res_odo
    (_print_n3 if cfg.map_kind == "n3" else _print)(res)
    _write(out, "bench.json", res)
    print(f"\n[bench] written to {os.path.join(out, 'bench.json')}")
    return 0


def slam_against_references(cfg, out: str) -> dict:
    """`jaxmap slam`, and the maps of the same frames with the true poses and with the odometry alone."""
    from jaxmap.finish import mesh_and_metrics
    from jaxmap.frame_loop import open_run_sequence
    from jaxmap.runs.imt import build_map
    from jaxmap.runs.slam import run_slam

    slam = run_slam(cfg, cfg.output)
    icfg = cfg.imt()
    seq = open_run_sequence(icfg)
    m_gt = mesh_and_metrics(build_map(icfg, seq, desc="GT poses"), icfg, out, "mesh_gt.ply")
    odo = np.asarray(slam_odometry(cfg.output))
    m_od = mesh_and_metrics(build_map(icfg, seq, poses=odo, desc="odometry poses"), icfg, out, "mesh_odometry.ply")
    return {"frames": slam["frames"], "keyframes": slam["keyframes"], "loops": slam["loops"],
            "ate": {"odometry": slam.get("ate_odometry"), "slam": slam.get("ate_slam")},
            "recon": {"GT poses": m_gt.get("metrics", {}), "odometry poses": m_od.get("metrics", {}),
                      "slam (remapped)": slam.get("metrics", {})},
            "sizes": {k: slam[k] for k in ("map_bytes", "store_bytes", "keyframes")}}


def n3_slam_against_references(cfg, out: str) -> dict:
    """`jaxmap slam` with map_kind n3, and the N3 maps of the same frames with the true poses (`jaxmap
    map`, run first: it pays the frame program's compile) and with the odometry alone. Seconds per frame
    are the wall-clock of each frame loop less its compiling, over the frames."""
    from jaxmap.frame_loop import open_run_sequence
    from jaxmap.runs.n3 import map_sequence
    from jaxmap.runs.slam_n3 import n3_map_config
    from jaxmap.runs.slam import n3_from_poses, run_slam

    load = os.getloadavg()
    gt = map_sequence(n3_map_config(cfg, os.path.join(out, "n3_gt")), os.path.join(out, "n3_gt"))
    slam = run_slam(cfg, cfg.output)
    seq = open_run_sequence(cfg)
    odo = n3_from_poses(cfg, seq, np.asarray(slam_odometry(cfg.output)), os.path.join(out, "n3_odometry"), True,
                        "odometry poses")

    def per_frame(r):
        return (r["wall_s"] - r.get("compile_s", 0.0)) / max(r["frames_run"], 1)

    return {"frames": slam["frames"], "keyframes": slam["keyframes"], "loops": slam["loops"],
            "ate": {"odometry": slam.get("ate_odometry"), "slam": slam.get("ate_slam")},
            "axes": {"odometry": slam.get("axes_odometry"), "slam": slam.get("axes_slam")},
            "recon": {"GT poses (jaxmap map)": gt.get("metrics", {}), "odometry poses": odo.get("metrics", {}),
                      "slam (online)": slam.get("metrics", {})},
            "s_per_frame": {"GT poses (jaxmap map)": per_frame(gt), "slam (online)": per_frame(slam)},
            "step": slam["step"], "tracked": [slam["tracked_ok"], slam["tracked_frames"]],
            "loop_map_s": slam["loop_map_s"], "load": [load, os.getloadavg()],
            "config": {k: getattr(cfg, k) for k in ("n3_config", "n3_track", "n3_track_min_valid", "n3_track_min_seen",
                                                    "n3_track_young_rotation", "n3_loop", "n3_loop_min_move_m",
                                                    "n3_loop_readd_iters")}}


def _print_ate(ates: dict, rule: bool) -> None:
    """The trajectory table `{name: ate()}` (rows without one are left out), then a blank line."""
    print(f"{'trajectory (ATE)':22s} {'RMSE cm':>8s} {'mean cm':>8s} {'max cm':>7s} {'rot deg':>8s}")
    if rule:
        print("-" * 57)
    for name, a in ates.items():
        if a:
            print(f"{name:22s} {100 * a['rmse_m']:8.2f} {100 * a['mean_m']:8.2f} {100 * a['max_m']:7.2f} "
                  f"{a['rot_rmse_deg']:8.3f}")
    print()


def _print_axes(axes: dict) -> None:
    """Per trajectory, what the ATE hides: height error (mean, min, max), horizontal RMSE, tilt error."""
    print(f"{'trajectory (per axis)':22s} {'dz mean cm':>10s} {'dz min':>7s} {'dz max':>7s} {'xy RMSE cm':>10s} "
          f"{'tilt mean deg':>13s} {'tilt max':>8s}")
    for name, a in axes.items():
        if a:
            print(f"{name:22s} {100 * a['dz_mean_m']:+10.2f} {100 * a['dz_min_m']:+7.2f} {100 * a['dz_max_m']:+7.2f} "
                  f"{100 * a['xy_rmse_m']:10.2f} {a['tilt_mean_deg']:13.3f} {a['tilt_max_deg']:8.3f}")
    print()


def _print_n3(res: dict) -> None:
    print(f"\njaxmap slam (map_kind n3) on {res['frames']} frames, {res['config']}")
    _print_ate(res["ate"], rule=False)
    if res.get("axes"):
        _print_axes(res["axes"])
    print_map_table(res["recon"])
    # each map's mean signed error per class (road and sidewalk: what a low trajectory lowers), the floor first
    print_signed_errors({name: {"metrics": m} for name, m in res["recon"].items() if m})
    print()
    r = res["recon"]
    if r["slam (online)"] and r["GT poses (jaxmap map)"]:
        print(f"slam / GT-pose C-L1 = {r['slam (online)']['chamfer_l1_cm'] / r['GT poses (jaxmap map)']['chamfer_l1_cm']:.3f}"
              " (target <= 1.10)")
    sp = res["s_per_frame"]
    print(f"s/frame (wall less compiling): GT poses {sp['GT poses (jaxmap map)']:.2f}, slam {sp['slam (online)']:.2f} "
          f"= {sp['slam (online)'] / sp['GT poses (jaxmap map)']:.2f}x (target <= 1.3); load {res['load'][0][0]:.1f} "
          f"-> {res['load'][1][0]:.1f}")
    st = res["step"]
    print(f"slam medians per frame: odometry {st['median_odometry_s']:.2f} s, tracking {st['median_refine_s']:.2f} s, "
          f"N3 frame {st['median_map_s']:.2f} s, loop search {st['median_loop_s']:.2f} s; tracked ok "
          f"{res['tracked'][0]} of {res['tracked'][1]}")
    # a loop re-integrates its frames at once (rebuild, moved with n3_loop_readd_per_frame 0) or queues
    # them for the next frames (moved, submaps)
    redo = lambda lp: lp.get("reintegrated", 0) + lp.get("queued", 0)  # noqa: E731
    moved = [lp for lp in res["loops"] if redo(lp)]
    print(f"{len(res['loops'])} loops; the map followed {len(moved)} of them in {res['loop_map_s']:.1f} s of the "
          f"main thread in all")
    for lp in moved:
        how = "queued" if "queued" in lp else "re-integrated"
        print(f"  loop at frame {lp['frame']}: frames moved up to {100 * lp['max_move_m']:.1f} cm, {redo(lp)} "
              f"of {lp['frames']} {how} ({lp['mode']}) in {lp['map_s']:.1f} s")


KINECT_ROOM = "data/room300_kinect"


def kinect_noise(path: str, k: float = 0.002, seed: int = 0) -> None:
    """Add Kinect-like depth noise to the depth PNGs of a depth-layout directory, in place: per pixel
    z + N(0, (k z^2)^2) metres (Khoshelham & Elberink 2012), rounded to millimetres; holes stay holes."""
    import glob

    from jaxmap.io.depth import read_depth_png, write_depth_png

    rng = np.random.default_rng(seed)
    for f in sorted(glob.glob(os.path.join(path, "depth", "*.png"))):
        mm = read_depth_png(f).astype(np.float64)
        z = mm / 1000.0
        noisy = np.where(mm > 0, z + rng.normal(size=z.shape) * k * z * z, 0.0)
        write_depth_png(f, np.clip(np.round(noisy * 1000.0), 0, 65535).astype(np.uint16))


def make_kinect_room(path: str = KINECT_ROOM, frames: int = 300, seed: int = 1) -> str:
    """The unseen room of the long and drift runs (made once: 300 frames, seed 1, 0.002 z^2 noise)."""
    from jaxmap.synth.room import generate_room

    if not os.path.isfile(os.path.join(path, "poses.txt")):
        print(f"[bench] synthesizing a {frames}-frame room (seed {seed}) with 0.002 z^2 depth noise into {path}")
        generate_room(path, seed=seed, n_frames=frames)
        kinect_noise(path, 0.002, seed)
    return path


def run_on(data: str, every: int, out: str, args, compare: bool) -> dict:
    """`jaxmap slam` on every `every`-th frame of `data`; with `compare`, also the maps of the same frames
    built with the true poses and with the odometry poses."""
    import time

    from jaxmap.bench import base_overrides
    from jaxmap.config import load_config, shipped_config_path
    from jaxmap.finish import mesh_and_metrics
    from jaxmap.frame_loop import open_run_sequence
    from jaxmap.runs.imt import build_map
    from jaxmap.config import SlamConfig
    from jaxmap.runs.slam import run_slam

    os.makedirs(out, exist_ok=True)
    over = base_overrides(args, data, os.path.join(out, "slam")) + [f"data.every_frame={every}"]
    cfg = load_config(shipped_config_path("room_slam.yaml"), over, schema=SlamConfig)
    t0 = time.perf_counter()
    slam = run_slam(cfg, cfg.output)
    res = {"frames": slam["frames"], "keyframes": slam["keyframes"], "every_frame": every,
           "wall_s": time.perf_counter() - t0, "load_avg": os.getloadavg()[0],
           "ate": {"odometry": slam.get("ate_odometry"), "slam": slam.get("ate_slam")},
           "loops": slam["loops"], "recon": {"slam (remapped)": slam.get("metrics", {})},
           "sizes": {k: slam[k] for k in ("map_bytes", "store_bytes", "keyframes")}}
    if compare:
        icfg = cfg.imt()
        seq = open_run_sequence(icfg)
        gt = mesh_and_metrics(build_map(icfg, seq, desc="GT poses"), icfg, out, "mesh_gt.ply")
        od = mesh_and_metrics(build_map(icfg, seq, poses=np.asarray(slam_odometry(cfg.output)),
                                         desc="odometry poses"), icfg, out, "mesh_odometry.ply")
        res["recon"] = {"GT poses": gt.get("metrics", {}), "odometry poses": od.get("metrics", {}),
                        **res["recon"]}
    return res


def _print_kinect(res: dict) -> None:
    for name, r in res.items():
        what = ("completes the shipped config" if name == "long" else
                "keyframe-rate frames: the odometry drifts, loop closure must fix it")
        print(f"\n{name}: jaxmap slam on {r['frames']} frames of the 300-frame Kinect-noise room (every "
              f"{r['every_frame']}), {r['keyframes']} keyframes, {len(r['loops'])} loops, {r['wall_s']:.0f} s "
              f"(load {r['load_avg']:.1f}); {what}")
        print(f"{'trajectory (ATE)':22s} {'RMSE cm':>8s} {'mean cm':>8s} {'max cm':>7s} {'rot deg':>8s}")
        for k, a in r["ate"].items():
            if a:
                print(f"{k:22s} {100 * a['rmse_m']:8.2f} {100 * a['mean_m']:8.2f} {100 * a['max_m']:7.2f} "
                      f"{a['rot_rmse_deg']:8.3f}")
        o, s_ = r["ate"].get("odometry"), r["ate"].get("slam")
        if o and s_:
            print(f"loop closure cuts the ATE RMSE by {100 * (1 - s_['rmse_m'] / o['rmse_m']):.0f} % (target >= 50 %)")
        print_map_table(r["recon"], rule=False)
        if "GT poses" in r["recon"]:
            g = r["recon"]["GT poses"].get("chamfer_l1_cm", float("nan"))
            m = r["recon"]["slam (remapped)"].get("chamfer_l1_cm", float("nan"))
            print(f"slam (remapped) / GT-pose C-L1 = {m / g:.3f} (target <= 1.10)")
        _print_loops(r["loops"])


def _print_loops(loops: list, each: int = 6) -> None:
    """A line per loop for a few loops; for many, a summary and the slowest remaps."""
    def line(lp):
        print(f"  loop at frame {lp['frame']}: pose graph {lp['optimize_s']:.3f} s, remap {lp['keyframes_moved']} of "
              f"{lp['keyframes']} keyframes in {lp['remap_s']:.2f} s")

    if len(loops) <= each:
        for lp in loops:
            line(lp)
        return
    t = np.array([lp["remap_s"] for lp in loops])
    moved = np.array([lp["keyframes_moved"] for lp in loops])
    per = t[moved > 0] / moved[moved > 0]
    print(f"  {len(loops)} loops: remap median {np.median(t):.2f} s, total {t.sum():.1f} s, "
          f"{1e3 * np.median(per):.0f} ms per moved keyframe (median); pose graph median "
          f"{np.median([lp['optimize_s'] for lp in loops]):.3f} s; the {min(3, len(loops))} slowest remaps:")
    for i in sorted(np.argsort(-t)[:3]):
        line(loops[i])


METHODS = {"kiss_icp": "KISS-ICP", "icp": "ICP (jaxmap)"}


def compare_odometry(cfg, seq) -> dict:
    """Odometry alone of each method over `seq` (from its first pose): ATE, RPE (1 frame), s/frame.
    A method whose package is missing gets {"error": why}."""
    import dataclasses

    from jaxmap.errors import JaxmapError
    from jaxmap.runs.slam import odometry_trajectory
    from jaxmap.slam.trajectory import ate, have_evo, rpe

    gt = np.asarray(seq.poses, dtype=np.float64)
    out = {}
    for method in METHODS:
        ocfg = dataclasses.replace(cfg.frontend.odometry, method=method)
        try:
            poses, s = odometry_trajectory(seq, ocfg, progress=True)
        except (JaxmapError, ImportError) as e:
            out[method] = {"error": str(e)}
            continue
        out[method] = {"ate": ate(poses, gt), "rpe": rpe(poses, gt) if len(gt) > 1 else None, "s_per_frame": s,
                       "metrics_by": "evo" if have_evo() else "jaxmap"}
    return out


def _print_odometry(res: dict) -> None:
    print(f"\nodometry alone ({next((r['metrics_by'] for r in res.values() if 'metrics_by' in r), '-')} metrics)")
    print(f"{'method':14s} {'ATE RMSE cm':>11s} {'ATE max cm':>10s} {'ATE rot deg':>11s} {'RPE cm/frame':>12s} "
          f"{'RPE deg':>8s} {'s/frame':>8s}")
    print("-" * 80)
    for method, r in res.items():
        name = METHODS[method]
        if "error" in r:
            print(f"{name:14s} {r['error']}")
            continue
        a, p = r["ate"], r["rpe"] or {"rmse_m": float("nan"), "rot_rmse_deg": float("nan")}
        print(f"{name:14s} {100 * a['rmse_m']:11.2f} {100 * a['max_m']:10.2f} {a['rot_rmse_deg']:11.3f} "
              f"{100 * p['rmse_m']:12.2f} {p['rot_rmse_deg']:8.3f} {r['s_per_frame']:8.3f}")


def slam_odometry(run_dir: str) -> np.ndarray:
    from jaxmap.io.kitti import read_poses

    return read_poses(os.path.join(run_dir, "odometry_kitti.txt"))


def _print(res: dict) -> None:
    print(f"\njaxmap slam on {res['frames']} frames ({res['keyframes']} keyframes)")
    _print_ate(res["ate"], rule=True)
    print_map_table(res["recon"])
    print(f"\nloops closed: {len(res['loops'])}")
    for lp in res["loops"]:
        print(f"  frame {lp['frame']:4d}: pose graph {lp['optimize_s']:.3f} s, remap {lp['keyframes_moved']} of "
              f"{lp['keyframes']} keyframes {lp['remap_s']:.2f} s (fitness {lp['fitness']:.2f}, "
              f"RMSE {100 * lp['rmse_m']:.1f} cm)")
    s = res["sizes"]
    print(f"map {s['map_bytes'] / 1e6:.1f} MB, keyframe store {s['store_bytes'] / 1e6:.1f} MB")
