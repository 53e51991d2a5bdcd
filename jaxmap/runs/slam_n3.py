"""`jaxmap slam` with `map_kind: n3`: the N3 map is the SLAM map, built online at the tracked poses.

Per frame of the sequence (`N3SlamStep`, the `Steps` of `jaxmap.frame_loop.run_frames`):
  1. the front end's odometry (`FrontEnd`: ICP or KISS-ICP) guesses the pose (while the map program of
     the frame before still runs: the map's frames are dispatched, not waited for);
  2. with `n3_track`, the scan is tracked against the N3 map as trained so far, that frame included
     (`jaxmap.slam.track.track_scan`: the pose that puts the scan on the map's zero level set; with
     submaps, against the nearest of at least `n3_track_submap_min_frames` frames); when tracking says
     ok (converged, small residual, and at least `n3_track_min_valid` of the points inside the map) the
     front end adopts that pose (`FrontEnd.add_frame(refine=...)`: its next prediction, the keyframe's
     graph node and the loop search start from it), else the odometry pose is kept;
  3. the frame goes into the N3 map at that pose (`N3Mapper.submit_prepared`, the frame program of
     `jaxmap map`), and its record comes back with the next frame's;
  4. when a loop is accepted and the pose graph moves the frames, the map follows with one call,
     `FollowingMap.correct(trajectory)` (`jaxmap.n3.following`, by `n3_loop`): `submaps` moves each
     submap as a rigid body to fit its frames' corrections (no re-training) and re-adds the frames of the
     submap being mapped that still moved against it; `moved` queues the frames that moved more than
     `n3_loop_min_move_m`, largest move first, and re-adds `n3_loop_readd_per_frame` of them after each
     of the next frames (0: all at the loop, which stalled the main thread 27-42 s on the suite's
     streets); `rebuild` maps every frame again; `none` leaves the map (an ablation). docs/slam.md has the
     measurements that chose between them.
The map keeps every frame's preprocessed scan (sensor frame) for step 4, one file a frame in the run's
slam_scans/ (`ScanStore`: ~1.5 MB a frame, two in memory).

`jaxmap.runs.slam.run_slam` drives, saves and resumes this step as it does the latent map's
(`jaxmap.runs.slam_step`: the map in checkpoint/, the step's state in slam_state.pkl: the front end with
its pose graph and KISS-ICP's local map, the per-frame records, the scans' count).
"""
from __future__ import annotations

import dataclasses
import logging
import os

import numpy as np

from jaxmap.config import ConfigError, MapConfig, SlamConfig, load_config, save_config, validate
from jaxmap.errors import JaxmapError
from jaxmap.n3 import scan
from jaxmap.n3.core import PROGRAMS
from jaxmap.n3.following import FollowingMap, FollowRule
from jaxmap.n3.mapper import N3Mapper
from jaxmap.n3.scan import MapStart, PreparedScan
from jaxmap.n3.scan_store import ScanStore
from jaxmap.n3.submap_mapper import new_map
from jaxmap.records import medians
from jaxmap.runs.slam_step import SlamFrame, SlamStep, show_loop
from jaxmap.slam.frontend import FrontEnd
from jaxmap.slam.odometry_common import Scan

log = logging.getLogger("jaxmap")

SCANS_DIR = "slam_scans"


def n3_map_config(cfg: SlamConfig, out_dir: str) -> MapConfig:
    """The N3 map's config: `cfg.n3_config` with `cfg.n3_set`'s overrides, the SLAM run's data selection
    (path, kind, frames) and `out_dir` as output."""
    d = cfg.data
    return load_config(cfg.n3_config, [*cfg.n3_set, f"data.path={d.path}", f"data.kind={d.kind}",
                                       f"data.begin_frame={d.begin_frame}", f"data.end_frame={d.end_frame}",
                                       f"data.every_frame={d.every_frame}", f"output={out_dir}"], schema=MapConfig)


def prepare_slam_frame(cfg: SlamConfig, start: MapStart, seq, i: int, fr=None) -> SlamFrame:
    """`Prefetcher` loader: the frame as read (fr: `seq.frame(i)` read already), its points and normals (and
    range image) made ready for the N3 map (`start.prepare`, before the pose is known), and the odometry's
    scan, each made once, off the main thread."""
    fr = seq.frame(i) if fr is None else fr
    ready, _ = start.prepare(fr.points, np.eye(4), i)
    raw = scan.clean_points(fr.points, i)
    return SlamFrame(i, int(fr.index), raw, fr.pose, image=ready.image, prepared=(ready.points, ready.normals),
                     odometry_scan=Scan(raw, cfg.frontend.odometry))


