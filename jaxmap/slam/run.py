"""`jaxmap slam CONFIG [--data DIR] [--out RUN]`: odometry, loop closure, pose graph and a neural map
that is remapped on the fly.

Per frame of the sequence (its poses.txt is only used for the first pose and for evaluation):
  1. the front end (`FrontEnd`: ICP odometry, keyframes, loop verification, open3d pose graph) gives
     the pose estimate;
  2. a keyframe is encoded and fused into the transformable latent map (`ImtMapper`) at that pose;
  3. when a loop is accepted and the graph optimised, the latent map is remapped to the optimised
     keyframe poses (`jaxmap.imt.remap`: only the keyframes whose pose moved are touched); with
     `mesh_at_loops` a mesh is written before and after (`loop_<n>_before.ply`, `loop_<n>_after.ply`).
With `external_poses: DIR` the front end is replaced by pose-graph snapshots of another SLAM system
(one TUM or KITTI file per keyframe update, in natural order, as ORB-SLAM2 writes them; snapshot i
holds the poses of the first n_i frames of the selection): new frames are fused with their snapshot
pose, and earlier keyframes are remapped as each snapshot arrives.

A run directory holds config.yaml, checkpoint/ (latent map + keyframe store), mesh.ply,
trajectory_kitti.txt and trajectory_tum.txt (every frame, and odometry_kitti.txt: odometry alone),
the loop meshes, metrics.json (ATE of odometry and of the optimised trajectory against the
sequence's poses, reconstruction metrics when the sequence has ground truth, per-loop timings) and,
with `n3_config`, an N3 map built from the optimised poses in n3/.

With `--view` a live browser viewer (`jaxmap.viewer`) shows each frame's points, the trajectory (redrawn
after each pose-graph optimisation), the loop closures and a mesh re-extracted in a background thread.
"""
from __future__ import annotations

import json
import logging
import os
import re
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from jaxmap.config import (DataConfig, EvalConfig, ImtConfig, LatentMapConfig, LatentMeshConfig,
                           PreprocessConfig, config_from_args, load_config, save_config)
from jaxmap.errors import DataError, JaxmapError
from jaxmap.geometry import compose
from jaxmap.slam.frontend import FrontEndConfig

log = logging.getLogger("jaxmap")


def _register_rules() -> None:
    """Value rules of the front end's config keys, checked at load (see `jaxmap.config.RULES`)."""
    from jaxmap.config import _host_preprocess_checks, at_least, one_of, register_rules
    from jaxmap.slam.frontend import EDGE_INFORMATION
    from jaxmap.slam.odometry import ODOMETRY_METHODS, OdometryConfig

    register_rules(OdometryConfig, method=one_of(*ODOMETRY_METHODS), max_iter=at_least(1), normals_k=at_least(3))
    register_rules(FrontEndConfig, edge_information=one_of(*EDGE_INFORMATION))
    register_rules(SlamConfig, checks=[_host_preprocess_checks])


@dataclass(frozen=True)
class SlamConfig:
    """Root config of `jaxmap slam` (front end + transformable latent map)."""

    data: DataConfig = field(default_factory=lambda: ImtConfig().data)
    preprocess: PreprocessConfig = field(default_factory=lambda: ImtConfig().preprocess)
    map: LatentMapConfig = field(default_factory=LatentMapConfig)
    mesh: LatentMeshConfig = field(default_factory=LatentMeshConfig)
    eval: EvalConfig = field(default_factory=lambda: ImtConfig().eval)
    frontend: FrontEndConfig = field(default_factory=FrontEndConfig)
    external_poses: str = ""          # directory of pose snapshots replacing the front end ("" = our own)
    mesh_at_loops: bool = False       # write meshes before and after each loop closure (a whole-map mesh each: slow)
    n3_config: str = ""               # also build an N3 map from the optimised poses with this config
    output: str = "runs/slam"           # run directory (`--out` overrides it)
    progress: bool = True             # tqdm progress bar

    def imt(self) -> ImtConfig:
        return ImtConfig(data=self.data, preprocess=self.preprocess, map=self.map, mesh=self.mesh, eval=self.eval,
                         output=self.output, progress=self.progress)


_register_rules()


def _bar(total, desc, enabled):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc=desc, file=sys.stderr)


