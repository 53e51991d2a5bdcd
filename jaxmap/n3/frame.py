"""One frame of the N3 map: the compiled frame program and its host-side driver.

    state, frame_stats, train_stats = step(static, state, scan)   # integrate + train, one jit
    ... = step_raw(static, state, raw_scan, rows)      # the same from a raw scan (preprocess.device)
    state, fs, ts, passes = run_frame(static, state, scan, headroom, seed=..., feature_std=...)

`step` is `integrate` and `train` in one compiled program with the state donated, so every table is
updated in place. When `FrameStats.ok` is False the frame did not fit: `train` did nothing and the
PRNG key did not advance, so the host grows what the stats name (`grow_for`, outside jit) and calls
`step` again with the same scan, with the same result as if the capacity had been there from the
start. `run_frame` does that loop, with one compiled program per shape (`compiled_step`, a small
least-recently-used cache).
"""
from __future__ import annotations

import collections
import functools
import logging
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap import compile_cache, hostmem
from jaxmap.grid import hashing
from jaxmap.grid.features import init_feature_rows
from jaxmap.n3 import evidence as n3evidence
from jaxmap.n3 import pool, window
from jaxmap.n3.integrate import FrameStats, integrate
from jaxmap.n3.scan_batch import RawScan, ScanBatch, prepare_scan
from jaxmap.n3.state import Capacities, N3State, N3Static
from jaxmap.n3.train import train
from jaxmap.sizes import bucket_for, pow2

log = logging.getLogger("jaxmap")


@functools.partial(jax.jit, static_argnums=0, donate_argnums=1)
def step(static: N3Static, state: N3State, scan: ScanBatch):
    """integrate + train of one frame, one compiled program, the state donated (updated in place).
    Returns (state, FrameStats, TrainStats); when `FrameStats.ok` is False nothing was trained and
    the key did not advance: grow (`grow_for`) and call again with the same scan."""
    key, k_sample, k_train = jax.random.split(state.key, 3)
    state, fstats = integrate(static, state, scan, k_sample)
    state, tstats = train(static, state, k_train, active=fstats.ok)
    return state.replace(key=jnp.where(fstats.ok, key, state.key)), fstats, tstats


@functools.partial(jax.jit, static_argnums=(0, 3), donate_argnums=1)
def step_raw(static: N3Static, state: N3State, raw: RawScan, rows: int):
    """`step` of a raw scan: preprocessing, integrate and train in one compiled program. When the
    preprocessed scan has more points than `rows`, nothing is stored or trained (`scan_overflow`)."""
    scan, kept, overflow = prepare_scan(static, raw, rows)
    key, k_sample, k_train = jax.random.split(state.key, 3)
    state, fstats = integrate(static, state, scan, k_sample, fits=~overflow)
    state, tstats = train(static, state, k_train, active=fstats.ok)
    fstats = fstats._replace(scan_points=kept)
    return state.replace(key=jnp.where(fstats.ok, key, state.key)), fstats, tstats


# ---------------------------------------------------------------------------------------------
# growth (host side, outside jit)
# ---------------------------------------------------------------------------------------------


