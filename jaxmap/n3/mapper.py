"""`N3Mapper`: the stateful map over the pure engine in `jaxmap.n3.core`: it holds the state, runs the
frame programs one frame ahead of their statistics (`core.FramePipeline`), and keeps each frame's record.

    m = N3Mapper(cfg)                      # cfg: jaxmap.config.MapConfig
    m.add_frame(points_s, pose)            # points_s [N,3] sensor frame; pose [4,4] T_world_sensor
    m.add_prepared(scan, pose)             # a scan made ready ahead: m.start.prepare(points_s, pose, i)
    sdf, valid = m.sdf(points_w)           # [M,3] world frame -> [M], [M]
    mesh = m.mesh(res=0.1)                 # trimesh.Trimesh, world frame
    m.save("runs/x/checkpoint"); m2 = N3Mapper.load("runs/x/checkpoint")
"""
from __future__ import annotations

import time
from typing import Callable, TypedDict

import jax
import numpy as np

from jaxmap import hostmem
from jaxmap.config import MapConfig
from jaxmap.records import medians
from jaxmap.n3 import core, scan
from jaxmap.n3.scan import MapStart, PreparedScan
from jaxmap.n3.query import extract_mesh_of, query_world
from jaxmap.n3 import window
from jaxmap.n3.evidence import void as void_of
from jaxmap.sizes import pow2
from jaxmap.snapshot import copy_arrays

_forget_jit = jax.jit(window.forget_frames)
# The empty map as one program: built op by op, it compiled some fifty small programs each run (~4 s).
empty_state = jax.jit(core.init_state, static_argnums=(0, 1, 2))


class N3Record(TypedDict, total=False):
    """What an N3 map keeps of each frame (`N3Mapper.timings`, timing.json; `add_frame` returns it with
    `kept`). Seconds: preprocess_s (its preparation), wait_s (the loop waited for it), dispatch_s /
    program_s / stats_s (handing its programs to the device / the programs / waiting for its stats),
    map_s = dispatch_s + program_s, total_s (map_s and the main thread's time before the dispatch).
    Sizes: points (prepared), bucket (padded rows), window_voxels, store_pairs, store_bytes, leaf_voxels,
    feature_rows, feature_bytes, feature_capacity. The frame's training: loss, bce, eikonal, passes (frame
    programs run for it: 1 unless a table grew). Free space: free_dropped, carved, points_filtered,
    points_void, voxels_free, voxels_void, voxels_raised, rays_left, voxels_untested. Memory: rss_mb,
    peak_rss_mb. A map of submaps adds submap, submap_frame, submaps, submaps_resident, submaps_on_disk,
    device_mb; the frame loop adds checkpoint_s."""

    frame: int
    points: int
    bucket: int
    preprocess_s: float
    wait_s: float
    dispatch_s: float
    program_s: float
    stats_s: float
    map_s: float
    total_s: float
    passes: int
    loss: float
    bce: float
    eikonal: float
    window_voxels: int
    store_pairs: int
    store_bytes: int
    leaf_voxels: int
    feature_rows: int
    feature_bytes: int
    free_dropped: int
    carved: int
    points_filtered: int
    points_void: int
    voxels_free: int
    voxels_void: int
    voxels_raised: int
    rays_left: int
    voxels_untested: int
    feature_capacity: int
    rss_mb: float
    peak_rss_mb: float


