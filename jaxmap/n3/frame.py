"""One frame of the N3 map: the compiled frame program and its host-side driver.

    state, frame_stats, train_stats = step(static, state, scan)   # integrate + train, one jit
    ... = step_raw(static, state, raw_scan, rows)      # the same from a raw scan (preprocess.device)
    ... = step_after(static, state, scan, prev_ok)     # either, if the frame before fit (what the host runs)
    pipe = FramePipeline(static, state, headroom, seed=..., feature_std=...)   # frames dispatched ahead
    state, fs, ts, passes = run_frame(static, state, scan, headroom, seed=..., feature_std=...)

`step` is `integrate` and `train` in one compiled program with the state donated, so every table is
updated in place. When `FrameStats.ok` is False the frame did not fit: `train` did nothing and the
PRNG key did not advance, so the host grows what the stats name (`grow_for`, outside jit) and calls
`step` again with the same scan, with the same result as if the capacity had been there from the
start. `FramePipeline` does that loop one frame behind the device (the next frame is dispatched
before this one's stats are read, and does nothing if this one did not fit), with one compiled
program per shape (`compiled_step`, a small least-recently-used cache); `run_frame` is one frame of it.

Process state (the rest of the module is functions and per-run objects): `PROGRAMS`, the compiled frame
programs and the seconds their compiles took (a `ProgramCache`; `forget_compiled` empties it), and
`_STATS_READER`, the one thread that reads dispatched frames' stats.
"""
from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import functools
import logging
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap import compile_cache, hostmem
from jaxmap.grid import hashing
from jaxmap.grid.features import init_feature_rows
from jaxmap.n3 import evidence as n3evidence
from jaxmap.n3 import pool, window
from jaxmap.n3.integrate import FrameStats, integrate
from jaxmap.n3.scan_batch import RawScan, ScanBatch, preprocess_raw
from jaxmap.n3.state import Capacities, N3State, N3Static
from jaxmap.n3.train import TrainStats, train
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
    scan, kept, overflow = jax.named_call(preprocess_raw, name="preprocess")(static, raw, rows)
    key, k_sample, k_train = jax.random.split(state.key, 3)
    state, fstats = integrate(static, state, scan, k_sample, fits=~overflow)
    state, tstats = train(static, state, k_train, active=fstats.ok)
    fstats = fstats._replace(scan_points=kept)
    return state.replace(key=jnp.where(fstats.ok, key, state.key)), fstats, tstats


@functools.partial(jax.jit, static_argnums=(0, 4), donate_argnums=1)
def step_after(static: N3Static, state: N3State, batch, prev_ok, rows: int = 0):
    """The frame program the host runs: `step` of a ScanBatch (or `step_raw` of a RawScan into `rows`
    rows) when the frame dispatched before it fit (prev_ok: [] bool), else nothing at all: the state
    comes back bit for bit as it went in, the stats say not ok and hold zeros. The host can so dispatch
    frame i + 1 before it reads frame i's stats (`FramePipeline`): when i did not fit, i + 1 did nothing,
    and the host grows, runs i again, then i + 1."""
    def run(st):
        return step_raw(static, st, batch, rows) if isinstance(batch, RawScan) else step(static, st, batch)

    shapes = jax.eval_shape(run, state)

    def skip(st):
        fs, ts = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes[1:])
        return st, fs, ts

    return jax.lax.cond(prev_ok, run, skip, state)


# ---------------------------------------------------------------------------------------------
# growth (host side, outside jit)
# ---------------------------------------------------------------------------------------------


GROW_TOGETHER = 0.6  # a table this full grows when another one must (one compile for both)


