"""The pure N3 engine (`jaxmap.n3.core`) against the facade, slow references and its own promises:
jax.grad eikonal vs float64 finite differences, sparse Adam vs dense optax Adam, the store's ranks
vs a stable sort, growth that loses nothing, and no compilation after the warm-up."""
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from analytic_lidar import corridor_scan, pose_at
from jaxmap.config import load_config
from jaxmap.frame_loop import Frame
from jaxmap.grid import features as gfeat
from jaxmap.grid import hashing
from jaxmap.n3 import adam, core, field, frame, scan, window
from jaxmap.n3.decoder import init_decoder
from jaxmap.n3.mapper import N3Mapper

SMALL = ["train.iters=6", "train.nv=128", "train.np_per_voxel=8", "preprocess.max_range_m=10.0",
         "preprocess.vox_down_m=0.2", "window.initial_blocks=4096", "mesh.min_component_faces=0"]


def _cfg(extra=()):
    return load_config("configs/city.yaml", SMALL + list(extra))


def _frames(n, step=1.5):
    return [(corridor_scan(step * i, max_range=10.0), pose_at(step * i)) for i in range(n)]


def test_pure_integrate_and_train_give_the_facades_state():
    """integrate and train jitted one by one, keys threaded by hand, equal the facade's fused step."""
    cfg = _cfg()
    frames = _frames(4)
    m = N3Mapper(cfg)
    for pts, pose in frames:
        m.add_frame(pts, pose)

    cfg = m.cfg  # with the range-image layout the mapper read off the first scan (the evidence's images)
    static = core.N3Static.from_config(cfg)
    state = core.init_state(static, cfg, core.capacities_for(static, cfg))
    integrate = jax.jit(functools.partial(core.integrate, static))
    train = jax.jit(functools.partial(core.train, static))
    bucket = 0
    for i, (pts, pose) in enumerate(frames):
        p, n, pose, img = scan.preprocess(pts, pose, cfg.preprocess, i, image=static.evidence)
        if i == 0:
            state = core.set_origin(static, state, pose[:3, 3])
        bucket = scan.bucket_for(len(p), bucket)
        batch = scan.to_batch(p, n, pose, core.origin_world(static, state), bucket, img)
        key, k_sample, k_train = jax.random.split(state.key, 3)
        state, fs = integrate(state, batch, k_sample)
        assert bool(fs.ok)  # the default capacities hold a corridor: one pass, no growth
        state, _ = train(state, k_train)
        state = state.replace(key=key)
    assert int(state.frame) == 4
    for a, b in zip(jax.tree_util.tree_leaves(state), jax.tree_util.tree_leaves(m.state)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)


def _sdf64(x, feats, vox, params, leaf=0.2, levels=3):
    """Slow float64 numpy reference of the field: trilinear weights per level, then the MLP."""
    w = []
    for lev in range(levels):
        s = leaf * 2**lev
        f = (x - np.floor_divide(vox, 2**lev) * s) / s
        for c in gfeat.CORNER_OFFSETS:
            w.append(np.prod(np.where(c, f, 1 - f)))
    h = np.asarray(w) @ feats
    layers = params["params"]
    names = sorted(layers, key=lambda k: int(k.split("_")[-1]))
    for name in names[:-1]:
        h = np.maximum(h @ np.asarray(layers[name]["kernel"], np.float64) + np.asarray(layers[name]["bias"]), 0)
    out = layers[names[-1]]
    return float((h @ np.asarray(out["kernel"], np.float64) + np.asarray(out["bias"]))[0])


