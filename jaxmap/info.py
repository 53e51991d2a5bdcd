"""`jaxmap info PATH`: what a sequence is before mapping it.

Prints the sequence kind (as `open_sequence` detects it), the frame count, the time span when the
format has timestamps, whether ground truth (gt_points.ply / gt_mesh.ply) is there and, for a ROS bag,
every topic with its message type and count (`jaxmap.io.describe`), so the PointCloud2 topic to map
(`data.topic`) can be chosen. A path that is missing or not a readable sequence raises DataError naming it.
"""
from __future__ import annotations

import os

from jaxmap.errors import DataError

CLOUD_TYPES = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/PointCloud2")


def sequence_info(path, kind: str = "auto", topic: str = "") -> dict:
    """Facts about the sequence at `path` -> dict(path, kind, frames, [topics], [duration_s], gt, [note]).

    frames: the frames `open_sequence` yields (for a ROS bag: PointCloud2 messages that have a pose). For a
    bag whose frames cannot be built (several cloud topics and no `topic`, no pose source) the topics are
    still listed, frames is the number of PointCloud2 messages and `note` says why mapping it needs more.
    """
    from jaxmap.io import describe, detect_kind, open_sequence

    path = os.fspath(path)
    if not os.path.exists(path):
        raise DataError(f"{path}: no such file or directory")
    kind = detect_kind(path) if kind == "auto" else kind
    out: dict = {"path": path, "kind": kind}
    if kind == "rosbag":
        topics = describe(path)        # DataError naming the path for an unreadable bag
        out["topics"] = [{"topic": t, "type": ty, "count": int(n)} for t, ty, n in topics]
        try:
            seq = open_sequence(path, kind="rosbag", topic=topic)
        except DataError as e:
            clouds = [n for t, ty, n in topics if ty in CLOUD_TYPES and (not topic or t == topic)]
            out["frames"] = int(sum(clouds))
            out["note"] = str(e)
            return out
        out["topic"] = seq.topic
        out["pose_source"] = seq.pose_source
        close = getattr(seq, "close", None)
        if close is not None:
            close()
    else:
        seq = open_sequence(path, kind=kind)
    out["frames"] = len(seq)
    ts = getattr(seq, "timestamps", None)
    if ts is not None and len(ts) > 1:
        out["duration_s"] = float(ts[-1] - ts[0])
    out["gt"] = [os.path.basename(p) for p in (seq.gt_points_path, seq.gt_mesh_path) if p]
    return out


def format_info(info: dict) -> str:
    """The human-readable lines `jaxmap info` prints."""
    lines = [f"path:    {info['path']}", f"kind:    {info['kind']}", f"frames:  {info['frames']}"]
    if "duration_s" in info:
        lines.append(f"span:    {info['duration_s']:.3f} s")
    if "topic" in info:
        lines.append(f"mapped:  {info['topic']} (poses from {info['pose_source']})")
    if "gt" in info:
        lines.append(f"ground truth: {', '.join(info['gt']) or 'none'}")
    if "topics" in info:
        w = max([len(t["topic"]) for t in info["topics"]] + [5])
        wt = max([len(t["type"]) for t in info["topics"]] + [4])
        lines.append(f"topics:  {len(info['topics'])}")
        lines.append(f"  {'topic':{w}s}  {'type':{wt}s}  {'count':>7s}")
        for t in info["topics"]:
            lines.append(f"  {t['topic']:{w}s}  {t['type']:{wt}s}  {t['count']:7d}")
    if "note" in info:
        lines.append(f"note:    {info['note']}")
    return "\n".join(lines)
