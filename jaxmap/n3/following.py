"""An N3 map that follows pose corrections: `FollowingMap.correct(poses)`.

A SLAM run maps each frame at the pose it has then; a loop closure later moves those poses. The map
follows with one call whatever it is made of, as the latent map does with `ImtMapper.correct`:

    fm = FollowingMap(mapper, FollowRule.of(slam_cfg), ScanStore(run_dir / "slam_scans"))
    n, finished = fm.add(prepared_scan, pose)        # frame len(fm) mapped at pose [4, 4] (world)
    record = fm.correct(poses)                        # poses [N, 4, 4]: every frame's, in the order added
    seconds = fm.readd(1, poses)                      # after each next frame: re-add one queued frame
    finished += fm.take_finished()                    # the map's records of frames finished meanwhile

How it follows (`FollowRule.mode`, the SLAM config's `n3_loop`):
  - one grid (`N3Mapper`): `moved` queues the frames whose position moved more than `min_move_m`, largest
    move first, and `readd` re-adds them a few at a time (each removes its frame's old training pairs,
    `N3Mapper.forget_frames`, and maps the frame again at its new pose); with `readd_per_frame` 0 they are
    re-added at once. `rebuild` empties the map and maps every frame again; `none` leaves it (an ablation);
  - submaps (`SubmapMapper`, mode `submaps`): each submap is moved as a rigid body to the pose that fits
    its frames' corrections best (`submap_pose`), and the frames of the submap being mapped that its move
    leaves more than `min_move_m` from their poses are queued to be re-added.
The map keeps what following needs: each frame's prepared scan (sensor frame, `ScanStore`), the pose it
was mapped at (in its submap's frame with submaps, else the world's), its number in the map (its training
pairs carry it) and its submap.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import time

import numpy as np

from jaxmap.geometry import orthonormalize
from jaxmap.n3.scan import PreparedScan
from jaxmap.n3.scan_store import ScanStore

log = logging.getLogger("jaxmap")


@dataclasses.dataclass(frozen=True)
class FollowRule:
    """How an N3 map follows a pose correction (the SLAM config's `n3_loop*` keys)."""

    mode: str = "moved"          # submaps | moved | rebuild | none
    min_move_m: float = 0.02     # a frame moved less than this stays as mapped
    readd_per_frame: int = 1     # queued frames re-added after each next frame (0: all at the correction)
    readd_iters: int = 0         # training iterations of a re-added frame (0: the map's train.iters)

    @classmethod
    def of(cls, cfg) -> "FollowRule":
        """The rule of a `SlamConfig`."""
        return cls(cfg.n3_loop, cfg.n3_loop_min_move_m, cfg.n3_loop_readd_per_frame, cfg.n3_loop_readd_iters)


def pose_moved(a: np.ndarray, b: np.ndarray) -> float:
    """Distance (m) between the positions of two poses [4,4]."""
    return float(np.linalg.norm(np.asarray(a)[:3, 3] - np.asarray(b)[:3, 3]))


def submap_pose(world: np.ndarray, local: np.ndarray) -> np.ndarray:
    """T_world_local [4, 4] of the rigid body that best carries a submap's frames from their poses in its
    frame, local [K, 4, 4], to their (optimised) world poses world [K, 4, 4]: the rotation is the chordal
    mean of the frames' R_world R_local^T, the translation the mean of t_world - R t_local (least squares
    for that rotation). With one frame, or a correction that is rigid over the submap, it is exact."""
    world, local = np.asarray(world, np.float64), np.asarray(local, np.float64)
    M = np.einsum("kij,klj->il", world[:, :3, :3], local[:, :3, :3])   # sum_k R_w,k R_l,k^T
    T = np.eye(4)
    T[:3, :3] = orthonormalize(M)
    T[:3, 3] = np.mean(world[:, :3, 3] - local[:, :3, 3] @ T[:3, :3].T, axis=0)
    return T


class FollowingMap:
    """An N3 map (`N3Mapper` or `SubmapMapper`) with its frames, so that it can follow pose corrections
    (see the module docstring). Pickled, it keeps the frames and the queue, not the map (saved beside)."""

    readds = pairs_removed = 0   # (a map pickled before these were counted resumes with them at 0)

    def __init__(self, mapper, rule: FollowRule, scans: ScanStore | None = None):
        self.mapper, self.rule = mapper, rule
        self.scans = scans if scans is not None else ScanStore()   # per frame: its PreparedScan (sensor frame)
        self.mapped_at: list[np.ndarray] = []    # per frame: the pose its pairs are in the map at (in its
                                                 # submap's frame with mode submaps, else the world's)
        self.counter: list[int] = []             # per frame: its number in its map (pairs carry it)
        self.submap: list[int] = []              # per frame: its submap (0: one grid)
        self.pending: list[int] = []             # frames a correction moved, to re-add (`readd`)
        self.readds = 0                          # frames re-added after corrections, and the old pairs they removed
        self.pairs_removed = 0
        self._finished: list = []                # the map's (record, kept) of frames finished, not yet taken

    def __len__(self) -> int:
        return len(self.scans)

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k not in ("mapper", "_finished")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.mapper, self._finished = None, []   # (the run sets the map loaded beside it)

    def take_finished(self) -> list:
        """The map's records ((record, kept) each, oldest first) of the frames that finished since the last
        call: new frames' and re-adds' alike."""
        out, self._finished = self._finished, []
        return out

    def settle(self) -> None:
        """Wait for every map frame in flight."""
        self._finished += self.mapper.finish()

    def add(self, prepared: PreparedScan, pose: np.ndarray) -> int:
        """Map a new frame (number len(self)) at world pose [4, 4], dispatched without waiting for it.
        Returns its number in the map (its record's "frame")."""
        self.scans.append(prepared)
        self.mapped_at.append(None)
        self.counter.append(0)
        self.submap.append(0)
        return self._map(len(self.scans) - 1, pose, wait=False)

    def _map(self, i: int, pose: np.ndarray, wait: bool = True, **kw) -> int:
        """Map frame i at world pose [4, 4], finished before it returns unless not `wait`; notes where its
        pairs went (submap, number, pose in the submap's frame). Returns its number in the map."""
        placed, done = self.mapper.submit_prepared(self.scans[i], pose, **kw)
        self._finished += done
        if wait:
            self.settle()
        self.submap[i] = int(placed.get("submap") or 0)
        self.counter[i] = int(placed["frame"] if placed.get("submap_frame") is None else placed["submap_frame"])
        S = self.mapper.submaps.infos[self.submap[i]].pose if self.rule.mode == "submaps" else np.eye(4)
        self.mapped_at[i] = np.linalg.inv(S) @ pose
        return int(placed["frame"])

    @contextlib.contextmanager
    def _readding(self):
        """Frames mapped inside are re-adds: `readd_iters` training iterations each (0: train.iters)."""
        n = self.rule.readd_iters
        if n <= 0:
            yield
            return
        self.mapper.set_iters(n)
        try:
            yield
        finally:
            self.mapper.set_iters(self.mapper.cfg.train.iters)

    def readd(self, n: int, poses: np.ndarray) -> float:
        """Re-add up to n queued frames at their poses in poses [N, 4, 4] (with submaps, those still in the
        submap being mapped; the others stay where their submap's move put them). Returns the seconds."""
        t0 = time.perf_counter()
        submaps = self.rule.mode == "submaps"
        with self._readding():
            for _ in range(n):
                while submaps and self.pending and self.submap[self.pending[0]] != self.mapper.submaps.active:
                    self.pending.pop(0)
                if not self.pending:
                    break
                i = self.pending.pop(0)
                self.pairs_removed += int(self.mapper.forget_frames([self.counter[i]]))
                self._map(i, poses[i], **({"stay": True} if submaps else {}))
                self.readds += 1
        return time.perf_counter() - t0

    def correct(self, poses: np.ndarray) -> dict:
        """Follow the corrected poses [N, 4, 4] of the frames mapped so far (in the order added), by the
        rule's mode. Returns the correction's record: how far the frames moved, what was queued or re-added,
        and "map_s", the seconds it took here (queued re-adds run later, in `readd`)."""
        self.settle()
        poses = np.asarray(poses, np.float64)
        if self.rule.mode == "submaps":
            return self._move_submaps(poses)
        moves = np.array([pose_moved(a, b) for a, b in zip(self.mapped_at, poses)])
        mode, mapper = self.rule.mode, self.mapper
        moved = [i for i in range(len(poses)) if moves[i] > self.rule.min_move_m]
        t0 = time.perf_counter()
        if mode == "moved" and self.rule.readd_per_frame > 0:
            # spread over the next frames, largest move first (the map's worst places are mended first);
            # each re-add removes its frame's old pairs then, so the map keeps every frame meanwhile
            queued = [i for i in sorted(moved, key=lambda i: -moves[i]) if i not in self.pending]
            self.pending.extend(queued)
            return self._record(mode, moves, t0, {"queued": len(queued)}, queued)
        # rebuild: every frame again, once any moved; moved: only those, at once
        redo = {"rebuild": list(range(len(poses))) if moved else [], "moved": moved}.get(mode, [])
        if mode == "rebuild" and redo:
            mapper.reset()
        removed = mapper.forget_frames([self.counter[i] for i in redo]) if mode == "moved" else 0
        with self._readding():
            for i in redo:
                self._map(i, poses[i])
        return self._record(mode, moves, t0, {"reintegrated": len(redo), "pairs_removed": removed}, redo)

    def _move_submaps(self, poses: np.ndarray) -> dict:
        """Mode `submaps`: each submap moved as a rigid body to fit its frames' corrected poses
        (`submap_pose`); the frames of the submap being mapped left more than min_move_m from where their
        submap's move put them are queued to be re-added."""
        t0 = time.perf_counter()
        local, sub = np.stack(self.mapped_at), np.asarray(self.submap)
        infos = self.mapper.submaps.infos
        before = np.stack([infos[k].pose @ L for k, L in zip(sub, local)])
        fits = {int(k): submap_pose(poses[sub == k], local[sub == k]) for k in np.unique(sub)}
        shifts = [pose_moved(infos[k].pose, T) for k, T in fits.items()]
        self.mapper.move_submaps(fits)
        after = np.stack([fits[int(k)] @ L for k, L in zip(sub, local)])
        moves = np.linalg.norm(before[:, :3, 3] - poses[:, :3, 3], axis=1)
        left = np.linalg.norm(after[:, :3, 3] - poses[:, :3, 3], axis=1)
        beyond = left > self.rule.min_move_m
        active = self.mapper.submaps.active
        queued = [i for i in np.nonzero(beyond & (sub == active))[0] if i not in self.pending]
        self.pending.extend(int(i) for i in queued)
        return self._record("submaps", moves, t0, {
            "submaps": len(fits), "submaps_moved": int(sum(d > self.rule.min_move_m for d in shifts)),
            "submap_max_shift_m": float(max(shifts)),
            "left_max_m": float(left.max()), "left_median_m": float(np.median(left)),
            "queued": len(queued), "left_beyond_elsewhere": int((beyond & (sub != active)).sum())}, queued)

    @staticmethod
    def _record(mode, moves, t0, extra, redo) -> dict:
        rec = {"mode": mode, "frames": len(moves), **extra,
               "max_move_m": float(moves.max()), "median_move_m": float(np.median(moves)),
               "map_s": time.perf_counter() - t0}
        (log.info if redo else log.debug)(
            "pose correction: the frames moved by up to %.3f m (median %.3f m); n3_loop %s re-integrated (or "
            "queued) %d of %d frames in %.1f s", rec["max_move_m"], rec["median_move_m"], mode, len(redo),
            len(moves), rec["map_s"])
        return rec