def test_eikonal_gradient_by_jax_grad_equals_float64_finite_differences():
    rng = np.random.default_rng(0)
    _, params = init_decoder(jax.random.PRNGKey(3), 8, 32, 2)
    grad = jax.jit(jax.grad(functools.partial(field.sdf_at, leaf=0.2, levels=3)))
    for _ in range(20):
        vox = rng.integers(-30, 30, 3).astype(np.int32)
        x = (vox + rng.uniform(0.05, 0.95, 3)) * 0.2
        feats = rng.normal(size=(24, 8)) * 0.5
        g = np.asarray(grad(jnp.asarray(x, jnp.float32), jnp.asarray(feats, jnp.float32), jnp.asarray(vox), params))
        h = 1e-6
        fd = np.array([(_sdf64(x + h * e, feats, vox, params) - _sdf64(x - h * e, feats, vox, params)) / (2 * h)
                       for e in np.eye(3)])
        np.testing.assert_allclose(g, fd, rtol=2e-3, atol=2e-4 * max(1.0, np.abs(fd).max()))


def test_custom_jvp_weights_give_the_autodiff_loss_gradients():
    """The closed-form JVP rule of the trilinear weights changes nothing: the loss and its
    gradients (second order through the eikonal term) equal plain autodiff of corner_weights."""
    rng = np.random.default_rng(1)
    g, k = 64, 8
    vox = rng.integers(-20, 20, (g, 3)).astype(np.int32)
    pts = ((vox[:, None] + rng.uniform(0.02, 0.98, (g, k, 3))) * 0.2).astype(np.float32)
    from jaxmap.n3.hierarchical import Batch

    b = Batch(jnp.zeros(g, jnp.int32), jnp.asarray(vox), jnp.asarray(pts), jnp.asarray(rng.normal(size=(g, k)) * 0.1, jnp.float32),
              jnp.asarray(rng.uniform(size=(g, k)) < 0.7), jnp.ones((g, k), bool))
    feats = jnp.asarray(rng.normal(size=(g, 24, 8)) * 0.3, jnp.float32)
    _, params = init_decoder(jax.random.PRNGKey(0), 8, 32, 2)
    args = (feats, params, b, jnp.asarray(vox), jnp.float32(0.1), jnp.float32(0.5))
    loss = functools.partial(field.n3_loss, leaf=0.2, levels=3)
    fast = jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)(*args)
    plain_w = lambda x, v, leaf, levels: gfeat.corner_weights(x[None], v[None], leaf, levels)[0]  # noqa: E731
    orig = field.trilinear_weights
    field.trilinear_weights = plain_w
    try:
        ref = jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)(*args)
    finally:
        field.trilinear_weights = orig
    for a, r in zip(jax.tree_util.tree_leaves(fast), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(r), rtol=1e-4, atol=1e-6)
    assert float(fast[0][1][1]) > 0  # the eikonal term is really there


