"""`jaxmap slam CONFIG [--data DIR] [--out RUN]`: odometry, loop closure, pose graph and a neural map
that is remapped on the fly.

Per frame of the sequence (its poses.txt is only used for the first pose and for evaluation):
  1. the front end (`FrontEnd`: ICP odometry, keyframes, loop verification, open3d pose graph) gives
     the pose estimate;
  2. a keyframe is encoded and fused into the transformable latent map (`ImtMapper`) at that pose;
  3. when a loop is accepted and the graph optimised, the latent map is remapped to the optimised
     keyframe poses (`jaxmap.imt.remap`: only the keyframes whose pose moved are touched); with
     `mesh_at_loops` a mesh is written before and after (`loop_<n>_before.ply`, `loop_<n>_after.ply`).
With `map_kind: n3` the map is instead the N3 map of `n3_config`, mapped online at the poses the front
end and tracking against that map give, and following each loop correction (`jaxmap.runs.slam_n3`).
With `external_poses: DIR` the front end is replaced by pose-graph snapshots of another SLAM system
(one TUM or KITTI file per keyframe update, in natural order, as ORB-SLAM2 writes them; snapshot i
holds the poses of the first n_i frames of the selection): new frames are fused with their snapshot
pose, and earlier keyframes are remapped as each snapshot arrives.

A run directory holds config.yaml, checkpoint/ (latent map + keyframe store), mesh.ply,
trajectory_kitti.txt and trajectory_tum.txt (every frame, and odometry_kitti.txt: odometry alone),
the loop meshes, slam.json (ATE of odometry and of the optimised trajectory against the sequence's
poses, per-loop records and timings, tracking), metrics.json (reconstruction metrics alone, when the
sequence has ground truth) and,
with `n3_config` (map_kind imt), an N3 map built from the optimised poses in n3/. With map_kind n3,
checkpoint/ is the N3 map (`N3Mapper.load`), n3_config.yaml its resolved config, timing.json its frames.

With `--view` a live browser viewer (`jaxmap.viewer`) shows each frame's points, the trajectory (redrawn
after each pose-graph optimisation), the loop closures and a mesh re-extracted in a background thread.
"""
from __future__ import annotations

import functools
import json
import logging
import os
import re
import time

import numpy as np

from jaxmap.config import SlamConfig, save_config
from jaxmap.config.slam import OdometryConfig
from jaxmap.errors import DataError, JaxmapError
from jaxmap.finish import finish_run
from jaxmap.frame_loop import Frame, FramesRun, Prefetcher, Progress, open_run_sequence, open_viewer, run_frames
from jaxmap.geometry import compose
from jaxmap.imt.mapper import ImtMapper
from jaxmap.n3.core import PROGRAMS
from jaxmap.runs.slam_n3 import SlamFrame, load_slam, n3_map_config, open_n3_mapper, run_n3_frontend, show_loop
from jaxmap.slam.frontend import FrontEnd
from jaxmap.slam.odometry import make_odometry
from jaxmap.slam.odometry_common import Scan
from jaxmap.slam.trajectory import ate, axis_errors, read_pose_snapshot, write_kitti, write_trajectory

log = logging.getLogger("jaxmap")


class FrontEndStep:
    """The SLAM step of the frame loop: the front end estimates the frame's pose; a keyframe is fused
    into the map at it; an accepted loop remaps the map to the optimised keyframe poses."""

    def __init__(self, cfg: SlamConfig, seq, out_dir: str, mapper, viewer=None):
        self.cfg, self.out_dir, self.mapper, self.viewer = cfg, out_dir, mapper, viewer
        self.fe = FrontEnd(cfg.frontend, initial_pose=seq.frame(0).pose)
        self.loops: list[dict] = []
        self.odometry: list[np.ndarray] = []   # odometry alone: the chain of frame-to-frame motions

    def __call__(self, frame: SlamFrame) -> tuple[dict, np.ndarray]:
        mapper = self.mapper
        try:
            r = self.fe.add_frame(frame.points, scan=frame.odometry_scan)
            # the odometry's own motion of the step just made, which loop corrections do not touch (a front
            # end that does not report it: its odometry's velocity)
            rel = r.odometry_rel if r.odometry_rel is not None else self.fe.odometry.velocity
            self.odometry.append(frame.pose.copy() if not self.odometry else compose(self.odometry[-1], rel))
            if r.is_keyframe:
                ready = frame.prepared if frame.prepared is not None else mapper.prepare(frame.points)
                mapper.add_prepared(ready, r.pose, frame=frame.index, pose_source="jaxmap's SLAM front end")
                if r.optimized:
                    self.loops.append(_close_loop(self.cfg, mapper, r.keyframe_poses, self.out_dir, len(self.loops),
                                                  {"frame": frame.index, "keyframe": int(r.keyframe_id),
                                                   "optimize_s": r.timings["optimize_s"],
                                                   "fitness": float(r.loop.fitness), "rmse_m": float(r.loop.rmse)}))
        except Exception as e:  # the front end or the mapper failed: keep what was mapped, say where
            raise _failed_at(mapper, self.out_dir, frame.index, e) from e
        record = dict(r.timings, kf=len(mapper.store), loops=len(self.loops), ok=r.odometry_ok)
        if r.is_keyframe and mapper.timings:
            record.update({k: v for k, v in mapper.timings[-1].items() if k.endswith("_s")})
        if r.optimized:
            show_loop(self.viewer, self.fe, r)
        return record, r.pose


