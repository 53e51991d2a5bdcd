"""A live view of the map in the browser, with viser (`pip install 'jaxmap[view]'`).

`Viewer` starts a viser server bound to 0.0.0.0 (so a headless mapping machine is viewed from another
one: open http://HOST:PORT) and prints the address. It shows the current scan (world frame), the
trajectory, the sensor pose, a mesh (plain, or coloured per vertex), loop closures, and a GUI panel
with the frame, the loss and timings. Every method may be called from the mapping loop: what it sends
is subsampled and handed to viser's own thread.

`MeshWorker` re-extracts the mesh in a background thread every N frames (one extraction at a time;
a request while one runs is skipped), so the mapping loop never waits for marching cubes.
`attach_viewer(...)` bundles both behind two callbacks for any mapping loop:

    hooks = attach_viewer(port=8080, mesh_every=10, mesh_fn=lambda: mapper.mesh())
    for i, frame in enumerate(seq):
        info = mapper.add_frame(frame.points, frame.pose)
        hooks.on_frame(i, to_world(frame.points, frame.pose), frame.pose, info)
    hooks.on_mesh(final_mesh); hooks.close()

`jaxmap imt --view` and `jaxmap slam --view` use it; `jaxmap view RUN_DIR` (`view_run`) opens a finished
run: mesh.ply, trajectory_kitti.txt when present, and, when the run's data (config.yaml data.path) has
gt_points.ply, the mesh coloured by each vertex's distance to the ground truth.
"""
from __future__ import annotations

import logging
import os
import socket
import sys
import threading
import time

import numpy as np

from jaxmap.errors import DataError, JaxmapError
from jaxmap.geometry import SE3

log = logging.getLogger("jaxmap")

SCAN_COLOR = (255, 140, 0)
TRAJ_COLOR = (220, 30, 60)
LOOP_COLOR = (30, 160, 60)
MESH_COLOR = (150, 190, 230)


def _import_viser():
    try:
        import viser
    except ImportError:
        raise JaxmapError("the viewer needs the viser package: pip install 'jaxmap[view]' (or pip install viser)") \
            from None
    return viser


def to_world(points_s: np.ndarray, pose: np.ndarray, max_points: int | None = None, seed: int = 0) -> np.ndarray:
    """Sensor-frame points [N,3] -> world frame [M,3] float32 (p_w = R p_s + t), subsampled to max_points."""
    pts = np.asarray(points_s, dtype=np.float32).reshape(-1, 3)
    if max_points is not None and len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
    T_w_s = SE3.from_matrix(np.asarray(pose, dtype=np.float64)).astype(np.float32)  # display: float32 is plenty
    return T_w_s.apply(pts).astype(np.float32)


