"""`ImtMapper`: the transformable latent map of a sequence, frame by frame, with remapping.

    mapper = ImtMapper(cfg)                   # cfg: jaxmap.config.ImtConfig
    mapper.add_frame(points_s, pose)          # [N,3] sensor frame, [4,4] T_world_sensor
    mapper.remap(new_keyframe_poses)          # [K,4,4] after a pose-graph update
    mapper.mesh(); mapper.sdf(points_w); mapper.save(dir); ImtMapper.load(dir)

Every added frame is preprocessed (crop, downsample to about voxel/4, PCA normals towards the
sensor), pooled into cells on the world grid at its pose (`pool_cells`), encoded (`encode_keyframes`,
the same function `remap` re-encodes with), fused into the global map (sums, no Jacobians) and its
cells kept as a keyframe (`KeyframeStore`) so that a later pose change can move it.
"""
from __future__ import annotations

import os
import time

import jax
import numpy as np

from jaxmap.config import ImtConfig, from_dict, to_dict
from jaxmap.errors import DataError
from jaxmap.frame_loop import medians
from jaxmap.geometry import transform_points, validate_pose
from jaxmap.imt import latent_map as lm
from jaxmap.imt.meshing import mesh as mesh_map
from jaxmap.imt.meshing import query
from jaxmap.imt.remap import KeyframeStore, RemapOptions, contributions, remap


def remap_options(cfg: ImtConfig) -> RemapOptions:
    c = cfg.map
    return RemapOptions(min_rotation_deg=c.remap_min_rotation_deg, min_translation_m=c.remap_min_translation_m,
                        min_points=c.min_points, rebuild_fraction=c.remap_rebuild_fraction)


