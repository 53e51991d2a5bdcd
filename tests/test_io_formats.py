"""jaxmap.io readers for data users already have: ROS bags (ROS 1, ROS 2 sqlite3/mcap, bare mcap), TUM RGB-D,
Replica and LAS/LAZ. Each test writes the format with its own library (rosbags, PIL, laspy) from the small
synthetic room and reads it back through `open_sequence`; one test per malformed input checks the DataError."""
import dataclasses
import json
import logging
import os
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxmap.errors import DataError
from jaxmap.io import (detect_kind, describe, open_sequence, pixel_rays, read_depth_png, write_depth_png,
                       write_intrinsics, write_poses)
from jaxmap.io.rosbag import pointcloud2_xyz

EPOCH_NS = 1_700_000_000_000_000_000  # realistic header stamps: float64 seconds must keep them apart
PERIOD_NS = 100_000_000               # 10 Hz
CLOUD = "sensor_msgs/msg/PointCloud2"
ODOM = "nav_msgs/msg/Odometry"
POSE = "geometry_msgs/msg/PoseStamped"


# ------------------------------------------------------------------------------------------------
# the small room, as the depth layout (the reference every converted layout must reproduce)
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """(directory, DepthSequence, [frames]) of a 4-frame 48 x 36 room."""
    from jaxmap.synth.room import generate_room

    out = tmp_path_factory.mktemp("room")
    generate_room(out, seed=0, small=True, n_frames=4, width=48, height=36)
    seq = open_sequence(out)
    return out, seq, list(seq)


def stamps_ns(n):
    return [EPOCH_NS + i * PERIOD_NS + 123 for i in range(n)]


def organised_grid(seq, i):
    """[H,W,3] float32 camera-frame points of frame i, NaN where there is no return (row-major = the order
    of DepthSequence's points)."""
    raw = read_depth_png(seq.depth_paths[i])
    H, W = raw.shape
    z = raw.astype(np.float64).reshape(-1) / seq.depth_scale
    pts = (pixel_rays(W, H, *seq.intrinsics) * z[:, None]).astype(np.float32)
    pts[z <= 0] = np.nan
    return pts.reshape(H, W, 3)


# ------------------------------------------------------------------------------------------------
# ROS messages and bags, written with rosbags
# ------------------------------------------------------------------------------------------------


def typestore(fmt):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)


def header(ts, stamp_ns, frame_id):
    H, T = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    kw = dict(stamp=T(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame_id)
    if "seq" in H.__dataclass_fields__:
        kw["seq"] = 0
    return H(**kw)


def cloud_msg(ts, stamp_ns, pts, layout, frame_id="camera"):
    """A PointCloud2 of pts ([H,W,3] organised or [N,3]) in one of several field layouts."""
    PC, PF = ts.types["sensor_msgs/msg/PointCloud2"], ts.types["sensor_msgs/msg/PointField"]
    grid = pts if pts.ndim == 3 else pts[None]
    h, w = grid.shape[:2]
    flat = grid.reshape(-1, 3)
    big = False
    if layout == "f32_padded":  # x y z float32, intensity at 16, 32-byte points (Velodyne/Ouster-like)
        spec = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7)]
        step, pad = 32, 0
    elif layout == "f64_reordered":  # float64, fields stored y, z, x with a uint16 ring before them
        spec = [("ring", 0, 4), ("y", 2, 8), ("z", 10, 8), ("x", 18, 8)]
        step, pad = 26, 0
    elif layout == "organised":  # float32 after a uint16, 8 bytes of padding at the end of every row
        spec = [("ring", 0, 4), ("x", 4, 7), ("y", 8, 7), ("z", 12, 7)]
        step, pad = 16, 8
    elif layout == "bigendian":
        spec = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
        step, pad, big = 12, 0, True
    else:
        raise AssertionError(layout)
    np_t = {4: "u2", 7: "f4", 8: "f8"}
    e = ">" if big else "<"
    dt = np.dtype({"names": [s[0] for s in spec], "formats": [e + np_t[s[2]] for s in spec],
                   "offsets": [s[1] for s in spec], "itemsize": step})
    rec = np.zeros(h * w, dtype=dt)
    for k, c in enumerate("xyz"):
        rec[c] = flat[:, k]
    rows = rec.tobytes()
    if pad:
        rows = b"".join(rows[r * w * step:(r + 1) * w * step] + b"\xee" * pad for r in range(h))
    return PC(header=header(ts, stamp_ns, frame_id), height=h, width=w,
              fields=[PF(name=n, offset=o, datatype=d, count=1) for n, o, d in spec], is_bigendian=big,
              point_step=step, row_step=w * step + pad, data=np.frombuffer(rows, np.uint8), is_dense=False)


