"""`jaxmap bench imt`: the transformable latent map on the synthetic room, in one run.

1. The IMT paper's two-branch test (section IV-B): for keyframes i, encode frame i at the pose of
   frame 0 and transform the local map by `T_i T_0^-1` (branch A), versus encode it at `T_i`
   (branch B); mesh both and measure Accuracy (A's surface samples to B's mesh) and Completeness
   (B's to A's), in cm. Rows: jaxmap (trilinear, `F - J t`), the paper's sign (`F + J t`), no
   Jacobian term, and the paper's softmax weighting (with the correct sign and with the paper's
   sign and metre-unit temperature).
2. Both remap methods (`map.remap`: reencode, transform), each: Acc / Comp / C-L1 / Comp. ratio /
   F-score at eval.threshold_m = 5 cm of the map built with ground-truth poses, with drifted poses
   (a growing rotation and translation error, 5 deg / 30 cm at the last frame), after the remap of
   the drifted map to the true poses (loop 1) and after LOOPS successive loop closures (`loop_poses`);
   the ratio remapped / GT-pose C-L1 (robust to changes of the evaluator); the keyframe store per
   keyframe, the frame program's time and the remap time per moved keyframe (loop 1: the first remap
   of the process; warm: the same again; loops 2-10: half the keyframes move).
3. Times of the default method (median after warm-up, with the load average): encode of a frame for
   the map (no Jacobian) and with the Jacobian at the two-branch tool's pooling, the pooled-cell count
   against the points; a remap that moves one keyframe; sizes of the map and of the keyframe store
   against the downsampled points and normals of the same keyframes (float32).
4. The remap against the room's length (`--only scale`): rooms of 120, 300 and 600 frames (60, 150 and 300
   keyframes), each mapped with drifted poses in a process of its own and remapped three times (every
   keyframe: cold, the first remap of the process; half of them; every keyframe again: warm), with the
   XLA programs built during each remap (none: a remap runs only programs that mapping compiled).

Everything is written to OUT/bench.json (meshes under OUT/).
"""
from __future__ import annotations

import json
import os
import time

import jax
import numpy as np

from jaxmap.bench import print_map_table
from jaxmap.synth.drift import drift_poses


def _mesh_of(prior, m, cfg):
    from jaxmap.imt.meshing import mesh

    c = cfg.mesh
    return mesh(prior, m, c.resolution, c.sigma_threshold_m, c.min_weight)


def _mesh_pair_error(A, B, n: int = 100_000) -> tuple[float, float]:
    """(accuracy, completeness) in cm between meshes A and B: A's samples to B, B's samples to A."""
    from jaxmap.metrics import mesh_distance, sample_mesh

    if len(A.faces) == 0 or len(B.faces) == 0:
        return float("nan"), float("nan")
    pa, pb = sample_mesh(A, n), sample_mesh(B, n)
    return 100 * float(np.mean(mesh_distance(B, pa))), 100 * float(np.mean(mesh_distance(A, pb)))


