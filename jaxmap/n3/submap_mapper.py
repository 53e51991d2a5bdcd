"""`SubmapMapper`: the N3 map over a chain of submaps (`submaps.enabled`; `jaxmap.n3.submaps`).

    m = SubmapMapper(cfg, directory="runs/x/submaps")   # or load_map("runs/x/checkpoint") of such a run
    m.add_frame(points_s, pose)            # maps into the submap the pose falls in (a new one, or an old one again)
    m.add_prepared(scan, pose, stay=True)  # a scan made ready ahead, into the active submap whatever its pose
    sdf, valid = m.sdf(points_w)           # blended over the submaps that hold the points
    mesh = m.mesh()                        # streamed through the mesher one submap at a time

It is a map over a `Submaps` store (the index, the submaps held in memory, their files) and one
`N3Mapper`, `grid`, that maps the submap being mapped: before a frame whose sensor has left that
submap (`Submaps.switch_for`, or the route the frame's batch was made on: `routing.Route`), the grid
finishes the frames in flight and hands its state over (`N3Mapper.detach`), the submap is parked
(written to disk in the background, kept in memory while `submaps.resident` allows) and the grid maps
on from the next one (`N3Mapper.attach`: same capacities, the compiled frame program is reused). The
grid counts the frames of its submap; this map counts the whole map's and adds to each frame's record
where it went ("submap", "submap_frame").
"""
from __future__ import annotations

import collections
import os
import tempfile
import time

import jax
import numpy as np

from jaxmap import hostmem
from jaxmap.n3 import core, scan
from jaxmap.n3.mapper import N3Mapper, empty_state
from jaxmap.n3.routing import NEW
from jaxmap.n3.submaps import Submaps


