"""The N3 mapping engine as pure functions over one state pytree: the public face of its modules.

    static = N3Static.from_config(cfg)                # frozen, hashable: shapes and modes
    state = init_state(static, cfg, capacities_for(static, cfg))
    state = set_origin(static, state, sensor_xyz_world) # once, before the first frame
    state, frame_stats, train_stats = step(static, state, scan)   # integrate + train, one jit
    ... = step_raw(static, state, raw_scan, rows)      # the same from a raw scan (preprocess.device)
    pipe = FramePipeline(static, state, headroom, seed=..., feature_std=...)   # the host's driver of frames
    sdf, valid = query(static, state, points_m)

Where each part lives, read top to bottom:
  - `jaxmap.n3.state`: `N3Static`, `N3State`, `Capacities`, the empty map and its origin;
  - `jaxmap.n3.scan_batch`: the scan as the frame program takes it (`ScanBatch`, `RawScan`);
  - `jaxmap.n3.query`: the SDF at map-frame points, and its host wrappers;
  - `jaxmap.n3.integrate`: one scan into the map (sample, allocate, store, slide, carve);
  - `jaxmap.n3.train`: K iterations of batch selection, loss and Adam;
  - `jaxmap.n3.frame`: `step` (both in one donated program), growth and the host's frame driver
    (`FramePipeline`: frames dispatched ahead of their stats), with this process's compiled frame programs
    (`PROGRAMS`, a `ProgramCache`: the programs kept and every compile's seconds).
"""
from jaxmap.grid.features import FEATURE_INIT_BLOCK
from jaxmap.n3.frame import (
    PROGRAMS,
    FrameDone,
    FramePipeline,
    ProgramCache,
    compiled_step,
    forget_compiled,
    frames_held_jit,
    grow_for,
    run_frame,
    step,
    step_after,
    step_raw,
    store_bytes,
)
from jaxmap.n3.integrate import FrameStats, integrate
from jaxmap.n3.query import query, query_grad_jit, query_jit
from jaxmap.n3.scan_batch import RawScan, ScanBatch, count_kept, preprocess_raw
from jaxmap.n3.state import (Capacities, Hyper, N3State, N3Static, capacities_for, init_state, origin_vox_for,
                             origin_world, set_origin)
from jaxmap.n3.train import TrainStats, train
from jaxmap.sizes import pow2

__all__ = [
    "PROGRAMS", "FEATURE_INIT_BLOCK", "Capacities", "FrameDone",
    "FramePipeline", "FrameStats", "Hyper", "ProgramCache",
    "N3State", "N3Static", "RawScan", "ScanBatch", "TrainStats", "capacities_for", "compiled_step", "count_kept",
    "forget_compiled", "frames_held_jit", "grow_for", "init_state", "integrate", "origin_vox_for", "origin_world", "pow2",
    "preprocess_raw", "query", "query_grad_jit", "query_jit", "run_frame", "set_origin", "step", "step_after", "step_raw",
    "store_bytes", "train",
]
