"""A map of N3 submaps: a drive of any length in bounded memory (`submaps.enabled`).

The map is a chain of submaps, each an N3 map of its own (one `N3State`: grid, features, pair store and
free-space evidence, with its own origin) holding the frames mapped while the sensor was within
`submaps.length_m` of the submap's first frame, its anchor. When the sensor moves farther, the map goes
on in the submap whose anchor is nearest, if one lies within half that distance (a loop: the old submap is
taken up again), else in a new one anchored at the sensor. A new submap is an N3 map of its own, with
the capacities of the one before it (the compiled frame program is reused), its own decoder (trained for
its first `train.freeze_after_frame` frames, as a map's is; a frozen decoder handed over does not learn
a grid of new features from zero) and an empty pair store: overlap comes from the sensor's range, which
the submaps on both sides of a switch have seen.

Memory holds the submap being mapped and the `submaps.resident - 1` used last (what a query reads of
them); a submap that is left is written at once (in the background) to `<dir>/<id>/<frame>/` as an N3
checkpoint without its pair store (`n3.checkpoint`; each file independent of the others) and dropped
from memory when more are resident; it is read back, bit for bit, when a query or a loop needs it. The
index (`SubmapInfo` per submap: pose, anchor, sensor path, bounds, checkpoint step) goes into the run's
checkpoint.

A submap's pose T_world_local [4, 4] places its frame (the "world" its N3 state was built in: map frame
plus origin) in the world; it is the identity until a pose graph moves the submap as a rigid body.

Reading the map blends the submaps that hold a point: each submap is weighted by the point's distance to
its sensor path, the nearest submap that holds the point (valid there) 1, the others falling linearly to 0
over `submaps.blend_m` (`blend_weights`), so that a seam is a smooth hand-over, not a step.

    subs = Submaps(static, cfg, directory)              # host side: index, resident states, files
    sdf, valid = subs.query_world(points_w)             # blended
    mesh = subs.mesh(res, min_component_faces)          # streamed one submap (and its neighbours) at a time
"""
from __future__ import annotations

import collections
import dataclasses
import os

import numpy as np

from jaxmap import hostmem
from jaxmap.n3 import checkpoint as n3checkpoint, window
from jaxmap.n3.query import check_mesh_resolution, mesh_cells, query_view, query_world
from jaxmap.n3.routing import Route, next_submap
from jaxmap.n3.state import N3State, N3Static, origin_world
from jaxmap.n3.evidence import void as void_of


@dataclasses.dataclass
class SubmapInfo:
    """What the index knows of one submap (host side, JSON in the run's checkpoint)."""

    id: int
    anchor: np.ndarray            # [3] float64 local frame: the sensor position of its first frame
    pose: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))  # [4, 4] float64 T_world_local
    path: list = dataclasses.field(default_factory=list)   # sensor positions [3] (local frame) of its frames
    frames: list = dataclasses.field(default_factory=list)  # the frames mapped into it (run positions)
    lo: np.ndarray | None = None  # [3] float64 local-frame bounds of what it can answer (None: nothing yet)
    hi: np.ndarray | None = None
    step: int = -1                # its checkpoint `<dir>/<id>/<step>` (-1: not written)

    def to_json(self) -> dict:
        f = lambda a: None if a is None else np.asarray(a, np.float64).tolist()  # noqa: E731
        return {"id": self.id, "anchor": f(self.anchor), "pose": f(self.pose),
                "path": f(np.reshape(self.path, (-1, 3))),
                "frames": [int(i) for i in self.frames], "lo": f(self.lo), "hi": f(self.hi), "step": int(self.step)}

    @classmethod
    def from_json(cls, d: dict) -> "SubmapInfo":
        a = lambda x: None if x is None else np.asarray(x, np.float64)  # noqa: E731
        return cls(id=int(d["id"]), anchor=a(d["anchor"]), pose=a(d["pose"]),
                   path=[np.asarray(p, np.float64) for p in d["path"]], frames=list(d["frames"]),
                   lo=a(d["lo"]), hi=a(d["hi"]), step=int(d["step"]))

    def world_path(self) -> np.ndarray:
        """[K, 3] float64 world positions of its frames."""
        return to_world(self.pose, np.reshape(np.asarray(self.path, np.float64), (-1, 3)))

    def world_bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(lo, hi) [3] float64 of the world box around its bounds (None: it holds nothing)."""
        if self.lo is None:
            return None
        corners = np.array([[x, y, z] for x in (self.lo[0], self.hi[0]) for y in (self.lo[1], self.hi[1])
                            for z in (self.lo[2], self.hi[2])])
        w = to_world(self.pose, corners)
        return w.min(0), w.max(0)


def to_local(pose: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """World points [N, 3] into the frame of a submap at pose T_world_local [4, 4] (float64)."""
    T = np.asarray(pose, np.float64)
    return (np.asarray(points_w, np.float64) - T[:3, 3]) @ T[:3, :3]


def to_world(pose: np.ndarray, points_l: np.ndarray) -> np.ndarray:
    """Points [N, 3] of a submap's frame into the world (pose T_world_local [4, 4], float64)."""
    T = np.asarray(pose, np.float64)
    return np.asarray(points_l, np.float64) @ T[:3, :3].T + T[:3, 3]