def run_frontend(cfg: SlamConfig, seq, out_dir: str, mapper, progress: bool = True, hooks=None) -> dict:
    """Our own front end drives the map. Returns trajectories and per-loop records.
    hooks: a `jaxmap.viewer.ViewerHooks` shown every frame (None = no viewer)."""
    from jaxmap.slam.frontend import FrontEnd

    fe = FrontEnd(cfg.frontend, initial_pose=seq.frame(0).pose)
    loops, odo = [], []
    bar = _bar(len(seq), "slam", progress)
    for i in range(len(seq)):
        fr = seq.frame(i)
        try:
            r = fe.add_frame(fr.points)
            # odometry alone: the chain of frame-to-frame motions (the velocity of the step just made),
            # which loop corrections do not touch
            odo.append(fr.pose.copy() if i == 0 else compose(odo[-1], fe.odometry.velocity))
            if r.is_keyframe:
                mapper.add_frame(fr.points, r.pose, frame=fr.index, pose_source="jaxmap's SLAM front end")
                if r.optimized:
                    loops.append(_close_loop(cfg, mapper, r.keyframe_poses, out_dir, len(loops),
                                             {"frame": int(fr.index), "keyframe": int(r.keyframe_id),
                                              "optimize_s": r.timings["optimize_s"],
                                              "fitness": float(r.loop.fitness), "rmse_m": float(r.loop.rmse)}))
        except Exception as e:  # the front end or the mapper failed: keep what was mapped, say where
            raise _failed_at(mapper, out_dir, int(fr.index), e) from e
        if hooks is not None:
            _view_frame(hooks, fe, fr, r, mapper)
        if bar is not None:
            bar.set_postfix(kf=len(mapper.store), loops=len(loops), ok=r.odometry_ok)
            bar.update(1)
    if bar is not None:
        bar.close()
    return {"trajectory": fe.trajectory(), "odometry": np.asarray(odo), "loops": loops,
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


def _view_frame(hooks, fe, fr, r, mapper) -> None:
    from jaxmap.viewer import to_world

    info = dict(r.timings)
    if r.is_keyframe and mapper.timings:
        info.update({k: v for k, v in mapper.timings[-1].items() if k.endswith("_s")})
    hooks.on_frame(int(fr.index), to_world(fr.points, r.pose, hooks.viewer.max_points), r.pose, info)
    if r.optimized:
        hooks.on_trajectory(fe.trajectory())
        if fe.loops:
            c, k = fe.loops[-1]
            hooks.on_loop(r.keyframe_poses[c], r.keyframe_poses[k])


def _close_loop(cfg, mapper, poses, out_dir, n, record):
    if cfg.mesh_at_loops:
        mapper.mesh().export(os.path.join(out_dir, f"loop_{n}_before.ply"))
    t0 = time.perf_counter()
    changed = mapper.remap(poses)
    record.update({"remap_s": time.perf_counter() - t0, "keyframes_moved": len(changed),
                   "keyframes": len(mapper.store)})
    if cfg.mesh_at_loops:
        mapper.mesh().export(os.path.join(out_dir, f"loop_{n}_after.ply"))
    log.info("loop %d at frame %d: optimised in %.2f s, %d of %d keyframes remapped in %.2f s", n, record["frame"],
             record.get("optimize_s", 0.0), len(changed), len(mapper.store), record["remap_s"])
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


def run_external(cfg: SlamConfig, seq, out_dir: str, mapper, progress: bool = True, hooks=None) -> dict:
    """Pose snapshots of another SLAM system drive the map (see the module docstring)."""
    from jaxmap.slam.trajectory import read_pose_snapshot

    files = snapshot_files(cfg.external_poses)
    updates, poses = [], np.zeros((0, 4, 4))
    bar = _bar(len(seq), "slam (external poses)", progress)
    for n, path in enumerate(files):
        poses = read_pose_snapshot(path)
        if len(poses) > len(seq):
            raise DataError(f"{path}: {len(poses)} poses but the sequence selection has {len(seq)} frames")
        if len(poses) < len(mapper.store):
            raise DataError(f"{path}: {len(poses)} poses, fewer than the {len(mapper.store)} frames of the "
                            "previous snapshots; each snapshot must cover every frame fused so far")
        t0 = time.perf_counter()
        changed = mapper.remap(poses[:len(mapper.store)]) if len(mapper.store) else []
        remap_s = time.perf_counter() - t0
        new = range(len(mapper.store), len(poses))
        for k in new:
            fr = seq.frame(k)
            info = mapper.add_frame(fr.points, poses[k], frame=fr.index)
            if hooks is not None:
                from jaxmap.viewer import to_world

                hooks.on_frame(int(fr.index), to_world(fr.points, poses[k], hooks.viewer.max_points), poses[k], info)
            if bar is not None:
                bar.update(1)
        updates.append({"snapshot": os.path.basename(path), "poses": len(poses), "remapped": changed,
                        "added": len(new), "remap_s": remap_s})
    if bar is not None:
        bar.close()
    return {"trajectory": poses, "odometry": None, "loops": updates, "keyframe_frames": list(mapper.store.frames)}


def run_slam(cfg: SlamConfig, out_dir: str, progress: bool = True, evaluate: bool = True,
             view: dict | None = None) -> dict:
    """view: {"port", "mesh_every"} for a live viewer (see `jaxmap.imt.run.start_view`), None = none."""
    from jaxmap.imt.mapper import ImtMapper
    from jaxmap.imt.run import finish_view, mesh_and_evaluate, open_run_sequence, start_view, summarize
    from jaxmap.slam.trajectory import ate, write_kitti, write_tum

    os.makedirs(out_dir, exist_ok=True)
    save_config(cfg, os.path.join(out_dir, "config.yaml"))
    icfg = cfg.imt()
    seq = open_run_sequence(icfg)
    mapper = ImtMapper(icfg)
    run = run_external if cfg.external_poses else run_frontend
    hooks = start_view(view, mapper)
    try:
        res = run(cfg, seq, out_dir, mapper, progress, hooks=hooks)
    except BaseException:
        if hooks is not None:
            hooks.close()
        raise
    mapper.save(os.path.join(out_dir, "checkpoint"))
    traj = np.asarray(res["trajectory"])
    write_kitti(os.path.join(out_dir, "trajectory_kitti.txt"), traj)
    # sensor timestamps where the data has them (ROS bags, TUM RGB-D), else frame numbers
    stamps = (np.asarray(seq.timestamps[:len(traj)], np.float64) if getattr(seq, "timestamps", None) is not None
              else np.asarray(seq.indices[:len(traj)], np.float64))
    write_tum(os.path.join(out_dir, "trajectory_tum.txt"), stamps, traj)
    out = {"run": out_dir, "frames": len(seq), "keyframes": len(mapper.store), "loops": res["loops"],
           **summarize(mapper.timings), **mapper.sizes()}
    gt = np.asarray(seq.poses[:len(traj)], np.float64)  # = seq.frame(i).pose, without re-reading the points
    if evaluate:
        out["ate_slam"] = ate(traj, gt)
        if res["odometry"] is not None:
            write_kitti(os.path.join(out_dir, "odometry_kitti.txt"), res["odometry"])
            out["ate_odometry"] = ate(res["odometry"], gt)
    try:
        rec = mesh_and_evaluate(mapper, icfg, out_dir, evaluate=evaluate)
    except BaseException:
        if hooks is not None:
            hooks.close()
        raise
    finish_view(hooks, rec.get("mesh"), out_dir)
    out.update({"mesh": rec["mesh"], "faces": rec["faces"]})
    if "metrics" in rec:
        out["metrics"] = rec["metrics"]
    if cfg.n3_config:
        out["n3"] = _n3_from_poses(cfg, seq, traj, os.path.join(out_dir, "n3"), progress)
    with open(os.path.join(out_dir, "metrics.json"), "w") as f:
        json.dump(out, f, default=_jsonable)
    return out


def _n3_from_poses(cfg: SlamConfig, seq, poses, out_dir: str, progress: bool) -> dict:
    """The N3 map of the same frames with the optimised poses (written as a KITTI pose file beside a
    symlinked copy of the data would be clumsy: the mapper is fed frame by frame instead)."""
    from jaxmap.config import MapConfig
    from jaxmap.n3.mapper import N3Mapper
    from jaxmap.n3.run import finish_run

    d = cfg.data
    ncfg = load_config(cfg.n3_config, [f"data.path={d.path}", f"data.begin_frame={d.begin_frame}",
                                       f"data.end_frame={d.end_frame}", f"data.every_frame={d.every_frame}",
                                       f"output={out_dir}"], schema=MapConfig)
    os.makedirs(out_dir, exist_ok=True)
    save_config(ncfg, os.path.join(out_dir, "config.yaml"))
    mapper = N3Mapper(ncfg)
    bar = _bar(len(seq), "n3 (optimised poses)", progress)
    for i in range(len(seq)):
        mapper.add_frame(seq.frame(i).points, poses[i])
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return finish_run(mapper, ncfg, out_dir, seq)


def _jsonable(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(type(x))


def cli_slam(args) -> int:
    cfg = config_from_args(args, SlamConfig)
    from jaxmap.rundir import claim
    from jaxmap.viewer import view_options

    with claim(cfg.output, "slam", overwrite=args.overwrite):  # one writer; an existing run needs --overwrite
        out = run_slam(cfg, cfg.output, progress=cfg.progress and not args.no_progress, view=view_options(args))
    brief = {k: out[k] for k in ("run", "frames", "keyframes", "mesh") if k in out}
    brief["loops"] = len(out["loops"])
    for k in ("ate_odometry", "ate_slam"):
        if k in out:
            brief[k + "_rmse_m"] = out[k]["rmse_m"]
    if "metrics" in out:
        brief["chamfer_l1_cm"] = out["metrics"]["chamfer_l1_cm"]
        brief["f_score"] = out["metrics"]["f_score"]
    print(json.dumps(brief))
    return 0