def test_sparse_adam_rows_first_touched_late_step_like_a_fresh_dense_adam():
    """Per-row bias correction: rows first touched after 1000 steps take the steps of a dense Adam
    started when they were first touched (a global count would scale their first steps by up to
    ~3x here: 1 / sqrt(1 - b2^t) against 1 / (1 - b1^t)); rows touched all along take the steps of a
    dense Adam over all 1010 steps; rows never touched keep values and moments."""
    rng = np.random.default_rng(4)
    r, d, lr = 16, 3, 0.01
    init = jnp.asarray(rng.normal(size=(r, d)), jnp.float32)
    opt = adam.sparse_adam(lr)

    @jax.jit
    def update(table, st, rows, g):
        upd, st = opt.update(adam.SparseGrads(rows, g), st, table)
        return adam.apply_updates(table, upd), st

    table, st = init, opt.init(init)
    tx = optax.adam(lr)
    dense_step = jax.jit(lambda g, s, p: tx.update(g, s, p))
    early, late = np.arange(4), np.arange(4, 10)  # rows 10..15 never touched
    dense_e, dst_e = init[:4], tx.init(init[:4])
    dense_l, dst_l = init[4:10], tx.init(init[4:10])
    first_late_step = None
    for step in range(1010):
        touched = early if step < 1000 else np.concatenate([early, late])
        rows = np.concatenate([touched, rng.choice(touched, 6), [-1, -1]]).astype(np.int32)  # duplicates, padding
        g = rng.normal(size=(len(rows), d)).astype(np.float32)
        before = np.asarray(table)[late]
        table, st = update(table, st, jnp.asarray(rows), jnp.asarray(g))
        if step == 1000:
            first_late_step = np.abs(np.asarray(table)[late] - before)
        gd = np.zeros((r, d), np.float32)
        np.add.at(gd, rows[rows >= 0], g[rows >= 0])
        u, dst_e = dense_step(jnp.asarray(gd[:4]), dst_e, dense_e)
        dense_e = optax.apply_updates(dense_e, u)
        if step >= 1000:
            u, dst_l = dense_step(jnp.asarray(gd[4:10]), dst_l, dense_l)
            dense_l = optax.apply_updates(dense_l, u)
    np.testing.assert_array_equal(np.asarray(st.count), [1010] * 4 + [10] * 6 + [0] * 6)
    np.testing.assert_allclose(np.asarray(table)[:4], np.asarray(dense_e), rtol=2e-4, atol=2e-5)
    np.testing.assert_allclose(np.asarray(table)[4:10], np.asarray(dense_l), rtol=2e-4, atol=2e-5)
    assert first_late_step.max() <= lr * 1.001  # a fresh Adam's first step is lr * sign(g)
    np.testing.assert_array_equal(np.asarray(table)[10:], np.asarray(init)[10:])
    np.testing.assert_array_equal(np.asarray(st.moments)[:, 2], 0.0)  # the scratch is clean between steps


def test_ranks_within_slot_equal_a_stable_sort():
    rng = np.random.default_rng(5)
    for n_slots, m in [(5, 1000), (1 << 17, 40000), (1 << 21, 3000)]:  # small, chunked, fallback
        slots = rng.integers(0, n_slots + 1, m).astype(np.int32)
        rank, n_in = jax.jit(window.ranks_within_slot, static_argnums=1)(jnp.asarray(slots), n_slots)
        seen = {}
        ref = np.zeros(m, np.int32)
        for i, s in enumerate(slots):
            ref[i] = seen.get(s, 0)
            seen[s] = ref[i] + 1
        keep = slots < n_slots
        np.testing.assert_array_equal(np.asarray(rank)[keep], ref[keep])
        np.testing.assert_array_equal(np.asarray(n_in), np.bincount(slots, minlength=n_slots + 1)[:n_slots])


