"""Multi-level corner features: numpy reference, linear-field exactness, weights, gradients, floor-division design."""

import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxmap.grid import features as F
from jaxmap.grid import hashing as H

N = 16  # points per example (fixed so op-by-op dispatch and jit caches are reused)
SETTINGS = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])

leaf_st = st.sampled_from([0.1, 0.2, 0.25, 0.3, 0.5])
levels_st = st.integers(1, 4)
alloc_levels_st = st.sampled_from([1, 3])  # tests that allocate in the hash table (one compile per L)
seed_st = st.integers(0, 2**31 - 1)


ROWS = 2048  # feature tables are padded to this many rows so the jitted helpers compile once per L


@functools.partial(jax.jit, static_argnums=2)
def keys_and_weights(pts, leaf, levels):
    """leaf voxel [N,3], corner keys [N,L*8,4], weights [N,L*8] (leaf traced: one compile per L)."""
    vox = F.leaf_voxel(pts, leaf)
    return vox, F.corner_keys(vox, levels), F.corner_weights(pts, vox, leaf, levels)


def _field(pts, vox, leaf, levels, feats, rows, coef):
    return F.interpolate(feats, rows, F.corner_weights(pts, vox, leaf, levels)) @ coef  # [N]


field = jax.jit(_field, static_argnums=3)
# d/dx of the per-point field: points are independent, so the gradient of the sum is per point
field_grad = jax.jit(jax.grad(lambda *a: _field(*a).sum()), static_argnums=3)


def allocate(vox, levels, table=None):
    """allocate_corners with the voxel batch padded to N rows (valid mask) and one capacity that
    always fits, so the insert compiles once per L. Returns (table, rows [len(vox), L*8])."""
    vox = np.asarray(vox, np.int32)
    m = len(vox)
    assert m <= N
    pad = np.zeros((N, 3), np.int32)
    pad[:m] = vox
    table = H.create(2048) if table is None else table
    table, rows, overflow, _ = F.allocate_corners(table, jnp.asarray(pad), levels, jnp.arange(N) < m, 1024)
    assert not bool(overflow)
    assert np.all(np.asarray(rows[m:]) == -1)
    return table, rows[:m]


def padded(feats):
    feats = np.asarray(feats, np.float32)
    out = np.zeros((ROWS, feats.shape[1]), np.float32)
    out[: len(feats)] = feats
    return jnp.asarray(out)