def _wxyz(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return np.array([w, x, y, z])


def error_colors(dist: np.ndarray, max_m: float) -> np.ndarray:
    """Per-vertex distances [V] (m) -> uint8 RGB [V,3]: blue (0) through green and yellow to red (>= max_m)."""
    t = np.clip(np.asarray(dist, dtype=np.float64) / max(float(max_m), 1e-9), 0.0, 1.0)
    stops = np.array([[40, 80, 220], [40, 200, 90], [250, 220, 40], [220, 30, 30]], dtype=np.float64)
    x = t * (len(stops) - 1)
    i = np.minimum(x.astype(int), len(stops) - 2)
    f = (x - i)[:, None]
    return (stops[i] * (1 - f) + stops[i + 1] * f).astype(np.uint8)


def _host_name() -> str:
    try:
        return socket.gethostname() or "localhost"
    except OSError:  # pragma: no cover
        return "localhost"


class Viewer:
    """A viser server showing a map as it is built (see the module docstring).

    port: the port to serve on (viser moves to the next free one if it is taken; `self.port` is the one
    used); host: the interface (0.0.0.0 = every one). max_points: scan points sent per frame (subsampled).
    """

    def __init__(self, port: int = 8080, host: str = "0.0.0.0", label: str = "jaxmap", max_points: int = 30_000,
                 point_size: float = 0.03, quiet: bool = False):
        viser = _import_viser()
        self.server = viser.ViserServer(host=host, port=int(port), label=label, verbose=False)
        self.port = int(self.server.get_port())
        self.host = host
        self.max_points = int(max_points)
        self.point_size = float(point_size)
        self._lock = threading.Lock()
        self._traj: list[np.ndarray] = []
        self.server.scene.set_up_direction("+z")
        self._make_gui()
        self.url = f"http://{_host_name()}:{self.port}"
        if not quiet:
            print(f"[jaxmap] viewer: {self.url} (listening on {host}:{self.port}; "
                  f"http://localhost:{self.port} on this machine)", file=sys.stderr, flush=True)

    # -- GUI ------------------------------------------------------------------------------------
    def _make_gui(self) -> None:
        gui = self.server.gui
        with gui.add_folder("jaxmap"):
            self._g_frame = gui.add_text("frame", "-", disabled=True)
            self._g_loss = gui.add_text("loss", "-", disabled=True)
            self._g_fps = gui.add_text("frames/s", "-", disabled=True)
            self._g_extra = gui.add_markdown("")
        with gui.add_folder("timings"):
            self._g_times = gui.add_markdown("")
        with gui.add_folder("layers"):
            self._g_show_scan = gui.add_checkbox("scan", True)
            self._g_show_mesh = gui.add_checkbox("mesh", True)
            self._g_show_traj = gui.add_checkbox("trajectory", True)
        self._g_show_scan.on_update(lambda _: self._set_visible("/scan", self._g_show_scan.value))
        self._g_show_mesh.on_update(lambda _: self._set_visible("/mesh", self._g_show_mesh.value))
        self._g_show_traj.on_update(lambda _: self._set_visible("/trajectory", self._g_show_traj.value))
        self._handles: dict[str, object] = {}
        self._t_last = None

    def _set_visible(self, name: str, visible: bool) -> None:
        h = self._handles.get(name)
        if h is not None:
            h.visible = bool(visible)

    def _put(self, name: str, handle) -> None:
        self._handles[name] = handle

    def update_info(self, frame: int | None = None, loss: float | None = None, timings: dict | None = None,
                    **extra) -> None:
        """The GUI panel: frame number, loss, frames/s (from the calls' spacing), timings {name: seconds}
        and any other key=value pairs."""
        now = time.perf_counter()
        if frame is not None:
            self._g_frame.value = str(frame)
            if self._t_last is not None and now > self._t_last:
                self._g_fps.value = f"{1.0 / (now - self._t_last):.2f}"
            self._t_last = now
        if loss is not None:
            self._g_loss.value = f"{float(loss):.5g}"
        if timings:
            self._g_times.content = "\n".join(f"- {k}: {1000 * float(v):.1f} ms" for k, v in timings.items())
        if extra:
            self._g_extra.content = "\n".join(f"- {k}: {v}" for k, v in extra.items())

    # -- scene ----------------------------------------------------------------------------------
    def show_scan(self, points_world: np.ndarray, colors=SCAN_COLOR) -> None:
        """The current scan, [N,3] world frame (subsampled to max_points)."""
        pts = np.asarray(points_world, dtype=np.float32).reshape(-1, 3)
        if len(pts) > self.max_points:
            pts = pts[np.random.default_rng(0).choice(len(pts), self.max_points, replace=False)]
        h = self.server.scene.add_point_cloud("/scan", pts, colors, point_size=self.point_size,
                                              visible=self._g_show_scan.value)
        self._put("/scan", h)

    def show_pose(self, pose: np.ndarray, axes_length: float = 0.5) -> None:
        """The sensor's current pose [4,4] T_world_sensor, as axes."""
        T_w_s = SE3.from_matrix(np.asarray(pose, dtype=np.float64))
        self.server.scene.add_frame("/sensor", axes_length=axes_length, axes_radius=axes_length / 20,
                                    wxyz=_wxyz(T_w_s.rotation().matrix), position=T_w_s.translation())

    def add_trajectory_pose(self, pose: np.ndarray) -> None:
        """Append one pose to the trajectory and redraw it."""
        self._traj.append(np.asarray(pose, dtype=np.float64)[:3, 3].copy())
        self.show_trajectory(np.asarray(self._traj))

    def show_trajectory(self, poses, name: str = "/trajectory", color=TRAJ_COLOR, thickness: float = 3.0) -> None:
        """A trajectory: poses [N,4,4] or positions [N,3], drawn as a polyline."""
        P = np.asarray(poses, dtype=np.float64)
        pos = P[:, :3, 3] if P.ndim == 3 else P.reshape(-1, 3)
        if name == "/trajectory":
            self._traj = [p.copy() for p in pos]
        if len(pos) < 2:
            return
        seg = np.stack([pos[:-1], pos[1:]], axis=1).astype(np.float32)
        h = self.server.scene.add_line_segments(name, seg, color, thickness=thickness, thickness_units="screen",
                                                visible=self._g_show_traj.value if name == "/trajectory" else True)
        self._put(name, h)

    def show_mesh(self, mesh=None, vertices=None, faces=None, vertex_colors=None, color=MESH_COLOR) -> None:
        """A mesh: a trimesh.Trimesh (its vertex colours are used when it has them), or vertices [V,3] +
        faces [F,3] (+ vertex_colors [V,3] uint8)."""
        if mesh is not None:
            vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
            if vertex_colors is None:
                vc = getattr(getattr(mesh, "visual", None), "vertex_colors", None)
                if vc is not None and getattr(mesh.visual, "kind", None) == "vertex":
                    vertex_colors = np.asarray(vc)[:, :3]
        if vertices is None or faces is None or len(faces) == 0:
            return
        visible = self._g_show_mesh.value
        if vertex_colors is not None:
            import trimesh

            tm = trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=False,
                                 vertex_colors=np.asarray(vertex_colors, dtype=np.uint8))
            h = self.server.scene.add_mesh_trimesh("/mesh", tm, visible=visible)
        else:
            h = self.server.scene.add_mesh_simple("/mesh", np.asarray(vertices, dtype=np.float32),
                                                  np.asarray(faces, dtype=np.uint32), color=color,
                                                  side="double", visible=visible)
        self._put("/mesh", h)

    def show_loops(self, pairs) -> None:
        """Loop closures: pairs of positions [L,2,3] (or of poses [L,2,4,4]), drawn as green segments."""
        P = np.asarray(pairs, dtype=np.float64)
        if P.size == 0:
            return
        if P.ndim == 4:
            P = P[:, :, :3, 3]
        self.server.scene.add_line_segments("/loops", P.reshape(-1, 2, 3).astype(np.float32), LOOP_COLOR,
                                            thickness=4.0, thickness_units="screen")

    def look_at(self, target, distance: float) -> None:
        """Initial camera of new clients: looking at `target` [3] from `distance` m, above and to the side."""
        t = np.asarray(target, dtype=np.float64)
        d = float(distance)
        ic = self.server.initial_camera
        ic.look_at = tuple(t)
        ic.position = tuple(t + np.array([-0.6 * d, -0.6 * d, 0.55 * d]))
        ic.up = (0.0, 0.0, 1.0)

    def close(self) -> None:
        try:
            self.server.stop()
        except Exception as e:  # pragma: no cover - shutting down anyway
            log.debug("viewer stop: %s", e)