def prepare_frontend_frame(cfg: SlamConfig, mapper, seq, i: int) -> SlamFrame:
    """`Prefetcher` loader of the front end's frames: read, the odometry's scan prepared and, when every
    frame is a keyframe, the map's preprocessing too (else the keyframes' is done as they are decided)."""
    fr = seq.frame(i)
    fe = cfg.frontend
    every = fe.keyframe_every <= 1 and fe.keyframe_min_translation_m <= 0 and fe.keyframe_min_rotation_deg <= 0
    return SlamFrame(i, int(fr.index), fr.points, fr.pose, prepared=mapper.prepare(fr.points) if every else None,
                     odometry_scan=Scan(fr.points, fe.odometry))


def run_frontend(cfg: SlamConfig, seq, out_dir: str, mapper, progress: bool = True, viewer=None) -> dict:
    """Our own front end drives the map. Returns trajectories and per-loop records.
    viewer: a `jaxmap.viewer.ViewerHooks` shown every frame (None = no viewer)."""
    step = FrontEndStep(cfg, seq, out_dir, mapper, viewer)
    bar = Progress("slam", progress, postfix=lambda r: {"kf": r["kf"], "loops": r["loops"], "ok": r["ok"]})
    frames = Prefetcher(seq, 0, len(seq), functools.partial(prepare_frontend_frame, cfg, mapper))
    run_frames(frames, step, total=len(seq), progress=bar, viewer=viewer)
    return {"trajectory": step.fe.trajectory(), "odometry": np.asarray(step.odometry), "loops": step.loops,
            "keyframe_frames": list(mapper.store.frames)}


def _failed_at(mapper, out_dir: str, frame: int, err: Exception) -> JaxmapError:
    """Save the map of the keyframes before `frame` and return the error that names the frame."""
    log.error("jaxmap slam: frame %d failed", frame, exc_info=err)
    path = os.path.join(out_dir, "checkpoint")
    try:
        mapper.save(path)
        saved = f"the map of the {len(mapper.store)} keyframes before it is saved in {path} (`ImtMapper.load`)"
    except Exception as e2:  # noqa: BLE001 - the first error is the one to report
        saved = f"saving a checkpoint failed too ({type(e2).__name__}: {e2})"
    return JaxmapError(f"jaxmap slam failed at frame {frame}: {type(err).__name__}: {err}; {saved}")


def _close_loop(cfg, mapper, poses, out_dir, n, record):
    if cfg.mesh_at_loops:
        mapper.mesh().export(os.path.join(out_dir, f"loop_{n}_before.ply"))
    corrected = mapper.correct(poses)
    record.update(remap_s=corrected.pop("map_s"), **corrected)
    if cfg.mesh_at_loops:
        mapper.mesh().export(os.path.join(out_dir, f"loop_{n}_after.ply"))
    log.info("loop %d at frame %d: optimised in %.2f s, %d of %d keyframes remapped in %.2f s", n, record["frame"],
             record.get("optimize_s", 0.0), record["keyframes_moved"], record["keyframes"], record["remap_s"])
    return record


