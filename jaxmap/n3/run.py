"""Runs of the N3 mapper: `jaxmap map`, `jaxmap mesh`, `jaxmap demo`.

A run directory holds:
  config.yaml     the resolved config the run used
  run.json        the command and the run's status (`jaxmap.rundir`; `.jaxmap.lock` while it runs)
  checkpoint/     the last two checkpoints of the whole map, `<frames>/` (one .npy per array + checksums; written
                  every `checkpoint_every` frames, at the end, and on Ctrl-C or SIGTERM), what
                  `--resume` and `jaxmap mesh` read (the newest intact one)
  mesh.ply        the marching-cubes mesh at mesh.resolution_m (world frame)
  metrics.json    reconstruction metrics, when the sequence has ground truth (gt_points.ply)
  timing.json     per-frame timings (preprocess / sampling / training) and store sizes, plus medians
"""
from __future__ import annotations

import json
import logging
import os
import signal
import sys
import time

import numpy as np

from jaxmap.config import (ConfigError, MapConfig, config_from_args, lattice_problem, load_config, save_config,
                           shipped_config_path, to_dict)
from jaxmap.errors import CheckpointError, DataError, NoCheckpointError
from jaxmap.hostmem import peak_rss_mb
from jaxmap.rundir import claim, interrupt_requests, output_file

log = logging.getLogger("jaxmap")


def summarize_timings(timings: list[dict], skip_first: int = 1) -> dict:
    """Per-frame medians and p95 over frames after the first `skip_first` (compiling) frames, and the
    count of frames that had no point to map (`empty_frames`: empty scans, or all cropped away)."""
    rows = timings[skip_first:] if len(timings) > skip_first else timings
    out = {}
    for k in ("preprocess_s", "map_s", "total_s"):
        vals = [r[k] for r in rows if k in r]
        out[f"median_{k}"] = float(np.median(vals)) if vals else float("nan")
    vals = [r["total_s"] for r in rows if "total_s" in r]
    out["p95_total_s"] = float(np.percentile(vals, 95)) if vals else float("nan")
    out["empty_frames"] = int(sum(1 for r in timings if r.get("points", 1) == 0))
    if timings:
        out["max_store_pairs"] = int(max(r["store_pairs"] for r in timings))
        out["final_feature_rows"] = int(timings[-1]["feature_rows"])
    return out


