"""`ImtMapper`: the transformable latent map of a sequence, frame by frame, with remapping.

    mapper = ImtMapper(cfg)                   # cfg: jaxmap.config.ImtConfig
    mapper.add_frame(points_s, pose)          # [N,3] sensor frame, [4,4] T_world_sensor
    mapper.add_prepared(mapper.prepare(points_s), pose)   # the host's part made ahead (a prefetch thread)
    mapper.remap(new_keyframe_poses)          # [K,4,4] after a pose-graph update
    mapper.mesh(); mapper.sdf(points_w); mapper.save(dir); ImtMapper.load(dir)

A thin facade over the pure functions of `jaxmap.imt.core`: it holds the state (`mapper.state`, the
map and its active-voxel count), the immutable keyframe store (`mapper.store`, replaced, never
changed) and the encode capacities that sufficed so far (`mapper.hints`). Every added frame is
preprocessed (crop, downsample to about voxel/4, PCA normals towards the sensor) and pooled into
cells on the world grid at its pose on the host, then kept as a keyframe and encoded and fused by
one compiled program (`core.integrate`), whose stats are read once. The host's part (`prepare`) can be
done ahead, in the frame loop's prefetch threads (`jaxmap.runs.imt.prepare_frame`), and the frame added
with `add_prepared`.
"""
from __future__ import annotations

import os
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.checkpoint import SAVES, read_meta, read_tree, save_tree
from jaxmap.config import ImtConfig, from_dict, to_dict
from jaxmap.errors import DataError
from jaxmap.records import medians
from jaxmap.geometry import SE3, validate_pose
from jaxmap.grid.hashing import HashTable
from jaxmap.imt import core
from jaxmap.imt import latent_map as lm
from jaxmap.imt.local_maps import encode_frame
from jaxmap.imt.meshing import mesh as mesh_map
from jaxmap.imt.meshing import query
from jaxmap.imt.prior import load_prior
from jaxmap.imt.keyframe_store import RemapOptions
from jaxmap.preprocess import preprocess_scan
from jaxmap.snapshot import copy_arrays


class HostScan(NamedTuple):
    """A scan as `ImtMapper.prepare` leaves it for the frame program."""

    points: np.ndarray           # [M, 3] float32 sensor frame, preprocessed
    normals: np.ndarray          # [M, 3] float32 sensor frame
    cells: tuple | None          # `latent_map.pool_cells` at the frame's pose (world grid), None: not yet
    seconds: float               # the host time it took


def remap_options(cfg: ImtConfig) -> RemapOptions:
    c = cfg.map
    return RemapOptions(min_rotation_deg=c.remap_min_rotation_deg, min_translation_m=c.remap_min_translation_m,
                        min_points=c.min_points, rebuild_fraction=c.remap_rebuild_fraction)


