"""`jaxmap localize MAP --data SEQ [--init POSE] [--out RUN]`: localise a new sequence in a saved N3 map
(tracking against the map, `jaxmap.slam.track`; the map is not updated).

Per frame (through the frame loop): the pose is predicted with a constant-velocity model from the two
poses before it (the first frame: --init, else the sequence's first pose), the scan is cropped as the
map's config crops (`preprocess`: range and height) and voxel-downsampled (`voxel_m`), and tracked
against the map from the prediction; if that fails (a corner the prediction did not turn into), again
after a search of shifts and turns (`TrackOptions.search_m`: +-0.5 m, +-20 degrees). The first two
frames, and the frame after a lost one, where no velocity is known, are searched at once (+-2 m). A frame whose tracking is not `ok` (too few points inside the map,
a large RMS SDF, no convergence) keeps the prediction and counts as not localised; the next frames
are predicted on from it. The first frame must localise: if it does not (a sequence outside the map,
or an initial pose far off), the run stops with a DataError that says so and what to try.

A run directory holds config.yaml (the map's), trajectory_kitti.txt and trajectory_tum.txt (every frame,
T_world_sensor in the map's world frame), frames.json (per frame: localised, valid fraction, RMS SDF,
iterations, time) and metrics.json: the fraction of frames localised and, when the sequence has a
poses.txt (ground truth in the same world frame), the position error (cm: median, mean, p95, max) and
the rotation error (degrees) of every frame and of the localised ones; the time of the first frame
(compiling included) and the median of the others.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import os
import time

import numpy as np

from jaxmap.config import save_config
from jaxmap.errors import CheckpointError, DataError, NoCheckpointError
from jaxmap.frame_loop import Frame, Prefetcher, Progress, run_frames
from jaxmap.geometry import compose, orthonormalize, pose_change, se3_inverse, validate_pose
from jaxmap.io import open_sequence
from jaxmap.preprocess import crop, voxel_downsample
from jaxmap.slam.track import TrackOptions, track_scan
from jaxmap.slam.trajectory import write_trajectory

DEFAULT_VOXEL_M = 0.2   # scans are downsampled to this before the `max_points` subset is drawn
SEARCH_WIDE_M = 2.0     # the search's half-width where the guess is weak: the first two frames, after a lost one
SEARCH_NARROW_M = 0.5   # ... and where LM from the constant-velocity prediction failed


def read_init(text: str) -> np.ndarray:
    """The --init pose: 12 (a KITTI line, row-major 3x4) or 16 (row-major 4x4) numbers, separated by
    spaces or commas, or a file holding them (its first pose: a KITTI line, or a 4x4 matrix on 4 lines).
    [4, 4] float64 T_world_sensor; a DataError naming what to write otherwise."""
    src = f"--init {text}"
    if os.path.isfile(text):
        with open(text) as f:
            lines = [ln for ln in f.read().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
        first = lines[0].replace(",", " ").split() if lines else []
        body = " ".join(lines[:1] if len(first) == 12 else lines[:4])
        src = f"{text} (--init)"
    else:
        body = text
    try:
        vals = [float(v) for v in body.replace(",", " ").split()]
    except ValueError:
        vals = []
    if len(vals) not in (12, 16):
        raise DataError(f"{src}: not a pose; give 12 numbers (a KITTI line, row-major 3x4 [R|t]) or 16 (a 4x4 "
                        "matrix), in quotes, or a file holding them")
    T = np.eye(4)
    T[:len(vals) // 4] = np.asarray(vals, np.float64).reshape(-1, 4)
    validate_pose(T, where="the initial pose", source=src)
    return T


def open_map(path: str):
    """The map (N3Mapper, or SubmapMapper for a map of submaps) of a `jaxmap map` run directory (its
    checkpoint/) or of a checkpoint directory."""
    from jaxmap.n3.submap_mapper import load_map

    if not os.path.isdir(path):
        raise DataError(f"{path}: not a directory; pass the run directory of a jaxmap map run (its --out)")
    ckpt = os.path.join(path, "checkpoint")
    try:
        return load_map(ckpt if os.path.isdir(ckpt) else path)
    except NoCheckpointError:
        raise DataError(f"{path}: no N3 map checkpoint; pass the --out of a finished jaxmap map run") from None
    except CheckpointError as e:
        raise DataError(f"{path}: the map cannot be read ({e})") from None


def tracking_frame(cfg_preprocess, voxel_m: float, seq, i: int) -> Frame:
    """`Prefetcher` loader: frame i cropped as the map's config crops, downsampled to voxel_m."""
    fr = seq.frame(i)
    p = cfg_preprocess
    pts = crop(np.asarray(fr.points, np.float32), p.min_range_m, p.max_range_m, p.min_z_m, p.max_z_m)
    return Frame(i, int(fr.index), voxel_downsample(pts, voxel_m), fr.pose)


