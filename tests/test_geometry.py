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
    # the same formulas; the inverse's product may round in another order (a last-bit difference)
    assert ang == pytest.approx(rotation_angle(D[:3, :3]), rel=1e-12, abs=1e-15)
    assert dist == pytest.approx(np.linalg.norm(D[:3, 3]), rel=1e-12)
    np.testing.assert_array_equal(compose(T, S), orthonormalize(T @ S))
    np.testing.assert_allclose(orthonormalize(T @ S), T @ S, atol=1e-12)
    np.testing.assert_allclose(yaw_rotation(0.7), rotation_from_axis_angle(np.array([0, 0, 1.0]), 0.7), atol=1e-15)
    # jax arrays stay jax arrays through the helpers
    assert isinstance(transform_points(jnp.asarray(T, jnp.float32), jnp.asarray(p, jnp.float32)), jax.Array)
    assert isinstance(transform_points(T, p, jnp), jax.Array)


# ------------------------------------------------------------------------------------------------
# the precision rule: products of poses and points at full float32 on a GPU too
# ------------------------------------------------------------------------------------------------


def _tf32(x):
    """x as a GPU's tensor cores read a float32 operand by default: 10 mantissa bits (TF32)."""
    return jax.lax.reduce_precision(x, exponent_bits=8, mantissa_bits=10) if x.dtype == jnp.float32 else x


def _full_precision(params) -> bool:
    p = params.get("precision")
    return p is not None and all(q == jax.lax.Precision.HIGHEST for q in (p if isinstance(p, tuple) else (p, p)))


def _eval_as_on_a_gpu(jaxpr, consts, *args):
    """Evaluate `jaxpr` as XLA on a GPU computes it by default: every dot_general below
    Precision.HIGHEST gets its float32 operands rounded to TF32 (and accumulates in float32). On the CPU,
    where XLA ignores the precision of a dot, this is the only way to see what a GPU does."""
    from jax.extend.core import Literal

    env = dict(zip(jaxpr.constvars, consts)) | dict(zip(jaxpr.invars, args))
    for eqn in jaxpr.eqns:
        ins = [v.val if isinstance(v, Literal) else env[v] for v in eqn.invars]
        if eqn.primitive.name == "dot_general" and not _full_precision(eqn.params):
            ins = [_tf32(x) for x in ins]
        outs = eqn.primitive.bind(*ins, **{k: _sub_programs_on_a_gpu(v) for k, v in eqn.params.items()})
        for v, x in zip(eqn.outvars, outs if eqn.primitive.multiple_results else [outs]):
            env[v] = x
    return [v.val if isinstance(v, Literal) else env[v] for v in jaxpr.outvars]


def _sub_programs_on_a_gpu(v):
    """A primitive's parameter with the programs in it (loop bodies, branches, solves) as on a GPU."""
    from jax.extend.core import ClosedJaxpr

    if isinstance(v, ClosedJaxpr):
        return _on_a_gpu_jaxpr(v)
    if isinstance(v, tuple) and any(isinstance(x, ClosedJaxpr) for x in v):
        items = [_sub_programs_on_a_gpu(x) for x in v]
        return type(v)(*items) if hasattr(v, "_fields") else tuple(items)
    return v


def _on_a_gpu_jaxpr(closed):
    """A sub-program (of a loop, a branch, a jit) with its dots rounded as `_eval_as_on_a_gpu` does."""
    avals = [jax.ShapeDtypeStruct(v.aval.shape, v.aval.dtype) for v in closed.jaxpr.invars]
    return jax.make_jaxpr(lambda *a: _eval_as_on_a_gpu(closed.jaxpr, closed.consts, *a))(*avals)


def as_on_a_gpu(fn):
    """fn, computed as a GPU's default float32 matrix units would (`_eval_as_on_a_gpu`)."""
    def run(*args):
        closed, shape = jax.make_jaxpr(fn, return_shape=True)(*args)
        flat = _eval_as_on_a_gpu(closed.jaxpr, closed.consts, *jax.tree_util.tree_leaves(args))
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(shape), flat)
    return run


