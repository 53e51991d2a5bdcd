"""The live browser viewer (jaxmap.viewer, viser): scene and GUI calls, the background mesh thread, and a
finished run loaded in headless chromium, whose screenshot must not be blank."""
import os
import shutil
import socket
import subprocess
import threading
import time

import numpy as np
import pytest

viser = pytest.importorskip("viser", reason="viser is not installed (pip install 'jaxmap[view]')")

from jaxmap.viewer import MeshWorker, Viewer, attach_viewer, error_colors, open_run, to_world  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _box_mesh():
    import trimesh

    return trimesh.creation.box(extents=(2.0, 1.0, 0.5))


def test_viewer_scene_and_gui_calls():
    v = Viewer(port=free_port(), quiet=True, max_points=500)
    try:
        assert v.host == "0.0.0.0" and v.url.endswith(f":{v.port}")
        pose = np.eye(4)
        pose[:3, 3] = [1.0, 2.0, 0.5]
        pts = np.random.default_rng(0).normal(size=(2000, 3)).astype(np.float32)
        w = to_world(pts, pose, max_points=800)
        assert w.shape == (800, 3) and np.allclose(to_world(pts, pose)[:, :3], pts + pose[:3, 3], atol=1e-6)
        v.show_scan(w)
        v.show_pose(pose)
        for i in range(3):
            p = pose.copy()
            p[0, 3] += i
            v.add_trajectory_pose(p)
        assert len(v._traj) == 3
        m = _box_mesh()
        v.show_mesh(m)
        v.show_mesh(m, vertex_colors=error_colors(np.linspace(0, 0.2, len(m.vertices)), 0.1))
        v.show_loops(np.array([[[0, 0, 0], [1, 1, 0]]], dtype=float))
        v.update_info(frame=3, loss=0.0123, timings={"encode_s": 0.5}, note="x")
        assert v._g_frame.value == "3" and v._g_loss.value == "0.0123" and "encode_s: 500.0 ms" in v._g_times.content
    finally:
        v.close()


def test_error_colors_blue_to_red():
    c = error_colors(np.array([0.0, 0.05, 0.1, 1.0]), 0.1)
    assert c.dtype == np.uint8 and c.shape == (4, 3)
    assert c[0, 2] > c[0, 0] and c[2, 0] > c[2, 2] and np.array_equal(c[2], c[3])


def test_mesh_worker_runs_in_the_background_and_skips_while_busy():
    gate, got = threading.Event(), []
    w = MeshWorker(lambda: (gate.wait(5), "mesh")[1], got.append)
    assert w.request() and w.busy()
    assert not w.request() and w.skipped == 1                 # one extraction at a time
    gate.set()
    w.join(5)
    assert got == ["mesh"] and w.runs == 1 and not w.busy()
    w.max_share, w._next_ok = 0.05, time.perf_counter() + 60   # duty-cycle budget: too soon after the last one
    assert not w.request() and w.throttled == 1


def test_attach_viewer_hooks():
    calls = []

    def mesh_fn():
        calls.append(1)
        return _box_mesh()

    hooks = attach_viewer(port=free_port(), mesh_every=2, mesh_fn=mesh_fn, mesh_max_share=0, quiet=True)
    try:
        for i in range(4):
            pose = np.eye(4)
            pose[0, 3] = i
            hooks.on_frame(i, np.random.default_rng(i).normal(size=(100, 3)), pose, {"loss": 0.5, "fuse_s": 0.01})
            hooks.worker.join(5)
        assert len(calls) == 2 and hooks.viewer._g_frame.value == "3"
        hooks.on_trajectory(np.tile(np.eye(4), (4, 1, 1)))
        hooks.on_loop(np.eye(4), np.eye(4))
        hooks.finish(_box_mesh())
    finally:
        hooks.close()


def test_snapshot_is_taken_in_the_loop_thread():
    """snapshot_fn runs where on_frame is called; mesh_fn gets its result in the background thread."""
    state = {"frame": 0}
    seen = []

    def mesh_fn(snap):
        seen.append((snap, threading.current_thread().name))
        return _box_mesh()

    hooks = attach_viewer(port=free_port(), mesh_every=1, mesh_fn=mesh_fn, mesh_max_share=0, quiet=True,
                          snapshot_fn=lambda: (dict(state), threading.current_thread().name))
    try:
        for i in range(2):
            state["frame"] = i
            hooks.on_frame(i, np.zeros((10, 3)), np.eye(4), {})
            hooks.worker.join(5)
    finally:
        hooks.close()
    main = threading.current_thread().name
    assert [s[0][0]["frame"] for s in seen] == [0, 1] and all(s[0][1] == main for s in seen)
    assert all(s[1] == "jaxmap-viewer-mesh" for s in seen)