def default_tracker(cfg: SlamConfig):
    """fn(static, state, points_s, T_init) -> TrackResult: `jaxmap.slam.track.track_scan` with its
    default options but the run's `n3_track_min_valid` and `n3_track_min_seen` (imported here: the
    tracker is only needed when `n3_track` is on). With `n3_track_young_rotation`, a scan whose points
    are mostly not settled (the map of the first frame, or of a new street's first pass) is tracked
    again with every point, and its rotation is taken with the guess's position: such a map's field is
    biased around the sensor (it reads the true road centimetres above its zero set between the rings
    it saw), which moves the position along the road's normal but not the tilt, fitted over the whole
    scan's extent (measured on the HDL-64E city, frame 1: tilt 0.014 deg off against the odometry's 0.064,
    height 1.1 cm low against 0.3 cm high; docs/slam.md)."""
    from jaxmap.slam.track import TrackOptions, track_scan

    opts = TrackOptions(min_valid_fraction=cfg.n3_track_min_valid, min_seen=cfg.n3_track_min_seen,
                        max_points=cfg.n3_track_points)
    if not cfg.n3_track_young_rotation or opts.min_seen <= 1:
        return lambda static, state, points, T_init: track_scan(static, state, points, T_init, opts)
    every = dataclasses.replace(opts, min_seen=1)   # every point (1: the settled program, its bar off)

    def track(static, state, points, T_init):
        r = track_scan(static, state, points, T_init, opts)
        if r.ok or r.settled_fraction >= opts.min_settled_fraction:
            return r
        y = track_scan(static, state, points, T_init, every)
        if not y.ok:
            return r
        pose = np.array(T_init, np.float64)
        pose[:3, :3] = y.pose[:3, :3]
        return y._replace(pose=pose, settled_fraction=r.settled_fraction)

    return track


