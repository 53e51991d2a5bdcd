"""Keyframe store and remapping of the latent map after a pose-graph update (IMT paper III-B, Fig. 4).

Every fused frame is a keyframe. The store keeps, per keyframe, its *original* local map (the
`VoxelBatch` that `encode_frame` gave, compacted: voxels, latents, Jacobians, weights, in the world
grid of the pose it was encoded with), that pose `pose_enc`, and the pose whose contribution is in
the global map now, `pose_fused`. A keyframe's contribution for a pose `P` is its local map moved by
`P pose_enc^-1` (the local map itself when that is the identity, so nothing is interpolated for a
keyframe that never moved).

`remap(global_map, store, new_poses)` finds the keyframes whose pose changed (rotation angle or
translation above the thresholds, compared with `pose_fused`), removes their current contributions,
and fuses the contributions for the new poses. Contributions are always computed from the original
local map, so repeated loop closures do not accumulate interpolation error, and the removal subtracts
exactly what was fused (the same function of the same inputs). All changed keyframes go through one
batched splat, one removal and one fusion (`VoxelBatch`es concatenate; see `latent_map`).

The store lives on the host (numpy): it grows by one keyframe per frame and is only read at a loop
closure. Its size is dominated by the Jacobians (18 x 3 x 3 floats per voxel).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from jaxmap.geometry import pose_change, se3_inverse
from jaxmap.imt.latent_map import LatentMap, VoxelBatch, concat_batches, fuse, remove
from jaxmap.imt.transform import METHODS, splat_trilinear, transform_batch

log = logging.getLogger("jaxmap")


@dataclass
class KeyframeStore:
    """Original local maps of the keyframes (host numpy) and their poses.

    frames: [K] int frame index per keyframe; locals_: K compact VoxelBatches;
    pose_enc, pose_fused: [K, 4, 4] float64 T_world_sensor.
    """

    frames: list = field(default_factory=list)
    locals_: list = field(default_factory=list)
    pose_enc: list = field(default_factory=list)
    pose_fused: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, frame: int, local: LatentMap | VoxelBatch, pose) -> int:
        """Append a keyframe whose local map was encoded (and fused) with `pose`. Returns its id."""
        b = local.as_batch() if isinstance(local, LatentMap) else local
        self.frames.append(int(frame))
        self.locals_.append(VoxelBatch(*(np.asarray(x) for x in b.compact())))
        pose = np.asarray(pose, np.float64)
        self.pose_enc.append(pose.copy())
        self.pose_fused.append(pose.copy())
        return len(self.frames) - 1

    def poses(self) -> np.ndarray:
        """[K, 4, 4] poses currently fused."""
        return np.asarray(self.pose_fused).reshape(-1, 4, 4)

    def nbytes(self) -> int:
        return int(sum(b.nbytes() for b in self.locals_) + 2 * 128 * len(self.frames))

    def voxel_count(self) -> int:
        return int(sum(int(np.sum(b.valid)) for b in self.locals_))

    # -- (de)serialisation as flat arrays (orbax / npz) --
    def to_arrays(self) -> dict:
        sizes = np.array([len(b.weight) for b in self.locals_], np.int64)
        cat = [np.concatenate([b[i] for b in self.locals_]) if self.locals_ else np.zeros((0,)) for i in range(5)]
        return {"frames": np.asarray(self.frames, np.int64), "sizes": sizes,
                "pose_enc": self.poses_enc_array(), "pose_fused": self.poses(),
                "coords": cat[0], "latent": cat[1], "jac": cat[2], "weight": cat[3], "valid": cat[4]}

    def poses_enc_array(self) -> np.ndarray:
        return np.asarray(self.pose_enc).reshape(-1, 4, 4)

    @classmethod
    def from_arrays(cls, a: dict) -> "KeyframeStore":
        s = cls()
        off = np.concatenate([[0], np.cumsum(a["sizes"])]).astype(np.int64)
        for k in range(len(a["frames"])):
            sl = slice(off[k], off[k + 1])
            s.frames.append(int(a["frames"][k]))
            s.locals_.append(VoxelBatch(*(np.asarray(a[n][sl]) for n in ("coords", "latent", "jac", "weight", "valid"))))
            s.pose_enc.append(np.asarray(a["pose_enc"][k], np.float64))
            s.pose_fused.append(np.asarray(a["pose_fused"][k], np.float64))
        return s


@dataclass(frozen=True)
class RemapOptions:
    min_rotation_deg: float = 0.05       # a keyframe is remapped when its pose moved more than this ...
    min_translation_m: float = 0.002     # ... or this (compared with the pose fused now)
    method: str = "trilinear"            # interpolation onto the global grid (see transform.py)
    jacobian_sign: float = -1.0          # -1: correct first-order term; +1: paper eq. 5; 0: none
    temperature: float = 1.0             # softmax only (voxel units^2)
    k: int = 8                           # softmax only: neighbours per global voxel
    splat_power: float = 2.0             # trilinear only: sharpening of the splat weights (1 = plain)


def _moved(a, b, opts: RemapOptions) -> bool:
    ang, trans = pose_change(a, b)
    return ang > np.deg2rad(opts.min_rotation_deg) or trans > opts.min_translation_m


def contributions(store: KeyframeStore, ids, poses, voxel_size: float, opts: RemapOptions) -> VoxelBatch | None:
    """The global-grid contributions of keyframes `ids` at `poses` ([len(ids), 4, 4]), one batch."""
    same, moved, deltas = [], [], []
    for kf, pose in zip(ids, poses):
        if np.allclose(pose, store.pose_enc[kf], rtol=0.0, atol=1e-9):
            same.append(store.locals_[kf])             # exactly what encode_frame fused
        else:
            moved.append(kf)
            deltas.append(np.asarray(pose, np.float64) @ se3_inverse(store.pose_enc[kf]))
    parts = list(same)
    if moved and opts.method == "trilinear":
        b = concat_batches([store.locals_[kf] for kf in moved])
        T = np.concatenate([np.broadcast_to(d.astype(np.float32), (len(store.locals_[kf].weight), 4, 4))
                            for kf, d in zip(moved, deltas)])
        n = len(T)
        pad = 1 << int(np.ceil(np.log2(max(n, 1024))))   # few compiled shapes
        b = VoxelBatch(*(np.concatenate([np.asarray(x), np.zeros((pad - n,) + np.shape(x)[1:], np.asarray(x).dtype)])
                         for x in b))
        T = np.concatenate([T, np.broadcast_to(np.eye(4, dtype=np.float32), (pad - n, 4, 4))])
        parts.append(splat_trilinear(b, T, voxel_size, float(opts.jacobian_sign), float(opts.splat_power)))
    elif moved:  # softmax gathers per keyframe (it needs each local map's own lattice)
        for kf, d in zip(moved, deltas):
            m = fuse(_empty_like(voxel_size, store.locals_[kf]), store.locals_[kf], log=False)
            parts.append(transform_batch(m, d, method=opts.method, jacobian_sign=opts.jacobian_sign,
                                         temperature=opts.temperature, k=opts.k))
    return concat_batches(parts) if parts else None


def _empty_like(voxel_size, b):
    from jaxmap.imt.latent_map import empty

    cap = 1 << max(10, int(np.ceil(np.log2(2 * max(int(np.sum(b.valid)), 1)))))
    return empty(voxel_size, capacity=cap, channels=np.shape(b.latent)[1])


def remap(global_map: LatentMap, store: KeyframeStore, new_poses, opts: RemapOptions = RemapOptions()):
    """Move every keyframe whose pose changed to its new pose in the global map.

    Args:
      global_map: the fused map (world frame).
      store: the keyframe store (updated in place: `pose_fused` of the remapped keyframes).
      new_poses: [K, 4, 4] new T_world_sensor of every keyframe (K = len(store)).
    Returns:
      `(global_map, changed)`: the new map and the list of keyframe ids that were remapped.
    """
    if opts.method not in METHODS:
        raise ValueError(f"unknown interpolation method {opts.method!r}; choose one of {METHODS}")
    new_poses = np.asarray(new_poses, np.float64)
    if new_poses.shape != (len(store), 4, 4):
        raise ValueError(f"remap: expected {len(store)} poses [K,4,4], got shape {new_poses.shape}")
    changed = [k for k in range(len(store)) if _moved(new_poses[k], store.pose_fused[k], opts)]
    if not changed:
        return global_map, []
    vs = global_map.voxel_size
    old = contributions(store, changed, [store.pose_fused[k] for k in changed], vs, opts)
    new = contributions(store, changed, [new_poses[k] for k in changed], vs, opts)
    global_map = fuse(remove(global_map, old), new)
    for k in changed:
        store.pose_fused[k] = new_poses[k].copy()
    log.info("remap: %d of %d keyframes moved", len(changed), len(store))
    return global_map, changed
