"""ROS bags (ROS 1 `.bag`, ROS 2 bag directories with `.db3`/`.mcap`, bare `.mcap`/`.db3` files) as sequences.

Read with the pure-Python `rosbags` library (no ROS install). One frame per `sensor_msgs/PointCloud2`
message of the chosen topic:

* points: the x, y, z fields, whatever their offsets and datatype (float32, float64 or integer),
  organised (height > 1) or not, with point_step / row_step padding and either byte order;
  points with a NaN/inf coordinate (the "no return" of organised clouds) are dropped.
* timestamp: the message's header stamp (the bag's receive time if the header stamp is 0).
* pose (T_world_sensor), from the first of these that exists:
    1. `pose_file=`: a TUM trajectory (`timestamp tx ty tz qx qy qz qw` per line);
    2. `pose_topic=`: a nav_msgs/Odometry, geometry_msgs/PoseStamped or PoseWithCovarianceStamped topic;
    3. a TUM trajectory beside the bag: `<stem>.tum` next to a bag file (run.bag -> run.tum), or
       `<name>.tum` inside or next to a ROS 2 bag directory `<name>/`;
    4. the bag's only pose topic (Odometry / PoseStamped / PoseWithCovarianceStamped).
  A frame's pose is INTERPOLATED (translation linear, rotation slerp) between the poses just before
  and just after its timestamp when both are within `time_tolerance` (default 0.1 s); otherwise it is
  the NEAREST pose if that is within `time_tolerance`; frames with neither are skipped (counted in a
  warning), and no frame with a pose is an error. The pose is used as the pose of the cloud's frame:
  there is no TF lookup, so the pose source must describe the sensor itself (a warning says so when an
  Odometry's child_frame_id differs from the cloud's frame_id).

`describe(path)` lists (topic, msgtype, count) of a bag, for `jaxmap info`.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from jaxmap.errors import DataError
from jaxmap.io.kitti import Sequence
from jaxmap.io.stamped import poses_at_times, poses_from_tum_rows, read_tum_trajectory

log = logging.getLogger("jaxmap")

BAG_SUFFIXES = (".bag", ".mcap", ".db3")
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
              "geometry_msgs/msg/PoseWithCovarianceStamped")
TIME_TOLERANCE_S = 0.1

# sensor_msgs/PointField datatypes
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def is_rosbag(path) -> bool:
    """A ROS 1 .bag, a bare .mcap/.db3 file, or a ROS 2 bag directory (with metadata.yaml)."""
    path = os.fspath(path)
    if os.path.isdir(path):
        return os.path.isfile(os.path.join(path, "metadata.yaml"))
    return os.path.isfile(path) and os.path.splitext(path)[1].lower() in BAG_SUFFIXES


def _short(msgtype: str) -> str:
    return msgtype.replace("/msg/", "/")


def open_reader(path):
    """An opened `rosbags.highlevel.AnyReader` on `path`; DataError naming the path if it cannot be read."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:  # pragma: no cover - a declared dependency
        raise DataError(f"{path}: reading ROS bags needs the 'rosbags' package; pip install rosbags") from None
    path = os.fspath(path)
    if not os.path.exists(path):
        raise DataError(f"{path}: ROS bag not found; check the path (data.path / --data)")
    if os.path.isdir(path) and not os.path.isfile(os.path.join(path, "metadata.yaml")):
        raise DataError(f"{path}: not a ROS 2 bag directory (no metadata.yaml); pass the .db3/.mcap file itself "
                        "or the directory `ros2 bag record` wrote")
    try:
        reader = AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as e:  # rosbags raises several error types (reader, typesys, sqlite, struct)
        hint = ""
        if "index" in str(e).lower():
            hint = "; an unindexed ROS 1 bag (recording interrupted) is fixed with `rosbag reindex`"
        raise DataError(f"{path}: not a readable ROS bag ({type(e).__name__}: {e}){hint}") from None
    return reader


def _topics(reader) -> dict[str, tuple[str, int]]:
    out = {}
    for name, info in reader.topics.items():
        types = sorted({c.msgtype for c in info.connections}) or [str(info.msgtype)]
        out[name] = ("|".join(types), int(info.msgcount))
    return out


def describe(path) -> list[tuple[str, str, int]]:
    """Topics of a ROS bag: [(topic, msgtype, message count)] sorted by topic (msgtype as rosbags names it,
    e.g. 'sensor_msgs/msg/PointCloud2'). Raises DataError naming the path if it is not a readable bag."""
    reader = open_reader(path)
    try:
        return [(t, ty, n) for t, (ty, n) in sorted(_topics(reader).items())]
    finally:
        reader.close()


