"""The one frame loop of every run: `jaxmap map`, `imt`, `slam` and the benches.

    frames = Prefetcher(seq, start, len(seq), load)          # read (and prepare) ahead in a thread
    loop = run_frames(frames, step, total=len(seq), ...)     # progress, viewer, checkpoints, Ctrl-C, wall
    summary = jaxmap.finish.finish_run(mapper, cfg, out_dir, loop)   # mesh.ply, metrics.json, timing.json

A run is a `Mapper` (N3's `N3Mapper`, the transformable map's `ImtMapper`) fed frame by frame by a
`step`: a function of one `Frame` that maps it and returns its record (timings, sizes) and the pose it
was mapped at, or a `Steps` that runs ahead of the host (N3's: `submit` dispatches a frame program and
returns the frames finished meanwhile). The step is all that differs between runs (a mapper's
`add_frame`, or a SLAM front end that estimates the pose first and closes loops); reading (and
preparing, and uploading) ahead, the progress bar, the live viewer,
checkpoints every N frames and on Ctrl-C / SIGTERM, and the run's wall-clock time live here once; what a
run leaves (mesh, metrics, timings) is written by the one finisher, `jaxmap.finish.finish_run`.
"""
from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import logging
import os
import signal
import sys
import time
from typing import Any, Callable, Iterable, Protocol

import numpy as np
import trimesh
from tqdm import tqdm

from jaxmap.io import open_sequence
from jaxmap.rundir import interrupt_requests
from jaxmap.viewer import attach_viewer, to_world

log = logging.getLogger("jaxmap")


class Mapper(Protocol):
    """What the loop and the finisher need of a map (both N3Mapper and ImtMapper are one)."""

    cfg: Any                 # the run's root config (data, preprocess, mesh, eval sections)
    timings: list[dict]      # one record per added frame (its `*_s` timings, sizes)

    def add_frame(self, points_s: np.ndarray, pose: np.ndarray, **kw) -> dict:
        """Map one scan: points [N, 3] sensor frame, pose [4, 4] T_world_sensor; returns its record."""

    def mesh(self):
        """trimesh.Trimesh of the zero level set at the config's mesh resolution, world frame."""

    def sdf(self, points_w: np.ndarray):
        """Signed distance at world points [M, 3]."""

    def save(self, path: str, background: bool = False) -> None:
        """A checkpoint of the whole map in directory `path`."""

    def timing_summary(self) -> dict:
        """Medians of the per-frame records and the map's sizes, for timing.json and the summary."""

    def live_mesh(self) -> dict:
        """`attach_viewer` arguments (mesh_fn, snapshot_fn) that mesh the map in a background thread."""

    def release(self) -> None:
        """Drop the map's arrays: the run is over (`jaxmap.finish.finish_run`); its records stay."""


@dataclasses.dataclass(frozen=True)
class Frame:
    """One frame as the loop hands it to a step.

    position: 0-based position in the run's frame selection; index: the sequence's own frame number;
    points: [N, 3] float32 sensor frame (preprocessed when `normals` is set); pose: [4, 4] float64
    T_world_sensor (the sequence's, or None where the step estimates it); normals: [N, 3] sensor frame;
    image: [H, W] float32 the whole scan's range image (`jaxmap.range_image`; N3's free-space evidence);
    dynamic: [N] bool, the points inside the frame's moving-object boxes (`jaxmap.metrics.dynamic`; None
    where the sequence has none); batch: the scan as a frame program takes it, padded and on the device,
    where the loader made it (N3's `scan.Uploader`); place: where that batch is mapped (N3's
    `routing.Place`: the map frame it is in, and in a map of submaps the submap); prepare_s: seconds the loader took (off the main
    thread); wait_s: seconds the loop waited for the frame (`run_frames` sets it)."""

    position: int
    index: int
    points: np.ndarray
    pose: np.ndarray | None
    normals: np.ndarray | None = None
    image: np.ndarray | None = None
    dynamic: np.ndarray | None = None
    batch: Any = None
    place: Any = None
    prepare_s: float = 0.0
    wait_s: float = 0.0