class N3Mapper:
    """Holds one `core.N3State` (in a `core.FramePipeline`, which runs the frame programs one frame ahead
    of their stats) and the host-side record of a run (one `N3Record` a frame, `timings`)."""

    def __init__(self, cfg: MapConfig | None = None, state: core.N3State | None = None,
                 timings: list | None = None, *, start: MapStart | None = None, first_scan: tuple | None = None,
                 first_batch=None, in_chain: bool = False, on_record: Callable[[N3Record], None] | None = None):
        """The ways in, all through one `scan.MapStart`:
            N3Mapper(cfg)                                     set up by the first frame added (layout, map frame)
            N3Mapper(cfg, first_scan=(points_s [N, 3], pose [4, 4]))   set up from the first frame now
            N3Mapper(start=MapStart.of(cfg, points_s, pose), first_batch=b)   the same, its batch made ahead
            N3Mapper(cfg, state, timings)                     a saved map (`load`)
        With a first frame, the frame program is compiled (from first_batch, the first frame as the frame
        loop uploads it, or from first_scan) before the map's buffers are allocated, so the compiler's heap
        (about a gigabyte on a CPU) and the map are not in memory at the same time.
        in_chain: this grid maps the submaps of a map of submaps one after another (`SubmapMapper`, which
        swaps their states: `detach` / `attach`); otherwise a config with submaps.enabled is refused.
        on_record(record): called with each frame's record as it comes back, before `timings` keeps it."""
        self._start = start or MapStart.of(cfg or MapConfig(), *(first_scan or ()))
        self.cfg, self.static = self._start.cfg, self._start.static
        if self.cfg.submaps.enabled and not in_chain:
            from jaxmap.errors import ConfigError

            raise ConfigError("submaps.enabled=true: a map of submaps is a SubmapMapper (jaxmap map makes one); "
                              "N3Mapper maps one grid: set submaps.enabled=false (jaxmap slam: n3_loop=submaps)")
        self._bucket, self._headroom = 0, {}
        if state is None:
            caps = core.capacities_for(self.static, self.cfg)
            if first_batch is None and first_scan is not None:
                first_batch = self._start.first_batch(*self._start.prepare(*first_scan, 0))
            if first_batch is not None:
                self._precompile(caps, first_batch)
            state = empty_state(self.static, self.cfg, caps)
            hostmem.trim()  # the initialisation's temporaries
        self.timings = list(timings or [])
        if self.timings:  # a resumed map pads its scans as the run did (the padding decides the samples)
            self._bucket = int(self.timings[-1].get("bucket", 0))
        self._pipe = core.FramePipeline(self.static, state, self._headroom, seed=self.cfg.train.seed,
                                        feature_std=self.cfg.grid.feature_std)
        self._unreported: list[tuple[N3Record, np.ndarray | None]] = []  # finished since `submit` / `finish` returned
        self._on_record = on_record
        self.frames = int(state.frame)      # frames submitted
        # A host copy of the origin (fixed once the first frame set it): reading the state's every
        # frame would be a second device->host transfer per frame.
        self._origin = core.origin_world(self.static, state)
        if self._start.anchor is not None and self.frames == 0:
            self._place(self._start.anchor)

    def detach(self) -> core.N3State:
        """Finish the frames in flight and hand the map's state over (the map holds none until `attach`):
        a map of submaps parks the submap it leaves (`SubmapMapper`)."""
        self.settle()
        state, self._pipe.state = self._pipe.state, None
        return state

    def attach(self, state: core.N3State) -> None:
        """Map on from `state` (of this map's static part and capacities: the compiled frame program is
        reused): its frame count and map frame are the state's."""
        self._pipe.state = state
        self.frames = int(state.frame)
        self._origin = core.origin_world(self.static, state)

    @property
    def state(self) -> core.N3State:
        """The map after every frame added (waits for the frames still on the device)."""
        self.settle()
        return self._pipe.state

    @state.setter
    def state(self, value: core.N3State) -> None:
        self.settle()
        self._pipe.state = value

    @property
    def start(self) -> MapStart:
        """How this map started (`scan.MapStart`): its settled config, its static part, its first position;
        its `prepare` makes a scan ready for this map (host or device path), e.g. in a prefetch thread."""
        return self._start

    def uploader(self) -> scan.Uploader:
        """The frame loop's last reading stage for this map: scans padded as the frames before them, in
        its map frame, uploaded (`scan.Uploader`)."""
        return scan.Uploader(self._origin, self._start.device, self._bucket)

    def _place(self, position_w) -> None:
        """Put the map frame at world position_w [3] (the first frame's sensor), snapped to the coarsest voxel."""
        self._pipe.state = core.set_origin(self.static, self._pipe.state, position_w)
        self._origin = core.origin_world(self.static, self._pipe.state)

    def begin(self, points_s, pose) -> None:
        """Set the map up from its first frame (a map made without one): the range-image layout read off the
        raw scan points_s [N, 3] (None: a prepared scan, the layout as configured; a new layout makes the
        empty map again: nothing was compiled or mapped yet), the map frame at pose [4, 4] (None: not yet)."""
        start = MapStart.of(self.cfg, points_s, pose, self.frames)
        if start.static != self.static:
            caps = core.Capacities.of(self.state)
            self.state = None
            self.state = empty_state(start.static, start.cfg, caps)
        self._start, self.cfg, self.static, self._pipe.static = start, start.cfg, start.static, start.static
        if start.anchor is not None:
            self._place(start.anchor)

    def _precompile(self, caps: core.Capacities, batch) -> None:
        """Compile the first frame's program from the shapes alone (`core.compiled_step` keeps it)."""
        abstract = jax.eval_shape(lambda: empty_state(self.static, self.cfg, caps))
        self._bucket = batch.points.shape[0]
        if self.static.preprocess is not None:
            self._headroom["scan_rows"] = scan.bucket_for(int(core.count_kept(self.static, batch)))
        core.compiled_step(self.static, abstract, batch, self._headroom.get("scan_rows", 0))

    def set_iters(self, iters: int) -> None:
        """Training iterations of the frames added from now on (`Hyper.iters`: traced, nothing recompiles),
        e.g. fewer for the frames SLAM re-adds after a loop correction; `cfg.train.iters` is the map's own."""
        st = self.state
        self.state = st.replace(hyper=st.hyper.replace(iters=jax.device_put(np.int32(iters))))  # (no jnp: it compiles a cast)

    def add_frame(self, points_s, pose) -> dict:
        """Integrate one scan: points_s [N, 3] float32 sensor frame; pose [4, 4] T_world_sensor. Returns, once
        the frame is in, its record (`N3Record`) and `kept` ([M] bool: the prepared points that got training
        samples; None with `preprocess.device`)."""
        t0 = time.perf_counter()
        if self.frames == 0 and self._start.anchor is None:  # set up from this frame: layout and map frame at once
            self.begin(points_s, pose)
        prepared, pose = self._start.prepare(points_s, pose, self.frames)
        return self.add_prepared(prepared, pose, since=t0)

    def add_prepared(self, prepared: PreparedScan, pose, *, since: float | None = None, **kw) -> dict:
        """`add_frame` of a scan made ready ahead (`start.prepare`, e.g. in a prefetch thread, as SLAM does
        before it knows the pose) at pose [4, 4] T_world_sensor; since: when its preparation began. Every
        frame submitted before it must have been finished (`finish`). kw: `submit_prepared`'s."""
        self.submit_prepared(prepared, pose, since=since, **kw)
        ((info, kept),) = self.finish()
        return {**info, "kept": kept}

    def submit_prepared(self, prepared: PreparedScan, pose, *, since: float | None = None) -> tuple[dict, list]:
        """`add_prepared` without waiting for the frame: returns (where it went: {"frame": its number in the
        map}, the (record, kept) of the frames finished meanwhile, as `submit`); its own record comes back
        from a later `submit` or `finish`."""
        batch, timed = self._batch_of(prepared, pose, since)
        done = self.submit(batch, **timed)
        return {"frame": self.frames - 1}, done

    def _batch_of(self, prepared: PreparedScan, pose, since: float | None) -> tuple:
        """(the frame program's batch of a prepared scan at pose [4, 4] in the map's frame, `submit`'s
        keyword arguments but the pose: its points and timings)."""
        t1 = time.perf_counter()
        if self.frames == 0 and self._start.anchor is None:  # a map with no place yet: this frame's pose places it
            self.begin(None, pose)
        self._bucket = scan.bucket_for(len(prepared.points), self._bucket)
        batch = self._start.batch(prepared, pose, self._origin, self._bucket)
        return batch, {"points": len(prepared.points), "prepare_s": t1 - (since or t1),
                       "main_s": time.perf_counter() - (since or t1)}

    def submit(self, batch, *, points: int, prepare_s: float = 0.0, wait_s: float = 0.0,
               main_s: float = 0.0, place=None) -> list[tuple[N3Record, np.ndarray | None]]:
        """Dispatch one frame's program and return without waiting for it: batch is its scan as the
        frame program takes it (`scan.Uploader`: padded, in the map frame, on the device), of `points`
        prepared points. Returns (record, kept) of the frames finished meanwhile (the one before it,
        usually), oldest first: the record is the one kept in `timings`, kept ([M] bool, None with
        `preprocess.device`) the prepared points that got training samples. prepare_s / wait_s: seconds
        its preparation took / the loop waited for it; main_s: seconds of the main thread's before the
        dispatch (in its record's total_s). place: where the uploader made the batch (`routing.Place`,
        `Frame.place`): a batch made in another map frame is refused (ValueError)."""
        self.check_place(place)
        if self.static.preprocess is not None and "scan_rows" not in self._headroom:
            # the first frame: size the preprocessed rows by what it keeps
            self._headroom["scan_rows"] = scan.bucket_for(int(core.count_kept(self.static, batch)))
        self._bucket = batch.points.shape[0]
        self._pipe.submit(batch, {"frame": self.frames, "preprocess_s": prepare_s, "wait_s": wait_s,
                                  "main_s": main_s, "bucket": self._bucket, "n": points})
        self.frames += 1
        self._collect()
        return self._take_unreported()

    def check_place(self, place) -> None:
        """ValueError for a batch made in another map frame than this map's (`routing.Place`; None: unchecked)."""
        if place is not None and not np.array_equal(place.origin_w, self._origin):
            raise ValueError(f"a batch made in the map frame at {place.origin_w} cannot be mapped into the one at "
                             f"{self._origin}: make the batches with this map's uploader()")

    def finish(self) -> list[tuple[N3Record, np.ndarray | None]]:
        """Wait for every frame submitted; (record, kept) of those not returned yet, oldest first."""
        self.settle()
        return self._take_unreported()

    def release(self) -> None:
        """The run is over (meshed, its final checkpoint written): drop the map's arrays, so that what comes
        after it (the evaluation) does not run beside them. Its records (`timings`) stay; nothing may read
        the map after this."""
        self.settle()
        self.state = None
        hostmem.trim()

    def _take_unreported(self) -> list[tuple[N3Record, np.ndarray | None]]:
        out, self._unreported = self._unreported, []
        return out

    def settle(self) -> None:
        """Wait for the frames in flight; their records wait for the next `submit` / `finish`."""
        self._pipe.drain()
        self._collect()

    def _collect(self) -> None:
        """The records of the frames whose stats came back."""
        st = self._pipe.state  # (its shapes only)
        device = self.static.preprocess is not None
        for d in self._pipe.done():
            fs, ts, tag = d.stats, d.train, d.tag
            info: N3Record = {"frame": tag["frame"], "points": int(fs.scan_points), "bucket": tag["bucket"],
                    "preprocess_s": tag["preprocess_s"],
                    "wait_s": tag["wait_s"], "dispatch_s": d.dispatch_s, "program_s": d.program_s,
                    "stats_s": d.stats_s, "map_s": d.dispatch_s + d.program_s,
                    "total_s": tag["main_s"] + d.dispatch_s + d.program_s, "passes": d.passes,
                    "loss": float(ts.loss), "bce": float(ts.bce), "eikonal": float(ts.eikonal),
                    "window_voxels": int(fs.window_blocks), "store_pairs": int(fs.store_pairs),
                    "store_bytes": core.store_bytes(st.pool if self.static.uses_pool else st.store),
                    "leaf_voxels": int(fs.voxels), "feature_rows": int(fs.feature_rows),
                    "feature_bytes": int(fs.feature_rows) * self.static.feature_dim * 4,
                    "free_dropped": int(fs.free_dropped), "carved": int(fs.carved),
                    "points_filtered": int(fs.points_filtered), "points_void": int(fs.points_void),
                    "voxels_free": int(fs.voxels_free), "voxels_void": int(fs.voxels_void),
                    "voxels_raised": int(fs.voxels_raised), "rays_left": int(fs.rays_left),
                    "voxels_untested": int(fs.voxels_untested),
                    "feature_capacity": int(st.feature_table.shape[0]),
                    "rss_mb": hostmem.rss_mb(), "peak_rss_mb": hostmem.peak_rss_mb()}
            if self._on_record is not None:
                self._on_record(info)
            self.timings.append(info)
            # (the mask is not in the timings: a per-point mask per frame would bloat timing.json and the checkpoints)
            self._unreported.append((info, None if device else np.asarray(fs.kept)[:tag["n"]]))

    def reset(self) -> None:
        """Forget the map: an empty state of the current capacities (so the compiled frame program is
        reused), frame 0, the origin set again by the next frame. The timings are kept."""
        caps = core.Capacities.of(self.state)
        self.state = None  # the old arrays go before the new ones are allocated
        self.state = empty_state(self.static, self.cfg, caps)
        self.frames = 0
        self._origin = core.origin_world(self.static, self.state)

    def forget_frames(self, frames) -> int:
        """Remove from the pair store the pairs of the given frames (0-based, in the order `add_frame`
        added them since the start or the last `reset`), e.g. before adding them again at corrected
        poses; the features they trained stay until training moves them. Returns the pairs removed
        (0 for the replay / keyframe ablations, whose flat pool is left as it is)."""
        return self._forget(frames, self.frames)

    def _forget(self, frames, count: int) -> int:
        """`forget_frames` of a state that has mapped `count` frames."""
        frames = [int(f) for f in frames if 0 <= int(f) < count]
        if self.static.uses_pool or not frames:
            return 0
        drop = np.zeros(pow2(count), bool)
        drop[frames] = True
        store, removed = _forget_jit(self.state.store, drop)
        self.state = self.state.replace(store=store)
        return int(removed)

    def frames_held(self, min_frames: int = 10) -> float:
        """Median over the window's voxels observed by >= min_frames frames (since they entered the
        window) of the fraction of those frames whose pairs the voxel's block still holds (1.0: every
        viewpoint kept; `window.frames_held_fraction`). NaN for the pool ablations (no blocks)."""
        if self.static.uses_pool:
            return float("nan")
        st = self.state.store
        return float(core.frames_held_jit(st, st.window_ids, st.window_n, min_frames))

    def voxel_coords(self, points_s, pose) -> np.ndarray:
        """[M, 3] int64 leaf voxels (map frame, as `N3State.voxel_coord` counts them) of sensor-frame points
        [M, 3] at pose [4, 4] T_world_sensor (host side; the map frame as `scan.to_batch` makes it)."""
        T = np.asarray(pose, np.float64)
        p = (np.asarray(points_s, np.float64) @ T[:3, :3].T + (T[:3, 3] - self._origin)).astype(np.float32)
        return np.floor(p.astype(np.float64) / np.float32(self.static.leaf)).astype(np.int64)

    def void_voxels(self) -> np.ndarray:
        """[K, 3] int32 leaf voxels (map frame) that are void (free-space evidence; none when it is off)."""
        if self.state.evidence is None:
            return np.zeros((0, 3), np.int32)
        n = int(self.state.voxels.count)
        void = np.asarray(void_of(self.state.evidence, self.static.void_frames)[:n])
        return np.asarray(self.state.voxel_coord[:n])[void]

    @property
    def bucket(self) -> int:
        """The padded scan size (rows) chosen so far (`scan.bucket_for`; 0 before the first frame)."""
        return self._bucket

    @property
    def origin(self) -> np.ndarray:
        """[3] float64 world position of the map frame."""
        return self._origin

    def tracking_map(self, position_w, min_frames: int = 1) -> tuple[core.N3Static, core.N3State, np.ndarray]:
        """(static, state, T_world_local [4, 4]) of the map a scan near world position_w [3] is tracked
        against (`jaxmap localize`, `jaxmap slam`): the whole map, in the world frame (a map of submaps:
        the nearest of at least min_frames frames)."""
        return self.static, self.state, np.eye(4)

    def sdf(self, points_w) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (metres) at world points [N,3] -> (sdf [N] float32, valid [N] bool)."""
        return query_world(self.static, self.state, points_w)

    def sdf_grad(self, points_w) -> tuple[np.ndarray, np.ndarray]:
        """(sdf [N], d sdf / d x [N,3]) at world points [N,3] (for planners)."""
        return query_world(self.static, self.state, points_w, grad=True)

    def mesh(self, res: float | None = None, min_component_faces: int | None = None):
        """Marching-cubes mesh of the zero level set, world frame (trimesh.Trimesh)."""
        mcf = self.cfg.mesh.min_component_faces if min_component_faces is None else min_component_faces
        return extract_mesh_of(self.static, self.state, float(res or self.cfg.mesh.resolution_m), mcf)

    def timing_summary(self, skip_first: int = 1) -> dict:
        """Per-frame medians and p95 over frames after the first `skip_first` (compiling) frames, the
        count of frames that had no point to map, and the store's and table's sizes (timing.json)."""
        out = medians(self.timings, ("preprocess_s", "map_s", "total_s"), skip_first, p95=("total_s",))
        if self.timings:
            out["max_store_pairs"] = int(max(r["store_pairs"] for r in self.timings))
            out["final_feature_rows"] = int(self.timings[-1]["feature_rows"])
        return out

    def live_mesh(self) -> dict:
        """`attach_viewer` arguments for a live view: a coarse mesh (twice the mesh spacing where it stays on
        the lattice) made in a background thread from a copy of the state (the next frame donates its
        buffers)."""
        res = 2 * self.cfg.mesh.resolution_m
        if abs(self.cfg.grid.leaf_vox_size / res - round(self.cfg.grid.leaf_vox_size / res)) > 1e-6:
            res = self.cfg.mesh.resolution_m
        mcf = self.cfg.mesh.min_component_faces
        return {"snapshot_fn": lambda: copy_arrays((self.static, self.state)),
                "mesh_fn": lambda s: extract_mesh_of(*s, res, mcf)}

    def save(self, path: str, background: bool = False, copy: bool = True) -> None:
        """Checkpoint to directory `path` once the frames submitted are in; `background`: written in a
        thread, from a copy of the state taken on the device (the next frames map meanwhile), or with
        copy=False from the state itself: then nothing may change the map until the save is written
        (`n3.checkpoint.wait_for_saves`; the end of a run, while it is meshed)."""
        from jaxmap.n3.checkpoint import save_state, save_state_async

        if background:
            save_state_async(path, self.cfg, self.state, self.timings, copy=copy)
        else:
            save_state(path, self.cfg, self.state, self.timings)

    @classmethod
    def load(cls, path: str) -> "N3Mapper":
        """The one-grid map of checkpoint directory `path` (or one checkpoint `path/<step>`); a map of
        submaps opens with `jaxmap.n3.submap_mapper.load_map` (which opens either)."""
        from jaxmap.errors import CheckpointError
        from jaxmap.n3.checkpoint import load_state_meta

        cfg, state, timings, meta = load_state_meta(path)
        if "submaps" in meta:
            raise CheckpointError(f"{path} holds a map of submaps: open it with jaxmap.n3.submap_mapper.load_map")
        return cls(cfg, state, timings)


def store_flat_after_full(store_pairs: list[int], tail: float = 0.5) -> tuple[bool, float]:
    """Did the store stop growing? Compares the max of the last `tail` fraction of frames with the
    max of the frames before it: growth ratio <= 1.25 counts as flat (the window is full)."""
    n = len(store_pairs)
    if n < 4:
        return True, 1.0
    cut = int(n * (1 - tail))
    ratio = max(store_pairs[cut:]) / max(max(store_pairs[:cut]), 1)
    return ratio <= 1.25, float(ratio)
