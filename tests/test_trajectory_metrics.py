"""ATE and RPE: evo (where installed) and jaxmap's own implementation agree on a synthetic trajectory."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxmap.slam.trajectory import ate, have_evo, rpe


def _trajectories(n=60, seed=0):
    """A ground-truth arc with yaw and pitch, and a noisy, drifting, rigidly displaced estimate of it."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 3.0, n)
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, :3, :3] = Rotation.from_rotvec(np.c_[0.05 * np.sin(s), 0.1 * s, s]).as_matrix()
    gt[:, :3, 3] = np.c_[5 * np.cos(s), 5 * np.sin(s), 0.3 * s]
    est = gt.copy()
    est[:, :3, 3] += rng.normal(0, 0.05, (n, 3)) + np.linspace(0, 0.4, n)[:, None]
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(rng.normal(0, 0.01, (n, 3))).as_matrix()
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    T[:3, 3] = [1.0, 2.0, -0.5]
    return T @ est, gt


def test_jaxmap_metrics_exact_cases():
    est, gt = _trajectories()
    assert ate(gt, gt, backend="jaxmap")["rmse_m"] == pytest.approx(0, abs=1e-12)
    shifted = gt.copy()
    shifted[:, :3, 3] += [0.3, 0.0, 0.4]                                # a constant 0.5 m offset
    a = ate(shifted, gt, backend="jaxmap")
    assert a["rmse_m"] == pytest.approx(0.5) and a["max_m"] == pytest.approx(0.5)
    assert ate(shifted, gt, align="se3", backend="jaxmap")["rmse_m"] == pytest.approx(0, abs=1e-9)
    T = np.eye(4)
    T[:3, 3] = [3, 1, 2]
    assert rpe(T @ gt, gt, backend="jaxmap")["rmse_m"] == pytest.approx(0, abs=1e-9)
    with pytest.raises(ValueError):
        rpe(gt[:3], gt[:3], delta=3, backend="jaxmap")


@pytest.mark.skipif(not have_evo(), reason="evo is not installed (pip install 'jaxmap[eval]'): nothing to compare")
@pytest.mark.parametrize("align", ["none", "se3"])
def test_evo_and_jaxmap_ate_agree(align):
    est, gt = _trajectories()
    a, b = ate(est, gt, align=align, backend="evo"), ate(est, gt, align=align, backend="jaxmap")
    assert a.keys() == b.keys()
    for k in a:
        assert a[k] == pytest.approx(b[k], rel=1e-6, abs=1e-9), k
    assert ate(est, gt, align=align) == a                               # "auto" picks evo when installed


@pytest.mark.skipif(not have_evo(), reason="evo is not installed (pip install 'jaxmap[eval]'): nothing to compare")
@pytest.mark.parametrize("delta", [1, 5])
def test_evo_and_jaxmap_rpe_agree(delta):
    est, gt = _trajectories()
    a, b = rpe(est, gt, delta=delta, backend="evo"), rpe(est, gt, delta=delta, backend="jaxmap")
    for k in a:
        assert a[k] == pytest.approx(b[k], rel=1e-6, abs=1e-9), k


def test_auto_falls_back_where_evo_refuses():
    """evo cannot SE(3)-align a straight-line (or one-pose) trajectory; "auto" then uses jaxmap's ATE."""
    n = 10
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 0, 3] = np.arange(n)
    est = gt.copy()
    est[:, 1, 3] += 0.1
    a = ate(est, gt, align="se3")
    assert a["rmse_m"] == pytest.approx(0.0, abs=1e-9)
    assert ate(gt[:1], gt[:1], align="se3")["rmse_m"] == 0.0