def grow_together(caps: Capacities, sizes: tuple, used: tuple) -> tuple:
    """(voxel rows, feature rows, store blocks) to grow to: `sizes`, those each table needs, and when any
    of them grows, also double those of the others that are more than GROW_TOGETHER full (`used`: their
    rows / blocks in use). Every growth compiles the frame program again (15-25 s on a 2-core CPU): a
    table that would soon grow on its own grows with the one that must, one compile for both."""
    now = (caps.voxel_rows, caps.feature_rows, caps.store_blocks)
    if tuple(sizes) == now:
        return now
    return tuple(max(size, 2 * cap) if n > GROW_TOGETHER * cap else size for size, cap, n in zip(sizes, now, used))


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
    v_rows, r_rows, blocks = grow_together(caps, (v_rows, r_rows, blocks), (voxels, rows, used))
    v_slots = max(caps.voxel_slots, pow2(v_rows / static.max_load))
    c_slots = max(caps.corner_slots, pow2(r_rows / static.max_load))
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
# frames on the host: compile once per shape, dispatch ahead, read the stats late, retry, grow
# ---------------------------------------------------------------------------------------------

class ProgramCache:
    """The compiled frame programs (`step_after`) of this process and the seconds each compile took.

    Keys: (static, capacities, scan bucket, preprocessed rows); `get` of a key makes it the newest, `put`
    drops the least recently used beyond `kept`. Bounded: an XLA:CPU frame program keeps its machine code
    in ~2,000 memory maps, a Linux process may hold 65,530 (vm.max_map_count), and a process that maps
    many times (a notebook, the test suite) aborted inside XLA once an unbounded cache had kept every
    program it ever compiled. Capacities only grow during a drive, so a drive never returns to an
    evicted key. `compile_seconds` is every compile of this process, in order (never dropped): a run
    takes `compiles()` when it starts and reports `compiles_since` that mark.
    """

    def __init__(self, kept: int = 4):
        self.kept = kept
        self._programs: collections.OrderedDict = collections.OrderedDict()
        self.compile_seconds: list[float] = []

    def get(self, key):
        """The program of `key` (made the newest), or None."""
        fn = self._programs.get(key)
        if fn is not None:
            self._programs.move_to_end(key)
        return fn

    def put(self, key, fn, seconds: float) -> None:
        """Keep `fn`, compiled for `key` in `seconds`, as the newest; drop the oldest beyond `kept`."""
        self.compile_seconds.append(seconds)
        self._programs[key] = fn
        while len(self._programs) > self.kept:
            self._programs.popitem(last=False)

    def keys(self) -> list:
        """The keys of the programs kept, least recently used first."""
        return list(self._programs)

    def programs(self) -> list:
        """The programs kept, least recently used first."""
        return list(self._programs.values())

    def newest(self) -> tuple:
        """(key, program) of the program used last."""
        return next(reversed(self._programs.items()))

    def compiles(self) -> int:
        """How many frame programs this process has compiled."""
        return len(self.compile_seconds)

    def compiles_since(self, n: int) -> dict:
        """`{"compile_s", "compiles"}` of the compiles after the first `n` (`n = compiles()` taken when a run
        starts): what a run's timing.json reports."""
        return {"compile_s": float(sum(self.compile_seconds[n:])), "compiles": len(self.compile_seconds) - n}

    def clear(self) -> None:
        """Drop the programs kept (their memory maps go with them); the compile seconds stay."""
        self._programs.clear()


# This process's frame programs: the one mutable cache of this module (`compiled_step` fills it).
PROGRAMS = ProgramCache()
_PREV_OK = jax.ShapeDtypeStruct((), jnp.bool_)


