"""The point scores of the dynamic-removal field (KTH's DynamicMap benchmark): of the scan points a mapper
received, how many static ones its map kept and how many dynamic ones it removed.

    SA (static accuracy)  = static points kept / static points        (%)
    DA (dynamic accuracy) = dynamic points removed / dynamic points   (%)

over the points of every mapped frame as the mapper received them (after its preprocessing: the rows of
the frame's prepared points, sensor frame, in order), in two senses:
  map      (DynamicMap's: the output map) a point is kept when the map still holds its place: its leaf
           voxel is not void at the end of the run (free-space evidence, `jaxmap.n3.evidence`; a map
           without evidence keeps every point). A car that drove off is removed, a car still there at the
           last frame is kept, as a static map built from the whole sequence would keep it.
  trained  a point is kept when it produced training samples in its frame (`N3Mapper.add_frame(...)["kept"]`,
           [M] bool; a mapper that does not report it trained on them all): what the online map learnt from.

A point is dynamic when it lies inside one of its frame's moving-object boxes (`jaxmap.moving`,
moving_objects.json: indexed by the sequence's own frame number), each box grown by DYNAMIC_INFLATE_M
(0.1 m, as the ghost area's) on its four sides and on top, but not below: the box's bottom is raised by
GROUND_CLEARANCE_M (0.1 m) over its base, so the road or sidewalk under and around a car or a pedestrian
stays static (it is in the static map; counting it dynamic would make a mapper that keeps the ground
look like one that keeps the car). The few returns on an object's lowest 0.1 m count static.

The labels of a frame cost one `jaxmap.moving.inside_boxes` over its points (vectorised, numpy): an N3
run's `RunScores` computes them where it prepares the frame (the prefetch thread), and counts them
against "kept" once the frame is mapped (four sums).
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


def voxel_keys(coords: np.ndarray) -> np.ndarray:
    """[N] int64 keys of integer voxel coordinates [N, 3] (each within +-2^20 voxels of the map origin)."""
    c = np.asarray(coords, np.int64) + (1 << 20)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


class _KeyCounts:
    """Points per voxel key (static and dynamic), merged every few frames so memory follows the voxels."""

    def __init__(self):
        self.keys = np.zeros(0, np.int64)
        self.counts = np.zeros((0, 2), np.int64)
        self.pending: list = []

    def add(self, keys: np.ndarray, dynamic: np.ndarray) -> None:
        self.pending.append((keys, dynamic))
        if len(self.pending) >= 32:
            self.merge()

    def merge(self) -> None:
        if not self.pending:
            return
        k = np.concatenate([self.keys] + [p[0] for p in self.pending])
        c = np.concatenate([self.counts] + [np.stack([~p[1], p[1]], 1).astype(np.int64) for p in self.pending])
        self.keys, inv = np.unique(k, return_inverse=True)
        self.counts = np.zeros((len(self.keys), 2), np.int64)
        np.add.at(self.counts, inv.reshape(-1), c)
        self.pending = []


@dataclasses.dataclass
class PointScores:
    """The counts over the frames added so far (running sums, host side), `trained` sense; the `map` sense
    from the points' voxel keys once the final map says which voxels are void (`result`)."""

    static_points: int = 0
    static_kept: int = 0
    dynamic_points: int = 0
    dynamic_removed: int = 0
    frames: int = 0
    by_voxel: _KeyCounts = dataclasses.field(default_factory=_KeyCounts, repr=False)

    def add(self, dynamic: np.ndarray, kept: np.ndarray | None = None, keys: np.ndarray | None = None) -> None:
        """One frame: dynamic [M] bool labels, kept [M] bool (None: every point trained on), keys [M] int64
        the points' leaf-voxel keys in the map (`voxel_keys`; None: no map sense)."""
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
        if keys is not None:
            self.by_voxel.add(np.asarray(keys, np.int64), dynamic)

    def result(self, void_keys: np.ndarray | None = None) -> dict:
        """{"sa_percent", "da_percent" (the map sense when void_keys, [K] int64 keys of the final map's void
        voxels, is given and keys were added; else the trained sense), "trained": {...}, the counts, "frames",
        "inflate_m", "ground_m"}: what metrics.json holds as "dynamic_points"."""
        nan = float("nan")

        def pct(a, b):
            return 100.0 * a / b if b else nan

        counts = {k: getattr(self, k) for k in ("static_points", "static_kept", "dynamic_points", "dynamic_removed")}
        trained = {"sa_percent": pct(self.static_kept, self.static_points),
                   "da_percent": pct(self.dynamic_removed, self.dynamic_points), **counts}
        out = {**trained, "sense": "trained"}
        self.by_voxel.merge()
        if void_keys is not None and len(self.by_voxel.keys):
            gone = np.isin(self.by_voxel.keys, np.asarray(void_keys, np.int64))
            st, dy = self.by_voxel.counts[:, 0], self.by_voxel.counts[:, 1]
            counts = {"static_points": int(st.sum()), "static_kept": int(st[~gone].sum()),
                      "dynamic_points": int(dy.sum()), "dynamic_removed": int(dy[gone].sum())}
            out = {"sa_percent": pct(counts["static_kept"], counts["static_points"]),
                   "da_percent": pct(counts["dynamic_removed"], counts["dynamic_points"]), **counts, "sense": "map"}
        return {**out, "trained": trained, "frames": self.frames, "inflate_m": DYNAMIC_INFLATE_M,
                "ground_m": GROUND_CLEARANCE_M}


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
    what = "of the final map" if s.get("sense") == "map" else "of the points trained on"
    line = (f"dynamic points (DynamicMap, {what}): SA {s['sa_percent']:.2f} % "
            f"({s['static_kept']} of {s['static_points']} static kept), DA {s['da_percent']:.2f} % "
            f"({s['dynamic_removed']} of {s['dynamic_points']} dynamic removed), {s['frames']} frames")
    t = s.get("trained")
    if s.get("sense") == "map" and t:
        line += f"; trained on: SA {t['sa_percent']:.2f} %, DA {t['da_percent']:.2f} %"
    return line


class RunScores:
    """The point scores of one mapping run of a sequence with moving objects, kept beside the mapping: its
    frames labelled where they are prepared (`label`, in the prefetch thread), each finished frame counted
    against the points the map trained on (`counter`, the frame loop's on_finished), the map sense once
    the map is final (`result`: metrics.json's "dynamic_points")."""

    def __init__(self, labeller: Labeller):
        self.labeller, self.scores = labeller, PointScores()

    @classmethod
    def of_sequence(cls, data_dir) -> "RunScores | None":
        """The scores of a run of the sequence in `data_dir`; None when it has no moving objects."""
        labeller = labeller_for(data_dir)
        return cls(labeller) if labeller is not None else None

    def label(self, points_s, pose, index: int) -> np.ndarray:
        """[M] bool: the frame's points (sensor frame, at pose [4, 4]) inside its moving-object boxes."""
        return self.labeller(points_s, pose, index)

    def counter(self, voxel_coords):
        """fn(frame, record, kept) counting a finished frame (its `dynamic` labels, kept [M] bool or None)
        at its points' map voxels `voxel_coords(points_s, pose)` ([M, 3] int, one lattice for the run)."""
        def add(frame, record, kept) -> None:
            if frame.dynamic is not None:
                self.scores.add(frame.dynamic, kept, voxel_keys(voxel_coords(frame.points, frame.pose)))

        return add

    def result(self, void_voxels: np.ndarray) -> dict:
        """`PointScores.result` with the final map's void voxels [K, 3] (the same lattice)."""
        return self.scores.result(voxel_keys(void_voxels))
