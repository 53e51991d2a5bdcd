"""What every `jaxmap slam` step shares, whatever its map: the frame, the front end's odometry chain, the
failure that names its frame, the run's summary parts, and one way to save and resume a SLAM run.

A SLAM step is the `Steps` of `jaxmap.frame_loop.run_frames` for one map kind (`jaxmap.runs.slam_imt`:
the transformable latent map, or pose snapshots of another SLAM system; `jaxmap.runs.slam_n3`: the N3
map). `jaxmap.runs.slam.run_slam` drives any of them the same way:

    step.attach(mapper, viewer=..., out_dir=..., total=step.frames_to_run(seq))   # made or loaded
    run_frames(Prefetcher(seq, step.frames_done, total, step.load_frame), step, ...,
               checkpoints=Checkpoints(save=lambda bg: save_slam(step, out_dir), ...))
    res = step.results(seq)   # trajectory, odometry, loops, keyframe frames
    out.update(step.summary(res))

The step keeps what the run needs to go on (front end with its pose graph, per-frame records, loop
records); the map is saved beside it (`save_slam`) and opened again by its kind (`load_slam`); the
run's mapper, viewer and tracker are set again by `attach` on resume.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import pickle

import numpy as np

from jaxmap.errors import CheckpointError, JaxmapError
from jaxmap.frame_loop import Frame
from jaxmap.geometry import compose

log = logging.getLogger("jaxmap")

STATE_FILE = "slam_state.pkl"
CHECKPOINT_DIR = "checkpoint"


@dataclasses.dataclass(frozen=True)
class SlamFrame(Frame):
    """A frame of a SLAM loop, its host work done in the prefetch threads: `points` as read (for the
    front end and the tracker), `prepared` the map's preprocessing of it (N3: (points, normals) sensor
    frame, and `image` the scan's range image for the map's free-space evidence, None when it is off; the
    latent map: `ImtMapper.prepare`'s HostScan; None: not made ahead), `odometry_scan` the odometry's
    (`slam.odometry_common.Scan`: downsampled points and normals at two levels)."""

    prepared: tuple | object | None = None
    odometry_scan: object = None


def show_loop(viewer, fe, r) -> None:
    """After a pose-graph optimisation (front-end result r): the viewer (None: none) redraws the
    trajectory and marks the loop just closed."""
    if viewer is None:
        return
    viewer.on_trajectory(fe.trajectory())
    if fe.loops:
        c, k = fe.loops[-1]
        viewer.on_loop(r.keyframe_poses[c], r.keyframe_poses[k])


class SlamStep:
    """The part of a SLAM step every map kind shares. Subclasses set `map_kind`, `label` (the progress
    bar's) and implement `_submit(frame)` (the frame's work; returns the frames finished, (frame, record,
    pose) each), `load_frame(seq, i)` (the prefetch threads' loader); `drain`, `settle`, `frames_done`,
    `frames_to_run`, `keyframe_frames`, `results`, `summary`, `mapped` and `progress` where theirs differ.

    fe: the front end (`jaxmap.slam.frontend.FrontEnd`), or None where poses come from elsewhere."""

    map_kind = ""
    label = "slam"
    progress = None    # fn(record) -> the progress bar's postfix (None: none)
    _run_only = ("mapper", "viewer", "track", "out_dir", "total", "_waiting", "_finished")  # not saved

    def __init__(self, cfg, fe=None):
        self.cfg, self.fe = cfg, fe
        self.odometry: list[np.ndarray] = []     # the odometry alone: its own motions chained from frame 0
        self.loops: list[dict] = []              # per loop correction (or pose snapshot): its record
        self.records: list[dict] = []            # per frame: the step's record (timings of each part)
        self.viewer, self.out_dir, self.total = None, None, 0

    def attach(self, mapper, *, viewer=None, out_dir: str | None = None, total: int = 0, track=None) -> None:
        """Set what the run, not the saved state, provides: the map, the viewer (None: none), the run
        directory (where a failure saves the map; None: not saved), the frames of the run, the tracker."""
        self.mapper, self.viewer, self.out_dir, self.total, self.track = mapper, viewer, out_dir, total, track

    # -- the frame loop's Steps --
    def submit(self, frame: Frame) -> list:
        """`Steps.submit`: the frame's work (`_submit`); a failure of the front end, the tracker or the
        map is raised as a JaxmapError that names the frame, after saving the map mapped so far."""
        try:
            return self._submit(frame)
        except Exception as e:  # say where, and keep what was mapped
            raise self._failed(frame.index, e) from e

    def drain(self) -> list:
        """`Steps.drain`: the frames finished and not yet returned (a step that finishes each frame in
        `submit` has none)."""
        return []

    def settle(self) -> None:
        """Wait for every map frame in flight (none where each frame is finished in `submit`)."""

    def _submit(self, frame: Frame) -> list:
        raise NotImplementedError

    def front_end(self, frame: SlamFrame, refine=None):
        """The front end on this frame (`FrontEnd.add_frame`), its odometry's own motion chained onto the
        odometry-alone trajectory (a front end that does not report it: its odometry's velocity)."""
        r = self.fe.add_frame(frame.points, refine=refine, scan=frame.odometry_scan)
        rel = r.odometry_rel if r.odometry_rel is not None else self.fe.odometry.velocity
        self.odometry.append(frame.pose.copy() if not self.odometry else compose(self.odometry[-1], rel))
        return r

    def _failed(self, frame: int, err: Exception) -> JaxmapError:
        """Save the map as mapped so far (when the run has a directory; a save of its own, not one that
        `--resume` reads: the step's state may be mid-frame) and return the error that names the frame,
        what was saved and how to go on."""
        log.error("jaxmap slam: frame %d failed", frame, exc_info=err)
        msg = f"jaxmap slam failed at frame {frame}: {type(err).__name__}: {err}"
        if self.out_dir is None:
            return JaxmapError(msg)
        path = os.path.join(self.out_dir, CHECKPOINT_DIR)
        try:
            self.settle()
            self.mapper.save(path)
            saved = f"the map as mapped so far ({self.mapped()}) is saved in {path}"
        except Exception as e2:  # noqa: BLE001 - the first error is the one to report
            saved = f"saving a checkpoint failed too ({type(e2).__name__}: {e2})"
        if os.path.isfile(os.path.join(self.out_dir, STATE_FILE)):
            saved += f"; `jaxmap slam --resume {self.out_dir}` goes on from the run's last save"
        return JaxmapError(f"{msg}; {saved}")

    def mapped(self) -> str:
        """What the map holds, in words ("12 frames")."""
        return f"{self.mapper.frames} frames"

    # -- the run's results --
    @property
    def frames_done(self) -> int:
        """Frames of the sequence this step has taken (a resumed run starts at the next)."""
        return len(self.odometry)

    def frames_to_run(self, seq) -> int:
        """Frames of `seq` the run takes (all of them, where poses are not read from elsewhere)."""
        return len(seq)

    def load_frame(self, seq, i: int) -> SlamFrame:
        raise NotImplementedError

    def keyframe_frames(self, seq) -> list[int]:
        """The sequence's frame indices of the keyframes."""
        return [int(seq.indices[i]) for i in self.fe.kf_frame]

    def results(self, seq) -> dict:
        """trajectory [N, 4, 4], odometry [N, 4, 4] (None: no odometry of our own), loops, keyframe frames."""
        return {"trajectory": np.asarray(self.fe.trajectory()), "odometry": np.asarray(self.odometry),
                "loops": self.loops, "keyframe_frames": self.keyframe_frames(seq)}

    def summary(self, res: dict) -> dict:
        """The keys of slam.json this map kind adds to the common ones."""
        return {}

    def compiles_since(self, n: int) -> dict | None:
        """The run's compiles to report in timing.json (None: the map reports its own)."""
        return None

    # -- pickling (`save_slam`) --
    def moved_to(self, out_dir: str) -> None:
        """A loaded state's run directory is `out_dir` (where files it names are kept)."""

    def __getstate__(self) -> dict:
        """What a SLAM checkpoint keeps of the step: the map is saved beside it, and what the run provides
        (`attach`) is set again on resume."""
        return {k: v for k, v in self.__dict__.items() if k not in self._run_only}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.mapper, self.viewer, self.out_dir, self.total, self.track = None, None, None, 0, None


def save_slam(step: SlamStep, out_dir: str) -> None:
    """The run's SLAM checkpoint, any map kind: the map in out_dir/checkpoint (a new checkpoint `<step>`
    there, the one before it kept), then the step's state in out_dir/slam_state.pkl, replaced whole once
    the map is written. The state names the map's checkpoint and kind, so a kill -9 between the two
    leaves the state before and its map (N3's scans are in out_dir/slam_scans, written as they came)."""
    from jaxmap.checkpoint import steps

    ckpt = os.path.join(out_dir, CHECKPOINT_DIR)
    step.settle()   # the frames in flight are in the map and their records in the state
    step.mapper.save(ckpt)
    path = os.path.join(out_dir, STATE_FILE)
    with open(path + ".tmp", "wb") as f:
        pickle.dump({"kind": step.map_kind, "frames": step.frames_done, "map_frames": step.mapper.frames,
                     "map_step": steps(ckpt)[0], "step": step}, f, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(path + ".tmp", path)


class _StateUnpickler(pickle.Unpickler):
    """slam_state.pkl's reader: a run saved while the N3 step was `jaxmap.slam.n3slam` still resumes."""
    MOVED = {"jaxmap.slam.n3slam": "jaxmap.runs.slam_n3", "jaxmap.slam.scan_store": "jaxmap.n3.scan_store"}

    def find_class(self, module, name):
        return super().find_class(self.MOVED.get(module, module), name)


def read_state(path: str) -> dict:
    """The contents of a slam_state.pkl (`save_slam`)."""
    with open(path, "rb") as f:
        return _StateUnpickler(f).load()


def load_slam(out_dir: str):
    """(map, step) of the SLAM checkpoint in out_dir (`save_slam`), the map opened by its kind;
    CheckpointError naming what is missing or does not match."""
    path = os.path.join(out_dir, STATE_FILE)
    if not os.path.isfile(path):
        raise CheckpointError(f"{path}: missing, so the run cannot be continued (it stopped before its first "
                              "save, or was killed): start again with --overwrite")
    saved = read_state(path)
    ckpt = os.path.join(out_dir, CHECKPOINT_DIR)
    if "map_step" in saved:  # the map written with this state (a later one may be there: killed in between)
        ckpt = os.path.join(ckpt, str(saved["map_step"]))
        if not os.path.isdir(ckpt):
            raise CheckpointError(f"{ckpt}: missing, the map saved with {STATE_FILE}; the run cannot be continued: "
                                  "start again with --overwrite")
    kind = saved.get("kind", "n3")   # (states saved before the latent map's runs resumed were N3's)
    if kind == "n3":
        from jaxmap.n3.submap_mapper import load_map

        mapper = load_map(ckpt)
    else:
        from jaxmap.imt.mapper import ImtMapper

        mapper = ImtMapper.load(ckpt)
    step = saved["step"]
    step.moved_to(out_dir)   # (the run directory may have moved since)
    if mapper.frames != saved["map_frames"]:
        raise CheckpointError(f"{out_dir}: the map's checkpoint holds {mapper.frames} frames and {STATE_FILE} "
                              f"{saved['map_frames']}: they are not one save; start again with --overwrite")
    return mapper, step
