"""Trajectory files (KITTI, TUM) and trajectory metrics: absolute (ATE) and relative (RPE) pose errors.

Metrics go through evo where it is installed (`pip install 'jaxmap[eval]'`), else through the
implementation here; both give the same figures. Poses are [N,4,4] float64 T_world_sensor.
KITTI: one line of 12 numbers (row-major 3x4 [R|t]) per pose.
TUM: one line `t tx ty tz qx qy qz qw` per pose (timestamp in seconds, Hamilton quaternion, w last);
lines starting with '#' are comments.
"""
from __future__ import annotations

import logging
import os

import numpy as np
from scipy.spatial.transform import Rotation

from jaxmap.errors import DataError
from jaxmap.geometry import rotation_angle, se3_inverse, validate_pose
from jaxmap.io.kitti import write_poses

log = logging.getLogger("jaxmap")


def write_kitti(path, poses) -> None:
    """Write poses [N,4,4] as a KITTI pose file (float64 values round-trip exactly)."""
    write_poses(path, poses)


def write_tum(path, timestamps, poses) -> None:
    """Write a TUM trajectory: timestamps [N] (s), poses [N,4,4] -> lines `t tx ty tz qx qy qz qw`."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if len(ts) != len(poses):
        raise DataError(f"{path}: {len(ts)} timestamps for {len(poses)} poses")
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()          # x, y, z, w
    d = os.path.dirname(os.fspath(path))
    if d:
        os.makedirs(d, exist_ok=True)
    with open(os.fspath(path), "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, T, qi in zip(ts, poses, q):
            f.write(" ".join(repr(float(v)) for v in (t, *T[:3, 3], *qi)) + "\n")


def write_trajectory(out_dir: str, seq, traj) -> None:
    """out_dir/trajectory_kitti.txt and trajectory_tum.txt of a run over `seq`: poses [N,4,4] of its first N
    frames, stamped with the sensor's timestamps where the data has them (ROS bags, TUM RGB-D), else with
    the frame numbers."""
    write_kitti(os.path.join(out_dir, "trajectory_kitti.txt"), traj)
    stamps = seq.timestamps if getattr(seq, "timestamps", None) is not None else seq.indices
    write_tum(os.path.join(out_dir, "trajectory_tum.txt"), np.asarray(stamps[:len(traj)], np.float64), traj)


def _read_table(path) -> tuple[np.ndarray, list[int]]:
    """Numbers of a whitespace table ([L,C] float64) and the file line number of each row (see
    `jaxmap.io.stamped.read_number_table`: every line as many numbers as the first)."""
    from jaxmap.io.stamped import read_number_table

    table, lines = read_number_table(path, None, "trajectory file not found")
    return (table if len(table) else np.zeros((0, 0))), lines


def _tum_to_poses(path, table: np.ndarray, lines: list[int]) -> tuple[np.ndarray, np.ndarray]:
    q = table[:, 4:8]
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
    if len(bad):
        raise DataError(f"{path} line {lines[bad[0]]}: quaternion (qx qy qz qw) has norm {norm[bad[0]]:.6f}, "
                        "expected 1")
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(q / norm[:, None]).as_matrix()
    poses[:, :3, 3] = table[:, 1:4]
    return table[:, 0].copy(), poses


def read_tum(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory -> (timestamps [N] float64, poses [N,4,4] float64). DataError if malformed."""
    table, lines = _read_table(path)
    if table.size == 0:
        return np.zeros(0), np.zeros((0, 4, 4))
    if table.shape[1] != 8:
        raise DataError(f"{os.fspath(path)}: TUM lines need 8 numbers (t tx ty tz qx qy qz qw), found "
                        f"{table.shape[1]}")
    _check_finite(path, table, lines)
    return _tum_to_poses(path, table, lines)


def _check_finite(path, table, lines):
    bad = np.flatnonzero(~np.all(np.isfinite(table), axis=1))
    if len(bad):
        raise DataError(f"{os.fspath(path)} line {lines[bad[0]]}: NaN or inf value")


