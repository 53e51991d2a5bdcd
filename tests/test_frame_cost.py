"""What a frame costs, and the steps that cut it: the frame's pairs as the store takes them
(`integrate.frame_pairs`: every near-surface and band sample in its place, then the usable ray samples
compacted into a budget of `window.carve_samples`), tables that grow together (one compile), and the
profile's attribution of XLA's operations to the frame program's stages."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmap.config import MapConfig
from jaxmap.n3.integrate import frame_pairs
from jaxmap.n3.sampling import Samples
from jaxmap.n3.state import N3Static

N = 40


def _inputs(static, ok_count: int, seed: int):
    ns, nb, nr = static.n_surface, static.n_free, static.n_ray
    per = ns + nb + nr
    rng = np.random.default_rng(seed)
    idx = np.arange(N * per)
    # every sample's point names it: x = its index, so a pair can be traced back to its sample
    points = np.stack([idx, -idx, np.zeros_like(idx)], -1).astype(np.float32)
    samples = Samples(jnp.asarray(points), jnp.asarray(idx * 0.01, jnp.float32),
                      jnp.asarray(np.tile(np.r_[np.ones(ns, bool), np.zeros(nb + nr, bool)], N)),
                      jnp.ones((N * per,), bool))
    vox = jnp.asarray(np.stack([idx, idx, idx], -1).astype(np.int32))
    valid = jnp.asarray(rng.random((N, per)) < 0.9)
    surf_rows = jnp.asarray(rng.integers(-1, 500, N * ns).astype(np.int32))
    free_rows = rng.integers(-1, 500, (N, nb + nr)).astype(np.int32)
    ray_ok = np.zeros(N * nr, bool)
    ray_ok[rng.choice(N * nr, ok_count, replace=False)] = True
    ray_ok = ray_ok.reshape(N, nr)
    free_rows[:, nb:] = np.where(ray_ok, np.abs(free_rows[:, nb:]), free_rows[:, nb:])
    free_ok = np.concatenate([rng.random((N, nb)) < 0.5, ray_ok], 1)
    free = (jnp.asarray(free_rows), jnp.asarray(free_ok), jnp.asarray(ray_ok), jnp.asarray(ray_ok))
    return samples, vox, valid, surf_rows, free


@pytest.mark.parametrize("ok_count,budget", [(30, 64), (150, 64)])
def test_usable_ray_samples_fill_the_budget_in_scan_order_and_the_rest_is_counted(ok_count, budget):
    static = dataclasses.replace(N3Static.from_config(MapConfig()), carve_samples=budget)
    ns, nb, nr = static.n_surface, static.n_free, static.n_ray
    per = ns + nb + nr
    samples, vox, valid, surf_rows, free = _inputs(static, ok_count, seed=ok_count)
    fp = jax.jit(lambda *a: frame_pairs(static, *a))(samples, vox, valid, surf_rows, free, jax.random.PRNGKey(0))
    rows, pts = np.asarray(fp.rows), np.asarray(fp.samples.points)
    assert rows.shape == (N * (ns + nb) + budget,)

    # the near-surface and band samples, point by point, each with its own row (or -1)
    free_rows, free_ok, ray_ok = (np.asarray(x) for x in free[:3])
    head = np.concatenate([np.where(np.asarray(valid)[:, :ns], np.asarray(surf_rows).reshape(N, ns), -1),
                           np.where(free_ok[:, :nb], free_rows[:, :nb], -1)], 1).reshape(-1)
    np.testing.assert_array_equal(rows[:N * (ns + nb)], head)
    own = (np.arange(N)[:, None] * per + np.arange(ns + nb)[None]).reshape(-1)
    np.testing.assert_array_equal(pts[:N * (ns + nb), 0], own)

    # the ray part: usable ray samples only, each with its own row, point, label and no surface flag
    r = slice(N * (ns + nb), None)
    used = rows[r] >= 0
    assert used.sum() == min(ok_count, budget)
    assert int(fp.rays_left) == ok_count - min(ok_count, budget)
    sample = pts[r][used, 0].astype(int)
    point, j = sample // per, sample % per - (ns + nb)
    assert (j >= 0).all() and ray_ok[point, j].all()
    np.testing.assert_array_equal(rows[r][used], free_rows[point, nb + j])
    np.testing.assert_allclose(np.asarray(fp.samples.labels)[r][used], sample * 0.01, rtol=1e-6)
    assert not np.asarray(fp.samples.surface)[r][used].any()
    assert len(set(sample)) == len(sample)
    # ... a run of consecutive usable ones in scan order (wrapping), so that every part of a scan is used
    order = np.flatnonzero(ray_ok.reshape(-1))
    pos = np.searchsorted(order, point * nr + j)
    steps = np.diff(pos) % len(order)
    assert (steps == 1).all()


def test_the_profile_charges_each_operation_its_own_time_and_not_its_bodys():
    from jaxmap.bench.n3_profile import exclusive_by_name, scope_of_instructions

    # a loop [0, 100) whose body runs two operations, then an operation after it; a lone one nested twice
    events = [(0, 100, "while.1"), (10, 30, "dot.2"), (50, 40, "fusion.3"), (120, 5, "copy.4"),
              (200, 50, "cond.5"), (210, 30, "while.6"), (215, 10, "scatter.7")]
    got = exclusive_by_name(events)
    assert got == {"while.1": 30, "dot.2": 30, "fusion.3": 40, "copy.4": 5, "cond.5": 20, "while.6": 20,
                   "scatter.7": 10}
    assert sum(got.values()) == 100 + 5 + 50
    hlo = ('  %fusion.3 = f32[8]{0} fusion(%p), metadata={op_name="jit(step_after)/cond/branch_1_fun/jit(step)/'
           'train/while/body/loss/mul" stack_frame_id=3}\n'
           '  ROOT %scatter.7 = f32[8]{0} scatter(%a), metadata={op_name="jit(step)/evidence/raise/scatter"}\n'
           '  %copy.4 = f32[8]{0} copy(%b)\n'
           '  %dot.2 = f32[8]{0} dot(%c), metadata={op_name="jit(step)/store/sort"}\n')
    assert scope_of_instructions(hlo) == {"fusion.3": "train/loss", "scatter.7": "evidence/raise", "dot.2": "store"}


def test_a_table_near_full_grows_with_the_one_that_must_so_that_they_compile_once():
    from jaxmap.n3.frame import GROW_TOGETHER, grow_together
    from jaxmap.n3.state import Capacities

    caps = Capacities(voxel_slots=1 << 11, voxel_rows=1000, corner_slots=1 << 12, feature_rows=2000,
                      store_blocks=500, pairs_per_block=64, pool_pairs=0)
    # nothing must grow: nothing grows, however full
    assert grow_together(caps, (1000, 2000, 500), (990, 1990, 499)) == (1000, 2000, 500)
    # the voxels must: the feature rows, beyond GROW_TOGETHER full, grow with them; the store, below, does not
    rows = int(GROW_TOGETHER * 2000) + 1
    assert grow_together(caps, (2000, 2000, 500), (990, rows, int(GROW_TOGETHER * 500))) == (2000, 4000, 500)
    # what must grow more than double keeps its size
    assert grow_together(caps, (1000, 8000, 500), (1000, 1990, 400)) == (2000, 8000, 1000)