def blend_weights(dist: np.ndarray, valid: np.ndarray, band: float) -> np.ndarray:
    """Weights [N, K] of K submaps at N points: dist [N, K] float, the point's distance to each submap's
    sensor path (inf: the submap does not hold the point); valid [N, K] bool, the submap answers there.
    The nearest valid submap weighs 1, each other valid one 1 - (its distance - the nearest's) / band,
    at least 0 (band 0: the nearest alone); invalid ones 0. A row without a valid submap is all 0."""
    d = np.where(valid, dist, np.inf)
    dmin = d.min(axis=1, keepdims=True)
    with np.errstate(invalid="ignore"):
        if band > 0:
            w = np.clip(1.0 - (d - dmin) / band, 0.0, 1.0)
        else:
            w = (d <= dmin).astype(np.float64)
    return np.where(np.isfinite(d) & np.isfinite(dmin), w, 0.0)


def state_bounds(static: N3Static, state: N3State) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
    """(lo, hi) [3] float64 local-frame box around the state's leaf voxels and their level-`mask_level`
    parents (what a query can find valid), or (None, None) for an empty map."""
    n = int(state.voxels.count)
    if n == 0:
        return None, None
    c = np.asarray(state.voxel_coord[:n]).astype(np.int64)
    k = 1 << static.mask_level
    lo = np.floor_divide(c.min(0), k) * k
    hi = (np.floor_divide(c.max(0), k) + 1) * k
    o = origin_world(static, state)
    return lo * static.leaf + o, hi * static.leaf + o


