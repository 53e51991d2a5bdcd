"""Step 1 of the evaluation protocol (`jaxmap.metrics.protocol`): the GT points kept, those near what the
scans observed (and near the sensor's path), for a whole GT cloud (`cull_gt`) or one read in pieces
(`GtCuller`).
"""
from __future__ import annotations

import numpy as np

from jaxmap.errors import DataError


def as_points(x, name: str) -> np.ndarray:
    """x as [N,3] float64, or a DataError naming it (wrong shape, NaN or inf)."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise DataError(f"{name}: expected an array of shape [N,3], got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise DataError(f"{name}: contains NaN or inf")
    return a


class GtCuller:
    """Step 1 of the protocol as a test of GT points, for GT read in pieces (`keep` of each piece gives
    what `cull_gt` of the whole would): the trees of the sensor positions and the observed points are
    built once. Arguments as `cull_gt`'s."""

    def __init__(self, *, observed_points=None, cull_distance_m: float = 0.3, sensor_positions=None,
                 eval_radius_m: float = -1.0):
        from scipy.spatial import cKDTree

        self.cull_distance_m, self.eval_radius_m = cull_distance_m, eval_radius_m
        self._sensors = self._observed = None  # (None: that test is off)
        self._no_sensor = False                # the radius test is on and there is no sensor: nothing is kept
        if eval_radius_m is not None and eval_radius_m > 0:
            if sensor_positions is None:
                raise DataError("eval_radius_m > 0 needs sensor_positions (the pose translations)")
            sp = as_points(sensor_positions, "sensor_positions")
            self._no_sensor = len(sp) == 0
            self._sensors = cKDTree(sp) if len(sp) else None
        if observed_points is not None:
            obs = as_points(observed_points, "observed_points")
            if len(obs) == 0:
                raise DataError("observed_points is empty: nothing was observed, so all GT would be culled")
            self._observed = cKDTree(obs)

    def keep(self, gt_points) -> np.ndarray:
        """[N] bool: which of the GT points [N,3] (world frame) the protocol keeps."""
        return self._keep(as_points(gt_points, "gt_points"))

    def _keep(self, gt: np.ndarray) -> np.ndarray:
        """`keep` of points already checked (`as_points`)."""
        idx = np.arange(len(gt)) if not self._no_sensor else np.zeros(0, np.int64)
        for tree, reach in ((self._sensors, self.eval_radius_m), (self._observed, self.cull_distance_m)):
            if tree is None or len(idx) == 0:
                continue
            d = tree.query(gt[idx], k=1, distance_upper_bound=reach * (1 + 1e-9) + 1e-12, workers=-1)[0]
            idx = idx[d <= reach]
        out = np.zeros(len(gt), bool)
        out[idx] = True
        return out


def cull_gt(gt_points, *, observed_points=None, cull_distance_m: float = 0.3, sensor_positions=None,
            eval_radius_m: float = -1.0, return_index: bool = False):
    """Step 1 of the protocol. gt_points [G,3] -> the kept GT points [G',3] (float64, world frame), and
    with return_index=True also their indices into gt_points [G'] (to carry normals and classes along).

    Kept: within eval_radius_m of some sensor position (when eval_radius_m > 0) and within
    cull_distance_m of some observed point (when observed_points is given). (`GtCuller` for GT in pieces.)"""
    gt = as_points(gt_points, "gt_points")
    idx = np.flatnonzero(GtCuller(observed_points=observed_points, cull_distance_m=cull_distance_m,
                                  sensor_positions=sensor_positions, eval_radius_m=eval_radius_m)._keep(gt))
    return (gt[idx], idx) if return_index else gt[idx]


def culled_or_fail(gt_points, cull_distance_m, eval_radius_m, **kw):
    gt, idx = cull_gt(gt_points, cull_distance_m=cull_distance_m, eval_radius_m=eval_radius_m, return_index=True,
                      **kw)
    if len(gt) == 0:
        raise DataError(no_gt_left(cull_distance_m, eval_radius_m))
    return gt, idx


def no_gt_left(cull_distance_m, eval_radius_m) -> str:
    """The error of a culling that kept no GT point."""
    return (f"no GT point is left after culling (cull distance {cull_distance_m} m, eval radius "
            f"{eval_radius_m} m): do the GT and the scans share a frame?")
