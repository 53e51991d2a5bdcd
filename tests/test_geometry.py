"""The SO3 / SE3 pytree types: group laws, agreement with plain matrix maths and scipy, numpy float64 vs
jax float32, batching, jit and vmap; and the raw-matrix helpers staying bit-identical to the types."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from jaxmap.geometry import (SE3, SO3, compose, make_pose, orthonormalize, pose_change, random_rotation,
                             rotate_vectors, rotation_angle, rotation_from_axis_angle, se3_inverse,
                             transform_points, yaw_rotation)

seeds = st.integers(0, 2**32 - 1)


def random_se3(rng, batch=()):
    """SE3 float64 [*batch, 4, 4]: uniform rotations (scipy), translations ~ N(0, 10 m)."""
    n = int(np.prod(batch))
    R = Rotation.random(max(n, 1), random_state=rng).as_matrix().reshape(*batch, 3, 3)
    t = rng.normal(scale=10.0, size=(*batch, 3))
    return SE3.from_rotation_and_translation(R, t)


@settings(max_examples=30, deadline=None)
@given(seeds)
def test_group_laws(seed):
    rng = np.random.default_rng(seed)
    a, b, c = (random_se3(rng) for _ in range(3))
    ident = SE3.identity()
    np.testing.assert_allclose(((a @ b) @ c).matrix, (a @ (b @ c)).matrix, atol=1e-9)
    np.testing.assert_allclose((a @ a.inverse()).matrix, ident.matrix, atol=1e-12)
    np.testing.assert_allclose((a.inverse() @ a).matrix, ident.matrix, atol=1e-12)
    np.testing.assert_array_equal((a @ ident).matrix, a.matrix)
    np.testing.assert_allclose((a @ b).inverse().matrix, (b.inverse() @ a.inverse()).matrix, atol=1e-9)
    np.testing.assert_allclose(a.inverse().matrix, np.linalg.inv(a.matrix), atol=1e-9)
    r = a.rotation()
    np.testing.assert_allclose((r @ r.inverse()).matrix, np.eye(3), atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(seeds, st.integers(1, 40))
def test_apply_is_matrix_maths(seed, n):
    rng = np.random.default_rng(seed)
    T = random_se3(rng)
    p = rng.normal(scale=20.0, size=(n, 3))
    homog = np.concatenate([p, np.ones((n, 1))], axis=1) @ T.matrix.T
    np.testing.assert_allclose(T.apply(p), homog[:, :3], atol=1e-9)
    # against scipy: R p + t
    ref = Rotation.from_matrix(T.rotation().matrix).apply(p) + T.translation()
    np.testing.assert_allclose(T.apply(p), ref, atol=1e-9)
    np.testing.assert_allclose(T.rotation().apply(p), Rotation.from_matrix(T.rotation().matrix).apply(p), atol=1e-9)
    # the composition acts like applying one after the other; the inverse undoes apply
    S = random_se3(rng)
    np.testing.assert_allclose((T @ S).apply(p), T.apply(S.apply(p)), atol=1e-9)
    np.testing.assert_allclose(T.inverse().apply(T.apply(p)), p, atol=1e-9)


def test_batched():
    rng = np.random.default_rng(0)
    T = random_se3(rng, (5, 2))
    assert T.batch_shape == (5, 2) and T.dtype == np.float64
    p = rng.normal(size=(5, 2, 7, 3))
    out = T.apply(p)
    for i in range(5):
        for j in range(2):
            np.testing.assert_array_equal(out[i, j], T[i, j].apply(p[i, j]))
            np.testing.assert_array_equal(T.inverse()[i, j].matrix, T[i, j].inverse().matrix)
    # one cloud [N, 3] moved by every pose
    assert T.apply(p[0, 0]).shape == (5, 2, 7, 3)
    # rotation batch with one translation broadcasts
    B = SE3.from_rotation_and_translation(T.rotation(), np.ones(3))
    np.testing.assert_array_equal(B.translation(), np.ones((5, 2, 3)))
    assert SE3.identity((3,)).batch_shape == (3,) and SO3.identity((2, 4)).batch_shape == (2, 4)
    assert (T @ T.inverse()).batch_shape == (5, 2)
    np.testing.assert_allclose(T.rotation().angle(), Rotation.from_matrix(T.rotation().matrix.reshape(-1, 3, 3))
                               .magnitude().reshape(5, 2), atol=1e-7)


@settings(max_examples=15, deadline=None)
@given(seeds)
def test_numpy_float64_vs_jax_float32(seed):
    rng = np.random.default_rng(seed)
    T, S = random_se3(rng), random_se3(rng)
    p = rng.normal(scale=20.0, size=(50, 3))
    Tj, Sj, pj = T.astype(np.float32).matrix, S.astype(np.float32).matrix, jnp.asarray(p, jnp.float32)
    Tj, Sj = SE3(jnp.asarray(Tj)), SE3(jnp.asarray(Sj))
    for host, dev in [(T.apply(p), Tj.apply(pj)), ((T @ S).matrix, (Tj @ Sj).matrix),
                      (T.inverse().matrix, Tj.inverse().matrix), (T.rotation().apply(p), Tj.rotation().apply(pj)),
                      (T.orthonormalize().matrix, Tj.orthonormalize().matrix)]:
        assert isinstance(dev, jax.Array) and dev.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(dev), host, atol=1e-4 * max(1.0, np.abs(host).max()))


def test_jit_and_vmap():
    rng = np.random.default_rng(1)
    T = random_se3(rng, (4,)).astype(np.float32)
    Tj = jax.tree_util.tree_map(jnp.asarray, T)
    assert isinstance(Tj, SE3) and len(jax.tree_util.tree_leaves(Tj)) == 1
    p = jnp.asarray(rng.normal(size=(4, 6, 3)), jnp.float32)

    @jax.jit
    def move(T, p):
        return (T @ T.inverse() @ T).apply(p), T.inverse()

    out, inv = move(Tj, p)
    assert isinstance(inv, SE3)
    np.testing.assert_allclose(np.asarray(out), T.apply(np.asarray(p)), atol=1e-4)
    per = jax.vmap(lambda T, p: T.apply(p))(Tj, p)
    np.testing.assert_allclose(np.asarray(per), np.asarray(Tj.apply(p)), atol=1e-6)
    # vmap over the poses with one shared cloud; scan carrying a pose
    shared = jax.vmap(lambda T: T.apply(p[0]))(Tj)
    np.testing.assert_allclose(np.asarray(shared), np.asarray(Tj.apply(p[0])), atol=1e-6)
    final, _ = jax.lax.scan(lambda c, x: (c @ x, None), SE3.identity((), jnp.float32, jnp), Tj)
    np.testing.assert_allclose(np.asarray(final.matrix), T[0].matrix @ T[1].matrix @ T[2].matrix @ T[3].matrix,
                               atol=1e-3)


def test_constructors_and_errors():
    R = SO3.from_axis_angle(np.array([0.0, 0.0, 2.0]), 0.3).matrix
    np.testing.assert_allclose(R, SO3.from_z_radians(0.3).matrix, atol=1e-15)
    np.testing.assert_allclose(R, Rotation.from_rotvec([0, 0, 0.3]).as_matrix(), atol=1e-15)
    T = SE3.from_matrix([[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    np.testing.assert_array_equal(T.translation(), [1, 2, 3])
    with pytest.raises(TypeError):
        T @ np.zeros((5, 3))
    with pytest.raises(TypeError):
        SO3.identity() @ T


@settings(max_examples=20, deadline=None)
@given(seeds)
def test_helpers_bit_identical_to_matrix_maths(seed):
    """The raw-matrix helpers are the types' operations, and those are exactly the former matrix code."""
    rng = np.random.default_rng(seed)
    R, t = random_rotation(rng), rng.normal(size=3)
    T = make_pose(R, t)
    ref = np.eye(4)
    ref[:3, :3], ref[:3, 3] = R, t
    np.testing.assert_array_equal(T, ref)
    p = rng.normal(scale=30.0, size=(20, 3))
    np.testing.assert_array_equal(transform_points(T, p), p @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_array_equal(rotate_vectors(R, p), p @ R.T)
    Rt = R.T
    inv = np.eye(4)
    inv[:3, :3], inv[:3, 3] = Rt, -(Rt @ t[:, None])[:, 0]
    np.testing.assert_array_equal(se3_inverse(T), inv)
    S = make_pose(random_rotation(rng), rng.normal(size=3))
    ang, dist = pose_change(T, S)
    D = inv @ S
    assert ang == rotation_angle(D[:3, :3]) and dist == np.linalg.norm(D[:3, 3])
    np.testing.assert_array_equal(compose(T, S), orthonormalize(T @ S))
    np.testing.assert_allclose(orthonormalize(T @ S), T @ S, atol=1e-12)
    np.testing.assert_allclose(yaw_rotation(0.7), rotation_from_axis_angle(np.array([0, 0, 1.0]), 0.7), atol=1e-15)
    # jax arrays stay jax arrays through the helpers
    assert isinstance(transform_points(jnp.asarray(T, jnp.float32), jnp.asarray(p, jnp.float32)), jax.Array)
    assert isinstance(transform_points(T, p, jnp), jax.Array)