def random_points(seed, leaf, n=N, extent=30.0):
    """Random points, a quarter of them exactly on (float32) voxel faces, some just beside them."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-extent, extent, size=(n, 3))
    k = rng.integers(-int(extent / leaf), int(extent / leaf), size=(n // 4, 3))
    pts[: n // 4] = k * leaf
    pts = pts.astype(np.float32)
    pts[n // 4 : n // 4 + 2] = np.nextafter(pts[:2], np.float32(-np.inf))
    return pts


# ----------------------------------------------------------------------------------------------
# slow, obviously-correct reference
# ----------------------------------------------------------------------------------------------


def ref_leaf(x, leaf):
    """The leaf index as specified: the unique v with fl32(v * leaf) <= x < fl32((v + 1) * leaf)."""
    x = np.float32(x)
    if abs(x) < np.finfo(np.float32).tiny:
        x = np.float32(0.0)  # XLA flushes subnormals to zero
    leaf = np.float32(leaf)
    v = math.floor(float(x) / float(leaf))  # float64 estimate, then search the exact float32 cell
    while np.float32(v) * leaf > x:
        v -= 1
    while np.float32(v + 1) * leaf <= x:
        v += 1
    return v


def ref_point(p, leaf, levels):
    """Corner keys [L*8, 4] and weights [L*8] of one point, with Python scalars and loops."""
    v0 = [ref_leaf(p[d], leaf) for d in range(3)]
    keys, weights = [], []
    for lvl in range(levels):
        vl = [v // 2**lvl for v in v0]  # Python floor division
        s = leaf * 2**lvl
        frac = [min(max((float(p[d]) - vl[d] * s) / s, 0.0), 1.0) for d in range(3)]
        for c in itertools.product((0, 1), repeat=3):
            keys.append([vl[0] + c[0], vl[1] + c[1], vl[2] + c[2], lvl])
            w = 1.0
            for d in range(3):
                w *= frac[d] if c[d] else 1.0 - frac[d]
            weights.append(w)
    return np.array(keys), np.array(weights), v0


def ref_interpolate(table, rows, weights):
    out = np.zeros((rows.shape[0], table.shape[1]))
    for i in range(rows.shape[0]):
        for k in range(rows.shape[1]):
            if rows[i, k] >= 0:
                out[i] += weights[i, k] * table[rows[i, k]].astype(np.float64)
    return out


interp = jax.jit(F.interpolate)
interp_grad_table = jax.jit(jax.grad(lambda t, r, w: F.interpolate(t, r, w).sum()))


@SETTINGS
@given(seed=seed_st, leaf=leaf_st, levels=levels_st)
def test_matches_numpy_reference(seed, leaf, levels):
    pts = random_points(seed, leaf)
    vox, keys, w = keys_and_weights(jnp.asarray(pts), leaf, levels)
    keys, w = np.asarray(keys), np.asarray(w)
    # the un-jitted library calls give the same (leaf as a Python float: a compile-time constant)
    np.testing.assert_array_equal(np.asarray(F.corner_keys(F.leaf_voxel(jnp.asarray(pts), leaf), levels)), keys)
    assert keys.shape == (N, levels * 8, 4) and keys.dtype == np.int32
    assert w.shape == (N, levels * 8) and w.dtype == np.float32
    # float32 rounding of frac = (x - v*s)/s is about eps * |x| / s
    tol = 4e-7 * (1 + 30.0 / leaf)
    for i, p in enumerate(pts):
        rk, rw, v0 = ref_point(p, leaf, levels)
        np.testing.assert_array_equal(np.asarray(vox[i]), v0)
        np.testing.assert_array_equal(keys[i], rk)
        np.testing.assert_allclose(w[i], rw, atol=tol)

    # interpolate: rows from a dict holding ~70% of the keys; the rest are -1 and must contribute 0
    rng = np.random.default_rng(seed)
    uniq = {tuple(k) for k in keys.reshape(-1, 4)}
    kept = [k for k in sorted(uniq) if rng.random() < 0.7]
    row_of = {k: r + 1 for r, k in enumerate(kept)}  # row 0 is a poisoned row nobody owns
    table = rng.normal(size=(len(kept) + 1, 5)).astype(np.float32)
    table[0] = np.nan
    rows = np.array([[row_of.get(tuple(k), -1) for k in pk] for pk in keys], np.int32)
    table = padded(table).at[len(kept) + 1 :].set(np.inf)  # padding rows are never read either
    got = np.asarray(interp(table, jnp.asarray(rows), jnp.asarray(w)))
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, ref_interpolate(np.asarray(table), rows, w), rtol=1e-5, atol=1e-5)
    # gradient w.r.t. the table is the scatter-add of the weights (masked rows get nothing)
    g = interp_grad_table(table, jnp.asarray(rows), jnp.asarray(w))
    expect = np.zeros(ROWS)
    np.add.at(expect, rows[rows >= 0], w[rows >= 0])
    np.testing.assert_allclose(np.asarray(g), np.repeat(expect[:, None], 5, 1), rtol=1e-5, atol=1e-6)


@SETTINGS
@given(seed=seed_st, leaf=leaf_st, levels=levels_st)
def test_weights_partition_of_unity(seed, leaf, levels):
    pts = random_points(seed, leaf)
    w = np.asarray(keys_and_weights(jnp.asarray(pts), leaf, levels)[2]).reshape(N, levels, 8)
    assert np.all(w >= 0.0) and np.all(w <= 1.0)
    np.testing.assert_allclose(w.sum(-1), 1.0, atol=1e-5)


# ----------------------------------------------------------------------------------------------
# linear fields through the real hash table
# ----------------------------------------------------------------------------------------------


def linear_table(table, a, d, leaf):
    """Features [ROWS, D]: the linear field a @ pos + d at every stored corner's position."""
    keys, rows = H.entries(table)
    pos = keys[:, :3].astype(np.float64) * leaf * (2.0 ** keys[:, 3:4])  # corner position in metres
    feats = np.zeros((int(table.count), a.shape[0]), np.float32)
    feats[rows] = pos @ a.T + d
    return padded(feats)