def compiled_step(static: N3Static, state: N3State, batch, rows: int = 0):
    """The compiled frame program (`step_after`) of a ScanBatch, or of a RawScan preprocessed into `rows`
    rows, for these shapes, compiled (and logged) on first use and kept in `PROGRAMS`. Compiling ahead of
    time, instead of on the first call, lets the log say what the wait is before it starts. Returns
    fn(state, batch, prev_ok)."""
    raw = isinstance(batch, RawScan)
    key = (static, Capacities.of(state), batch.points.shape[0], rows if raw else 0)
    fn = PROGRAMS.get(key)
    if fn is None:
        est = compile_cache.estimate("n3_step")
        log.info("compiling the mapper (one time for these table sizes%s)",
                 f", up to about {est:.0f} s" if est else ", usually 5-30 s the first time on a machine")
        t0 = time.perf_counter()
        fn = step_after.lower(static, state, batch, _PREV_OK, rows if raw else 0).compile()
        secs = time.perf_counter() - t0
        hostmem.trim()  # the compiler's ~1 GB of freed heap back to the system, not held for the drive
        compile_cache.record("n3_step", secs)
        log.info("compiled in %.1f s", secs)
        PROGRAMS.put(key, fn, secs)
    return fn


def forget_compiled() -> None:
    """Drop the compiled frame programs this process keeps (their memory maps go with them)."""
    PROGRAMS.clear()


class FrameDone(NamedTuple):
    """A frame whose statistics the host has read (`FramePipeline.done`)."""

    tag: Any              # what `submit` was given with the frame
    stats: FrameStats     # numpy values, of the pass that fit
    train: TrainStats
    passes: int           # frame programs run for it (1 unless it had to grow)
    dispatch_s: float     # host time handing its programs to the device
    program_s: float      # its programs on the device: from the later of its dispatch and the end of the
    #                       frame before, to the moment its stats were ready
    stats_s: float        # time the host waited for its stats


@dataclasses.dataclass
class _Dispatched:
    batch: Any
    tag: Any
    out: tuple                                  # (FrameStats, TrainStats) on the device
    ready: concurrent.futures.Future            # -> ((FrameStats, TrainStats) as numpy, time they were ready)
    dispatched_at: float
    dispatch_s: float


# One thread reads every dispatched frame's stats as soon as the device has them, so the time each frame
# program ended is known however late the host looks (and the device->host copy is off the main thread).
_STATS_READER = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="jaxmap-stats")


def _read_when_ready(out):
    values = jax.device_get(out)
    return values, time.perf_counter()