def _scene_at_50m(n=2000, seed=0):
    """Sensor-frame points [n, 3] float32 up to 50 m, and a pose [4, 4] float32 50 m from the origin."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    pts = (d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(5, 50, (n, 1))).astype(np.float32)
    T = np.eye(4, dtype=np.float32)
    T[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 1.1]).as_matrix()
    T[:3, 3] = (35.0, -35.0, 2.0)
    return pts, T


def test_pose_products_keep_float32_precision_where_a_gpu_would_round_to_tf32():
    """A 50 m scan moved by a pose 50 m out: computed as a GPU's default float32 dot does (operands
    rounded to TF32, emulated here), the plain matmul misplaces points by millimetres to centimetres,
    SE3.apply (the `geometry` rule: Precision.HIGHEST) by float32 rounding only (micrometres)."""
    pts, T = _scene_at_50m()
    exact = pts.astype(np.float64) @ T[:3, :3].astype(np.float64).T + T[:3, 3]
    rule = np.asarray(as_on_a_gpu(lambda p, T: SE3.from_matrix(T).apply(p))(jnp.asarray(pts), jnp.asarray(T)))
    plain = np.asarray(as_on_a_gpu(lambda p, T: p @ T[:3, :3].T + T[:3, 3])(jnp.asarray(pts), jnp.asarray(T)))
    err_rule, err_plain = (np.abs(x - exact).max() for x in (rule, plain))
    assert err_rule < 2e-5, err_rule                   # float32 at 70 m: ~4 um
    assert 1e-3 < err_plain < 5e-2, err_plain          # what the rule prevents: mm to cm
    # the emulation leaves full-precision products alone, and the rule changes nothing on the CPU
    np.testing.assert_array_equal(rule, np.asarray(jnp.asarray(pts) @ jnp.asarray(T[:3, :3]).T + T[:3, 3]))


def _box_sdf(x):
    """Signed distance to the inside of a 120 x 120 x 30 m box centred at (20, -20, 10): walls all round
    a scan taken 50 m from the origin (a pose pins down against it in every direction)."""
    q = jnp.abs(x - jnp.array([20.0, -20.0, 10.0])) - jnp.array([60.0, 60.0, 15.0])
    return -jnp.max(q, axis=-1), jnp.ones(x.shape[:-1], bool)


def _pose_consumers():
    """(name, fn, args) of every place a pose moves float32 points on the device."""
    from jaxmap.config import load_config
    from jaxmap.imt.latent_map import VoxelBatch
    from jaxmap.imt.interpolation import splat_trilinear
    from jaxmap.imt.vn import rotate_jacobians
    from jaxmap.n3.scan import to_raw
    from jaxmap.n3.scan_batch import preprocess_raw
    from jaxmap.n3.state import N3Static
    from jaxmap.slam.track import TrackOptions, grid_search, refine_pose

    pts, T = _scene_at_50m(1024)
    P, T, R, t = jnp.asarray(pts), jnp.asarray(T), jnp.asarray(T[:3, :3]), jnp.asarray(T[:3, 3])
    rng = np.random.default_rng(1)
    # the scan, on the walls of the box, seen from a sensor at T
    inside = SE3.from_matrix(T).inverse().apply(jnp.asarray(rng.uniform([-40, -80, -5], [80, 40, 25], (1024, 3)),
                                                            jnp.float32))
    near = jnp.asarray(Rotation.from_rotvec([0.0, 0.0, 0.02]).as_matrix(), jnp.float32) @ R
    mask = jnp.ones(1024, bool)
    batch = VoxelBatch(jnp.asarray(rng.integers(200, 300, (256, 3)), jnp.int32),
                       jnp.asarray(rng.normal(size=(256, 4, 3)), jnp.float32),
                       jnp.asarray(rng.normal(size=(256, 4, 3, 3)), jnp.float32),
                       jnp.ones(256, jnp.float32), jnp.ones(256, bool))
    cfg = load_config("configs/city.yaml", ["preprocess.device=true", "preprocess.normals=grid",
                                            "preprocess.max_range_m=60.0", "preprocess.normal_cell_m=0.5",
                                            "preprocess.veil_m=0.0"])  # no layout read off a scan here
    raw = to_raw(pts, np.asarray(T, np.float64), np.zeros(3), 1024)
    search = opts = TrackOptions(iterations=8, max_points=1024, search_points=256)  # (grid_search reads search_*)
    return [
        ("SE3.apply", lambda p, T: SE3.from_matrix(T).apply(p), (P, T)),
        ("SE3 @ SE3.inverse", lambda T: (SE3.from_matrix(T) @ SE3.from_matrix(T).inverse()).matrix, (T,)),
        ("SO3.apply", lambda p, R: SO3.from_matrix(R).apply(p), (P, R)),
        ("slam.track.refine_pose", lambda p, R, t: refine_pose(_box_sdf, inside, mask, R, t, opts)[:2],
         (P, near, t)),
        ("slam.track.grid_search", lambda R, t: SE3.from_rotation_and_translation(*grid_search(
            _box_sdf, inside, mask, R, t, jnp.array([1.0, 0.1]), search)).apply(inside), (near, t)),
        ("imt.interpolation.splat_trilinear", lambda T: splat_trilinear(batch, T, 0.4), (T,)),
        ("imt.vn.rotate_jacobians", lambda R: rotate_jacobians(batch.jac, R), (R,)),
        ("n3.scan_batch.preprocess_raw", lambda raw: preprocess_raw(N3Static.from_config(cfg), raw, 1024)[0],
         (jax.device_put(raw),)),
    ]


@pytest.mark.parametrize("case", range(8))
def test_every_place_a_pose_moves_points_follows_the_rule(case):
    """Each device program that moves points by a pose gives the same result when computed as a GPU's
    default float32 dot would (TF32 operands, `as_on_a_gpu`) as on the CPU (float32 throughout), to
    float32 rounding: its products go through `geometry.matmul` / `einsum`. A product written as a plain
    `@` or `jnp.einsum` (points 50 m out) differs by millimetres to centimetres."""
    name, fn, args = _pose_consumers()[case]
    cpu, gpu = jax.jit(fn)(*args), as_on_a_gpu(fn)(*args)
    for a, b in zip(jax.tree_util.tree_leaves(cpu), jax.tree_util.tree_leaves(gpu)):
        a, b = np.asarray(a), np.asarray(b)
        if a.dtype == np.float32:
            scale = float(np.abs(a).max())
            assert np.abs(a - b).max() <= 1e-5 * scale + 1e-4, (name, np.abs(a - b).max())
        else:
            np.testing.assert_array_equal(a, b, err_msg=name)
