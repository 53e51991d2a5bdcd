"""Remapping by transform (`map.remap: transform`): keyframes keep the latent local map they were fused
with (float16 latents and Jacobians, `LatentStore`), and a remap removes a keyframe's contribution and
fuses its stored map moved by the pose change (`core.move_keyframes`). Properties: the moved stored map
equals the map encoded at the new pose (exactly for a lattice motion, within the two-branch bound for
any other); removal subtracts exactly what was fused; ten successive remaps end where one ends (no
blur accumulates); the store survives a checkpoint. And neither method's first remap builds an XLA
program: reencode reuses the frame programs (on a map that grew after its largest keyframe, and on many
small keyframes that share a batch), transform's `move_step` ran while mapping."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmap.compile_cache import programs_built
from jaxmap.errors import DataError
from jaxmap.geometry import make_pose, random_rotation, rotation_from_axis_angle, transform_points
from jaxmap.imt import core, load_prior
from jaxmap.imt import latent_map as lm
from jaxmap.imt.latent_store import LatentStore
from jaxmap.imt.meshing import query
from jaxmap.imt.keyframe_store import KeyframeStore

VS = 0.1
LATENT = core.ImtStatic(voxel_size=VS, min_points=10, cells_per_voxel=1, remap="transform")
CELLS = dataclasses.replace(LATENT, remap="reencode")


@pytest.fixture(scope="module")
def prior():
    return load_prior()


def scene(rng, n=2500):
    """A keyframe's view in its sensor frame: a wavy wall, a floor and a ball (points, unit normals)."""
    x, y = rng.uniform(-1.2, 1.2, n), rng.uniform(-1.2, 1.2, n)
    wall = np.column_stack([x, np.full(n, 1.0) + 0.08 * np.sin(4 * x), y + 1.2])
    wall_n = np.column_stack([0.32 * np.cos(4 * x), -np.ones(n), np.zeros(n)])
    floor = np.column_stack([x, y, np.zeros(n)])
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ball = np.array([0.2, 0.1, 0.45]) + 0.35 * d
    pts = np.concatenate([wall, floor, ball])
    nrm = np.concatenate([wall_n, np.tile([0.0, 0.0, 1.0], (n, 1)), d])
    return pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def cells_at(pts_s, nrm_s, pose):
    return lm.pool_cells(transform_points(pose, pts_s), nrm_s @ pose[:3, :3].T, VS, 1)


def fused(static, prior, views, poses, capacity=1 << 16):
    """(state, store) of keyframes `views` [(pts_s, nrm_s)] fused at `poses`."""
    state, store, hints = core.init(static, capacity, prior.latent_channels), static.new_store(), {}
    for k, ((p, n), T) in enumerate(zip(views, poses)):
        state, store, _ = core.integrate(static, state, store, prior, cells_at(p, n, T), T, k, hints)
    return state, store, hints


def moved(static, prior, store, ids, poses):
    """An empty map into which the stored maps of keyframes `ids` are fused, moved to `poses`."""
    state = core.init(static, 1 << 16, prior.latent_channels)
    return core.move_keyframes(static, state, store, list(ids), np.asarray(poses), np.ones(len(ids), np.float32))


def sums(state):
    """The map's voxels, weights and latent sums, sorted by voxel (host numpy)."""
    m = state.map
    w = np.asarray(m.weight)
    sel = np.flatnonzero(w > 0)
    c = np.asarray(m.coords)[sel]
    order = np.lexsort(c.T[::-1])
    return c[order], w[sel][order], np.asarray(m.latent_sum)[sel][order]


def assert_same_map(a, b, rtol=1e-5):
    (ca, wa, sa), (cb, wb, sb) = sums(a), sums(b)
    np.testing.assert_array_equal(ca, cb)
    np.testing.assert_allclose(wa, wb, rtol=rtol, atol=1e-4)
    np.testing.assert_allclose(sa, sb, atol=rtol * np.abs(sb).max())