def two_branch(mapper, seq, ids, cfg) -> dict:
    from jaxmap.geometry import se3_inverse
    from jaxmap.imt.local_maps import transform

    vs = cfg.map.voxel_size_m
    variants = {
        "jaxmap: trilinear^2, F - J t": dict(method="trilinear", jacobian_sign=-1.0),
        "plain trilinear, F - J t": dict(method="trilinear", jacobian_sign=-1.0, splat_power=1.0),
        "paper sign: trilinear^2, F + J t": dict(method="trilinear", jacobian_sign=1.0),
        "no Jacobian: trilinear^2, F": dict(method="trilinear", jacobian_sign=0.0),
        "softmax (voxel units), F - J t": dict(method="softmax", jacobian_sign=-1.0, temperature=1.0),
        "paper: softmax (metres), F + J t": dict(method="softmax", jacobian_sign=1.0, temperature=1.0 / vs ** 2),
    }
    T0 = seq.frame(0).pose
    errs = {k: [] for k in variants}
    for i in ids:
        fr = seq.frame(i)
        pts, nrm = mapper.preprocess(fr.points)
        b = mapper.encode(pts, nrm, fr.pose, with_jacobian=True)
        a0 = mapper.encode(pts, nrm, T0, with_jacobian=True)
        D = fr.pose @ se3_inverse(T0)
        mesh_b = _mesh_of(mapper.prior, b, cfg)
        for name, kw in variants.items():
            errs[name].append(_mesh_pair_error(_mesh_of(mapper.prior, transform(a0, D, **kw), cfg), mesh_b))
        print(f"[bench] two-branch frame {fr.index}: " + ", ".join(f"{e[-1][0]:.2f}/{e[-1][1]:.2f}"
                                                                   for e in errs.values()), flush=True)
    out = {}
    for name, e in errs.items():
        e = np.asarray(e)
        out[name] = {"accuracy_cm": float(np.nanmean(e[:, 0])), "completeness_cm": float(np.nanmean(e[:, 1])),
                     "per_frame": e.tolist()}
    return out


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up (compiles)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def time_encode(mapper, seq, ids) -> dict:
    """Median seconds of one frame's encode for the map (no Jacobian) and with the Jacobian (each the frame
    program on an empty map, `local_maps.encode_cells`: encode and fuse), and the cells / points of those
    frames."""
    from jaxmap.geometry import SE3
    from jaxmap.imt import latent_map as lm
    from jaxmap.imt.local_maps import encode_cells

    c = mapper.cfg.map
    t_map, t_jac, cells, cells_jac, points = [], [], [], [], []
    for i in ids:
        fr = seq.frame(i)
        pts, nrm = mapper.preprocess(fr.points)
        T_w_s = SE3.from_matrix(fr.pose)
        pw = T_w_s.apply(pts.astype(np.float64))
        nw = T_w_s.rotation().apply(nrm.astype(np.float64))

        def enc_map():
            cl = lm.pool_cells(pw, nw, c.voxel_size_m, c.cells_per_voxel)
            m = encode_cells(mapper.prior, *cl, c.voxel_size_m, c.min_points, with_jacobian=False,
                             hints=mapper.local_hints)
            jax.block_until_ready(m.latent_sum)
            return cl

        def enc_jac():
            jax.block_until_ready(mapper.encode(pts, nrm, fr.pose, with_jacobian=True).jac_sum)

        t_map.append(_median_time(enc_map, 3))
        t_jac.append(_median_time(enc_jac, 3))
        cells.append(len(enc_map()[0]))
        cells_jac.append(len(lm.pool_cells(pw, nw, c.voxel_size_m, c.transform_cells_per_voxel)[0]))
        points.append(len(pts))
    return {"encode_map_s": float(np.median(t_map)), "encode_jacobian_s": float(np.median(t_jac)),
            "cells_per_frame": float(np.median(cells)), "jacobian_cells_per_frame": float(np.median(cells_jac)),
            "points_per_frame": float(np.median(points)),
            "load_avg": os.getloadavg()[0]}


def time_remap_one(mapper, ks) -> dict:
    """Median seconds of a remap that moves one keyframe (remove its contribution + re-encode at the new
    pose + fuse, one signed batch), over keyframes `ks`; the map is put back after each."""
    from jaxmap.geometry import make_pose, rotation_from_axis_angle
    from jaxmap.imt.core import remap

    opts = _opts(mapper)
    D = make_pose(rotation_from_axis_angle(np.array([0.0, 0.0, 1.0]), 0.01), np.array([0.013, -0.007, 0.004]))
    ts = []
    run = (mapper.static, mapper.prior)
    state, store = mapper.state, mapper.store  # the state is donated to each remap: kept here, handed back
    for r in range(2):  # the first round compiles
        for k in ks:
            base = store.poses().copy()
            new = base.copy()
            new[k] = D @ base[k]
            t0 = time.perf_counter()
            state, moved, _ = remap(run[0], state, store, run[1], new, opts, mapper.hints)
            jax.block_until_ready(state.active)
            dt = time.perf_counter() - t0
            state, store, _ = remap(run[0], state, moved, run[1], base, opts, mapper.hints)  # put it back
            if r:
                ts.append(dt)
    mapper.state, mapper.store = state, store
    return {"remap_one_keyframe_s": float(np.median(ts)), "load_avg": os.getloadavg()[0]}


def _opts(mapper):
    from jaxmap.imt.mapper import remap_options

    return remap_options(mapper.cfg)


def store_vs_points(mapper) -> dict:
    """Bytes of the keyframe store against the keyframes' downsampled points + normals as float32."""
    pts = sum(t["points"] for t in mapper.timings)
    return {"store_bytes": mapper.store.nbytes(), "points_normals_bytes": int(pts * 6 * 4),
            "keyframes": len(mapper.store), "cells": mapper.store.cell_count(), "points": int(pts)}


DRIFT = (5.0, 0.30)       # the drifted map: 5 deg and 30 cm of error at the last frame (`synth.drift`)
LOOPS = 10                # successive loop closures after which the remapped map is scored again
REMAP_METHODS = ("reencode", "transform")


