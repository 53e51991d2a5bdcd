"""`jaxmap bench imt`: the transformable latent map on the synthetic room, in one run.

1. The IMT paper's two-branch test (section IV-B): for keyframes i, encode frame i at the pose of
   frame 0 and transform the local map by `T_i T_0^-1` (branch A), versus encode it at `T_i`
   (branch B); mesh both and measure Accuracy (A's surface samples to B's mesh) and Completeness
   (B's to A's), in cm. Rows: jaxmap (trilinear, `F - J t`), the paper's sign (`F + J t`), no
   Jacobian term, and the paper's softmax weighting (with the correct sign and with the paper's
   sign and metre-unit temperature).
2. Reconstruction (Acc / Comp / C-L1 / Comp. ratio / F-score at eval.threshold_m = 5 cm) of the map
   built with ground-truth poses, with drifted poses (a slowly growing rotation and translation
   error), and after `remap` of the drifted map to the ground-truth poses.
3. Per-frame time of encode, remove, transform + interpolate, and fuse; sizes of the map and of the
   keyframe store.

Everything is written to OUT/bench.json (meshes under OUT/).
"""
from __future__ import annotations

import json
import os
import time

import jax
import numpy as np

COLS = ("accuracy_cm", "completion_cm", "chamfer_l1_cm", "completion_ratio", "f_score")


def drift_poses(poses: np.ndarray, rot_deg: float = 2.0, trans_m: float = 0.10) -> np.ndarray:
    """Poses with an error that grows linearly to `rot_deg` (about a tilted axis) and `trans_m` at the
    last frame, applied in the world frame about the first camera: a slow odometry drift."""
    from jaxmap.geometry import make_pose, rotation_from_axis_angle

    n = len(poses)
    axis = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    direction = np.array([1.0, 0.6, -0.2]) / np.linalg.norm([1.0, 0.6, -0.2])
    c = poses[0][:3, 3]
    out = []
    for k, P in enumerate(poses):
        a = k / max(n - 1, 1)
        R = rotation_from_axis_angle(axis, np.deg2rad(rot_deg) * a)
        E = make_pose(R, c - R @ c + trans_m * a * direction)
        out.append(E @ P)
    return np.asarray(out)


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
        b = mapper.encode(pts, nrm, fr.pose)
        a0 = mapper.encode(pts, nrm, T0)
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


def time_ops(mapper, ks) -> dict:
    """Median seconds of remove, transform + interpolate, and fuse for single keyframes."""
    from jaxmap.geometry import make_pose, rotation_from_axis_angle
    from jaxmap.imt import latent_map as lm
    from jaxmap.imt.transform import splat_trilinear

    vs = mapper.map.voxel_size
    T = make_pose(rotation_from_axis_angle(np.array([0.0, 0.0, 1.0]), 0.01), np.array([0.013, -0.007, 0.004]))
    t_rm, t_tr, t_fu = [], [], []
    m = mapper.map
    for r in range(2):  # the first round compiles
        for k in ks:
            b = mapper.store.locals_[k]
            t0 = time.perf_counter()
            m = lm.remove(m, b)
            jax.block_until_ready(m.latent)
            t1 = time.perf_counter()
            c = splat_trilinear(b, T.astype(np.float32), vs, -1.0, 2.0)
            jax.block_until_ready(c.latent)
            t2 = time.perf_counter()
            m = lm.fuse(m, c)
            jax.block_until_ready(m.latent)
            t3 = time.perf_counter()
            m = lm.fuse(lm.remove(m, c), b)  # put it back for the next round
            if r:
                t_rm.append(t1 - t0)
                t_tr.append(t2 - t1)
                t_fu.append(t3 - t2)
    return {"remove_s": float(np.median(t_rm)), "transform_interpolate_s": float(np.median(t_tr)),
            "fuse_s": float(np.median(t_fu))}


def main(args) -> int:
    from jaxmap.bench import base_overrides
    from jaxmap.config import ImtConfig, load_config, shipped_config_path
    from jaxmap.imt.mapper import ImtMapper
    from jaxmap.imt.run import build_map, mesh_and_evaluate, open_run_sequence, summarize
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
        drifted = drift_poses(gt_poses)
        rows = {}
        m_gt = build_map(cfg, seq, desc="GT poses")
        rows["GT poses"] = mesh_and_evaluate(m_gt, cfg, out, "mesh_gt.ply")
        m_dr = build_map(cfg, seq, poses=drifted, desc="drifted poses")
        rows["drifted poses"] = mesh_and_evaluate(m_dr, cfg, out, "mesh_drift.ply")
        t0 = time.perf_counter()
        changed = m_dr.remap(gt_poses)
        remap_s = time.perf_counter() - t0
        rows["remapped to GT"] = mesh_and_evaluate(m_dr, cfg, out, "mesh_remap.ply")
        res["recon"] = {k: v.get("metrics", {}) for k, v in rows.items()}
        res["remap"] = {"keyframes_moved": len(changed), "seconds": remap_s}
        res["timing"] = {**summarize(m_gt.timings), **time_ops(m_gt, list(range(0, len(m_gt.store), 7)))}
        res["sizes"] = m_gt.sizes()
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
    print(f"{'map':16s} {'Acc cm':>7s} {'Comp cm':>8s} {'C-L1 cm':>8s} {'CR %':>6s} {'F %':>6s}")
    print("-" * 56)
    for name, m in res["recon"].items():
        vals = [m.get(c, float("nan")) for c in COLS]
        print(f"{name:16s} {vals[0]:7.2f} {vals[1]:8.2f} {vals[2]:8.2f} {vals[3]:6.2f} {vals[4]:6.2f}")
    gt = res["recon"]["GT poses"].get("chamfer_l1_cm", float("nan"))
    rm = res["recon"]["remapped to GT"].get("chamfer_l1_cm", float("nan"))
    print(f"remapped / GT-pose C-L1 = {rm / gt:.3f} (target <= 1.10); remap of {res['remap']['keyframes_moved']} "
          f"keyframes took {res['remap']['seconds']:.2f} s")
    t, s = res["timing"], res["sizes"]
    print(f"\nper frame (median): preprocess {t['median_preprocess_s'] * 1e3:.1f} ms, encode "
          f"{t['median_encode_s'] * 1e3:.1f} ms, remove {t['remove_s'] * 1e3:.1f} ms, transform + interpolate "
          f"{t['transform_interpolate_s'] * 1e3:.1f} ms, fuse {t['fuse_s'] * 1e3:.1f} ms "
          f"(paper, GTX 2080 Ti: 7.7 / 4.0 / 18 / 3.2 ms)")
    print(f"map: {s['map_voxels']} voxels, {s['map_bytes'] / 1e6:.1f} MB; keyframe store: {s['keyframes']} keyframes, "
          f"{s['store_voxels']} voxels, {s['store_bytes'] / 1e6:.1f} MB")
