"""A map of N3 submaps (`jaxmap.n3.submaps`, `SubmapMapper`): blending at seams, placement by pose,
eviction and reading back bit for bit, resuming, and the mesh welded across submaps."""
import dataclasses

import jax
import numpy as np
import pytest

from analytic_lidar import corridor_scan, pose_at
from jaxmap.checkpoint import steps
from jaxmap.config import ConfigError, load_config
from jaxmap.errors import CheckpointError
from jaxmap.mesh import extract_mesh, extract_mesh_groups
from jaxmap.n3 import submaps as sm
from jaxmap.n3.mapper import N3Mapper
from jaxmap.n3.submap_mapper import SubmapMapper, load_map

SMALL = ["train.iters=6", "train.nv=128", "train.np_per_voxel=8", "preprocess.max_range_m=10.0",
         "preprocess.vox_down_m=0.2", "window.initial_blocks=4096", "mesh.min_component_faces=0"]
SUB = ["submaps.enabled=true", "submaps.length_m=8", "submaps.blend_m=3"]


def _frames(n, step=1.0, beams=16, steps=256):
    return [(corridor_scan(step * i, beams=beams, steps=steps, max_range=10.0), pose_at(step * i)) for i in range(n)]


def _mapped(tmp_path, n=20, extra=(), **kw):
    m = SubmapMapper(load_config("configs/city.yaml", SMALL + SUB + list(extra)), directory=str(tmp_path / "subs"))
    for pts, pose in _frames(n, **kw):
        m.add_frame(pts, pose)
    return m


