"""Which submap a frame is mapped into, and the map frame its scan is made in (a map of submaps).

One rule (`next_submap`) decides from the chain's anchors and the sensor path driven in the active
submap; two callers apply it, each the only one deciding for the frames it sees:
- `Route`, for a drive at known poses (`jaxmap map`): the thread that uploads the frames ahead
  (`scan.Uploader`) routes each frame, in order, and makes its batch in its submap's map frame; the map
  follows the route the frame carries (`Place`, `SubmapMapper.submit`). Nothing else moves the uploads'
  origin, so no batch is ever made in a frame it is not mapped in.
- `Submaps.switch_for`, for poses that come one at a time on the main thread (`jaxmap slam`, whose loop
  closures also move submaps).

    route = Route.first(static, cfg.submaps, anchor_w)    # a new map: submap 0 anchored at the first frame
    place = route(position_w)                             # Place(origin_w, submap, position_w)
"""
from __future__ import annotations

import dataclasses

import numpy as np

from jaxmap.geometry import path_length
from jaxmap.n3.state import N3Static, origin_vox_for

NEW = -1  # `next_submap`: start a new submap


def next_submap(length_m: float, revisit: bool, anchors_w: np.ndarray, active: int, path_w: np.ndarray,
                position_w: np.ndarray) -> int | None:
    """Where the frame at sensor position_w [3] (world) goes: None = the active submap; NEW = a new one;
    an id = that earlier submap, whose anchor is the nearest and within half of length_m. anchors_w [K, 3]:
    each submap's anchor (its first frame's sensor position, world); path_w [P, 3]: the sensor positions of
    the active submap's frames. With revisit false, a new one once the sensor has driven length_m in the
    active one (a drive around a block never leaves a radius of length_m; its return must be another
    submap to be moved apart)."""
    here = np.asarray(position_w, np.float64)
    if not revisit:
        return None if path_length([*np.reshape(path_w, (-1, 3)), here]) <= length_m else NEW
    anchors_w = np.reshape(np.asarray(anchors_w, np.float64), (-1, 3))
    if np.linalg.norm(here - anchors_w[active]) <= length_m:
        return None
    d = np.linalg.norm(anchors_w - here, axis=1)
    d[active] = np.inf
    k = int(np.argmin(d))
    return k if d[k] <= 0.5 * length_m else NEW


def submap_origin(static: N3Static, anchor_w: np.ndarray) -> np.ndarray:
    """[3] float64 world position of the map frame of a submap anchored at anchor_w [3] (its first frame's
    sensor position, snapped to the coarsest voxel as `state.set_origin` places it)."""
    return origin_vox_for(static, anchor_w) * static.leaf


@dataclasses.dataclass(frozen=True, eq=False)
class Place:
    """Where an uploaded batch is mapped (`Frame.place`). origin_w: [3] float64 world position of the map
    frame the batch was made in; submap: the submap it goes to (a map of one grid: None); position_w: [3]
    float64 the sensor's world position (a map of submaps records its path)."""

    origin_w: np.ndarray
    submap: int | None = None
    position_w: np.ndarray | None = None


class Route:
    """`next_submap` applied to the frames of a drive at known poses, in their order, by the one thread that
    makes their batches (`scan.Uploader`). It keeps what the rule reads: the anchors of the submaps so far
    (world), the active one, the path driven in it. A new submap takes the next id, as `Submaps.start`
    gives it, so the map that follows the routes (`SubmapMapper.submit`) builds the same chain."""

    def __init__(self, static: N3Static, length_m: float, revisit: bool, anchors_w=(), active: int | None = None,
                 path_w=()):
        self.static, self.length_m, self.revisit = static, float(length_m), bool(revisit)
        self.anchors = [np.asarray(a, np.float64) for a in anchors_w]
        self.active = active
        self.path = [np.asarray(p, np.float64) for p in np.reshape(np.asarray(path_w, np.float64), (-1, 3))]

    @classmethod
    def first(cls, static: N3Static, sub_cfg, anchor_w: np.ndarray | None) -> "Route":
        """The route of a new map whose first submap is anchored at anchor_w [3] (None: at its first frame)."""
        anchors = [] if anchor_w is None else [anchor_w]
        return cls(static, sub_cfg.length_m, sub_cfg.revisit, anchors, 0 if anchors else None)

    def origin(self, k: int) -> np.ndarray:
        """[3] float64 world position of submap k's map frame."""
        return submap_origin(self.static, self.anchors[k])

    def __call__(self, position_w: np.ndarray) -> Place:
        """The place of the next frame, whose sensor is at world position_w [3]."""
        here = np.asarray(position_w, np.float64).reshape(3)
        k = None if self.active is None else next_submap(
            self.length_m, self.revisit, np.asarray(self.anchors), self.active, np.asarray(self.path), here)
        if self.active is None or k == NEW:
            self.anchors.append(here.copy())
            self.active, self.path = len(self.anchors) - 1, []
        elif k is not None:
            # (an earlier submap taken up again: only revisit comes back, and its rule reads no path)
            self.active, self.path = k, []
        self.path.append(here)
        return Place(self.origin(self.active), self.active, here)
