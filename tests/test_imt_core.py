"""The transformable map's pure core (`jaxmap.imt.core`): one compiled program per frame, an immutable
keyframe store, growth that re-runs a frame, and removal that subtracts exactly what was fused."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmap.geometry import make_pose, random_rotation
from jaxmap.imt import core, load_prior
from jaxmap.imt import latent_map as lm
from jaxmap.imt.keyframe_store import KeyframeStore

STATIC = core.ImtStatic(voxel_size=0.1, min_points=10, cells_per_voxel=1)


@pytest.fixture(scope="module")
def prior():
    return load_prior()


def frame_cells(k: int, n: int = 3000):
    """Pooled cells of a wavy wall and a floor seen from pose k (world frame), with that pose."""
    rng = np.random.default_rng(k)
    x, y = rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n)
    wall = np.column_stack([x, np.full(n, 1.0) + 0.05 * np.sin(3 * x), y + 1.5])
    floor = np.column_stack([x, y, np.zeros(n)])
    pts = np.concatenate([wall, floor]) + 0.05 * k
    nrm = np.concatenate([np.tile([0.0, -1.0, 0.0], (n, 1)), np.tile([0.0, 0.0, 1.0], (n, 1))])
    pose = make_pose(random_rotation(rng), rng.normal(size=3))
    return lm.pool_cells(pts, nrm, STATIC.voxel_size, STATIC.cells_per_voxel), pose


def build(prior, n_frames: int, capacity: int = 1 << 16, hints=None):
    state, store, hints = core.init(STATIC, capacity, prior.latent_channels), KeyframeStore(), hints or {}
    for k in range(n_frames):
        cells, pose = frame_cells(k)
        state, store, _ = core.integrate(STATIC, state, store, prior, cells, pose, k, hints)
    return state, store


def map_dict(state):
    m = state.map
    w = np.asarray(m.weight)
    sel = np.flatnonzero(w > 0)
    order = np.lexsort(np.asarray(m.coords)[sel].T[::-1])
    return np.asarray(m.coords)[sel][order], w[sel][order], np.asarray(m.latent_sum)[sel][order]


def test_a_frame_is_one_compiled_program_with_one_host_read(prior, monkeypatch):
    hints = {2048: 1 << 15}   # a scratch table that no frame here overflows (8 voxels x 2048 cells fit)
    state, store = build(prior, 1, hints=hints)                         # compiles the frame program
    compiles, calls = [], []
    listener = lambda event, secs, **kw: compiles.append(event) if event == "/jax/core/compile/backend_compile_duration" else None  # noqa: E731
    jax.monitoring.register_event_duration_secs_listener(listener)
    real = core.step
    monkeypatch.setattr(core, "step", lambda *a: calls.append(a[-1]) or real(*a))
    try:
        for k in range(1, 4):
            cells, pose = frame_cells(k)
            # any implicit device -> host copy (a `bool(x)`, an `np.asarray`) raises; the stats read is explicit
            with jax.transfer_guard_device_to_host("disallow"):
                state, store, stats = core.integrate(STATIC, state, store, prior, cells, pose, k, hints)
            assert stats.ok
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert compiles == []                    # frames 2..4: same bucket, same capacities, nothing compiles
    assert len(calls) == 3                   # and each is one call of the one jitted program
    assert int(state.active) == state.map.num_active() and len(store) == 4


def test_the_store_is_immutable_and_remap_returns_a_new_one(prior):
    state, store = build(prior, 3)
    before = store.poses().copy()
    assert all(not p.flags.writeable for p in store.points)
    new = before.copy()
    new[1] = make_pose(random_rotation(np.random.default_rng(5)), [0.05, 0.0, 0.0]) @ before[1]
    state2, store2, changed = core.remap(STATIC, state, store, prior, new)
    assert changed == [1] and store2 is not store
    np.testing.assert_array_equal(store.poses(), before)                 # the old store is unchanged
    np.testing.assert_allclose(store2.poses(), new)
    bigger = store.add(9, *frame_cells(9)[0], before[0])
    assert len(store) == 3 and len(bigger) == 4
    with pytest.raises((AttributeError, TypeError)):
        store.frames = ()
    assert int(state2.active) == state2.map.num_active()


def test_growth_on_overflow_reruns_the_frame_and_gives_the_big_capacity_map(prior):
    small, _ = build(prior, 3, capacity=1024)          # 1024 slots = 512 rows: grows (several times)
    big, _ = build(prior, 3, capacity=1 << 16)
    assert small.map.table.capacity > 1024
    a, b = map_dict(small), map_dict(big)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[2], b[2])
    assert int(small.active) == int(big.active) == len(a[0])


def test_removing_a_keyframe_subtracts_exactly_what_its_fusion_added(prior):
    state, store = build(prior, 2)
    w0, s0 = map_dict(state)[1:]
    ref = jax.tree_util.tree_map(jnp.copy, state)
    cells, pose = frame_cells(2)
    state, store, _ = core.integrate(STATIC, state, store, prior, cells, pose, 2, {})
    state = core.apply_keyframes(STATIC, state, store, prior, [2], store.poses()[2:], np.float32([-1.0]), {})
    c1, w1, s1 = map_dict(state)
    np.testing.assert_array_equal(c1, map_dict(ref)[0])                  # the same voxels ...
    np.testing.assert_allclose(w1, w0, rtol=1e-6)                        # ... weights and sums, to float32 rounding
    np.testing.assert_allclose(s1, s0, atol=1e-6 * np.abs(s0).max())
    assert int(state.active) == len(c1)