class SubmapMapper:
    """An N3 map over a chain of submaps (the `Mapper` of `jaxmap.frame_loop`, as `N3Mapper` is). cfg, state,
    timings, start, first_scan, first_batch: as `N3Mapper`'s (state: the active submap's); directory: where
    the submaps are written (a run's `submaps/`; default a new temporary folder); index: a checkpoint's
    submap index (`load_map`)."""

    def __init__(self, cfg=None, state=None, timings=None, *, start=None, first_scan=None, first_batch=None,
                 directory: str | None = None, index: dict | None = None):
        # (the whole map's frame, its submap) of the frames submitted whose records are not back yet
        self._in_flight: collections.deque[tuple[int, int]] = collections.deque()
        self.grid = N3Mapper(cfg, state, timings, start=start, first_scan=first_scan, first_batch=first_batch,
                             in_chain=True, on_record=self._annotate)
        self._subs = Submaps(self.static, self.cfg, directory or tempfile.mkdtemp(prefix="jaxmap-submaps-"),
                             live=lambda: self.grid.state)
        self.frames = self.grid.frames  # frames submitted to the whole map (the grid counts its submap's)
        if index is not None:
            self._subs.restore(index)
            self.frames = int(index.get("frames", sum(len(i.frames) for i in self._subs.infos)))
        elif self.frames == 0 and self.start.anchor is not None:
            self._subs.active = self._subs.start(self.start.anchor)

    # ---- what the grid holds -----------------------------------------------------------------------
    @property
    def submaps(self) -> Submaps:
        return self._subs

    @property
    def cfg(self):
        return self.grid.cfg

    @property
    def static(self) -> core.N3Static:
        return self.grid.static

    @property
    def start(self) -> scan.MapStart:
        return self.grid.start

    @property
    def state(self) -> core.N3State:
        """The state of the submap being mapped (after every frame added)."""
        return self.grid.state

    @property
    def timings(self) -> list:
        """Every frame's record (`N3Record` with "submap", "submap_frame", "submaps", ...), in order."""
        return self.grid.timings

    @property
    def bucket(self) -> int:
        return self.grid.bucket

    @property
    def origin(self) -> np.ndarray:
        """[3] float64 world position of the map frame of the submap being mapped."""
        return self.grid.origin

    def set_iters(self, iters: int) -> None:
        self.grid.set_iters(iters)

    def frames_held(self, min_frames: int = 10) -> float:
        """`N3Mapper.frames_held` of the submap being mapped."""
        return self.grid.frames_held(min_frames)

    def timing_summary(self, skip_first: int = 1) -> dict:
        return self.grid.timing_summary(skip_first)

    def live_mesh(self) -> dict:
        """`attach_viewer` arguments: the live view meshes the submap being mapped."""
        return self.grid.live_mesh()

    def uploader(self) -> scan.Uploader:
        """The frame loop's last reading stage for this map (`scan.Uploader`): it routes the frames of a drive
        at known poses to their submaps (`Submaps.route`, handed over: from now on the frames this map is
        given come with their `Place`) and makes each batch in its submap's frame."""
        return scan.Uploader(self.origin, self.start.device, self.bucket, self._subs.route())

    # ---- mapping -----------------------------------------------------------------------------------
    def add_frame(self, points_s, pose) -> dict:
        """`N3Mapper.add_frame` into the submap the pose [4, 4] T_world_sensor falls in."""
        t0 = time.perf_counter()
        if not self._subs.infos:  # set up from this frame: the layout, and the first submap at its pose
            self._begin(points_s, pose)
        prepared, pose = self.start.prepare(points_s, pose, self.frames)
        return self.add_prepared(prepared, pose, since=t0)

    def add_prepared(self, prepared, pose, *, since: float | None = None, stay: bool = False) -> dict:
        """`N3Mapper.add_prepared` (`submit_prepared`, then the frame finished)."""
        self.submit_prepared(prepared, pose, since=since, stay=stay)
        ((info, kept),) = self.finish()
        return {**info, "kept": kept}

    def submit_prepared(self, prepared, pose, *, since: float | None = None, stay: bool = False) -> tuple[dict, list]:
        """`N3Mapper.submit_prepared` with pose [4, 4] T_world_sensor in the world: mapped into the submap
        the pose falls in (stay: the active one, e.g. a frame of it added again), at the pose in that
        submap's frame (a moved submap's, not the world's); where it went also names the submap and the
        frame's number in it ("submap", "submap_frame")."""
        pose = np.asarray(pose, np.float64)
        if not self._subs.infos:  # a map made with no first pose: this one places it
            self._begin(None, pose)
        elif self.frames and not stay:
            self._enter(pose)
        k = self._subs.active
        self._in_flight.append((self.frames, k))
        _, done = self.grid.submit_prepared(prepared, np.linalg.inv(self._subs.infos[k].pose) @ pose, since=since)
        self._subs.record(pose[:3, 3], self.frames, again=stay)
        self.frames += 1
        return {"frame": self.frames - 1, "submap": k, "submap_frame": self.grid.frames - 1}, done

    def submit(self, batch, *, points: int, prepare_s: float = 0.0, wait_s: float = 0.0, main_s: float = 0.0,
               place=None) -> list:
        """`N3Mapper.submit` of a batch made by this map's `uploader()`: its place (`routing.Place`) names the
        submap the route sent it to (the active one, the next new one, or an earlier one), which this map
        takes up first; the batch is in that submap's map frame already (ValueError otherwise)."""
        if place is None or place.submap is None:
            raise ValueError("a map of submaps maps batches routed to their submaps: make them with its uploader() "
                             "(or map prepared scans with add_prepared)")
        self._follow(place)
        self.grid.check_place(place)
        if not np.array_equal(self._subs.infos[self._subs.active].pose, np.eye(4)):
            raise ValueError("a batch uploaded in the world frame cannot go into a moved submap: map it with "
                             "add_prepared (which places the pose in the submap's frame)")
        self._in_flight.append((self.frames, self._subs.active))
        done = self.grid.submit(batch, points=points, prepare_s=prepare_s, wait_s=wait_s, main_s=main_s, place=place)
        self._subs.record(np.asarray(place.position_w, np.float64), self.frames)
        self.frames += 1
        return done

    def finish(self) -> list:
        """Wait for every frame submitted; (record, kept) of those not returned yet, oldest first."""
        return self.grid.finish()

    def forget_frames(self, frames) -> int:
        """`N3Mapper.forget_frames` in the active submap: frames are counted in it (records'
        `submap_frame`); the other submaps keep no pair store to remove pairs from."""
        return self.grid.forget_frames(frames)

    def release(self) -> None:
        """`N3Mapper.release`, and every submap held in memory."""
        self.grid.release()
        self._subs.release()

    def _annotate(self, record: dict) -> None:
        """Where a frame whose record came back went (the grid numbered it in its submap)."""
        frame, k = self._in_flight.popleft()
        record.update({"frame": frame, "submap": k, "submap_frame": record["frame"], "submaps": len(self._subs.infos),
                       "submaps_resident": self._subs.resident(), "submaps_on_disk": self._subs.on_disk(),
                       "device_mb": _device_mb()})

    def _begin(self, points_s, pose) -> None:
        """`N3Mapper.begin`, and the first submap anchored where the map frame is placed."""
        self.grid.begin(points_s, pose)
        self._subs.static, self._subs.cfg = self.static, self.cfg  # the submaps are written with the layout
        if not self._subs.infos and self.start.anchor is not None:
            self._subs.active = self._subs.start(self.start.anchor)

    def _follow(self, place) -> None:
        """Take up the submap a routed frame goes to (`Route` numbers a new one as the next id)."""
        k, n = int(place.submap), len(self._subs.infos)
        if k == self._subs.active:
            return
        if n == 0 and k == 0:  # a map made with no first pose: the first frame places it
            at = np.eye(4)
            at[:3, 3] = place.position_w
            self._begin(None, at)
            return
        if not 0 <= k <= n:
            raise ValueError(f"a frame routed to submap {k} of a map of {n}: its route did not start from this map")
        self._switch(NEW if k == n else k, np.asarray(place.position_w, np.float64))

    def _enter(self, pose: np.ndarray) -> None:
        """Switch to the submap of the frame at `pose` when it is not the active one (`Submaps.switch_for`)."""
        target = self._subs.switch_for(pose[:3, 3])
        if target is not None:
            self._switch(target, pose[:3, 3])

    def _switch(self, target: int, position_w: np.ndarray) -> None:
        """Park the active submap and map on in `target` (an id, or NEW: a new one anchored at the sensor's
        world position_w [3])."""
        old_id, old = self._subs.active, self.grid.detach()
        caps = core.Capacities.of(old)
        self._subs.park(old_id, old)
        del old  # (its pair store goes now, the rest once written: before the next submap is allocated)
        if target == NEW:
            # An N3 map of its own: a fresh decoder that trains for its first train.freeze_after_frame frames.
            # (The previous submap's decoder, frozen, does not learn new features from zero: with all of a
            # grid's features near zero its ReLUs sit where the trained biases put them, mostly dead, and
            # the features get no gradient; measured: the loss of a new submap stayed at 0.12-0.14.)
            new = empty_state(self.static, self.cfg, caps)
            new = new.replace(key=jax.random.fold_in(new.key, len(self._subs.infos)))
            new = core.set_origin(self.static, new, position_w)
            target = self._subs.start(position_w)
        else:
            new = self._subs.take(target, caps.store_blocks)
        self._subs.active = target
        self.grid.attach(new)
        hostmem.trim()

    # ---- reading the whole map ---------------------------------------------------------------------
    def sdf(self, points_w):
        """Blended signed distance at world points [N, 3] -> (sdf [N] float32, valid [N] bool)."""
        self.grid.settle()
        return self._subs.query_world(points_w)

    def sdf_grad(self, points_w):
        """(sdf [N], d sdf / d x [N, 3]) at world points [N, 3], blended."""
        self.grid.settle()
        s, g, _ = self._subs.query_world(points_w, grad=True)
        return s, g

    def mesh(self, res: float | None = None, min_component_faces: int | None = None):
        mcf = self.cfg.mesh.min_component_faces if min_component_faces is None else min_component_faces
        self.grid.settle()
        return self._subs.mesh(float(res or self.cfg.mesh.resolution_m), mcf)

    def tracking_map(self, position_w, min_frames: int = 1):
        """(static, state, T_world_local) of the submap whose sensor path passes nearest to world
        position_w [3]: a scan is tracked against one submap (it holds the sensor's range around its path).
        min_frames: only submaps of at least this many frames (a young one holds little: the one before
        it is tracked against), unless none has as many."""
        p = np.asarray(position_w, np.float64).reshape(1, 3)
        infos = self._subs.infos
        d = np.array([self._subs.path_distance(k, p)[0] if infos[k].path else np.inf for k in range(len(infos))])
        grown = np.array([len(i.frames) >= min_frames for i in infos])
        if grown.any():
            d = np.where(grown, d, np.inf)
        k = int(np.argmin(d))
        return self.static, self._subs.state(k), infos[k].pose

    def move_submaps(self, poses: dict) -> None:
        """Place each submap k of `poses` {k: T_world_local [4, 4]} there, as a rigid body (a loop
        correction of `jaxmap slam`); the frames mapped next into the active one go in at their pose
        in its new frame."""
        self.grid.settle()
        for k, T in poses.items():
            self._subs.move(int(k), T)

    def voxel_coords(self, points_s, pose) -> np.ndarray:
        """[M, 3] int64 world leaf voxels (origin 0: one lattice for every submap) of sensor-frame points."""
        o = np.round(self.origin / self.static.leaf).astype(np.int64)
        return self.grid.voxel_coords(points_s, pose) + o

    def void_voxels(self) -> np.ndarray:
        """[K, 3] int32 world leaf voxels (origin 0) that are void in any submap."""
        from jaxmap.n3.evidence import void as void_of

        out = []
        for k in range(len(self._subs.infos)):
            st = self._subs.state(k)
            if st.evidence is None:
                continue
            n = int(st.voxels.count)
            void = np.asarray(void_of(st.evidence, self.static.void_frames)[:n])
            out.append(np.asarray(st.voxel_coord[:n])[void] + np.asarray(st.origin_vox))
        return np.concatenate(out).astype(np.int32) if out else np.zeros((0, 3), np.int32)

    # ---- checkpoints -------------------------------------------------------------------------------
    def save(self, path: str, background: bool = False, copy: bool = True) -> None:
        """The submap being mapped as checkpoint `<frames in all submaps>` in `path`, with the index (the
        others are on disk in the submaps' directory: `park` wrote them, and the saves run in order)."""
        from jaxmap.n3.checkpoint import save_state, save_state_async

        extra = {"submaps": {**self._subs.index(), "frames": self.frames, "dir": os.path.relpath(self._subs.dir, os.path.dirname(
            os.path.abspath(path)))}}
        # numbered by the frames of every submap (the active one's own count restarts at each switch, and a
        # save numbered below the one before it would delete it: the SLAM state names that one until it is
        # replaced, `jaxmap.runs.slam_step.save_slam`)
        if background:
            save_state_async(path, self.cfg, self.state, self.timings, copy=copy, extra=extra, step=self.frames)
        else:
            save_state(path, self.cfg, self.state, self.timings, extra=extra, step=self.frames)