# ------------------------------------------------------------------------------------------------
# a finished run in a real browser
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """`jaxmap imt` on a 4-frame small room (2 frames mapped, coarse mesh): a finished run directory."""
    from jaxmap.cli import main
    from jaxmap.synth.room import generate_room

    root = tmp_path_factory.mktemp("viewer_run")
    data, run = root / "room", root / "run"
    generate_room(data, seed=0, small=True, n_frames=4)
    rc = main(["imt", "configs/room_imt.yaml", "--data", str(data), "--out", str(run), "--no-progress",
               "--set", "mesh.resolution=2", "--set", "eval.n_samples=20000"])
    assert rc == 0 and (run / "mesh.ply").is_file()
    return run


def screenshot(url: str, out: str, size=(1280, 800), budget_ms: int = 15000) -> subprocess.CompletedProcess:
    """Load `url` in headless chromium (software WebGL) and save a PNG screenshot."""
    cmd = [chromium(), "--headless", "--no-sandbox", "--disable-gpu-sandbox", "--use-gl=angle",
           "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars", "--mute-audio",
           "--no-first-run", f"--window-size={size[0]},{size[1]}", f"--virtual-time-budget={budget_ms}",
           f"--user-data-dir={os.path.dirname(out)}/chromium-profile", f"--screenshot={out}", url]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=240)


def _canvas(path: str) -> np.ndarray:
    """The 3D canvas of a viewer screenshot (left of viser's control panel), as int RGB."""
    from PIL import Image

    img = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert img.shape[:2] == (800, 1280)
    return img[150:750, 100:900]


def _drawn(canvas: np.ndarray) -> bool:
    """Whether the scene was drawn at all: an empty page is a handful of grey shades."""
    return len(np.unique(canvas.reshape(-1, 3), axis=0)) > 50


@pytest.mark.skipif(chromium() is None, reason="chromium is not installed (make sysdeps, or apt-get install chromium)")
def test_viewer_in_headless_chromium_shows_the_run(small_run, tmp_path):
    v, facts = open_run(small_run, port=free_port(), quiet=True)
    try:
        assert facts["faces"] > 0 and "error_mean_m" in facts     # the room has ground truth: error colours
        # On a busy CI machine the page can be captured before the websocket has delivered the scene (a
        # blank grey canvas). That is the browser's timing, not the viewer: try again with a longer budget;
        # the assertions below still require the mesh once the page has drawn.
        for attempt, budget_ms in enumerate((15000, 30000, 60000)):
            out = str(tmp_path / f"viewer{attempt}.png")
            r = screenshot(f"http://127.0.0.1:{v.port}/", out, budget_ms=budget_ms)
            assert r.returncode == 0 and os.path.isfile(out), r.stderr[-2000:]
            canvas = _canvas(out)
            if _drawn(canvas) and _mesh_share(canvas) > 0.05 and _coloured_share(canvas) > 0.01:
                break  # (a loaded machine has also captured the page with the scene only half delivered)
    finally:
        v.close()
    assert _drawn(canvas), "three screenshots showed an empty canvas"
    # the mesh covers part of the canvas
    assert _mesh_share(canvas) > 0.05, f"only {100 * _mesh_share(canvas):.2f} % of the canvas differs from the background"
    # error-coloured mesh: some pixels are clearly bluish/greenish (not grey UI)
    assert _coloured_share(canvas) > 0.01


def _mesh_share(canvas: np.ndarray) -> float:
    """Share of the canvas that differs from its background (the median of its top and bottom rows)."""
    background = np.median(np.concatenate([canvas[:5].reshape(-1, 3), canvas[-5:].reshape(-1, 3)]), axis=0)
    return float((np.abs(canvas - background).sum(-1) > 30).mean())


def _coloured_share(canvas: np.ndarray) -> float:
    """Share of the canvas in clearly saturated colours (the error colours; the UI is grey)."""
    return float((canvas.max(-1) - canvas.min(-1) > 60).mean())


def test_view_command_no_wait(small_run, capsys):
    from jaxmap.cli import main

    assert main(["view", str(small_run), "--port", str(free_port()), "--no-wait"]) == 0
    assert "faces=" in capsys.readouterr().err
    assert main(["view", str(small_run.parent / "missing")]) == 2
    assert "missing" in capsys.readouterr().err


def test_copy_arrays_survives_donation():
    """A snapshot for the background mesh must outlive the next frame's donated update (N3 donates)."""
    import jax
    import jax.numpy as jnp

    from jaxmap.snapshot import copy_arrays

    step = jax.jit(lambda s: {"a": s["a"] + 1}, donate_argnums=0)
    state = {"a": jnp.arange(4.0)}
    snap = copy_arrays((state, 3, np.ones(2)))
    state = step(state)
    np.testing.assert_array_equal(np.asarray(snap[0]["a"]), np.arange(4.0))
    assert snap[1] == 3 and isinstance(snap[2], np.ndarray)
    np.testing.assert_array_equal(np.asarray(state["a"]), np.arange(4.0) + 1)


# ------------------------------------------------------------------------------------------------
# a background mesh while the map goes on mapping
# ------------------------------------------------------------------------------------------------


class _Seq:
    """A sequence of analytic corridor scans (`seq.frame(i)`, as `jaxmap.io` reads them)."""

    def __init__(self, frames):
        self.frames = frames

    def __len__(self):
        return len(self.frames)

    def frame(self, i):
        import types

        return types.SimpleNamespace(points=self.frames[i][0], pose=self.frames[i][1], index=i)


