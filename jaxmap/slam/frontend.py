"""Streaming SLAM front end: odometry, keyframes, loop closure and pose-graph optimisation.

Per frame (`FrontEnd.add_frame(points_s)`):
  1. odometry gives the current pose estimate: frame-to-frame ICP (`Odometry`) or KISS-ICP
     (`jaxmap.slam.kiss.KissOdometry`), as `odometry.method` says;
  2. the frame becomes a keyframe when enough frames/motion passed since the last keyframe; a
     keyframe stores its downsampled points + normals (sensor frame) and gets a pose-graph node, linked
     to the previous keyframe by an odometry edge (the odometry motion between them, with the
     information of the frame ICPs in between; a direct keyframe-to-keyframe ICP was tried and was
     less accurate than the chained frame-to-frame ICPs on the room: wider baseline, less overlap);
  3. on a keyframe, earlier keyframes near the current estimate are verified as loop closures; the
     first accepted one adds a loop edge and the graph is optimised. The current keyframe's correction
     is applied to the odometry, so the next frames continue from the optimised pose.
Non-keyframes are stored relative to their keyframe, so `trajectory()` moves them with it.
Poses are [4,4] float64 T_world_sensor; scans [N,3] float32 in the sensor frame.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from jaxmap.config.slam import EDGE_INFORMATION, FrontEndConfig
from jaxmap.geometry import compose, orthonormalize, pose_change, rotation_from_axis_angle, se3_inverse
from jaxmap.slam.level import Leveller
from jaxmap.slam.loops import LoopResult, find_candidates, verify
from jaxmap.slam.odometry import Scan, make_odometry
from jaxmap.slam.posegraph import PoseGraph

log = logging.getLogger("jaxmap")

WEAK_INFORMATION = np.eye(6)   # information of an edge from the motion prior alone (ICP failed)


def isotropic_information(info: np.ndarray) -> np.ndarray:
    """[6,6] information (open3d order: rotation, translation) -> diag(a I3, b I3), a and b the mean
    eigenvalues of its rotation and translation blocks.

    Why: open3d's ICP information counts correspondences under a point-to-point model; its cross terms
    say that a rotation about an axis and a translation across it are nearly interchangeable for points
    a few metres away, and the pose graph then pushes a loop's correction into exactly that combination.
    With depth noise that grows with range the real errors of an ICP edge are not shaped like that, and
    on the drifting room the cross terms made the optimised trajectory worse than odometry alone (see
    FrontEndConfig.edge_information). The per-block scale keeps each edge's overall confidence, and the
    balance of rotation and translation, that the ICP measured."""
    info = np.asarray(info, np.float64)
    a, b = np.trace(info[:3, :3]) / 3.0, np.trace(info[3:, 3:]) / 3.0
    return np.diag([a, a, a, b, b, b])


@dataclass(frozen=True)
class FrameResult:
    """What `FrontEnd.add_frame` did with one frame.

    index:          frame number (0-based, in the order frames were added)
    pose:           [4,4] current estimate T_world_sensor of this frame (after any optimisation)
    is_keyframe, keyframe_id: keyframe id, or -1 for a non-keyframe
    loop:           the accepted LoopResult, else the last rejected one, None if no candidate was verified
    optimized:      True when a loop was accepted and the pose graph optimised in this step
    keyframe_poses: [K,4,4] all keyframe poses after this step
    odometry_ok:    False when ICP odometry failed and the motion prior was kept
    timings:        seconds: odometry_s, loop_s, optimize_s (and refine_s with a `refine`)
    odometry_rel:   [4,4] the odometry's own motion from the previous frame (before any refinement)
    refined:        True when `refine` replaced the odometry pose of this frame
    """
    index: int
    pose: np.ndarray
    is_keyframe: bool
    keyframe_id: int
    loop: LoopResult | None
    optimized: bool
    keyframe_poses: np.ndarray
    odometry_ok: bool
    timings: dict
    odometry_rel: np.ndarray | None = None
    refined: bool = False


class FrontEnd:
    """Streaming front end; see the module docstring. `FrontEnd(cfg, initial_pose)`, then `add_frame` per scan."""

    leveller: Leveller | None = None   # (a front end pickled before levelling existed resumes without it)

    def __init__(self, cfg: FrontEndConfig | None = None, initial_pose: np.ndarray | None = None):
        self.cfg = cfg or FrontEndConfig()
        if self.cfg.edge_information not in EDGE_INFORMATION:
            raise ValueError(f"frontend.edge_information must be one of {', '.join(EDGE_INFORMATION)}, "
                             f"got {self.cfg.edge_information!r}")
        self.odometry = make_odometry(self.cfg.odometry, initial_pose)   # ICP or KISS-ICP (odometry.method)
        self.graph = PoseGraph()
        self.kf_scans: list[Scan] = []          # per keyframe: prepared points/normals, sensor frame
        self.kf_frame: list[int] = []           # per keyframe: its frame index
        self.frame_ref: list[tuple[int, np.ndarray]] = []   # per frame: (keyframe id, T_keyframe_frame)
        self.loops: list[tuple[int, int]] = []  # accepted loops (candidate keyframe, current keyframe)
        self._cooldown = 0
        self._cov_since_kf = np.zeros((6, 6))     # summed covariance of the frame steps since the last keyframe
        self.leveller = (Leveller(self.cfg.level_gain, self.cfg.level_reference_frames, self.odometry.pose)
                         if self.cfg.level_gain > 0 else None)

    # ---------------------------------------------------------------------------------------------
    def keyframe_poses(self) -> np.ndarray:
        """[K,4,4] float64 current keyframe poses (optimised after a loop)."""
        return np.stack(self.graph.poses) if self.graph.poses else np.zeros((0, 4, 4))

    def trajectory(self) -> np.ndarray:
        """[N,4,4] float64 pose of every frame: its keyframe's current pose @ its offset from it."""
        if not self.frame_ref:
            return np.zeros((0, 4, 4))
        return orthonormalize(np.stack([self.graph.poses[k] @ T for k, T in self.frame_ref]))

    def _is_keyframe(self, index: int, pose: np.ndarray) -> bool:
        cfg = self.cfg
        if not self.kf_frame:
            return True
        if index - self.kf_frame[-1] < cfg.keyframe_every:
            return False
        if cfg.keyframe_min_translation_m <= 0 and cfg.keyframe_min_rotation_deg <= 0:
            return True
        ang, dist = pose_change(self.graph.poses[-1], pose)  # (a threshold of 0 is not used: 0 would pass any motion)
        moved = cfg.keyframe_min_translation_m > 0 and dist >= cfg.keyframe_min_translation_m
        return moved or (cfg.keyframe_min_rotation_deg > 0 and np.degrees(ang) >= cfg.keyframe_min_rotation_deg)

    # ---------------------------------------------------------------------------------------------
    def add_frame(self, points_s: np.ndarray, refine=None, scan=None) -> FrameResult:
        """Process the next scan. points_s: [N,3] float32, sensor frame. Returns a FrameResult. scan: the
        odometry's `Scan(points_s, cfg.odometry)` (downsampled points and normals) if made ahead.

        refine: None, or fn(pose guess [4,4]) -> a better pose [4,4] or None (keep the guess), called
        after the odometry step and before the keyframe decision (e.g. tracking against a map): the
        refined pose becomes the frame's pose, the odometry continues from it (its next prediction and
        the keyframe's graph node use it) and the odometry edge keeps the ICP's information."""
        cfg = self.cfg
        index = len(self.frame_ref)
        timings = {"odometry_s": 0.0, "loop_s": 0.0, "optimize_s": 0.0}
        t0 = time.perf_counter()
        step = self.odometry.step(points_s, scan)
        timings["odometry_s"] = time.perf_counter() - t0
        rel = self.odometry.velocity.copy()
        pose, refined = step.pose, False
        if refine is not None:
            t0 = time.perf_counter()
            better = refine(step.pose)
            timings["refine_s"] = time.perf_counter() - t0
            if better is not None:
                pose, refined = self._adopt(step.pose, better), True
        if self.leveller is not None:   # after the refinement: the tracked pose holds the map's tilt
            pose = self._level(index, pose, scan if scan is not None else self.odometry.last, timings)
        if index > 0:
            info = step.information if step.ok else WEAK_INFORMATION
            # (+ a tiny ridge: a degenerate ICP information must not make the inverse blow up or fail)
            self._cov_since_kf = self._cov_since_kf + np.linalg.inv(info + 1e-6 * np.eye(6))
        if not self._is_keyframe(index, pose):
            k = len(self.graph) - 1
            self.frame_ref.append((k, compose(se3_inverse(self.graph.poses[k]), pose)))
            return FrameResult(index, pose, False, -1, None, False, self.keyframe_poses(), step.ok, timings, rel,
                               refined)

        scan = self.odometry.last
        k = self.graph.add_node(pose)
        if k > 0:
            self._link_keyframe(k)
        self._cov_since_kf = np.zeros((6, 6))
        self.kf_scans.append(scan)
        self.kf_frame.append(index)
        self.frame_ref.append((k, np.eye(4)))

        loop, optimized = None, False
        if self._cooldown > 0:
            self._cooldown -= 1
        else:
            t0 = time.perf_counter()
            loop = self._search_loop(k, pose)
            timings["loop_s"] = time.perf_counter() - t0
            if loop is not None and loop.accepted:
                t0 = time.perf_counter()
                pose = self._optimize(k)
                timings["optimize_s"] = time.perf_counter() - t0
                optimized = True
                self._cooldown = cfg.loop_cooldown
        return FrameResult(index, pose.copy(), True, k, loop, optimized, self.keyframe_poses(), step.ok, timings,
                           rel, refined)

    def _level(self, index: int, pose: np.ndarray, scan: Scan, timings: dict) -> np.ndarray:
        """Frame `index`'s pose turned by the leveller (the first frame's kept: it only sets the up), made
        the odometry's current pose (`jaxmap.slam.level`); its seconds in timings["level_s"]."""
        t0 = time.perf_counter()
        level = self.leveller(pose, scan.normals, turn=index > 0)
        if index > 0:
            pose = self._adopt(pose, level)
        timings["level_s"] = time.perf_counter() - t0
        return pose

    def _adopt(self, guess: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Make `pose` the odometry's current pose in place of its `guess`: the world correction moves
        the odometry (as a loop correction does) and the motion prior takes the refinement in."""
        pose = orthonormalize(np.asarray(pose, np.float64))
        self.odometry.correct(compose(pose, se3_inverse(guess)))
        self.odometry.velocity = compose(self.odometry.velocity, se3_inverse(guess) @ pose)
        return pose

    def _link_keyframe(self, k: int) -> None:
        """Add the odometry edge (k-1, k): the odometry motion between the two keyframes, with the
        information of the chained frame-to-frame ICPs (covariances added, frame rotations ignored)."""
        T = compose(se3_inverse(self.graph.poses[k - 1]), self.graph.poses[k])
        info = np.linalg.inv(self._cov_since_kf)
        self.graph.add_odometry(k - 1, k, T, self._edge_information(0.5 * (info + info.T)))

    def _edge_information(self, info: np.ndarray) -> np.ndarray:
        return isotropic_information(info) if self.cfg.edge_information == "isotropic" else info

    def _search_loop(self, k: int, pose: np.ndarray) -> LoopResult | None:
        """Verify loop candidates for keyframe k (nearest first); adds the first accepted loop edge."""
        lcfg = self.cfg.loops
        kp = self.keyframe_poses()
        last = None
        for c in find_candidates(kp, k, pose, lcfg):
            src, tgt = self.kf_scans[k], self.kf_scans[c]
            res = verify(src.points, src.normals, tgt.points, tgt.normals, se3_inverse(kp[c]) @ pose, lcfg)
            log.debug("loop candidate keyframe %d -> %d: %s", k, c, res.reason)
            last = res
            if res.accepted:
                T_rel = res.T_rel
                if self.leveller is not None and all(self.leveller.precise(self.kf_frame[i]) for i in (c, k)):
                    T_rel = self._levelled_loop(kp[c], pose, T_rel)
                self.graph.add_loop(c, k, T_rel, self._edge_information(res.information))
                self.loops.append((c, k))
                log.info("loop closed: keyframe %d (frame %d) -> keyframe %d (frame %d), fitness %.3f, RMSE %.4f m",
                         k, self.kf_frame[k], c, self.kf_frame[c], res.fitness, res.rmse)
                break
        return last

    def _levelled_loop(self, P_c: np.ndarray, P_k: np.ndarray, T_rel: np.ndarray) -> np.ndarray:
        """The loop edge T_rel [4, 4] (keyframe k's points into keyframe c's frame) with its tilt taken from
        the levelled poses P_c, P_k [4, 4] (the heading and the position stay the registration's); used
        where both keyframes' facades measure their tilt precisely (`Leveller.precise`).
        Why: the loop's scan-to-scan ICP (0.3 m voxels, a young keyframe against an old one) was 0.15 deg
        off in tilt on the 32-beam street, and the pose graph spread that over the whole chain back to
        the loop's start (levelled, the front end alone: every frame within 0.025 deg before the loop,
        0.02-0.15 deg after it; docs/slam.md). Where one scan's facades are noisy (2 cm range noise:
        ~80 mdeg) the registration's tilt is the better one and is kept."""
        up = self.leveller.up
        R_loop = P_c[:3, :3] @ T_rel[:3, :3]                 # keyframe k's world rotation as the loop says
        a, b = R_loop @ (P_k[:3, :3].T @ up), up           # where the loop puts k's up, where its facades do
        axis = np.cross(a, b)
        s = float(np.linalg.norm(axis))
        if s < 1e-12:
            return T_rel
        out = np.array(T_rel, np.float64)
        out[:3, :3] = P_c[:3, :3].T @ np.asarray(rotation_from_axis_angle(axis, np.arctan2(s, float(a @ b))),
                                                np.float64) @ R_loop
        return out

    def _optimize(self, k: int) -> np.ndarray:
        """Optimise the graph; move the odometry with keyframe k's correction. Returns keyframe k's pose."""
        cfg = self.cfg
        old = self.graph.poses[k].copy()
        corr = cfg.graph_max_corr_m if cfg.graph_max_corr_m is not None else cfg.loops.max_correction_m
        poses = self.graph.optimize(corr, edge_prune_threshold=cfg.edge_prune_threshold,
                                    preference_loop_closure=cfg.preference_loop_closure, reference_node=0)
        conf = self.graph.loop_confidence.get(len(self.graph.edges) - 1, 1.0)
        if conf < cfg.edge_prune_threshold:
            log.warning("loop edge keyframe %d -> %d was pruned by the pose-graph optimisation (confidence %.3f): "
                        "it disagrees with the odometry by more than graph_max_corr_m allows", k, self.loops[-1][0],
                        conf)
        self.odometry.correct(compose(poses[k], se3_inverse(old)))
        return poses[k].copy()