def read_frame(seq, position: int) -> Frame:
    """`Prefetcher` loader of the sequence's frame as it is on disk."""
    fr = seq.frame(position)
    return Frame(position, int(fr.index), fr.points, fr.pose)


def prepared_frame(prepare: Callable, seq, position: int, poses=None, label: Callable | None = None) -> Frame:
    """`Prefetcher` loader of a frame made ready for a map: read, at poses[position] when `poses` [N, 4, 4] is
    given (else at the sequence's pose), prepared by `prepare(points_s, pose, position) -> (scan, pose)` (N3:
    `MapStart.prepare`; scan.points, .normals, .image), and with `label` its points labelled
    (`label(points, pose, index) -> [M] bool`: the moving objects' points, `jaxmap.metrics.dynamic`)."""
    fr = seq.frame(position)
    scan, pose = prepare(fr.points, fr.pose if poses is None else poses[position], position)
    return Frame(position, int(fr.index), scan.points, pose, scan.normals, scan.image,
                 dynamic=label(scan.points, pose, int(fr.index)) if label is not None else None)


class Prefetcher:
    """Iterate `load(seq, i)` for i in [start, stop), computed ahead by `workers` threads (default: one
    per two CPU cores, at least one), in order, each then passed through `then` (if given) in one more
    thread, in order (a stage that must see the frames one after the other: N3 pads each scan to the
    bucket the scans before it chose, and uploads it). On a 2-core laptop one thread overlaps the device's
    work (numpy, scipy's k-d tree and file reads release the GIL); on a GPU machine the device maps a
    city frame in ~20 ms, and several frames are prepared at once to keep up. A `Frame`'s `prepare_s`
    is set to the seconds its load and `then` took. Errors are re-raised in the consumer."""

    def __init__(self, seq, start: int, stop: int, load: Callable[[Any, int], Any] = read_frame,
                 workers: int | None = None, then: Callable[[Any], Any] | None = None):
        # Only sequences that read each frame from its own file are read from several threads
        # (a ROS bag reader is one open file).
        parallel = getattr(seq, "thread_safe_frames", False)
        self._workers = workers or (max(1, (os.cpu_count() or 2) // 2) if parallel else 1)
        self._pool = concurrent.futures.ThreadPoolExecutor(self._workers, thread_name_prefix="jaxmap-prefetch")
        self._ordered = (concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="jaxmap-upload")
                         if then is not None else None)
        self._depth = self._workers + 1
        self._next, self._stop = start, stop
        self._futures: list = []
        self._seq, self._load, self._then = seq, load, then
        self._fill()  # reading starts now, while the caller sets up (compiles) the rest

    def _timed_load(self, i: int):
        t0 = time.perf_counter()
        item = self._load(self._seq, i)
        return item, time.perf_counter() - t0

    def _timed_then(self, loaded: concurrent.futures.Future):
        item, secs = loaded.result()
        t0 = time.perf_counter()
        item = self._then(item)
        return item, secs + time.perf_counter() - t0

    def _fill(self):
        while self._next < self._stop and len(self._futures) < self._depth:
            f = self._pool.submit(self._timed_load, self._next)
            if self._ordered is not None:  # one thread, so in submission order
                f = self._ordered.submit(self._timed_then, f)
            self._futures.append(f)
            self._next += 1

    def first(self):
        """The first item, waited for but not consumed (iterating still yields it first); None if none."""
        return self._item(self._futures[0]) if self._futures else None

    def __iter__(self):
        self._fill()
        while self._futures:
            item = self._item(self._futures.pop(0))
            self._fill()
            yield item

    @staticmethod
    def _item(future):
        item, secs = future.result()
        return dataclasses.replace(item, prepare_s=secs) if isinstance(item, Frame) else item

    def close(self):
        for f in self._futures:
            f.cancel()
        self._futures = []
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self._ordered is not None:
            self._ordered.shutdown(wait=True, cancel_futures=True)


@dataclasses.dataclass(frozen=True)
class Checkpoints:
    """How a run saves its map: every `every` frames in the background (0: never), at the end, and on
    Ctrl-C / SIGTERM. `save(background)` writes one; `busy()` says a background save still runs
    (the next frame tries again); `wait()` waits for it; `resume` is the command that continues the
    run ("" where the command has no --resume); `final`: the end-of-run save where it is not
    `save(False)` (N3's starts writing the finished map in the background, while the run meshes it:
    the finisher `wait`s for it)."""

    save: Callable[[bool], None]
    path: str
    every: int = 0
    busy: Callable[[], bool] = lambda: False
    wait: Callable[[], None] = lambda: None
    resume: str = ""
    final: Callable[[], None] | None = None


@dataclasses.dataclass(frozen=True)
class Progress:
    """The progress bar: `desc`, a `postfix(record) -> dict` of short strings, and `first` appended to
    the description while the first frame runs (it compiles the frame program: say so)."""

    desc: str = "mapping"
    enabled: bool = True
    postfix: Callable[[dict], dict] | None = None
    first: str = ""


@dataclasses.dataclass(frozen=True)
class FramesRun:
    """What a `run_frames` loop did (not a loop closure: that is `jaxmap.slam.loops.LoopResult`)."""

    frames_run: int     # frames mapped by this loop (after a resume: the new ones)
    wall_s: float       # wall-clock from `t_start`: compilation, checkpoints and the final save included
    final_save_s: float = 0.0   # of which the final checkpoint (started: `Checkpoints.final` writes on)


Finished = tuple  # (Frame, record: dict, pose [4, 4] or None): a frame a step has finished


class Steps(Protocol):
    """A step that runs ahead of the host: `submit(frame)` starts mapping a frame and returns the frames
    finished since the last call (oldest first, each once); `drain()` finishes every frame submitted and
    returns those not returned yet. A plain step function is one that finishes each frame at once."""

    def submit(self, frame: Frame) -> list[Finished]: ...

    def drain(self) -> list[Finished]: ...


class SubmitSteps:
    """`Steps` of a map that runs its frames ahead of their records (N3's `submit` / `finish`): each frame's
    `batch` (uploaded by the Prefetcher's `then`, N3's `scan.Uploader`) is submitted as soon as it is read,
    and its record comes back a frame later, paired here with its frame. on_finished(frame, record, kept):
    called for each finished frame (kept: the map's [M] bool of the points it trained on, or None), e.g.
    a run's running evaluation."""

    def __init__(self, mapper, on_finished: Callable | None = None):
        self.mapper, self.on_finished = mapper, on_finished
        self._frames: collections.deque[Frame] = collections.deque()  # submitted, record not back yet

    def submit(self, frame: Frame) -> list[Finished]:
        self._frames.append(frame)
        return self._paired(self.mapper.submit(frame.batch, points=len(frame.points), prepare_s=frame.prepare_s,
                                               wait_s=frame.wait_s, place=frame.place))

    def drain(self) -> list[Finished]:
        return self._paired(self.mapper.finish())

    def _paired(self, finished: list) -> list[Finished]:
        out = []
        for record, kept in finished:
            frame = self._frames.popleft()
            if self.on_finished is not None:
                self.on_finished(frame, record, kept)
            out.append((frame, record, frame.pose))
        return out


class _AtOnce:
    """A step function as `Steps`: each frame finished when `submit` returns."""

    def __init__(self, step: Callable[[Frame], tuple[dict, np.ndarray | None]]):
        self.step = step

    def submit(self, frame: Frame) -> list[Finished]:
        return [(frame, *self.step(frame))]

    def drain(self) -> list[Finished]:
        return []


def run_frames(frames: Iterable[Frame], step, *, total: int, start: int = 0, progress: Progress = Progress(),
               viewer=None, checkpoints: Checkpoints | None = None, t_start: float | None = None) -> FramesRun:
    """Run `step` on every frame of `frames` (positions start .. total - 1) and return what it cost.

    step: a function of a frame -> (record, pose), or a `Steps` (frames finished later than submitted):
    `record` (timings, sizes; shown by the bar and the viewer), `pose` [4, 4] the frame was mapped at
    (None: not shown by the viewer, e.g. a frame that is not a keyframe). The loop adds to the records
    `checkpoint_s` (seconds it spent starting a background checkpoint after that frame) and sets each
    frame's `wait_s` (seconds it waited for the frame to be read). viewer: `jaxmap.viewer.ViewerHooks`
    or None. The first SIGINT / SIGTERM stops the loop between two frames (never inside one: a frame's
    new state is swapped in at its end), finishes the frames submitted, saves a checkpoint and re-raises
    (`jaxmap.rundir.Interrupted`); a second Ctrl-C stops at once, without saving. `frames` is closed
    (its `close()`, a `Prefetcher`'s threads) however the loop ends."""
    t_start = time.perf_counter() if t_start is None else t_start
    steps = step if hasattr(step, "submit") else _AtOnce(step)
    books = _Books(_bar(progress, total, start), progress, viewer, checkpoints, total)
    try:
        with interrupt_requests() as stop:
            try:
                it = iter(frames)
                while True:
                    t0 = time.perf_counter()
                    frame = next(it, None)
                    if frame is None:
                        break
                    if isinstance(frame, Frame):
                        frame = dataclasses.replace(frame, wait_s=time.perf_counter() - t0)
                    books.finished(steps.submit(books.submitted(frame)))
                    stop.check()  # Ctrl-C or SIGTERM during the frame: stop here, between frames
                books.finished(steps.drain())
            except KeyboardInterrupt as e:
                _close(frames, books.bar)  # no frame is read while the checkpoint is written
                if not stop.forced:  # the frames submitted go in before the checkpoint
                    books.done += len(steps.drain())
                _interrupted(e, stop.forced, checkpoints, start + books.done)
                raise
    except BaseException:
        if viewer is not None:
            viewer.close()
        raise
    finally:
        _close(frames, books.bar)
    final_save_s = 0.0
    if checkpoints is not None:
        t0 = time.perf_counter()
        checkpoints.final() if checkpoints.final is not None else checkpoints.save(False)
        final_save_s = time.perf_counter() - t0
    return FramesRun(books.done, time.perf_counter() - t_start, final_save_s)


class _Books:
    """What `run_frames` keeps between frames: the bar, the viewer, the checkpoints every N frames."""

    def __init__(self, bar, progress: Progress, viewer, checkpoints: Checkpoints | None, total: int):
        self.bar, self.progress, self.viewer, self.checkpoints, self.total = bar, progress, viewer, checkpoints, total
        self.done, self.since_save, self.last = 0, 0, None  # frames finished, since a save; submitted last

    def submitted(self, frame: Frame) -> Frame:
        if self.bar is not None and self.last is None and self.progress.first:
            self.bar.set_description_str(f"{self.progress.desc} ({self.progress.first})")
        self.last = frame
        return frame

    def finished(self, items: list[Finished]) -> None:
        ck, viewer = self.checkpoints, self.viewer
        for frame, record, pose in items:
            _show(self.bar, self.progress, record, first=self.done == 0)
            self.done += 1
            self.since_save += 1
            if viewer is not None and pose is not None:
                viewer.on_frame(frame.index, to_world(frame.points, pose, viewer.viewer.max_points), pose, record)
            # Written while the next frames map; if the last one is still being written (a GPU maps
            # 10 frames faster than a map is written), the next frame tries again.
            if (ck is not None and ck.every > 0 and self.since_save >= ck.every
                    and self.last.position + 1 < self.total and not ck.busy()):
                t0 = time.perf_counter()
                ck.save(True)
                record["checkpoint_s"] = record.get("checkpoint_s", 0.0) + time.perf_counter() - t0
                self.since_save = 0


def _show(bar, progress: Progress, record: dict, first: bool) -> None:
    if bar is None:
        return
    if first and progress.first:
        bar.set_description_str(progress.desc)
    if progress.postfix is not None:
        bar.set_postfix(**progress.postfix(record))
    bar.update(1)


def _bar(progress: Progress, total: int, start: int):
    if not progress.enabled:
        return None
    return tqdm(total=total, initial=start, unit="frame", desc=progress.desc, file=sys.stderr)


def _close(frames, bar) -> None:
    if hasattr(frames, "close"):
        frames.close()
    if bar is not None:
        bar.close()


def _interrupted(e: KeyboardInterrupt, forced: bool, checkpoints: Checkpoints | None, frames: int) -> None:
    """Save what the stopped run mapped (unless Ctrl-C came twice) and say how to go on."""
    if checkpoints is None:
        return
    what = "terminated (SIGTERM)" if getattr(e, "signum", None) == signal.SIGTERM else "interrupted"
    if forced:
        checkpoints.wait()
        msg, go_on = f"{what} twice: stopped without saving", "continue from the last checkpoint with"
    else:
        checkpoints.save(False)
        msg, go_on = f"{what}: checkpoint of {frames} frames saved in {checkpoints.path}", "continue with"
    print(f"\n{msg}" + (f"; {go_on}: {checkpoints.resume}" if checkpoints.resume else ""), file=sys.stderr)


def open_run_sequence(cfg):
    """The frames a run's config selects (`cfg.data`: path, kind, begin / end / every frame, topic)."""
    d = cfg.data
    return open_sequence(d.path, kind=d.kind, begin_frame=d.begin_frame, end_frame=d.end_frame,
                         every_frame=d.every_frame, topic=d.topic)


def outside_programs(timings: list[dict], wall_s: float, compile_s: float = 0.0) -> dict:
    """Where a run's wall-clock went, for runs whose records have `program_s` (the frame programs on the
    device, `jaxmap.n3.frame.FramePipeline`): their sum, and what was neither they nor compilation
    ("outside the frame programs": reading and waiting for scans, dispatching, reading stats,
    checkpoints, the final save), in seconds, ms a frame and % of the wall. {} for other records."""
    if not timings or not all("program_s" in r for r in timings):
        return {}
    program = float(sum(r["program_s"] for r in timings))
    outside = wall_s - program - compile_s
    return {"program_s": program, "outside_s": outside, "outside_ms_per_frame": 1e3 * outside / len(timings),
            "outside_pct": 100.0 * outside / wall_s if wall_s > 0 else float("nan"),
            **{f"{k}_s_sum": float(sum(r.get(f"{k}_s", 0.0) for r in timings))
               for k in ("wait", "dispatch", "stats", "checkpoint")}}


# ------------------------------------------------------------------------------------------------
# the live viewer of a run (`--view`)
# ------------------------------------------------------------------------------------------------


def open_viewer(view: dict | None, mapper: Mapper):
    """ViewerHooks for `view` = {"port": int, "mesh_every": int} (None: no viewer) that mesh `mapper`
    in a background thread (`mapper.live_mesh()`: a preview at a coarser resolution)."""
    if not view:
        return None
    return attach_viewer(port=int(view.get("port", 8080)), mesh_every=int(view.get("mesh_every", 10)),
                         **mapper.live_mesh())


def close_viewer(hooks, mesh_path: str | None, out_dir: str) -> None:
    """Show the final mesh, then stop the viewer (`jaxmap view RUN` opens the run again)."""
    mesh = None
    if mesh_path and os.path.isfile(mesh_path):
        mesh = trimesh.load(mesh_path, process=False, force="mesh")
    hooks.finish(mesh)
    hooks.close()
    log.info("viewer closed; `jaxmap view %s` shows the finished run", out_dir)
