"""Session-wide fixtures: the --small synthetic scenes, generated once per test session (per xdist
worker). Treat the returned directories as read-only; copy them before modifying anything.

The session compiles into its own empty XLA cache, shared by the xdist workers (they inherit the
environment) and removed at the end: a suite that loads executables from the user's cache tests that
cache, not the code, and one written on another CPU aborts the process that loads it."""
import os
import shutil
import tempfile

import pytest

if "JAXMAP_TEST_CACHE_DIR" not in os.environ:  # the controller (or a run without xdist) makes it
    os.environ["JAXMAP_TEST_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxmap-test-xla-")
    _OWN_CACHE = True
else:
    _OWN_CACHE = False
os.environ["JAXMAP_CACHE_DIR"] = os.environ["JAXMAP_TEST_CACHE_DIR"]


def pytest_sessionfinish(session):
    if _OWN_CACHE:
        shutil.rmtree(os.environ["JAXMAP_TEST_CACHE_DIR"], ignore_errors=True)


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
