"""`jaxmap imt CONFIG [--data DIR] [--out RUN]`: encode, fuse, mesh and evaluate a sequence.

A run directory holds:
  config.yaml     the resolved config
  checkpoint/     orbax checkpoint of the latent map and the keyframe store (`ImtMapper.load`)
  mesh.ply        marching-cubes mesh of the latent map (world frame)
  metrics.json    reconstruction metrics when the sequence has ground truth (threshold eval.threshold_m)
  timing.json     per-frame preprocess / encode / fuse times, medians, map and keyframe-store sizes

With `--view` (`run_imt(..., view={"port": 8080, "mesh_every": 10})`) a live browser viewer
(`jaxmap.viewer`) shows each frame's points, the trajectory and a mesh re-extracted in a background
thread every `mesh_every` frames while the map is built.
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


def build_map(cfg: ImtConfig, seq, poses=None, progress: bool = True, mapper=None, desc: str = "imt", hooks=None):
    """Fuse every frame of `seq` (with `poses` [n,4,4] instead of the sequence's, if given).
    hooks: a `jaxmap.viewer.ViewerHooks` that is shown every frame (None = no viewer)."""
    from jaxmap.imt.mapper import ImtMapper

    mapper = mapper or ImtMapper(cfg)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(seq), unit="frame", desc=desc, file=sys.stderr)
    for i in range(len(seq)):
        fr = seq.frame(i)
        pose = fr.pose if poses is None else poses[i]
        info = mapper.add_frame(fr.points, pose, frame=fr.index)
        if hooks is not None:
            from jaxmap.viewer import to_world

            hooks.on_frame(int(fr.index), to_world(fr.points, pose, hooks.viewer.max_points), pose, info)
        if bar is not None:
            bar.set_postfix(enc=f"{info['encode_s']:.2f}s", voxels=info["map_voxels"])
            bar.update(1)
    if bar is not None:
        bar.close()
    return mapper


def summarize(timings: list[dict], skip_first: int = 1) -> dict:
    rows = timings[skip_first:] if len(timings) > skip_first else timings
    out = {f"median_{k}": float(np.median([r[k] for r in rows])) if rows else float("nan")
           for k in ("preprocess_s", "encode_s", "fuse_s")}
    out["empty_frames"] = int(sum(1 for r in timings if r.get("points", 1) == 0))  # nothing left to encode
    return out


def mesh_and_evaluate(mapper, cfg: ImtConfig, out_dir: str, name: str = "mesh.ply", evaluate: bool = True,
                      floor: bool = True) -> dict:
    """Write the mesh; metrics against the sequence's ground truth when it has one (with the protocol
    floor under "floor" unless floor=False)."""
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
            end_frame=d.end_frame, every_frame=d.every_frame, min_range_m=p.min_range_m, max_range_m=p.max_range_m,
            floor=floor)
    return out


def start_view(view: dict | None, mapper):
    """ViewerHooks for `view` = {"port": int, "mesh_every": int} (None: no viewer), meshing `mapper` in the
    background at half its mesh resolution (a preview; the final mesh is the full one)."""
    if not view:
        return None
    from jaxmap.viewer import attach_viewer

    res = max(2, (mapper.cfg.mesh.resolution // 2) // 2 * 2)   # the live mesh at half the lattice resolution
    return attach_viewer(port=int(view.get("port", 8080)), mesh_every=int(view.get("mesh_every", 10)),
                         mesh_fn=lambda: mapper.mesh(resolution=res))


def finish_view(hooks, mesh_path: str | None, out_dir: str) -> None:
    """Show the final mesh, then stop the viewer (`jaxmap view RUN` opens the run again)."""
    if hooks is None:
        return
    mesh = None
    if mesh_path and os.path.isfile(mesh_path):
        import trimesh

        mesh = trimesh.load(mesh_path, process=False, force="mesh")
    hooks.finish(mesh)
    hooks.close()
    log.info("viewer closed; `jaxmap view %s` shows the finished run", out_dir)


def run_imt(cfg: ImtConfig, out_dir: str, progress: bool = True, evaluate: bool = True,
            view: dict | None = None) -> dict:
    from jaxmap.imt.mapper import ImtMapper

    os.makedirs(out_dir, exist_ok=True)
    save_config(cfg, os.path.join(out_dir, "config.yaml"))
    seq = open_run_sequence(cfg)
    mapper = ImtMapper(cfg)
    hooks = start_view(view, mapper)
    try:
        mapper = build_map(cfg, seq, progress=progress, mapper=mapper, hooks=hooks)
        mapper.save(os.path.join(out_dir, "checkpoint"))
        res = mesh_and_evaluate(mapper, cfg, out_dir, evaluate=evaluate)
    except BaseException:
        if hooks is not None:
            hooks.close()
        raise
    finish_view(hooks, res.get("mesh"), out_dir)
    timing = {"frames": mapper.timings, "summary": summarize(mapper.timings), "sizes": mapper.sizes(),
              "mesh_s": res["mesh_s"]}
    with open(os.path.join(out_dir, "timing.json"), "w") as f:
        json.dump(timing, f)
    if "metrics" in res:
        with open(os.path.join(out_dir, "metrics.json"), "w") as f:
            json.dump(res["metrics"], f)
    return {"run": out_dir, **res, **timing["summary"], **timing["sizes"]}


def cli_imt(args) -> int:
    from jaxmap.rundir import claim
    from jaxmap.viewer import view_options

    cfg = config_from_args(args, ImtConfig)
    with claim(cfg.output, "imt", overwrite=args.overwrite):  # one writer; an existing run needs --overwrite
        summary = run_imt(cfg, cfg.output, progress=cfg.progress and not args.no_progress, view=view_options(args))
    print(json.dumps(summary))
    return 0
