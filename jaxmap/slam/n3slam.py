"""`jaxmap slam` with `map_kind: n3`: the N3 map is the SLAM map, built online at the tracked poses.

Per frame of the sequence (`N3SlamStep`, a step of `jaxmap.frame_loop.run_frames`):
  1. the front end's odometry (`FrontEnd`: ICP or KISS-ICP) guesses the pose;
  2. with `n3_track`, the scan is tracked against the N3 map as trained so far
     (`jaxmap.slam.track.track_scan`: the pose that puts the scan on the map's zero level set); when
     tracking says ok (converged, small residual, and at least `n3_track_min_valid` of the points
     inside the map) the front end adopts that pose (`FrontEnd.add_frame(refine=...)`: its next
     prediction, the keyframe's graph node and the loop search start from it), else the odometry
     pose is kept;
  3. the frame goes into the N3 map at that pose (`N3Mapper.add_frame`, the frame program of `jaxmap map`);
  4. when a loop is accepted and the pose graph moves the frames, the map follows (`n3_loop`):
     `rebuild` empties the map and integrates every frame so far again at its optimised pose (when
     any frame moved more than `n3_loop_min_move_m`); `moved` removes the stored training pairs of
     the frames whose position moved more than that (`N3Mapper.forget_frames`) and adds those frames
     again, into the map as it is; `none` leaves the map as mapped (an ablation). docs/slam.md has the
     measurements that chose between them.
The preprocessed scans (sensor frame) of every frame are kept on the host for step 4 (a few hundred
kB a frame).
"""
from __future__ import annotations

import dataclasses
import logging
import os
import time

import numpy as np

from jaxmap.config import MapConfig, SlamConfig, load_config
from jaxmap.errors import JaxmapError
from jaxmap.frame_loop import Frame, Prefetcher, Progress, medians, run_frames
from jaxmap.geometry import compose
from jaxmap.n3 import scan
from jaxmap.n3.mapper import N3Mapper
from jaxmap.slam.frontend import FrontEnd
from jaxmap.slam.odometry_common import Scan

log = logging.getLogger("jaxmap")


def n3_map_config(cfg: SlamConfig, out_dir: str) -> MapConfig:
    """The N3 map's config: `cfg.n3_config` with the SLAM run's data selection (path, kind, frames) and
    `out_dir` as output."""
    d = cfg.data
    return load_config(cfg.n3_config, [f"data.path={d.path}", f"data.kind={d.kind}",
                                       f"data.begin_frame={d.begin_frame}", f"data.end_frame={d.end_frame}",
                                       f"data.every_frame={d.every_frame}", f"output={out_dir}"], schema=MapConfig)


@dataclasses.dataclass(frozen=True)
class SlamFrame(Frame):
    """A frame of a SLAM loop, its host work done in the prefetch threads: `points` as read (for the
    front end and the tracker), `prepared` the map's preprocessing of it (N3: (points, normals) sensor
    frame, and `image` the scan's range image for the map's free-space evidence, None when it is off; the
    latent map: `ImtMapper.prepare`'s HostScan; None: not made ahead), `odometry_scan` the odometry's
    (`slam.odometry_common.Scan`: downsampled points and normals at two levels)."""

    prepared: tuple | None = None
    odometry_scan: object = None


def prepare_slam_frame(cfg: SlamConfig, cfg_preprocess, seq, i: int, image: bool = False) -> SlamFrame:
    """`Prefetcher` loader: the frame as read, its N3-preprocessed points and normals (and range image),
    and the odometry's scan, each made once, off the main thread."""
    fr = seq.frame(i)
    pts, nrm, _, img = scan.preprocess(fr.points, np.eye(4), cfg_preprocess, i, image=image)
    raw = scan.clean_points(fr.points, i)
    return SlamFrame(i, int(fr.index), raw, fr.pose, image=img, prepared=(pts, nrm),
                     odometry_scan=Scan(raw, cfg.frontend.odometry))


