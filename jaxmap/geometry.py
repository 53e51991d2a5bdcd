"""Rigid transforms: the `SO3` and `SE3` pytree types, and helpers written once for numpy and jax.numpy.

A pose `T_w_s` maps sensor-frame points into the world frame, `p_w = R p_s + t`; as a matrix it is the
4x4 homogeneous `[[R, t], [0, 1]]`. `SE3` wraps that matrix (`SO3` a 3x3 rotation), batched over
leading axes, and works on numpy arrays (float64 host poses: the SLAM front end, the pose graph) and
jax arrays (float32 inside jit) alike: each operation uses the array module of its operands (jax.numpy
as soon as one is a jax array or tracer), never casts, and does exactly the float ops of the plain
matrix maths it replaces (`a @ b` is the 4x4 matrix product), so results are bit-identical to them.

    T_w_s = SE3.from_matrix(pose)                 # [..., 4, 4]
    p_w = T_w_s.apply(p_s)                        # [..., N, 3] -> [..., N, 3]: p_s R^T + t
    T_a_b = T_w_a.inverse() @ T_w_b               # composition, right to left like matrices
    R, t = T_w_s.rotation(), T_w_s.translation()  # SO3 [..., 3, 3], array [..., 3]
    n_w = R.apply(n_s)                            # directions: rotation only

Both are frozen dataclasses registered as pytrees (one leaf, `matrix`), so they pass through `jax.jit`,
`jax.vmap` and `jax.lax.scan` like arrays. Points and vectors are rows (`[..., N, 3]`, one cloud per
pose); for one point per pose pass `points[..., None, :]`.

The one precision rule: every product of poses and points on jax arrays is `matmul` / `einsum` below,
at `Precision.HIGHEST`. A GPU's float32 matrix product otherwise rounds its operands to TF32 (10
mantissa bits, ~5e-4 relative): 1-2.5 cm at 50 m (`tests/test_geometry.py` shows it on the CPU by
emulating those units). On a CPU HIGHEST is what XLA always does: results are the same bits.

The functions below (transform_points, se3_inverse, ...) are the same operations on raw matrices; their
`xnp` argument (numpy or jax.numpy) converts the inputs to that module's arrays first (None: keep them).
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.errors import DataError


class PoseError(DataError):
    """A pose matrix is not a rigid transform."""


def matmul(a, b):
    """`a @ b`; for jax arrays at full float32 precision on every backend (the module's precision rule)."""
    if array_module(a, b) is np:
        return a @ b
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def einsum(spec: str, *operands):
    """`einsum(spec, *operands)`; for jax arrays at full float32 precision (the module's precision rule)."""
    if array_module(*operands) is np:
        return np.einsum(spec, *operands)
    return jnp.einsum(spec, *operands, precision=jax.lax.Precision.HIGHEST)


def array_module(*arrays):
    """jax.numpy when any of `arrays` is a jax array (or tracer), else numpy."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def _host_or_jax(x):
    # python lists and scalars become numpy arrays; numpy and jax arrays are kept as they are (no cast)
    return x if isinstance(x, (np.ndarray, jax.Array)) else np.asarray(x)


def _bottom_row(shape, dtype, xnp):
    """[..., 1, 4] rows [0 0 0 1] for matrices whose top [..., 3, 4] has `shape`."""
    return xnp.broadcast_to(xnp.asarray([0.0, 0.0, 0.0, 1.0], dtype=dtype), tuple(shape[:-2]) + (1, 4))


def _nearest_rotation(R):
    """R [..., 3, 3] projected onto SO(3) by SVD (`U V^T`, det fixed to +1), same dtype."""
    xnp = array_module(R)
    U, _, Vt = xnp.linalg.svd(R)
    d = xnp.sign(xnp.linalg.det(matmul(U, Vt)))
    d = xnp.where(d == 0, 1.0, d)
    Vt = xnp.concatenate([Vt[..., :2, :], Vt[..., 2:, :] * d[..., None, None]], axis=-2)
    return matmul(U, Vt).astype(R.dtype)


class _Batched:
    """What SO3 and SE3 share: one leaf `matrix` [..., k, k] batched over its leading axes."""

    matrix: Any

    def tree_flatten(self):
        return (self.matrix,), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        del aux
        return cls(*children)

    @classmethod
    def from_matrix(cls, matrix):
        """From a matrix [..., k, k] (numpy, jax or nested lists), kept as it is (no copy, no cast)."""
        return cls(_host_or_jax(matrix))

    @classmethod
    def identity(cls, batch_shape: tuple = (), dtype=np.float64, xnp=np):
        """Identity [*batch_shape, k, k] of `dtype` as `xnp` arrays (k = 3 for SO3, 4 for SE3)."""
        k = cls.SIZE
        return cls(xnp.broadcast_to(xnp.eye(k, dtype=dtype), tuple(batch_shape) + (k, k)))

    def as_matrix(self):
        """The matrix [..., k, k]."""
        return self.matrix

    @property
    def batch_shape(self) -> tuple:
        return tuple(self.matrix.shape[:-2])

    @property
    def dtype(self):
        return self.matrix.dtype

    def astype(self, dtype):
        """The same transform(s) with the matrix cast to `dtype`."""
        return type(self)(self.matrix.astype(dtype))

    def __getitem__(self, index):
        """Index the batch axes: `poses[i]`, `poses[2:5]` (the matrix axes are never indexed)."""
        return type(self)(self.matrix[index])


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True, eq=False)
class SO3(_Batched):
    """Rotations, `matrix` [..., 3, 3] (numpy or jax array), batched over the leading axes.

    `SO3.from_matrix(R)`, `as_matrix()`, `inverse()`, `a @ b` (composition), `apply(v)` (v R^T),
    `angle()` (geodesic angle), `orthonormalize()`; constructors `identity`, `from_axis_angle`,
    `from_z_radians`.
    """

    matrix: Any
    SIZE = 3   # the matrix is [..., 3, 3]

    @staticmethod
    def from_axis_angle(axis, angle) -> SO3:
        """Rodrigues' formula. axis: [3] (normalised here), angle: scalar radians (unbatched)."""
        xnp = array_module(axis, angle)
        axis = _host_or_jax(axis)
        axis = axis / xnp.linalg.norm(axis)
        x, y, z = axis[0], axis[1], axis[2]
        K = xnp.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
        return SO3(xnp.eye(3) + xnp.sin(angle) * K + (1.0 - xnp.cos(angle)) * matmul(K, K))

    @staticmethod
    def from_z_radians(yaw) -> SO3:
        """Rotation about +z by `yaw` radians (a scalar), [3, 3] (float64 for a python float)."""
        xnp = array_module(yaw)
        c, s = xnp.cos(yaw), xnp.sin(yaw)
        return SO3(xnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))

    def inverse(self) -> SO3:
        """R^T."""
        return SO3(array_module(self.matrix).swapaxes(self.matrix, -1, -2))

    def __matmul__(self, other: SO3) -> SO3:
        if not isinstance(other, SO3):
            raise TypeError(f"SO3 @ {type(other).__name__}: compose with an SO3; rotate vectors with .apply")
        return SO3(matmul(self.matrix, other.matrix))

    def apply(self, vectors):
        """Rotate row vectors: [..., N, 3] (or [3]) -> the same shape, `v R^T`."""
        return matmul(vectors, array_module(self.matrix, vectors).swapaxes(self.matrix, -1, -2))

    def angle(self):
        """Geodesic angle (radians) [...] of each rotation."""
        xnp = array_module(self.matrix)
        cos = (xnp.trace(self.matrix, axis1=-2, axis2=-1) - 1.0) / 2.0
        return xnp.arccos(xnp.clip(cos, -1.0, 1.0))

    def orthonormalize(self) -> SO3:
        """The nearest rotation (SVD, det +1), same dtype: see `orthonormalize`."""
        return SO3(_nearest_rotation(self.matrix))


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True, eq=False)
class SE3(_Batched):
    """Rigid transforms, `matrix` [..., 4, 4] homogeneous `[[R, t], [0, 1]]` (numpy or jax array), batched
    over the leading axes. `T_a_b` maps frame-b points into frame a: `p_a = T_a_b.apply(p_b)`.

    `SE3.from_matrix(T)`, `from_rotation_and_translation(R, t)`, `identity()`, `as_matrix()`,
    `rotation()` (SO3), `translation()` ([..., 3]), `inverse()`, `a @ b` (T_a_b @ T_b_c = T_a_c: the 4x4
    matrix product), `apply(points)` (p R^T + t), `orthonormalize()`.
    """

    matrix: Any
    SIZE = 4   # the matrix is [..., 4, 4]

    @staticmethod
    def from_rotation_and_translation(rotation, translation) -> SE3:
        """rotation: SO3 or [..., 3, 3]; translation [..., 3] (cast to the rotation's dtype); the batch
        axes broadcast. -> SE3 [..., 4, 4] of the rotation's dtype."""
        R = rotation.matrix if isinstance(rotation, SO3) else _host_or_jax(rotation)
        xnp = array_module(R, translation)
        t = xnp.asarray(translation, dtype=R.dtype)
        batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
        R, t = xnp.broadcast_to(R, batch + (3, 3)), xnp.broadcast_to(t, batch + (3,))
        top = xnp.concatenate([R, t[..., None]], axis=-1)
        return SE3(xnp.concatenate([top, _bottom_row(top.shape, R.dtype, xnp)], axis=-2))

    def rotation(self) -> SO3:
        """The rotation block, SO3 [..., 3, 3] (a view)."""
        return SO3(self.matrix[..., :3, :3])

    def translation(self):
        """The translation [..., 3] (a view)."""
        return self.matrix[..., :3, 3]

    def inverse(self) -> SE3:
        """`[[R^T, -R^T t], [0, 1]]`, without a general matrix inverse."""
        xnp = array_module(self.matrix)
        Rt = xnp.swapaxes(self.matrix[..., :3, :3], -1, -2)
        ti = -matmul(Rt, self.matrix[..., :3, 3][..., None])[..., 0]
        top = xnp.concatenate([Rt, ti[..., None]], axis=-1)
        return SE3(xnp.concatenate([top, _bottom_row(top.shape, self.matrix.dtype, xnp)], axis=-2))

    def __matmul__(self, other: SE3) -> SE3:
        if not isinstance(other, SE3):
            raise TypeError(f"SE3 @ {type(other).__name__}: compose with an SE3; move points with .apply")
        return SE3(matmul(self.matrix, other.matrix))

    def apply(self, points):
        """Move row points: [..., N, 3] -> [..., N, 3], `p R^T + t` (the batch axes broadcast)."""
        R = self.matrix[..., :3, :3]
        return matmul(points, array_module(R, points).swapaxes(R, -1, -2)) + self.matrix[..., None, :3, 3]

    def orthonormalize(self) -> SE3:
        """The nearest rigid transform, same dtype: see `orthonormalize`."""
        xnp = array_module(self.matrix)
        top = xnp.concatenate([_nearest_rotation(self.matrix[..., :3, :3]), self.matrix[..., :3, 3:]], axis=-1)
        return SE3(xnp.concatenate([top, _bottom_row(top.shape, self.matrix.dtype, xnp)], axis=-2))