class N3SlamStep(SlamStep):
    """The frame-loop step of `map_kind: n3` (see the module docstring).
    track (`attach`): fn(static, state, points_s, T_init) -> TrackResult, or None (odometry poses only)."""

    map_kind = "n3"
    label = "slam (n3)"
    _run_only = (*SlamStep._run_only, "last", "_first")   # (`last`: a state saved before `total` replaced it)

    def __init__(self, cfg: SlamConfig, initial_pose: np.ndarray, mapper: N3Mapper, scans: ScanStore | None = None,
                 first: SlamFrame | None = None):
        """first: frame 0 made ready already (`open_n3_step`: the map compiled its program from it), handed to
        the frame loop by `load_frame` instead of read and prepared again."""
        super().__init__(cfg, FrontEnd(cfg.frontend, initial_pose=initial_pose))
        self.map = FollowingMap(mapper, FollowRule.of(cfg), scans)   # the map and its frames (step 4)
        self._first = first
        self.tracks: list[dict] = []             # per frame: what tracking said (ok, valid_fraction, rms_m, ...)
        self._waiting: dict = {}                 # map frame number -> (frame, record, pose): in flight
        self._finished: list = []                # (frame, record, pose) finished, not yet returned to the loop

    @property
    def mapper(self) -> N3Mapper:
        return self.map.mapper

    @mapper.setter
    def mapper(self, value: N3Mapper) -> None:
        self.map.mapper = value

    @property
    def scans(self) -> ScanStore:
        return self.map.scans

    @property
    def frames_done(self) -> int:
        return len(self.scans)

    @staticmethod
    def progress(record: dict) -> dict:
        return {"loops": record["loops"], "tracked": record["tracked"]}

    def __setstate__(self, state: dict) -> None:
        if "prepared" in state:  # saved before the scans went to disk (their lists in the state itself)
            state["scans"] = ScanStore()
            for (points, normals), image in zip(state.pop("prepared"), state.pop("images")):
                state["scans"].append(PreparedScan(points, normals, image))
        if "map" not in state:  # saved before the map followed corrections itself: its frames were the step's
            fm = FollowingMap.__new__(FollowingMap)
            fm.__setstate__({k: state.pop(k) for k in ("scans", "mapped_at", "counter", "submap", "pending",
                                                       "readds", "pairs_removed") if k in state})
            fm.rule = FollowRule.of(state["cfg"]) if "cfg" in state else FollowRule()
            state["map"] = fm
        for k in ("mapper", "last"):
            state.pop(k, None)
        super().__setstate__(state)
        self._waiting, self._finished = {}, []   # (a save settles the frames in flight first: `save_slam`)
        self._first = None

    def attach(self, mapper, *, viewer=None, out_dir: str | None = None, total: int = 0, track=None) -> None:
        """`SlamStep.attach`; track None: `default_tracker` when `n3_track` is on."""
        if track is None and self.cfg.n3_track:
            track = default_tracker(self.cfg)
        super().attach(mapper, viewer=viewer, out_dir=out_dir, total=total, track=track)

    def moved_to(self, out_dir: str) -> None:
        if self.scans.directory is not None:
            self.scans.directory = os.path.join(out_dir, SCANS_DIR)

    def _refine(self, points: np.ndarray):
        """The front end's `refine` for this frame: track against the map (none before the first frame)."""
        if self.track is None or self.mapper.frames == 0:
            self.tracks.append({"ok": False, "tracked": False})
            return None

        def refine(guess: np.ndarray):
            # one grid: the map; submaps: the one whose path passes nearest, of n3_track_submap_min_frames at least
            static, state, T = self.mapper.tracking_map(guess[:3, 3], min_frames=self.cfg.n3_track_submap_min_frames)
            r = self.track(static, state, points, np.linalg.inv(T) @ guess)
            self.tracks.append({"tracked": True, "ok": bool(r.ok), "valid_fraction": float(r.valid_fraction),
                                "rms_m": float(r.rms_m), "iterations": int(r.iterations),
                                "settled_fraction": float(r.settled_fraction)})
            return T @ np.asarray(r.pose, np.float64) if r.ok else None

        return refine

    def _submit(self, frame: SlamFrame) -> list:
        """The front end (odometry, tracking) on this frame, then its map frame dispatched without waiting
        for it, so that the next frame's odometry runs while the map trains (its tracking waits for the
        map: it reads the state this frame makes). Returns the frames whose map frame finished meanwhile,
        (frame, record, pose) each, oldest first."""
        # tracked with the map's own preprocessed points (cropped to its range, downsampled)
        pts = frame.prepared[0]
        if self.cfg.n3_track_max_range_m > 0:
            pts = pts[np.linalg.norm(pts, axis=1) <= self.cfg.n3_track_max_range_m]
        r = self.front_end(frame, refine=self._refine(pts))
        record = dict(r.timings, loops=len(self.loops), ok=r.odometry_ok, tracked=r.refined)
        n = self.map.add(PreparedScan(*frame.prepared, frame.image), r.pose)
        self._waiting[n] = (frame, record, r.pose)
        self._route()
        if r.optimized:
            self.loops.append(self.follow_loop(frame.index))
            record["loop_map_s"] = self.loops[-1]["map_s"]
            show_loop(self.viewer, self.fe, r)
        if self.map.pending:  # n3_loop_readd_per_frame a frame; the last frame re-adds those left
            k = len(self.map.pending) if frame.position >= self.total - 1 else max(1, self.cfg.n3_loop_readd_per_frame)
            record["readd_s"] = self.map.readd(k, self.fe.trajectory())
            self._route()
        return self._take_finished()

    def drain(self) -> list:
        """The frame loop's `Steps.drain`: wait for the frames in flight; what `submit` returns."""
        self.settle()
        return self._take_finished()

    def settle(self) -> None:
        """Wait for every map frame in flight (their records go into `records`)."""
        self.map.settle()
        self._route()

    def _route(self) -> None:
        """Pair the map's records of finished frames ((record, kept) each) with the frames waiting for them
        (a re-add's record has none waiting: its frame's record was made when it was first mapped)."""
        for info, _ in self.map.take_finished():
            entry = self._waiting.pop(int(info["frame"]), None)
            if entry is not None:
                entry[1].update(map_s=info["total_s"], loss=info["loss"])
                self.records.append(entry[1])
                self._finished.append(entry)

    def _take_finished(self) -> list:
        out, self._finished = self._finished, []
        return out

    def follow_loop(self, frame_index: int) -> dict:
        """The map follows the optimised trajectory (`FollowingMap.correct`, by `n3_loop`); returns the
        loop's record."""
        record = self.map.correct(self.fe.trajectory())
        self._route()
        return {"frame": frame_index, **record}

    def load_frame(self, seq, i: int) -> SlamFrame:
        first = self._first
        if first is not None and first.position == i:  # (handed over once; another thread's frame leaves it)
            self._first = None
            return first
        return prepare_slam_frame(self.cfg, self.mapper.start, seq, i)

    def summary(self, res: dict) -> dict:
        """Tracking, the loops' map time and re-adds, the medians of the step's parts."""
        tracked = [t for t in self.tracks if t.get("tracked")]
        return {"tracked_frames": len(tracked), "tracked_ok": sum(t["ok"] for t in tracked),
                "loop_map_s": float(sum(lp["map_s"] for lp in self.loops)),
                "loop_readd_s": float(sum(r.get("readd_s", 0.0) for r in self.records)),
                "loop_readds": self.map.readds, "loop_readd_pairs_removed": self.map.pairs_removed,
                "tracking": self.tracks,
                "step": medians(self.records, ("odometry_s", "refine_s", "level_s", "map_s", "loop_s"))}

    def compiles_since(self, n: int) -> dict:
        return PROGRAMS.compiles_since(n)


