"""KISS-ICP (Vizzo et al., "KISS-ICP: In Defense of Point-to-Point ICP", RA-L 2023) as jaxmap's odometry.

`KissOdometry` wraps `kiss_icp.kiss_icp.KissICP` (`pip install kiss-icp`) behind the interface of
`jaxmap.slam.odometry.Odometry`, so the front end (`FrontEnd`, `jaxmap slam`) uses either one by
`frontend.odometry.method` ("icp" or "kiss_icp"). KISS-ICP registers each scan to a voxel-hashed local
map (not to the previous scan) with a constant-velocity prediction and an adaptive correspondence
threshold; its parameters come from the OdometryConfig: range crop (min_range_m, max_range_m), the
local-map voxel (kiss_voxel_m, 0 = max_range_m / 100 as KISS-ICP's default) and the initial threshold
(kiss_initial_threshold_m, see below). Deskewing is off (jaxmap frames have no per-point times).

The first step is seeded. KISS-ICP predicts each motion from the last one (constant velocity), and for
the second scan it has none: it starts from no motion, against a local map of one scan, with a wide
kernel (its initial threshold, 2.0 m), where its point-to-point ICP converges short of the true motion
(the beams' rings on the road move with the sensor and pull towards no motion). On the 10 Hz small city
(0.97 m steps, 2 cm noise) its first step measured 0.58 m, a lag the rest of the drive keeps as an
offset without drifting (KISS-ICP's own pipeline does the same: it is not this wrapper). So the second
scan's prediction is jaxmap's frame-to-frame ICP of the two scans (`jaxmap.slam.registration.register`
from no motion, FPFH + RANSAC where it fits below retry_below_fitness), set as KISS-ICP's last motion
before it registers the scan, and KISS-ICP's threshold starts at kiss_initial_threshold_m (0.3 m) instead
of 2.0 m; where no registration of the two scans fits, KISS-ICP starts from no motion with its own 2.0 m.
Odometry ATE on the city / small city: 16.1 / 54.2 cm unseeded, 2.8 / 9.6 cm seeded (docs/slam.md).

KISS-ICP keeps its own trajectory, starting at the identity. The world pose of frame i is
C @ T0 @ K_i, with T0 the initial pose and C the accumulated pose-graph corrections (`correct`), so a
loop closure moves the estimate without disturbing KISS-ICP's local map.

For the pose graph each step also gets what `Odometry` gives: fitness, inlier RMSE and the 6x6
information of the relative motion, from the prepared scans (`Scan`, voxel_m / normals as for ICP)
of this frame and the previous one (open3d's evaluate_registration / information matrix at
max_corr_m). A step whose fitness or RMSE fails min_fitness / max_rmse_m is reported with ok=False
and a weak information; its motion is still KISS-ICP's (the local map already holds the scan).
"""
from __future__ import annotations

import logging

import numpy as np

from jaxmap.errors import JaxmapError
from jaxmap.geometry import compose, orthonormalize
from jaxmap.slam.odometry_common import OdometryConfig, OdomStep, Scan, quiet_open3d, to_o3d
from jaxmap.slam.registration import global_register, register

log = logging.getLogger("jaxmap")
KISS_INITIAL_THRESHOLD_M = 2.0  # KISS-ICP's own initial threshold, for a first step from no motion


def kiss_config(cfg: OdometryConfig):
    """The KISSConfig of an OdometryConfig (range crop, local-map voxel, initial threshold, no deskewing)."""
    try:
        from kiss_icp.config import KISSConfig
    except ImportError:
        raise JaxmapError("frontend.odometry.method is 'kiss_icp' but the kiss-icp package is not installed; "
                          "pip install kiss-icp (or set frontend.odometry.method=icp)") from None
    kc = KISSConfig()
    kc.data.deskew = False
    kc.data.min_range = float(cfg.min_range_m)
    kc.data.max_range = float(cfg.max_range_m)
    kc.mapping.voxel_size = float(cfg.kiss_voxel_m) if cfg.kiss_voxel_m > 0 else float(cfg.max_range_m) / 100.0
    kc.adaptive_threshold.initial_threshold = float(cfg.kiss_initial_threshold_m)
    return kc