def predict(poses: list) -> np.ndarray:
    """Constant velocity: the last pose moved again by the motion between the last two."""
    if len(poses) < 2:
        return poses[-1]
    return orthonormalize(compose(poses[-1], se3_inverse(poses[-2]), poses[-1]))


class LocalizeStep:
    """The step of the frame loop: predict, track against the map, keep the prediction if lost."""

    def __init__(self, mapper, init_pose: np.ndarray, opts: TrackOptions, seq, map_path: str):
        self.mapper, self.opts, self.seq, self.map_path = mapper, opts, seq, map_path
        self.init = np.asarray(init_pose, np.float64)
        self.poses: list[np.ndarray] = []
        self.records: list[dict] = []

    def __call__(self, frame: Frame) -> tuple[dict, np.ndarray]:
        guess = predict(self.poses) if self.poses else self.init
        weak = len(self.poses) < 2 or not self.records[-1]["ok"]
        t0 = time.perf_counter()
        # where constant velocity predicted the pose, LM from it alone first (the search costs more than LM)
        tries = [SEARCH_WIDE_M] if weak else [0.0, SEARCH_NARROW_M]
        # the map to track against: the whole map, or the submap whose sensor path passes nearest the guess
        static, state, T = self.mapper.tracking_map(guess[:3, 3])
        local = np.linalg.inv(T) @ guess
        for search_m in tries:
            res = track_scan(static, state, frame.points, local, dataclasses.replace(self.opts, search_m=search_m))
            if res.ok:
                break
        res = res._replace(pose=T @ res.pose)
        record = {"frame": frame.index, "ok": res.ok, "valid": round(res.valid_fraction, 4),
                  "rms_cm": round(100 * res.rms_m, 2), "iterations": res.iterations, "search_m": search_m,
                  "points": len(frame.points), "track_s": time.perf_counter() - t0}
        if not self.poses and not res.ok:
            raise self._first_frame_error(frame, res)
        pose = res.pose if res.ok else guess
        self.poses.append(pose)
        self.records.append(record)
        return record, pose

    def _first_frame_error(self, frame: Frame, res) -> DataError:
        where = self.seq.source(frame.index)
        o = self.opts
        return DataError(
            f"{where}: the first frame could not be localised in the map {self.map_path}: "
            f"{100 * res.valid_fraction:.0f} % of its points inside the map (needs {100 * o.min_valid_fraction:.0f} %), "
            f"RMS SDF {100 * res.rms_m:.1f} cm (needs <= {100 * o.max_rms_m:.0f} cm). Either the sequence lies "
            "outside the map, or the initial pose is off by more than about 2 m or 20 degrees: pass --init "
            "with the first scan's LiDAR pose in the map's world frame (12 numbers as a line of jaxmap's "
            "trajectory_kitti.txt, or a file)")


def pose_errors(est: np.ndarray, gt: np.ndarray, ok: np.ndarray) -> dict:
    """Position (cm) and rotation (degrees) errors of est against gt ([N, 4, 4] each), over all frames
    and over the localised ones (`ok`)."""
    rot, _ = pose_change(gt, est)
    pos = np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1) * 100.0
    rot = np.rad2deg(rot)
    out = {}
    for tag, sel in (("", np.ones(len(est), bool)), ("localised_", ok)):
        if not sel.any():
            continue
        p, r = pos[sel], rot[sel]
        out.update({f"{tag}position_error_cm": {"median": float(np.median(p)), "mean": float(p.mean()),
                                                "p95": float(np.percentile(p, 95)), "max": float(p.max())},
                    f"{tag}rotation_error_deg": {"median": float(np.median(r)), "max": float(r.max())}})
    return out


