"""Keyframe store and remapping of the latent map after a pose-graph update (IMT paper III-B, Fig. 4).

Every fused frame is a keyframe. The store (immutable: `add` and `with_poses` return new stores)
keeps, per keyframe, the pooled cells its local map was encoded from (`latent_map.pool_cells` at the
pose it was fused with: one centroid, mean normal and point count per occupied cell of
voxel_size / cells_per_voxel), in the *sensor* frame, plus the pose whose contribution is in the
global map now, `pose_fused`. Stored compactly: centroids float32, normals float16 (|error| <= 5e-4),
counts uint16, i.e. 20 bytes per cell, about 45 kB for a 320x240 room frame (its 31k downsampled
points and normals take 750 kB as float32). Every encode of a keyframe, its first fusion included,
takes its world-frame cells from `cells_at` (float64 on the host), so the same keyframe at the same
pose always gives bitwise the same cells, voxels and counts.

`jaxmap.imt.core.remap` finds the keyframes whose pose changed (`moved_keyframes`: rotation angle or
translation above the thresholds, compared with `pose_fused`) and re-encodes them: their current
contributions (the cells at `pose_fused`) with weight -w and the contributions at the new poses with
+w, in the same frame programs (the global map stores sums, so this is exact up to float rounding).
When more than `rebuild_fraction` of the keyframes moved, the map is rebuilt from all keyframes
instead (one encode of K keyframes is cheaper than 2 x K). Re-encoding at the new pose is exact:
there is no interpolation blur, so a remapped map equals the map built with those poses (`jaxmap
bench imt` measures it), and repeated loop closures accumulate nothing. `transform` (the paper's
first-order interpolation with Jacobians) moves local maps whose points are gone.

A remap reuses the frame program (`core.step`) at the largest cell count the frames were padded to, with
their keyframe slots, so a loop closure compiles nothing that mapping did not. `latent_store` holds
the other method, `map.remap: transform`: each keyframe keeps its latent local map and a remap moves it.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from jaxmap.errors import DataError
from jaxmap.geometry import SE3, pose_change


def frozen(x: np.ndarray) -> np.ndarray:
    """`x`, made read-only (the stores share their arrays between versions)."""
    x.setflags(write=False)
    return x


@dataclass(frozen=True)
class PosedStore:
    """What both keyframe stores share: the frame index of each keyframe and the pose whose contribution
    is in the global map now (`pose_fused`, [4, 4] float64 T_world_sensor)."""

    frames: tuple = ()
    pose_fused: tuple = ()

    def __len__(self) -> int:
        return len(self.frames)

    def with_poses(self, ids, poses):
        """The store with `pose_fused` of keyframes `ids` replaced by `poses` ([len(ids), 4, 4])."""
        fused = list(self.pose_fused)
        for k, P in zip(ids, poses):
            fused[k] = frozen(np.array(P, np.float64))
        return dataclasses.replace(self, pose_fused=tuple(fused))

    def poses(self) -> np.ndarray:
        """[K, 4, 4] poses currently fused."""
        return np.asarray(self.pose_fused).reshape(-1, 4, 4)


@dataclass(frozen=True)
class KeyframeStore(PosedStore):
    """Pooled cells of the keyframes (host numpy, sensor frame) and their fused poses. Immutable: `add` and
    `with_poses` return new stores sharing the (read-only) arrays of the old one.

    frames: [K] int frame index per keyframe; points / normals / counts: per keyframe [M_k, 3] float32
    centroids, [M_k, 3] float16 unit normals, [M_k] uint16 point counts; pose_fused: [K] x [4, 4]
    float64 T_world_sensor currently in the global map.
    """

    points: tuple = ()
    normals: tuple = ()
    counts: tuple = ()

    def add(self, frame: int, cells_w, normals_w, counts, pose) -> "KeyframeStore":
        """The store with one more keyframe: its pooled cells in the world frame at `pose` (kept in the
        sensor frame). Its id is the old `len(store)`."""
        pose = np.asarray(pose, np.float64)
        T_s_w = SE3.from_matrix(pose).inverse()
        pts = T_s_w.apply(np.asarray(cells_w, np.float64))
        return KeyframeStore(
            self.frames + (int(frame),), self.pose_fused + (frozen(pose.copy()),),
            self.points + (frozen(pts.astype(np.float32)),),
            self.normals + (frozen(T_s_w.rotation().apply(np.asarray(normals_w, np.float64)).astype(np.float16)),),
            self.counts + (frozen(np.asarray(counts).astype(np.uint16)),))

    def nbytes(self) -> int:
        return int(sum(p.nbytes + n.nbytes + c.nbytes for p, n, c in zip(self.points, self.normals, self.counts))
                   + 128 * len(self.frames))

    def cell_count(self) -> int:
        return int(sum(len(c) for c in self.counts))

    def sizes(self, ids) -> list[int]:
        return [len(self.counts[k]) for k in ids]

    def cells_at(self, ids, poses):
        """World-frame cells of keyframes `ids` at `poses` ([len(ids), 4, 4]), float64 on the host (so the
        same keyframe at the same pose always gives bitwise the same cells). Returns
        `(points [N, 3] float32, normals [N, 3] float32, counts [N] float32, slot [N] int32)`."""
        pts, nrm, cnt, slot = [], [], [], []
        for j, (k, P) in enumerate(zip(ids, poses)):
            T_w_s = SE3.from_matrix(np.asarray(P, np.float64))
            pts.append(T_w_s.apply(self.points[k].astype(np.float64)))
            nrm.append(T_w_s.rotation().apply(self.normals[k].astype(np.float64)))
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
            raise DataError("this checkpoint's keyframe store holds latent local maps (map.remap: transform); "
                            "load it with that setting, or map the sequence again to get a store of pooled cells")
        off = np.concatenate([[0], np.cumsum(a["sizes"])]).astype(np.int64)
        sl = [slice(off[k], off[k + 1]) for k in range(len(a["frames"]))]
        return cls(tuple(int(f) for f in a["frames"]),
                   tuple(frozen(np.array(a["pose_fused"][k], np.float64)) for k in range(len(sl))),
                   tuple(frozen(np.array(a["points"][x], np.float32)) for x in sl),
                   tuple(frozen(np.array(a["normals"][x], np.float16)) for x in sl),
                   tuple(frozen(np.array(a["counts"][x], np.uint16)) for x in sl))


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