def test_a_stored_map_moved_on_the_lattice_equals_the_map_encoded_there(prior):
    """A motion that maps the voxel lattice onto itself (90 deg about z, whole voxels): the splat puts all
    of a voxel's weight on one voxel and the first-order term vanishes, so only equivariance remains:
    the moved store must equal the encode at the new pose to the store's float16 rounding."""
    pts, nrm = scene(np.random.default_rng(0))
    T0 = make_pose(np.eye(3), np.array([0.3, -0.2, 0.1]))
    D = make_pose(rotation_from_axis_angle(np.array([0.0, 0.0, 1.0]), np.pi / 2), np.array([0.4, 0.7, -0.3]))
    _, store, _ = fused(LATENT, prior, [(pts, nrm)], [T0])
    a = moved(LATENT, prior, store, [0], [D @ T0])
    b, _, _ = fused(LATENT, prior, [(pts, nrm)], [D @ T0])
    (ca, wa, sa), (cb, wb, sb) = sums(a), sums(b)
    np.testing.assert_array_equal(ca, cb)
    np.testing.assert_allclose(wa, wb, rtol=1e-6)
    # float16 latents (rel. step 2^-10) on both sides; a latent left unrotated is off by O(1)
    np.testing.assert_allclose(sa / wa[:, None, None], sb / wb[:, None, None], atol=4e-3 * np.abs(sb / wb[:, None, None]).max())


def test_a_stored_map_moved_anywhere_is_within_the_two_branch_bound(prior):
    """Any other motion: moved stored map vs encode at the new pose, decoded SDF near the surface. The
    Jacobian term with jaxmap's sign must beat no term (and the paper's sign) by a margin."""
    rng = np.random.default_rng(1)
    pts, nrm = scene(rng)
    T0 = make_pose(random_rotation(rng), rng.normal(size=3))
    T1 = make_pose(random_rotation(rng), np.array([0.437, -0.261, 0.093])) @ T0
    _, store, _ = fused(LATENT, prior, [(pts, nrm)], [T0])
    ref, _, _ = fused(LATENT, prior, [(pts, nrm)], [T1])
    probe = transform_points(T1, pts[::6] + 0.02 * rng.normal(size=(len(pts[::6]), 3)))
    s_ref, _, v_ref = query(prior, ref.map, probe)
    err = {}
    for sign in (-1.0, 0.0, 1.0):
        st = dataclasses.replace(LATENT, jacobian_sign=sign)
        s, _, v = query(prior, moved(st, prior, store, [0], [T1]).map, probe)
        ok = v & v_ref
        assert ok.mean() > 0.9
        err[sign] = float(np.mean(np.abs(s - s_ref)[ok]))
    # measured 6.3 mm against 10.2 (no term) and 23 (paper sign)
    assert err[-1.0] < 0.008 and err[-1.0] < 0.75 * err[0.0] < 0.75 * err[1.0], err


def views_and_poses(n_kf, seed):
    rng = np.random.default_rng(seed)
    pts, nrm = scene(rng, 1500)
    poses = [make_pose(random_rotation(rng), rng.normal(size=3) * 0.3) for _ in range(n_kf)]
    # the keyframe sees the scene placed at its pose: views in the sensor frame
    return [(transform_points(np.linalg.inv(P), pts), nrm @ P[:3, :3]) for P in poses], np.asarray(poses)


def test_remap_removes_exactly_what_it_fused_and_moving_back_restores_the_map(prior):
    views, poses = views_and_poses(3, 2)
    state, store, _ = fused(LATENT, prior, views, poses)
    ref = jax.tree_util.tree_map(jnp.copy, state)
    new = poses.copy()
    new[1] = make_pose(random_rotation(np.random.default_rng(3)), [0.06, -0.03, 0.02]) @ poses[1]
    state, store, changed = core.remap(LATENT, state, store, prior, new)
    assert changed == [1] and isinstance(store, LatentStore)
    # the remapped map = keyframes 0, 2 as fused + keyframe 1's stored map moved (built afresh)
    state_fresh = core.move_keyframes(LATENT, core.init(LATENT, 1 << 16, 18), store, [0, 1, 2], new,
                                      np.ones(3, np.float32))
    assert_same_map(state, state_fresh)
    # and back: the stored map goes in as stored (no splat), so the map is the original one
    state, store, changed = core.remap(LATENT, state, store, prior, poses)
    assert changed == [1]
    assert_same_map(state, ref)
    assert int(state.active) == state.map.num_active()


