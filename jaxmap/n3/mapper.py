"""`N3Mapper`: a thin stateful facade over the pure engine in `jaxmap.n3.core`.

    m = N3Mapper(cfg)                      # cfg: jaxmap.config.MapConfig
    m.add_frame(points_s, pose)            # points_s [N,3] sensor frame; pose [4,4] T_world_sensor
    sdf, valid = m.sdf(points_w)           # [M,3] world frame -> [M], [M]
    mesh = m.mesh(res=0.1)                 # trimesh.Trimesh, world frame
    m.save("runs/x/checkpoint"); m2 = N3Mapper.load("runs/x/checkpoint")
"""
from __future__ import annotations

import time

import jax
import numpy as np

from jaxmap import hostmem
from jaxmap.config import MapConfig
from jaxmap.frame_loop import medians
from jaxmap.n3 import core, scan
from jaxmap.n3.query import extract_mesh_of, query_world
from jaxmap.n3 import window
from jaxmap.n3.evidence import void as void_of
from jaxmap.sizes import pow2
from jaxmap.viewer import copy_arrays

_forget_jit = jax.jit(window.forget_frames)


class N3Mapper:
    """Holds one `core.N3State` and the host-side record of a run (per-frame timings)."""

    def __init__(self, cfg: MapConfig | None = None, state: core.N3State | None = None,
                 timings: list | None = None, first_scan: tuple | None = None):
        """first_scan: (points_s [N,3], pose [4,4]) of the frame that will be added first, if known:
        the frame program is then compiled before the map's buffers are allocated, so the compiler's
        heap (about a gigabyte on a CPU) and the map are not in memory at the same time."""
        self.cfg = cfg or MapConfig()
        if state is None and first_scan is not None:
            self.cfg = scan.resolve_layout(self.cfg, first_scan[0])
        self.static = core.N3Static.from_config(self.cfg)
        self._bucket, self._headroom = 0, {}
        if state is None:
            caps = core.capacities_for(self.static, self.cfg)
            if first_scan is not None:
                self._precompile(caps, *first_scan)
            state = core.init_state(self.static, self.cfg, caps)
            hostmem.trim()  # the initialisation's temporaries
        self.state, self.timings = state, list(timings or [])
        self.frames = int(self.state.frame)
        # A host copy of the origin (fixed once the first frame set it): reading the state's every
        # frame would be a second device->host transfer per frame.
        self._origin = core.origin_world(self.static, self.state)

    def _precompile(self, caps: core.Capacities, points_s, pose) -> None:
        """Compile the first frame's program from the shapes alone (`core.compiled_step` keeps it)."""
        abstract = jax.eval_shape(lambda: core.init_state(self.static, self.cfg, caps))
        if self.static.preprocess is not None:
            pts, pose = scan.check_frame(points_s, pose, 0)
            self._bucket = scan.bucket_for(len(pts))
            batch = scan.to_raw(pts, pose, pose[:3, 3], self._bucket)
            self._headroom["scan_rows"] = scan.bucket_for(int(core.count_kept(self.static, batch)))
        else:
            pts, nrm, pose, img = scan.preprocess(points_s, pose, self.cfg.preprocess, 0, image=self.static.evidence)
            self._bucket = scan.bucket_for(len(pts))
            batch = scan.to_batch(pts, nrm, pose, pose[:3, 3], self._bucket, img)
        core.compiled_step(self.static, abstract, batch, self._headroom.get("scan_rows", 0))

    def fix_layout(self, points_s) -> None:
        """Read the range-image layout off the first scan when the config leaves it open (an empty map is
        made again with it: nothing was compiled or mapped yet)."""
        if not scan.needs_layout(self.cfg):
            return
        self.cfg = scan.resolve_layout(self.cfg, points_s, self.frames)
        self.static = core.N3Static.from_config(self.cfg)
        caps = core.Capacities.of(self.state)
        self.state = None
        self.state = core.init_state(self.static, self.cfg, caps)

    def add_frame(self, points_s, pose, prepared: tuple | None = None) -> dict:
        """Integrate one scan: points_s [N,3] float32 sensor frame; pose [4,4] T_world_sensor.
        `prepared` = (points, normals, pose[, image]) already preprocessed (`scan.preprocess`, e.g. in the
        frame loop's prefetch thread; the image, the whole scan's range image, feeds the free-space evidence).
        Returns the frame's timings (s), loss, map/store sizes and `kept` ([M] bool: the prepared points
        that got training samples; None with `preprocess.device`)."""
        t0 = time.perf_counter()
        device = self.static.preprocess is not None
        img = None
        if prepared is None and self.frames == 0:
            self.fix_layout(points_s)
        if prepared is not None:
            pts, nrm, pose = prepared[:3]
            img = prepared[3] if len(prepared) > 3 else None
        elif device:
            (pts, pose), nrm = scan.check_frame(points_s, pose, self.frames), None
        else:
            pts, nrm, pose, img = scan.preprocess(points_s, pose, self.cfg.preprocess, self.frames,
                                                  image=self.static.evidence)
        if self.static.evidence and not device and img is None:
            img = scan.empty_image(self.static.image)  # no image: this frame sees nothing free
        t1 = time.perf_counter()
        if self.frames == 0:
            self.state = core.set_origin(self.static, self.state, pose[:3, 3])
            self._origin = core.origin_world(self.static, self.state)
        self._bucket = scan.bucket_for(len(pts), self._bucket)
        if device:
            batch = scan.to_raw(pts, pose, self._origin, self._bucket)
            if "scan_rows" not in self._headroom:  # the first frame: size the rows by what it keeps
                self._headroom["scan_rows"] = scan.bucket_for(int(core.count_kept(self.static, batch)))
        else:
            batch = scan.to_batch(pts, nrm, pose, self._origin, self._bucket, img)
        self.state, fs, ts, passes = core.run_frame(self.static, self.state, batch, self._headroom,
                                                     seed=self.cfg.train.seed, feature_std=self.cfg.grid.feature_std)
        t2 = time.perf_counter()
        info = {"frame": self.frames, "points": int(fs.scan_points), "preprocess_s": t1 - t0, "map_s": t2 - t1,
                "total_s": t2 - t0, "passes": passes, "loss": float(ts.loss), "bce": float(ts.bce),
                "eikonal": float(ts.eikonal), "window_voxels": int(fs.window_blocks),
                "store_pairs": int(fs.store_pairs),
                "store_bytes": core.store_bytes(self.state.pool if self.static.uses_pool else self.state.store),
                "leaf_voxels": int(fs.voxels), "feature_rows": int(fs.feature_rows),
                "feature_bytes": int(fs.feature_rows) * self.static.feature_dim * 4,
                "free_dropped": int(fs.free_dropped), "carved": int(fs.carved),
                "points_filtered": int(fs.points_filtered), "points_void": int(fs.points_void),
                "voxels_free": int(fs.voxels_free), "voxels_void": int(fs.voxels_void),
                "voxels_raised": int(fs.voxels_raised),
                "feature_capacity": int(self.state.feature_table.shape[0]),
                "rss_mb": hostmem.rss_mb(), "peak_rss_mb": hostmem.peak_rss_mb()}
        self.frames += 1
        self.timings.append(info)
        # (not in the timings: a per-point mask per frame would bloat timing.json and the checkpoints)
        return {**info, "kept": None if device else np.asarray(fs.kept)[:len(pts)]}

    def reset(self) -> None:
        """Forget the map: an empty state of the current capacities (so the compiled frame program is
        reused), frame 0, the origin set again by the next frame. The timings are kept."""
        caps = core.Capacities.of(self.state)
        self.state = None  # the old arrays go before the new ones are allocated
        self.state = core.init_state(self.static, self.cfg, caps)
        self.frames = 0
        self._origin = core.origin_world(self.static, self.state)

    def forget_frames(self, frames) -> int:
        """Remove from the pair store the pairs of the given frames (0-based, in the order `add_frame`
        added them since the start or the last `reset`), e.g. before adding them again at corrected
        poses; the features they trained stay until training moves them. Returns the pairs removed
        (0 for the replay / keyframe ablations, whose flat pool is left as it is)."""
        frames = [int(f) for f in frames if 0 <= int(f) < self.frames]
        if self.static.uses_pool or not frames:
            return 0
        drop = np.zeros(pow2(self.frames), bool)
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
    def origin(self) -> np.ndarray:
        """[3] float64 world position of the map frame."""
        return self._origin

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

    def save(self, path: str, background: bool = False) -> None:
        """Checkpoint to directory `path`; `background`: write in a thread (see n3.checkpoint)."""
        from jaxmap.n3.checkpoint import save_state, save_state_async

        (save_state_async if background else save_state)(path, self.cfg, self.state, self.timings)

    @classmethod
    def load(cls, path: str) -> "N3Mapper":
        from jaxmap.n3.checkpoint import load_state

        cfg, state, timings = load_state(path)
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