def _list(topics: dict, types) -> str:
    items = [f"{t} ({_short(ty)}, {n} message{'' if n == 1 else 's'})" for t, (ty, n) in sorted(topics.items())
             if ty in types]
    return ", ".join(items) if items else "none"


def _all(topics: dict) -> str:
    return ", ".join(f"{t} ({_short(ty)})" for t, (ty, _) in sorted(topics.items())) or "no topics"


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def pointcloud2_xyz(msg, where: str) -> np.ndarray:
    """x, y, z of a deserialised sensor_msgs/PointCloud2 -> [N,3] float32, non-finite points dropped.

    Any field layout: offsets and datatypes from `msg.fields`, `point_step`/`row_step` padding,
    organised (height > 1) or flat, big- or little-endian. DataError naming `where` if x/y/z are missing
    or the data is shorter than the header says."""
    fields = {f.name: f for f in msg.fields}
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        raise DataError(f"{where}: PointCloud2 has no field {', '.join(missing)} (fields: "
                        f"{', '.join(fields) or 'none'}); choose a topic with x, y, z points (data.topic)")
    h, w = int(msg.height), int(msg.width)
    step, row_step = int(msg.point_step), int(msg.row_step)
    if h * w == 0:
        return np.zeros((0, 3), np.float32)
    endian = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for c in "xyz":
        f = fields[c]
        if int(f.datatype) not in _FIELD_TYPES:
            raise DataError(f"{where}: PointCloud2 field {c} has unknown datatype {f.datatype}")
        dt = np.dtype(endian + _FIELD_TYPES[int(f.datatype)])
        if int(f.offset) + dt.itemsize > step:
            raise DataError(f"{where}: PointCloud2 field {c} (offset {f.offset}, {dt.itemsize} bytes) does not fit "
                            f"in point_step {step}; the message is corrupt")
        formats.append(dt)
        offsets.append(int(f.offset))
    if h > 1 and row_step < w * step:
        raise DataError(f"{where}: PointCloud2 row_step {row_step} < width {w} x point_step {step}; corrupt message")
    row_step = row_step if h > 1 else w * step
    data = np.ascontiguousarray(np.asarray(msg.data, dtype=np.uint8).reshape(-1))
    need = (h - 1) * row_step + w * step
    if data.size < need:
        raise DataError(f"{where}: PointCloud2 has {data.size} data bytes, its header ({h} x {w} points, "
                        f"point_step {step}, row_step {row_step}) needs {need}; the message is truncated")
    dtype = np.dtype({"names": ["x", "y", "z"], "formats": formats, "offsets": offsets, "itemsize": step})
    arr = np.ndarray(shape=(h, w), dtype=dtype, buffer=data, offset=0, strides=(row_step, step))
    pts = np.stack([arr["x"].reshape(-1), arr["y"].reshape(-1), arr["z"].reshape(-1)], axis=1)
    pts = pts.astype(np.float32)
    good = np.isfinite(pts).all(axis=1)
    if not good.all():
        log.debug("%s: dropped %d of %d points with NaN/inf coordinates", where, int((~good).sum()), len(pts))
        pts = pts[good]
    return np.ascontiguousarray(pts)


def _pose_of(msg, msgtype: str):
    """(header, geometry_msgs/Pose) of a pose message."""
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return msg.header, msg.pose
    return msg.header, msg.pose.pose  # Odometry, PoseWithCovarianceStamped


def tum_candidates(path) -> list[str]:
    """Where a TUM trajectory beside a bag is looked for (first existing one is used)."""
    path = os.path.normpath(os.fspath(path))
    if os.path.isdir(path):
        name = os.path.basename(path)
        return [os.path.join(path, name + ".tum"), path + ".tum"]
    return [os.path.splitext(path)[0] + ".tum"]