class ImtMapper:
    """Global latent map + keyframe store of one run (see the module docstring)."""

    def __init__(self, cfg: ImtConfig = ImtConfig(), prior=None):
        from jaxmap.imt.prior import load_prior

        if cfg.map.interpolation not in ("trilinear", "softmax"):
            raise ValueError(f"map.interpolation must be 'trilinear' or 'softmax', got {cfg.map.interpolation!r}")
        self.cfg = cfg
        self.prior = prior if prior is not None else load_prior(cfg.map.prior or None)
        cap = 1 << max(10, int(np.ceil(np.log2(max(cfg.map.initial_capacity, 2)))))
        self.map = lm.empty(cfg.map.voxel_size_m, cap, self.prior.latent_channels)
        self.store = KeyframeStore()
        self.timings: list[dict] = []
        self.remaps: list[dict] = []

    # -- mapping --
    def preprocess(self, points_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Crop, downsample and normals: [N,3] sensor frame -> (points [M,3], normals [M,3]) sensor frame."""
        from jaxmap.preprocess import preprocess_scan

        return preprocess_scan(np.asarray(points_s, np.float32), self.cfg.preprocess)

    def encode(self, points_s, normals_s, pose, with_jacobian: bool = True) -> lm.LatentMap:
        """Local map of preprocessed points at `pose` (world grid), with Jacobians for `transform`.

        With Jacobians the points are pooled finer (`map.transform_cells_per_voxel`, default 2): a
        transformed local map is compared with one pooled on another grid, and one cell per voxel doubles
        that difference (two-branch test 0.78 cm against 0.41 cm at 2 and 0.39 cm unpooled, `jaxmap bench
        imt`). The map's own path (`add_frame`, `remap`) re-encodes the same stored cells, so it keeps the
        coarser, 4x cheaper `map.cells_per_voxel`."""
        c = self.cfg.map
        cpv = c.transform_cells_per_voxel if with_jacobian else c.cells_per_voxel
        return lm.encode_frame(self.prior, points_s, normals_s, pose, c.voxel_size_m, c.min_points,
                               with_jacobian=with_jacobian, cells_per_voxel=cpv)

    def add_frame(self, points_s, pose, frame: int | None = None, pose_source: str | None = None) -> dict:
        """Encode, fuse and keep a frame. Returns its timings (s) and sizes.

        pose_source: where the pose came from, named by the error when it is not a rigid transform
        (None: the user's pose file, and the error says how to fix it)."""
        pose = np.asarray(pose, np.float64)
        validate_pose(pose, f"pose of frame {frame if frame is not None else len(self.store)}", source=pose_source)
        c = self.cfg.map
        t0 = time.perf_counter()
        pts, nrm = self.preprocess(points_s)
        t1 = time.perf_counter()
        pw = transform_points(pose, pts.astype(np.float64))
        nw = np.asarray(nrm, np.float64) @ pose[:3, :3].T
        cells, cnrm, cnt = lm.pool_cells(pw, nw, c.voxel_size_m, c.cells_per_voxel)
        kf = self.store.add(len(self.store) if frame is None else frame, cells, cnrm, cnt, pose)
        try:
            # encode the stored cells (as `remap` will), so a later removal subtracts exactly this
            local = contributions(self.prior, self.store, [kf], pose[None], c.voxel_size_m, c.min_points)
            jax.block_until_ready(local.latent)
            t2 = time.perf_counter()
            self.map = lm.fuse(self.map, local)
            jax.block_until_ready(self.map.latent_sum)
        except BaseException:
            self.store.pop()          # the store holds exactly the keyframes that are in the map
            raise
        t3 = time.perf_counter()
        info = {"frame": int(self.store.frames[-1]), "points": int(len(pts)), "cells": int(len(cells)),
                "preprocess_s": t1 - t0, "encode_s": t2 - t1, "fuse_s": t3 - t2,
                "local_voxels": int(np.count_nonzero(np.asarray(local.weight) > 0)),
                "map_voxels": self.map.num_active()}
        self.timings.append(info)
        return info

    def remap(self, new_poses) -> list[int]:
        """Move the keyframes whose pose changed ([K,4,4] new poses). Returns the ids that moved."""
        t0 = time.perf_counter()
        self.map, changed = remap(self.map, self.store, new_poses, self.prior, remap_options(self.cfg))
        jax.block_until_ready(self.map.latent_sum)
        self.remaps.append({"keyframes": len(changed), "time_s": time.perf_counter() - t0})
        return changed

    # -- outputs --
    def mesh(self, resolution: int | None = None):
        c = self.cfg.mesh
        return mesh_map(self.prior, self.map, resolution or c.resolution, c.sigma_threshold_m, c.min_weight,
                        c.min_component_faces)

    def sdf(self, points_w):
        """(sdf [P] m, std [P] m, valid [P]) at world points [P,3]; voxels with at most mesh.min_weight are
        not decoded (as for the mesh)."""
        return query(self.prior, self.map, points_w, min_weight=self.cfg.mesh.min_weight)

    def timing_summary(self, skip_first: int = 1) -> dict:
        """Per-frame medians after the first `skip_first` (compiling) frames, the count of frames with
        nothing left to encode, and the map's and keyframe store's sizes (timing.json)."""
        return {**medians(self.timings, ("preprocess_s", "encode_s", "fuse_s"), skip_first), **self.sizes()}

    def live_mesh(self) -> dict:
        """`attach_viewer` arguments for a live view: the mesh at half the lattice resolution (a preview;
        the final mesh is the full one), made in a background thread."""
        res = max(2, (self.cfg.mesh.resolution // 2) // 2 * 2)
        return {"mesh_fn": lambda: self.mesh(resolution=res)}

    def keyframe_poses(self) -> np.ndarray:
        return self.store.poses()

    def sizes(self) -> dict:
        return {"map_bytes": self.map.nbytes(), "map_voxels": self.map.num_active(),
                "store_bytes": self.store.nbytes(), "store_cells": self.store.cell_count(),
                "keyframes": len(self.store)}

    # -- checkpoints (orbax) --
    def save(self, path: str) -> None:
        """Write the map, the keyframe store and the config to directory `path` (atomically)."""
        from jaxmap.checkpoint import save_tree

        meta = {"config": to_dict(self.cfg), "table_capacity": int(self.map.table.capacity),
                "keyframes": len(self.store), "timings": self.timings, "remaps": self.remaps}
        save_tree(path, {"map": self.map, "store": self.store.to_arrays()}, meta)

    @classmethod
    def load(cls, path: str, prior=None) -> "ImtMapper":
        from jaxmap.checkpoint import read_meta, read_tree
        from jaxmap.grid.hashing import HashTable

        path, meta = read_meta(path, "jaxmap imt")
        cfg = from_dict(ImtConfig, meta["config"], source=os.path.join(path, "meta.json"))
        m = cls(cfg, prior)
        tree = read_tree(path)
        mp, t = tree["map"], tree["map"]["table"]
        if "latent_sum" not in mp:
            raise DataError(f"{path}: the latent map of this checkpoint was written by an older jaxmap (means and "
                            "Jacobians); map the sequence again")
        m.map = lm.LatentMap(HashTable(np.asarray(t["keys"]), np.asarray(t["rows"]), np.asarray(t["count"])),
                             np.asarray(mp["coords"]), np.asarray(mp["latent_sum"]), np.asarray(mp["weight"]), None,
                             cfg.map.voxel_size_m)
        m.store = KeyframeStore.from_arrays({k: np.asarray(v) for k, v in tree["store"].items()})
        m.timings, m.remaps = meta.get("timings", []), meta.get("remaps", [])
        return m
