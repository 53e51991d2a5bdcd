"""`jaxmap info PATH`: kind, frame count, ROS bag topics; errors are one line naming the path, exit code 2."""
import numpy as np

from jaxmap.cli import main
from jaxmap.info import sequence_info

from test_io_formats import CLOUD, ODOM, room_bag_entries, write_bag


def test_info_depth_sequence(small_room, capsys):
    assert main(["info", str(small_room)]) == 0
    out = capsys.readouterr().out
    assert "kind:    depth" in out and "frames:  10" in out and "gt_points.ply" in out


def test_info_rosbag_lists_topics_with_types_and_counts(tmp_path, small_room, capsys):
    from jaxmap.io import open_sequence

    seq = open_sequence(small_room, end_frame=3)
    frames = list(seq)
    bag = write_bag(tmp_path / "room", "ros1", room_bag_entries(seq, frames))
    info = sequence_info(bag)
    assert info["kind"] == "rosbag" and info["frames"] == 3 and info["topic"] == "/camera/points"
    assert info["topics"] == [{"topic": "/camera/points", "type": CLOUD, "count": 3},
                              {"topic": "/odom", "type": ODOM, "count": 3}]
    assert main(["info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "kind:    rosbag" in out and "frames:  3" in out
    line = next(ln for ln in out.splitlines() if "/odom" in ln and ODOM in ln)
    assert line.split()[-1] == "3"


def test_info_rosbag_without_poses_still_lists_topics(tmp_path, small_room, capsys):
    from jaxmap.io import open_sequence

    seq = open_sequence(small_room, end_frame=2)
    bag = write_bag(tmp_path / "clouds", "ros2_mcap", room_bag_entries(seq, list(seq), pose_type=None))
    assert main(["info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "frames:  2" in out and "/camera/points" in out and "note:" in out


def test_info_errors_name_the_path(tmp_path, capsys):
    missing = tmp_path / "nope"
    assert main(["info", str(missing)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(missing) in err and err.startswith("jaxmap info: error:")
    bad = tmp_path / "broken.bag"
    bad.write_bytes(np.random.default_rng(0).bytes(256))
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(bad) in err and "ROS bag" in err