def test_blend_weights_nearest_valid_is_one_and_the_others_fall_off():
    dist = np.array([[1.0, 2.0, 9.0], [1.0, 2.0, 2.5], [np.inf, 3.0, 4.0], [1.0, 1.5, np.inf]])
    valid = np.array([[True, True, True], [False, True, True], [True, True, False], [False, False, False]])
    w = sm.blend_weights(dist, valid, band=2.0)
    np.testing.assert_allclose(w[0], [1.0, 0.5, 0.0])
    np.testing.assert_allclose(w[1], [0.0, 1.0, 0.75])   # the nearest is invalid: the nearest valid leads
    np.testing.assert_allclose(w[2], [0.0, 1.0, 0.0])    # inf distance = not a candidate; invalid = 0
    np.testing.assert_allclose(w[3], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(sm.blend_weights(dist, valid, band=0.0)[0], [1.0, 0.0, 0.0])


def test_a_query_near_a_seam_reads_both_submaps_and_blends_them(tmp_path):
    m = _mapped(tmp_path)
    subs = m.submaps
    assert len(subs.infos) >= 2 and subs.on_disk() >= 1
    seam = subs.infos[1].anchor[0]  # x where the second submap started
    q = np.stack([np.full(40, seam), np.linspace(-5.9, 5.9, 40), np.full(40, 0.3)], 1)
    reads = []
    real = sm.Submaps._read_submap

    def spy(self, k, pts_w, idx, *a):
        reads.append((k, len(idx)))
        return real(self, k, pts_w, idx, *a)

    sm.Submaps._read_submap = spy
    try:
        s, v = m.sdf(q)
    finally:
        sm.Submaps._read_submap = real
    assert v.all()
    assert {0, 1} <= {k for k, n in reads if n > 0}, reads
    # the blend is the weighted mean of the two readings, not either one
    s0, v0 = sm.query_world(subs.static, subs.state(0), sm.to_local(subs.infos[0].pose, q))
    s1, v1 = sm.query_world(subs.static, subs.state(1), sm.to_local(subs.infos[1].pose, q))
    assert v0.all() and v1.all()
    lo, hi = np.minimum(s0, s1), np.maximum(s0, s1)
    assert np.all(s >= lo - 1e-6) and np.all(s <= hi + 1e-6)
    inner = (hi - lo) > 1e-3
    assert inner.any() and np.all(np.minimum(s - lo, hi - s)[inner] > 0), "one submap's reading alone"


def test_a_wall_across_a_seam_is_as_flat_as_inside_a_submap(tmp_path):
    """The zero crossing of the wall y = 6 m along x: near the seams it deviates from the plane no more
    than in the middle of a submap (1.5x + 5 mm)."""
    m = _mapped(tmp_path, n=26, beams=32, steps=512, extra=["train.iters=20"])
    subs = m.submaps
    seams = [i.anchor[0] for i in subs.infos[1:]]
    assert len(seams) >= 2
    xs = np.arange(2.0, 22.0, 0.1)
    ys = np.linspace(5.6, 6.2, 61)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    q = np.stack([X.ravel(), Y.ravel(), np.full(X.size, 1.0)], 1)
    s, v = m.sdf(q)
    s, v = s.reshape(X.shape), v.reshape(X.shape)
    crossing = np.full(len(xs), np.nan)
    for i in range(len(xs)):
        ok = v[i]
        j = np.nonzero(ok[:-1] & ok[1:] & (s[i, :-1] > 0) & (s[i, 1:] <= 0))[0]
        if len(j):
            j = j[0]
            crossing[i] = ys[j] + (ys[j + 1] - ys[j]) * s[i, j] / (s[i, j] - s[i, j + 1])
    dev = np.abs(crossing - 6.0)
    near = np.min(np.abs(xs[:, None] - np.array(seams)[None]), axis=1) < 1.5
    inside = np.min(np.abs(xs[:, None] - np.array(seams)[None]), axis=1) > 3.0
    assert np.isfinite(dev[near]).all() and np.isfinite(dev[inside]).all()
    assert np.percentile(dev[near], 90) <= 1.5 * np.percentile(dev[inside], 90) + 0.005, (
        np.percentile(dev[near], 90), np.percentile(dev[inside], 90))


def test_a_submap_is_placed_by_its_pose_not_its_inverse(tmp_path):
    m = _mapped(tmp_path, n=10)
    subs = m.submaps
    rng = np.random.default_rng(0)
    p_local = np.stack([rng.uniform(1, 7, 300), rng.uniform(-5.9, 5.9, 300), rng.uniform(0.05, 2.0, 300)], 1)
    before, valid = m.sdf(p_local)
    _, g_before = m.sdf_grad(p_local)
    c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
    T = np.array([[c, -s, 0, 5.0], [s, c, 0, -2.0], [0, 0, 1, 0.5], [0, 0, 0, 1]])
    for info in subs.infos:
        info.pose = T.copy()
    p_world = sm.to_world(T, p_local)
    after, valid_after = m.sdf(p_world)
    _, g_after = m.sdf_grad(p_world)
    np.testing.assert_array_equal(valid_after, valid)
    np.testing.assert_allclose(after[valid], before[valid], atol=1e-5)
    np.testing.assert_allclose(g_after[valid], (g_before @ T[:3, :3].T)[valid], atol=1e-4)
    inverse = sm.to_world(np.linalg.inv(T), p_local)
    wrong, wv = m.sdf(inverse)
    both = wv & valid
    assert (~wv).mean() > 0.2 or np.abs(wrong[both] - before[both]).mean() > 0.05


def test_an_evicted_submap_comes_back_bit_for_bit(tmp_path):
    parked = {}
    real = sm.Submaps.park

    def keep(self, k, state):
        parked.setdefault(k, jax.tree_util.tree_map(np.array, state))
        return real(self, k, state)

    sm.Submaps.park = keep
    try:
        m = _mapped(tmp_path, n=20, extra=["submaps.resident=1"])
    finally:
        sm.Submaps.park = real
    subs = m.submaps
    assert 0 in parked and 0 not in subs.states  # written and dropped
    full = subs.take(0, parked[0].store.pairs.shape[0])  # the whole state, as mapping takes it up again
    # ... with an empty pair store of the same capacity (the window's pairs are not kept: `Submaps.park`)
    assert full.store.n_slots == parked[0].store.pairs.shape[0] and int(full.store.count.sum()) == 0
    back, want = full.replace(store=None), parked[0].replace(store=None)
    slots = {id(x) for t in (back.voxels, back.corners) for x in jax.tree_util.tree_leaves(t)}
    n = 0
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(back), jax.tree_util.tree_leaves(want)):
        if id(a) in slots:  # hash tables: same keys and rows, slots may differ (`n3.checkpoint`)
            continue
        np.testing.assert_array_equal(np.asarray(a), b, err_msg=jax.tree_util.keystr(path))
        n += 1
    assert n > 20
    q = np.stack([np.linspace(0, 7, 50), np.full(50, 5.9), np.full(50, 1.0)], 1)
    s_back = sm.query_world(subs.static, back, q)[0]
    s_kept = sm.query_world(subs.static, jax.tree_util.tree_map(jax.numpy.asarray, want), q)[0]
    np.testing.assert_array_equal(s_back, s_kept)
    # the mesh reads every submap, up to resident + 4 at once, and leaves `submaps.resident` in memory (the
    # one mapped): the end of a run is evaluated beside what the mesh held
    assert len(subs.infos) >= 3 and len(m.mesh().faces) > 0
    assert subs.resident() == 1 and not subs.states