def loop_poses(gt: np.ndarray, j: int) -> np.ndarray:
    """The keyframe poses after loop closure j (2..LOOPS-1): the second half of the keyframes off by a
    drift that alternates in sign and shrinks (so each loop moves them, and at most half of the
    keyframes: a remove and a re-fusion each, no rebuild); the first half at the true poses."""
    s = (-1.0) ** j * (LOOPS - j) / LOOPS
    out = gt.copy()
    half = len(gt) // 2
    out[half:] = drift_poses(gt, DRIFT[0] * s, DRIFT[1] * s)[half:]
    return out


def _remap_timed(mapper, poses) -> dict:
    t0 = time.perf_counter()
    moved = mapper.remap(poses)
    dt = time.perf_counter() - t0
    return {"keyframes_moved": len(moved), "seconds": dt, "ms_per_keyframe": 1e3 * dt / max(len(moved), 1),
            "load_avg": os.getloadavg()[0]}


def remap_method(cfg, seq, gt, out: str, method: str) -> tuple[dict, dict]:
    """One remap method on the room: the true-pose map; a map built with drifted poses, remapped to the
    true poses (loop 1: every keyframe moves, the map is rebuilt; the first remap of the process), then
    LOOPS - 1 further loops that move the second half of the keyframes (`loop_poses`), the last one back
    to the true poses; and a second whole-map remap (warm). Returns (metrics rows, remap figures, the
    true-pose mapper)."""
    from dataclasses import replace

    from jaxmap.finish import mesh_and_metrics
    from jaxmap.runs.imt import build_map

    c = replace(cfg, map=replace(cfg.map, remap=method))
    rows, fig = {}, {}
    m_gt = build_map(c, seq, desc=f"{method}: GT poses")
    rows[f"{method}: GT poses"] = mesh_and_metrics(m_gt, c, out, f"mesh_{method}_gt.ply")
    fig["store_bytes_per_keyframe"] = m_gt.store.nbytes() / len(m_gt.store)
    fig["frame_program_s"] = m_gt.timing_summary()["median_encode_s"]
    drifted = drift_poses(gt, *DRIFT)
    m = build_map(c, seq, poses=drifted, desc=f"{method}: drifted")
    rows[f"{method}: drifted"] = mesh_and_metrics(m, c, out, f"mesh_{method}_drift.ply")
    fig["loop1"] = _remap_timed(m, gt)
    rows[f"{method}: remapped, 1 loop"] = mesh_and_metrics(m, c, out, f"mesh_{method}_loop1.ply")
    fig["loops"] = [_remap_timed(m, loop_poses(gt, j)) for j in range(2, LOOPS)] + [_remap_timed(m, gt)]
    rows[f"{method}: remapped, {LOOPS} loops"] = mesh_and_metrics(m, c, out, f"mesh_{method}_loop{LOOPS}.ply")
    fig["rebuild_warm"] = _remap_timed(m, drifted)
    return rows, fig, m_gt


SCALE_FRAMES = (120, 300, 600)   # rooms of 60, 150 and 300 keyframes (every 2nd frame fused)


def scale_room(data: str, frames: int) -> str:
    """The bench's room with `frames` frames on its one loop (`jaxmap synth room --frames`): `data` itself when
    it has that many, else `DATA_<frames>frames`, made if missing."""
    from jaxmap.synth.room import generate_room

    def frames_of(path: str):
        try:
            with open(os.path.join(path, "meta.json")) as f:
                return json.load(f).get("frames")
        except (OSError, ValueError):
            return None

    if frames_of(data) == frames:
        return data
    path = f"{data.rstrip('/')}_{frames}frames"
    if frames_of(path) != frames:
        print(f"[bench] synthesizing the room with {frames} frames into {path}")
        generate_room(path, seed=0, n_frames=frames)
    return path


def remap_at_scale(cfg, data: str) -> dict:
    """One room (run in a process of its own, so that its first remap is the first of the process): the map
    built with drifted poses through `ImtMapper.add_frame`, remapped to the true poses (cold: every keyframe
    moves, the map is rebuilt), then half of the keyframes moved (`loop_poses`: each removed and fused back),
    then every keyframe again (warm). Per remap: ms per moved keyframe and the XLA programs built during it
    (`compile_cache.programs_built`: compiled, or loaded from the compile cache)."""
    from dataclasses import replace

    from jaxmap.compile_cache import programs_built
    from jaxmap.frame_loop import open_run_sequence
    from jaxmap.runs.imt import build_map

    cfg = replace(cfg, data=replace(cfg.data, path=data, end_frame=-1))
    seq = open_run_sequence(cfg)
    gt = np.asarray([seq.frame(i).pose for i in range(len(seq))])
    drifted = drift_poses(gt, *DRIFT)
    m = build_map(cfg, seq, poses=drifted, desc=f"{len(seq)} keyframes, drifted")
    out = {"keyframes": len(m.store), "cells_per_keyframe": m.store.cell_count() / len(m.store),
           "frame_program_s": m.timing_summary()["median_encode_s"]}
    for name, poses in (("cold", gt), ("half", loop_poses(gt, 2)), ("warm", drifted)):
        with programs_built() as built:
            out[name] = _remap_timed(m, poses)
        out[name]["programs_built"] = len(built)
        if name == "cold":
            out["map_voxels"] = int(m.state.active)     # the map at the true poses
    return out