def _converted(xnp, *arrays):
    return arrays if xnp is None else tuple(xnp.asarray(a) for a in arrays)


def transform_points(T, points, xnp=None):
    """Apply rigid transform(s) T [..., 4, 4] to points [..., N, 3] -> [..., N, 3] (`SE3.apply`)."""
    T, points = _converted(xnp, T, points)
    return SE3.from_matrix(T).apply(points)


def rotate_vectors(R, vectors, xnp=None):
    """Rotate row vectors by R [..., 3, 3]: [..., N, 3] -> [..., N, 3], `v R^T` (`SO3.apply`).

    The one rotate_vectors, rotation first. Nothing is cast: numpy promotes float32 vectors by a float64 R
    to float64, so pass R in the vectors' dtype to keep float32 (`R.astype(v.dtype)`)."""
    R, vectors = _converted(xnp, R, vectors)
    return SO3.from_matrix(R).apply(vectors)


def se3_inverse(T, xnp=None):
    """Inverse of rigid transform(s) [..., 4, 4] (`SE3.inverse`)."""
    return SE3.from_matrix(*_converted(xnp, T)).inverse().matrix


def make_pose(R, t, xnp=None):
    """[..., 3, 3] rotation and [..., 3] translation -> [..., 4, 4] pose of R's dtype."""
    R, t = _converted(xnp, R, t)
    return SE3.from_rotation_and_translation(R, t).matrix