def map_sequence(cfg: MapConfig, out_dir: str, *, resume: bool = False, progress: bool = True,
                 mapper=None, evaluate: bool = True, mesh: bool = True, view: dict | None = None) -> dict:
    """Map cfg.data.path into out_dir; returns a summary dict (paths, metrics, timings).

    Frames are read and preprocessed one or two ahead in a background thread (`scan.Prefetcher`),
    so the device maps frame i while the host prepares frame i + 1. `wall_s` in the summary is
    the wall-clock time of the mapping loop, compilation and checkpoints included: what a user waits.
    resume: continue from the newest intact checkpoint in out_dir (`resume_mapper`). Ctrl-C and SIGTERM
    (in the main thread) stop the loop after the frame being mapped, save a checkpoint and re-raise
    (`jaxmap.rundir.Interrupted`). The caller owns out_dir (`jaxmap.rundir.claim` in the CLI).
    """
    from jaxmap.io import open_sequence
    from jaxmap.n3.mapper import N3Mapper
    from jaxmap.n3.scan import Prefetcher

    os.makedirs(out_dir, exist_ok=True)
    ckpt = os.path.join(out_dir, "checkpoint")
    from jaxmap.n3 import checkpoint
    from jaxmap.n3.core import COMPILE_SECONDS

    t_start = time.perf_counter()
    n_compiles = len(COMPILE_SECONDS)
    d = cfg.data
    seq = open_sequence(d.path, kind=d.kind, begin_frame=d.begin_frame, end_frame=d.end_frame,
                        every_frame=d.every_frame, topic=d.topic)
    if resume:
        mapper = resume_mapper(out_dir, cfg)
        log.info("resuming %s at frame %d of %d", out_dir, mapper.frames, len(seq))
    else:
        if mapper is None:
            first = seq.frame(0) if len(seq) else None
            mapper = N3Mapper(cfg, first_scan=(first.points, first.pose) if first is not None else None)
        save_config(cfg, os.path.join(out_dir, "config.yaml"))
    start = mapper.frames
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(seq), initial=start, unit="frame", desc="mapping", file=sys.stderr)
    every = max(cfg.checkpoint_every, 1)
    done_since_save = 0
    hooks = _viewer_hooks(mapper, cfg, view)
    frames = Prefetcher(seq, start, len(seq), cfg.preprocess)
    with interrupt_requests() as stop:
        try:
            for i, pts, nrm, pose in frames:
                if bar is not None and i == start:  # the first frame compiles the frame program: say so
                    bar.set_description_str(f"mapping (compiling{_compile_estimate()})")
                info = mapper.add_frame(None, None, prepared=(pts, nrm, pose))
                if bar is not None and i == start:
                    bar.set_description_str("mapping")
                if hooks is not None:
                    from jaxmap.viewer import to_world

                    hooks.on_frame(i, to_world(pts, pose, hooks.viewer.max_points), pose, info)
                done_since_save += 1
                if bar is not None:
                    bar.set_postfix(loss=f"{info['loss']:.4f}", t=f"{info['total_s']:.2f}s",
                                    store=info["store_pairs"])
                    bar.update(1)
                # Written while the next frames map; if the last one is still being written (a GPU maps
                # 10 frames faster than a map is written), the next frame tries again.
                if done_since_save >= every and i + 1 < len(seq) and not checkpoint.saving():
                    mapper.save(ckpt, background=True)
                    done_since_save = 0
                stop.check()  # Ctrl-C or SIGTERM during the frame: stop here, between frames
        except KeyboardInterrupt as e:
            # SIGINT/SIGTERM stop between frames (`stop.check`); a KeyboardInterrupt raised inside a frame
            # leaves the state of the last complete frame, since a frame's new state is only swapped in at
            # its end. Only a second Ctrl-C (`stop.forced`) may cut a frame in half: then nothing is saved.
            frames.close()
            if hooks is not None:
                hooks.close()
            if bar is not None:
                bar.close()
            what = "terminated (SIGTERM)" if getattr(e, "signum", None) == signal.SIGTERM else "interrupted"
            if stop.forced:
                checkpoint.wait_for_saves()
                print(f"\n{what} twice: stopped without saving; continue from the last checkpoint with: "
                      f"jaxmap map --resume {out_dir}", file=sys.stderr)
                raise
            mapper.save(ckpt)
            print(f"\n{what}: checkpoint of {mapper.frames} frames saved in {ckpt}; "
                  f"continue with: jaxmap map --resume {out_dir}", file=sys.stderr)
            raise
        finally:
            frames.close()
    if bar is not None:
        bar.close()
    mapper.save(ckpt)
    wall = time.perf_counter() - t_start
    extra = {"compile_s": float(sum(COMPILE_SECONDS[n_compiles:])), "compiles": len(COMPILE_SECONDS) - n_compiles,
             "peak_rss_mapping_mb": peak_rss_mb(), "store_frames_held": mapper.frames_held()}
    summary = finish_run(mapper, cfg, out_dir, seq, evaluate=evaluate, wall_s=wall, frames_run=len(seq) - start,
                         extra=extra, mesh=mesh)
    if hooks is not None:
        import trimesh

        hooks.finish(trimesh.load(summary["mesh"]) if summary.get("mesh") else None)
        hooks.close()
    return summary