def test_ten_successive_remaps_end_where_one_remap_ends(prior):
    """Every move starts from the stored map, never from the map an earlier remap left: ten loop closures
    through other poses (some moving one keyframe, some all) give the map of one remap to the last poses."""
    views, poses = views_and_poses(4, 4)
    rng = np.random.default_rng(5)
    final = np.asarray([make_pose(random_rotation(rng), rng.normal(size=3) * 0.05) @ P for P in poses])
    state, store, _ = fused(LATENT, prior, views, poses)
    once, _, _ = core.remap(LATENT, jax.tree_util.tree_map(jnp.copy, state), store, prior, final)
    current = poses.copy()
    for j in range(9):
        ids = [j % 4] if j % 3 else range(4)     # one keyframe moves (remove + fuse) or all (rebuild)
        for k in ids:
            current[k] = make_pose(rotation_from_axis_angle(rng.normal(size=3), 0.1), rng.normal(size=3) * 0.1) @ final[k]
        state, store, _ = core.remap(LATENT, state, store, prior, current)
    state, store, _ = core.remap(LATENT, state, store, prior, final)
    assert_same_map(state, once, rtol=2e-5)
    np.testing.assert_array_equal(store.poses(), final)


def test_the_latent_store_round_trips_and_says_which_setting_reads_it(prior, tmp_path):
    views, poses = views_and_poses(2, 6)
    _, store, _ = fused(LATENT, prior, views, poses)
    again = LatentStore.from_arrays(store.to_arrays())
    assert again.frames == store.frames
    for name in ("coords", "latent", "jac", "weight", "pose_encoded", "pose_fused"):
        for a, b in zip(getattr(again, name), getattr(store, name)):
            np.testing.assert_array_equal(a, b)
    assert store.latent[0].dtype == np.float16 and store.jac[0].dtype == np.float16
    # 448 bytes a stored voxel (+ the poses): the size the bench reports
    assert store.nbytes() == 448 * store.cell_count() + 256 * len(store)
    _, cells, _ = fused(CELLS, prior, views, poses)
    with pytest.raises(DataError, match="map.remap: reencode"):
        LatentStore.from_arrays(cells.to_arrays())
    with pytest.raises(DataError, match="map.remap: transform"):
        KeyframeStore.from_arrays(store.to_arrays())
    with pytest.raises(ValueError, match="cannot be remapped"):
        core.remap(CELLS, core.init(CELLS, 1024, 18), store, prior, poses[::-1].copy())


def test_a_reencode_remap_runs_the_frame_programs_and_compiles_nothing(prior):
    """The first keyframe is the largest, and the map grows after it: the frames keep its padded size
    (`core.frame_pad`), so the last capacity has a compiled shape for every keyframe, and a remap (one
    keyframe moved, or a rebuild) calls only programs the frames compiled. Nor does the rebuild's empty
    map at the grown capacity build a program (filled on the device, it built five: a `jnp.full` per array
    shape, caught when no earlier test made arrays of those shapes)."""
    rng = np.random.default_rng(7)
    small = scene(rng, 900)
    big = tuple(np.concatenate([a, b]) for a, b in zip(scene(rng), (small[0] + [3.0, 0.0, 0.0], small[1])))
    worlds = [big] + [(small[0] + [0.0, 4.0 * k, 0.0], small[1]) for k in (1, 2, 3)]   # each adds new voxels
    poses = np.asarray([make_pose(random_rotation(rng), rng.normal(size=3) * 0.3) for _ in range(4)])
    views = [(transform_points(np.linalg.inv(P), w[0]), w[1] @ P[:3, :3]) for P, w in zip(poses, worlds)]
    state, store, hints = fused(CELLS, prior, views, poses, capacity=8192)   # the first keyframe fits, then it grows
    sizes = store.sizes(range(4))
    assert state.map.table.capacity > 8192 and lm.bucket(sizes[0]) > lm.bucket(max(sizes[1:]))
    programs, capacity = core.step._cache_size(), state.map.table.capacity
    new = poses.copy()
    # a loop correction's few centimetres (a large move adds voxels, and a map that grows compiles its new size)
    new[0] = make_pose(rotation_from_axis_angle(np.array([0.2, 0.1, 1.0]), 0.01), [0.03, 0.0, 0.0]) @ poses[0]
    with programs_built() as built:
        state, store, changed = core.remap(CELLS, state, store, prior, new, hints=hints)   # remove + fuse
        assert changed == [0]
        new[1:] = [make_pose(np.eye(3), [0.0, 0.02, 0.0]) @ P for P in new[1:]]
        state, store, changed = core.remap(CELLS, state, store, prior, new, hints=hints)   # rebuild
        jax.block_until_ready(state.active)
    assert changed == [1, 2, 3] and state.map.table.capacity == capacity
    assert core.step._cache_size() == programs and built == []