def test_a_map_of_submaps_saved_and_loaded_goes_on_as_if_never_stopped(tmp_path):
    frames = _frames(16)
    cfg = load_config("configs/city.yaml", SMALL + SUB)
    a = SubmapMapper(cfg, directory=str(tmp_path / "a"))
    for pts, pose in frames:
        a.add_frame(pts, pose)
    b = SubmapMapper(cfg, directory=str(tmp_path / "b" / "submaps"))
    for i, (pts, pose) in enumerate(frames[:11]):
        b.add_frame(pts, pose)
        if i + 1 in (7, 11):  # one save in the first submap, one in the second (3 frames of its own)
            b.save(str(tmp_path / "b" / "checkpoint"))
    # numbered by the whole map's frames: the later save does not delete the one before it (a SLAM state
    # names that one until the state written after the new save replaces it)
    assert len(b.submaps.infos) == 2 and steps(str(tmp_path / "b" / "checkpoint")) == [11, 7]
    c = load_map(str(tmp_path / "b" / "checkpoint"))
    with pytest.raises(CheckpointError, match="load_map"):  # one grid's loader says where to go
        N3Mapper.load(str(tmp_path / "b" / "checkpoint"))
    assert isinstance(c, SubmapMapper) and len(c.submaps.infos) == len(b.submaps.infos)
    assert c.frames == 11 and c.bucket == b.bucket  # the whole map's frames, not the active submap's
    for pts, pose in frames[11:]:
        c.add_frame(pts, pose)
    assert len(c.submaps.infos) == len(a.submaps.infos)
    assert [r["frame"] for r in c.timings] == list(range(16))
    assert [i.frames for i in c.submaps.infos] == [i.frames for i in a.submaps.infos]
    q = np.stack([np.linspace(0, 15, 200), np.full(200, -5.9), np.full(200, 0.8)], 1)
    np.testing.assert_array_equal(c.sdf(q)[0], a.sdf(q)[0])


def test_groups_meshed_apart_weld_into_the_one_mesh():
    """`extract_mesh_groups` of cells split in two groups equals `extract_mesh` of them all."""
    def sphere(p):
        return np.linalg.norm(p - np.array([0.15, 0.1, 0.05]), axis=1) - 0.6, np.ones(len(p), bool)

    g = np.stack(np.meshgrid(*[np.arange(-5, 6)] * 3, indexing="ij"), -1).reshape(-1, 3)
    one = extract_mesh(sphere, g, 0.2, 0.1)
    split = g[:, 0] + g[:, 1] < 1
    two = extract_mesh_groups(lambda _: sphere, [g[split], g[~split]], 0.2, 0.1)
    assert len(two.faces) == len(one.faces) and len(two.vertices) == len(one.vertices)
    assert two.is_watertight and one.is_watertight
    np.testing.assert_allclose(np.sort(two.vertices, axis=0), np.sort(one.vertices, axis=0), atol=1e-6)


def test_cells_far_from_seams_read_their_submap_alone_and_mesh_as_the_blend_does(tmp_path, monkeypatch):
    """The mesh reads a submap's own cells far from every seam from that submap alone (`_owner`'s alone:
    the other paths farther than blend_m + the cell's diagonal); the mesh is the one the blended query
    makes everywhere, vertex for vertex. A margin without the diagonal, or cells near a seam read alone,
    leave the blend out where it weighs and move the vertices there."""
    m = _mapped(tmp_path, n=24)
    subs = m.submaps
    assert len(subs.infos) >= 3
    read = [subs._owner(subs._cells_world(k, subs.limit + 4)) for k in range(len(subs.infos))]
    alone = np.concatenate([a & (o == k) for k, (o, a) in enumerate(read)])
    assert 0.2 < alone.mean() < 0.8  # both kinds of cells (8 m submaps, 3 m blend, 10 m range)
    fast = m.mesh()
    monkeypatch.setattr(sm.Submaps, "_owner", lambda self, c: (real_owner(self, c)[0], np.zeros(len(c), bool)))
    blended = m.mesh()
    assert len(fast.faces) == len(blended.faces) > 1000
    key = lambda mesh: np.sort(np.round(mesh.vertices[mesh.faces].reshape(-1, 9) * 1e4).astype(np.int64), axis=0)  # noqa: E731
    np.testing.assert_array_equal(key(fast), key(blended))


