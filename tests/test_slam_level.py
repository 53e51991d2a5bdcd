"""Levelling by vertical surfaces (`jaxmap.slam.level`): the tilt a scan's facades measure, and the
front end that turns it away frame by frame."""
import numpy as np
import pytest

from jaxmap.config.slam import FrontEndConfig, OdometryConfig
from jaxmap.slam.frontend import FrontEnd
from jaxmap.slam.level import Leveller, level_rotation, rotvec_matrix
from jaxmap.slam.odometry_common import Scan


def tilt_deg(R_est, R_true):
    """Angle (deg) between the two rotations' z axes."""
    return float(np.degrees(np.arccos(np.clip(R_est[:, 2] @ R_true[:, 2], -1, 1))))


def street_normals(rng, facade_dirs=(0.0, 90.0), n=3000, spread_deg=0.1):
    """Sensor-frame unit normals of a street scan: facades facing `facade_dirs` (deg about z, both
    sides), each normal off by `spread_deg` of noise, plus the road (up) and a third of clutter."""
    out = []
    for d in facade_dirs:
        a = np.radians(d)
        for s in (1, -1):
            m = np.tile(s * np.array([np.cos(a), np.sin(a), 0.0]), (n, 1))
            out.append(m + rng.normal(0, np.radians(spread_deg), (n, 3)))
    out.append(np.tile([0.0, 0.0, 1.0], (2 * n, 1)) + rng.normal(0, 0.01, (2 * n, 3)))
    out.append(rng.normal(size=(n, 3)))                      # foliage, edges: any direction
    v = np.concatenate(out)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("tilt_axis", [[1.0, 0, 0], [0.6, 0.8, 0], [0, 1.0, 0]])
def test_the_tilt_of_a_scan_with_facades_both_ways_is_measured_to_a_millidegree(tilt_axis):
    """A scan seen at a pose tilted by 0.1 deg (about any horizontal axis): the levelling rotation puts
    its z axis back within 5 mdeg (20x below the tilt; clutter, the road and 0.1 deg normal noise in:
    ~3 mdeg of spread over its 12,000 facade normals)."""
    rng = np.random.default_rng(0)
    normals = street_normals(rng)
    R_true = rotvec_matrix(np.radians([0, 0, 37.0]))          # any heading
    tilt = rotvec_matrix(np.radians(0.1) * np.asarray(tilt_axis))
    R = tilt @ R_true
    lv = level_rotation(normals, R, up=np.array([0, 0, 1.0]))
    assert lv.count > 5000
    assert tilt_deg(R, R_true) == pytest.approx(0.1, abs=1e-6)
    assert tilt_deg(rotvec_matrix(lv.rotvec) @ R, R_true) < 0.005
    assert abs(lv.rotvec[2]) < 1e-12                         # no turn about up


def test_one_facade_direction_fixes_the_tilt_across_it_and_leaves_the_other_axis_alone():
    """Facades facing x only (a straight street): a tilt about y (across them) is measured, a tilt about
    x (along the facades: they stay vertical) is not, and it is left, not invented."""
    rng = np.random.default_rng(1)
    normals = street_normals(rng, facade_dirs=(0.0,))
    up = np.array([0, 0, 1.0])
    about_y = rotvec_matrix(np.radians([0, 0.1, 0]))
    fixed = rotvec_matrix(level_rotation(normals, about_y, up).rotvec) @ about_y
    assert tilt_deg(fixed, np.eye(3)) < 0.005
    about_x = rotvec_matrix(np.radians([0.1, 0, 0]))
    kept = rotvec_matrix(level_rotation(normals, about_x, up).rotvec) @ about_x
    assert tilt_deg(kept, np.eye(3)) == pytest.approx(0.1, abs=0.005)


def test_a_scan_without_vertical_surfaces_measures_nothing():
    rng = np.random.default_rng(2)
    ground = np.tile([0.0, 0.0, 1.0], (5000, 1)) + rng.normal(0, 0.01, (5000, 3))
    lv = level_rotation(ground / np.linalg.norm(ground, axis=1, keepdims=True), np.eye(3), np.array([0, 0, 1.0]))
    assert lv.count == 0 and not lv.rotvec.any()


def test_the_leveller_turns_a_tilted_pose_back_by_its_gain_and_takes_up_from_the_first_frames():
    """The reference up is the facades' (a sensor mounted 0.5 deg off level: not the sensor's z), the
    first pose is never turned, and each later frame loses `gain` of its tilt."""
    rng = np.random.default_rng(3)
    mount = rotvec_matrix(np.radians([0.5, -0.2, 0]))   # the sensor's z is 0.54 deg off the true up
    lev = Leveller(gain=0.5, reference_frames=3, first_pose=np.eye(4))
    for _ in range(3):   # frames 0-2 at the mounting's pose: the reference
        normals = street_normals(rng) @ mount.T          # sensor frame: n_s = R_ws^T n_w, R_ws = mount^T
        first = np.eye(4)
        first[:3, :3] = mount.T
        assert np.array_equal(lev(first, normals, turn=False), first)
    assert np.degrees(np.arccos(lev.up @ mount.T[:, 2] / 1.0)) < 0.55
    assert np.degrees(np.arccos(lev.up[2])) < 0.005              # the facades' up, not the sensor's
    tilted = np.eye(4)
    tilted[:3, :3] = rotvec_matrix(np.radians([0.2, 0, 0])) @ mount.T
    out = lev(tilted, street_normals(rng) @ mount.T)
    assert tilt_deg(out[:3, :3], mount.T) == pytest.approx(0.1, abs=0.003)
    assert np.array_equal(out[:3, 3], tilted[:3, 3])              # turned about its own position


