"""`jaxmap bench path`: what follows a scan and how its way is counted (no map is run here)."""
import dataclasses

import numpy as np

from jaxmap.bench.path import ScanTrace, summary


@dataclasses.dataclass(frozen=True)
class _Scan:
    points: np.ndarray
    pose: np.ndarray


def test_what_is_made_of_the_scan_is_followed_and_nothing_else():
    trace = ScanTrace(frame=3)
    points, other = np.zeros((5, 3)), np.zeros((5, 3))
    trace.taint((_Scan(points, np.eye(4)), 7))
    assert trace.marked_in(points) and trace.marked_in([1, (points,)])        # in a tuple in a list
    assert trace.marked_in(_Scan(other, np.eye(4))) is False                 # a different scan
    assert trace.marked_in(other) is False and trace.marked_in(7) is False    # (plain numbers are never marked)


def test_the_way_counts_modules_and_moves_between_them():
    calls = [("t", "jaxmap.io.kitti", "KittiSequence.frame", "", ""),
             ("t", "jaxmap.n3.scan", "MapStart.prepare", "jaxmap.frame_loop", "prepared_frame"),
             ("t", "jaxmap.n3.scan", "preprocess", "jaxmap.n3.scan", "MapStart.prepare"),
             ("t", "jaxmap.preprocess", "crop", "jaxmap.n3.scan", "preprocess"),
             ("t", "jaxmap.preprocess", "crop", "jaxmap.n3.scan", "preprocess"),          # again: one move
             ("t", "jaxmap.n3.scan", "__create_fn__.<locals>.__init__", "dataclasses", "replace"),
             ("t", "jaxmap.n3.frame", "FramePipeline._dispatch", "jaxmap.n3.mapper", "N3Mapper.submit")]
    s = summary(calls)
    assert s["modules"] == ["jaxmap.io.kitti", "jaxmap.n3.scan", "jaxmap.preprocess", "jaxmap.n3.frame"]
    assert s["calls_between_modules"] == 4            # prepare, crop twice, _dispatch (a module's own: not)
    assert s["moves"] == 4 and s["moves_between_modules"] == 3