def test_growth_from_tiny_capacities_loses_nothing():
    """A map that starts too small for the first frame grows its voxel table, feature rows and store
    (a failed pass retried, then growth between frames) and ends with exactly the voxels, corner rows
    and pairs of a map that never grew; fed one frame ahead of its stats, it is the same map bit for bit."""
    cfg = _cfg(["train.iters=2"])
    frames = _frames(2, step=2.0)
    static = core.N3Static.from_config(cfg)
    # The first frame brings 4.6k voxels, 19k corner rows and 4.6k blocks: the growing map starts with
    # room for the voxels only, so its first pass fails on the corners and the store; it grows all three
    # (the voxel table for the headroom) and, after the frame, the feature table and the store again,
    # to the sizes the map that never grows has from the start and keeps for both frames. Every size
    # compiles the frame program, so there are three (measured: seven with five frames from 1024 rows).
    ended = core.Capacities(voxel_slots=32768, voxel_rows=16384, corner_slots=131072, feature_rows=65536,
                            store_blocks=16384, pairs_per_block=cfg.window.pairs_per_voxel)
    tiny = core.Capacities(voxel_slots=16384, voxel_rows=8192, corner_slots=32768, feature_rows=16384,
                           store_blocks=4096, pairs_per_block=cfg.window.pairs_per_voxel)
    big = N3Mapper(cfg, state=core.init_state(static, cfg, ended))
    small = N3Mapper(cfg, state=core.init_state(static, cfg, tiny))
    passes = 0
    for pts, pose in frames:
        assert big.add_frame(pts, pose)["passes"] == 1
        passes += small.add_frame(pts, pose)["passes"]
    assert core.Capacities.of(big.state) == ended  # it never grew
    assert passes > len(frames)  # some passes failed and were retried after growing
    caps = core.Capacities.of(small.state)
    assert caps.voxel_rows > tiny.voxel_rows and caps.feature_rows > tiny.feature_rows
    assert caps.store_blocks > tiny.store_blocks
    a, b = big.state, small.state
    n = int(a.voxels.count)
    assert int(b.voxels.count) == n and int(b.corners.count) == int(a.corners.count)
    np.testing.assert_array_equal(np.asarray(a.voxel_coord[:n]), np.asarray(b.voxel_coord[:n]))
    np.testing.assert_array_equal(np.asarray(a.voxel_corner_rows[:n]), np.asarray(b.voxel_corner_rows[:n]))

    def pairs(st):
        s = st.store
        out = []
        for slot in np.nonzero(np.asarray(s.voxel_of_slot) >= 0)[0]:
            c = int(s.count[slot])
            out.append((int(s.voxel_of_slot[slot]), tuple(sorted(map(tuple, np.asarray(s.pairs[slot, :c]).tolist())))))
        return sorted(out)

    assert pairs(a) == pairs(b)

    # The same frames dispatched one ahead of their stats (`core.FramePipeline`, lag 1, as `jaxmap map`
    # runs them): frame 1 is dispatched before frame 0 is known not to fit, so it must do nothing then
    # and run again after frame 0's retries; growth planned from a frame's stats lands a frame later.
    # The map is bit for bit the one of the frame-by-frame mapper (the hash tables: the same keys in the
    # same rows). A pipeline that ran frame 1 on top of frame 0's failed pass, or did not run it again,
    # gives other rows, pairs and features.
    start = scan.MapStart.of(cfg, *frames[0])
    piped = N3Mapper(start=start, state=core.init_state(start.static, start.cfg, tiny))
    upload = piped.uploader()
    for i, (pts, pose) in enumerate(frames):
        ready, pose = piped.start.prepare(pts, pose, i)
        frame = upload(Frame(i, i, ready.points, pose, ready.normals, ready.image))
        piped.submit(frame.batch, points=len(ready.points))
    piped.finish()
    assert [r["passes"] for r in piped.timings] == [r["passes"] for r in small.timings]
    assert sum(r["passes"] for r in piped.timings) > len(frames)
    c = piped.state
    for ta, tc in ((b.voxels, c.voxels), (b.corners, c.corners)):
        for x, y in zip(hashing.entries(ta), hashing.entries(tc)):
            np.testing.assert_array_equal(x, y)
    strip = lambda s: s.replace(voxels=None, corners=None)  # noqa: E731
    for x, y in zip(jax.tree_util.tree_leaves(strip(b)), jax.tree_util.tree_leaves(strip(c))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_the_mapper_keeps_its_newest_compiled_programs_and_no_more(monkeypatch):
    """The frame programs are kept least recently used first and at most `PROGRAMS.kept` of them
    (each holds ~2,000 memory maps; a process may hold 65,530): a hit is not compiled again and
    becomes the newest, the oldest is dropped; every compile's seconds are kept."""
    import types

    compiled = []

    class Step:
        def lower(self, static, state, batch, prev_ok, rows):
            return types.SimpleNamespace(compile=lambda: compiled.append(state) or (lambda *a: state))

    monkeypatch.setattr(frame, "step_after", Step())
    monkeypatch.setattr(core.Capacities, "of", staticmethod(lambda state: state))
    programs = core.ProgramCache(kept=core.PROGRAMS.kept)  # this test's, the process's left as it is
    monkeypatch.setattr(frame, "PROGRAMS", programs)
    batch = types.SimpleNamespace(points=np.zeros((8, 3)))
    n = programs.kept
    assert 2 <= n <= 8  # a few programs for a process that maps again, not hundreds of thousands of maps
    for caps in range(n):
        assert core.compiled_step("static", caps, batch)() == caps
    assert core.compiled_step("static", 0, batch)() == 0 and compiled == list(range(n))  # a hit
    core.compiled_step("static", n, batch)  # one more: the least recently used (1, not 0) goes
    assert programs.keys() == [("static", c, 8, 0) for c in [*range(2, n), 0, n]]
    assert programs.newest()[0] == ("static", n, 8, 0)
    core.compiled_step("static", 1, batch)
    assert compiled == [*range(n + 1), 1]
    assert programs.compiles() == n + 2 and programs.compiles_since(n)["compiles"] == 2
    core.forget_compiled()
    assert programs.keys() == [] and programs.compiles() == n + 2  # the programs go, the seconds stay


def test_thirty_frames_compile_nothing_after_the_warm_up():
    """Fixed shapes: once the first frame has compiled the frame program, 29 more frames (the
    window sliding along a corridor, maps growing) compile nothing."""
    from jax import monitoring

    compiles = []
    monitoring.register_event_duration_secs_listener(
        lambda name, secs, **kw: compiles.append(name) if name == "/jax/core/compile/backend_compile_duration"
        else None)
    m = N3Mapper(_cfg(["train.iters=1", "train.nv=64"]))
    frames = _frames(30, step=1.0)
    m.add_frame(*frames[0])
    warm = len(compiles)
    assert warm >= 1  # the listener sees compiles at all
    for pts, pose in frames[1:]:
        m.add_frame(pts, pose)
    assert len(compiles) == warm, compiles[warm:]
    # the iterations a frame are traced (`Hyper.iters`): a frame added with none (what SLAM may do with the
    # frames it re-adds after a loop) trains no feature and compiles nothing; with them back, it trains
    for iters, trained in ((0, False), (1, True)):
        rows = m.timings[-1]["feature_rows"]
        before = np.array(m.state.feature_table)[:rows]  # (host side: a device slice would compile)
        m.set_iters(iters)
        m.add_frame(*frames[-1 if trained else -2])  # (added again, as SLAM re-adds after a loop)
        assert int(m.state.hyper.iters) == iters
        assert np.any(np.asarray(m.state.feature_table)[:rows] != before) == trained
    assert len(compiles) == warm, compiles[warm:]


def test_hierarchical_sampler_matches_algorithm_1():
    """Stage 1 uniform over the window's voxels (not pairs), stage 2 (vmapped per voxel) uniform
    within a block, Np pairs from blocks holding >= Nt pairs and Np // 3 from the others."""
    from jaxmap.n3 import hierarchical

    s, p = 6, 32
    st = window.create(s, p, 16)
    counts = [30, 3, 12, 0, 9, 20]
    rows, pts, lab = [], [], []
    for v, c in enumerate(counts):
        for j in range(c):
            rows.append(v), pts.append([v, j, 0]), lab.append(v * 100 + j)
    m = len(rows)
    rows = jnp.asarray(rows, jnp.int32)
    st, ids, n, stats = window.update(st, rows, jnp.zeros((m, 3), jnp.int32), jnp.asarray(pts, jnp.float32),
                                      jnp.asarray(lab, jnp.float32), jnp.ones(m, bool), jnp.int32(0),
                                      jnp.zeros(3, jnp.int32), radius_vox=10)
    assert bool(stats.ok) and int(n) == 5
    slot_of = np.asarray(st.slot_of_voxel)
    inside = jnp.zeros(s, bool).at[jnp.asarray(slot_of[[0, 1, 3, 4, 5]])].set(True)  # voxel 2 outside
    inside = inside.at[int(slot_of[2])].set(False)
    ids, n = window.window_slots(inside & (st.count > 0))
    b = hierarchical.sample_hierarchical(jax.random.PRNGKey(0), st, ids, n, nv=4000, np_=9, nt=10)
    vox_b = np.asarray(b.voxel_rows)
    mask, labels = np.asarray(b.mask), np.asarray(b.labels)
    assert set(vox_b.tolist()) == {0, 1, 4, 5}
    for v in (0, 1, 4, 5):
        assert np.all(mask[vox_b == v].sum(1) == (9 if counts[v] >= 10 else 3))
        lab = labels[vox_b == v][mask[vox_b == v]]
        assert np.all((lab >= v * 100) & (lab < v * 100 + counts[v]))
        # stage 2 is uniform within the block: every pair of block 0 (30 pairs) is drawn
        if v == 0:
            assert len(np.unique(lab)) == 30
    freq = np.bincount(vox_b, minlength=s)[[0, 1, 4, 5]] / 4000
    np.testing.assert_allclose(freq, 0.25, atol=0.04)
    u = hierarchical.sample_uniform(jax.random.PRNGKey(1), st, ids, n, batch=20000)
    share0 = (np.asarray(u.voxel_rows) == 0).mean()
    assert abs(share0 - 30 / 62) < 0.03  # uniform over pairs: voxel 0 holds 30 of the 62 window pairs


def test_store_update_keeps_the_newest_p_pairs_per_voxel_like_a_python_ring_buffer():
    rng = np.random.default_rng(3)
    s, p, v = 32, 5, 64
    st = window.create(s, p, v)
    ref = {}
    upd = jax.jit(functools.partial(window.update, radius_vox=1000))
    for f in range(6):
        m = 60
        rows = rng.integers(-1, 12, size=m).astype(np.int32)
        vals = rng.normal(size=m).astype(np.float32)
        st, _, _, stats = upd(st, jnp.asarray(rows), jnp.zeros((m, 3), jnp.int32), jnp.tile(jnp.asarray(vals)[:, None],
                              (1, 3)), jnp.asarray(vals), jnp.ones(m, bool), jnp.int32(f), jnp.zeros(3, jnp.int32))
        assert bool(stats.ok)
        for r_, x in zip(rows, vals):
            if r_ >= 0:
                ref.setdefault(int(r_), []).append(float(x))
    for r_, xs in ref.items():
        slot = int(st.slot_of_voxel[r_])
        got = sorted(np.asarray(st.pairs[slot, : int(st.count[slot]), 3]).tolist())
        np.testing.assert_allclose(got, sorted(xs[-p:]), rtol=1e-6)
    # too few free blocks: nothing changes, ok is False (the caller grows and retries)
    full = window.create(2, p, v)
    out, _, _, stats = upd(full, jnp.asarray([1, 2, 3], jnp.int32), jnp.zeros((3, 3), jnp.int32),
                           jnp.zeros((3, 3)), jnp.zeros(3), jnp.ones(3, bool), jnp.int32(0), jnp.zeros(3, jnp.int32))
    assert not bool(stats.ok) and int(stats.blocks_needed) == 3 and int(stats.blocks_free) == 2
    for a, b in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(full)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _offer(st, upd, voxel, n, frame, key, value0=0.0):
    """Offer n pairs of one frame to `voxel`; the label of pair i is value0 + i."""
    vals = value0 + jnp.arange(n, dtype=jnp.float32)
    return upd(st, jnp.full((n,), voxel, jnp.int32), jnp.zeros((n, 3), jnp.int32), jnp.zeros((n, 3)), vals,
               jnp.ones(n, bool), jnp.int32(frame), jnp.zeros(3, jnp.int32), True, key)


def test_a_voxel_observed_by_k_frames_in_the_window_holds_pairs_from_all_k():
    """Near the sensor a voxel gets ~30 pairs a frame. With the per-frame quota and the reservoir, a
    block of 64 holds pairs of all 8 frames that saw it; the newest-64 ring buffer holds 3 of them."""
    s, p, k = 4, 64, 8
    held = {}
    for policy, q in (("reservoir", 8), ("ring", 0)):
        upd = jax.jit(functools.partial(window.update, radius_vox=1000, policy=policy,
                                        pairs_per_frame=q))
        st = window.create(s, p, 8)
        for f in range(k):
            st, ids, n, stats = _offer(st, upd, 2, 30, f, jax.random.PRNGKey(f), value0=100.0 * f)
            assert bool(stats.ok)
        slot = int(st.slot_of_voxel[2])
        assert int(st.frames_seen[slot]) == k and int(st.count[slot]) == min(p, k * (q or 30))
        frames = np.asarray(st.frame[slot, : int(st.count[slot])])
        held[policy] = len(set(frames.tolist()))
        assert float(window.frames_held_fraction(st, ids, n, 5)) == held[policy] / k
    assert held == {"reservoir": k, "ring": 3}


def test_reservoir_keeps_each_offered_pair_with_equal_probability():
    """Algorithm R vectorised per frame (several pairs of one frame may draw one position; the later
    wins): after 50 pairs offered in 5 frames, each is held with probability P / 50."""
    p, trials = 8, 300
    upd = jax.jit(functools.partial(window.update, radius_vox=1000, policy="reservoir"))
    hits = np.zeros(50)
    for t in range(trials):
        st = window.create(2, p, 4)
        for f in range(5):
            st, _, _, _ = _offer(st, upd, 1, 10, f, jax.random.PRNGKey(1000 * t + f), value0=10.0 * f)
        slot = int(st.slot_of_voxel[1])
        labels = np.asarray(st.pairs[slot, :, 3]).astype(int)
        assert len(set(labels.tolist())) == p  # no pair held twice
        hits[labels] += 1
    freq = hits / trials
    np.testing.assert_allclose(freq.mean(), p / 50, rtol=1e-6)
    # binomial std of one item's frequency is ~0.021: every item within 4.5 std of P / 50
    assert np.all(np.abs(freq - p / 50) < 0.095), freq
    # the first frame's items are not favoured over the last frame's (a ring would keep none of them)
    assert abs(freq[:10].mean() - freq[40:].mean()) < 0.04


def test_static_config_is_hashable_and_lr_is_not_static():
    a = core.N3Static.from_config(_cfg())
    b = core.N3Static.from_config(_cfg(["train.lr=0.5", "train.sigma_sigmoid_m=0.2", "train.weight_e=0.3",
                                        "train.iters=3"]))
    assert hash(a) == hash(b) and a == b  # learning rate, beta, eikonal weight and iterations do not recompile
    assert dataclasses.replace(a, nv=7) != a


def test_window_cube_test_is_exact_on_this_backend():
    """in_window on 131072 random blocks equals numpy (XLA's GPU backend once got the |d| <= r
    form of it wrong for 15 % of rows; this runs the real function on whatever backend is present)."""
    rng = np.random.default_rng(0)
    s = 1 << 17
    st = window.create(s, 2, 8)
    coord = rng.integers(-300, 300, (s, 3)).astype(np.int32)
    st = st.replace(coord=jnp.asarray(coord), voxel_of_slot=jnp.zeros(s, jnp.int32))
    c = np.array([100, 14, 0], np.int32)
    got = jax.jit(lambda st, c: window.in_window(st, c, 100))(st, jnp.asarray(c))
    np.testing.assert_array_equal(np.asarray(got), np.all(np.abs(coord - c) <= 100, axis=1))


def test_a_save_on_the_cpu_holds_no_copy_of_the_map(tmp_path):
    """`save_state` writes each table from the state's own buffers, one at a time: the host memory it
    allocates at its peak (numpy's allocations, traced) is about its largest array (the store's
    blocks in use, gathered), where building the compact tree first (and orbax) held the whole map
    once or more."""
    import tracemalloc

    from jaxmap.n3.checkpoint import compact, save_state

    m = N3Mapper(_cfg())
    for pts, pose in _frames(3):
        m.add_frame(pts, pose)
    sizes = [x.nbytes for x in jax.tree_util.tree_leaves(compact(m.state))]
    size, largest = sum(sizes), max(sizes)
    assert size > 2**20 and largest < 0.6 * size  # MBs, in several arrays: the bound below separates
    tracemalloc.start()
    try:
        save_state(str(tmp_path / "a"), m.cfg, m.state, m.timings)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1.25 * largest, (peak, largest, size)


def test_compact_checkpoint_restores_the_state_leaf_for_leaf(tmp_path):
    """Saved compactly (keys in row order, used rows and blocks only) and rebuilt, the state equals
    the original in every leaf except the hash tables' slot layout, where the same keys map to the
    same rows; a background save writes the same."""
    from jaxmap.grid import hashing
    from jaxmap.n3.checkpoint import load_state, save_state, wait_for_saves

    def same(a, b):
        for ta, tb in ((a.voxels, b.voxels), (a.corners, b.corners)):
            ka, ra = hashing.entries(ta)
            kb, rb = hashing.entries(tb)
            np.testing.assert_array_equal(ka, kb), np.testing.assert_array_equal(ra, rb)
            assert ta.capacity == tb.capacity and int(ta.count) == int(tb.count)
        strip = lambda s: s.replace(voxels=None, corners=None)  # noqa: E731
        for x, y in zip(jax.tree_util.tree_leaves(strip(a)), jax.tree_util.tree_leaves(strip(b))):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))

    m = N3Mapper(_cfg())
    for pts, pose in _frames(3):
        m.add_frame(pts, pose)
    save_state(str(tmp_path / "a"), m.cfg, m.state, m.timings)
    m.save(str(tmp_path / "b"), background=True)
    wait_for_saves()
    for name in ("a", "b"):
        cfg, state, timings = load_state(str(tmp_path / name))
        assert cfg == m.cfg and len(timings) == 3
        same(state, m.state)
    # a checkpoint of earlier versions (an orbax tree under state/) is still read, to the same state
    from jaxmap.checkpoint import save_tree
    from jaxmap.n3.checkpoint import meta_of, compact

    assert (tmp_path / "a" / "3" / "arrays").is_dir() and not (tmp_path / "a" / "3" / "state").exists()
    save_tree(str(tmp_path / "o"), compact(m.state), meta_of(m.cfg, m.state, m.timings), step=3)
    _, state, _ = load_state(str(tmp_path / "o"))
    same(state, m.state)
    # an empty map round-trips too
    e = N3Mapper(_cfg())
    save_state(str(tmp_path / "e"), e.cfg, e.state, [])
    _, state, _ = load_state(str(tmp_path / "e"))
    same(state, e.state)
    # and the replay ablation's flat pool of pairs
    r = N3Mapper(_cfg(["window.mode=replay"]))
    for pts, pose in _frames(2):
        r.add_frame(pts, pose)
    assert int(r.state.pool.n) > 0
    save_state(str(tmp_path / "r"), r.cfg, r.state, r.timings)
    _, state, _ = load_state(str(tmp_path / "r"))
    same(state, r.state)


def test_a_background_save_runs_one_at_a_time_and_its_error_reaches_the_waiting_thread():
    """`jaxmap.checkpoint.BackgroundSaves`: busy while the write runs, a second save starts once the first is
    written, the write's error is raised by `wait` in the caller's thread, once."""
    import threading

    from jaxmap.checkpoint import BackgroundSaves

    saves, gate, order = BackgroundSaves(), threading.Event(), []

    def first():
        gate.wait()
        order.append(1)
        raise OSError("disk full")

    saves.start(first)
    assert saves.busy()
    gate.set()
    with pytest.raises(OSError, match="disk full"):
        saves.start(lambda: order.append(2))  # waits for the first, which failed
    assert order == [1] and not saves.busy()
    saves.start(lambda: order.append(2))
    saves.wait()
    saves.wait()  # nothing left: no error again
    assert order == [1, 2] and not saves.busy()