def read_pose_snapshot(path, n_expected: int | None = None) -> np.ndarray:
    """Read poses [N,4,4] float64 from a TUM (8 columns) or KITTI (12 columns) file, detected per file.

    n_expected: if given, the file must hold exactly that many poses. Raises DataError naming the file
    (and line) for a missing file, a wrong column count, a non-number, NaN/inf, a non-rigid rotation,
    or a wrong number of poses.
    """
    path = os.fspath(path)
    table, lines = _read_table(path)
    if table.size == 0:
        raise DataError(f"{path}: no poses found (expected TUM lines of 8 numbers or KITTI lines of 12)")
    cols = table.shape[1]
    if cols not in (8, 12):
        raise DataError(f"{path}: {cols} numbers per line; expected 8 (TUM: t tx ty tz qx qy qz qw) or "
                        "12 (KITTI: row-major 3x4 [R|t])")
    _check_finite(path, table, lines)
    if cols == 8:
        _, poses = _tum_to_poses(path, table, lines)
    else:
        poses = np.tile(np.eye(4), (len(table), 1, 1))
        poses[:, :3, :] = table.reshape(-1, 3, 4)
        for T, lineno in zip(poses, lines):
            validate_pose(T, where=f"{path} line {lineno}")
    if n_expected is not None and len(poses) != int(n_expected):
        raise DataError(f"{path}: {len(poses)} poses, expected {int(n_expected)} (one per frame)")
    return poses


def align_se3(est_xyz: np.ndarray, gt_xyz: np.ndarray) -> np.ndarray:
    """Rigid transform S [4,4] minimising sum |S est - gt|^2 (Umeyama / Horn, no scale).

    est_xyz, gt_xyz: [N,3] corresponding positions (N >= 3, not all collinear for a unique answer)."""
    mu_e, mu_g = est_xyz.mean(0), gt_xyz.mean(0)
    H = (gt_xyz - mu_g).T @ (est_xyz - mu_e)             # cross-covariance [3,3]
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    S = np.eye(4)
    S[:3, :3] = R
    S[:3, 3] = mu_g - R @ mu_e
    return S


def _poses_pair(est, gt, name: str) -> tuple[np.ndarray, np.ndarray]:
    est = np.asarray(est, dtype=np.float64).reshape(-1, 4, 4)
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 4, 4)
    if est.shape != gt.shape or len(est) == 0:
        raise ValueError(f"{name}: need equally many poses, got {est.shape} and {gt.shape}")
    return est, gt


def have_evo() -> bool:
    """True when the `evo` package (trajectory evaluation, `pip install 'jaxmap[eval]'`) is importable."""
    try:
        import evo.core.metrics  # noqa: F401
    except ImportError:
        return False
    return True


def _backend(backend: str) -> str:
    if backend == "auto":
        return "evo" if have_evo() else "jaxmap"
    if backend not in ("evo", "jaxmap"):
        raise ValueError(f"backend must be 'auto', 'evo' or 'jaxmap', got {backend!r}")
    return backend


def _stats(err: np.ndarray, rot_deg: np.ndarray) -> dict:
    return {"rmse_m": float(np.sqrt(np.mean(err ** 2))), "mean_m": float(err.mean()), "max_m": float(err.max()),
            "rot_rmse_deg": float(np.sqrt(np.mean(rot_deg ** 2)))}


def ate(est, gt, align: str = "none", backend: str = "auto") -> dict:
    """Absolute trajectory error of estimated vs ground-truth poses ([N,4,4] each, same frames).

    align: "none" compares as is; "se3" first applies the rigid transform that best aligns the estimated
    positions to the ground truth (Umeyama). Returns dict(rmse_m, mean_m, max_m) of the position errors
    and rot_rmse_deg, the RMSE of the rotation angle of gt_i^-1 @ est_i (after alignment).
    backend: "evo" (evo's APE; `pip install 'jaxmap[eval]'`), "jaxmap" (this module's implementation) or
    "auto" (evo where it is installed and accepts the input, else jaxmap's: evo refuses to align a straight
    or one-pose trajectory); both give the same figures (tests/test_trajectory_metrics.py).
    """
    est, gt = _poses_pair(est, gt, "ate")
    if align not in ("none", "se3"):
        raise ValueError(f"ate: align must be 'none' or 'se3', got {align!r}")
    if _backend(backend) == "evo":
        try:
            return _evo_ape(est, gt, align)
        except Exception as e:  # evo refuses some alignments (e.g. a straight or one-pose trajectory)
            if backend == "evo":
                raise
            log.debug("evo APE failed (%s); jaxmap's ATE instead", e)
    if align == "se3":
        est = align_se3(est[:, :3, 3], gt[:, :3, 3]) @ est
    err = np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1)
    rot = np.degrees(rotation_angle(se3_inverse(gt)[:, :3, :3] @ est[:, :3, :3]))
    return _stats(err, rot)