def grow_for(static: N3Static, state: N3State, stats: FrameStats, seed: int, feature_std: float,
             headroom: dict) -> N3State:
    """Grow (doubling) whatever `stats` says is full or will be within a frame or two.

    headroom: host-side maxima seen so far ({"voxels", "feature_rows", "blocks"} per pass), so that
    growth happens between frames, not as a failed pass. Returns the state unchanged when nothing
    needs to grow. Every growth is logged; it changes array shapes, so the next `step` compiles.
    """
    caps = Capacities.of(state)
    voxels, rows = int(stats.voxels), int(stats.feature_rows)
    v_need = voxels + 2 * max(headroom.get("voxels", 0), static.new_voxels_per_pass // 4)
    c_need = rows + 2 * max(headroom.get("feature_rows", 0), static.new_voxels_per_pass // 2)
    v_rows, r_rows = caps.voxel_rows, caps.feature_rows
    while v_need > v_rows or (bool(stats.voxel_overflow) and v_rows == caps.voxel_rows):
        v_rows *= 2
    while c_need > r_rows or (bool(stats.corner_overflow) and r_rows == caps.feature_rows):
        r_rows *= 2
    v_slots = max(caps.voxel_slots, pow2(v_rows / static.max_load))
    c_slots = max(caps.corner_slots, pow2(r_rows / static.max_load))
    if static.uses_pool:
        need = int(stats.blocks_needed) + 2 * max(int(stats.blocks_needed) - int(stats.store_pairs), 0)
        cap = caps.pool_pairs
        while need > cap:
            cap *= 2
        if cap != caps.pool_pairs:
            log.info("growing the pair pool %d -> %d pairs", caps.pool_pairs, cap)
            state = state.replace(pool=pool.grow(state.pool, cap))
        return state
    blocks = caps.store_blocks
    used = caps.store_blocks - int(stats.blocks_free) + int(stats.blocks_needed)
    b_need = used + headroom.get("blocks", 0)
    while b_need > blocks or (bool(stats.store_overflow) and blocks == caps.store_blocks):
        blocks *= 2
    if v_rows != caps.voxel_rows:
        log.info("growing the voxel table %d -> %d voxels (%d in use)", caps.voxel_rows, v_rows, voxels)
        state = state.replace(
            voxels=hashing.grow(state.voxels, v_slots) if v_slots != caps.voxel_slots else state.voxels,
            voxel_coord=_pad_rows(state.voxel_coord, v_rows, 0),
            voxel_corner_rows=_pad_rows(state.voxel_corner_rows, v_rows, -1),
            store=window.grow(state.store, n_voxel_rows=v_rows),
            evidence=n3evidence.grow(state.evidence, v_rows) if state.evidence is not None else None,
        )
    if r_rows != caps.feature_rows:
        log.info("growing the feature table %d -> %d rows (%d in use)", caps.feature_rows, r_rows, rows)
        extra = init_feature_rows(seed, caps.feature_rows, r_rows - caps.feature_rows, static.feature_dim, feature_std)
        o = state.feature_opt
        state = state.replace(
            corners=hashing.grow(state.corners, c_slots) if c_slots != caps.corner_slots else state.corners,
            feature_table=jnp.concatenate([state.feature_table, extra]),
            feature_opt=o._replace(count=_pad_rows(o.count, r_rows, 0), moments=_pad_rows(o.moments, r_rows, 0.0)),
        )
    if blocks != caps.store_blocks:
        log.info("growing the pair store %d -> %d blocks", caps.store_blocks, blocks)
        state = state.replace(store=window.grow(state.store, n_slots=blocks))
    return state


def _pad_rows(x: jax.Array, n: int, fill) -> jax.Array:
    if x.shape[0] >= n:
        return x
    return jnp.concatenate([x, jnp.full((n - x.shape[0],) + x.shape[1:], fill, x.dtype)])


frames_held_jit = jax.jit(window.frames_held_fraction, static_argnums=3)


def store_bytes(store) -> int:
    """Bytes of the arrays of a pair store or pool (the training pairs' memory)."""
    return int(sum(np.prod(x.shape) * x.dtype.itemsize for x in jax.tree_util.tree_leaves(store)))


# ---------------------------------------------------------------------------------------------
# one frame on the host: compile once per shape, retry passes, plan growth
# ---------------------------------------------------------------------------------------------

# (static, capacities, scan bucket, preprocessed rows) -> compiled `step` / `step_raw`, least recently
# used first. Bounded: an XLA:CPU frame program keeps its machine code in ~2,000 memory maps, a Linux
# process may hold 65,530 (vm.max_map_count), and a process that maps many times (a notebook, the test
# suite) aborted inside XLA once an unbounded cache had kept every program it ever compiled. Capacities
# only grow during a drive, so a drive never returns to an evicted key.
EXECUTABLES: collections.OrderedDict = collections.OrderedDict()
EXECUTABLES_KEPT = 4
COMPILE_SECONDS: list = []  # seconds of every compile of `step` in this process (benchmarks read it)


def compiles_since(n: int) -> dict:
    """`{"compile_s", "compiles"}` of the frame program's compiles after the first `n` of this process
    (`n = len(COMPILE_SECONDS)` taken when a run starts): what a run's timing.json reports."""
    return {"compile_s": float(sum(COMPILE_SECONDS[n:])), "compiles": len(COMPILE_SECONDS) - n}


def compiled_step(static: N3Static, state: N3State, batch, rows: int = 0):
    """The compiled `step` (a ScanBatch) or `step_raw` (a RawScan, `rows` preprocessed rows) for these
    shapes, compiled (and logged) on first use. Compiling ahead of time, instead of on the first
    call, lets the log say what the wait is before it starts. Returns fn(state, batch)."""
    raw = isinstance(batch, RawScan)
    key = (static, Capacities.of(state), batch.points.shape[0], rows if raw else 0)
    fn = EXECUTABLES.get(key)
    if fn is not None:
        EXECUTABLES.move_to_end(key)
    else:
        est = compile_cache.estimate("n3_step")
        log.info("compiling the mapper (one time for these table sizes%s)",
                 f", up to about {est:.0f} s" if est else ", usually 5-30 s the first time on a machine")
        t0 = time.perf_counter()
        fn = (step_raw.lower(static, state, batch, rows) if raw else step.lower(static, state, batch)).compile()
        secs = time.perf_counter() - t0
        hostmem.trim()  # the compiler's ~1 GB of freed heap back to the system, not held for the drive
        compile_cache.record("n3_step", secs)
        COMPILE_SECONDS.append(secs)
        log.info("compiled in %.1f s", secs)
        EXECUTABLES[key] = fn
        while len(EXECUTABLES) > EXECUTABLES_KEPT:
            EXECUTABLES.popitem(last=False)
    return fn


def forget_compiled() -> None:
    """Drop the compiled frame programs this process keeps (their memory maps go with them)."""
    EXECUTABLES.clear()


def run_frame(static: N3Static, state: N3State, batch: ScanBatch, headroom: dict, *, seed: int,
              feature_std: float):
    """Integrate and train one frame, growing capacities as its stats ask (host side).

    Returns (state, FrameStats, TrainStats, passes) as numpy values; `headroom` (the largest
    per-pass allocations seen) is updated in place and used to grow before a table is full. A
    RawScan is preprocessed into `headroom["scan_rows"]` rows, grown when its points do not fit.
    """
    passes = 0
    while True:
        rows = headroom.get("scan_rows", 0)
        state, fs, ts = compiled_step(static, state, batch, rows)(state, batch)
        fs, ts = jax.device_get((fs, ts))  # the one host sync of a pass
        passes += 1
        if bool(fs.scan_overflow):
            headroom["scan_rows"] = bucket_for(int(fs.scan_points))
            log.info("growing the preprocessed scan %d -> %d rows", rows, headroom["scan_rows"])
            continue
        if int(fs.voxels) > 2 * int(fs.new_voxels):  # not the first frames, where everything is new
            headroom["voxels"] = max(headroom.get("voxels", 0), int(fs.new_voxels))
            headroom["feature_rows"] = max(headroom.get("feature_rows", 0), int(fs.new_feature_rows))
            headroom["blocks"] = max(headroom.get("blocks", 0), int(fs.blocks_needed))
        state = grow_for(static, state, fs, seed, feature_std, headroom)
        if bool(fs.ok):
            return state, fs, ts, passes
        if passes > 64:
            raise RuntimeError(f"frame did not fit after {passes} passes ({fs}); please report this bug")