class RosbagSequence(Sequence):
    """PointCloud2 frames of a ROS bag (see the module docstring).

    Extra attributes: topic (the cloud topic), pose_source (a topic name or a TUM file path),
    stamps_ns ([M] int64 header stamps of the selected frames), time_tolerance (s), n_skipped (clouds
    without a pose within the tolerance). The bag is opened once on the first `frame()` and kept open;
    `close()` (or `with`) releases it.
    """

    kind = "rosbag"

    def __init__(self, path, begin_frame: int = 0, end_frame: int = -1, every_frame: int = 1, topic: str = "",
                 pose_topic: str = "", pose_file: str = "", time_tolerance: float | None = None):
        path = os.fspath(path)
        self._reader = None
        self.time_tolerance = TIME_TOLERANCE_S if time_tolerance is None else float(time_tolerance)
        reader = open_reader(path)
        try:
            topics = _topics(reader)
            self.topic = self._choose_cloud_topic(path, topics, topic)
            cloud_ns, bag_ns, ordinal, frame_id = self._index_clouds(path, reader)
            src, pose_ns, poses, child = self._read_pose_source(path, reader, topics, pose_topic, pose_file)
        finally:
            reader.close()
        self.pose_source = src
        if child and frame_id and child != frame_id:
            log.warning("%s: poses on %s are of frame '%s' but the clouds on %s are in frame '%s'; jaxmap uses "
                        "them as the sensor's poses (no TF lookup). If they differ, supply LiDAR poses as a TUM "
                        "file %s", path, src, child, self.topic, frame_id, tum_candidates(path)[0])
        t_cloud = cloud_ns.astype(np.float64) * 1e-9
        t0 = min(int(cloud_ns.min()), int(pose_ns.min()) if len(pose_ns) else int(cloud_ns.min()))
        # interpolate in seconds relative to a common origin, so float64 keeps sub-microsecond resolution
        ok, T, _ = poses_at_times((cloud_ns - t0) * 1e-9, (pose_ns - t0) * 1e-9, poses, self.time_tolerance,
                                  interpolate=True)
        self.n_skipped = int((~ok).sum())
        if not ok.any():
            span = (f"{(pose_ns.min() - t0) * 1e-9:.3f} .. {(pose_ns.max() - t0) * 1e-9:.3f} s" if len(pose_ns)
                    else "no poses")
            raise DataError(f"{path}: none of the {len(cloud_ns)} clouds on {self.topic} has a pose from {src} within "
                            f"{self.time_tolerance} s (clouds at {(cloud_ns.min() - t0) * 1e-9:.3f} .. "
                            f"{(cloud_ns.max() - t0) * 1e-9:.3f} s, poses at {span}, relative to the first stamp); "
                            "check that both use the same clock, or pass a larger open_sequence(..., "
                            "time_tolerance=...)")
        if self.n_skipped:
            log.warning("%s: skipped %d of %d clouds on %s with no pose from %s within %g s", path, self.n_skipped,
                        len(cloud_ns), self.topic, src, self.time_tolerance)
        self._bag_ns_all, self._ordinal_all = bag_ns[ok], ordinal[ok]
        stamps_all = cloud_ns[ok]
        super().__init__(path, int(ok.sum()), T[ok], begin_frame, end_frame, every_frame,
                         timestamps_all=t_cloud[ok])
        self.stamps_ns = stamps_all[self.indices]
        here = path if os.path.isdir(path) else os.path.dirname(os.path.abspath(path))
        gp, gm = os.path.join(here, "gt_points.ply"), os.path.join(here, "gt_mesh.ply")
        self.gt_points_path = gp if os.path.isfile(gp) else None
        self.gt_mesh_path = gm if os.path.isfile(gm) else None

    # -------------------------------------------------------------------------------------------
    @staticmethod
    def _choose_cloud_topic(path, topics, topic):
        clouds = sorted(t for t, (ty, _) in topics.items() if ty == CLOUD_TYPE)
        if topic:
            if topic not in topics:
                raise DataError(f"{path}: no topic {topic!r} (data.topic); PointCloud2 topics: "
                                f"{_list(topics, (CLOUD_TYPE,))}")
            if topics[topic][0] != CLOUD_TYPE:
                raise DataError(f"{path}: topic {topic} is {_short(topics[topic][0])}, not sensor_msgs/PointCloud2; "
                                f"PointCloud2 topics: {_list(topics, (CLOUD_TYPE,))}")
            return topic
        if not clouds:
            raise DataError(f"{path}: no sensor_msgs/PointCloud2 topic to map; the bag has: {_all(topics)}")
        if len(clouds) > 1:
            raise DataError(f"{path}: {len(clouds)} PointCloud2 topics: {_list(topics, (CLOUD_TYPE,))}; choose one "
                            f"with --set data.topic={clouds[0]} (or open_sequence(..., topic=...))")
        return clouds[0]

    def _index_clouds(self, path, reader):
        conns = [c for c in reader.connections if c.topic == self.topic]
        cloud_ns, bag_ns, ordinal = [], [], []
        frame_id, last_t, run, zero = "", None, 0, 0
        for conn, t, raw in reader.messages(connections=conns):
            msg = self._deserialize(reader, raw, conn.msgtype, path, len(bag_ns))
            s = _stamp_ns(msg.header)
            if s <= 0:
                s, zero = int(t), zero + 1
            frame_id = frame_id or str(msg.header.frame_id)
            run = run + 1 if t == last_t else 0
            last_t = t
            cloud_ns.append(s)
            bag_ns.append(int(t))
            ordinal.append(run)
        if not cloud_ns:
            raise DataError(f"{path}: topic {self.topic} has no messages; choose another topic (data.topic)")
        if zero:
            log.info("%s: %d clouds on %s have a zero header stamp; using their bag receive time", path, zero,
                     self.topic)
        return (np.asarray(cloud_ns, np.int64), np.asarray(bag_ns, np.int64), np.asarray(ordinal, np.int64),
                frame_id)

    def _read_pose_source(self, path, reader, topics, pose_topic, pose_file):
        """-> (source name, stamps [P] int64 ns, poses [P,4,4], pose child frame or '')."""
        if pose_file:
            return self._tum(pose_file)
        pose_topics = sorted(t for t, (ty, _) in topics.items() if ty in POSE_TYPES)
        if pose_topic:
            if pose_topic not in topics or topics[pose_topic][0] not in POSE_TYPES:
                have = f"is {_short(topics[pose_topic][0])}" if pose_topic in topics else "does not exist"
                raise DataError(f"{path}: pose topic {pose_topic!r} {have}; pose topics (Odometry, PoseStamped, "
                                f"PoseWithCovarianceStamped): {_list(topics, POSE_TYPES)}")
            return self._pose_topic(path, reader, pose_topic)
        for cand in tum_candidates(path):
            if os.path.isfile(cand):
                log.info("%s: poses from the TUM trajectory %s", path, cand)
                return self._tum(cand)
        if len(pose_topics) == 1:
            log.info("%s: poses from topic %s", path, pose_topics[0])
            return self._pose_topic(path, reader, pose_topics[0])
        if pose_topics:
            raise DataError(f"{path}: {len(pose_topics)} pose topics: {_list(topics, POSE_TYPES)}; choose one with "
                            f"open_sequence(..., pose_topic=...) or write the poses as a TUM file "
                            f"{tum_candidates(path)[0]}")
        raise DataError(f"{path}: no pose source: the bag has no nav_msgs/Odometry, geometry_msgs/PoseStamped or "
                        f"PoseWithCovarianceStamped topic (it has: {_all(topics)}) and there is no TUM trajectory "
                        f"{tum_candidates(path)[0]}; write the sensor poses there, one line "
                        "'timestamp tx ty tz qx qy qz qw' per pose")

    @staticmethod
    def _tum(pose_file):
        t, P = read_tum_trajectory(pose_file, what="TUM trajectory (pose file)")
        return os.fspath(pose_file), np.round(t * 1e9).astype(np.int64), P, ""

    def _pose_topic(self, path, reader, topic):
        conns = [c for c in reader.connections if c.topic == topic]
        stamps, rows, child = [], [], ""
        for conn, t, raw in reader.messages(connections=conns):
            msg = self._deserialize(reader, raw, conn.msgtype, path, len(rows), topic)
            header, pose = _pose_of(msg, conn.msgtype)
            s = _stamp_ns(header)
            stamps.append(s if s > 0 else int(t))
            p, q = pose.position, pose.orientation
            rows.append([p.x, p.y, p.z, q.x, q.y, q.z, q.w])
            child = child or str(getattr(msg, "child_frame_id", "") or "")
        if not rows:
            raise DataError(f"{path}: pose topic {topic} has no messages; write the poses as a TUM file "
                            f"{tum_candidates(path)[0]} instead")
        P = poses_from_tum_rows(np.asarray(rows), f"{path} topic {topic} message")
        return topic, np.asarray(stamps, np.int64), P, child

    def _deserialize(self, reader, raw, msgtype, path, k, topic=None):
        try:
            return reader.deserialize(raw, msgtype)
        except Exception as e:
            raise DataError(f"{path}: message {k} on {topic or self.topic} cannot be decoded as {_short(msgtype)} "
                            f"({e}); the bag is corrupt or its message definitions are wrong") from None

    # -------------------------------------------------------------------------------------------
    def _read_points(self, index: int) -> np.ndarray:
        if self._reader is None:
            self._reader = open_reader(self.data_dir)
        r = self._reader
        t, want = int(self._bag_ns_all[index]), int(self._ordinal_all[index])
        conns = [c for c in r.connections if c.topic == self.topic]
        where = f"{self.data_dir} topic {self.topic} frame {index}"
        k = 0
        # start 1 ns early and no stop: rosbags < 0.11.7 skips an mcap chunk whose last message is at `start`
        for conn, tm, raw in r.messages(connections=conns, start=max(t - 1, 0)):
            if tm > t:
                break
            if tm == t:
                if k == want:
                    return pointcloud2_xyz(self._deserialize(r, raw, conn.msgtype, self.data_dir, index), where)
                k += 1
        raise DataError(f"{where}: message at bag time {t} ns is gone; was the bag changed while it was open?")

    def close(self) -> None:
        """Close the bag (it is reopened by the next `frame()`)."""
        if self._reader is not None:
            reader, self._reader = self._reader, None
            try:
                reader.close()
            except Exception:  # pragma: no cover - closing a half-open reader
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def __del__(self):
        try:
            self.close()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass
