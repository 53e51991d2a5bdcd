"""`jaxmap imt CONFIG [--data DIR] [--out RUN]`: encode, fuse, mesh and evaluate a sequence.

A run directory holds:
  config.yaml     the resolved config
  checkpoint/     orbax checkpoint of the latent map and the keyframe store (`ImtMapper.load`)
  mesh.ply        marching-cubes mesh of the latent map (world frame)
  metrics.json    reconstruction metrics when the sequence has ground truth (threshold eval.threshold_m)
  timing.json     per-frame preprocess / encode / fuse times, medians, map and keyframe-store sizes
"""
from __future__ import annotations

import json
import logging
import os
import sys
import time

import numpy as np

from jaxmap.config import ImtConfig, config_from_args, save_config

log = logging.getLogger("jaxmap")


def open_run_sequence(cfg: ImtConfig):
    from jaxmap.io import open_sequence

    d = cfg.data
    return open_sequence(d.path, kind=d.kind, begin_frame=d.begin_frame, end_frame=d.end_frame,
                         every_frame=d.every_frame, topic=d.topic)


def build_map(cfg: ImtConfig, seq, poses=None, progress: bool = True, mapper=None, desc: str = "imt"):
    """Fuse every frame of `seq` (with `poses` [n,4,4] instead of the sequence's, if given)."""
    from jaxmap.imt.mapper import ImtMapper

    mapper = mapper or ImtMapper(cfg)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(seq), unit="frame", desc=desc, file=sys.stderr)
    for i in range(len(seq)):
        fr = seq.frame(i)
        info = mapper.add_frame(fr.points, fr.pose if poses is None else poses[i], frame=fr.index)
        if bar is not None:
            bar.set_postfix(enc=f"{info['encode_s']:.2f}s", voxels=info["map_voxels"])
            bar.update(1)
    if bar is not None:
        bar.close()
    return mapper


def summarize(timings: list[dict], skip_first: int = 1) -> dict:
    rows = timings[skip_first:] if len(timings) > skip_first else timings
    return {f"median_{k}": float(np.median([r[k] for r in rows])) if rows else float("nan")
            for k in ("preprocess_s", "encode_s", "fuse_s")}


def mesh_and_evaluate(mapper, cfg: ImtConfig, out_dir: str, name: str = "mesh.ply", evaluate: bool = True) -> dict:
    """Write the mesh; metrics against the sequence's ground truth when it has one."""
    t0 = time.perf_counter()
    mesh = mapper.mesh()
    path = os.path.join(out_dir, name)
    mesh.export(path)
    out = {"mesh": path, "faces": int(len(mesh.faces)), "mesh_s": time.perf_counter() - t0}
    gt = os.path.join(cfg.data.path, "gt_points.ply")
    if evaluate and os.path.isfile(gt):
        if len(mesh.faces) == 0:
            log.warning("the mesh %s is empty: no metrics", path)
            return out
        from jaxmap.metrics import evaluate_mesh_file

        d, p = cfg.data, cfg.preprocess
        out["metrics"] = evaluate_mesh_file(
            path, d.path, threshold_m=cfg.eval.threshold_m, cull_distance_m=cfg.eval.cull_distance_m,
            eval_radius_m=cfg.eval.eval_radius_m, n_samples=cfg.eval.n_samples, begin_frame=d.begin_frame,
            end_frame=d.end_frame, every_frame=d.every_frame, min_range_m=p.min_range_m, max_range_m=p.max_range_m)
    return out


def run_imt(cfg: ImtConfig, out_dir: str, progress: bool = True, evaluate: bool = True) -> dict:
    os.makedirs(out_dir, exist_ok=True)
    save_config(cfg, os.path.join(out_dir, "config.yaml"))
    seq = open_run_sequence(cfg)
    mapper = build_map(cfg, seq, progress=progress)
    mapper.save(os.path.join(out_dir, "checkpoint"))
    res = mesh_and_evaluate(mapper, cfg, out_dir, evaluate=evaluate)
    timing = {"frames": mapper.timings, "summary": summarize(mapper.timings), "sizes": mapper.sizes(),
              "mesh_s": res["mesh_s"]}
    with open(os.path.join(out_dir, "timing.json"), "w") as f:
        json.dump(timing, f)
    if "metrics" in res:
        with open(os.path.join(out_dir, "metrics.json"), "w") as f:
            json.dump(res["metrics"], f)
    return {"run": out_dir, **res, **timing["summary"], **timing["sizes"]}


def cli_imt(args) -> int:
    cfg = config_from_args(args, ImtConfig)
    summary = run_imt(cfg, cfg.output, progress=cfg.progress and not args.no_progress)
    print(json.dumps(summary))
    return 0
