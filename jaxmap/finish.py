"""The one finisher of every run: what a mapped run leaves in its directory.

    summary = finish_run(mapper, cfg, out_dir, loop)   # mesh.ply, metrics.json (with ground truth), timing.json

`mapper` is a `jaxmap.frame_loop.Mapper`, `loop` the `FramesRun` of the run's frame loop.
"""
from __future__ import annotations

import json
import logging
import os
import time
from typing import Callable

from jaxmap.frame_loop import FramesRun, Mapper, close_viewer, outside_programs
from jaxmap.hostmem import peak_rss_mb
from jaxmap.metrics import evaluate_mesh_file

log = logging.getLogger("jaxmap")


def finish_run(mapper: Mapper, cfg, out_dir: str, loop: FramesRun | None = None, *, evaluate: bool = True,
               mesh: bool = True, extra: dict | None = None, viewer=None, point_scores: dict | None = None,
               wait_saves: Callable[[], None] | None = None) -> dict:
    """Mesh (`out_dir/mesh.ply`), metrics against the sequence's ground truth (`metrics.json`, when it
    has gt_points.ply) and timings (`timing.json`) of a mapped run; returns the run's summary.
    mesh=False: timings only. The viewer, if any, shows the final mesh and is closed. point_scores: the
    run's `jaxmap.metrics.dynamic.PointScores.result()` (sequences with moving objects), written to
    metrics.json and the summary as "dynamic_points". wait_saves: waits for the final checkpoint, written
    in the background while the map is meshed (`Checkpoints.final`); what is left of it once the mesh is
    done counts in the run's wall_s and final_save_s.

    The run ends here: once its mesh and its final checkpoint are written, the map's arrays are released
    (`mapper.release()`; its records stay), so that the evaluation does not run beside them."""
    out = mesh_file(mapper, out_dir) if mesh else {"mesh": None, "faces": 0, "mesh_s": 0.0}
    t0 = time.perf_counter()
    if wait_saves is not None:
        wait_saves()
    waited = time.perf_counter() - t0
    summ = dict(mapper.timing_summary())
    if viewer is not None:
        close_viewer(viewer, out["mesh"], out_dir)
    mapper.release()
    if mesh and evaluate:
        out.update(metrics_of(out, cfg))
    if point_scores is not None:
        out["dynamic_points"] = point_scores
        if "metrics" in out:
            out["metrics"]["dynamic_points"] = point_scores
    ran = loop is not None and loop.frames_run
    if ran:
        wall = loop.wall_s + waited
        summ.update({"wall_s": wall, "wall_s_per_frame": wall / loop.frames_run, "frames_run": loop.frames_run,
                     "final_save_s": loop.final_save_s + waited})
    summ.update(extra or {})
    if ran:
        summ.update(outside_programs(mapper.timings[-loop.frames_run:], wall, summ.get("compile_s", 0.0)))
    with open(os.path.join(out_dir, "timing.json"), "w") as f:
        json.dump({"frames": mapper.timings, "summary": summ, "mesh_s": out["mesh_s"]}, f)
    if "metrics" in out:
        with open(os.path.join(out_dir, "metrics.json"), "w") as f:
            json.dump(out["metrics"], f)
    return {"run": out_dir, **out, **summ, "peak_rss_mb": peak_rss_mb()}


def mesh_and_metrics(mapper: Mapper, cfg, out_dir: str, name: str = "mesh.ply", evaluate: bool = True,
                     floor: bool = True) -> dict:
    """Write the map's mesh to `out_dir/name`; its metrics against the ground truth of the run's data
    when `evaluate` and the data has gt_points.ply (with the protocol's floor unless floor=False).
    Returns {"mesh": path, "faces", "mesh_s", "metrics"?}."""
    out = mesh_file(mapper, out_dir, name)
    if evaluate:
        out.update(metrics_of(out, cfg, floor))
    return out


def mesh_file(mapper: Mapper, out_dir: str, name: str = "mesh.ply") -> dict:
    """The map's mesh written to `out_dir/name`: {"mesh": path, "faces", "mesh_s"}."""
    t0 = time.perf_counter()
    m = mapper.mesh()
    path = os.path.join(out_dir, name)
    m.export(path)
    return {"mesh": path, "faces": int(len(m.faces)), "mesh_s": time.perf_counter() - t0}


def metrics_of(mesh_out: dict, cfg, floor: bool = True) -> dict:
    """{"metrics": ...} of the mesh `mesh_file` wrote, when the run's data has ground truth, else {}."""
    if not has_ground_truth(cfg.data.path):
        return {}
    if mesh_out["faces"] == 0:
        log.warning("the mesh %s is empty (too few frames or iterations?): no metrics", mesh_out["mesh"])
        return {}
    return {"metrics": evaluate_run_mesh(mesh_out["mesh"], cfg, floor=floor)}


def has_ground_truth(data_path: str) -> bool:
    """The run's data is a directory holding gt_points.ply: what the evaluator reads
    (`jaxmap.metrics.read_gt`; a ROS bag or LAS file with a GT beside it is not evaluated here)."""
    return os.path.isfile(os.path.join(data_path, "gt_points.ply"))


def evaluate_run_mesh(mesh_path: str, cfg, floor: bool = True, protocol: str = "shine", ghost: bool = True) -> dict:
    """The standard protocol's metrics of a mesh against the ground truth of the run's data, culled to
    exactly the frames and range the run mapped (`jaxmap.metrics.evaluate_mesh_file`). The one scoring of
    a run's mesh: its metrics.json, and `jaxmap eval RUN` (`jaxmap.eval_run`) after it."""
    d, p, e = cfg.data, cfg.preprocess, cfg.eval
    return evaluate_mesh_file(mesh_path, d.path, threshold_m=e.threshold_m, cull_distance_m=e.cull_distance_m,
                              eval_radius_m=e.eval_radius_m, n_samples=e.n_samples, begin_frame=d.begin_frame,
                              end_frame=d.end_frame, every_frame=d.every_frame, min_range_m=p.min_range_m,
                              max_range_m=p.max_range_m, floor=floor, protocol=protocol, ghost=ghost)
