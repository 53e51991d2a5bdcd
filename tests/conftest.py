"""Session-wide fixtures: the --small synthetic scenes, generated once per test session (per xdist
worker). Treat the returned directories as read-only; copy them before modifying anything.

Each xdist worker compiles into its own folder of the user's per-CPU XLA cache (`jaxmap.compile_cache`):
warm, the cache saves half the suite's time, but two processes that write and read one entry at the
same time can abort the reader inside XLA (seen in CI: `Fatal Python error: Aborted` in
`compilation_cache.get_executable_and_time`), and JAX's cache does not lock unless it evicts."""
import os

import pytest

from jaxmap import compile_cache  # noqa: E402  (jax itself is not imported yet: the environment still decides)

_WORKER_CACHE = os.path.join(compile_cache.DEFAULT_DIR, "tests-" + os.environ.get("PYTEST_XDIST_WORKER", "main"))
os.environ["JAXMAP_CACHE_DIR"] = _WORKER_CACHE        # for the CLI subprocesses the tests start
os.environ["JAX_COMPILATION_CACHE_DIR"] = _WORKER_CACHE  # for this process


@pytest.fixture(scope="session")
def small_city(tmp_path_factory):
    """Directory (pathlib.Path) of `generate_city(small=True, seed=0)`: KITTI layout, 15 frames of a
    32 x 512 LiDAR on a closed loop, non-identity calib.txt, gt_mesh.ply, gt_points.ply, meta.json."""
    from jaxmap.synth.city import generate_city

    out = tmp_path_factory.mktemp("small_city")
    generate_city(out, seed=0, small=True)
    return out


@pytest.fixture(scope="session")
def small_room(tmp_path_factory):
    """Directory (pathlib.Path) of `generate_room(small=True, seed=0)`: depth layout, 10 frames of
    160 x 120 uint16-mm depth on a closed loop, intrinsics.txt, gt_mesh.ply, gt_points.ply, meta.json."""
    from jaxmap.synth.room import generate_room

    out = tmp_path_factory.mktemp("small_room")
    generate_room(out, seed=0, small=True)
    return out