def open_n3_step(cfg: SlamConfig, out_dir: str, seq) -> tuple[N3Mapper, N3SlamStep]:
    """A new run's (map, step), the map an N3 map: one grid, or with `n3_loop: submaps` a `SubmapMapper` (submaps of
    n3_submap_m, each pass its own, in out_dir/submaps); the map's resolved config saved as
    out_dir/n3_config.yaml, the scans kept in out_dir/slam_scans. Frame 0 is read and made ready once: the
    map's start (range-image layout, map frame at the first pose) and its frame program come from it, and
    the step hands it to the frame loop."""
    mcfg = slam_map_config(cfg, out_dir)
    pose0 = np.asarray(seq.poses[0], np.float64) if len(seq) else np.eye(4)
    first = first_batch = None
    if not len(seq):
        start = MapStart.of(mcfg)
    else:
        fr = seq.frame(0)
        start = MapStart.of(mcfg, fr.points, fr.pose)
        first = prepare_slam_frame(cfg, start, seq, 0, fr)
        first_batch = start.first_batch(PreparedScan(*first.prepared, first.image), pose0)
    mapper = new_map(start, os.path.join(out_dir, "submaps"), first_batch=first_batch)
    save_config(mapper.cfg, os.path.join(out_dir, "n3_config.yaml"))
    return mapper, N3SlamStep(cfg, pose0, mapper, ScanStore(os.path.join(out_dir, SCANS_DIR)), first)


def slam_map_config(cfg: SlamConfig, out_dir: str) -> MapConfig:
    """The N3 map's config in a SLAM run (`n3_map_config`, checked): preprocessed on the host (the tracker
    reads the map's preprocessed points), in submaps with `n3_loop: submaps`."""
    mcfg = n3_map_config(cfg, out_dir)
    if mcfg.preprocess.device == "true":
        raise JaxmapError(f"{cfg.n3_config}: preprocess.device=true is not supported by jaxmap slam; set it to false "
                          "or auto")
    # the tracker reads the map's preprocessed points on the host: auto is the host here
    mcfg = dataclasses.replace(mcfg, preprocess=dataclasses.replace(mcfg.preprocess, device="false"))
    if cfg.n3_loop == "submaps":
        # two resident: a new submap's first frames are tracked against the one left (not read back from disk)
        sub = dataclasses.replace(mcfg.submaps, enabled=True, length_m=cfg.n3_submap_m, revisit=False,
                                  resident=max(mcfg.submaps.resident, 2))
        mcfg = dataclasses.replace(mcfg, submaps=sub)
        validate(mcfg, cfg.n3_config)
    elif mcfg.submaps.enabled:
        raise ConfigError(f"{cfg.n3_config}: submaps.enabled=true: jaxmap slam maps in submaps with "
                          f"n3_loop=submaps (now {cfg.n3_loop}); set submaps.enabled=false or n3_loop=submaps")
    return mcfg