def rotation_angle(R, xnp=None):
    """Geodesic angle (radians) of rotation matrices [..., 3, 3] (`SO3.angle`)."""
    return SO3.from_matrix(*_converted(xnp, R)).angle()


def pose_change(T_a, T_b, xnp=None):
    """(rotation angle in radians, translation norm in metres) of T_a^-1 T_b, each [...].

    Poses are compared by angle and distance, never by a signed sum of matrix entries.
    """
    T_a, T_b = _converted(xnp, T_a, T_b)
    D = SE3.from_matrix(T_a).inverse() @ SE3.from_matrix(T_b)
    return D.rotation().angle(), array_module(D.matrix).linalg.norm(D.translation(), axis=-1)


def rotation_from_axis_angle(axis, angle, xnp=None):
    """Rodrigues' formula. axis: [3] (normalised here), angle: scalar -> [3, 3] (`SO3.from_axis_angle`)."""
    return SO3.from_axis_angle(*_converted(xnp, axis, angle)).matrix


def yaw_rotation(yaw: float) -> np.ndarray:
    """Rotation about +z by `yaw` radians, [3, 3] float64 (`SO3.from_z_radians`)."""
    return SO3.from_z_radians(yaw).matrix


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly random rotation (QR of a Gaussian matrix, det fixed to +1), [3, 3] float64."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def random_rotation_jax(key):
    """Uniformly random rotation from a jax PRNG key (for property tests under jit), [3, 3]."""
    q, r = jnp.linalg.qr(jax.random.normal(key, (3, 3)))
    q = q * jnp.sign(jnp.diag(r))
    flip = jnp.where(jnp.linalg.det(q) < 0, -1.0, 1.0)
    return q.at[:, 0].multiply(flip)


def orthonormalize(T):
    """The nearest rigid transform: the rotation block of T ([..., 4, 4], or [..., 3, 3]) projected onto
    SO(3) by SVD (`U V^T`, det fixed to +1), the last row reset to [0 0 0 1]; same dtype, numpy.

    Every pose that jaxmap composes, integrates or optimises goes through this where it is produced, so
    chains of thousands of float64 products stay on SE(3) (|R^T R - I| ~ 1e-15) instead of drifting off
    it (open3d's optimiser and long ICP chains leave ~1e-3 after a few hundred frames).
    """
    T = np.asarray(T)
    return (SO3(T) if T.shape[-1] == 3 else SE3(T)).orthonormalize().matrix


def path_length(positions) -> float:
    """Length (m) of the path through positions [N, 3] in order (0 for fewer than two)."""
    p = np.reshape(np.asarray(positions, np.float64), (-1, 3))
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def compose(*poses):
    """Product of rigid transforms [4, 4] (left to right) in float64, re-orthonormalised (`orthonormalize`)."""
    out = SE3.from_matrix(np.asarray(poses[0], np.float64))
    for P in poses[1:]:
        out = out @ SE3.from_matrix(np.asarray(P, np.float64))
    return out.orthonormalize().matrix


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