class MeshWorker:
    """Re-extract a mesh in a background thread: `request()` starts `mesh_fn()` and hands its result to
    `on_mesh`, unless one is still running or the duty-cycle budget says wait.

    max_share bounds the share of wall time spent meshing: after an extraction of t seconds the next one
    starts no earlier than t * (1 - max_share) / max_share seconds later (0.05: at most ~5 % of the time;
    <= 0 or >= 1: no limit). On a laptop CPU the extraction competes with the mapping for the cores
    (marching cubes and the decoder's XLA threads), so this, not the thread, keeps the mapping fast.
    The thread itself runs at the lowest CPU priority (Linux: per-thread nice 19). `join()` waits for it."""

    def __init__(self, mesh_fn, on_mesh, nice: int = 19, max_share: float = 0.05, snapshot_fn=None):
        self.mesh_fn, self.on_mesh, self.nice, self.max_share = mesh_fn, on_mesh, nice, float(max_share)
        self.snapshot_fn = snapshot_fn
        self._thread: threading.Thread | None = None
        self._next_ok = 0.0
        self.runs, self.skipped, self.throttled, self.seconds = 0, 0, 0, 0.0

    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def request(self) -> bool:
        """Start an extraction; False (skipped) when one is still running or the budget says wait.
        With a snapshot_fn, it is called here, in the caller's thread, and mesh_fn gets its result: a
        consistent copy of the map state (e.g. `(mapper.static, mapper.state)`) taken between frames."""
        if self.busy():
            self.skipped += 1
            return False
        if time.perf_counter() < self._next_ok:
            self.throttled += 1
            return False
        args = (self.snapshot_fn(),) if self.snapshot_fn is not None else ()
        self._thread = threading.Thread(target=self._run, args=args, name="jaxmap-viewer-mesh", daemon=True)
        self._thread.start()
        return True

    def _run(self, *args) -> None:
        if self.nice and hasattr(os, "setpriority") and hasattr(threading, "get_native_id"):
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.nice)
            except OSError:  # pragma: no cover - not allowed here: run at the normal priority
                pass
        t0 = time.perf_counter()
        try:
            mesh = self.mesh_fn(*args)
            self.on_mesh(mesh)
        except Exception as e:  # the view must never stop the mapping
            log.warning("viewer: mesh extraction failed: %s", e)
        dt = time.perf_counter() - t0
        if 0 < self.max_share < 1:
            self._next_ok = time.perf_counter() + dt * (1 - self.max_share) / self.max_share
        self.seconds += dt
        self.runs += 1

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)