def remap_scaling(cfg, data: str) -> dict:
    """`remap_at_scale` on the rooms of SCALE_FRAMES frames, each in a fresh process (spawned: the parent's
    jax is not forked). Returns {frames: figures}."""
    import concurrent.futures
    import multiprocessing

    out = {}
    for frames in SCALE_FRAMES:
        room = scale_room(data, frames)
        with concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            out[frames] = pool.submit(remap_at_scale, cfg, room).result()
        _print_scale_row(frames, out[frames])
    return out


def main(args) -> int:
    from jaxmap.bench import base_overrides
    from jaxmap.config import ImtConfig, load_config, shipped_config_path
    from jaxmap.frame_loop import open_run_sequence
    from jaxmap.imt.mapper import ImtMapper
    from jaxmap.synth.room import generate_room

    data, out = args.data, args.out
    os.makedirs(out, exist_ok=True)
    if not os.path.isfile(os.path.join(data, "poses.txt")):
        print(f"[bench] synthesizing the room into {data}")
        generate_room(data, seed=0)
    cfg = load_config(shipped_config_path("room_imt.yaml"), base_overrides(args, data, out), schema=ImtConfig)
    seq = open_run_sequence(cfg)
    n = len(seq)
    res: dict = {"frames": n, "config": {"voxel_size_m": cfg.map.voxel_size_m, "every_frame": cfg.data.every_frame}}
    only = set((args.only or "two_branch,recon,scale").split(","))

    if "two_branch" in only:
        ids = sorted(set(np.linspace(1, n - 1, 6).round().astype(int).tolist()))
        res["two_branch"] = two_branch(ImtMapper(cfg), seq, ids, cfg)
        _print_two_branch(res["two_branch"])

    if "recon" in only:
        gt = np.asarray([seq.frame(i).pose for i in range(n)])
        res["recon"], res["remap"], mappers = {}, {}, {}
        for method in REMAP_METHODS:
            rows, res["remap"][method], mappers[method] = remap_method(cfg, seq, gt, out, method)
            res["recon"].update({k: v.get("metrics", {}) for k, v in rows.items()})
        m_gt = mappers[cfg.map.remap]   # the default method's timings and sizes
        ids = sorted(set(np.linspace(1, n - 1, 5).round().astype(int).tolist()))
        res["timing"] = {**m_gt.timing_summary(), **time_encode(m_gt, seq, ids),
                         **time_remap_one(m_gt, list(range(0, len(m_gt.store), 7)))}
        res["sizes"] = {**m_gt.sizes(), **store_vs_points(m_gt)}
        _print_recon(res, cfg.map.remap)

    if "scale" in only:
        _print_scale_header(cfg.map.remap)
        res["scale"] = remap_scaling(cfg, data)
        _print_scale_footer(res["scale"])
    with open(os.path.join(out, "bench.json"), "w") as f:
        json.dump(res, f, indent=1)
    print(f"\n[bench] written to {os.path.join(out, 'bench.json')}")
    return 0


def _print_two_branch(tb: dict) -> None:
    print("\ntwo-branch test (encode at T0 + transform by Ti T0^-1  vs  encode at Ti), mean over keyframes")
    print(f"{'variant':36s} {'Acc cm':>7s} {'Comp cm':>8s}")
    print("-" * 53)
    for name, r in tb.items():
        print(f"{name:36s} {r['accuracy_cm']:7.2f} {r['completeness_cm']:8.2f}")


def _ratio(recon: dict, a: str, b: str) -> float:
    return recon[a].get("chamfer_l1_cm", float("nan")) / recon[b].get("chamfer_l1_cm", float("nan"))