def pose_msg(ts, msgtype, stamp_ns, T, frame_id="map", child="camera"):
    P, Pt, Q = ts.types["geometry_msgs/msg/Pose"], ts.types["geometry_msgs/msg/Point"], \
        ts.types["geometry_msgs/msg/Quaternion"]
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    pose = P(position=Pt(x=T[0, 3], y=T[1, 3], z=T[2, 3]), orientation=Q(x=q[0], y=q[1], z=q[2], w=q[3]))
    if msgtype == POSE:
        return ts.types[POSE](header=header(ts, stamp_ns, frame_id), pose=pose)
    V3, Tw = ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Twist"]
    return ts.types[ODOM](header=header(ts, stamp_ns, frame_id), child_frame_id=child,
                          pose=ts.types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                          twist=ts.types["geometry_msgs/msg/TwistWithCovariance"](
                              twist=Tw(linear=V3(x=0, y=0, z=0), angular=V3(x=0, y=0, z=0)),
                              covariance=np.zeros(36)))


def write_bag(path, fmt, entries):
    """Write entries [(topic, msgtype, bag_time_ns, factory(typestore) -> msg)] as a `fmt` bag:
    "ros1" (path.bag), "ros2_db3" / "ros2_mcap" (directory), "mcap" (the bare .mcap file of a ros2 bag).
    Returns the path to open."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    ts = typestore(fmt)
    if fmt == "ros1":
        path = path.with_suffix(".bag")
        w = Writer1(path)
    else:
        plugin = StoragePlugin.SQLITE3 if fmt == "ros2_db3" else StoragePlugin.MCAP
        w = Writer2(path, version=9, storage_plugin=plugin)
    conns = {}
    with w:
        for topic, msgtype, t, make in sorted(entries, key=lambda e: e[2]):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            msg = make(ts)
            raw = ts.serialize_ros1(msg, msgtype) if fmt == "ros1" else ts.serialize_cdr(msg, msgtype)
            w.write(conns[topic], t, raw)
    if fmt == "mcap":
        (f,) = path.glob("*.mcap")
        return f
    return path


LAYOUTS = ("f32_padded", "organised", "f64_reordered", "bigendian")


def room_bag_entries(room_seq, frames, pose_type=ODOM, cloud_topic="/camera/points", pose_topic="/odom",
                     nan_rows=True):
    """The room's frames as PointCloud2 (one layout per frame, received 30 ms after their stamp) plus one
    pose message per frame, stamped like the cloud."""
    entries = []
    for i, (fr, s) in enumerate(zip(frames, stamps_ns(len(frames)))):
        layout = LAYOUTS[i % len(LAYOUTS)]
        if layout == "organised":
            pts = organised_grid(room_seq, i)
        else:
            pts = fr.points.copy()
            if nan_rows:  # NaN points anywhere in a flat cloud are dropped too
                pts = np.insert(pts, [0, 5, len(pts)], np.float32(np.nan), axis=0)
        entries.append((cloud_topic, CLOUD, s + 30_000_000,
                        lambda ts, s=s, pts=pts, layout=layout: cloud_msg(ts, s, pts, layout)))
        if pose_type:
            entries.append((pose_topic, pose_type, s + 10_000_000,
                            lambda ts, s=s, T=fr.pose: pose_msg(ts, pose_type, s, T)))
    return entries


# ------------------------------------------------------------------------------------------------
# ROS bags
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["ros1", "ros2_db3", "ros2_mcap", "mcap"])
def test_rosbag_roundtrip_room(tmp_path, room, fmt):
    _, room_seq, frames = room
    path = write_bag(tmp_path / "room", fmt, room_bag_entries(room_seq, frames))
    assert detect_kind(path) == "rosbag"
    seq = open_sequence(path)
    assert seq.kind == "rosbag" and len(seq) == len(frames) and seq.topic == "/camera/points"
    assert seq.pose_source == "/odom" and seq.n_skipped == 0
    np.testing.assert_array_equal(seq.stamps_ns, stamps_ns(len(frames)))  # header stamps, not bag time
    np.testing.assert_array_equal(seq.timestamps, np.asarray(stamps_ns(len(frames)), np.float64) * 1e-9)
    for i, (fr, ref) in enumerate(zip(seq, frames)):
        assert fr.index == i and fr.timestamp == seq.timestamps[i]
        assert fr.points.dtype == np.float32 and fr.points.shape == ref.points.shape, LAYOUTS[i % 4]
        np.testing.assert_array_equal(fr.points, ref.points, err_msg=LAYOUTS[i % 4])  # f32 and f64 exact
        np.testing.assert_allclose(fr.pose, ref.pose, rtol=0, atol=1e-12)
    assert describe(path) == [("/camera/points", CLOUD, len(frames)), ("/odom", ODOM, len(frames))]
    # selection, and the reader stays open across frames until close()
    sub = open_sequence(path, kind="rosbag", begin_frame=1, every_frame=2)
    assert [f.index for f in sub] == [1, 3]
    np.testing.assert_array_equal(sub.frame(1).points, frames[3].points)
    sub.close()
    np.testing.assert_array_equal(sub.frame(0).points, frames[1].points)  # reopened


def test_rosbag_pose_interpolation_nearest_and_skip(tmp_path, caplog):
    """PoseStamped at 10 Hz; clouds between two poses get the slerp/lerp, clouds just outside the stream the
    nearest pose, clouds farther than the tolerance are skipped with a count."""
    t0 = EPOCH_NS
    Ta, Tb = np.eye(4), np.eye(4)
    Tb[:3, :3] = Rotation.from_rotvec([0, 0, 0.4]).as_matrix()
    Tb[:3, 3] = [1.0, -2.0, 0.5]
    pts = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    cloud_at = {"mid": t0 + 25_000_000, "before": t0 - 60_000_000, "far": t0 + 2_000_000_000}
    entries = [("/pose", POSE, t0, lambda ts: pose_msg(ts, POSE, t0, Ta)),
               ("/pose", POSE, t0 + 100_000_000, lambda ts: pose_msg(ts, POSE, t0 + 100_000_000, Tb))]
    entries += [("/lidar", CLOUD, s, lambda ts, s=s: cloud_msg(ts, s, pts, "f32_padded")) for s in cloud_at.values()]
    path = write_bag(tmp_path / "b", "ros2_mcap", entries)
    with caplog.at_level(logging.WARNING, logger="jaxmap"):
        seq = open_sequence(path)
    assert len(seq) == 2 and seq.n_skipped == 1
    assert "skipped 1 of 3 clouds" in caplog.text and str(path) in caplog.text
    np.testing.assert_array_equal(seq.stamps_ns, [cloud_at["before"], cloud_at["mid"]])
    np.testing.assert_array_equal(seq.frame(0).pose, Ta)  # nearest: only one neighbour within 0.1 s
    expect = np.eye(4)
    expect[:3, :3] = Rotation.from_rotvec([0, 0, 0.1]).as_matrix()  # a = 0.25
    expect[:3, 3] = 0.25 * Tb[:3, 3]
    np.testing.assert_allclose(seq.frame(1).pose, expect, atol=1e-9)
    np.testing.assert_array_equal(seq.frame(1).points, pts)
    # a tighter tolerance: the mid cloud is 25 ms from a pose, the other one 60 ms
    seq = open_sequence(path, time_tolerance=0.03)
    assert len(seq) == 1 and seq.n_skipped == 2
    np.testing.assert_array_equal(seq.frame(0).pose, Ta)


def test_rosbag_poses_from_tum_file(tmp_path, room):
    """A bag without pose topics: poses from `<stem>.tum` beside it, or from pose_file=."""
    from jaxmap.slam.trajectory import write_tum

    _, room_seq, frames = room
    path = write_bag(tmp_path / "scan", "ros1", room_bag_entries(room_seq, frames, pose_type=None))
    poses = np.stack([f.pose for f in frames])
    write_tum(tmp_path / "scan.tum", np.asarray(stamps_ns(len(frames))) * 1e-9, poses)
    seq = open_sequence(path)
    assert seq.pose_source == str(tmp_path / "scan.tum") and len(seq) == len(frames)
    np.testing.assert_allclose(seq.poses, poses, atol=1e-9)
    os.rename(tmp_path / "scan.tum", tmp_path / "gt.txt")
    seq = open_sequence(path, pose_file=tmp_path / "gt.txt")
    np.testing.assert_allclose(seq.poses, poses, atol=1e-9)
    np.testing.assert_array_equal(seq.frame(2).points, frames[2].points)


def test_rosbag_topic_choice(tmp_path, room):
    _, room_seq, frames = room
    entries = room_bag_entries(room_seq, frames[:2], cloud_topic="/a/points")
    entries += room_bag_entries(room_seq, frames[:2], cloud_topic="/b/points", pose_type=None)
    path = write_bag(tmp_path / "two", "ros2_db3", entries)
    with pytest.raises(DataError) as e:
        open_sequence(path)
    msg = str(e.value)
    assert str(path) in msg and "/a/points" in msg and "/b/points" in msg and "data.topic" in msg
    assert "\n" not in msg
    seq = open_sequence(path, topic="/b/points")
    assert seq.topic == "/b/points" and len(seq) == 2
    np.testing.assert_array_equal(seq.frame(1).points, frames[1].points)


def test_rosbag_wrong_topic(tmp_path, room):
    _, room_seq, frames = room
    path = write_bag(tmp_path / "b", "ros1", room_bag_entries(room_seq, frames[:1]))
    with pytest.raises(DataError, match=r"b\.bag: no topic '/nope'.*/camera/points"):
        open_sequence(path, topic="/nope")
    with pytest.raises(DataError, match=r"b\.bag: topic /odom is nav_msgs/Odometry, not sensor_msgs/PointCloud2"):
        open_sequence(path, topic="/odom")
    with pytest.raises(DataError, match=r"b\.bag: pose topic '/camera/points' is sensor_msgs/PointCloud2"):
        open_sequence(path, pose_topic="/camera/points")


def test_rosbag_no_pose_source(tmp_path, room):
    _, room_seq, frames = room
    path = write_bag(tmp_path / "b", "ros1", room_bag_entries(room_seq, frames[:1], pose_type=None))
    with pytest.raises(DataError) as e:
        open_sequence(path)
    msg = str(e.value)
    assert msg.startswith(str(path)) and "no pose source" in msg and str(tmp_path / "b.tum") in msg


def test_rosbag_pose_of_another_frame_warns(tmp_path, caplog):
    pts = np.ones((3, 3), np.float32)
    s = EPOCH_NS
    path = write_bag(tmp_path / "b", "ros1", [
        ("/velodyne_points", CLOUD, s, lambda ts: cloud_msg(ts, s, pts, "bigendian", frame_id="velodyne")),
        ("/odom", ODOM, s, lambda ts: pose_msg(ts, ODOM, s, np.eye(4), child="base_link"))])
    with caplog.at_level(logging.WARNING, logger="jaxmap"):
        seq = open_sequence(path)
    assert "'base_link'" in caplog.text and "'velodyne'" in caplog.text and "no TF lookup" in caplog.text
    np.testing.assert_array_equal(seq.frame(0).points, pts)


def test_rosbag_several_pose_topics(tmp_path, room):
    _, room_seq, frames = room
    entries = room_bag_entries(room_seq, frames[:2], pose_topic="/odom")
    entries += [e for e in room_bag_entries(room_seq, frames[:2], pose_topic="/gt", pose_type=POSE)
                if e[0] == "/gt"]
    path = write_bag(tmp_path / "b", "ros2_mcap", entries)
    with pytest.raises(DataError, match=r"/b: 2 pose topics: /gt .*/odom .*pose_topic"):
        open_sequence(path)
    np.testing.assert_allclose(open_sequence(path, pose_topic="/gt").poses,
                               [f.pose for f in frames[:2]], atol=1e-12)


def test_rosbag_no_pose_within_tolerance(tmp_path, room):
    _, room_seq, frames = room
    entries = [e if e[1] != ODOM else (e[0], e[1], e[2] + 10**9, lambda ts, T=frames[0].pose, s=e[2] + 10**9:
                                       pose_msg(ts, ODOM, s, T))
               for e in room_bag_entries(room_seq, frames[:2])]
    path = write_bag(tmp_path / "b", "ros1", entries)
    with pytest.raises(DataError, match=r"b\.bag: none of the 2 clouds on /camera/points has a pose from /odom "
                                        r"within 0\.1 s"):
        open_sequence(path)


def test_rosbag_unreadable_or_missing(tmp_path):
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 50)
    with pytest.raises(DataError, match=r"junk\.bag: not a readable ROS bag"):
        open_sequence(tmp_path / "junk.bag")
    (tmp_path / "junk.mcap").write_bytes(b"not mcap")
    with pytest.raises(DataError, match=r"junk\.mcap: not a readable ROS bag"):
        describe(tmp_path / "junk.mcap")
    with pytest.raises(DataError, match=r"gone\.bag: ROS bag not found"):
        open_sequence(tmp_path / "gone.bag", kind="rosbag")
    (tmp_path / "dir").mkdir()
    with pytest.raises(DataError, match=r"dir: not a ROS 2 bag directory \(no metadata\.yaml\)"):
        open_sequence(tmp_path / "dir", kind="rosbag")


def test_pointcloud2_malformed():
    ts = typestore("ros2_mcap")
    pts = np.arange(12, dtype=np.float32).reshape(4, 3)
    msg = cloud_msg(ts, 1, pts, "f32_padded")
    np.testing.assert_array_equal(pointcloud2_xyz(msg, "bag.mcap topic /p"), pts)
    short = dataclasses.replace(msg, data=msg.data[:-40])
    with pytest.raises(DataError, match=r"bag\.mcap topic /p: PointCloud2 has 88 data bytes.*needs 128.*truncated"):
        pointcloud2_xyz(short, "bag.mcap topic /p")
    noz = dataclasses.replace(msg, fields=[f for f in msg.fields if f.name != "z"])
    with pytest.raises(DataError, match=r"bag\.mcap topic /p: PointCloud2 has no field z \(fields: x, y, "
                                        r"intensity\)"):
        pointcloud2_xyz(noz, "bag.mcap topic /p")


# ------------------------------------------------------------------------------------------------
# TUM RGB-D
# ------------------------------------------------------------------------------------------------


def room_to_tum(room_dir, room_seq, frames, out, intrinsics=True, gt_shift_s=0.004):
    """The room in the TUM layout: depth at 5000 per metre, depth.txt, groundtruth.txt at 100 Hz-like
    offsets (the true pose gt_shift_s after each image, a decoy 0.03 s later), plus one depth image with no
    ground truth near it. Returns the depth timestamps."""
    os.makedirs(out / "depth", exist_ok=True)
    t = np.array([float(f"{v:.6f}") for v in 1305031102.175304 + 0.1 * np.arange(len(frames) + 1)])
    lines, gt = ["# depth maps", "# file: 'x.bag'", "# timestamp filename"], ["# ground truth", "# tx ..."]
    for i in range(len(frames) + 1):
        raw = read_depth_png(room_seq.depth_paths[min(i, len(frames) - 1)])
        write_depth_png(out / "depth" / f"{t[i]:.6f}.png", (raw.astype(np.uint32) * 5).astype(np.uint16))
        lines.append(f"{t[i]:.6f} depth/{t[i]:.6f}.png")
    for i, fr in enumerate(frames):
        for dt, T in ((gt_shift_s, fr.pose), (0.03, np.eye(4))):
            q = Rotation.from_matrix(T[:3, :3]).as_quat()
            gt.append(" ".join(repr(float(v)) for v in (t[i] + dt, *T[:3, 3], *q)))
    (out / "depth.txt").write_text("\n".join(lines) + "\n")
    (out / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    (out / "rgb.txt").write_text("# no colour needed\n")
    if intrinsics:
        write_intrinsics(out / "intrinsics.txt", *room_seq.intrinsics)
    return t[:len(frames)]


def test_tum_roundtrip_room(tmp_path, room, caplog):
    room_dir, room_seq, frames = room
    out = tmp_path / "rgbd_dataset_freiburg1_room"
    t = room_to_tum(room_dir, room_seq, frames, out)
    # the extra (last) image is 0.07 s and 0.096 s from the nearest ground-truth lines: skipped
    assert detect_kind(out) == "tum"
    with caplog.at_level(logging.WARNING, logger="jaxmap"):
        seq = open_sequence(out)
    assert seq.kind == "tum" and len(seq) == len(frames) and seq.n_skipped == 1
    assert "skipped 1 of 5 depth images" in caplog.text
    assert seq.intrinsics_source == str(out / "intrinsics.txt") and seq.depth_scale == 5000.0  # overrides fr1
    np.testing.assert_array_equal(seq.timestamps, t)
    np.testing.assert_allclose(seq.pose_dt, 0.004, atol=1e-6)
    for fr, ref in zip(seq, frames):
        assert fr.timestamp is not None
        np.testing.assert_allclose(fr.points, ref.points, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(fr.pose, ref.pose, atol=1e-12)
    assert [f.index for f in open_sequence(out, end_frame=3, every_frame=2)] == [0, 2]


def test_tum_freiburg_intrinsics_from_directory_name(tmp_path, room):
    room_dir, room_seq, frames = room
    out = tmp_path / "rgbd_dataset_freiburg3_long_office_household"
    room_to_tum(room_dir, room_seq, frames[:1], out, intrinsics=False)
    seq = open_sequence(out, kind="tum")
    assert seq.intrinsics == (535.4, 539.2, 320.1, 247.6) and seq.depth_scale == 5000.0
    raw = read_depth_png(seq.depth_paths[0])
    v, u = np.argwhere(raw > 0)[7]
    z = raw[v, u] / 5000.0
    k = np.count_nonzero(raw.reshape(-1)[:v * raw.shape[1] + u])
    np.testing.assert_allclose(seq.frame(0).points[k], [(u - 320.1) * z / 535.4, (v - 247.6) * z / 539.2, z],
                               rtol=1e-6)


def test_tum_no_intrinsics(tmp_path, room):
    room_dir, room_seq, frames = room
    out = tmp_path / "my_kinect_run"
    room_to_tum(room_dir, room_seq, frames[:1], out, intrinsics=False)
    with pytest.raises(DataError) as e:
        open_sequence(out)
    assert str(out / "intrinsics.txt") in str(e.value) and "freiburg" in str(e.value)


def test_tum_no_pose_within_tolerance(tmp_path, room):
    room_dir, room_seq, frames = room
    out = tmp_path / "rgbd_dataset_freiburg2_xyz"
    room_to_tum(room_dir, room_seq, frames[:2], out, gt_shift_s=0.5)
    # the decoy poses are 0.03 s away: outside the default 0.02 s, inside 0.05 s
    with pytest.raises(DataError, match=r"groundtruth\.txt: no ground-truth pose within 0\.02 s of any of the 3 "
                                        r"depth images"):
        open_sequence(out)
    assert len(open_sequence(out, time_tolerance=0.05)) == 2


def test_tum_missing_files(tmp_path, room):
    room_dir, room_seq, frames = room
    out = tmp_path / "rgbd_dataset_freiburg1_xyz"
    room_to_tum(room_dir, room_seq, frames[:1], out)
    lines = (out / "groundtruth.txt").read_text().splitlines()
    (out / "groundtruth.txt").write_text("\n".join(lines[:2] + [lines[2] + " 7"]) + "\n")
    with pytest.raises(DataError, match=r"groundtruth\.txt line 3: expected 8 numbers"):
        open_sequence(out)
    os.remove(out / "groundtruth.txt")
    with pytest.raises(DataError, match=r"groundtruth\.txt: missing"):
        open_sequence(out)
    with pytest.raises(DataError, match=r"depth\.txt: missing"):
        open_sequence(tmp_path / "rgbd_dataset_freiburg1_xyz" / "depth", kind="tum")


# ------------------------------------------------------------------------------------------------
# Replica
# ------------------------------------------------------------------------------------------------


def room_to_replica(room_seq, frames, root, scale=1000.0):
    """Replica layout: root/cam_params.json (shared by scenes), root/room0/results/depth%06d.png + frame%06d.jpg,
    root/room0/traj.txt. Returns the scene directory."""
    from PIL import Image

    scene = root / "room0"
    (scene / "results").mkdir(parents=True)
    for i in range(len(frames)):
        shutil.copy(room_seq.depth_paths[i], scene / "results" / f"depth{i:06d}.png")
        Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(scene / "results" / f"frame{i:06d}.jpg")
    raw = read_depth_png(room_seq.depth_paths[0])
    fx, fy, cx, cy = room_seq.intrinsics
    (root / "cam_params.json").write_text(json.dumps({"camera": {
        "w": raw.shape[1], "h": raw.shape[0], "fx": fx, "fy": fy, "cx": cx, "cy": cy, "scale": scale}}))
    (scene / "traj.txt").write_text("".join(" ".join(repr(float(v)) for v in f.pose.reshape(-1)) + "\n"
                                            for f in frames))
    return scene


def test_replica_roundtrip_room(tmp_path, room):
    _, room_seq, frames = room
    scene = room_to_replica(room_seq, frames, tmp_path / "Replica")
    assert detect_kind(scene) == "replica"
    seq = open_sequence(scene)
    assert seq.kind == "replica" and len(seq) == len(frames) and seq.timestamps is None
    assert seq.cam_params_path == str(tmp_path / "Replica" / "cam_params.json")
    for fr, ref in zip(seq, frames):
        assert fr.timestamp is None
        np.testing.assert_array_equal(fr.points, ref.points)
        np.testing.assert_array_equal(fr.pose, ref.pose)
    # Replica's own depth scale, with the file beside the scene instead of in its parent
    cam = json.loads((tmp_path / "Replica" / "cam_params.json").read_text())
    cam["camera"]["scale"] = 6553.5
    (scene / "cam_params.json").write_text(json.dumps(cam))
    d = open_sequence(scene).frame(0).points[:, 2]
    raw = read_depth_png(room_seq.depth_paths[0]).reshape(-1)
    np.testing.assert_allclose(d, raw[raw > 0] / 6553.5, rtol=1e-6)


def test_replica_missing_cam_params(tmp_path, room):
    _, room_seq, frames = room
    scene = room_to_replica(room_seq, frames[:1], tmp_path / "Replica")
    os.remove(tmp_path / "Replica" / "cam_params.json")
    with pytest.raises(DataError, match=r"room0/cam_params\.json: missing \(also not in the parent"):
        open_sequence(scene)


def test_replica_malformed(tmp_path, room):
    _, room_seq, frames = room
    scene = room_to_replica(room_seq, frames[:2], tmp_path / "Replica")
    cp = tmp_path / "Replica" / "cam_params.json"
    good = cp.read_text()
    cam = json.loads(good)
    del cam["camera"]["scale"]
    cp.write_text(json.dumps(cam))
    with pytest.raises(DataError, match=r"cam_params\.json: \"camera\" lacks scale"):
        open_sequence(scene)
    cp.write_text("{not json")
    with pytest.raises(DataError, match=r"cam_params\.json: not valid JSON"):
        open_sequence(scene)
    cam = json.loads(good)
    cam["camera"]["w"] += 1
    cp.write_text(json.dumps(cam))
    with pytest.raises(DataError, match=r"depth000000\.png: image is 48 x 36 but .*cam_params\.json says w=49"):
        open_sequence(scene).frame(0)
    cp.write_text(good)
    lines = (scene / "traj.txt").read_text().splitlines()
    (scene / "traj.txt").write_text(lines[0] + "\n")
    with pytest.raises(DataError, match=r"traj\.txt: 1 poses for 2 depth images"):
        open_sequence(scene)
    (scene / "traj.txt").write_text(lines[0] + "\n" + " ".join(lines[1].split()[:15]) + "\n")
    with pytest.raises(DataError, match=r"traj\.txt line 2: expected 16 numbers"):
        open_sequence(scene)
    os.remove(scene / "traj.txt")
    with pytest.raises(DataError, match=r"traj\.txt: missing"):
        open_sequence(scene)


# ------------------------------------------------------------------------------------------------
# LAS / LAZ
# ------------------------------------------------------------------------------------------------


def write_las(path, pts, scale=0.001, offset=(100.0, -50.0, 2.0)):
    import laspy

    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = np.array([scale] * 3)
    hdr.offsets = np.array(offset)
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.write(str(path))


def test_las_laz_directory_with_poses(tmp_path, room):
    _, room_seq, frames = room
    d = tmp_path / "scans"
    d.mkdir()
    for i, fr in enumerate(frames):
        write_las(d / f"scan_{i}.{'laz' if i % 2 else 'las'}", fr.points.astype(np.float64))
    write_poses(d / "poses.txt", [f.pose for f in frames])
    assert (d / "scan_1.laz").read_bytes()[:4] == b"LASF" and detect_kind(d) == "las"
    seq = open_sequence(d)
    assert seq.kind == "las" and len(seq) == len(frames)
    assert [os.path.basename(p) for p in seq.scan_paths] == ["scan_0.las", "scan_1.laz", "scan_2.las", "scan_3.laz"]
    for fr, ref in zip(seq, frames):
        np.testing.assert_allclose(fr.points, ref.points, rtol=0, atol=0.0005 + 1e-6)  # scale 1 mm: +-0.5 mm
        np.testing.assert_array_equal(fr.pose, ref.pose)


def test_las_single_file_identity_pose_scale_offset(tmp_path):
    import laspy

    pts = np.array([[1.2345, -6.789, 0.5], [10.0, 20.0, 30.0], [-3.25, 0.0, 7.125]])
    write_las(tmp_path / "cloud.las", pts, scale=0.01, offset=(1000.0, 2000.0, -5.0))
    las = laspy.read(str(tmp_path / "cloud.las"))
    assert las.X[0] == round((1.2345 - 1000.0) / 0.01)  # stored as integers: scale and offset must be applied
    assert detect_kind(tmp_path / "cloud.las") == "las"
    seq = open_sequence(tmp_path / "cloud.las")
    assert len(seq) == 1 and seq.gt_points_path is None
    fr = seq.frame(0)
    np.testing.assert_array_equal(fr.pose, np.eye(4))
    np.testing.assert_allclose(fr.points, pts, atol=0.005 + 1e-5)


def test_las_errors(tmp_path, monkeypatch):
    d = tmp_path / "scans"
    d.mkdir()
    write_las(d / "0.las", np.zeros((3, 3)))
    write_las(d / "1.las", np.ones((3, 3)))
    with pytest.raises(DataError, match=r"scans/poses\.txt: missing; a directory of LAS/LAZ scans needs poses\.txt"):
        open_sequence(d)
    write_poses(d / "poses.txt", [np.eye(4)])
    with pytest.raises(DataError, match=r"poses\.txt: 1 poses for 2 scans"):
        open_sequence(d)
    write_poses(d / "poses.txt", [np.eye(4)] * 2)
    (d / "1.las").write_bytes((d / "1.las").read_bytes()[:150])
    with pytest.raises(DataError, match=r"1\.las: not a readable LAS/LAZ file"):
        open_sequence(d).frame(1)
    import laspy

    def no_backend(*a, **k):
        raise laspy.LaspyException("No LazBackend selected, cannot decompress data")

    write_las(tmp_path / "one.laz", np.zeros((3, 3)))
    monkeypatch.setattr(laspy, "read", no_backend)
    with pytest.raises(DataError, match=r"one\.laz: cannot decompress LAZ .*pip install 'laspy\[lazrs\]'"):
        open_sequence(tmp_path / "one.laz").frame(0)
    monkeypatch.undo()
    (tmp_path / "x.laz").write_bytes(b"garbage")
    with pytest.raises(DataError, match=r"x\.laz: .*"):
        open_sequence(tmp_path / "x.laz").frame(0)


# ------------------------------------------------------------------------------------------------
# detection, kinds and the config key
# ------------------------------------------------------------------------------------------------


def test_detect_and_unknown(tmp_path):
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(DataError, match=r"notes\.txt: unknown sequence file type '\.txt'"):
        open_sequence(tmp_path / "notes.txt")
    with pytest.raises(DataError) as e:
        open_sequence(tmp_path)
    for word in ("velodyne", "depth", "ROS bag", "TUM", "Replica", "LAS"):
        assert word in str(e.value)
    with pytest.raises(DataError, match=r"unknown sequence kind 'ply'.*'rosbag', 'tum', 'replica', 'las'"):
        open_sequence(tmp_path, kind="ply")


def test_config_topic_reaches_the_bag(tmp_path, room):
    from jaxmap.config import DataConfig, ImtConfig
    from jaxmap.frame_loop import open_run_sequence

    _, room_seq, frames = room
    entries = room_bag_entries(room_seq, frames[:1], cloud_topic="/a")
    entries += room_bag_entries(room_seq, frames[:1], cloud_topic="/b", pose_type=None)
    path = write_bag(tmp_path / "two", "mcap", entries)
    cfg = ImtConfig(data=DataConfig(path=str(path), kind="rosbag", topic="/b"))
    assert open_run_sequence(cfg).topic == "/b"
    assert DataConfig().topic == ""


# ------------------------------------------------------------------------------------------------
# End to end: the mapping commands on the converted sequences
# ------------------------------------------------------------------------------------------------


def test_map_imt_and_slam_run_on_a_bag_a_tum_and_a_replica_sequence(tmp_path, room):
    """`jaxmap map` on a ROS 2 MCAP bag, `jaxmap imt` on the TUM layout and `jaxmap slam` on the
    Replica layout of the same small room: each runs to a mesh, and the mapped frames are the room's."""
    from jaxmap.cli import main

    room_dir, room_seq, frames = room
    bag = write_bag(tmp_path / "room", "mcap", room_bag_entries(room_seq, frames))
    tum = tmp_path / "rgbd_dataset_freiburg1_room"
    room_to_tum(room_dir, room_seq, frames, tum)
    replica = room_to_replica(room_seq, frames, tmp_path / "Replica")
    common = ["--no-progress"]
    rc = main(["map", "configs/rgbd.yaml", "--data", str(bag), "--out", str(tmp_path / "map")] + common
              + ["--set", "train.iters=3", "--set", "train.nv=64", "--set", "mesh.min_component_faces=0"])
    assert rc == 0 and (tmp_path / "map" / "mesh.ply").exists()
    timing = json.loads((tmp_path / "map" / "timing.json").read_text())
    assert len(timing["frames"]) == len(frames)
    rc = main(["imt", "configs/room_imt.yaml", "--data", str(tum), "--out", str(tmp_path / "imt")] + common
              + ["--set", "data.every_frame=1", "--set", "map.min_points=2", "--set", "mesh.min_weight=1"])
    assert rc == 0 and (tmp_path / "imt" / "mesh.ply").exists()
    rc = main(["slam", "configs/room_slam.yaml", "--data", str(replica), "--out", str(tmp_path / "slam")] + common
              + ["--set", "data.every_frame=1"])
    assert rc == 0 and (tmp_path / "slam" / "trajectory_kitti.txt").exists()
    traj = np.loadtxt(tmp_path / "slam" / "trajectory_kitti.txt").reshape(-1, 3, 4)
    assert len(traj) == len(frames)
