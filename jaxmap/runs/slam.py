"""`jaxmap slam CONFIG [--data DIR] [--out RUN]` and `jaxmap slam --resume RUN`: odometry, loop closure,
pose graph and a neural map that follows each pose correction, one run whatever the map.

`run_slam` drives the frame loop (`jaxmap.frame_loop.run_frames`) with the map kind's step, a
`jaxmap.runs.slam_step.SlamStep` (the sequence's poses.txt is only used for the first pose and for
evaluation):
  - `map_kind: imt` (`jaxmap.runs.slam_imt.ImtSlamStep`): the front end (`FrontEnd`: ICP odometry,
    keyframes, loop verification, open3d pose graph) gives each frame's pose; a keyframe is fused into
    the transformable latent map (`ImtMapper`); an optimised loop remaps the keyframes that moved
    (`ImtMapper.correct`; with `mesh_at_loops` a mesh before and after, `loop_<n>_before.ply`,
    `loop_<n>_after.ply`). With `external_poses: DIR` pose-graph snapshots of another SLAM system
    replace the front end (`SnapshotStep`).
  - `map_kind: n3` (`jaxmap.runs.slam_n3.N3SlamStep`): the N3 map of `n3_config`, mapped online at the
    poses the front end and tracking against that map give, following each loop correction
    (`FollowingMap.correct`).
Every `checkpoint_every` frames, on Ctrl-C or SIGTERM (between two frames) and at the end the run is
saved, the map in checkpoint/ and then the step's state in slam_state.pkl (`save_slam`);
`jaxmap slam --resume RUN` goes on from there (`load_slam`) with the trajectory and map the run would
have made without the stop, also after kill -9 (from the last save). A frame that fails saves the map
as mapped so far and names the frame.

A run directory holds config.yaml, checkpoint/ (the map: `ImtMapper.load`, or `load_map` for N3),
slam_state.pkl, mesh.ply, trajectory_kitti.txt and trajectory_tum.txt (every frame, and
odometry_kitti.txt: odometry alone), the loop meshes, slam.json (ATE of odometry and of the optimised
trajectory against the sequence's poses, per-loop records and timings, tracking), metrics.json
(reconstruction metrics alone, when the sequence has ground truth), timing.json and, with `n3_config`
(map_kind imt), an N3 map built from the optimised poses in n3/. With map_kind n3, n3_config.yaml is
the map's resolved config and slam_scans/ its frames' preprocessed scans.

With `--view` a live browser viewer (`jaxmap.viewer`) shows each frame's points, the trajectory (redrawn
after each pose-graph optimisation), the loop closures and a mesh re-extracted in a background thread.
"""
from __future__ import annotations

import json
import logging
import os
import time

import numpy as np

from jaxmap.config import SlamConfig, save_config
from jaxmap.config.slam import OdometryConfig
from jaxmap.finish import finish_run
from jaxmap.frame_loop import Checkpoints, Frame, Prefetcher, Progress, open_run_sequence, open_viewer, run_frames
from jaxmap.n3.core import PROGRAMS
from jaxmap.runs.slam_imt import open_imt_step
from jaxmap.runs.slam_n3 import n3_map_config, open_n3_step
from jaxmap.runs.slam_step import CHECKPOINT_DIR, SlamStep, load_slam, save_slam
from jaxmap.slam.odometry import make_odometry
from jaxmap.slam.trajectory import ate, axis_errors, write_kitti, write_trajectory

log = logging.getLogger("jaxmap")


def open_step(cfg: SlamConfig, out_dir: str, seq) -> tuple[object, SlamStep]:
    """A new run's (map, step), by map kind: the N3 map (`jaxmap.runs.slam_n3`), or the latent map
    driven by the front end or by pose snapshots (`jaxmap.runs.slam_imt`)."""
    return open_n3_step(cfg, out_dir, seq) if cfg.map_kind == "n3" else open_imt_step(cfg, seq)


