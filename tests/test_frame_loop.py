"""The one frame loop (`jaxmap.frame_loop`) on a sequence of plain frames and a recording step: order,
read-ahead, checkpoints every N frames and at the end, Ctrl-C between frames, errors from the reader."""
import os
import signal
import threading

import numpy as np
import pytest

from jaxmap.frame_loop import Checkpoints, Frame, Prefetcher, Progress, run_frames
from jaxmap.records import medians
from jaxmap.rundir import Interrupted


class FakeSequence:
    """`n` frames of one point each; frame i reads as [[i, 0, 0]] (or raises at `broken`)."""

    thread_safe_frames = True

    def __init__(self, n: int, broken: int = -1):
        self.n, self.broken, self.read = n, broken, []

    def __len__(self):
        return self.n

    def frame(self, i):
        if i == self.broken:
            raise OSError(f"frame {i}: truncated file")
        self.read.append((i, threading.current_thread().name))
        return type("F", (), {"index": 10 + i, "points": np.array([[float(i), 0.0, 0.0]], np.float32),
                              "pose": np.eye(4)})()


def _step(log):
    def step(frame: Frame):
        log.append((frame.position, frame.index, float(frame.points[0, 0])))
        return {"points": 1}, frame.pose
    return step


def test_frames_come_in_order_read_ahead_in_a_thread():
    seq, log = FakeSequence(9), []
    loop = run_frames(Prefetcher(seq, 2, 9, workers=2), _step(log), total=9, start=2, progress=Progress(enabled=False))
    assert log == [(i, 10 + i, float(i)) for i in range(2, 9)]      # positions 2..8, in order, each once
    assert loop.frames_run == 7 and loop.wall_s >= 0
    assert all(name.startswith("jaxmap-prefetch") for _, name in seq.read)


def test_checkpoints_every_n_frames_and_at_the_end():
    saves = []
    ck = Checkpoints(save=lambda background: saves.append(("bg" if background else "end", len(log))), path="x",
                     every=3)
    log = []
    run_frames(Prefetcher(FakeSequence(8), 0, 8), _step(log), total=8, progress=Progress(enabled=False),
               checkpoints=ck)
    # after frames 3 and 6 in the background (never after the last frame: the end saves it), then once at the end
    assert saves == [("bg", 3), ("bg", 6), ("end", 8)]


def test_a_busy_background_save_moves_to_the_next_frame():
    saves, busy = [], iter([True, False, False, False, False])
    ck = Checkpoints(save=lambda background: saves.append((background, len(log))), path="x", every=2,
                     busy=lambda: next(busy))
    log = []
    run_frames(Prefetcher(FakeSequence(7), 0, 7), _step(log), total=7, progress=Progress(enabled=False),
               checkpoints=ck)
    assert saves == [(True, 3), (True, 5), (False, 7)]


def test_sigint_stops_between_frames_saves_and_reraises(capsys):
    saves, log = [], []
    ck = Checkpoints(save=lambda background: saves.append((background, len(log))), path="RUN/checkpoint",
                     resume="jaxmap map --resume RUN")

    def step(frame):
        log.append(frame.position)
        if frame.position == 2:
            os.kill(os.getpid(), signal.SIGINT)   # Ctrl-C while frame 2 maps: frame 2 still finishes
        return {}, None

    with pytest.raises(Interrupted):
        run_frames(Prefetcher(FakeSequence(6), 0, 6), step, total=6, progress=Progress(enabled=False),
                   checkpoints=ck)
    assert log == [0, 1, 2] and saves == [(False, 3)]
    err = capsys.readouterr().err
    assert "checkpoint of 3 frames saved in RUN/checkpoint; continue with: jaxmap map --resume RUN" in err


def test_a_reader_error_reaches_the_caller_and_nothing_is_saved():
    saves, log = [], []
    ck = Checkpoints(save=lambda background: saves.append(background), path="x", every=1)
    with pytest.raises(OSError, match="frame 3: truncated"):
        run_frames(Prefetcher(FakeSequence(6, broken=3), 0, 6), _step(log), total=6,
                   progress=Progress(enabled=False), checkpoints=ck)
    assert [p for p, _, _ in log] == [0, 1, 2] and saves == [True, True, True]   # no final save of a broken run


def test_medians_skip_the_compiling_frame_and_count_empty_frames():
    rows = [{"total_s": 9.0, "points": 5}, {"total_s": 1.0, "points": 0}, {"total_s": 3.0, "points": 2}]
    assert medians(rows, ("total_s", "absent_s")) == {"median_total_s": 2.0, "median_absent_s": pytest.approx(
        float("nan"), nan_ok=True), "empty_frames": 1}