def _slow(mesh_fn, meshes, delay=0.4):
    """mesh_fn that waits first (so the next frames' programs run, and donate the map's buffers, while it
    meshes) and keeps what it made."""
    def run(*snap):
        time.sleep(delay)
        mesh = mesh_fn(*snap)
        meshes.append(mesh)
        return mesh
    return run


def test_n3_background_mesh_while_mapping(caplog):
    """`jaxmap map --view`'s live mesh on an N3 map: the mesh thread meshes a copy of the map taken between
    frames (`N3Mapper.live_mesh`'s snapshot) while the frame loop maps on and each frame program donates
    the map's buffers. Every mesh is made (none fails on a deleted buffer) and shows the corridor; meshing
    the state itself (no copy) fails here, as `jaxmap.snapshot` says."""
    import logging

    from analytic_lidar import corridor_scan, pose_at

    from jaxmap.config import load_config
    from jaxmap.frame_loop import Prefetcher, SubmitSteps, prepared_frame, run_frames
    from jaxmap.n3.mapper import N3Mapper

    cfg = load_config("configs/city.yaml", ["train.iters=6", "train.nv=128", "train.np_per_voxel=8",
                                            "preprocess.max_range_m=10.0", "preprocess.vox_down_m=0.2",
                                            "window.initial_blocks=4096", "mesh.min_component_faces=0",
                                            "mesh.resolution_m=0.2"])
    seq = _Seq([(corridor_scan(1.5 * i, max_range=10.0), pose_at(1.5 * i)) for i in range(6)])
    mapper = N3Mapper(cfg, first_scan=(seq.frames[0][0], seq.frames[0][1]))
    live, meshes = mapper.live_mesh(), []
    hooks = attach_viewer(port=free_port(), mesh_every=1, mesh_max_share=0, quiet=True,
                          snapshot_fn=live["snapshot_fn"], mesh_fn=_slow(live["mesh_fn"], meshes))
    uploader = mapper.uploader()
    frames = Prefetcher(seq, 0, len(seq), lambda s, i: prepared_frame(mapper.start.prepare, s, i), then=uploader)
    try:
        with caplog.at_level(logging.WARNING, logger="jaxmap"):
            run_frames(frames, SubmitSteps(mapper), total=len(seq), viewer=hooks)
            hooks.worker.join(30)
    finally:
        hooks.close()
    failed = [r.getMessage() for r in caplog.records if "mesh extraction failed" in r.getMessage()]
    assert not failed, failed
    # frames were mapped while a mesh was being made (those frames' requests were skipped as busy)
    assert hooks.worker.runs >= 1 and hooks.worker.skipped >= 1 and len(meshes) == hooks.worker.runs
    assert all(len(m.faces) > 100 for m in meshes)


def test_imt_map_meshes_in_the_background_while_frames_are_added(small_room, caplog):
    """The IMT map's live mesh works on a snapshot taken between frames: a snapshot meshed after the next
    frame's step (which donates the map's buffers) is the map as it was, and a mapping loop with the
    viewer's mesh thread meshing every frame finishes with meshes and no failed extraction."""
    import logging

    from jaxmap.config import ImtConfig, load_config
    from jaxmap.frame_loop import open_run_sequence
    from jaxmap.imt.mapper import ImtMapper
    from jaxmap.runs.imt import fuse_sequence

    cfg = load_config("room_imt", [f"data.path={small_room}", "data.end_frame=5", "data.every_frame=1",
                                   "mesh.resolution=4"], ImtConfig)
    seq = open_run_sequence(cfg)
    mapper = ImtMapper(cfg)
    fuse_sequence(mapper, seq, progress=False)
    live = mapper.live_mesh()
    snap = live["snapshot_fn"]()
    ref = live["mesh_fn"](mapper.map)
    before = mapper.map
    fr = seq.frame(0)
    mapper.add_frame(fr.points, fr.pose)                    # the step donates the map the snapshot copied
    assert before.weight.is_deleted()
    again = live["mesh_fn"](snap)
    np.testing.assert_array_equal(np.asarray(again.vertices), np.asarray(ref.vertices))

    mapper = ImtMapper(cfg)
    meshes = []
    hooks = attach_viewer(port=free_port(), mesh_every=1, mesh_max_share=0, quiet=True, **mapper.live_mesh())
    hooks.on_mesh = lambda m: meshes.append(m)
    hooks.worker.on_mesh = hooks.on_mesh
    try:
        with caplog.at_level(logging.WARNING, logger="jaxmap"):
            fuse_sequence(mapper, seq, progress=False, viewer=hooks)
            hooks.worker.join(60)
    finally:
        hooks.close()
    # every frame asked for a mesh: one ran, or was still running (then the frame skipped it) while it mapped
    assert hooks.worker.runs + hooks.worker.skipped == len(seq)
    assert meshes and all(len(m.faces) > 0 for m in meshes)
    assert not [r for r in caplog.records if "mesh extraction failed" in r.getMessage()]
