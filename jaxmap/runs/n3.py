"""Runs of the N3 mapper: `jaxmap map`, `jaxmap mesh`, `jaxmap demo`.

A run directory holds:
  config.yaml     the resolved config the run used
  run.json        the command and the run's status (`jaxmap.rundir`; `.jaxmap.lock` while it runs)
  checkpoint/     the last two checkpoints of the whole map, `<frames>/` (one .npy per array + checksums; written
                  every `checkpoint_every` frames, at the end, and on Ctrl-C or SIGTERM), what
                  `--resume` and `jaxmap mesh` read (the newest intact one)
  submaps/        with submaps.enabled: one N3 checkpoint per submap, `<id>/<frame>/` (written when the sensor
                  leaves it; the index of submaps is in checkpoint/)
  mesh.ply        the marching-cubes mesh at mesh.resolution_m (world frame)
  metrics.json    reconstruction metrics, when the sequence has ground truth (gt_points.ply); with moving
                  objects (moving_objects.json) also "dynamic_points": SA / DA of the points trained on
                  (`jaxmap.metrics.dynamic`; after a --resume, of the frames mapped since)
  timing.json     per-frame timings (preprocess / sampling / training) and store sizes, plus medians
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import os
import time

import numpy as np

from jaxmap import compile_cache
from jaxmap.config import MapConfig, save_config, shipped_config_path, to_dict
from jaxmap.errors import CheckpointError, NoCheckpointError
from jaxmap.finish import finish_run
from jaxmap.frame_loop import (Checkpoints, Prefetcher, Progress, SubmitSteps, open_run_sequence, open_viewer,
                               prepared_frame, run_frames)
from jaxmap.geometry import path_length
from jaxmap.hostmem import peak_rss_mb
from jaxmap.metrics import dynamic
from jaxmap.n3 import checkpoint
from jaxmap.n3.core import PROGRAMS
from jaxmap.n3.mapper import N3Mapper
from jaxmap.n3.scan import MapStart
from jaxmap.n3.submap_mapper import load_map, new_map

log = logging.getLogger("jaxmap")


def map_sequence(cfg: MapConfig, out_dir: str, *, resume: bool = False, progress: bool = True,
                 evaluate: bool = True, mesh: bool = True, view: dict | None = None) -> dict:
    """Map cfg.data.path into out_dir; returns a summary dict (paths, metrics, timings).

    Frames are read, preprocessed and uploaded ahead in background threads (`frame_loop.Prefetcher`,
    from the start, while the frame program compiles), and each frame's program is dispatched before
    the previous one's statistics are read (`frame_loop.SubmitSteps`), so the device maps frame after frame
    while the host prepares the next ones and keeps the books. `wall_s` in the summary is the wall-clock
    time of the mapping loop, compilation and checkpoints included: what a user waits.
    resume: continue from the newest intact checkpoint in out_dir (`resume_mapper`). Ctrl-C and SIGTERM
    (in the main thread) stop the loop after the frame being mapped, save a checkpoint and re-raise
    (`jaxmap.rundir.Interrupted`). The caller owns out_dir (`jaxmap.rundir.claim` in the CLI).
    """
    os.makedirs(out_dir, exist_ok=True)
    ckpt, t_start, n_compiles = os.path.join(out_dir, "checkpoint"), time.perf_counter(), PROGRAMS.compiles()
    seq = open_run_sequence(cfg)
    scores = dynamic.RunScores.of_sequence(cfg.data.path)  # None: no moving objects to score
    labeller = scores.label if scores is not None else None
    if resume:
        mapper = resume_mapper(out_dir, cfg, seq)
        log.info("resuming %s at frame %d of %d", out_dir, mapper.frames, len(seq))
        uploader = mapper.uploader()
        load = functools.partial(prepared_frame, mapper.start.prepare, label=labeller)
        frames = Prefetcher(seq, mapper.frames, len(seq), load, then=uploader)
    else:
        # Frames are read, preprocessed and uploaded while the frame program compiles: the map frame
        # is the first pose's, and the first prepared frame gives the program its shapes.
        start = first_start(cfg, seq)
        uploader = start.uploader()
        frames = Prefetcher(seq, 0, len(seq), functools.partial(prepared_frame, start.prepare, label=labeller),
                            then=uploader)
        try:
            first = frames.first()
            mapper = new_map(start, os.path.join(out_dir, "submaps"),
                             first_batch=first.batch if first is not None else None)
        except BaseException:
            frames.close()
            raise
        save_config(mapper.cfg, os.path.join(out_dir, "config.yaml"))
    cfg = mapper.cfg
    viewer = open_viewer(view, mapper)
    saves = Checkpoints(save=lambda background: mapper.save(ckpt, background=background), path=ckpt,
                        every=max(cfg.checkpoint_every, 1), busy=checkpoint.saving, wait=checkpoint.wait_for_saves,
                        resume=f"jaxmap map --resume {out_dir}",
                        final=lambda: mapper.save(ckpt, background=True, copy=False))
    bar = Progress("mapping", progress, first=f"compiling{_compile_estimate()}",
                   postfix=lambda r: {"loss": f"{r['loss']:.4f}", "t": f"{r['total_s']:.2f}s", "store": r["store_pairs"]})
    steps = SubmitSteps(mapper, on_finished=scores.counter(mapper.voxel_coords) if scores is not None else None)
    loop = run_frames(frames, steps, total=len(seq), start=mapper.frames, progress=bar,
                      viewer=viewer, checkpoints=saves, t_start=t_start)
    extra = {**PROGRAMS.compiles_since(n_compiles), "peak_rss_mapping_mb": peak_rss_mb(),
             "store_frames_held": mapper.frames_held()}
    return finish_run(mapper, cfg, out_dir, loop, evaluate=evaluate, mesh=mesh, extra=extra, viewer=viewer,
                      point_scores=scores.result(mapper.void_voxels()) if scores is not None else None,
                      wait_saves=checkpoint.wait_for_saves)


def first_start(cfg: MapConfig, seq, poses=None) -> MapStart:
    """The `MapStart` of a map of `seq` (its first frame's scan, at poses[0] when given, else its pose),
    in submaps when the drive is long (`submaps_for_drive`)."""
    if not len(seq):
        return MapStart.of(cfg)
    cfg = submaps_for_drive(cfg, seq.poses if poses is None else poses)
    first = seq.frame(0)
    return MapStart.of(cfg, first.points, first.pose if poses is None else poses[0])


def submaps_for_drive(cfg: MapConfig, poses) -> MapConfig:
    """cfg with submaps.enabled when the drive is longer than submaps.auto_m: the path of its poses
    [N, 4, 4] (the sensor's positions, known before mapping), so that a long drive maps in bounded memory
    with no flag; unchanged when submaps are on already, auto_m is 0, or the window is a replay ablation
    (one grid only). The run's config.yaml holds the result, so `--resume` maps the same way."""
    sub = cfg.submaps
    if sub.enabled or sub.auto_m <= 0 or cfg.window.mode != "voxel" or len(poses) < 2:
        return cfg
    path = path_length(np.asarray(poses, np.float64)[:, :3, 3])
    if path <= sub.auto_m:
        return cfg
    log.info("the drive is %.0f m long (over submaps.auto_m = %.0f m): mapping it in submaps of %.0f m "
             "(submaps.auto_m=0 keeps one grid)", path, sub.auto_m, sub.length_m)
    return dataclasses.replace(cfg, submaps=dataclasses.replace(sub, enabled=True))


def map_at_poses(cfg: MapConfig, seq, poses, progress: bool = True, desc: str = "mapping"):
    """A new N3 map of every frame of `seq` at `poses` [N, 4, 4] (instead of the sequence's), the frames
    read, preprocessed and uploaded ahead and dispatched ahead of their stats as in `map_sequence`
    (no checkpoints); a map of submaps with `submaps.enabled`. Returns (N3Mapper, frame_loop.FramesRun)."""
    mapper = new_map(first_start(cfg, seq, poses), os.path.join(cfg.output, "submaps"))  # (with submaps.enabled)
    frames = Prefetcher(seq, 0, len(seq), functools.partial(prepared_frame, mapper.start.prepare, poses=poses),
                        then=mapper.uploader())
    return mapper, run_frames(frames, SubmitSteps(mapper), total=len(seq), progress=Progress(desc, progress))


def city_config_path() -> str | None:
    """The shipped config `city` (jaxmap/configs/city.yaml, package data; `config.shipped_config_path`)."""
    return shipped_config_path("city.yaml")


def _compile_estimate() -> str:
    """", up to ~N s" from the last compile of the frame program on this machine, else a typical range."""
    est = compile_cache.estimate("n3_step")
    return f", up to ~{est:.0f} s" if est else ", usually 5-30 s"


def no_usable_checkpoint(run_dir: str, e: CheckpointError) -> CheckpointError:
    faults = "; ".join(getattr(e, "faults", None) or [str(e)])
    return CheckpointError(f"no usable checkpoint in {run_dir} ({faults}); start again with --overwrite")


def resume_mapper(run_dir: str, cfg: MapConfig, seq) -> N3Mapper:
    """The N3Mapper of the newest intact checkpoint of run directory `run_dir` (falling back to the
    previous one with a warning), or a new one at frame 0 of `seq` (with a warning) when the run never
    saved one. CheckpointError when every checkpoint is damaged, or when the checkpoint's config is not
    `cfg` (the run's config.yaml): then the directory mixes two runs."""
    try:
        mapper = load_map(os.path.join(run_dir, "checkpoint"))
    except NoCheckpointError:
        log.warning("%s: no checkpoint yet (the run stopped before its first one, saved every %d frames): "
                    "mapping again from frame 0", run_dir, cfg.checkpoint_every)
        return new_map(first_start(cfg, seq), os.path.join(run_dir, "submaps"))
    except CheckpointError as e:
        raise no_usable_checkpoint(run_dir, e) from None
    a, b = to_dict(mapper.cfg), to_dict(cfg)
    differ = [k for k in a if k != "output" and a[k] != b.get(k)]
    if differ:
        raise CheckpointError(f"{run_dir}: the checkpoint and config.yaml were made with different configs "
                              f"(sections {', '.join(differ)}): the directory mixes two runs; start again with "
                              "--overwrite")
    return mapper
