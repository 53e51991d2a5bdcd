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

import functools
import os
import time

import numpy as np

from jaxmap.config import ImtConfig, save_config
from jaxmap.finish import finish_run
from jaxmap.frame_loop import (Checkpoints, Frame, FramesRun, Prefetcher, Progress, open_run_sequence, open_viewer,
                               run_frames)
from jaxmap.checkpoint import SAVES
from jaxmap.imt.mapper import ImtMapper


def prepare_frame(mapper: ImtMapper, poses, seq, i: int) -> Frame:
    """`Prefetcher` loader of frame i: read, preprocessed and pooled at its pose (the sequence's, or
    poses[i]) on the host (`ImtMapper.prepare`), off the main thread; `batch` holds the `HostScan`."""
    fr = seq.frame(i)
    pose = np.asarray(fr.pose if poses is None else poses[i], np.float64)
    prepared = mapper.prepare(fr.points, pose)
    return Frame(i, int(fr.index), prepared.points, pose, prepared.normals, batch=prepared)


def fuse_frame(mapper: ImtMapper, frame: Frame) -> tuple[dict, np.ndarray]:
    """The transformable map's step of the frame loop: the prepared frame fused at its pose."""
    return mapper.add_prepared(frame.batch, frame.pose, frame=frame.index), frame.pose


def fuse_sequence(mapper: ImtMapper, seq, poses=None, progress: bool = True, desc: str = "imt", viewer=None,
                  checkpoints: Checkpoints | None = None, t_start: float | None = None) -> FramesRun:
    """Fuse every frame of `seq` into `mapper` at the sequence's poses (or `poses` [n, 4, 4]) through the
    frame loop, each prepared ahead in the prefetch threads. viewer: `jaxmap.viewer.ViewerHooks` shown
    every frame (None = no viewer)."""
    bar = Progress(desc, progress, postfix=lambda r: {"enc": f"{r['encode_s']:.2f}s", "voxels": r["map_voxels"]})
    frames = Prefetcher(seq, 0, len(seq), functools.partial(prepare_frame, mapper, poses))
    return run_frames(frames, functools.partial(fuse_frame, mapper), total=len(seq), progress=bar, viewer=viewer,
                      checkpoints=checkpoints, t_start=t_start)


def build_map(cfg: ImtConfig, seq, poses=None, progress: bool = True, desc: str = "imt") -> ImtMapper:
    """A new map of every frame of `seq` (at `poses` [n, 4, 4] instead of the sequence's, if given)."""
    mapper = ImtMapper(cfg)
    fuse_sequence(mapper, seq, poses, progress, desc)
    return mapper


def run_imt(cfg: ImtConfig, out_dir: str, progress: bool = True, evaluate: bool = True,
            view: dict | None = None) -> dict:
    """Map cfg.data.path into out_dir with the transformable latent map; returns the run's summary."""
    t_start = time.perf_counter()
    os.makedirs(out_dir, exist_ok=True)
    save_config(cfg, os.path.join(out_dir, "config.yaml"))
    seq = open_run_sequence(cfg)
    mapper = ImtMapper(cfg)
    viewer = open_viewer(view, mapper)
    ckpt = os.path.join(out_dir, "checkpoint")
    # the last checkpoint is written in the background while the map is meshed (nothing changes the map then)
    saves = Checkpoints(save=lambda background: mapper.save(ckpt, background=background), path=ckpt,
                        busy=SAVES.busy, wait=SAVES.wait, final=lambda: mapper.save(ckpt, background=True, copy=False))
    loop = fuse_sequence(mapper, seq, progress=progress, viewer=viewer, checkpoints=saves, t_start=t_start)
    return finish_run(mapper, cfg, out_dir, loop, evaluate=evaluate, viewer=viewer, wait_saves=SAVES.wait)
