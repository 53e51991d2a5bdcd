"""The point scores of the dynamic-removal field (KTH's DynamicMap benchmark): of the scan points a mapper
trained on, how many static ones it kept and how many dynamic ones it removed.

    SA (static accuracy)  = static points kept / static points        (%)
    DA (dynamic accuracy) = dynamic points removed / dynamic points   (%)

over the points of every mapped frame as the mapper received them (after its preprocessing: the rows of
the frame's prepared points, sensor frame, in order), where "kept" means the point produced training
samples (`N3Mapper.add_frame(...)["kept"]`, [M] bool; a mapper that does not report it kept them all).

A point is dynamic when it lies inside one of its frame's moving-object boxes (`jaxmap.moving`,
moving_objects.json: indexed by the sequence's own frame number), each box grown by DYNAMIC_INFLATE_M
(0.1 m, as the ghost area's) on its four sides and on top, but not below: the box's bottom is raised by
GROUND_CLEARANCE_M (0.1 m) over its base, so the road or sidewalk under and around a car or a pedestrian
stays static (it is in the static map; counting it dynamic would make a mapper that keeps the ground
look like one that keeps the car). The few returns on an object's lowest 0.1 m count static.

The labels of a frame cost one `jaxmap.moving.inside_boxes` over its points (vectorised, numpy): the N3
run computes them where it prepares the frame (the prefetch thread), and counts them against "kept"
once the frame is mapped (four sums).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from jaxmap import moving

DYNAMIC_INFLATE_M = moving.GHOST_INFLATE_M
GROUND_CLEARANCE_M = 0.1


def dynamic_boxes(boxes: moving.Boxes, inflate_m: float = DYNAMIC_INFLATE_M,
                  ground_m: float = GROUND_CLEARANCE_M) -> moving.Boxes:
    """The boxes whose growth by inflate_m (`inside_boxes`) is the labelling region: grown by inflate_m
    on the sides and on top, the bottom at base + ground_m (params [B,7] moved up, height reduced)."""
    p = boxes.params.copy()
    lift = ground_m + inflate_m
    p[:, 2] += lift
    p[:, 6] = np.maximum(p[:, 6] - lift, 0.0)
    return dataclasses.replace(boxes, params=p)


def dynamic_labels(points_s: np.ndarray, pose: np.ndarray, boxes: moving.Boxes,
                   inflate_m: float = DYNAMIC_INFLATE_M, ground_m: float = GROUND_CLEARANCE_M) -> np.ndarray:
    """[M] bool: the points (points_s [M,3] sensor frame, pose [4,4] T_world_sensor) inside one of the
    frame's boxes (world frame), grown as the module docstring says."""
    pts = np.asarray(points_s, dtype=np.float64).reshape(-1, 3)
    if len(boxes) == 0 or len(pts) == 0:
        return np.zeros(len(pts), bool)
    T = np.asarray(pose, dtype=np.float64)
    world = pts @ T[:3, :3].T + T[:3, 3]
    return moving.inside_boxes(world, dynamic_boxes(boxes, inflate_m, ground_m), inflate_m)


class Labeller:
    """Labels the points of a sequence's frames: `labeller(points_s, pose, index)` -> [M] bool dynamic,
    index the sequence's own frame number (`jaxmap.frame_loop.Frame.index`)."""

    def __init__(self, objects: moving.MovingObjects):
        self.objects = objects

    def __call__(self, points_s, pose, index: int) -> np.ndarray:
        return dynamic_labels(points_s, pose, self.objects.boxes_at(index))


def labeller_for(data_dir) -> Labeller | None:
    """The Labeller of a sequence directory with moving objects (`jaxmap.moving.load_moving_objects`), else
    None (a malformed file is a DataError naming it)."""
    objects = moving.load_moving_objects(data_dir)
    return Labeller(objects) if objects is not None else None


@dataclasses.dataclass
class PointScores:
    """The four counts over the frames added so far (a running sum, host side)."""

    static_points: int = 0
    static_kept: int = 0
    dynamic_points: int = 0
    dynamic_removed: int = 0
    frames: int = 0

    def add(self, dynamic: np.ndarray, kept: np.ndarray | None = None) -> None:
        """One frame: dynamic [M] bool labels, kept [M] bool (None: every point kept)."""
        dynamic = np.asarray(dynamic, bool)
        kept = np.ones(len(dynamic), bool) if kept is None else np.asarray(kept, bool)
        if kept.shape != dynamic.shape:
            raise ValueError(f"kept has shape {kept.shape}, the frame's labels {dynamic.shape}: they must "
                             "describe the same points")
        n_dyn = int(dynamic.sum())
        self.static_points += len(dynamic) - n_dyn
        self.static_kept += int((kept & ~dynamic).sum())
        self.dynamic_points += n_dyn
        self.dynamic_removed += int((~kept & dynamic).sum())
        self.frames += 1

    def result(self) -> dict:
        """{"sa_percent", "da_percent" (nan without points of that kind), the four counts, "frames",
        "inflate_m", "ground_m"}: what metrics.json holds as "dynamic_points"."""
        nan = float("nan")
        sa = 100.0 * self.static_kept / self.static_points if self.static_points else nan
        da = 100.0 * self.dynamic_removed / self.dynamic_points if self.dynamic_points else nan
        return {"sa_percent": sa, "da_percent": da, **dataclasses.asdict(self),
                "inflate_m": DYNAMIC_INFLATE_M, "ground_m": GROUND_CLEARANCE_M}


def scores_of_run(mesh_path, data_dir) -> dict | None:
    """The "dynamic_points" of the run that wrote mesh_path (its directory's metrics.json), when that run
    mapped data_dir (its config.yaml's data.path, or no config.yaml to say otherwise); else None. They are
    scores of the run's input points, so `jaxmap eval` can only show them, not compute them."""
    import json
    import os

    run_dir = os.path.dirname(os.path.abspath(os.fspath(mesh_path)))
    try:
        with open(os.path.join(run_dir, "metrics.json")) as f:
            scores = json.load(f).get("dynamic_points")
    except (OSError, ValueError, AttributeError):
        return None
    if not scores:
        return None
    cfg_path = os.path.join(run_dir, "config.yaml")
    if os.path.isfile(cfg_path):
        import yaml

        try:
            with open(cfg_path) as f:
                mapped = (yaml.safe_load(f) or {}).get("data", {}).get("path")
        except (OSError, yaml.YAMLError, AttributeError):
            return None
        if not mapped or os.path.realpath(mapped) != os.path.realpath(os.fspath(data_dir)):
            return None
    return scores


def format_scores(s: dict) -> str:
    """One line for `jaxmap eval` and the run summary."""
    return (f"dynamic points (DynamicMap, of the points trained on): SA {s['sa_percent']:.2f} % "
            f"({s['static_kept']} of {s['static_points']} static kept), DA {s['da_percent']:.2f} % "
            f"({s['dynamic_removed']} of {s['dynamic_points']} dynamic removed), {s['frames']} frames")
