"""Scan-to-scan odometry: point-to-plane ICP (open3d) with a constant-velocity motion prior.

Frames and conventions: scans are [N,3] float32 in their SENSOR frame; poses are [4,4] float64
T_world_sensor (p_w = R p_s + t). A relative transform `rel` from frame i-1 to frame i is
T_{i-1,i} = T_w_{i-1}^-1 @ T_w_i: it maps points of the newer scan into the older scan's frame, which
is exactly what ICP with source = newer scan and target = older scan estimates.

open3d is imported inside the functions, so `import jaxmap` (and the mapping core) works without it.
"""
from __future__ import annotations

import logging

import numpy as np

from jaxmap.config import ConfigError
from jaxmap.config.slam import ODOMETRY_METHODS
from jaxmap.geometry import compose, pose_change
from jaxmap.slam.kiss import KissOdometry
# The config, prepared scan, step result and open3d helpers live in odometry_common, the registrations
# (ICP, coarse-to-fine, FPFH + RANSAC) in registration (KISS-ICP shares them); they are imported from here too.
from jaxmap.slam.odometry_common import (OdometryConfig, OdomStep, Scan, odometry_points, quiet_open3d,  # noqa: F401
                                        to_o3d)
from jaxmap.slam.registration import IcpResult, global_register, icp, register  # noqa: F401 (re-exported)

log = logging.getLogger("jaxmap")


class Odometry:
    """Streaming frame-to-frame point-to-plane ICP odometry with a constant-velocity prior.

    Each new scan is registered to the previous scan, initialised with the previous relative motion
    (constant velocity); a poor fit triggers a global registration (see OdometryConfig).
    Frame-to-frame (not frame-to-local-map) keeps it simple; its drift on the synthetic data is small
    (about 3 cm over the 40-frame room loop, 0.3 m over the 70 m city loop) and the loop closure
    removes much of it.

    Usage: `odo = Odometry(cfg, initial_pose)`, then `odo.step(points_s)` per frame in order.
    After a pose-graph correction, `odo.correct(T_corr)` moves the current pose (T_world <- T_corr @ T_world).
    """

    def __init__(self, cfg: OdometryConfig | None = None, initial_pose: np.ndarray | None = None):
        self.cfg = cfg or OdometryConfig()
        self.pose = np.eye(4) if initial_pose is None else np.array(initial_pose, dtype=np.float64)
        self.velocity = np.eye(4)        # T_{i-1,i} of the last step, the motion prior
        self.prev: Scan | None = None    # the previous prepared scan (the ICP target)
        self.last: Scan | None = None    # the prepared scan of the last step (same as prev after step)
        self.n_frames = 0

    def step(self, points_s: np.ndarray, scan: Scan | None = None) -> OdomStep:
        """Register the next scan. points_s: [N,3] float32, sensor frame; scan: `Scan(points_s, cfg)` if
        made already (in a prefetch thread). Returns an OdomStep."""
        cfg = self.cfg
        scan = Scan(points_s, cfg) if scan is None else scan
        frame = self.n_frames
        self.n_frames += 1
        self.last = scan
        if self.prev is None:
            self.prev = scan
            return OdomStep(self.pose.copy(), np.eye(4), 1.0, 0.0, True, np.eye(6))
        prior = self.velocity
        if len(scan) < cfg.min_points or len(self.prev) < cfg.min_points:
            log.warning("odometry frame %d: too few points for ICP (%d and %d after downsampling, need %d); "
                        "keeping the constant-velocity motion", frame, len(scan), len(self.prev), cfg.min_points)
            res, ok = None, False
        else:
            res = register(scan, self.prev, prior, cfg)
            if res.fitness < cfg.retry_below_fitness:
                alt = global_register(scan, self.prev, cfg)
                if alt.fitness > res.fitness:
                    log.debug("odometry frame %d: global registration beat the motion prior (fitness %.3f > %.3f)",
                              frame, alt.fitness, res.fitness)
                    res = alt
            ok = res.fitness >= cfg.min_fitness and res.inlier_rmse <= cfg.max_rmse_m
            if not ok:
                ang, dist = pose_change(prior, res.T)
                log.warning("odometry frame %d: ICP failed (fitness %.3f < %.2f or RMSE %.4f m > %.4f m; "
                            "correction %.3f m / %.2f deg); keeping the constant-velocity motion", frame,
                            res.fitness, cfg.min_fitness, res.inlier_rmse, cfg.max_rmse_m, dist, np.degrees(ang))
        rel = res.T if ok else prior.copy()
        self.velocity = rel
        self.pose = compose(self.pose, rel)   # re-orthonormalised: chained products drift off SO(3) otherwise
        self.prev = scan
        return OdomStep(self.pose.copy(), rel.copy(), res.fitness if res else 0.0, res.inlier_rmse if res else np.inf,
                        ok, res.information if ok else np.eye(6))

    def correct(self, T_corr: np.ndarray) -> None:
        """Apply a world-frame correction (e.g. from a pose-graph optimisation): pose <- T_corr @ pose.

        The velocity (a relative motion) is unchanged, so tracking continues smoothly from the new pose."""
        self.pose = compose(T_corr, self.pose)




def make_odometry(cfg: OdometryConfig | None = None, initial_pose: np.ndarray | None = None):
    """The odometry `cfg.method` names: `Odometry` ("icp") or `jaxmap.slam.kiss.KissOdometry` ("kiss_icp").

    Both have step(points_s) -> OdomStep, correct(T_corr), and the attributes pose, velocity, last (the
    prepared Scan of the last step), n_frames. ConfigError for an unknown method."""
    cfg = cfg or OdometryConfig()
    if cfg.method == "icp":
        return Odometry(cfg, initial_pose)
    if cfg.method == "kiss_icp":
        return KissOdometry(cfg, initial_pose)
    raise ConfigError(f"frontend.odometry.method: unknown odometry {cfg.method!r}; use one of "
                      + ", ".join(repr(m) for m in ODOMETRY_METHODS))