@SETTINGS
@given(seed=seed_st, leaf=leaf_st, levels=alloc_levels_st)
def test_linear_field_is_reproduced_exactly(seed, leaf, levels):
    rng = np.random.default_rng(seed)
    pts = random_points(seed, leaf, extent=10.0)
    a = rng.normal(size=(3, 3))
    d = rng.normal(size=3)
    vox, _, w = keys_and_weights(jnp.asarray(pts), leaf, levels)
    table, rows = allocate(vox, levels)
    feats = linear_table(table, a, d, leaf)
    want = pts.astype(np.float64) @ a.T + d  # [N, 3]
    scale = np.abs(a).sum(1) * 11.0 + np.abs(d)  # magnitude of the terms, for a relative tolerance
    per_level = np.asarray(interp_levels(feats, rows, w))  # [L, N, 3]
    for lvl in range(levels):  # each level alone reproduces the field
        assert np.all(np.abs(per_level[lvl] - want) < 1e-5 * scale)
    got = np.asarray(interp(feats, rows, w))  # summed over levels
    assert np.all(np.abs(got - levels * want) < 1e-5 * levels * scale)

    # d/dx through the weights equals the field's gradient (times L when summed), at faces too
    coef = rng.normal(size=3)
    g = np.asarray(field_grad(jnp.asarray(pts), vox, leaf, levels, feats, rows, jnp.asarray(coef, jnp.float32)))
    np.testing.assert_allclose(g, np.broadcast_to(levels * coef @ a, g.shape), rtol=1e-4, atol=1e-4 * levels)


