"""`jaxmap slam` with `map_kind: imt`: the steps whose map is the transformable latent map (`ImtMapper`).

`ImtSlamStep`: per frame, the front end (`FrontEnd`: ICP odometry, keyframes, loop verification, open3d
pose graph) gives the pose; a keyframe is encoded and fused into the latent map at it; when a loop is
accepted and the graph optimised, the map follows the optimised keyframe poses with one call,
`ImtMapper.correct` (only the keyframes whose pose moved are remapped); with `mesh_at_loops` a mesh is
written before and after (`loop_<n>_before.ply`, `loop_<n>_after.ply`).

`SnapshotStep` (`external_poses: DIR`): pose-graph snapshots of another SLAM system replace the front
end (one TUM or KITTI file per keyframe update, in natural order, as ORB-SLAM2 writes them; snapshot i
holds the poses of the first n_i frames of the selection): new frames are fused at their snapshot pose,
and earlier keyframes are remapped as each snapshot arrives.

Both are `jaxmap.runs.slam_step.SlamStep`s: `jaxmap.runs.slam.run_slam` drives, saves and resumes them
as it does the N3 map's.
"""
from __future__ import annotations

import logging
import os
import re
import time

import numpy as np

from jaxmap.errors import DataError
from jaxmap.frame_loop import Frame
from jaxmap.imt.mapper import ImtMapper
from jaxmap.runs.slam_step import SlamFrame, SlamStep, show_loop
from jaxmap.slam.frontend import FrontEnd
from jaxmap.slam.odometry_common import Scan
from jaxmap.slam.trajectory import read_pose_snapshot

log = logging.getLogger("jaxmap")


class LatentMapStep(SlamStep):
    """What the latent map's steps share: its keyframes are the frames it holds."""

    map_kind = "imt"

    def keyframe_frames(self, seq) -> list[int]:
        return [int(f) for f in self.mapper.store.frames]

    def mapped(self) -> str:
        return f"{len(self.mapper.store)} keyframes"


class ImtSlamStep(LatentMapStep):
    """The front end estimates each frame's pose; a keyframe is fused into the latent map at it; an
    accepted loop remaps the map to the optimised keyframe poses (see the module docstring)."""

    label = "slam"

    def __init__(self, cfg, initial_pose: np.ndarray):
        super().__init__(cfg, FrontEnd(cfg.frontend, initial_pose=initial_pose))

    def _submit(self, frame: SlamFrame) -> list:
        mapper = self.mapper
        r = self.front_end(frame)
        if r.is_keyframe:
            ready = frame.prepared if frame.prepared is not None else mapper.prepare(frame.points)
            mapper.add_prepared(ready, r.pose, frame=frame.index, pose_source="jaxmap's SLAM front end")
            if r.optimized:
                self.loops.append(self._close_loop(r.keyframe_poses,
                                                   {"frame": frame.index, "keyframe": int(r.keyframe_id),
                                                    "optimize_s": r.timings["optimize_s"],
                                                    "fitness": float(r.loop.fitness), "rmse_m": float(r.loop.rmse)}))
        record = dict(r.timings, kf=len(mapper.store), loops=len(self.loops), ok=r.odometry_ok)
        if r.is_keyframe and mapper.timings:
            record.update({k: v for k, v in mapper.timings[-1].items() if k.endswith("_s")})
        if r.optimized:
            show_loop(self.viewer, self.fe, r)
        self.records.append(record)
        return [(frame, record, r.pose)]

    def _close_loop(self, poses: np.ndarray, record: dict) -> dict:
        """The map follows the optimised keyframe poses (`ImtMapper.correct`); the loop's record."""
        mapper, n, mesh_at = self.mapper, len(self.loops), self.cfg.mesh_at_loops and self.out_dir is not None
        if mesh_at:
            mapper.mesh().export(os.path.join(self.out_dir, f"loop_{n}_before.ply"))
        corrected = mapper.correct(poses)
        record.update(remap_s=corrected.pop("map_s"), **corrected)
        if mesh_at:
            mapper.mesh().export(os.path.join(self.out_dir, f"loop_{n}_after.ply"))
        log.info("loop %d at frame %d: optimised in %.2f s, %d of %d keyframes remapped in %.2f s", n,
                 record["frame"], record.get("optimize_s", 0.0), record["keyframes_moved"], record["keyframes"],
                 record["remap_s"])
        return record

    def load_frame(self, seq, i: int) -> SlamFrame:
        """`Prefetcher` loader: read, the odometry's scan prepared and, when every frame is a keyframe,
        the map's preprocessing too (else the keyframes' is done as they are decided)."""
        fr = seq.frame(i)
        fe = self.cfg.frontend
        every = fe.keyframe_every <= 1 and fe.keyframe_min_translation_m <= 0 and fe.keyframe_min_rotation_deg <= 0
        return SlamFrame(i, int(fr.index), fr.points, fr.pose, prepared=self.mapper.prepare(fr.points) if every else None,
                         odometry_scan=Scan(fr.points, fe.odometry))

    @staticmethod
    def progress(record: dict) -> dict:
        return {"kf": record["kf"], "loops": record["loops"], "ok": record["ok"]}