def _viewer_hooks(mapper, cfg: MapConfig, view: dict | None):
    """Live viewer (`--view`): scans and poses every frame, a coarse mesh every N frames made in a
    background thread from a copy of the state (the mapper donates its buffers to the next frame)."""
    if not view:
        return None
    from jaxmap.n3.query import extract_mesh_of
    from jaxmap.viewer import attach_viewer, copy_arrays

    res = 2 * cfg.mesh.resolution_m
    if abs(cfg.grid.leaf_vox_size / res - round(cfg.grid.leaf_vox_size / res)) > 1e-6:
        res = cfg.mesh.resolution_m
    return attach_viewer(port=view["port"], mesh_every=view["mesh_every"],
                         snapshot_fn=lambda: copy_arrays((mapper.static, mapper.state)),
                         mesh_fn=lambda s: extract_mesh_of(*s, res, cfg.mesh.min_component_faces))


def finish_run(mapper, cfg: MapConfig, out_dir: str, seq, evaluate: bool = True, wall_s: float | None = None,
               frames_run: int | None = None, extra: dict | None = None, mesh: bool = True) -> dict:
    """Mesh, metrics and timings of a finished map (`mesh=False`: timings only)."""
    import trimesh

    t0 = time.perf_counter()
    mesh_path = os.path.join(out_dir, "mesh.ply")
    if mesh:
        mesh = mapper.mesh(cfg.mesh.resolution_m)
        mesh.export(mesh_path)
    else:
        mesh, mesh_path, evaluate = trimesh.Trimesh(), None, False
    mesh_s = time.perf_counter() - t0
    summ = summarize_timings(mapper.timings)
    if wall_s is not None and frames_run:
        summ.update({"wall_s": wall_s, "wall_s_per_frame": wall_s / frames_run, "frames_run": frames_run})
    summ.update(extra or {})
    timing = {"frames": mapper.timings, "summary": summ, "mesh_s": mesh_s}
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
                                     n_samples=cfg.eval.n_samples, floor=True, **_frame_selection(cfg))
        with open(os.path.join(out_dir, "metrics.json"), "w") as f:
            json.dump(metrics, f)
        summary["metrics"] = metrics
    summary["peak_rss_mb"] = peak_rss_mb()
    return summary


def city_config_path() -> str | None:
    """configs/city.yaml of the source checkout, or None (see `config.shipped_config_path`)."""
    return shipped_config_path("city.yaml")


def _frame_selection(cfg: MapConfig) -> dict:
    """The frames and range a run mapped, so that GT culling uses exactly what the mapper saw."""
    return {"begin_frame": cfg.data.begin_frame, "end_frame": cfg.data.end_frame,
            "every_frame": cfg.data.every_frame, "min_range_m": cfg.preprocess.min_range_m,
            "max_range_m": cfg.preprocess.max_range_m}


def _compile_estimate() -> str:
    """", up to ~N s" from the last compile of the frame program on this machine, else a typical range."""
    from jaxmap import compile_cache

    est = compile_cache.estimate("n3_step")
    return f", up to ~{est:.0f} s" if est else ", usually 5-30 s"


def _no_usable(run_dir: str, e: CheckpointError) -> CheckpointError:
    faults = "; ".join(getattr(e, "faults", None) or [str(e)])
    return CheckpointError(f"no usable checkpoint in {run_dir} ({faults}); start again with --overwrite")


def resume_mapper(run_dir: str, cfg: MapConfig):
    """The N3Mapper of the newest intact checkpoint of run directory `run_dir` (falling back to the
    previous one with a warning), or a new one at frame 0 (with a warning) when the run never saved
    one. CheckpointError when every checkpoint is damaged, or when the checkpoint's config is not
    `cfg` (the run's config.yaml): then the directory mixes two runs."""
    from jaxmap.n3.mapper import N3Mapper

    try:
        mapper = N3Mapper.load(os.path.join(run_dir, "checkpoint"))
    except NoCheckpointError:
        log.warning("%s: no checkpoint yet (the run stopped before its first one, saved every %d frames): "
                    "mapping again from frame 0", run_dir, cfg.checkpoint_every)
        return N3Mapper(cfg)
    except CheckpointError as e:
        raise _no_usable(run_dir, e) from None
    a, b = to_dict(mapper.cfg), to_dict(cfg)
    differ = [k for k in a if k != "output" and a[k] != b.get(k)]
    if differ:
        raise CheckpointError(f"{run_dir}: the checkpoint and config.yaml were made with different configs "
                              f"(sections {', '.join(differ)}): the directory mixes two runs; start again with "
                              "--overwrite")
    return mapper