class ImtMapper:
    """Global latent map + keyframe store of one run (see the module docstring)."""

    def __init__(self, cfg: ImtConfig = ImtConfig(), prior=None):
        if cfg.map.interpolation not in ("trilinear", "softmax"):
            raise ValueError(f"map.interpolation must be 'trilinear' or 'softmax', got {cfg.map.interpolation!r}")
        self.cfg = cfg
        self.prior = prior if prior is not None else load_prior(cfg.map.prior or None)
        self.static = core.ImtStatic.from_config(cfg)
        self.state = core.init(self.static, cfg.map.initial_capacity, self.prior.latent_channels)
        self.store = self.static.new_store()   # KeyframeStore (remap: reencode) or LatentStore (transform)
        # what the programs learnt: padded cell count -> encode table size that sufficed (grown on overflow);
        # ("compiled", map capacity, padded cell count) -> the step shapes run; "frame_pad" -> the frames' pad;
        # ("move_step", map capacity) -> move_step ran (transform); "remap_group_cells" -> cells a remap batch holds
        self.hints: dict = {}
        self.local_hints: dict = {}   # the same for `encode`'s local maps (other programs than the map's)
        self.timings: list[dict] = []
        self.remaps: list[dict] = []

    @property
    def map(self) -> lm.LatentMap:
        """The global latent map (world frame)."""
        return self.state.map

    @map.setter
    def map(self, m: lm.LatentMap) -> None:
        self.state = core.state_of(m)

    @property
    def frames(self) -> int:
        """Frames fused into the map (the keyframes, in a SLAM run)."""
        return len(self.store)

    # -- mapping --
    def preprocess(self, points_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Crop, downsample and normals: [N,3] sensor frame -> (points [M,3], normals [M,3]) sensor frame."""
        return preprocess_scan(np.asarray(points_s, np.float32), self.cfg.preprocess)

    def prepare(self, points_s: np.ndarray, pose: np.ndarray | None = None) -> HostScan:
        """What `add_frame` does on the host before its frame program, for a prefetch thread (it reads
        only the config): the preprocessed scan and, when the pose is known, its cells pooled on the
        world grid at that pose."""
        t0 = time.perf_counter()
        pts, nrm = self.preprocess(points_s)
        cells = None if pose is None else self._pool(pts, nrm, np.asarray(pose, np.float64))
        return HostScan(pts, nrm, cells, time.perf_counter() - t0)

    def _pool(self, pts, nrm, pose):
        T_w_s = SE3.from_matrix(pose)
        pw = T_w_s.apply(pts.astype(np.float64))
        nw = T_w_s.rotation().apply(np.asarray(nrm, np.float64))
        return lm.pool_cells(pw, nw, self.cfg.map.voxel_size_m, self.cfg.map.cells_per_voxel)

    def encode(self, points_s, normals_s, pose, with_jacobian: bool = True) -> lm.LatentMap:
        """Local map of preprocessed points at `pose` (world grid), with Jacobians for `transform`.

        With Jacobians the points are pooled finer (`map.transform_cells_per_voxel`, default 2): a
        transformed local map is compared with one pooled on another grid, and one cell per voxel doubles
        that difference (two-branch test 0.78 cm against 0.41 cm at 2 and 0.39 cm unpooled, `jaxmap bench
        imt`). The map's own path (`add_frame`, `remap`) re-encodes the same stored cells, so it keeps the
        coarser, 4x cheaper `map.cells_per_voxel`. The frame program encodes it (`local_maps.encode_frame`)."""
        c = self.cfg.map
        cpv = c.transform_cells_per_voxel if with_jacobian else c.cells_per_voxel
        return encode_frame(self.prior, points_s, normals_s, pose, c.voxel_size_m, c.min_points,
                            with_jacobian=with_jacobian, cells_per_voxel=cpv, hints=self.local_hints)

    def add_frame(self, points_s, pose, frame: int | None = None, pose_source: str | None = None) -> dict:
        """Encode, fuse and keep a frame: points_s [N, 3] sensor frame, pose [4, 4] T_world_sensor. Returns
        its timings (s) and sizes: `preprocess_s` the host's preprocessing, `encode_s` the host's pooling
        and the frame program (encode and fuse, one program), `fuse_s` what follows it on the host.

        pose_source: where the pose came from, named by the error when it is not a rigid transform
        (None: the user's pose file, and the error says how to fix it)."""
        return self.add_prepared(self.prepare(points_s), pose, frame, pose_source)

    def add_prepared(self, prepared: HostScan, pose, frame: int | None = None, pose_source: str | None = None) -> dict:
        """`add_frame` of a scan made ready ahead (`prepare(points_s)`, e.g. in the frame loop's prefetch
        thread; with its cells when made at this pose); `preprocess_s` is then its time there."""
        pose = np.asarray(pose, np.float64)
        validate_pose(pose, f"pose of frame {frame if frame is not None else len(self.store)}", source=pose_source)
        pts, nrm, cells, prep_s = prepared
        t1 = time.perf_counter()
        if cells is None:
            cells = self._pool(pts, nrm, pose)
        frame = len(self.store) if frame is None else frame
        # the store and the state are replaced only once the frame is in: a failure leaves both as they were
        self.state, self.store, stats = core.integrate(self.static, self.state, self.store, self.prior, cells, pose,
                                                       frame, self.hints)
        t2 = time.perf_counter()
        info = {"frame": int(self.store.frames[-1]), "points": int(len(pts)), "cells": int(len(cells[0])),
                "preprocess_s": prep_s, "encode_s": t2 - t1, "fuse_s": time.perf_counter() - t2,
                "local_voxels": int(stats.local_voxels), "map_voxels": int(stats.active)}
        self.timings.append(info)
        return info

    def remap(self, new_poses) -> list[int]:
        """Move the keyframes whose pose changed ([K,4,4] new poses). Returns the ids that moved."""
        t0 = time.perf_counter()
        self.state, self.store, changed = core.remap(self.static, self.state, self.store, self.prior, new_poses,
                                                     remap_options(self.cfg), self.hints)
        jax.block_until_ready(self.state.active)
        self.remaps.append({"keyframes": len(changed), "time_s": time.perf_counter() - t0})
        return changed

    def correct(self, poses) -> dict:
        """Follow a pose correction: poses [K, 4, 4], every keyframe's, in the order added (the map's side
        of the protocol `jaxmap.n3.following.FollowingMap.correct` keeps for N3). Returns its record: the
        keyframes moved (remapped) and "map_s", the seconds it took (`remap`'s own record)."""
        changed = self.remap(poses)
        return {"keyframes_moved": len(changed), "keyframes": len(self.store), "map_s": self.remaps[-1]["time_s"]}

    # -- outputs --
    def mesh(self, resolution: int | None = None):
        c = self.cfg.mesh
        return mesh_map(self.prior, self.map, resolution or c.resolution, c.sigma_threshold_m, c.min_weight,
                        c.min_component_faces)

    def sdf(self, points_w):
        """(sdf [P] m, std [P] m, valid [P]) at world points [P,3]; voxels with at most mesh.min_weight are
        not decoded (as for the mesh)."""
        return query(self.prior, self.map, points_w, min_weight=self.cfg.mesh.min_weight)

    def release(self) -> None:
        """The run is over: drop the latent map and the keyframes (`timings` and `remaps` stay)."""
        self.state = self.store = None

    def timing_summary(self, skip_first: int = 1) -> dict:
        """Per-frame medians after the first `skip_first` (compiling) frames, the count of frames with
        nothing left to encode, and the map's and keyframe store's sizes (timing.json)."""
        return {**medians(self.timings, ("preprocess_s", "encode_s", "fuse_s"), skip_first), **self.sizes()}

    def live_mesh(self) -> dict:
        """`attach_viewer` arguments for a live view: the mesh at half the lattice resolution (a preview;
        the final mesh is the full one), made in a background thread from a copy of the map taken between
        frames (the next frame's step donates the map's buffers)."""
        res = max(2, (self.cfg.mesh.resolution // 2) // 2 * 2)
        c = self.cfg.mesh
        return {"snapshot_fn": lambda: copy_arrays(self.map),
                "mesh_fn": lambda m: mesh_map(self.prior, m, res, c.sigma_threshold_m, c.min_weight,
                                              c.min_component_faces)}

    def keyframe_poses(self) -> np.ndarray:
        return self.store.poses()

    def sizes(self) -> dict:
        return {"map_bytes": self.map.nbytes(), "map_voxels": int(self.state.active),
                "store_bytes": self.store.nbytes(), "store_cells": self.store.cell_count(),
                "keyframes": len(self.store)}

    # -- checkpoints --
    def save(self, path: str, background: bool = False, copy: bool = True) -> None:
        """Write the map, the keyframe store and the config to directory `path` (atomically). `background`:
        written in a thread (`jaxmap.checkpoint.SAVES`: `busy`, `wait`), from a copy of the map taken on the device (the
        next frames map meanwhile: their steps donate the map's buffers), or with copy=False from the map
        itself: then nothing may change the map until the save is written (the end of a run, while it is
        meshed). The keyframe store is immutable, so the thread reads it as it is now."""
        meta = {"config": to_dict(self.cfg), "table_capacity": int(self.map.table.capacity),
                "keyframes": len(self.store), "timings": list(self.timings), "remaps": list(self.remaps)}
        if not background:
            SAVES.wait()
            save_tree(path, {"map": self.map, "store": self.store.to_arrays()}, meta)
            return
        SAVES.wait()  # (before the copy: the copy is then the only extra map in memory)
        m, store = copy_arrays(self.map) if copy else self.map, self.store
        SAVES.start(lambda: save_tree(path, {"map": m, "store": store.to_arrays()}, meta))

    @classmethod
    def load(cls, path: str, prior=None) -> "ImtMapper":
        SAVES.wait()
        path, meta = read_meta(path, "jaxmap imt")
        cfg = from_dict(ImtConfig, meta["config"], source=os.path.join(path, "meta.json"))
        m = cls(cfg, prior)
        tree = read_tree(path)
        mp, t = tree["map"], tree["map"]["table"]
        if "latent_sum" not in mp:
            raise DataError(f"{path}: the latent map of this checkpoint was written by an older jaxmap (means and "
                            "Jacobians); map the sequence again")
        m.map = lm.LatentMap(HashTable(*(jnp.asarray(t[k]) for k in ("keys", "rows", "count"))),
                             *(jnp.asarray(mp[k]) for k in ("coords", "latent_sum", "weight")), None,
                             cfg.map.voxel_size_m)
        arrays = {k: np.asarray(v) for k, v in tree["store"].items()}
        m.store = type(m.store).from_arrays(arrays)
        m.timings, m.remaps = meta.get("timings", []), meta.get("remaps", [])
        return m