def open_imt_step(cfg, seq) -> tuple[ImtMapper, SlamStep]:
    """A new run's (latent map, step): the front end's step, or with `external_poses` the snapshots'."""
    if cfg.external_poses:
        step = SnapshotStep(cfg, read_snapshots(cfg.external_poses, len(seq)))
    else:
        step = ImtSlamStep(cfg, np.asarray(seq.poses[0], np.float64))
    return ImtMapper(cfg.imt()), step


def snapshot_files(directory: str) -> list[str]:
    """Pose snapshot files of `directory` in natural order (`kf_2.txt` before `kf_10.txt`)."""
    if not os.path.isdir(directory):
        raise DataError(f"external_poses: {directory} is not a directory of pose snapshots")
    names = [n for n in os.listdir(directory) if n.endswith(".txt")]
    if not names:
        raise DataError(f"external_poses: {directory} has no .txt pose snapshots (TUM or KITTI, one per update)")
    key = lambda s: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]  # noqa: E731
    return [os.path.join(directory, n) for n in sorted(names, key=key)]


def read_snapshots(directory: str, frames: int) -> list[tuple[str, np.ndarray]]:
    """(path, poses [n_i, 4, 4]) of every pose snapshot of `directory` in order, checked: each covers at
    most the `frames` of the selection and at least every frame of the snapshots before it."""
    out, covered = [], 0
    for path in snapshot_files(directory):
        poses = read_pose_snapshot(path)
        if len(poses) > frames:
            raise DataError(f"{path}: {len(poses)} poses but the sequence selection has {frames} frames")
        if len(poses) < covered:
            raise DataError(f"{path}: {len(poses)} poses, fewer than the {covered} frames of the "
                            "previous snapshots; each snapshot must cover every frame fused so far")
        out.append((path, poses))
        covered = len(poses)
    return out


class SnapshotStep(LatentMapStep):
    """Another SLAM system's pose snapshots drive the map: before the first frame that snapshot i adds,
    the map is remapped to snapshot i's poses (and to those of the snapshots before it that added no
    frame); the frame is fused at its snapshot pose. Once the last frame is in, the snapshots left (those
    that add no frame) are applied. `loops` holds one record per snapshot applied."""

    label = "slam (external poses)"

    def __init__(self, cfg, snapshots: list[tuple[str, np.ndarray]]):
        super().__init__(cfg)
        self.snapshots = snapshots
        self.applied = 0                 # snapshots whose remap is done
        self.fused = 0                   # frames fused

    @property
    def frames_done(self) -> int:
        return self.fused

    @property
    def frames_held(self) -> int:
        """The frames the snapshots hold: the run's frames."""
        return len(self.snapshots[-1][1]) if self.snapshots else 0

    def frames_to_run(self, seq) -> int:
        return self.frames_held

    def _apply(self, n: int) -> None:
        """Remap to snapshot n's poses of the frames fused so far."""
        path, poses = self.snapshots[n]
        mapper, fused = self.mapper, len(self.mapper.store)
        t0 = time.perf_counter()
        changed = mapper.remap(poses[:fused]) if fused else []
        self.loops.append({"snapshot": os.path.basename(path), "poses": len(poses), "remapped": changed,
                           "added": len(poses) - fused, "remap_s": time.perf_counter() - t0})
        self.applied = n + 1

    def _submit(self, frame: Frame) -> list:
        k = frame.position
        while self.applied == 0 or len(self.snapshots[self.applied - 1][1]) <= k:
            self._apply(self.applied)
        pose = self.snapshots[self.applied - 1][1][k]
        record = self.mapper.add_prepared(frame.prepared, pose, frame=frame.index)
        self.fused += 1
        self.records.append(record)
        return [(frame, record, pose)]

    def drain(self) -> list:
        """Once every frame is fused (not when a stop drains the loop early): the snapshots left."""
        if self.fused >= self.frames_held:
            while self.applied < len(self.snapshots):
                self._apply(self.applied)
        return []

    def load_frame(self, seq, i: int) -> SlamFrame:
        """`Prefetcher` loader: read, and the map's preprocessing of it (its pose, and so its cells, is
        known only when its snapshot is applied)."""
        fr = seq.frame(i)
        return SlamFrame(i, int(fr.index), fr.points, fr.pose, prepared=self.mapper.prepare(fr.points))

    def results(self, seq) -> dict:
        poses = self.snapshots[-1][1] if self.snapshots else np.zeros((0, 4, 4))
        return {"trajectory": poses, "odometry": None, "loops": self.loops,
                "keyframe_frames": self.keyframe_frames(seq)}