real_owner = sm.Submaps._owner


def test_submaps_are_refused_where_they_would_be_ignored():
    with pytest.raises(ConfigError, match="submaps"):
        load_config("configs/city.yaml", ["submaps.enabled=true", "window.mode=replay"])
    with pytest.raises(ConfigError, match="SubmapMapper"):
        N3Mapper(load_config("configs/city.yaml", SMALL + SUB))


@pytest.mark.parametrize("revisit", [True, False])
def test_frames_uploaded_before_a_switch_are_made_in_the_submap_they_map_into(tmp_path, monkeypatch, revisit):
    """`jaxmap map` uploads frames ahead (`scan.Uploader`), and the uploader alone routes them
    (`routing.Route`): with every frame of a drive out and back uploaded before the first is mapped (a
    full prefetch queue across every switch), each frame reaches the grid in the map frame of the submap
    it is mapped into, bit for bit the batch made there, and the chain is the one the map builds routing
    each frame itself (`add_frame`). An uploader whose origin the main thread moves at a switch would
    make the queued frames in the old submap's frame."""
    from jaxmap.frame_loop import Frame
    from jaxmap.n3 import routing, scan
    from jaxmap.n3.mapper import N3Mapper as Grid

    xs = list(range(13)) + list(range(11, -1, -1))
    frames = [(corridor_scan(float(x), max_range=10.0), pose_at(float(x))) for x in xs]
    cfg = load_config("configs/city.yaml", SMALL + SUB + [f"submaps.revisit={str(revisit).lower()}"])
    m = SubmapMapper(start=scan.MapStart.of(cfg, *frames[0]), directory=str(tmp_path / "s"))
    upload, got, real = m.uploader(), [], Grid.submit

    def spy(self, batch, **kw):
        got.append((jax.tree_util.tree_map(np.asarray, batch), self.origin.copy()))
        return real(self, batch, **kw)

    monkeypatch.setattr(Grid, "submit", spy)
    queued = []
    for i, (pts, pose) in enumerate(frames):
        p, nrm, pose, img = scan.preprocess(pts, pose, m.cfg.preprocess, i, image=m.static.evidence)
        queued.append((Frame(i, i, p, pose, nrm, img), upload(Frame(i, i, p, pose, nrm, img))))
    for _, f in queued:
        m.submit(f.batch, points=len(f.points), place=f.place)
    m.finish()
    monkeypatch.undo()

    alone = SubmapMapper(cfg, directory=str(tmp_path / "a"))
    for pts, pose in frames:
        alone.add_frame(pts, pose)
    chain = [r["submap"] for r in m.timings]
    assert chain == [r["submap"] for r in alone.timings] and len(set(chain)) >= 2, chain
    assert (chain[-1] == 0) == revisit  # the way back: the first submap again, or (no revisit) a new one
    for k, info in enumerate(m.submaps.infos):
        np.testing.assert_array_equal(info.anchor, alone.submaps.infos[k].anchor)
    for (batch, origin), (plain, f), k in zip(got, queued, chain):
        np.testing.assert_array_equal(origin, routing.submap_origin(m.static, m.submaps.infos[k].anchor))
        want = scan.Uploader(origin, raw=False)(plain).batch
        np.testing.assert_array_equal(batch.points, np.asarray(want.points))
        np.testing.assert_array_equal(batch.sensor, np.asarray(want.sensor))


def test_a_batch_made_in_another_map_frame_is_refused(tmp_path):
    from jaxmap.frame_loop import Frame
    from jaxmap.n3 import routing, scan

    frames = _frames(2)
    cfg = load_config("configs/city.yaml", SMALL + SUB)
    m = SubmapMapper(start=scan.MapStart.of(cfg, *frames[0]), directory=str(tmp_path / "s"))
    p, nrm, pose, img = scan.preprocess(*frames[0], m.cfg.preprocess, 0, image=m.static.evidence)
    f = scan.Uploader(m.origin + 3.2, raw=False)(Frame(0, 0, p, pose, nrm, img))
    with pytest.raises(ValueError, match="uploader"):  # no route: which submap is not known
        m.submit(f.batch, points=len(p), place=f.place)
    wrong = routing.Place(m.origin + 3.2, 0, pose[:3, 3])
    with pytest.raises(ValueError, match="map frame"):
        m.submit(f.batch, points=len(p), place=wrong)
    assert m.frames == 0 and m.submaps.infos[0].frames == []  # nothing of the refused frame kept
    one = N3Mapper(load_config("configs/city.yaml", SMALL), first_scan=frames[0])
    with pytest.raises(ValueError, match="map frame"):
        one.submit(f.batch, points=len(p), place=f.place)