def corridor(n_kf, seed):
    """(views, poses) of `n_kf` small keyframes (the scene at 0.6 scale, ~460 cells) along a corridor, each
    seeing it shifted by 0.7 m."""
    rng = np.random.default_rng(seed)
    pts, nrm = scene(rng, 600)
    poses = np.asarray([make_pose(random_rotation(rng), [0.0, 0.7 * k, 0.0] + rng.normal(size=3) * 0.1)
                        for k in range(n_kf)])
    views = [(transform_points(np.linalg.inv(P), 0.6 * pts + [0.0, 0.7 * k, 0.0]), nrm @ P[:3, :3])
             for k, P in enumerate(poses)]
    return views, poses


def test_a_remap_of_many_small_keyframes_builds_no_program_and_equals_one_keyframe_at_a_time(prior):
    """24 keyframes of ~460 cells: a remap encodes up to four in one frame-sized batch, whose (voxel,
    keyframe) records can overflow the scratch table that sufficed for each frame. Such a batch is run
    again one keyframe at a time with the frames' programs; growing the scratch table instead (the code
    before) compiled a program at the first remap. Either way every keyframe goes in exactly once: the
    remapped map equals the one re-encoded a keyframe per batch (a keyframe dropped or fused twice by the
    retry changes it)."""
    views, poses = corridor(24, 9)
    state, store, hints = fused(CELLS, prior, views, poses, capacity=1 << 15)
    assert 4 * max(store.sizes(range(24))) <= hints["frame_pad"]     # a remap's batches hold several keyframes
    rng = np.random.default_rng(10)
    half, new = (np.asarray([make_pose(rotation_from_axis_angle(rng.normal(size=3), 0.01), rng.normal(size=3) * 0.02)
                             @ P for P in poses]) for _ in range(2))
    half[:12] = poses[:12]
    with programs_built() as built:
        state, store, changed = core.remap(CELLS, state, store, prior, half, hints=hints)   # remove + fuse
        assert changed == list(range(12, 24))
        state, store, changed = core.remap(CELLS, state, store, prior, new, hints=hints)    # rebuild
        jax.block_until_ready(state.active)
    assert changed == list(range(24)) and built == []
    assert "remap_group_cells" in hints      # a batch overflowed and was split (the case this test is about)
    one_at_a_time = core.apply_keyframes(CELLS, core.init(CELLS, 1 << 15, 18), store, prior, list(range(24)), new,
                                         np.ones(24, np.float32), {**hints, "remap_group_cells": 1})
    assert_same_map(state, one_at_a_time)


def test_a_transform_remap_builds_no_program(prior):
    """`move_step` runs once while mapping at each map capacity (on padding: nothing moves), so the first
    remap of a transformable map builds nothing; before, it compiled `move_step` there (`clear_cache`
    makes that visible whatever ran earlier in the process)."""
    core.move_step.clear_cache()
    views, poses = views_and_poses(3, 8)
    state, store, hints = fused(LATENT, prior, views, poses)
    new = poses.copy()
    new[2] = make_pose(rotation_from_axis_angle(np.array([0.0, 0.3, 1.0]), 0.02), [0.02, 0.0, 0.01]) @ poses[2]
    with programs_built() as built:
        state, store, changed = core.remap(LATENT, state, store, prior, new, hints=hints)   # remove + fuse
        assert changed == [2]
        state, store, changed = core.remap(LATENT, state, store, prior, poses, hints=hints)  # and back
        jax.block_until_ready(state.active)
    assert changed == [2] and built == []
    # nothing moved by the runs on padding: moved back, the map is the stored maps fused as stored
    assert_same_map(state, moved(LATENT, prior, store, range(3), poses))
