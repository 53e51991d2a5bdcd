"""Timestamped poses: TUM trajectory files, quaternions, and matching frames to poses by time.

Shared by the ROS bag reader (`jaxmap.io.rosbag`) and the TUM RGB-D reader (`jaxmap.io.tum`).

TUM trajectory format: one line `timestamp tx ty tz qx qy qz qw` per pose (seconds; Hamilton quaternion,
w last; T_world_sensor); blank lines and lines starting with '#' are skipped.
"""
from __future__ import annotations

import os

import numpy as np

from jaxmap.errors import DataError

QUAT_NORM_TOL = 1e-2  # TUM ground truth prints 4 decimals; a quaternion this far from unit norm is an error


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternions [N,4] (qx qy qz qw) -> rotation matrices [N,3,3] float64 (normalised first)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    return Rotation.from_quat(q / np.linalg.norm(q, axis=1, keepdims=True)).as_matrix().reshape(-1, 3, 3)


def poses_from_tum_rows(rows: np.ndarray, where: str, lines=None) -> np.ndarray:
    """[N,7] rows `tx ty tz qx qy qz qw` -> poses [N,4,4] float64. DataError (naming `where` and the line)
    for a non-finite value or a quaternion that is not of unit norm."""
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
    lines = list(range(1, len(rows) + 1)) if lines is None else lines
    bad = np.flatnonzero(~np.isfinite(rows).all(axis=1))
    if len(bad):
        raise DataError(f"{where} line {lines[bad[0]]}: NaN or inf value; fix or remove that line")
    norm = np.linalg.norm(rows[:, 3:7], axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUAT_NORM_TOL)
    if len(bad):
        raise DataError(f"{where} line {lines[bad[0]]}: quaternion (qx qy qz qw) has norm {norm[bad[0]]:.6f}, "
                        "expected 1; the columns must be 'timestamp tx ty tz qx qy qz qw'")
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    if len(rows):
        T[:, :3, :3] = quat_to_matrix(rows[:, 3:7])
        T[:, :3, 3] = rows[:, :3]
    return T


def read_number_table(path, n_columns: int | None = None, missing: str = "not found",
                      layout: str = "") -> tuple[np.ndarray, list[int]]:
    """Numbers of a whitespace table ([L, C] float64) and the file line number of each row.

    Blank and '#' lines are skipped. Every row has `n_columns` numbers (`layout` says what they are), or,
    with None, as many as the first row. DataError naming the file (and the line) when it is missing
    (`missing` says what to do), for a ragged row or a non-number."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DataError(f"{path}: {missing}")
    rows, lines = [], []
    with open(path) as f:
        for lineno, line in enumerate(f, start=1):
            words = line.split()
            if not words or words[0].startswith("#"):
                continue
            if n_columns is not None and len(words) != n_columns:
                raise DataError(f"{path} line {lineno}: expected {n_columns} numbers{' ' + layout if layout else ''}, "
                                f"found {len(words)}; fix or remove that line")
            if n_columns is None and rows and len(words) != len(rows[0]):
                raise DataError(f"{path} line {lineno}: {len(words)} numbers, but the first pose line has "
                                f"{len(rows[0])}; every line must have the same number of columns")
            try:
                rows.append([float(w) for w in words])
            except ValueError:
                raise DataError(f"{path} line {lineno}: not a number in {line.strip()!r}") from None
            lines.append(lineno)
    return (np.asarray(rows, np.float64) if rows else np.zeros((0, n_columns or 0))), lines


def read_tum_trajectory(path, what: str = "TUM trajectory") -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file -> (timestamps [N] float64 s, poses [N,4,4] float64 T_world_sensor).

    Raises DataError naming the file (and line) when it is missing, empty, or a line has not 8 numbers,
    a non-number, NaN/inf or a non-unit quaternion."""
    layout = "'timestamp tx ty tz qx qy qz qw'"
    table, lines = read_number_table(path, 8, f"{what} not found; write one line {layout} per pose", layout)
    if not len(table):
        raise DataError(f"{os.fspath(path)}: {what} has no pose lines; expected {layout} per line")
    return table[:, 0].copy(), poses_from_tum_rows(table[:, 1:], os.fspath(path), lines)


def poses_at_times(times, pose_times, poses, tolerance: float, interpolate: bool):
    """Poses of frames at `times` [N] (s) from a pose stream (`pose_times` [P] s, `poses` [P,4,4]).

    interpolate=False: the pose nearest in time, if within `tolerance` seconds.
    interpolate=True: if the poses just before and just after the frame time are both within `tolerance`,
    their interpolation (translation linear, rotation slerp); otherwise the nearest pose if within
    `tolerance`. A pose stamped exactly at the frame time is returned unchanged either way.
    Returns (ok [N] bool, out [N,4,4] float64 (identity where not ok), dt [N] float64: time to the nearest
    pose).
    """
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    pt = np.asarray(pose_times, dtype=np.float64).reshape(-1)
    P = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    order = np.argsort(pt, kind="stable")
    pt, P = pt[order], P[order]
    n, m = len(times), len(pt)
    out = np.tile(np.eye(4), (n, 1, 1))
    if m == 0 or n == 0:
        return np.zeros(n, bool), out, np.full(n, np.inf)
    j = np.searchsorted(pt, times, side="left")          # pt[j-1] < t <= pt[j]
    nxt = np.minimum(j, m - 1)
    prv = np.maximum(j - 1, 0)
    d_next = np.where(j < m, pt[nxt] - times, np.inf)
    d_prev = np.where(j > 0, times - pt[prv], np.inf)
    dt = np.minimum(d_next, d_prev)
    ok = dt <= tolerance
    nearest = np.where(d_next <= d_prev, nxt, prv)
    out[ok] = P[nearest[ok]]
    if interpolate:
        both = ok & (d_next <= tolerance) & (d_prev <= tolerance) & (d_next > 0) & (d_prev > 0)
        if np.any(both):
            from scipy.spatial.transform import Rotation

            a = d_prev[both] / (d_prev[both] + d_next[both])
            P0, P1 = P[prv[both]], P[nxt[both]]
            r0 = Rotation.from_matrix(P0[:, :3, :3])
            rel = r0.inv() * Rotation.from_matrix(P1[:, :3, :3])
            out[both, :3, :3] = (r0 * Rotation.from_rotvec(rel.as_rotvec() * a[:, None])).as_matrix()
            out[both, :3, 3] = (1 - a)[:, None] * P0[:, :3, 3] + a[:, None] * P1[:, :3, 3]
    return ok, out, dt