def default_tracker(min_valid_fraction: float):
    """fn(static, state, points_s, T_init) -> TrackResult: `jaxmap.slam.track.track_scan` with its
    default options but `min_valid_fraction` (imported here: the tracker is only needed when `n3_track`
    is on)."""
    from jaxmap.slam.track import TrackOptions, track_scan

    opts = TrackOptions(min_valid_fraction=min_valid_fraction)
    return lambda static, state, points, T_init: track_scan(static, state, points, T_init, opts)


def pose_moved(a: np.ndarray, b: np.ndarray) -> float:
    """Distance (m) between the positions of two poses [4,4]."""
    return float(np.linalg.norm(np.asarray(a)[:3, 3] - np.asarray(b)[:3, 3]))


class N3SlamStep:
    """The frame-loop step of `map_kind: n3` (see the module docstring).
    track: fn(static, state, points_s, T_init) -> TrackResult, or None (odometry poses only)."""

    def __init__(self, cfg: SlamConfig, initial_pose: np.ndarray, mapper: N3Mapper, track=None, viewer=None):
        self.cfg, self.mapper, self.track, self.viewer = cfg, mapper, track, viewer
        self.fe = FrontEnd(cfg.frontend, initial_pose=initial_pose)
        self.prepared: list[tuple] = []          # per frame: (points, normals) sensor frame
        self.images: list = []                   # per frame: its range image (None: evidence off)
        self.mapped_at: list[np.ndarray] = []    # per frame: the pose its pairs are in the map at
        self.counter: list[int] = []             # per frame: its number in the map (`N3Mapper.frames` as added)
        self.odometry: list[np.ndarray] = []     # the odometry alone (its own motions chained)
        self.loops: list[dict] = []
        self.tracks: list[dict] = []             # per frame: what tracking said (ok, valid_fraction, rms_m, ...)
        self.records: list[dict] = []            # per frame: the step's record (timings of each part)

    def _refine(self, points: np.ndarray):
        """The front end's `refine` for this frame: track against the map (none before the first frame)."""
        if self.track is None or self.mapper.frames == 0:
            self.tracks.append({"ok": False, "tracked": False})
            return None

        def refine(guess: np.ndarray):
            r = self.track(self.mapper.static, self.mapper.state, points, guess)
            self.tracks.append({"tracked": True, "ok": bool(r.ok), "valid_fraction": float(r.valid_fraction),
                                "rms_m": float(r.rms_m), "iterations": int(r.iterations)})
            return np.asarray(r.pose, np.float64) if r.ok else None

        return refine

    def __call__(self, frame: SlamFrame) -> tuple[dict, np.ndarray]:
        try:
            # tracked with the map's own preprocessed points (cropped to its range, downsampled)
            pts = frame.prepared[0]
            if self.cfg.n3_track_max_range_m > 0:
                pts = pts[np.linalg.norm(pts, axis=1) <= self.cfg.n3_track_max_range_m]
            r = self.fe.add_frame(frame.points, refine=self._refine(pts), scan=frame.odometry_scan)
            self.odometry.append(frame.pose.copy() if not self.odometry else compose(self.odometry[-1], r.odometry_rel))
            self.prepared.append(frame.prepared)
            self.images.append(frame.image)
            self.mapped_at.append(r.pose.copy())
            self.counter.append(self.mapper.frames)
            info = self.mapper.add_frame(None, None, prepared=(*frame.prepared, r.pose, frame.image))
            record = dict(r.timings, map_s=info["total_s"], loss=info["loss"], loops=len(self.loops),
                          ok=r.odometry_ok, tracked=r.refined)
            if r.optimized:
                self.loops.append(self.follow_loop(frame.index))
                record["loop_map_s"] = self.loops[-1]["map_s"]
                self._show_loop(r)
            self.records.append(record)
        except Exception as e:  # the front end, the tracker or the mapper failed: say where
            log.error("jaxmap slam: frame %d failed", frame.index, exc_info=e)
            raise JaxmapError(f"jaxmap slam (map_kind n3) failed at frame {frame.index}: {type(e).__name__}: {e}") from e
        return record, r.pose

    def _show_loop(self, r) -> None:
        """The viewer redraws the trajectory and marks the loop (as `jaxmap.slam.run.FrontEndStep` does)."""
        if self.viewer is None:
            return
        self.viewer.on_trajectory(self.fe.trajectory())
        if self.fe.loops:
            c, k = self.fe.loops[-1]
            self.viewer.on_loop(r.keyframe_poses[c], r.keyframe_poses[k])

    def follow_loop(self, frame_index: int) -> dict:
        """Make the map follow the optimised trajectory (`n3_loop`); returns the loop's record."""
        traj = self.fe.trajectory()
        moves = np.array([pose_moved(a, b) for a, b in zip(self.mapped_at, traj)])
        mode, mapper = self.cfg.n3_loop, self.mapper
        moved = [i for i in range(len(traj)) if moves[i] > self.cfg.n3_loop_min_move_m]
        # rebuild: every frame again, once any moved; moved: only those
        redo = {"rebuild": list(range(len(traj))) if moved else [], "moved": moved}.get(mode, [])
        t0 = time.perf_counter()
        if mode == "rebuild" and redo:
            mapper.reset()
        removed = mapper.forget_frames([self.counter[i] for i in redo]) if mode == "moved" else 0
        for i in redo:
            self.counter[i] = mapper.frames
            mapper.add_frame(None, None, prepared=(*self.prepared[i], traj[i], self.images[i]))
            self.mapped_at[i] = traj[i].copy()
        rec = {"frame": frame_index, "mode": mode, "frames": len(traj), "reintegrated": len(redo),
               "pairs_removed": removed,
               "max_move_m": float(moves.max()), "median_move_m": float(np.median(moves)),
               "map_s": time.perf_counter() - t0}
        (log.info if redo else log.debug)(
            "loop at frame %d: the pose graph moved the frames by up to %.3f m (median %.3f m); n3_loop %s "
            "re-integrated %d of %d frames in %.1f s", frame_index, rec["max_move_m"], rec["median_move_m"],
            mode, len(redo), len(traj), rec["map_s"])
        return rec