class ViewerHooks:
    """Callbacks of a mapping loop that drive a `Viewer` (see `attach_viewer`)."""

    def __init__(self, viewer: Viewer, mesh_every: int = 10, mesh_fn=None, mesh_max_share: float = 0.05,
                 snapshot_fn=None):
        self.viewer = viewer
        self.mesh_every = int(mesh_every)
        self.worker = (MeshWorker(mesh_fn, self.on_mesh, max_share=mesh_max_share, snapshot_fn=snapshot_fn)
                       if mesh_fn is not None and self.mesh_every > 0 else None)
        self.frames = 0
        self._centred = False

    def on_frame(self, frame_index: int, points_world: np.ndarray, pose: np.ndarray, info: dict | None = None) -> None:
        """After a frame is mapped: its points [N,3] world frame, its pose [4,4] T_world_sensor, and `info`
        (optional keys: loss, and any `*_s` timings). Starts a background mesh every mesh_every frames."""
        v = self.viewer
        info = info or {}
        v.show_scan(points_world)
        v.show_pose(pose)
        v.add_trajectory_pose(pose)
        if not self._centred:
            p = np.asarray(pose, dtype=np.float64)[:3, 3]
            ext = np.ptp(np.asarray(points_world, dtype=np.float64).reshape(-1, 3), axis=0) if len(points_world) else [1]
            v.look_at(p, 1.5 * max(float(np.max(ext)), 1.0))   # the first scan in view, from above
            self._centred = True
        timings = {k: float(x) for k, x in info.items() if k.endswith("_s") and np.isscalar(x)}
        v.update_info(frame=frame_index, loss=info.get("loss"), timings=timings)
        self.frames += 1
        if self.worker is not None and self.frames % self.mesh_every == 0:
            self.worker.request()

    def on_mesh(self, mesh) -> None:
        """A new mesh (trimesh.Trimesh) to show."""
        self.viewer.show_mesh(mesh)

    def on_trajectory(self, poses) -> None:
        """The whole trajectory changed (e.g. after a pose-graph optimisation): poses [N,4,4]."""
        self.viewer.show_trajectory(poses)

    def on_loop(self, pose_a: np.ndarray, pose_b: np.ndarray) -> None:
        """A loop closure between two poses: drawn with the earlier ones."""
        self._loops = getattr(self, "_loops", []) + [(np.asarray(pose_a)[:3, 3], np.asarray(pose_b)[:3, 3])]
        self.viewer.show_loops(np.asarray(self._loops))

    def finish(self, mesh=None) -> None:
        """End of the run: wait for a running background mesh, then show `mesh` (the final one) if given."""
        if self.worker is not None:
            self.worker.join()
        if mesh is not None:
            self.on_mesh(mesh)

    def close(self) -> None:
        if self.worker is not None:
            self.worker.join()
        self.viewer.close()


def attach_viewer(viewer: Viewer | None = None, port: int = 8080, mesh_every: int = 10, mesh_fn=None,
                  mesh_max_share: float = 0.05, snapshot_fn=None, **viewer_kw) -> ViewerHooks:
    """Callbacks that drive a live viewer from any mapping loop (N3, imt, slam).

    viewer: an existing Viewer (default: start one on `port`, 0.0.0.0). mesh_fn: a no-argument callable
    returning the current mesh (trimesh.Trimesh), run in a background thread every `mesh_every` frames
    (0 = never), and then only while meshing takes at most `mesh_max_share` of the wall time (see
    MeshWorker). snapshot_fn: called in the loop's thread when a mesh starts; mesh_fn then takes its
    result (for a mapper whose state is several attributes, so the thread sees one frame's state).
    Returns a ViewerHooks with on_frame(frame_index, points_world, pose, info),
    on_mesh(mesh), on_trajectory(poses), on_loop(pose_a, pose_b), finish(mesh) and close().
    """
    return ViewerHooks(viewer or Viewer(port=port, **viewer_kw), mesh_every=mesh_every, mesh_fn=mesh_fn,
                       mesh_max_share=mesh_max_share, snapshot_fn=snapshot_fn)


