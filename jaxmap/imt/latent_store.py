"""Keyframe store of latent local maps: remapping by transform (`map.remap: transform`, IMT paper III-B).

Each keyframe keeps the local map it was fused with: per voxel of the world grid *at the pose it was
encoded at* (`pose_encoded`, the keyframe's first fused pose), its coords, mean latent `F [C, 3]` and
translation Jacobian `J [C, 3, 3]` in float16 (`COMPACT`), and its weight (point count, float32). The
map fuses exactly these float16 values (`core.step` rounds them before it fuses), so the
contribution of a keyframe is a function of its stored map and the pose it is fused at, nothing else:

    contribution(k, T) = L_k                               if T == pose_encoded[k] (bitwise)
                         splat(L_k, T pose_encoded[k]^-1)  otherwise (`transform.splat_trilinear`)

and a remap removes `contribution(k, pose_fused[k])` and adds `contribution(k, T_new)`. Every move
starts from the stored `L_k`, never from an earlier move's result, so interpolation blur does not
accumulate over successive loop closures: ten remaps end where one remap to the last poses ends
(up to the rounding of the sums).

`rows` flattens the keyframes of a remap into one `RowBatch` (host numpy): one entry per stored voxel,
with the 3x4 world-frame motion `D = T pose_encoded^-1` of its keyframe, whether that motion is the
identity (`exact`: the voxel is fused as stored, without a splat) and the sign (+1 fuse, -1 remove).
Size: 4 + 12 + 2 x 18 x 3 + 2 x 18 x 9 = 448 bytes a voxel (about 2 MB for a 320x240 room keyframe
of 4.4k voxels), 40x the pooled cells of `keyframe_store.KeyframeStore` (`jaxmap bench imt` prints both).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from jaxmap.errors import DataError
from jaxmap.imt.keyframe_store import PosedStore, frozen

COMPACT = np.float16     # latents and Jacobians of the store (|rel. error| <= 2^-11; the map fuses these values)


class RowBatch(NamedTuple):
    """Stored voxels of one or more keyframes with the motion that places them (host numpy, padded).

    coords [P, 3] int32 (world grid at the keyframe's pose_encoded); latent [P, C, 3] and jac
    [P, C, 3, 3] float16 means; weight [P] float32 (0 = padding); sign [P] float32 (+1 fuse, -1 remove);
    motion [P, 3, 4] float32 world-frame `D = T pose_encoded^-1`; exact [P] bool (D is the identity)."""

    coords: np.ndarray
    latent: np.ndarray
    jac: np.ndarray
    weight: np.ndarray
    sign: np.ndarray
    motion: np.ndarray
    exact: np.ndarray


@dataclass(frozen=True)
class LatentStore(PosedStore):
    """Latent local maps of the keyframes (see the module docstring). Immutable, like `KeyframeStore`.

    coords / latent / jac / weight: per keyframe [R_k, 3] int32, [R_k, C, 3] and [R_k, C, 3, 3]
    float16, [R_k] float32; pose_encoded: per keyframe [4, 4] float64."""

    coords: tuple = ()
    latent: tuple = ()
    jac: tuple = ()
    weight: tuple = ()
    pose_encoded: tuple = ()

    def add(self, frame: int, coords, latent, jac, weight, pose) -> "LatentStore":
        """The store with one more keyframe: its local map (voxels with weight > 0 only), encoded and
        fused at `pose`."""
        keep = np.asarray(weight) > 0
        pose = frozen(np.array(pose, np.float64))
        return dataclasses.replace(
            self, frames=self.frames + (int(frame),), pose_fused=self.pose_fused + (pose,),
            coords=self.coords + (frozen(np.asarray(coords, np.int32)[keep]),),
            latent=self.latent + (frozen(np.asarray(latent).astype(COMPACT)[keep]),),
            jac=self.jac + (frozen(np.asarray(jac).astype(COMPACT)[keep]),),
            weight=self.weight + (frozen(np.asarray(weight, np.float32)[keep]),),
            pose_encoded=self.pose_encoded + (pose,))

    def nbytes(self) -> int:
        return int(sum(sum(x.nbytes for x in xs) for xs in (self.coords, self.latent, self.jac, self.weight))
                   + 256 * len(self.frames))

    def cell_count(self) -> int:
        """Stored voxels (the unit of this store, as cells are `KeyframeStore`'s)."""
        return int(sum(len(w) for w in self.weight))

    def sizes(self, ids) -> list[int]:
        return [len(self.weight[k]) for k in ids]

    def rows(self, ids, poses, signs) -> RowBatch:
        """The stored voxels of keyframes `ids`, each placed at its pose in `poses` ([len(ids), 4, 4]) with
        its sign (see `RowBatch`)."""
        parts = []
        for k, T, s in zip(ids, poses, signs):
            enc = self.pose_encoded[k]
            T = np.asarray(T, np.float64)
            exact = bool(np.array_equal(T, enc))
            D = np.eye(4) if exact else T @ np.linalg.inv(enc)
            n = len(self.weight[k])
            parts.append((self.coords[k], self.latent[k], self.jac[k], self.weight[k], np.full(n, s, np.float32),
                          np.broadcast_to(D[:3].astype(np.float32), (n, 3, 4)), np.full(n, exact)))
        if not parts:
            raise ValueError("rows: no keyframes")
        return RowBatch(*(np.concatenate(col) for col in zip(*parts)))

    # -- (de)serialisation as flat arrays (orbax / npz) --
    def to_arrays(self) -> dict:
        return {"frames": np.asarray(self.frames, np.int64),
                "sizes": np.asarray(self.sizes(range(len(self))), np.int64), "pose_fused": self.poses(),
                "pose_encoded": np.asarray(self.pose_encoded).reshape(-1, 4, 4),
                **{name: _cat(getattr(self, name), shape, dt) for name, shape, dt in _FIELDS}}

    @classmethod
    def from_arrays(cls, a: dict) -> "LatentStore":
        if "latent" not in a or "jac" not in a:
            raise DataError("this checkpoint's keyframe store holds pooled cells (map.remap: reencode); "
                            "load it with that setting or map the sequence again with map.remap: transform")
        off = np.concatenate([[0], np.cumsum(a["sizes"])]).astype(np.int64)
        sl = [slice(off[k], off[k + 1]) for k in range(len(a["frames"]))]
        cols = {name: tuple(frozen(np.array(a[name][x], dt)) for x in sl) for name, _, dt in _FIELDS}
        pose = lambda key: tuple(frozen(np.array(a[key][k], np.float64)) for k in range(len(sl)))  # noqa: E731
        return cls(frames=tuple(int(f) for f in a["frames"]), pose_fused=pose("pose_fused"),
                   pose_encoded=pose("pose_encoded"), **cols)


_FIELDS = (("coords", (0, 3), np.int32), ("latent", (0, 18, 3), COMPACT), ("jac", (0, 18, 3, 3), COMPACT),
           ("weight", (0,), np.float32))


def _cat(xs, shape, dtype):
    return np.concatenate(xs) if xs else np.zeros(shape, dtype)