def snapshot_files(directory: str) -> list[str]:
    """Pose snapshot files of `directory` in natural order (`kf_2.txt` before `kf_10.txt`)."""
    if not os.path.isdir(directory):
        raise DataError(f"external_poses: {directory} is not a directory of pose snapshots")
    names = [n for n in os.listdir(directory) if n.endswith(".txt")]
    if not names:
        raise DataError(f"external_poses: {directory} has no .txt pose snapshots (TUM or KITTI, one per update)")
    key = lambda s: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]  # noqa: E731
    return [os.path.join(directory, n) for n in sorted(names, key=key)]


def read_snapshots(directory: str, frames: int) -> list[tuple[str, np.ndarray]]:
    """(path, poses [n_i, 4, 4]) of every pose snapshot of `directory` in order, checked: each covers at
    most the `frames` of the selection and at least every frame of the snapshots before it."""
    out, covered = [], 0
    for path in snapshot_files(directory):
        poses = read_pose_snapshot(path)
        if len(poses) > frames:
            raise DataError(f"{path}: {len(poses)} poses but the sequence selection has {frames} frames")
        if len(poses) < covered:
            raise DataError(f"{path}: {len(poses)} poses, fewer than the {covered} frames of the "
                            "previous snapshots; each snapshot must cover every frame fused so far")
        out.append((path, poses))
        covered = len(poses)
    return out


class SnapshotStep:
    """The step of the frame loop when another SLAM system's pose snapshots drive the map: before the
    first frame that snapshot i adds, the map is remapped to snapshot i's poses (and to those of the
    snapshots before it that added no frame); the frame is fused at its snapshot pose."""

    def __init__(self, snapshots: list[tuple[str, np.ndarray]], mapper):
        self.snapshots, self.mapper = snapshots, mapper
        self.applied = 0                 # snapshots whose remap is done
        self.updates: list[dict] = []

    def _apply(self, n: int) -> None:
        """Remap to snapshot n's poses of the frames fused so far."""
        path, poses = self.snapshots[n]
        mapper, fused = self.mapper, len(self.mapper.store)
        t0 = time.perf_counter()
        changed = mapper.remap(poses[:fused]) if fused else []
        self.updates.append({"snapshot": os.path.basename(path), "poses": len(poses), "remapped": changed,
                             "added": len(poses) - fused, "remap_s": time.perf_counter() - t0})
        self.applied = n + 1

    def finish(self) -> np.ndarray:
        """Apply the snapshots left (those that add no frame); the last snapshot's poses."""
        while self.applied < len(self.snapshots):
            self._apply(self.applied)
        return self.snapshots[-1][1] if self.snapshots else np.zeros((0, 4, 4))

    def __call__(self, frame: Frame) -> tuple[dict, np.ndarray]:
        k = frame.position
        while self.applied == 0 or len(self.snapshots[self.applied - 1][1]) <= k:
            self._apply(self.applied)
        pose = self.snapshots[self.applied - 1][1][k]
        return self.mapper.add_prepared(frame.prepared, pose, frame=frame.index), pose


def prepare_snapshot_frame(mapper, seq, i: int) -> SlamFrame:
    """`Prefetcher` loader when pose snapshots drive the map: read, and the map's preprocessing of it (its
    pose, and so its cells, is known only when its snapshot is applied)."""
    fr = seq.frame(i)
    return SlamFrame(i, int(fr.index), fr.points, fr.pose, prepared=mapper.prepare(fr.points))


def run_external(cfg: SlamConfig, seq, out_dir: str, mapper, progress: bool = True, viewer=None) -> dict:
    """Pose snapshots of another SLAM system drive the map (see the module docstring)."""
    step = SnapshotStep(read_snapshots(cfg.external_poses, len(seq)), mapper)
    total = len(step.snapshots[-1][1])
    run_frames(Prefetcher(seq, 0, total, functools.partial(prepare_snapshot_frame, mapper)), step, total=total,
               progress=Progress("slam (external poses)", progress), viewer=viewer)
    poses = step.finish()
    return {"trajectory": poses, "odometry": None, "loops": step.updates, "keyframe_frames": list(mapper.store.frames)}