def view_options(args) -> dict | None:
    """{"port", "mesh_every"} of the `--view --view-port --view-mesh-every` flags, None without --view."""
    if not getattr(args, "view", False):
        return None
    return {"port": args.view_port, "mesh_every": args.view_mesh_every}


# ------------------------------------------------------------------------------------------------
# jaxmap view RUN_DIR
# ------------------------------------------------------------------------------------------------


def _run_data_path(run_dir: str) -> str | None:
    cfg = os.path.join(run_dir, "config.yaml")
    if not os.path.isfile(cfg):
        return None
    import yaml

    with open(cfg) as f:
        data = yaml.safe_load(f) or {}
    path = (data.get("data") or {}).get("path")
    return str(path) if path else None


def mesh_errors(vertices: np.ndarray, gt_points_path: str) -> np.ndarray:
    """Distance (m) of each vertex [V,3] to the nearest ground-truth point of a gt_points.ply."""
    from scipy.spatial import cKDTree

    from jaxmap.io import read_points_ply

    gt = read_points_ply(gt_points_path)
    gt = gt[0] if isinstance(gt, tuple) else gt
    d, _ = cKDTree(np.asarray(gt, dtype=np.float64)[:, :3]).query(np.asarray(vertices, dtype=np.float64), k=1)
    return d


def open_run(run_dir: str, port: int = 8080, viewer: Viewer | None = None, error_max_m: float | None = None,
             quiet: bool = False) -> tuple[Viewer, dict]:
    """Show a finished run in a Viewer: mesh.ply (coloured by its distance to the data's gt_points.ply when
    there is one), trajectory_kitti.txt (else the sequence's poses). Returns (viewer, facts shown)."""
    import trimesh

    run_dir = os.fspath(run_dir)
    if not os.path.isdir(run_dir):
        raise DataError(f"{run_dir}: run directory not found")
    mesh_path = os.path.join(run_dir, "mesh.ply")
    if not os.path.isfile(mesh_path):
        raise DataError(f"{run_dir}: no mesh.ply (is the run finished? `jaxmap mesh {run_dir}` re-extracts one)")
    mesh = trimesh.load(mesh_path, process=False, force="mesh")
    v = viewer or Viewer(port=port, quiet=quiet)
    facts: dict = {"mesh": mesh_path, "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces))}
    data = _run_data_path(run_dir)
    gt = os.path.join(data, "gt_points.ply") if data else None
    colors = None
    if gt and os.path.isfile(gt) and len(mesh.vertices):
        d = mesh_errors(mesh.vertices, gt)
        thr = error_max_m
        if thr is None:
            thr = 0.1
            mj = os.path.join(run_dir, "metrics.json")
            if os.path.isfile(mj):
                import json

                with open(mj) as f:
                    m = json.load(f)
                m = m.get("metrics", m)
                thr = float(m.get("threshold_m", thr))
        colors = error_colors(d, thr)
        facts.update({"gt": gt, "error_max_m": thr, "error_mean_m": float(d.mean()),
                      "error_median_m": float(np.median(d))})
        v.update_info(**{"error (blue 0 -> red)": f">= {100 * thr:.1f} cm", "mean error": f"{100 * d.mean():.2f} cm"})
    v.show_mesh(mesh, vertex_colors=colors)
    poses = None
    tk = os.path.join(run_dir, "trajectory_kitti.txt")
    if os.path.isfile(tk):
        from jaxmap.io.kitti import read_poses

        poses = read_poses(tk)
        facts["trajectory"] = tk
    if poses is not None and len(poses):
        v.show_trajectory(poses)
        facts["poses"] = int(len(poses))
    if len(mesh.vertices):
        lo, hi = mesh.bounds
        v.look_at((lo + hi) / 2, float(np.linalg.norm(hi - lo)) * 0.8)
    return v, facts


def view_run(run_dir: str, port: int = 8080, wait: bool = True) -> int:
    """`jaxmap view RUN_DIR`: serve the run until Ctrl-C (wait=False: show it and return)."""
    v, facts = open_run(run_dir, port=port)
    print(" ".join(f"{k}={val}" for k, val in facts.items()), file=sys.stderr, flush=True)
    if not wait:
        v.close()
        return 0
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        v.close()
    return 0
