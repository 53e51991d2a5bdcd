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

import collections
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
from jaxmap.frame_loop import Checkpoints, Frame, Prefetcher, Progress, open_run_sequence, open_viewer, run_frames
from jaxmap.hostmem import peak_rss_mb
from jaxmap.metrics import dynamic
from jaxmap.n3 import checkpoint, scan
from jaxmap.n3.core import COMPILE_SECONDS, compiles_since
from jaxmap.n3.mapper import N3Mapper, origin_at
from jaxmap.n3.submap_mapper import SubmapMapper, load_map
from jaxmap.preprocess_device import resolve

log = logging.getLogger("jaxmap")


def map_sequence(cfg: MapConfig, out_dir: str, *, resume: bool = False, progress: bool = True,
                 evaluate: bool = True, mesh: bool = True, view: dict | None = None) -> dict:
    """Map cfg.data.path into out_dir; returns a summary dict (paths, metrics, timings).

    Frames are read, preprocessed and uploaded ahead in background threads (`frame_loop.Prefetcher`,
    from the start, while the frame program compiles), and each frame's program is dispatched before
    the previous one's statistics are read (`MapSteps`), so the device maps frame after frame while the host
    prepares the next ones and keeps the books. `wall_s` in the summary is the wall-clock time of the
    mapping loop, compilation and checkpoints included: what a user waits.
    resume: continue from the newest intact checkpoint in out_dir (`resume_mapper`). Ctrl-C and SIGTERM
    (in the main thread) stop the loop after the frame being mapped, save a checkpoint and re-raise
    (`jaxmap.rundir.Interrupted`). The caller owns out_dir (`jaxmap.rundir.claim` in the CLI).
    """
    os.makedirs(out_dir, exist_ok=True)
    cfg = dataclasses.replace(cfg, preprocess=resolve(cfg.preprocess))  # device: auto decided (config.yaml says which)
    device = cfg.preprocess.device == "true"
    ckpt, t_start, n_compiles = os.path.join(out_dir, "checkpoint"), time.perf_counter(), len(COMPILE_SECONDS)
    seq = open_run_sequence(cfg)
    labeller = dynamic.labeller_for(cfg.data.path)
    scores = dynamic.PointScores() if labeller is not None else None
    if resume:
        mapper = resume_mapper(out_dir, cfg)
        log.info("resuming %s at frame %d of %d", out_dir, mapper.frames, len(seq))
        if mapper.frames == 0 and len(seq):
            mapper.fix_layout(seq.frame(0).points)
            mapper.place_origin(seq.frame(0).pose)
        cfg = mapper.cfg
        uploader = scan.Uploader(mapper.origin, device, mapper.bucket)
        frames = Prefetcher(seq, mapper.frames, len(seq), _loader(cfg, labeller), then=uploader)
    else:
        # Frames are read, preprocessed and uploaded while the frame program compiles: the map frame
        # is the first pose's, and the first prepared frame gives the program its shapes.
        first = seq.frame(0) if len(seq) else None
        if first is not None:
            cfg = scan.resolve_layout(cfg, first.points)  # the range-image layout read off the first scan
        origin = origin_at(cfg, first.pose) if first is not None else np.zeros(3)
        uploader = scan.Uploader(origin, device)
        frames = Prefetcher(seq, 0, len(seq), _loader(cfg, labeller), then=uploader)
        try:
            mapper = new_mapper(cfg, out_dir, first_frame=frames.first())
        except BaseException:
            frames.close()
            raise
        save_config(cfg, os.path.join(out_dir, "config.yaml"))
    mapper.follow(uploader)  # (a map of submaps moves the uploads' origin to the submap it maps into)
    viewer = open_viewer(view, mapper)
    saves = Checkpoints(save=lambda background: mapper.save(ckpt, background=background), path=ckpt,
                        every=max(cfg.checkpoint_every, 1), busy=checkpoint.saving, wait=checkpoint.wait_for_saves,
                        resume=f"jaxmap map --resume {out_dir}",
                        final=lambda: mapper.save(ckpt, background=True, copy=False))
    bar = Progress("mapping", progress, first=f"compiling{_compile_estimate()}",
                   postfix=lambda r: {"loss": f"{r['loss']:.4f}", "t": f"{r['total_s']:.2f}s", "store": r["store_pairs"]})
    loop = run_frames(frames, MapSteps(mapper, scores), total=len(seq), start=mapper.frames, progress=bar,
                      viewer=viewer, checkpoints=saves, t_start=t_start)
    extra = {**compiles_since(n_compiles), "peak_rss_mapping_mb": peak_rss_mb(),
             "store_frames_held": mapper.frames_held()}
    return finish_run(mapper, cfg, out_dir, loop, evaluate=evaluate, mesh=mesh, extra=extra, viewer=viewer,
                      point_scores=scores.result(dynamic.voxel_keys(mapper.void_voxels())) if scores is not None else None,
                      wait_saves=checkpoint.wait_for_saves)


def new_mapper(cfg: MapConfig, run_dir: str, **kw) -> N3Mapper:
    """The empty map of a run of `cfg` in `run_dir`: one grid (N3Mapper), or with submaps.enabled a
    SubmapMapper writing its submaps to run_dir/submaps. kw: N3Mapper's (first_frame, first_scan)."""
    if cfg.submaps.enabled:
        return SubmapMapper(cfg, directory=os.path.join(run_dir, "submaps"), **kw)
    return N3Mapper(cfg, **kw)


