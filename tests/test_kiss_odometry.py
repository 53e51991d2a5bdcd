"""KISS-ICP as the odometry of `jaxmap slam` (frontend.odometry.method: kiss_icp)."""
import dataclasses

import numpy as np
import pytest

from jaxmap.config import ConfigError, load_config
from jaxmap.slam.odometry import Odometry, OdometryConfig, make_odometry

kiss_icp = pytest.importorskip("kiss_icp", reason="kiss-icp is not installed (pip install kiss-icp)")


@pytest.fixture(scope="module")
def dense_city(tmp_path_factory):
    """The small city with 2 cm LiDAR noise, 60 frames (1.2 m apart) instead of 15 (4.7 m apart and turns of
    up to 82 deg between scans: too far for KISS-ICP's constant-velocity prediction, see docs/slam.md)."""
    from jaxmap.synth.city import generate_city

    out = tmp_path_factory.mktemp("city_dense")
    generate_city(out, seed=0, small=True, n_frames=60, noise_m=0.02)
    return out


def test_method_key_selects_the_odometry():
    assert isinstance(make_odometry(OdometryConfig()), Odometry)
    from jaxmap.slam.kiss import KissOdometry

    assert isinstance(make_odometry(OdometryConfig.lidar(method="kiss_icp")), KissOdometry)
    with pytest.raises(ConfigError, match="frontend.odometry.method"):
        make_odometry(OdometryConfig(method="loam"))
    from jaxmap.config import SlamConfig

    assert load_config("configs/room_slam.yaml", schema=SlamConfig).frontend.odometry.method == "icp"
    cfg = load_config("configs/city_slam.yaml", ["frontend.odometry.method=kiss_icp"], schema=SlamConfig)
    assert cfg.frontend.odometry.method == "kiss_icp"


def test_kiss_icp_odometry_on_the_noisy_small_city(dense_city):
    from jaxmap.io import open_sequence
    from jaxmap.slam.odometry import odometry_trajectory
    from jaxmap.slam.trajectory import ate

    seq = open_sequence(dense_city, end_frame=7)           # the straight street before the first corner
    cfg = OdometryConfig.lidar(method="kiss_icp")
    poses, _ = odometry_trajectory(seq, cfg)
    err = ate(poses, np.asarray(seq.poses), backend="jaxmap")
    assert err["rmse_m"] < 0.10 and err["rot_rmse_deg"] < 0.5, err


def test_kiss_icp_drives_the_front_end(dense_city):
    """The front end with KISS-ICP: poses, keyframe scans for loop closure, and a correction moves the pose."""
    from jaxmap.io import open_sequence
    from jaxmap.slam.frontend import FrontEnd, FrontEndConfig

    seq = open_sequence(dense_city, end_frame=4)
    lidar = FrontEndConfig.lidar()
    fe = FrontEnd(dataclasses.replace(lidar, odometry=dataclasses.replace(lidar.odometry, method="kiss_icp")),
                  initial_pose=seq.poses[0])
    results = [fe.add_frame(f.points) for f in seq]
    assert all(r.odometry_ok for r in results) and len(fe.kf_scans) == 4
    assert np.abs(fe.trajectory()[:, :3, 3] - np.asarray(seq.poses)[:, :3, 3]).max() < 0.2
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, 0.0]
    before = fe.odometry.pose.copy()
    fe.odometry.correct(T)
    np.testing.assert_allclose(fe.odometry.pose, T @ before)
