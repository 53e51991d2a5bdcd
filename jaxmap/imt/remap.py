"""Keyframe store and remapping of the latent map after a pose-graph update (IMT paper III-B, Fig. 4).

Every fused frame is a keyframe. The store keeps, per keyframe, the pooled cells its local map was
encoded from (`latent_map.pool_cells` at the pose it was fused with: one centroid, mean normal and
point count per occupied cell of voxel_size / cells_per_voxel), in the *sensor* frame, plus the pose
whose contribution is in the global map now, `pose_fused`. Stored compactly: centroids float32,
normals float16 (|error| <= 5e-4), counts uint16, i.e. 20 bytes per cell, about 45 kB for a 320x240
room frame (its 31k downsampled points and normals take 750 kB as float32).

`remap(global_map, store, new_poses, prior)` finds the keyframes whose pose changed (rotation angle
or translation above the thresholds, compared with `pose_fused`) and re-encodes them: their current
contributions (the cells at `pose_fused`, encoded exactly as when they were fused: the world-frame
cells are computed in float64 on the host, so the voxels and counts are bitwise the same) go into
one batch with weight -w, the contributions at the new poses with +w, and one `fuse` applies both
(the global map stores sums, so this is exact up to float rounding). When more than
`rebuild_fraction` of the keyframes moved, the map is rebuilt from all keyframes instead (one encode
of K keyframes is cheaper than 2 x K). Re-encoding at the new pose is exact: there is no
interpolation blur, so a remapped map equals the map built with those poses (`jaxmap bench imt`
measures it), and repeated loop closures accumulate nothing. `transform` (the paper's first-order
interpolation with Jacobians) remains the tool for moving a local map whose points are gone.

Keyframes are encoded in groups of at most `GROUP_CELLS` cells and `GROUP_SLOTS` keyframes (about 15
room keyframes), padded to a `bucket` of at least 4096 cells and to `GROUP_SLOTS` slots: a whole-loop
remap is a few calls of one compiled program, and every remap uses one of a dozen shapes.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from jaxmap.errors import DataError
from jaxmap.geometry import pose_change, se3_inverse
from jaxmap.imt.latent_map import LatentMap, bucket, empty, encode_keyframes, fuse

log = logging.getLogger("jaxmap")

GROUP_CELLS = 32768   # cells per encode call of a remap (one compiled shape; a 14 MB scratch accumulator)
GROUP_SLOTS = 64      # keyframes per encode call of a remap


@dataclass
class KeyframeStore:
    """Pooled cells of the keyframes (host numpy, sensor frame) and their fused poses.

    frames: [K] int frame index per keyframe; points / normals / counts: per keyframe [M_k, 3] float32
    centroids, [M_k, 3] float16 unit normals, [M_k] uint16 point counts; pose_fused: [K] x [4, 4]
    float64 T_world_sensor currently in the global map.
    """

    frames: list = field(default_factory=list)
    points: list = field(default_factory=list)
    normals: list = field(default_factory=list)
    counts: list = field(default_factory=list)
    pose_fused: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, frame: int, cells_w, normals_w, counts, pose) -> int:
        """Append a keyframe: its pooled cells in the world frame at `pose` (what was fused). Returns its id."""
        pose = np.asarray(pose, np.float64)
        inv = se3_inverse(pose)
        pts = np.asarray(cells_w, np.float64) @ inv[:3, :3].T + inv[:3, 3]
        self.frames.append(int(frame))
        self.points.append(pts.astype(np.float32))
        self.normals.append((np.asarray(normals_w, np.float64) @ pose[:3, :3]).astype(np.float16))
        self.counts.append(np.asarray(counts).astype(np.uint16))
        self.pose_fused.append(pose.copy())
        return len(self.frames) - 1

    def pop(self) -> None:
        """Drop the last keyframe (one whose fusion failed)."""
        for xs in (self.frames, self.points, self.normals, self.counts, self.pose_fused):
            xs.pop()

    def poses(self) -> np.ndarray:
        """[K, 4, 4] poses currently fused."""
        return np.asarray(self.pose_fused).reshape(-1, 4, 4)

    def nbytes(self) -> int:
        return int(sum(p.nbytes + n.nbytes + c.nbytes for p, n, c in zip(self.points, self.normals, self.counts))
                   + 128 * len(self.frames))

    def cell_count(self) -> int:
        return int(sum(len(c) for c in self.counts))

    def cells_at(self, ids, poses):
        """World-frame cells of keyframes `ids` at `poses` ([len(ids), 4, 4]), float64 on the host (so the
        same keyframe at the same pose always gives bitwise the same cells). Returns
        `(points [N, 3] float32, normals [N, 3] float32, counts [N] float32, slot [N] int32)`."""
        pts, nrm, cnt, slot = [], [], [], []
        for j, (k, P) in enumerate(zip(ids, poses)):
            P = np.asarray(P, np.float64)
            pts.append(self.points[k].astype(np.float64) @ P[:3, :3].T + P[:3, 3])
            nrm.append(self.normals[k].astype(np.float64) @ P[:3, :3].T)
            cnt.append(self.counts[k])
            slot.append(np.full(len(self.counts[k]), j, np.int32))
        if not pts:
            z = np.zeros((0, 3), np.float32)
            return z, z, np.zeros(0, np.float32), np.zeros(0, np.int32)
        return (np.concatenate(pts).astype(np.float32), np.concatenate(nrm).astype(np.float32),
                np.concatenate(cnt).astype(np.float32), np.concatenate(slot))

    # -- (de)serialisation as flat arrays (orbax / npz) --
    def to_arrays(self) -> dict:
        sizes = np.array([len(c) for c in self.counts], np.int64)
        cat = lambda xs, shape, dt: np.concatenate(xs) if xs else np.zeros(shape, dt)  # noqa: E731
        return {"frames": np.asarray(self.frames, np.int64), "sizes": sizes, "pose_fused": self.poses(),
                "points": cat(self.points, (0, 3), np.float32), "normals": cat(self.normals, (0, 3), np.float16),
                "counts": cat(self.counts, (0,), np.uint16)}

    @classmethod
    def from_arrays(cls, a: dict) -> "KeyframeStore":
        if "points" not in a:
            raise DataError("this checkpoint's keyframe store holds latents (written by an older jaxmap); "
                            "map the sequence again to get a store of pooled cells")
        s = cls()
        off = np.concatenate([[0], np.cumsum(a["sizes"])]).astype(np.int64)
        for k in range(len(a["frames"])):
            sl = slice(off[k], off[k + 1])
            s.frames.append(int(a["frames"][k]))
            s.points.append(np.asarray(a["points"][sl], np.float32))
            s.normals.append(np.asarray(a["normals"][sl], np.float16))
            s.counts.append(np.asarray(a["counts"][sl], np.uint16))
            s.pose_fused.append(np.asarray(a["pose_fused"][k], np.float64))
        return s


@dataclass(frozen=True)
class RemapOptions:
    min_rotation_deg: float = 0.05       # a keyframe is remapped when its pose moved more than this ...
    min_translation_m: float = 0.002     # ... or this (compared with the pose fused now)
    min_points: int = 10                 # as when the keyframes were fused (map.min_points)
    rebuild_fraction: float = 0.5        # rebuild from every keyframe when more than this share moved


def moved_keyframes(store: KeyframeStore, new_poses, opts: RemapOptions) -> list[int]:
    """Ids of the keyframes whose new pose differs from the fused one by more than the thresholds."""
    if not len(store):
        return []
    ang, trans = pose_change(store.poses(), np.asarray(new_poses, np.float64))
    return np.flatnonzero((ang > np.deg2rad(opts.min_rotation_deg)) | (trans > opts.min_translation_m)).tolist()


def contributions(prior, store: KeyframeStore, ids, poses, voxel_size: float, min_points: int = 10, signs=None,
                  grouped: bool = False):
    """The global-grid contributions of keyframes `ids` at `poses` (a `VoxelBatch`, weights times `signs`).
    grouped: pad as a remap group (`bucket` of at least 4096 cells, GROUP_SLOTS slots)."""
    pts, nrm, cnt, slot = store.cells_at(ids, poses)
    pad = {}
    if grouped:
        pad = {"n_pad": bucket(len(pts), 4096), "slots_pad": GROUP_SLOTS}
    return encode_keyframes(prior, pts, nrm, cnt, slot, len(ids), voxel_size, min_points, signs, **pad)


def apply_keyframes(m: LatentMap, prior, store: KeyframeStore, ids, poses, signs, min_points: int) -> LatentMap:
    """Fuse (sign +1) or remove (-1) the contributions of keyframes `ids` at `poses`, in groups of at most
    `GROUP_CELLS` cells (a keyframe's removal and re-fusion stay in one group when they are adjacent)."""
    sizes = [len(store.counts[k]) for k in ids]
    start = 0
    while start < len(ids):
        stop, total = start + 1, sizes[start]
        while stop < len(ids) and stop - start < GROUP_SLOTS and total + sizes[stop] <= GROUP_CELLS:
            total += sizes[stop]
            stop += 1
        sl = slice(start, stop)
        m = fuse(m, contributions(prior, store, ids[sl], poses[sl], m.voxel_size, min_points, signs[sl], True),
                 log=False)
        start = stop
    return m


def remap(global_map: LatentMap, store: KeyframeStore, new_poses, prior, opts: RemapOptions = RemapOptions()):
    """Move every keyframe whose pose changed to its new pose in the global map.

    Args:
      global_map: the fused map (world frame).
      store: the keyframe store (updated in place: `pose_fused` of the remapped keyframes).
      new_poses: [K, 4, 4] new T_world_sensor of every keyframe (K = len(store)).
      prior: the `Prior` the map was encoded with.
    Returns:
      `(global_map, changed)`: the new map and the list of keyframe ids that were remapped.
    """
    new_poses = np.asarray(new_poses, np.float64)
    if new_poses.shape != (len(store), 4, 4):
        raise ValueError(f"remap: expected {len(store)} poses [K,4,4], got shape {new_poses.shape}")
    changed = moved_keyframes(store, new_poses, opts)
    if not changed:
        return global_map, []
    if len(changed) > opts.rebuild_fraction * len(store):
        ids = list(range(len(store)))
        fresh = empty(global_map.voxel_size, global_map.table.capacity, global_map.channels)
        m = apply_keyframes(fresh, prior, store, ids, new_poses, np.ones(len(ids), np.float32), opts.min_points)
    else:
        ids = changed + changed
        poses = np.concatenate([store.poses()[changed], new_poses[changed]])
        signs = np.concatenate([-np.ones(len(changed)), np.ones(len(changed))]).astype(np.float32)
        # removal and fusion of a keyframe in the same group: its -w and +w land in one scatter
        order = np.argsort(np.tile(np.arange(len(changed)), 2), kind="stable")
        m = apply_keyframes(global_map, prior, store, [ids[i] for i in order], poses[order], signs[order],
                            opts.min_points)
    for k in changed:
        store.pose_fused[k] = new_poses[k].copy()
    log.info("remap: %d of %d keyframes moved%s", len(changed), len(store),
             " (rebuilt from every keyframe)" if len(changed) > opts.rebuild_fraction * len(store) else "")
    return m, changed