def _loader(cfg: MapConfig, label=None, poses=None):
    """The `Prefetcher` loader of a run of `cfg` (`prepare_frame`, with the range images the map needs)."""
    from jaxmap.n3.state import N3Static

    evidence = N3Static.from_config(cfg).evidence
    return functools.partial(prepare_frame, cfg.preprocess, image=evidence, label=label, poses=poses)


def prepare_frame(cfg_preprocess, seq, i: int, image: bool = False, label=None, poses=None) -> Frame:
    """`Prefetcher` loader of frame i: read, checked and preprocessed on the host, with its range image
    when `image` (with `preprocess.device` true only read and checked: the frame program preprocesses,
    and `normals` is None); at poses[i] when `poses` [N, 4, 4] is given, else at the sequence's pose.
    label: a `jaxmap.metrics.dynamic.Labeller` (the sequence has moving objects): `dynamic` labels its
    points here, in the prefetch thread, off the mapping loop."""
    fr = seq.frame(i)
    pose = fr.pose if poses is None else poses[i]
    img = None
    if cfg_preprocess.device == "true":
        (pts, pose), nrm = scan.check_frame(fr.points, pose, i), None
    else:
        pts, nrm, pose, img = scan.preprocess(fr.points, pose, cfg_preprocess, i, image=image)
    return Frame(i, int(fr.index), pts, pose, nrm, img,
                 dynamic=label(pts, pose, int(fr.index)) if label is not None else None)


def map_at_poses(cfg: MapConfig, seq, poses, progress: bool = True, desc: str = "mapping"):
    """A new N3 map of every frame of `seq` at `poses` [N, 4, 4] (instead of the sequence's), the frames
    read, preprocessed and uploaded ahead and dispatched ahead of their stats as in `map_sequence`
    (no checkpoints); a map of submaps with `submaps.enabled`. Returns (N3Mapper, frame_loop.LoopResult)."""
    cfg = dataclasses.replace(cfg, preprocess=resolve(cfg.preprocess))
    if len(seq):
        cfg = scan.resolve_layout(cfg, seq.frame(0).points)
    mapper = new_mapper(cfg, cfg.output)  # (with submaps.enabled, written to cfg.output's submaps/)
    if len(seq):
        mapper.place_origin(poses[0])
    uploader = scan.Uploader(mapper.origin, cfg.preprocess.device == "true")
    mapper.follow(uploader)
    frames = Prefetcher(seq, 0, len(seq), _loader(cfg, poses=poses), then=uploader)
    return mapper, run_frames(frames, MapSteps(mapper), total=len(seq), progress=Progress(desc, progress))


class MapSteps:
    """The N3 step of the frame loop (`frame_loop.Steps`): each frame's program is dispatched as soon as
    its scan is on the device (`N3Mapper.submit`; the scan was prepared and uploaded ahead by
    `prepare_frame` and `scan.Uploader`), its record comes back a frame later. With `scores`, each
    frame's labelled points are counted against those the mapper trained on."""

    def __init__(self, mapper: N3Mapper, scores: dynamic.PointScores | None = None):
        self.mapper, self.scores = mapper, scores
        self._frames: collections.deque[Frame] = collections.deque()  # submitted, record not back yet

    def submit(self, frame: Frame) -> list:
        self._frames.append(frame)
        return self._paired(self.mapper.submit(frame.batch, points=len(frame.points), prepare_s=frame.prepare_s,
                                               wait_s=frame.wait_s, pose=frame.pose, origin=frame.origin))

    def drain(self) -> list:
        return self._paired(self.mapper.finish())

    def _paired(self, finished: list) -> list:
        out = []
        for record, kept in finished:
            frame = self._frames.popleft()
            if self.scores is not None and frame.dynamic is not None:
                self.scores.add(frame.dynamic, kept,
                                dynamic.voxel_keys(self.mapper.voxel_coords(frame.points, frame.pose)))
            out.append((frame, record, frame.pose))
        return out


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


def resume_mapper(run_dir: str, cfg: MapConfig):
    """The N3Mapper of the newest intact checkpoint of run directory `run_dir` (falling back to the
    previous one with a warning), or a new one at frame 0 (with a warning) when the run never saved
    one. CheckpointError when every checkpoint is damaged, or when the checkpoint's config is not
    `cfg` (the run's config.yaml): then the directory mixes two runs."""
    try:
        mapper = load_map(os.path.join(run_dir, "checkpoint"))
    except NoCheckpointError:
        log.warning("%s: no checkpoint yet (the run stopped before its first one, saved every %d frames): "
                    "mapping again from frame 0", run_dir, cfg.checkpoint_every)
        return new_mapper(cfg, run_dir)
    except CheckpointError as e:
        raise no_usable_checkpoint(run_dir, e) from None
    a, b = to_dict(mapper.cfg), to_dict(cfg)
    differ = [k for k in a if k != "output" and a[k] != b.get(k)]
    if differ:
        raise CheckpointError(f"{run_dir}: the checkpoint and config.yaml were made with different configs "
                              f"(sections {', '.join(differ)}): the directory mixes two runs; start again with "
                              "--overwrite")
    return mapper
