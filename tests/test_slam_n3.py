"""`jaxmap slam` with `map_kind: n3`: the front end adopts refined (tracked) poses, and the online N3 map
follows a loop correction (jaxmap.slam.n3slam)."""
from __future__ import annotations

import numpy as np
import pytest

from jaxmap.config import FrontEndConfig, load_config
from jaxmap.config.slam import SlamConfig
from jaxmap.errors import ConfigError
from jaxmap.io import open_sequence
from jaxmap.slam.frontend import FrontEnd


def _shift(pose: np.ndarray, dx: float) -> np.ndarray:
    out = np.array(pose, np.float64)
    out[0, 3] += dx
    return out


def test_front_end_continues_from_a_refined_pose(small_city):
    """A refinement of frame 1 is the frame's pose, and frame 2's odometry starts from it: with frame 1
    moved 0.5 m by `refine`, frame 2 ends up 0.5 m from where the plain front end puts it (a front end
    that ignored the refinement would put it within centimetres of the plain one)."""
    seq = open_sequence(str(small_city))
    plain = FrontEnd(FrontEndConfig.lidar(), initial_pose=seq.poses[0])
    fed = FrontEnd(FrontEndConfig.lidar(), initial_pose=seq.poses[0])
    poses = {}
    for i in range(3):
        pts = seq.frame(i).points
        a = plain.add_frame(pts)
        b = fed.add_frame(pts, refine=(lambda g: _shift(g, 0.5)) if i == 1 else None)
        poses[i] = (a, b)
    a1, b1 = poses[1]
    assert b1.refined and not a1.refined
    np.testing.assert_allclose(b1.pose[:3, 3] - a1.pose[:3, 3], [0.5, 0.0, 0.0], atol=1e-9)
    # the odometry's own motion is reported unrefined (the "odometry alone" trajectory)
    np.testing.assert_allclose(b1.odometry_rel, a1.odometry_rel, atol=1e-9)
    a2, b2 = poses[2]
    d = b2.pose[:3, 3] - a2.pose[:3, 3]
    assert abs(d[0] - 0.5) < 0.1 and np.linalg.norm(d[1:]) < 0.1, d
    # keyframe poses (the pose graph's nodes) carry it too
    np.testing.assert_allclose(fed.keyframe_poses()[1], b1.pose, atol=1e-9)


def test_map_kind_n3_needs_an_n3_config():
    with pytest.raises(ConfigError, match="n3_config"):
        load_config(None, ["map_kind=n3"], schema=SlamConfig)
    with pytest.raises(ConfigError, match="n3_loop"):
        load_config(None, ["map_kind=n3", "n3_config=configs/city.yaml", "n3_loop=later"], schema=SlamConfig)