def run_n3_frontend(cfg: SlamConfig, seq, mapper: N3Mapper, progress: bool = True, viewer=None, track=None) -> dict:
    """The front end, tracking and the online N3 map over the whole sequence.
    Returns the trajectory, the odometry alone, per-loop and per-frame tracking records, and the LoopResult."""
    if track is None and cfg.n3_track:
        track = default_tracker(cfg.n3_track_min_valid)
    step = N3SlamStep(cfg, np.asarray(seq.poses[0], np.float64), mapper, track, viewer)
    load = lambda s, i: prepare_slam_frame(cfg, mapper.cfg.preprocess, s, i, mapper.static.evidence)  # noqa: E731
    bar = Progress("slam (n3)", progress, postfix=lambda r: {"loops": r["loops"], "tracked": r["tracked"]})
    loop = run_frames(Prefetcher(seq, 0, len(seq), load), step, total=len(seq), progress=bar, viewer=viewer)
    return {"trajectory": step.fe.trajectory(), "odometry": np.asarray(step.odometry), "loops": step.loops,
            "keyframe_frames": [int(seq.indices[i]) for i in step.fe.kf_frame], "tracking": step.tracks,
            "loop": loop, "step_medians": medians(step.records, ("odometry_s", "refine_s", "map_s", "loop_s"))}


def open_n3_mapper(cfg: SlamConfig, out_dir: str, seq) -> N3Mapper:
    """The run's N3 map (config in out_dir/n3_config.yaml's place: the caller saves it)."""
    mcfg = n3_map_config(cfg, out_dir)
    if mcfg.preprocess.device == "true":
        raise JaxmapError(f"{cfg.n3_config}: preprocess.device=true is not supported by jaxmap slam; set it to false "
                          "or auto")
    # the tracker reads the map's preprocessed points on the host: auto is the host here
    mcfg = dataclasses.replace(mcfg, preprocess=dataclasses.replace(mcfg.preprocess, device="false"))
    first = seq.frame(0) if len(seq) else None
    return N3Mapper(mcfg, first_scan=(first.points, first.pose) if first is not None else None)


def n3_checkpoint(mapper: N3Mapper, out_dir: str) -> str:
    path = os.path.join(out_dir, "checkpoint")
    mapper.save(path)
    return path