def run_slam(cfg: SlamConfig, out_dir: str, progress: bool = True, evaluate: bool = True,
             view: dict | None = None, resume: bool = False, mesh: bool = True) -> dict:
    """view: {"port", "mesh_every"} for a live viewer (`jaxmap.frame_loop.open_viewer`), None = none.
    resume: go on from the run's SLAM checkpoint in out_dir (map_kind n3; `jaxmap.runs.slam_n3.load_slam`).
    mesh=False: no mesh and no reconstruction metrics at the end (`jaxmap slam --no-mesh`)."""
    t_start = time.perf_counter()
    os.makedirs(out_dir, exist_ok=True)
    if not resume:
        save_config(cfg, os.path.join(out_dir, "config.yaml"))
    if cfg.map_kind == "n3":
        return run_slam_n3(cfg, out_dir, progress, evaluate, view, resume=resume, mesh=mesh)
    if resume:
        raise JaxmapError(f"--resume {out_dir}: a map_kind {cfg.map_kind} run is not checkpointed (map_kind n3 "
                          "runs are); start it again with --overwrite")
    icfg = cfg.imt()
    seq = open_run_sequence(icfg)
    mapper = ImtMapper(icfg)
    run = run_external if cfg.external_poses else run_frontend
    viewer = open_viewer(view, mapper)
    res = run(cfg, seq, out_dir, mapper, progress, viewer=viewer)
    mapper.save(os.path.join(out_dir, "checkpoint"))
    loop = FramesRun(len(res["trajectory"]), time.perf_counter() - t_start)
    traj = np.asarray(res["trajectory"])
    out = {"run": out_dir, "frames": len(seq), "keyframes": len(mapper.store), "loops": res["loops"],
           **_write_trajectories(out_dir, seq, traj, res["odometry"], evaluate)}
    rec = finish_run(mapper, icfg, out_dir, loop, evaluate=evaluate, viewer=viewer, mesh=mesh)
    out.update({k: v for k, v in rec.items() if k not in ("run", "peak_rss_mb")})
    if cfg.n3_config:
        out["n3"] = n3_from_poses(cfg, seq, traj, os.path.join(out_dir, "n3"), progress, mesh=mesh)
    write_slam_summary(out_dir, out)
    return out


def run_slam_n3(cfg: SlamConfig, out_dir: str, progress: bool = True, evaluate: bool = True,
                view: dict | None = None, track=None, resume: bool = False, mesh: bool = True) -> dict:
    """`map_kind: n3` (`jaxmap.runs.slam_n3`): the N3 map of `n3_config`, mapped online at the tracked poses
    and following each loop correction. Leaves what `run_slam` does, the map being N3's (checkpoint/
    `N3Mapper.load`s; n3_config.yaml is the map's resolved config). track: a tracker in place of
    `jaxmap.slam.track.track_scan` (tests)."""
    seq = open_run_sequence(cfg)
    n_compiles = PROGRAMS.compiles()
    step = None
    if resume:
        mapper, step = load_slam(out_dir)
        log.info("resuming %s at frame %d of %d", out_dir, len(step.scans), len(seq))
    else:
        mapper = open_n3_mapper(cfg, out_dir, seq)
        save_config(mapper.cfg, os.path.join(out_dir, "n3_config.yaml"))
    viewer = open_viewer(view, mapper)
    res = run_n3_frontend(cfg, seq, mapper, progress, viewer=viewer, track=track, step=step, out_dir=out_dir)
    traj = np.asarray(res["trajectory"])
    tracked = [t for t in res["tracking"] if t.get("tracked")]
    out = {"run": out_dir, "map_kind": "n3", "frames": len(seq), "keyframes": len(res["keyframe_frames"]),
           "loops": res["loops"], "tracked_frames": len(tracked), "tracked_ok": sum(t["ok"] for t in tracked),
           "loop_map_s": float(sum(lp["map_s"] for lp in res["loops"])), "loop_readd_s": res["readd_s"],
           "loop_readds": res["readds"], "loop_readd_pairs_removed": res["readd_pairs_removed"],
           "tracking": res["tracking"],
           "step": res["step_medians"],
           **_write_trajectories(out_dir, seq, traj, res["odometry"], evaluate)}
    rec = finish_run(mapper, mapper.cfg, out_dir, res["loop"], evaluate=evaluate, viewer=viewer, mesh=mesh,
                     extra=PROGRAMS.compiles_since(n_compiles))
    out.update({k: v for k, v in rec.items() if k not in ("run", "peak_rss_mb")})
    # the SLAM run's saves are the step's (save_slam), not the map's own: its record would say 0
    out["checkpoint_s_sum"] = res["checkpoint_s"]
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
