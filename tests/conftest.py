"""Session-wide fixtures: the --small synthetic scenes, generated once per test session (per xdist
worker), and the compiled programs dropped after each test module.

An xdist worker runs half the suite in one process, and every XLA:CPU executable keeps its machine
code in memory maps (a frame program about 2,000): kept for the whole session they reached 64,400 of
the 65,530 maps Linux allows a process (vm.max_map_count), and past it XLA aborts the worker inside a
compile or a cache load (`Fatal Python error: Aborted`, seen in CI). Both workers, their CLI
subprocesses and notebook kernels compile into one folder, `tests`, of the XLA cache that
`JAXMAP_CACHE_DIR` names (the user's per-CPU cache of `jaxmap.compile_cache` when unset; empty: no
cache), so a program one worker compiled the other loads (the test work summed over both workers:
1842 s with a folder each, 1690 s shared; the suite's wall time moved within the machine's spread,
890-959 s against 939 s). JAX writes an entry in place, so a worker may read one the other is still
writing: its load fails, JAX warns and compiles the program itself (`jax._src.compiler._cache_read`),
which costs a compile and fails nothing. `make test` points it at an empty folder made for the run,
as a new machine has; warm, the cache saves half the suite's time (`make test TEST_CACHE=warm`)."""
import os

import pytest

from jaxmap import compile_cache  # noqa: E402  (jax itself is not imported yet: the environment still decides)

_CACHE = compile_cache.cache_dir()
if _CACHE:
    # (the workers inherit the folder the controller set: it is not nested again)
    _TEST_CACHE = _CACHE if os.path.basename(_CACHE) == "tests" else os.path.join(_CACHE, "tests")
    os.environ["JAXMAP_CACHE_DIR"] = _TEST_CACHE        # for the CLI subprocesses and notebook kernels
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _TEST_CACHE  # for this process
    # every program, also those that compile in under 0.5 s: each module drops its compiled programs (below),
    # and the next module loads them from the cache instead of compiling them again
    os.environ["JAXMAP_CACHE_MIN_COMPILE_S"] = "0"                 # (jaxmap.compile_cache.enable, the CLI)
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"  # this process: jax is not imported yet
else:  # JAXMAP_CACHE_DIR= : every program compiles, in every process
    os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs():
    """After each module: drop JAX's compiled programs and the mapper's, so their memory maps go."""
    yield
    import gc

    import jax

    from jaxmap.n3 import core

    jax.clear_caches()
    core.forget_compiled()
    gc.collect()
    try:
        with open("/proc/self/maps") as f:
            maps = sum(1 for _ in f)
    except OSError:  # not Linux
        return
    # Held after the cleanup, maps would pile up module by module until XLA aborts: fail here instead.
    assert maps < 20_000, f"{maps} memory maps held after the module's programs were dropped (limit 65,530)"


@pytest.fixture(scope="session")
def small_city(tmp_path_factory):
    """Directory (pathlib.Path) of `generate_city(small=True, seed=0)`: KITTI layout, 15 frames of a
    32 x 512 LiDAR on a closed loop, non-identity calib.txt, gt_mesh.ply, gt_points.ply, meta.json."""
    from jaxmap.synth.city import generate_city

    out = tmp_path_factory.mktemp("small_city")
    generate_city(out, seed=0, small=True)
    return out


@pytest.fixture(scope="session")
def small_noisy_city(tmp_path_factory):
    """The small city (64 frames ~1 m apart, a 62 m loop) with 2 cm range noise: the odometry drifts
    9.6 cm, and the loop closure at frame 56 moves the frames by up to ~5 cm."""
    from jaxmap.synth.city import generate_city

    out = tmp_path_factory.mktemp("city_small_noisy")
    generate_city(out, seed=0, small=True, noise_m=0.02)
    return out


@pytest.fixture(scope="session")
def small_parking_city(tmp_path_factory):
    """Directory (pathlib.Path) of `generate_city(small=True, seed=0, parking=True)`: the small city with
    exactly the two parking cars (one drives off its place, one parks; moving_objects.json)."""
    from jaxmap.synth.city import generate_city

    out = tmp_path_factory.mktemp("small_parking_city")
    generate_city(out, seed=0, small=True, parking=True)
    return out


@pytest.fixture(scope="session")
def small_room(tmp_path_factory):
    """Directory (pathlib.Path) of `generate_room(small=True, seed=0)`: depth layout, 10 frames of
    160 x 120 uint16-mm depth on a closed loop, intrinsics.txt, gt_mesh.ply, gt_points.ply, meta.json."""
    from jaxmap.synth.room import generate_room

    out = tmp_path_factory.mktemp("small_room")
    generate_room(out, seed=0, small=True)
    return out