def run_slam(cfg: SlamConfig, out_dir: str, progress: bool = True, evaluate: bool = True,
             view: dict | None = None, resume: bool = False, mesh: bool = True, track=None) -> dict:
    """The SLAM run of `cfg` in out_dir, any map kind (see the module docstring): the kind's step over the
    one frame loop, saved every `checkpoint_every` frames, on Ctrl-C / SIGTERM and at the end
    (`jaxmap.runs.slam_step.save_slam`), then finished like every run (`finish_run`).
    view: {"port", "mesh_every"} for a live viewer (`jaxmap.frame_loop.open_viewer`), None = none.
    resume: go on from the run's SLAM checkpoint in out_dir (`load_slam`).
    mesh=False: no mesh and no reconstruction metrics at the end (`jaxmap slam --no-mesh`).
    track: a tracker in place of `jaxmap.slam.track.track_scan` (map_kind n3; tests)."""
    os.makedirs(out_dir, exist_ok=True)
    if not resume:
        save_config(cfg, os.path.join(out_dir, "config.yaml"))
    seq = open_run_sequence(cfg)
    n_compiles = PROGRAMS.compiles()
    if resume:
        mapper, step = load_slam(out_dir)
        log.info("resuming %s at frame %d of %d", out_dir, step.frames_done, len(seq))
    else:
        mapper, step = open_step(cfg, out_dir, seq)
    viewer = open_viewer(view, mapper)
    total = step.frames_to_run(seq)
    step.attach(mapper, viewer=viewer, out_dir=out_dir, total=total, track=track)
    saves = Checkpoints(save=lambda background: save_slam(step, out_dir), path=os.path.join(out_dir, CHECKPOINT_DIR),
                        every=cfg.checkpoint_every, resume=f"jaxmap slam --resume {out_dir}")
    start = step.frames_done
    loop = run_frames(Prefetcher(seq, start, total, step.load_frame), step, total=total, start=start,
                      progress=Progress(step.label, progress, postfix=step.progress), viewer=viewer, checkpoints=saves)
    res = step.results(seq)
    traj = np.asarray(res["trajectory"])
    out = {"run": out_dir, "map_kind": cfg.map_kind, "frames": len(seq), "keyframes": len(res["keyframe_frames"]),
           "loops": res["loops"], **step.summary(res),
           **_write_trajectories(out_dir, seq, traj, res["odometry"], evaluate)}
    rec = finish_run(mapper, mapper.cfg, out_dir, loop, evaluate=evaluate, viewer=viewer, mesh=mesh,
                     extra=step.compiles_since(n_compiles))
    out.update({k: v for k, v in rec.items() if k not in ("run", "peak_rss_mb")})
    # the SLAM run's saves are the step's (save_slam), not the map's own: its record would say 0
    out["checkpoint_s_sum"] = float(sum(r.get("checkpoint_s", 0.0) for r in step.records))
    if cfg.map_kind == "imt" and cfg.n3_config:
        out["n3"] = n3_from_poses(cfg, seq, traj, os.path.join(out_dir, "n3"), progress, mesh=mesh)
    write_slam_summary(out_dir, out)
    return out


def write_slam_summary(out_dir: str, out: dict) -> None:
    """slam.json: the run's SLAM summary (frames, keyframes, loops, ATE, tracking, step timings); the
    reconstruction metrics are metrics.json's alone (`finish_run` wrote it)."""
    with open(os.path.join(out_dir, "slam.json"), "w") as f:
        json.dump({k: v for k, v in out.items() if k != "metrics"}, f, default=_jsonable)


def _write_trajectories(out_dir: str, seq, traj: np.ndarray, odometry: np.ndarray | None, evaluate: bool) -> dict:
    """trajectory_kitti.txt, trajectory_tum.txt (and odometry_kitti.txt); the ATE of each against the
    sequence's poses when `evaluate`."""
    write_trajectory(out_dir, seq, traj)
    out = {}
    gt = np.asarray(seq.poses[:len(traj)], np.float64)  # = seq.frame(i).pose, without re-reading the points
    if evaluate:
        out["ate_slam"], out["axes_slam"] = ate(traj, gt), axis_errors(traj, gt)
    if odometry is not None:
        write_kitti(os.path.join(out_dir, "odometry_kitti.txt"), odometry)
        if evaluate:
            out["ate_odometry"], out["axes_odometry"] = ate(odometry, gt), axis_errors(odometry, gt)
    return out


def n3_from_poses(cfg: SlamConfig, seq, poses, out_dir: str, progress: bool, desc: str = "optimised poses",
                  mesh: bool = True) -> dict:
    """The N3 map of the same frames at `poses` [N,4,4] (the optimised ones in `run_slam`) (written as a KITTI pose file beside a
    symlinked copy of the data would be clumsy: the mapper is fed frame by frame instead); mesh=False: not meshed."""
    from jaxmap.runs.n3 import map_at_poses

    os.makedirs(out_dir, exist_ok=True)
    mapper, loop = map_at_poses(n3_map_config(cfg, out_dir), seq, poses, progress, f"n3 ({desc})")
    save_config(mapper.cfg, os.path.join(out_dir, "config.yaml"))
    return finish_run(mapper, mapper.cfg, out_dir, loop, mesh=mesh)


def _jsonable(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(type(x))


def odometry_trajectory(seq, cfg: OdometryConfig, progress: bool = False) -> tuple[np.ndarray, float]:
    """Run the odometry `cfg.method` names over every frame of `seq` from its first pose.

    Returns (poses [N,4,4] float64, median seconds per frame after the first)."""
    odo = make_odometry(cfg, np.asarray(seq.poses[0], dtype=np.float64))
    poses, times = [], []

    def step(frame: Frame):
        t0 = time.perf_counter()
        poses.append(odo.step(frame.points).pose)
        times.append(time.perf_counter() - t0)
        return {}, poses[-1]

    run_frames(Prefetcher(seq, 0, len(seq)), step, total=len(seq),
               progress=Progress(f"odometry ({cfg.method})", progress))
    return np.stack(poses), float(np.median(times[1:])) if len(times) > 1 else float(times[0])