def cli_map(args) -> int:
    from jaxmap.rundir import exit_code
    from jaxmap.viewer import view_options

    if args.resume:
        if args.overrides or args.data or args.config or args.out:
            raise ConfigError(f"--resume {args.resume} continues a run with its own config.yaml; drop "
                              "CONFIG/--set/--data/--out (or start a new run with them)")
        out = args.resume
    else:
        if not args.config:
            raise ConfigError("jaxmap map needs a CONFIG (e.g. configs/city.yaml) or --resume RUN_DIR")
        cfg = config_from_args(args)  # validated before the run directory is touched
        out = cfg.output
    try:
        with claim(out, "map", resume=bool(args.resume), overwrite=args.overwrite):
            if args.resume:
                cfg_path = os.path.join(out, "config.yaml")
                if not os.path.isfile(cfg_path):
                    raise DataError(f"{cfg_path}: missing, so the run cannot be continued; start again with "
                                    "--overwrite")
                cfg = load_config(cfg_path)
            summary = map_sequence(cfg, out, resume=bool(args.resume), progress=not args.no_progress,
                                   mesh=not args.no_mesh, view=view_options(args))
    except KeyboardInterrupt as e:
        return exit_code(e)
    print(json.dumps(summary))
    return 0


def cli_mesh(args) -> int:
    """`jaxmap mesh RUN [--res R] [--out PATH]`: a mesh of the newest intact checkpoint of a map run."""
    from jaxmap.n3.mapper import N3Mapper
    from jaxmap.rundir import inspect

    run = args.run
    if not os.path.isdir(run):
        raise DataError(f"{run}: not a directory; pass the run directory of a jaxmap map run (--out of the run)")
    if args.res is not None and not args.res > 0:
        raise ConfigError(f"--res {args.res:g}: must be > 0 (metres), e.g. --res 0.1")
    state = inspect(run)
    if state.command not in (None, "map"):
        raise DataError(f"{run}: holds a jaxmap {state.command} run; jaxmap mesh re-meshes jaxmap map runs")
    try:
        mapper = N3Mapper.load(os.path.join(run, "checkpoint"))
    except NoCheckpointError:
        raise CheckpointError(f"{run}: no checkpoint yet; map at least `checkpoint_every` frames first "
                              f"(continue the run with: jaxmap map --resume {run})") from None
    except CheckpointError as e:
        raise _no_usable(run, e) from None
    res = args.res or mapper.cfg.mesh.resolution_m
    problem = lattice_problem(res, mapper.cfg.grid.leaf_vox_size, "the run's grid.leaf_vox_size")
    if problem:
        raise ConfigError(f"--res {res:g} for {run}: {problem}")
    out = output_file(args.out or os.path.join(run, f"mesh_{res:g}.ply"), "--out")
    mesh = mapper.mesh(res)
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
    with claim(args.out, "map", overwrite=True):  # `make demo` again replaces the last demo run
        summary = map_sequence(cfg, args.out)
    m = summary.get("metrics", {})
    print(f"\nmesh:    {summary['mesh']}")
    print(f"metrics: {os.path.join(args.out, 'metrics.json')}")
    print(f"timing:  {os.path.join(args.out, 'timing.json')}  ({summary.get('wall_s_per_frame', float('nan')):.2f} s "
          f"per frame wall-clock, compilation included; median {summary['median_total_s']:.2f} s)")
    if m:
        print(json.dumps(m))
    return 0
