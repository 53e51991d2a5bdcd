"""Runs of the N3 mapper: `jaxmap map`, `jaxmap mesh`, `jaxmap demo`.

A run directory holds:
  config.yaml     the resolved config the run used
  checkpoint/     orbax checkpoint of the whole map (written every `checkpoint_every` frames,
                  at the end, and on Ctrl-C), what `--resume` and `jaxmap mesh` read
  mesh.ply        the marching-cubes mesh at mesh.resolution_m (world frame)
  metrics.json    reconstruction metrics, when the sequence has ground truth (gt_points.ply)
  timing.json     per-frame timings (preprocess / sampling / training) and store sizes, plus medians
"""
from __future__ import annotations

import json
import logging
import os
import sys
import time

import numpy as np

from jaxmap.config import ConfigError, MapConfig, config_from_args, load_config, save_config, shipped_config_path
from jaxmap.errors import DataError

log = logging.getLogger("jaxmap")


def summarize_timings(timings: list[dict], skip_first: int = 1) -> dict:
    """Medians over frames after the first `skip_first` (compilation) frames."""
    rows = timings[skip_first:] if len(timings) > skip_first else timings
    out = {}
    for k in ("preprocess_s", "sampling_s", "training_s", "total_s"):
        vals = [r[k] for r in rows]
        out[f"median_{k}"] = float(np.median(vals)) if vals else float("nan")
    if timings:
        out["max_store_pairs"] = int(max(r["store_pairs"] for r in timings))
        out["final_feature_rows"] = int(timings[-1]["feature_rows"])
    return out


def map_sequence(cfg: MapConfig, out_dir: str, *, resume: bool = False, progress: bool = True,
                 mapper=None, evaluate: bool = True) -> dict:
    """Map cfg.data.path into out_dir; returns a summary dict (paths, metrics, timing medians)."""
    from jaxmap.io import open_sequence
    from jaxmap.n3.mapper import N3Mapper

    os.makedirs(out_dir, exist_ok=True)
    ckpt = os.path.join(out_dir, "checkpoint")
    seq = open_sequence(cfg.data.path, kind=cfg.data.kind, begin_frame=cfg.data.begin_frame,
                        end_frame=cfg.data.end_frame, every_frame=cfg.data.every_frame)
    if resume:
        mapper = N3Mapper.load(ckpt)
        log.info("resuming %s at frame %d of %d", out_dir, int(mapper.state.frame), len(seq))
    else:
        mapper = mapper or N3Mapper(cfg)
        save_config(cfg, os.path.join(out_dir, "config.yaml"))
    start = int(mapper.state.frame)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(seq), initial=start, unit="frame", desc="mapping", file=sys.stderr)
    every = max(cfg.checkpoint_every, 1)
    done_since_save = 0
    try:
        for i in range(start, len(seq)):
            fr = seq.frame(i)
            info = mapper.add_frame(fr.points, fr.pose)
            done_since_save += 1
            if bar is not None:
                bar.set_postfix(loss=f"{info['loss']:.4f}", t=f"{info['total_s']:.2f}s",
                                store=info["store_pairs"])
                bar.update(1)
            if done_since_save >= every and i + 1 < len(seq):
                mapper.save(ckpt)
                done_since_save = 0
    except KeyboardInterrupt:
        # add_frame only swaps in a new state once a frame is complete, so this state is consistent.
        if bar is not None:
            bar.close()
        mapper.save(ckpt)
        print(f"\ninterrupted: checkpoint of {int(mapper.state.frame)} frames saved in {ckpt}; "
              f"continue with: jaxmap map --resume {out_dir}", file=sys.stderr)
        raise
    if bar is not None:
        bar.close()
    mapper.save(ckpt)
    return finish_run(mapper, cfg, out_dir, seq, evaluate=evaluate)


