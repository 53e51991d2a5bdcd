"""`jaxmap bench imt`: the transformable latent map on the synthetic room, in one run.

1. The IMT paper's two-branch test (section IV-B): for keyframes i, encode frame i at the pose of
   frame 0 and transform the local map by `T_i T_0^-1` (branch A), versus encode it at `T_i`
   (branch B); mesh both and measure Accuracy (A's surface samples to B's mesh) and Completeness
   (B's to A's), in cm. Rows: jaxmap (trilinear, `F - J t`), the paper's sign (`F + J t`), no
   Jacobian term, and the paper's softmax weighting (with the correct sign and with the paper's
   sign and metre-unit temperature).
2. Reconstruction (Acc / Comp / C-L1 / Comp. ratio / F-score at eval.threshold_m = 5 cm) of the map
   built with ground-truth poses, with drifted poses (a slowly growing rotation and translation
   error: 2 deg / 10 cm and 5 deg / 30 cm at the last frame), and after `remap` of each drifted map
   to the ground-truth poses; the ratio remapped / GT-pose C-L1 (robust to changes of the evaluator).
3. Times (median after warm-up, with the load average): encode of a frame for the map (no
   Jacobian) and with the Jacobian (for `transform`), the pooled-cell count against the points;
   remove + re-encode + fuse of one keyframe (a remap that moves one keyframe), the whole-loop remap;
   sizes of the map and of the keyframe store against the downsampled points and normals of the
   same keyframes (float32).

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
    from jaxmap.imt.transform import transform

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
    """Median seconds of one frame's encode for the map (no Jacobian) and with the Jacobian, and the
    cells / points of those frames."""
    from jaxmap.geometry import SE3
    from jaxmap.imt import latent_map as lm

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
            b = lm.encode_keyframes(mapper.prior, *cl, np.zeros(len(cl[0]), np.int32), 1, c.voxel_size_m,
                                    c.min_points, hints=mapper.hints)
            jax.block_until_ready(b.latent)
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


DRIFTS = {"2 deg / 10 cm": (2.0, 0.10), "5 deg / 30 cm": (5.0, 0.30)}


def main(args) -> int:
    from jaxmap.bench import base_overrides
    from jaxmap.config import ImtConfig, load_config, shipped_config_path
    from jaxmap.imt.mapper import ImtMapper
    from jaxmap.finish import mesh_and_metrics
    from jaxmap.frame_loop import open_run_sequence
    from jaxmap.imt.run import build_map
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
    only = set((args.only or "two_branch,recon").split(","))

    helper = ImtMapper(cfg)
    if "two_branch" in only:
        ids = sorted(set(np.linspace(1, n - 1, 6).round().astype(int).tolist()))
        res["two_branch"] = two_branch(helper, seq, ids, cfg)
        _print_two_branch(res["two_branch"])

    if "recon" in only:
        gt_poses = np.asarray([seq.frame(i).pose for i in range(n)])
        rows, remaps = {}, {}
        m_gt = build_map(cfg, seq, desc="GT poses")
        rows["GT poses"] = mesh_and_metrics(m_gt, cfg, out, "mesh_gt.ply")
        for name, (deg, metres) in DRIFTS.items():
            m_dr = build_map(cfg, seq, poses=drift_poses(gt_poses, deg, metres), desc=f"drift {name}")
            tag = name.split()[0]
            rows[f"drifted {name}"] = mesh_and_metrics(m_dr, cfg, out, f"mesh_drift{tag}.ply")
            t0 = time.perf_counter()
            changed = m_dr.remap(gt_poses)
            remaps[name] = {"keyframes_moved": len(changed), "seconds": time.perf_counter() - t0,
                            "load_avg": os.getloadavg()[0]}
            rows[f"remapped {name}"] = mesh_and_metrics(m_dr, cfg, out, f"mesh_remap{tag}.ply")
        res["recon"] = {k: v.get("metrics", {}) for k, v in rows.items()}
        res["remap"] = remaps
        ids = sorted(set(np.linspace(1, n - 1, 5).round().astype(int).tolist()))
        res["timing"] = {**m_gt.timing_summary(), **time_encode(m_gt, seq, ids),
                         **time_remap_one(m_gt, list(range(0, len(m_gt.store), 7)))}
        res["sizes"] = {**m_gt.sizes(), **store_vs_points(m_gt)}
        _print_recon(res)
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


def _print_recon(res: dict) -> None:
    print(f"\nreconstruction at {res['frames']} frames (threshold 5 cm)")
    print_map_table(res["recon"], width=24)
    gt = res["recon"]["GT poses"].get("chamfer_l1_cm", float("nan"))
    for name, r in res["remap"].items():
        rm = res["recon"][f"remapped {name}"].get("chamfer_l1_cm", float("nan"))
        print(f"drift {name}: remapped / GT-pose C-L1 = {rm / gt:.3f} (target <= 1.10); whole-loop remap of "
              f"{r['keyframes_moved']} keyframes {r['seconds']:.2f} s (target <= 2 s; load {r['load_avg']:.1f})")
    t, s = res["timing"], res["sizes"]
    print(f"\nper frame (median after warm-up, load {t['load_avg']:.1f}): preprocess {t['median_preprocess_s'] * 1e3:.1f} ms, "
          f"encode for the map {t['encode_map_s'] * 1e3:.1f} ms ({t['cells_per_frame']:.0f} cells from "
          f"{t['points_per_frame']:.0f} points), encode with Jacobian for transform {t['encode_jacobian_s'] * 1e3:.1f} ms "
          f"({t.get('jacobian_cells_per_frame', float('nan')):.0f} cells) (target <= 250 ms), "
          f"fuse {t['median_fuse_s'] * 1e3:.1f} ms")
    print(f"remap of one keyframe (remove + re-encode + fuse, one signed batch): {t['remap_one_keyframe_s'] * 1e3:.1f} ms "
          f"(target <= 20 ms)")
    print(f"map: {s['map_voxels']} voxels, {s['map_bytes'] / 1e6:.1f} MB; keyframe store: {s['keyframes']} keyframes, "
          f"{s['cells']} cells, {s['store_bytes'] / 1e6:.2f} MB; their downsampled points + normals (float32): "
          f"{s['points']} points, {s['points_normals_bytes'] / 1e6:.2f} MB")