def new_map(start, directory: str | None = None, **kw) -> N3Mapper | SubmapMapper:
    """The empty map of a `scan.MapStart`: one grid (N3Mapper), or with submaps.enabled a SubmapMapper writing
    its submaps to `directory` (a run's `submaps/`; None: a new temporary folder). kw: first_batch."""
    if start.cfg.submaps.enabled:
        return SubmapMapper(start=start, directory=directory, **kw)
    return N3Mapper(start=start, **kw)


def load_map(path: str) -> N3Mapper | SubmapMapper:
    """The map of checkpoint directory `path` (or one checkpoint `path/<step>`): an N3Mapper, or a
    SubmapMapper where the checkpoint holds a map of submaps (its submaps read from the run's submaps/)."""
    from jaxmap.n3.checkpoint import load_state_meta

    cfg, state, timings, meta = load_state_meta(path)
    if "submaps" in meta:
        return SubmapMapper(cfg, state, timings, directory=submaps_dir(path, meta["submaps"]), index=meta["submaps"])
    return N3Mapper(cfg, state, timings)


def submaps_dir(checkpoint_path: str, index: dict) -> str:
    """The submaps' directory of a checkpoint at `checkpoint_path` (its index names it relative to the
    checkpoint directory's parent: a run's `submaps/`)."""
    ckpt = os.path.abspath(checkpoint_path.rstrip("/"))
    if os.path.basename(ckpt).isdigit():  # one checkpoint `<dir>/<step>` of the checkpoint directory
        ckpt = os.path.dirname(ckpt)
    return os.path.normpath(os.path.join(os.path.dirname(ckpt), index.get("dir", "submaps")))


def _device_mb() -> float | None:
    """Device memory in use (MB) where the backend reports it (GPUs), else None."""
    import jax

    try:
        stats = jax.devices()[0].memory_stats()
    except Exception:  # noqa: BLE001 - a backend without memory stats
        return None
    return None if not stats else stats.get("bytes_in_use", 0) / 2**20