def test_a_drive_back_takes_up_its_old_submap_again(tmp_path):
    """Out 12 m and back: the way back maps into the first submap again (no third submap), which comes
    back from its file whole and goes on training: its wall as close to the truth as one grid's."""
    xs = list(range(13)) + list(range(11, -1, -1))
    frames = [(corridor_scan(float(x), max_range=10.0), pose_at(float(x))) for x in xs]
    m = SubmapMapper(load_config("configs/city.yaml", SMALL + SUB + ["submaps.resident=1"]),
                     directory=str(tmp_path / "s"))
    one = N3Mapper(load_config("configs/city.yaml", SMALL))
    for pts, pose in frames:
        m.add_frame(pts, pose)
        one.add_frame(pts, pose)
    subs = [r["submap"] for r in m.timings]
    assert subs[0] == 0 and 1 in subs and subs[-1] == 0 and len(m.submaps.infos) == 2, subs
    assert m.submaps.infos[0].frames[-1] == len(xs) - 1
    q = np.stack([np.linspace(0.5, 4, 50), np.full(50, 5.9), np.full(50, 1.0)], 1)
    (s, v), (s1, v1) = m.sdf(q), one.sdf(q)
    err, err1 = np.median(np.abs(s - 0.1)), np.median(np.abs(s1 - 0.1))
    assert v.all() and err <= 1.5 * err1 + 0.01, (err, err1)


def test_a_drive_longer_than_auto_m_maps_in_submaps_with_no_flag():
    """`submaps_for_drive`: submaps.enabled false (the default) and a drive whose poses' path is longer
    than submaps.auto_m: submaps on; a shorter one, auto_m 0, or the replay window (one grid only): the
    config as it was."""
    from jaxmap.runs.n3 import submaps_for_drive

    poses = np.stack([np.eye(4)] * 11)
    poses[:, 0, 3] = np.arange(11) * 10.0 + np.sin(np.arange(11))   # 100 m and the wiggles along x
    path = np.abs(np.diff(poses[:, 0, 3])).sum()
    cfg = load_config("configs/city.yaml")
    assert not cfg.submaps.enabled and cfg.submaps.auto_m == 300.0   # the shipped default: on past 300 m
    for auto_m, window, on in ((path - 1.0, "voxel", True), (path + 1.0, "voxel", False), (0.0, "voxel", False),
                               (path - 1.0, "replay", False)):
        c = load_config("configs/city.yaml", [f"submaps.auto_m={auto_m}", f"window.mode={window}"])
        got = submaps_for_drive(c, poses)
        assert got.submaps.enabled is on, (auto_m, window)
        assert dataclasses.replace(got, submaps=c.submaps) == c          # nothing else changes


def test_mapping_at_given_poses_makes_a_map_of_submaps(small_city, tmp_path):
    """`map_at_poses` (the N3 map `jaxmap slam` builds offline at its optimised poses) of a drive longer
    than submaps.auto_m, with no flag, maps into submaps placed at the given poses (it refused: N3Mapper
    maps one grid)."""
    from jaxmap.frame_loop import open_run_sequence
    from jaxmap.runs.n3 import map_at_poses

    cfg = load_config("configs/city.yaml", SMALL + ["submaps.length_m=2", "train.iters=10",
                                                    f"data.path={small_city}", "data.end_frame=6",
                                                    f"output={tmp_path}"])
    seq = open_run_sequence(cfg)
    t = np.asarray(seq.poses)[:, :3, 3]
    cfg = dataclasses.replace(cfg, submaps=dataclasses.replace(
        cfg.submaps, auto_m=0.5 * float(np.linalg.norm(np.diff(t, axis=0), axis=1).sum())))
    assert not cfg.submaps.enabled
    m, loop = map_at_poses(cfg, seq, np.asarray(seq.poses), progress=False)
    assert isinstance(m, SubmapMapper) and len(m.submaps.infos) >= 2 and loop.frames_run == 6
    assert (tmp_path / "submaps").is_dir()
    T = np.asarray(seq.poses[5])
    pts = seq.frame(5).points[::20]
    pts = pts[np.linalg.norm(pts, axis=1) < 8.0]
    s, v = m.sdf(pts @ T[:3, :3].T + T[:3, 3])
    assert v.mean() > 0.8 and np.median(np.abs(s[v])) < 0.05, (v.mean(), np.median(np.abs(s[v])))