def test_a_tilt_given_to_the_odometry_is_levelled_away_by_the_front_end(small_city):
    """The small city's scans, the odometry's pose tilted by 0.3 deg after frame 1 (as a young map's
    pull would): without levelling the tilt stays (KISS-ICP follows its own local map), with
    `level_gain` 0.3 it is below 0.06 deg within 6 frames."""
    from jaxmap.io import open_sequence

    seq = open_sequence(str(small_city))
    gt = np.asarray(seq.poses, np.float64)
    frames = [seq.frame(i).points for i in range(10)]

    def run(gain):
        fe = FrontEnd(FrontEndConfig.lidar(level_gain=gain, level_reference_frames=2), initial_pose=gt[0])
        out = []
        for i, pts in enumerate(frames):
            r = fe.add_frame(pts)
            if i == 1:   # a tilt about the sensor's position
                T = np.eye(4)
                T[:3, :3] = rotvec_matrix(np.radians([0.3, 0, 0]))
                p = r.pose[:3, 3]
                T[:3, 3] = p - T[:3, :3] @ p
                fe.odometry.correct(T)
            out.append(tilt_deg(r.pose[:3, :3], gt[i][:3, :3]))
        return np.array(out)

    off, on = run(0.0), run(0.3)
    last = slice(-3, None)   # the tilt of the last three frames, mean
    assert np.mean(off[last]) > 0.2 and np.mean(on[last]) < 0.06       # measured: 0.25 and 0.024
    assert max(on[:2]) < 0.06   # the first frames as without levelling (frame 1: the odometry's 0.05 deg)


def test_the_up_is_the_first_frames_facades_when_precise_and_an_average_when_noisy():
    """A precise first frame (0.1 deg normal spread) closes the reference at once, so the next frames'
    poses (whose tilt is the odometry's) never enter it; with 3 deg of spread (a noisy sensor's normals)
    it averages frames until its standard error is below REFERENCE_STDERR_DEG (or ten are in), and
    ends nearer the true up than one frame says on average."""
    from jaxmap.slam.level import REFERENCE_STDERR_DEG, facade_up

    up = np.array([0, 0, 1.0])
    rng = np.random.default_rng(4)
    lev = Leveller(gain=1.0, reference_frames=10, first_pose=np.eye(4))
    lev(np.eye(4), street_normals(rng), turn=False)
    assert not lev.reference_open and lev.frames == 1

    rng = np.random.default_rng(5)
    noisy = [street_normals(rng, n=150, spread_deg=3.0) for _ in range(10)]
    single = [facade_up(n, np.eye(3), up) for n in noisy]
    assert all(stderr > np.radians(REFERENCE_STDERR_DEG) for _, stderr in single)
    lev = Leveller(gain=1.0, reference_frames=10, first_pose=np.eye(4))
    for i, normals in enumerate(noisy):
        lev(np.eye(4), normals, turn=i > 0)
    assert lev.frames == 10
    assert np.arccos(lev.up @ up) < 0.5 * np.mean([np.arccos(u @ up) for u, _ in single])



def test_a_loop_edge_keeps_its_heading_and_position_and_takes_the_levelled_tilt():
    """A loop edge whose registration is 0.15 deg off in tilt (and 0.3 deg in heading): where both
    keyframes' facades are precise, the levelled front end puts keyframe k's up where its facades put
    it, keeps the edge's heading (the loop's to correct) and its translation."""
    P_c, P_k = np.eye(4), np.eye(4)
    P_c[:3, :3] = rotvec_matrix(np.radians([0, 0, 20.0]))
    P_k[:3, :3] = rotvec_matrix(np.radians([0, 0, 110.0]))
    P_k[:3, 3] = [3.0, -1.0, 0.02]
    true_rel = np.linalg.inv(P_c) @ P_k
    bad = true_rel.copy()   # registered: tilted 0.15 deg about k's x axis, heading 0.3 deg off
    bad[:3, :3] = true_rel[:3, :3] @ rotvec_matrix(np.radians([0.15, 0, 0.3]))
    fe = FrontEnd(FrontEndConfig.lidar(level_gain=1.0), initial_pose=np.eye(4))
    fixed = fe._levelled_loop(P_c, P_k, bad)
    R_world = P_c[:3, :3] @ fixed[:3, :3]
    assert tilt_deg(R_world, P_k[:3, :3]) < 1e-6
    assert tilt_deg(P_c[:3, :3] @ bad[:3, :3], P_k[:3, :3]) == pytest.approx(0.15, abs=1e-3)
    heading = lambda R: np.degrees(np.arctan2(R[1, 0], R[0, 0]))  # noqa: E731
    assert heading(R_world) - heading(P_k[:3, :3]) == pytest.approx(0.3, abs=1e-3)
    assert np.array_equal(fixed[:3, 3], bad[:3, 3])


def test_only_a_precisely_levelled_frame_may_set_a_loops_tilt():
    """The first frame (its pose given) and a scan of clean facades are precise; a scan of noisy ones
    (3 deg of normal spread) and one without facades are not."""
    rng = np.random.default_rng(6)
    lev = Leveller(gain=1.0, reference_frames=1, first_pose=np.eye(4))
    lev(np.eye(4), street_normals(rng), turn=False)
    lev(np.eye(4), street_normals(rng), turn=True)
    lev(np.eye(4), street_normals(rng, n=150, spread_deg=3.0), turn=True)
    lev(np.eye(4), np.tile([0.0, 0.0, 1.0], (1000, 1)), turn=True)
    assert [lev.precise(i) for i in range(4)] == [True, True, False, False]