class Submaps:
    """The submaps of one map: their index, the states held in memory (least recently used first) and
    their files. `live()` gives the state of the submap being mapped (`active`), which the mapper holds."""

    def __init__(self, static: N3Static, cfg, directory: str, live=None):
        self.static, self.cfg, self.dir = static, cfg, directory
        self.infos: list[SubmapInfo] = []
        self.active: int | None = None
        self.live = live
        self.states: collections.OrderedDict[int, N3State] = collections.OrderedDict()
        self.limit = max(int(cfg.submaps.resident), 1)
        self._trees: dict = {}

    # ---- the index ---------------------------------------------------------------------------------
    def index(self) -> dict:
        """The index as JSON (the run's checkpoint holds it, with the submaps' folder: `SubmapMapper.save`)."""
        return {"active": self.active, "submaps": [i.to_json() for i in self.infos]}

    def restore(self, index: dict) -> None:
        self.infos = [SubmapInfo.from_json(d) for d in index["submaps"]]
        self.active = index["active"]

    def on_disk(self) -> int:
        return sum(1 for i in self.infos if i.step >= 0)

    def resident(self) -> int:
        return len(self.states) + (self.active is not None)

    # ---- mapping -----------------------------------------------------------------------------------
    def start(self, anchor_w: np.ndarray) -> int:
        """A new submap anchored at world position anchor_w [3] (its pose the identity); returns its id."""
        info = SubmapInfo(id=len(self.infos), anchor=np.asarray(anchor_w, np.float64).copy())
        self.infos.append(info)
        return info.id

    def switch_for(self, position_w: np.ndarray) -> int | None:
        """Where the frame at sensor position_w [3] (world) is mapped (`routing.next_submap`: None = the
        active submap; NEW = a new one; an id = that earlier submap), the submaps where they are now."""
        anchors = np.array([to_world(i.pose, i.anchor[None])[0] for i in self.infos])
        return next_submap(self.cfg.submaps.length_m, self.cfg.submaps.revisit, anchors, self.active,
                           self.infos[self.active].world_path(), position_w)

    def route(self) -> Route:
        """The `routing.Route` that goes on from the chain as it is (a resumed `jaxmap map`): the frames of a
        drive at known poses routed in the thread that uploads them. Refused once a submap has moved (a
        batch is made in the world's frame shifted, never rotated, as a moved submap's frame would be)."""
        if any(not np.array_equal(i.pose, np.eye(4)) for i in self.infos):
            raise ValueError("a map of submaps moved by a pose graph maps its frames with add_prepared (each "
                             "placed in its submap's frame), not with batches uploaded in the world's frame")
        sub = self.cfg.submaps
        path = self.infos[self.active].world_path() if self.infos else ()
        return Route(self.static, sub.length_m, sub.revisit, [i.anchor for i in self.infos], self.active, path)

    def move(self, k: int, pose: np.ndarray) -> None:
        """Place submap k at pose T_world_local [4, 4] (a pose graph moved it as a rigid body): its
        features are untouched, every reading of it (queries, mesh, paths, anchor) follows the pose."""
        self.infos[k].pose = np.asarray(pose, np.float64).copy()

    def record(self, position_w: np.ndarray, frame: int, again: bool = False) -> None:
        """The active submap maps the frame at sensor position_w [3] (world); again: a frame of it added
        again (its position is on the path already: appended, it would lengthen the path driven)."""
        info = self.infos[self.active]
        if not again:
            info.path.append(to_local(info.pose, np.asarray(position_w, np.float64)[None])[0])
        info.frames.append(int(frame))

    def park(self, k: int, state: N3State) -> None:
        """Submap k is left (its last frame mapped): its bounds noted, written to disk in the background
        (from its buffers: nothing changes it now) without its pair store, and its query view kept in
        memory while the limit allows. The store goes at once: it held the window's pairs, and the window
        (the sensor's range) has moved on to the next submap; a submap taken up again collects new ones.
        So the memory of a switch is the new submap and the old one's tables until they are written (a
        third less than both whole), not two whole maps."""
        info = self.infos[k]
        info.lo, info.hi = state_bounds(self.static, state)
        info.step = int(state.frame)
        st = state.store
        state = state.replace(store=window.create(1, st.block_size, st.slot_of_voxel.shape[0]))
        del st
        n3checkpoint.save_state_async(self._path(k), self.cfg, state, [], copy=False)
        self.states[k] = query_view(state)
        self.states.move_to_end(k)
        self._fit(self.limit - 1)

    def take(self, k: int, store_blocks: int) -> N3State:
        """The whole state of submap k, to be mapped again (the mapper holds it), its pair store empty with
        `store_blocks` blocks (the capacity of the one mapped before it: the same compiled program)."""
        self.states.pop(k, None)
        n3checkpoint.wait_for_saves()  # (its file may still be being written)
        state = self._read(k, full=True)
        return state.replace(store=window.grow(state.store, n_slots=max(store_blocks, state.store.n_slots)))

    # ---- reading -----------------------------------------------------------------------------------
    def state(self, k: int, limit: int | None = None) -> N3State:
        """Submap k's state (the live one for the active submap), read from disk when not resident; the
        least recently used are dropped beyond `limit` (default: the config's) resident submaps."""
        if k == self.active and self.live is not None:
            return self.live()
        if k in self.states:
            self.states.move_to_end(k)
            return self.states[k]
        self._fit((limit or self.limit) - self._live_held() - 1)  # room for it
        state = self._read(k)
        self.states[k] = state
        return state

    def _live_held(self) -> int:
        """1 when the submap being mapped is held (by the mapper, `live`), else 0: it counts in `limit`."""
        return int(self.active is not None and self.live is not None)

    def release(self) -> None:
        """Drop every resident state and the live one's reader (the map is over: `SubmapMapper.release`)."""
        self.live = None
        self._fit(0)

    def _fit(self, n: int) -> None:
        """Drop the least recently used resident states beyond n (each is on disk: `park` wrote it)."""
        dropped = False
        while len(self.states) > max(n, 0):
            self.states.popitem(last=False)
            dropped = True
        if dropped:
            hostmem.trim()

    def _path(self, k: int) -> str:
        return os.path.join(self.dir, f"{k:04d}")

    def _read(self, k: int, full: bool = False) -> N3State:
        """Submap k from its file: the whole state (full), or what a query reads (`query_view`)."""
        info = self.infos[k]
        if info.step < 0:
            raise RuntimeError(f"submap {k} was never written and is not in memory")
        ckpt = os.path.join(self._path(k), str(info.step))
        _, state, _ = n3checkpoint.load_state(ckpt if os.path.isdir(ckpt) else self._path(k))
        return state if full else query_view(state)

    def bounds(self, k: int):
        """World box (lo, hi) of submap k (the live one's from its state), None when it holds nothing."""
        info = self.infos[k]
        if k == self.active and self.live is not None:
            info.lo, info.hi = state_bounds(self.static, self.live())
        return info.world_bounds()

    def path_distance(self, k: int, points_w: np.ndarray) -> np.ndarray:
        """[N] float64 distance of world points [N, 3] to submap k's sensor path."""
        from scipy.spatial import cKDTree

        info = self.infos[k]
        key = (k, len(info.path), info.pose.tobytes())
        tree = self._trees.get(key)
        if tree is None:  # (the path grew or the submap moved: its older tree goes)
            self._trees = {kk: t for kk, t in self._trees.items() if kk[0] != k}
            tree = self._trees[key] = cKDTree(info.world_path())
        return tree.query(points_w, workers=-1)[0]

    def query_world(self, points_w, grad: bool = False, limit: int | None = None, known: tuple | None = None):
        """The blended SDF at world points [N, 3] -> (sdf [N] float32, valid [N] bool), or with `grad`
        (sdf [N], d sdf / d x [N, 3], valid [N]). A point is read from the submaps whose box holds it
        and whose path is within blend_m of the nearest such path; where none of those is valid, from
        the others that hold it; the valid readings are blended by `blend_weights`. known: (k, sdf [N],
        valid [N]) submap k's reading at the points, made already (not with `grad`)."""
        pts = np.asarray(points_w, np.float64).reshape(-1, 3)
        n = len(pts)
        band = float(self.cfg.submaps.blend_m)
        cands, inside = [], []
        for k in range(len(self.infos)):
            b = self.bounds(k)
            if b is None:
                continue
            m = np.all((pts >= b[0]) & (pts <= b[1]), axis=1)
            if m.any():
                cands.append(k)
                inside.append(m)
        sdf_out = np.zeros(n, np.float32)
        grad_out = np.zeros((n, 3), np.float32)
        if not cands:
            return (sdf_out, grad_out, np.zeros(n, bool)) if grad else (sdf_out, np.zeros(n, bool))
        c = len(cands)
        dist = np.full((n, c), np.inf)
        for j, k in enumerate(cands):
            dist[inside[j], j] = self.path_distance(k, pts[inside[j]])
        sdf = np.zeros((n, c), np.float32)
        valid = np.zeros((n, c), bool)
        g = np.zeros((n, c, 3), np.float32) if grad else None
        near = dist <= dist.min(axis=1, keepdims=True) + band
        for second in (False, True):
            # the second pass only where the first found no valid reading (evaluated after the first)
            read = ~near & ~np.any(valid, axis=1, keepdims=True) if second else near
            for j, k in enumerate(cands):
                idx = np.nonzero(read[:, j] & np.isfinite(dist[:, j]))[0]
                if len(idx) and known is not None and k == known[0]:
                    sdf[idx, j], valid[idx, j] = known[1][idx], known[2][idx]
                elif len(idx):
                    self._read_submap(k, pts[idx], idx, j, sdf, valid, g, limit)
            if valid.any(axis=1).all():
                break
        w = blend_weights(dist, valid, band)
        total = w.sum(axis=1)
        ok = total > 0
        wn = w / np.where(ok, total, 1.0)[:, None]
        sdf_out = np.sum(wn * sdf, axis=1).astype(np.float32)
        if grad:
            grad_out = np.einsum("nc,ncd->nd", wn, g).astype(np.float32)
            return sdf_out, grad_out, ok
        return sdf_out, ok

    def _read_submap(self, k, pts_w, idx, j, sdf, valid, g, limit) -> None:
        info = self.infos[k]
        state = self.state(k, limit)
        local = to_local(info.pose, pts_w)
        s, v = query_world(self.static, state, local, small_tail=True)
        sdf[idx, j], valid[idx, j] = s, v
        if g is not None:
            _, gl = query_world(self.static, state, local, grad=True, small_tail=True)
            g[idx, j] = gl @ np.asarray(info.pose, np.float64)[:3, :3].T

    # ---- the mesh ----------------------------------------------------------------------------------
    def mesh(self, res: float, min_component_faces: int):
        """Marching-cubes mesh of the blended zero level set (trimesh.Trimesh, world frame) on the world
        lattice of `res` (which must divide the leaf voxel size). Each lattice cell is meshed with the
        cells of the submap whose sensor path is nearest to it, one submap after another, each while it and
        its neighbours are in memory (at most resident + 4 submaps at once, `resident` again after); the
        pieces are welded. A submap's own cells far from every seam (`_owner`'s alone) are read from it
        alone (`_read_alone`), the rest through the blended query: the same values, without the other
        submaps' path distances and the blend where the blend has one submap to read."""
        from jaxmap.mesh import extract_mesh_groups

        static = self.static
        check_mesh_resolution(static.leaf, res)
        limit = self.limit + 4  # a submap and its neighbours (query views: ~100 MB each on the city)
        groups: dict[tuple[int, bool], list] = collections.defaultdict(list)
        for k in range(len(self.infos)):
            if self.bounds(k) is None:
                continue
            cells = self._cells_world(k, limit)
            if len(cells) == 0:
                continue
            owner, alone = self._owner(cells)
            alone &= (owner == k) & np.array_equal(self.infos[k].pose, np.eye(4))
            groups[(k, True)].append(cells[alone])
            for o in np.unique(owner[~alone]):
                groups[(int(o), False)].append(cells[~alone & (owner == o)])
        # the submaps in order, each's own cells first; a cell is meshed once: one its owner reads alone is
        # taken out of the owner's blended group (another submap's set brought it there too)
        keys = sorted(groups, key=lambda g: (g[0], not g[1]))
        cell_groups = {g: np.unique(np.concatenate(groups[g]), axis=0) for g in keys}
        for k, alone in keys:
            if alone and (k, False) in cell_groups:
                cell_groups[(k, False)] = _rows_not_in(cell_groups[(k, False)], cell_groups[(k, True)])
        cell_groups = [cell_groups[g] for g in keys]
        del groups

        def sdf_fn_of(g):
            k, alone = keys[g]
            if not alone:
                return lambda p: self.query_world(p, limit=limit)
            return lambda p: self._read_alone(k, p, limit)

        try:
            return extract_mesh_groups(sdf_fn_of, cell_groups, static.leaf, res,
                                       min_component_faces=min_component_faces)
        finally:  # back to `submaps.resident` once meshed (what the end of a run holds while it is evaluated)
            self._fit(self.limit - self._live_held())

    def _read_alone(self, k: int, points_w, limit: int):
        """`query_world` at world points [N, 3] that only submap k (unmoved) reads: its reading where valid and
        in its box, the blended query's (which falls back on the other submaps) elsewhere."""
        pts = np.asarray(points_w, np.float64).reshape(-1, 3)
        sdf, valid = query_world(self.static, self.state(k, limit), pts, small_tail=True)
        sdf, valid = np.array(sdf, np.float32), np.array(valid, bool)
        lo, hi = self.bounds(k)  # (a corner on the box's face, rounded to float32, may fall just outside it)
        valid &= np.all((pts >= lo) & (pts <= hi), axis=1)
        if not valid.all():  # (k's reading handed over: the blend's first pass reads no other submap there)
            bad = ~valid
            sdf[bad], valid[bad] = self.query_world(pts[bad], limit=limit, known=(k, sdf[bad], valid[bad]))
        return sdf, valid

    def _cells_world(self, k: int, limit: int) -> np.ndarray:
        """[M, 3] int64 world-lattice leaf cells that submap k meshes (its non-void leaves, with their
        level-`mask_level` parents' other leaves), as `extract_mesh_of` takes them."""
        static, info = self.static, self.infos[k]
        state = self.state(k, limit)
        n = int(state.voxels.count)
        coords = np.asarray(state.voxel_coord[:n])
        if static.evidence:
            coords = coords[~np.asarray(void_of(state.evidence, static.void_frames)[:n])]
        cells = mesh_cells(coords, static.mask_level).astype(np.int64) + np.asarray(state.origin_vox, np.int64)
        if np.allclose(info.pose, np.eye(4)):
            return cells
        # a moved submap: its cells land on the world lattice where their centres go
        centres = to_world(info.pose, (cells + 0.5) * static.leaf)
        return np.unique(np.floor(centres / static.leaf).astype(np.int64), axis=0)

    def _owner(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For world-lattice leaf cells [N, 3]: (owner [N] int, the submap whose sensor path is nearest to the
        cell's centre among those whose box holds it: a function of the cell alone, so a cell that several
        submaps hold is meshed once; alone [N] bool, every corner of the cell is nearer to the owner's path
        than to any other submap's by more than blend_m, so the blended query reads the owner alone there).
        A path distance moves by at most the half-diagonal h between the centre and a corner: alone holds
        when, at the centre, every other submap whose box grown by h holds it is farther than the owner
        by more than blend_m + 2 h."""
        centres = (cells + 0.5) * self.static.leaf
        h = 0.5 * np.sqrt(3.0) * self.static.leaf + 1e-3  # (+ the corners' rounding to float32, with room)
        best = np.full(len(centres), np.inf)
        owner = np.full(len(centres), -1)
        near1, near2 = np.full(len(centres), np.inf), np.full(len(centres), np.inf)  # two nearest, grown boxes
        near_id = np.full(len(centres), -1)
        for k in range(len(self.infos)):
            b = self.infos[k].world_bounds() if k != self.active else self.bounds(k)
            if b is None:
                continue
            m = np.nonzero(np.all((centres >= b[0] - h) & (centres <= b[1] + h), axis=1))[0]
            if len(m) == 0:
                continue
            d = self.path_distance(k, centres[m])
            inside = np.all((centres[m] >= b[0]) & (centres[m] <= b[1]), axis=1)
            better = inside & (d < best[m])
            best[m[better]] = d[better]
            owner[m[better]] = k
            first = d < near1[m]
            near2[m] = np.where(first, near1[m], np.minimum(near2[m], d))
            near_id[m[first]] = k
            near1[m] = np.where(first, d, near1[m])
        alone = (near_id == owner) & (near2 - near1 > float(self.cfg.submaps.blend_m) + 2 * h)
        return owner, alone


def _rows_not_in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rows of int64 a [M, 3] that are not rows of b [K, 3]."""
    if len(a) == 0 or len(b) == 0:
        return a
    lo = np.minimum(a.min(0), b.min(0))
    span = np.maximum(a.max(0), b.max(0)) - lo + 1
    key = lambda c: ((c[:, 0] - lo[0]) * span[1] + (c[:, 1] - lo[1])) * span[2] + (c[:, 2] - lo[2])  # noqa: E731
    return a[~np.isin(key(a), key(b))]