def localize_sequence(map_path: str, data: str, out_dir: str, init: np.ndarray | None = None,
                      opts: TrackOptions = TrackOptions(), voxel_m: float = DEFAULT_VOXEL_M,
                      progress: bool = True) -> dict:
    """Localise the sequence `data` in the map of `map_path` (see the module docstring); returns metrics."""
    mapper = open_map(map_path)
    seq = open_sequence(data)
    has_gt = os.path.isfile(os.path.join(seq.data_dir, "poses.txt"))
    if init is None:
        init = np.array(seq.poses[0]) if has_gt else np.eye(4)
    os.makedirs(out_dir, exist_ok=True)
    save_config(mapper.cfg, os.path.join(out_dir, "config.yaml"))
    step = LocalizeStep(mapper, init, opts, seq, map_path)
    bar = Progress("localize", progress, first="compiling",
                   postfix=lambda r: {"ok": r["ok"], "valid": f"{r['valid']:.2f}", "rms": f"{r['rms_cm']:.1f}cm"})
    loop = run_frames(Prefetcher(seq, 0, len(seq), functools.partial(tracking_frame, mapper.cfg.preprocess, voxel_m)),
                      step, total=len(seq), progress=bar)
    return write_outputs(out_dir, seq, step, has_gt, loop.wall_s)


def write_outputs(out_dir: str, seq, step: LocalizeStep, has_gt: bool, wall_s: float) -> dict:
    """trajectory_kitti.txt, trajectory_tum.txt, frames.json and metrics.json; returns the metrics."""
    traj = np.stack(step.poses)
    recs = step.records
    write_trajectory(out_dir, seq, traj)
    ok = np.array([r["ok"] for r in recs], bool)
    times = [r["track_s"] for r in recs]
    m = {"run": out_dir, "frames": len(recs), "localised": int(ok.sum()), "localised_fraction": float(ok.mean()),
         "lost_frames": [int(r["frame"]) for r in recs if not r["ok"]],
         "first_frame_s": float(times[0]), "median_frame_s": float(np.median(times[1:] or times)),
         "wall_s": float(wall_s)}
    if has_gt:
        m.update(pose_errors(traj, np.asarray(seq.poses[:len(traj)], np.float64), ok))
    with open(os.path.join(out_dir, "frames.json"), "w") as f:
        json.dump(recs, f)
    with open(os.path.join(out_dir, "metrics.json"), "w") as f:
        json.dump(m, f, indent=1)
    return m


def frame_ranges(frames: list[int]) -> str:
    """Frame numbers as ranges: [10, 11, 12, 15] -> "10-12, 15"."""
    runs: list[list[int]] = []
    for f in sorted(frames):
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    return ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in runs)


def summary_table(m: dict) -> str:
    """The lines `jaxmap localize` prints before its JSON line: the frames localised and those lost (as
    ranges), the errors over all frames and, when some were lost, over the localised ones beside them (a
    lost frame keeps its prediction, whose error says little about the localisation)."""
    rows = [f"frames localised   {m['localised']} / {m['frames']} ({100 * m['localised_fraction']:.1f} %)"]
    if m.get("lost_frames"):
        rows.append(f"lost frames        {frame_ranges(m['lost_frames'])}")
    lost = bool(m.get("lost_frames")) and "localised_position_error_cm" in m
    for tag, key, fmt in (("position", "position_error_cm", "median {median:.1f} cm, p95 {p95:.1f} cm, max {max:.1f} cm"),
                          ("rotation", "rotation_error_deg", "median {median:.2f} deg, max {max:.2f} deg")):
        if key in m:
            rows.append(f"{tag + ' error':<19}" + ("all frames: " if lost else "") + fmt.format(**m[key]))
            if lost:
                rows.append(" " * 19 + "localised:  " + fmt.format(**m[f"localised_{key}"]))
    rows.append(f"time per frame     first {m['first_frame_s']:.2f} s (compiling), then median "
                f"{1000 * m['median_frame_s']:.0f} ms")
    return "\n".join(rows)