class FramePipeline:
    """The host side of the frame programs: frames dispatched ahead of their statistics.

        pipe = FramePipeline(static, state, headroom, seed=..., feature_std=..., lag=1)
        pipe.submit(batch, tag)      # dispatches (asynchronously) and returns
        for d in pipe.done(): ...    # FrameDone of the frames whose stats are read, in order
        pipe.drain(); pipe.state     # every submitted frame in; the state after them

    Frame i's stats are read once frame i + `lag` is dispatched, so the device runs one frame program
    after the other while the host prepares, dispatches and bookkeeps (lag 0: each frame waits for its
    own stats, as `run_frame`). Each program runs only if the one before it fit (`step_after`); when
    the host reads that frame i did not fit, the frames after it did nothing: it grows what i's stats
    name (`grow_for`), runs i again until it fits, then dispatches the later frames again. Growth
    planned from a frame's stats (`headroom`: the largest per-pass allocations seen) reaches the state
    `lag` frames later; it only ever adds room, and the map is bit for bit the one of lag 0 (tested).
    `headroom` is updated in place; `pipe.state` is the state after every dispatched frame (read it
    after `drain()` to see them all in).
    """

    def __init__(self, static: N3Static, state: N3State, headroom: dict, *, seed: int, feature_std: float,
                 lag: int = 1):
        self.static, self.state, self.headroom = static, state, headroom
        self.seed, self.feature_std, self.lag = seed, feature_std, lag
        self._pending: collections.deque[_Dispatched] = collections.deque()
        self._done: list[FrameDone] = []
        self._last_ready = 0.0   # when the stats of the last frame read were ready (the device's end of it)

    def submit(self, batch, tag=None) -> None:
        """Dispatch the frame program of `batch` (a ScanBatch or RawScan, on the device or the host) after
        the frames submitted before it; read the stats of those more than `lag` frames back."""
        prev_ok = self._pending[-1].out[0].ok if self._pending else np.True_
        self._pending.append(self._dispatch(batch, tag, prev_ok))
        while len(self._pending) > self.lag:
            self._settle_oldest()

    def drain(self) -> None:
        """Read the stats of every submitted frame (retrying those that did not fit)."""
        while self._pending:
            self._settle_oldest()

    def done(self) -> list[FrameDone]:
        """The frames whose stats were read since the last call, in the order submitted."""
        out, self._done = self._done, []
        return out

    def _dispatch(self, batch, tag, prev_ok) -> _Dispatched:
        rows = self.headroom.get("scan_rows", 0)
        fn = compiled_step(self.static, self.state, batch, rows)
        t0 = time.perf_counter()
        self.state, fs, ts = fn(self.state, batch, prev_ok)
        t1 = time.perf_counter()
        return _Dispatched(batch, tag, (fs, ts), _STATS_READER.submit(_read_when_ready, (fs, ts)), t1, t1 - t0)

    def _settle_oldest(self) -> None:
        d = self._pending.popleft()
        passes, dispatch_s, program_s, stats_s = 0, 0.0, 0.0, 0.0
        while True:
            t0 = time.perf_counter()
            (fs, ts), ready_at = d.ready.result()
            stats_s += time.perf_counter() - t0
            program_s += max(ready_at - max(d.dispatched_at, self._last_ready), 0.0)
            self._last_ready = ready_at
            dispatch_s += d.dispatch_s
            passes += 1
            if self._plan(fs):
                break
            if passes > 64:
                raise RuntimeError(f"frame did not fit after {passes} passes ({fs}); please report this bug")
            # The frames dispatched after it did nothing (`step_after`): it goes again on its own first.
            d = self._dispatch(d.batch, d.tag, np.True_)
        if passes > 1 and self._pending:  # ... and then they go again
            later = list(self._pending)
            self._pending.clear()
            prev_ok = np.True_
            for x in later:
                self._pending.append(self._dispatch(x.batch, x.tag, prev_ok))
                prev_ok = self._pending[-1].out[0].ok
        self._done.append(FrameDone(d.tag, fs, ts, passes, dispatch_s, program_s, stats_s))

    def _plan(self, fs: FrameStats) -> bool:
        """Headroom and growth after one pass's stats; whether the frame fit."""
        h = self.headroom
        if bool(fs.scan_overflow):
            rows = h.get("scan_rows", 0)
            h["scan_rows"] = bucket_for(int(fs.scan_points))
            log.info("growing the preprocessed scan %d -> %d rows", rows, h["scan_rows"])
            return False
        if int(fs.voxels) > 2 * int(fs.new_voxels):  # not the first frames, where everything is new
            h["voxels"] = max(h.get("voxels", 0), int(fs.new_voxels))
            h["feature_rows"] = max(h.get("feature_rows", 0), int(fs.new_feature_rows))
            h["blocks"] = max(h.get("blocks", 0), int(fs.blocks_needed))
        self.state = grow_for(self.static, self.state, fs, self.seed, self.feature_std, h)
        return bool(fs.ok)


def run_frame(static: N3Static, state: N3State, batch: ScanBatch, headroom: dict, *, seed: int,
              feature_std: float):
    """Integrate and train one frame, growing capacities as its stats ask (host side): a
    `FramePipeline` of lag 0. Returns (state, FrameStats, TrainStats, passes) as numpy values; `headroom`
    (the largest per-pass allocations seen) is updated in place and used to grow before a table is
    full. A RawScan is preprocessed into `headroom["scan_rows"]` rows, grown when its points do not fit.
    """
    pipe = FramePipeline(static, state, headroom, seed=seed, feature_std=feature_std, lag=0)
    pipe.submit(batch)
    (d,) = pipe.done()
    return pipe.state, d.stats, d.train, d.passes