@jax.jit
def interp_levels(feats, rows, w):
    """[L, N, D]: each level's interpolation alone (the other levels' weights zeroed)."""
    levels = w.shape[1] // 8
    mask = (jnp.arange(levels)[:, None] == jnp.arange(levels * 8)[None] // 8)  # [L, L*8]
    return jax.vmap(lambda m: F.interpolate(feats, rows, jnp.where(m[None], w, 0.0)))(mask)


@SETTINGS
@given(seed=seed_st, leaf=leaf_st, levels=alloc_levels_st)
def test_gradient_matches_finite_differences(seed, leaf, levels):
    rng = np.random.default_rng(seed)
    v = rng.integers(-50, 50, size=(N, 3))
    u = rng.uniform(0.1, 0.9, size=(N, 3))  # away from leaf faces: the field is multilinear there
    pts = ((v + u) * leaf).astype(np.float32)
    vox = keys_and_weights(jnp.asarray(pts), leaf, levels)[0]
    np.testing.assert_array_equal(np.asarray(vox), v)
    table, rows = allocate(vox, levels)
    feats = padded(rng.normal(size=(int(table.count), 3)))
    coef = jnp.asarray(rng.normal(size=3), jnp.float32)
    g = np.asarray(field_grad(jnp.asarray(pts), vox, leaf, levels, feats, rows, coef))
    eps = 0.05 * leaf
    fd = np.zeros_like(g)
    for dim in range(3):
        e = np.zeros(3, np.float32)
        e[dim] = eps
        hi = np.asarray(field(jnp.asarray(pts + e), vox, leaf, levels, feats, rows, coef), np.float64)
        lo = np.asarray(field(jnp.asarray(pts - e), vox, leaf, levels, feats, rows, coef), np.float64)
        fd[:, dim] = (hi - lo) / (2 * eps)
    # multilinear along each axis => central differences are exact up to float32 rounding of f
    fscale = float(jnp.abs(feats).max()) * float(jnp.abs(coef).sum()) * levels
    np.testing.assert_allclose(g, fd, atol=2e-6 * fscale / eps + 1e-4 * np.abs(g).max())


# ----------------------------------------------------------------------------------------------
# the floor-division design
# ----------------------------------------------------------------------------------------------


def test_level_voxels_floor_division_negative():
    v = jnp.array([[-1, -3, 3], [-4, 0, 7], [-5, 5, -8]], jnp.int32)
    got = np.asarray(F.level_voxels(v, 4))
    want = np.array([[[x // 2**lvl for x in row] for lvl in range(4)] for row in np.asarray(v)])
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got[0, :, 0], [-1, -1, -1, -1])  # not truncation towards zero
    np.testing.assert_array_equal(got[0, :, 1], [-3, -2, -1, -1])


def boundary_points(seed, leaf, n):
    """Points exactly on leaf-voxel faces (as float32), their neighbours one ulp away, negative too."""
    rng = np.random.default_rng(seed)
    k = rng.integers(-200, 200, size=(n, 3))
    pts = (k * leaf).astype(np.float32)
    step = rng.integers(-1, 2, size=(n, 3))
    pts = np.where(step < 0, np.nextafter(pts, np.float32(-np.inf)), pts)
    pts = np.where(step > 0, np.nextafter(pts, np.float32(np.inf)), pts)
    return pts


@SETTINGS
@given(seed=seed_st, leaf=leaf_st, levels=alloc_levels_st)
def test_same_leaf_voxel_same_rows(seed, leaf, levels):
    rng = np.random.default_rng(seed)
    # 4 groups of points inside one leaf voxel each: lower corner (on the faces), interior, one ulp
    # below the upper faces; plus boundary points anywhere, negative coordinates included
    v = rng.integers(-100, 100, size=(4, 3))
    lo = (v * leaf).astype(np.float32)
    hi = np.nextafter(((v + 1) * leaf).astype(np.float32), np.float32(-np.inf))
    mid = ((v + rng.uniform(0, 1, size=(4, 3))) * leaf).astype(np.float32)
    pts = np.concatenate([lo, mid, hi, boundary_points(seed, leaf, N - 12)]).astype(np.float32)
    vox = F.leaf_voxel(jnp.asarray(pts), leaf)
    table, rows = allocate(vox, levels)
    rows = np.asarray(rows)
    vox = np.asarray(vox)
    # points sharing a leaf voxel share all L*8 corner rows
    for i in range(len(pts)):
        for j in range(len(pts)):
            if np.array_equal(vox[i], vox[j]):
                np.testing.assert_array_equal(rows[i], rows[j])
    # allocating per leaf voxel covers every point: the query path (lookup) finds all L*8 corners
    feats = padded(rng.normal(size=(int(table.count), 2)))
    f, rows_q = F.query_features(table, feats, jnp.asarray(pts), leaf, levels)
    np.testing.assert_array_equal(np.asarray(rows_q), rows)  # the query finds the allocated rows
    want = field(jnp.asarray(pts), jnp.asarray(vox), leaf, levels, feats, jnp.asarray(rows), jnp.eye(2))
    np.testing.assert_allclose(np.asarray(f), np.asarray(want), rtol=1e-6, atol=1e-6)
    # every level's voxel contains the leaf voxel
    vl = np.asarray(F.level_voxels(jnp.asarray(vox), levels))
    for lvl in range(levels):
        assert np.all(vl[:, lvl] * 2**lvl <= vox) and np.all(vox < (vl[:, lvl] + 1) * 2**lvl)
    # the field is continuous across leaf faces: a point on a face gives the same feature from either
    # side's voxel (shared corner rows), so the choice floor() makes at a boundary does not matter
    face = (v * leaf).astype(np.float32)
    both = np.concatenate([v, v - 1])  # the voxel above and the one below in every axis
    table, _ = allocate(both, levels, table)
    feats = padded(rng.normal(size=(int(table.count), 2)))
    vals = []
    for vv in (v, v - 1):
        r = H.lookup(table, F.corner_keys(jnp.asarray(vv), levels).reshape(-1, 4)).reshape(4, levels * 8)
        assert np.all(np.asarray(r) >= 0)
        vals.append(np.asarray(field(jnp.asarray(face), jnp.asarray(vv), leaf, levels, feats, r, jnp.eye(2))))
    # frac = 1 vs 0 on the two sides; float32 rounding of frac is about 1e-7 * |x| / leaf (|x| <= 100 leaf)
    np.testing.assert_allclose(vals[0], vals[1], atol=2e-5 * levels * float(jnp.abs(feats).max()))


def test_leaf_voxel_exact_and_level_consistent():
    """Why v_l is derived from v_0: float division is not exact (XLA:CPU's x / 0.2 is off by one ulp on
    many face points, and x * (1/s) is what compilers turn division by constants into), so per-level
    floor(x / s_l) can disagree with the leaf index; leaf_voxel is exact and v_0 >> l is consistent."""
    leaf = 0.2
    x = (np.arange(-3000, 3000) * leaf).astype(np.float32)
    x = np.concatenate([x, np.nextafter(x, np.float32(np.inf)), np.nextafter(x, np.float32(-np.inf))])
    pts = jnp.asarray(np.stack([x, -x, x[::-1]], 1))
    v0 = np.asarray(F.leaf_voxel(pts, leaf))
    ref = np.array([[ref_leaf(c, leaf) for c in p] for p in np.asarray(pts)[::7]])
    np.testing.assert_array_equal(v0[::7], ref)
    naive = np.floor(x * (np.float32(1) / np.float32(2 * leaf))).astype(np.int64)
    assert np.any(naive != v0[:, 0] // 2)  # the naive per-level route has inconsistent face points
    vl = np.asarray(F.level_voxels(jnp.asarray(v0), 3))
    for lvl in range(3):
        np.testing.assert_array_equal(vl[:, lvl], v0 // 2**lvl)
        np.testing.assert_array_equal(vl[:, lvl], np.asarray(F.leaf_voxel(pts, leaf * 2**lvl)))
    # the same inside jit
    np.testing.assert_array_equal(np.asarray(jax.jit(F.leaf_voxel, static_argnums=1)(pts, leaf)), v0)


def test_query_features_missing_corners_and_feature_growth():
    leaf, levels = 0.2, 3
    table, rows, overflow, n_new = F.allocate_corners(H.create(256), jnp.array([[0, 0, 0], [5, 5, 5]]), levels,
                                                      jnp.array([True, False]), 128)
    np.testing.assert_array_equal(np.asarray(rows[1]), -1)
    assert int(table.count) == int(n_new) == 8 + 8 + 8 and not bool(overflow)  # one voxel's corners per level
    # past the row capacity: nothing is allocated, the table is unchanged
    same, none, over, _ = F.allocate_corners(table, jnp.array([[9, 9, 9]]), levels, jnp.array([True]), 30)
    assert bool(over) and int(same.count) == 24 and np.all(np.asarray(none) == -1)
    feats = F.init_features(jax.random.PRNGKey(0), 32, 4, 0.1)
    assert feats.shape == (32, 4) and feats.dtype == jnp.float32
    pts = jnp.array([[0.1, 0.1, 0.1], [1.1, 1.1, 1.1], [-0.1, 0.1, 0.1]], jnp.float32)
    _, rows_q = F.query_features(table, feats, pts, leaf, levels)
    found = np.sum(np.asarray(rows_q) >= 0, axis=1)
    # inside voxel 0: all 24; at leaf voxel (5,5,5) only the level-2 corner (1,1,1) is shared with
    # voxel 0's; leaf voxel (-1,0,0) shares its x=0 face (4 corners) at every level
    np.testing.assert_array_equal(np.asarray(found), [24, 1, 12])
    # a growing table's rows do not depend on when it grew (blocks of FEATURE_INIT_BLOCK rows, own keys)
    b = F.FEATURE_INIT_BLOCK
    whole = np.asarray(F.init_feature_rows(0, 0, 3 * b, 4, 0.1))
    grown = np.concatenate([np.asarray(F.init_feature_rows(0, 0, b // 2, 4, 0.1)),
                            np.asarray(F.init_feature_rows(0, b // 2, 5 * b // 2, 4, 0.1))])
    np.testing.assert_array_equal(grown, whole)


def test_init_features_std():
    f = np.asarray(F.init_features(jax.random.PRNGKey(3), 4096, 8, 0.05))
    assert f.shape == (4096, 8) and f.dtype == np.float32
    assert abs(f.std() - 0.05) < 0.002 and abs(f.mean()) < 0.002