def finish_run(mapper, cfg: MapConfig, out_dir: str, seq, evaluate: bool = True) -> dict:
    """Mesh, metrics and timings of a finished map."""
    t0 = time.perf_counter()
    mesh = mapper.mesh(cfg.mesh.resolution_m)
    mesh_path = os.path.join(out_dir, "mesh.ply")
    mesh.export(mesh_path)
    mesh_s = time.perf_counter() - t0
    timing = {"frames": mapper.timings, "summary": summarize_timings(mapper.timings), "mesh_s": mesh_s}
    with open(os.path.join(out_dir, "timing.json"), "w") as f:
        json.dump(timing, f)
    summary = {"run": out_dir, "mesh": mesh_path, "faces": int(len(mesh.faces)), **timing["summary"]}
    if evaluate and seq.gt_points_path and len(mesh.faces) == 0:
        log.warning("the mesh is empty (too few frames or iterations?): no metrics written; the map is in %s",
                    os.path.join(out_dir, "checkpoint"))
    elif evaluate and seq.gt_points_path:
        from jaxmap.metrics import evaluate_mesh_file

        radius = cfg.eval.eval_radius_m
        metrics = evaluate_mesh_file(mesh_path, cfg.data.path, threshold_m=cfg.eval.threshold_m,
                                     cull_distance_m=cfg.eval.cull_distance_m, eval_radius_m=radius,
                                     n_samples=cfg.eval.n_samples, **_frame_selection(cfg))
        with open(os.path.join(out_dir, "metrics.json"), "w") as f:
            json.dump(metrics, f)
        summary["metrics"] = metrics
    return summary


def city_config_path() -> str | None:
    """configs/city.yaml of the source checkout, or None (see `config.shipped_config_path`)."""
    return shipped_config_path("city.yaml")


def _frame_selection(cfg: MapConfig) -> dict:
    """The frames and range a run mapped, so that GT culling uses exactly what the mapper saw."""
    return {"begin_frame": cfg.data.begin_frame, "end_frame": cfg.data.end_frame,
            "every_frame": cfg.data.every_frame, "min_range_m": cfg.preprocess.min_range_m,
            "max_range_m": cfg.preprocess.max_range_m}


def cli_map(args) -> int:
    if args.resume:
        cfg_path = os.path.join(args.resume, "config.yaml")
        if not os.path.isfile(cfg_path):
            raise DataError(f"{args.resume}: no config.yaml; is this a jaxmap run directory?")
        if args.overrides or args.data:
            raise ConfigError("--resume continues a run with its own config.yaml; drop --set/--data")
        cfg = load_config(cfg_path)
        out = args.resume
    else:
        if not args.config:
            raise ConfigError("jaxmap map needs a CONFIG (e.g. configs/city.yaml) or --resume RUN_DIR")
        cfg = config_from_args(args)
        out = cfg.output
    try:
        summary = map_sequence(cfg, out, resume=bool(args.resume), progress=not args.no_progress)
    except KeyboardInterrupt:
        return 130
    print(json.dumps(summary))
    return 0


def cli_mesh(args) -> int:
    from jaxmap.n3.mapper import N3Mapper

    mapper = N3Mapper.load(os.path.join(args.run, "checkpoint"))
    res = args.res or mapper.cfg.mesh.resolution_m
    mesh = mapper.mesh(res)
    out = args.out or os.path.join(args.run, f"mesh_{res:g}.ply")
    mesh.export(out)
    print(json.dumps({"mesh": out, "faces": int(len(mesh.faces)), "vertices": int(len(mesh.vertices))}))
    return 0


def cli_demo(args) -> int:
    """Synthesize the city (once), map it with configs/city.yaml, mesh, evaluate, say where it went."""
    from jaxmap.synth.city import generate_city

    if not os.path.isfile(os.path.join(args.data, "poses.txt")):
        log.info("synthesizing the demo city into %s", args.data)
        generate_city(args.data, seed=0)
    cfg = load_config(city_config_path(), [f"data.path={args.data}", f"output={args.out}"])
    summary = map_sequence(cfg, args.out)
    m = summary.get("metrics", {})
    print(f"\nmesh:    {summary['mesh']}")
    print(f"metrics: {os.path.join(args.out, 'metrics.json')}")
    print(f"timing:  {os.path.join(args.out, 'timing.json')}  (median {summary['median_total_s']:.2f} s/frame)")
    if m:
        print(json.dumps(m))
    return 0