def _print_remap_methods(res: dict, default: str) -> None:
    rec = res["recon"]
    print(f"\nremap methods (map.remap; default {default}): the map built with poses drifted by {DRIFT[0]:g} deg / "
          f"{DRIFT[1] * 100:g} cm, remapped to the true poses; C-L1 against the map built with the true poses")
    print(f"{'method':10s} {'store kB/kf':>11s} {'frame ms':>8s} {'loop 1 ms/kf':>12s} {'warm ms/kf':>10s} "
          f"{'loops 2-10 ms/kf':>16s} {'C-L1 1 loop':>11s} {f'C-L1 {LOOPS} loops':>13s}")
    for method, f in res["remap"].items():
        gt = f"{method}: GT poses"
        later = np.median([x["ms_per_keyframe"] for x in f["loops"]])
        print(f"{method:10s} {f['store_bytes_per_keyframe'] / 1e3:11.1f} {f['frame_program_s'] * 1e3:8.1f} "
              f"{f['loop1']['ms_per_keyframe']:12.1f} {f['rebuild_warm']['ms_per_keyframe']:10.1f} {later:16.1f} "
              f"{_ratio(rec, f'{method}: remapped, 1 loop', gt):11.3f} {_ratio(rec, f'{method}: remapped, {LOOPS} loops', gt):13.3f}")
    print("(loop 1: every keyframe moves and the map is rebuilt, the first remap of the process; warm: the same "
          "again; loops 2-10: half the keyframes move, each removed and fused back; load "
          f"{max(x['load_avg'] for f in res['remap'].values() for x in f['loops']):.1f})")


def _print_recon(res: dict, default: str) -> None:
    print(f"\nreconstruction at {res['frames']} frames (threshold 5 cm)")
    print_map_table(res["recon"], width=30)
    _print_remap_methods(res, default)
    t, s = res["timing"], res["sizes"]
    print(f"\nper frame (median after warm-up, load {t['load_avg']:.1f}): preprocess {t['median_preprocess_s'] * 1e3:.1f} ms, "
          f"encode for the map {t['encode_map_s'] * 1e3:.1f} ms ({t['cells_per_frame']:.0f} cells from "
          f"{t['points_per_frame']:.0f} points), encode with Jacobian for the two-branch tool "
          f"{t['encode_jacobian_s'] * 1e3:.1f} ms ({t.get('jacobian_cells_per_frame', float('nan')):.0f} cells), "
          f"fuse {t['median_fuse_s'] * 1e3:.1f} ms")
    print(f"remap of one keyframe ({default}; remove + re-fuse): {t['remap_one_keyframe_s'] * 1e3:.1f} ms (target <= 20 ms)")
    print(f"map: {s['map_voxels']} voxels, {s['map_bytes'] / 1e6:.1f} MB; keyframe store: {s['keyframes']} keyframes, "
          f"{s['cells']} cells, {s['store_bytes'] / 1e6:.2f} MB; their downsampled points + normals (float32): "
          f"{s['points']} points, {s['points_normals_bytes'] / 1e6:.2f} MB")


def _print_scale_header(method: str) -> None:
    print(f"\nremap against the room's length (map.remap: {method}; the room of --frames N, every 2nd frame fused; "
          f"the map built with poses drifted by {DRIFT[0]:g} deg / {DRIFT[1] * 100:g} cm)")
    print(f"{'frames':>6s} {'keyframes':>9s} {'voxels':>7s} {'cells/kf':>8s} {'frame ms':>8s} {'cold ms/kf':>10s} "
          f"{'warm ms/kf':>10s} {'half ms/kf':>10s} {'programs built':>14s}", flush=True)


def _print_scale_row(frames: int, r: dict) -> None:
    built = "/".join(str(r[k]["programs_built"]) for k in ("cold", "warm", "half"))
    print(f"{frames:6d} {r['keyframes']:9d} {r['map_voxels']:7d} {r['cells_per_keyframe']:8.0f} "
          f"{r['frame_program_s'] * 1e3:8.1f} {r['cold']['ms_per_keyframe']:10.1f} {r['warm']['ms_per_keyframe']:10.1f} "
          f"{r['half']['ms_per_keyframe']:10.1f} {built:>14s}", flush=True)


def _print_scale_footer(scale: dict) -> None:
    load = max(r[k]["load_avg"] for r in scale.values() for k in ("cold", "warm", "half"))
    print("(voxels: the map at the true poses; cold: the first remap of the process, every keyframe moves and the map "
          "is rebuilt; warm: the same again; half: the second half of the keyframes moves, each removed and fused back; "
          "XLA programs built during the cold / warm / half remap; targets <= 25 ms cold and <= 20 warm on an idle "
          f"2-core CPU; load {load:.1f})")
