"""Session-wide fixtures: the --small synthetic scenes, generated once per test session (per xdist
worker). Treat the returned directories as read-only; copy them before modifying anything.

The suite compiles into the user's per-CPU XLA cache (`jaxmap.compile_cache`), as `jaxmap` does:
warm, it saves half the suite's time; per CPU, it never loads an executable compiled elsewhere."""
import pytest


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
