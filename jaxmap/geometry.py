"""SE(3)/SO(3) helpers written once for numpy and jax.numpy.

Poses are 4x4 homogeneous matrices `T_w_s` that map sensor-frame points into the world frame:
`p_w = R p_s + t`. Functions that accept an `xnp` argument work with `numpy` or `jax.numpy`
(pass the module); the default is numpy.
"""
from __future__ import annotations

import numpy as np


from jaxmap.errors import DataError


class PoseError(DataError):
    """A pose matrix is not a rigid transform."""


def transform_points(T, points, xnp=np):
    """Apply a rigid transform. T: [4,4] (or [...,4,4]); points: [N,3] -> [N,3]."""
    return points @ xnp.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]


def rotate_vectors(R, vectors, xnp=np):
    """Rotate direction vectors. R: [3,3]; vectors: [N,3] -> [N,3]."""
    return vectors @ xnp.swapaxes(R, -1, -2)


def se3_inverse(T, xnp=np):
    """Inverse of a rigid transform [...,4,4] without a general matrix inverse."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = xnp.swapaxes(R, -1, -2)
    ti = -(Rt @ t[..., None])[..., 0]
    top = xnp.concatenate([Rt, ti[..., None]], axis=-1)
    bottom = xnp.broadcast_to(xnp.asarray([0.0, 0.0, 0.0, 1.0], dtype=T.dtype), top.shape[:-2] + (1, 4))
    return xnp.concatenate([top, bottom], axis=-2)


def make_pose(R, t, xnp=np):
    """[3,3] rotation and [3] translation -> [4,4] pose."""
    T = xnp.eye(4, dtype=xnp.asarray(R).dtype)
    if xnp is np:
        T = T.copy()
        T[:3, :3] = R
        T[:3, 3] = t
        return T
    return T.at[:3, :3].set(R).at[:3, 3].set(t)


def rotation_angle(R, xnp=np):
    """Geodesic angle (radians) of rotation matrices [...,3,3]."""
    cos = (xnp.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return xnp.arccos(xnp.clip(cos, -1.0, 1.0))


def pose_change(T_a, T_b, xnp=np):
    """(rotation angle in radians, translation norm in metres) of T_a^-1 T_b.

    Poses are compared by angle and distance, never by a signed sum of matrix entries.
    """
    D = se3_inverse(T_a, xnp) @ T_b
    return rotation_angle(D[..., :3, :3], xnp), xnp.linalg.norm(D[..., :3, 3], axis=-1)


def rotation_from_axis_angle(axis, angle, xnp=np):
    """Rodrigues' formula. axis: [3] (normalised here), angle: scalar -> [3,3]."""
    axis = axis / xnp.linalg.norm(axis)
    x, y, z = axis[0], axis[1], axis[2]
    K = xnp.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return xnp.eye(3) + xnp.sin(angle) * K + (1.0 - xnp.cos(angle)) * (K @ K)


def yaw_rotation(yaw: float) -> np.ndarray:
    """Rotation about +z by `yaw` radians, [3,3] float64."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly random rotation (QR of a Gaussian matrix, det fixed to +1), [3,3] float64."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def random_rotation_jax(key):
    """Uniformly random rotation from a jax PRNG key (for property tests under jit), [3,3]."""
    import jax
    import jax.numpy as jnp

    q, r = jnp.linalg.qr(jax.random.normal(key, (3, 3)))
    q = q * jnp.sign(jnp.diag(r))
    flip = jnp.where(jnp.linalg.det(q) < 0, -1.0, 1.0)
    return q.at[:, 0].multiply(flip)


def orthonormalize(T):
    """The nearest rigid transform: the rotation block of T ([..., 4, 4], or [..., 3, 3]) projected onto
    SO(3) by SVD (`U V^T`, det fixed to +1), the last row reset to [0 0 0 1]; same dtype.

    Every pose that jaxmap composes, integrates or optimises goes through this where it is produced, so
    chains of thousands of float64 products stay on SE(3) (|R^T R - I| ~ 1e-15) instead of drifting off
    it (open3d's optimiser and long ICP chains leave ~1e-3 after a few hundred frames).
    """
    T = np.asarray(T)
    R = T[..., :3, :3] if T.shape[-1] == 4 else T
    U, _, Vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    Vt = np.concatenate([Vt[..., :2, :], Vt[..., 2:, :] * d[..., None, None]], axis=-2)
    Rn = (U @ Vt).astype(T.dtype)
    if T.shape[-1] == 3:
        return Rn
    top = np.concatenate([Rn, T[..., :3, 3:]], axis=-1)
    bottom = np.broadcast_to(np.asarray([0.0, 0.0, 0.0, 1.0], dtype=T.dtype), top.shape[:-2] + (1, 4))
    return np.concatenate([top, bottom], axis=-2)


def compose(*poses):
    """Product of rigid transforms [4, 4] (left to right), re-orthonormalised (`orthonormalize`)."""
    out = np.asarray(poses[0], np.float64)
    for P in poses[1:]:
        out = out @ np.asarray(P, np.float64)
    return orthonormalize(out)


def validate_pose(T: np.ndarray, where: str = "pose", tol: float = 1e-3, source: str | None = None) -> None:
    """Raise PoseError unless T is a finite 4x4 rigid transform (orthonormal R, det +1).

    source: where the pose came from when it was not read from the user's files (e.g. "jaxmap's SLAM
    front end"); the message then names it instead of telling the user to fix a pose file.
    """
    T = np.asarray(T, dtype=np.float64)
    origin = f" (from {source})" if source else ""
    if T.shape != (4, 4):
        raise PoseError(f"{where}{origin}: expected a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise PoseError(f"{where}{origin}: contains NaN or inf")
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > tol or np.linalg.det(R) < 0:
        hint = ("this is a bug in jaxmap: a pose it computed left SE(3); please report it" if source else
                "check that each line holds 12 numbers of a row-major 3x4 [R|t] matrix")
        raise PoseError(
            f"{where}{origin}: rotation is not orthonormal (max |R^T R - I| = {err:.2e}, "
            f"det = {np.linalg.det(R):.4f}); {hint}"
        )
    if np.abs(T[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        raise PoseError(f"{where}{origin}: last row must be [0 0 0 1], got {T[3]}")