def axis_errors(est, gt) -> dict:
    """What the ATE's one number hides ([N,4,4] each, same frames, no alignment: a SLAM run starts at the
    sequence's first pose): the height error est - gt (dz_mean_m, dz_min_m, dz_max_m), the horizontal
    error (xy_rmse_m), and the tilt error, the angle between the estimated and the true up axis
    (tilt_mean_deg, tilt_max_deg). A trajectory a centimetre or two low has a small ATE, and maps the road
    that much low."""
    est, gt = _poses_pair(est, gt, "axis_errors")
    d = est[:, :3, 3] - gt[:, :3, 3]
    cos = np.clip(np.sum(est[:, :3, 2] * gt[:, :3, 2], axis=1), -1.0, 1.0)   # the sensors' z axes in the world
    tilt = np.degrees(np.arccos(cos))
    return {"dz_mean_m": float(d[:, 2].mean()), "dz_min_m": float(d[:, 2].min()), "dz_max_m": float(d[:, 2].max()),
            "xy_rmse_m": float(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, axis=1)))),
            "tilt_mean_deg": float(tilt.mean()), "tilt_max_deg": float(tilt.max())}


def rpe(est, gt, delta: int = 1, backend: str = "auto") -> dict:
    """Relative pose error over `delta` frames ([N,4,4] each, same frames, N > delta).

    For i = 0, delta, 2 delta, ...: E_i = (gt_i^-1 gt_{i+delta})^-1 (est_i^-1 est_{i+delta}); returns dict(rmse_m,
    mean_m, max_m)
    of |translation of E_i| and rot_rmse_deg of the rotation angle of E_i (evo's RPE with delta in frames).
    backend as for `ate`.
    """
    est, gt = _poses_pair(est, gt, "rpe")
    delta = int(delta)
    if delta < 1 or len(est) <= delta:
        raise ValueError(f"rpe: need delta >= 1 and more than delta poses, got delta={delta} for {len(est)} poses")
    if _backend(backend) == "evo":
        try:
            return _evo_rpe(est, gt, delta)
        except Exception as e:
            if backend == "evo":
                raise
            log.debug("evo RPE failed (%s); jaxmap's RPE instead", e)
    ids = np.arange(0, len(est), delta)            # pairs (0, d), (d, 2d), ...: evo's all_pairs=False
    i, j = ids[:-1], ids[1:]
    rel_e = se3_inverse(est[i]) @ est[j]
    rel_g = se3_inverse(gt[i]) @ gt[j]
    E = se3_inverse(rel_g) @ rel_e
    return _stats(np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(rotation_angle(E[:, :3, :3])))


def _evo_paths(est, gt):
    from evo.core.trajectory import PosePath3D

    return PosePath3D(poses_se3=list(est)), PosePath3D(poses_se3=list(gt))


def _evo_stats(metric_t, metric_r) -> dict:
    from evo.core.metrics import StatisticsType as S

    return {"rmse_m": float(metric_t.get_statistic(S.rmse)), "mean_m": float(metric_t.get_statistic(S.mean)),
            "max_m": float(metric_t.get_statistic(S.max)), "rot_rmse_deg": float(metric_r.get_statistic(S.rmse))}


def _evo_ape(est, gt, align: str) -> dict:
    from evo.core.metrics import APE, PoseRelation

    p_est, p_gt = _evo_paths(est, gt)
    if align == "se3":
        p_est.align(p_gt, correct_scale=False)
    t, r = APE(PoseRelation.translation_part), APE(PoseRelation.rotation_angle_deg)
    t.process_data((p_gt, p_est))
    r.process_data((p_gt, p_est))
    return _evo_stats(t, r)


def _evo_rpe(est, gt, delta: int) -> dict:
    from evo.core.metrics import RPE, PoseRelation, Unit

    p_est, p_gt = _evo_paths(est, gt)
    t = RPE(PoseRelation.translation_part, delta=delta, delta_unit=Unit.frames, all_pairs=False)
    r = RPE(PoseRelation.rotation_angle_deg, delta=delta, delta_unit=Unit.frames, all_pairs=False)
    t.process_data((p_gt, p_est))
    r.process_data((p_gt, p_est))
    return _evo_stats(t, r)