class KissOdometry:
    """Streaming KISS-ICP odometry with the interface of `Odometry` (see the module docstring).

    Usage: `odo = KissOdometry(cfg, initial_pose)`, then `odo.step(points_s)` per frame in order;
    `odo.correct(T_corr)` after a pose-graph correction (T_world <- T_corr @ T_world).
    """

    def __init__(self, cfg: OdometryConfig | None = None, initial_pose: np.ndarray | None = None):
        from kiss_icp.kiss_icp import KissICP

        self.cfg = cfg or OdometryConfig(method="kiss_icp")
        self.kiss = KissICP(kiss_config(self.cfg))
        self.T0 = np.eye(4) if initial_pose is None else np.array(initial_pose, dtype=np.float64)
        self.C = np.eye(4)               # accumulated world-frame corrections
        self.pose = self.T0.copy()
        self.velocity = np.eye(4)        # T_{i-1,i} of the last step
        self.prev: Scan | None = None
        self.last: Scan | None = None
        self.n_frames = 0
        self.threshold_m = float(self.cfg.kiss_initial_threshold_m)  # the adaptive threshold's start
        self.deviations: list[np.ndarray] = []  # KISS-ICP's model deviation of each step (see __getstate__)

    def step(self, points_s: np.ndarray, scan: Scan | None = None) -> OdomStep:
        """Register the next scan. points_s: [N,3] float, sensor frame; scan: `Scan(points_s, cfg)` if made
        already (in a prefetch thread). Returns an OdomStep."""
        cfg = self.cfg
        scan = Scan(points_s, cfg) if scan is None else scan
        frame = self.n_frames
        self.n_frames += 1
        self.last = scan
        pts = np.ascontiguousarray(np.asarray(points_s, dtype=np.float64).reshape(-1, 3))
        if frame == 1:
            self._seed_first_step(scan)
        guess = self.kiss.last_pose @ self.kiss.last_delta
        self.kiss.register_frame(pts, np.empty((0,), dtype=np.float64))
        self.deviations.append(np.linalg.inv(guess) @ self.kiss.last_pose)  # as KISS-ICP computes it
        self.pose = compose(self.C, self.T0, self.kiss.last_pose)
        if self.prev is None:
            self.prev = scan
            return OdomStep(self.pose.copy(), np.eye(4), 1.0, 0.0, True, np.eye(6))
        rel = orthonormalize(np.array(self.kiss.last_delta, dtype=np.float64))
        fitness, rmse, info = self._quality(scan, self.prev, rel)
        ok = fitness >= cfg.min_fitness and rmse <= cfg.max_rmse_m
        if not ok:
            log.warning("odometry frame %d: KISS-ICP step fits poorly (fitness %.3f < %.2f or RMSE %.4f m > %.4f m); "
                        "kept, with a weak pose-graph edge", frame, fitness, cfg.min_fitness, rmse, cfg.max_rmse_m)
        self.velocity = rel
        self.prev = scan
        return OdomStep(self.pose.copy(), rel.copy(), fitness, rmse, ok, info if ok else np.eye(6))

    def _seed_first_step(self, scan: Scan) -> None:
        """Predict KISS-ICP's first step (see the module docstring): T_{0,1} by jaxmap's ICP from no motion (a
        global registration where that fits poorly). Where no registration fits, KISS-ICP starts from no
        motion with its own initial threshold (2.0 m) instead of kiss_initial_threshold_m."""
        from kiss_icp.threshold import get_threshold_estimator

        cfg, first = self.cfg, self.prev
        res = None
        if len(scan) >= cfg.min_points and len(first) >= cfg.min_points:
            res = register(scan, first, np.eye(4), cfg)
            if res.fitness < cfg.retry_below_fitness:
                alt = global_register(scan, first, cfg)
                res = alt if alt.fitness > res.fitness else res
        if res is not None and res.fitness >= cfg.min_fitness:
            self.kiss.last_delta = res.T
            return
        log.warning("odometry frame 1: no registration of the first two scans fits (fitness %.3f); KISS-ICP starts "
                    "from no motion", res.fitness if res else 0.0)
        self.threshold_m = KISS_INITIAL_THRESHOLD_M
        self.kiss.adaptive_threshold = get_threshold_estimator(self._kiss_config())

    def _kiss_config(self):
        kc = kiss_config(self.cfg)
        kc.adaptive_threshold.initial_threshold = self.threshold_m
        return kc

    def __getstate__(self) -> dict:
        """KISS-ICP's C++ state cannot be pickled (a `jaxmap slam` checkpoint pickles the front end): its
        local map is kept as its points, and its adaptive threshold as the deviations it was given."""
        st = dict(self.__dict__)
        kiss = st.pop("kiss")
        st["kiss_state"] = {"last_pose": kiss.last_pose, "last_delta": kiss.last_delta,
                            "local_map": kiss.local_map.point_cloud().copy()}
        return st

    def __setstate__(self, st: dict) -> None:
        """KISS-ICP rebuilt: its local map's points added back voxel by voxel in their order (the same
        voxels, the same points), the threshold fed the same deviations again."""
        from kiss_icp.kiss_icp import KissICP

        ks = st.pop("kiss_state")
        self.__dict__.update(st)
        self.kiss = KissICP(self._kiss_config())
        self.kiss.last_pose, self.kiss.last_delta = ks["last_pose"], ks["last_delta"]
        if len(ks["local_map"]):
            self.kiss.local_map.add_points(ks["local_map"])
        for d in self.deviations:
            self.kiss.adaptive_threshold.update_model_deviation(d)

    def _quality(self, source: Scan, target: Scan, T: np.ndarray) -> tuple[float, float, np.ndarray]:
        """(fitness, inlier RMSE, [6,6] information) of T_target_source on the prepared scans."""
        if len(source) == 0 or len(target) == 0:
            return 0.0, float("inf"), np.eye(6)
        import open3d as o3d

        reg = o3d.pipelines.registration
        src, tgt = to_o3d(source.points, source.normals), to_o3d(target.points, target.normals)
        with quiet_open3d():
            ev = reg.evaluate_registration(src, tgt, float(self.cfg.max_corr_m), T)
            info = np.array(reg.get_information_matrix_from_point_clouds(src, tgt, float(self.cfg.max_corr_m), T))
        return float(ev.fitness), float(ev.inlier_rmse), info

    def correct(self, T_corr: np.ndarray) -> None:
        """Apply a world-frame correction: pose <- T_corr @ pose (KISS-ICP's local map is untouched)."""
        self.C = compose(T_corr, self.C)
        self.pose = compose(T_corr, self.pose)
