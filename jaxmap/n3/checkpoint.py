"""Checkpoints of an N3 map: the `n3state.N3State` in a compact form, plus the config that made it.

The state's arrays are sized for growth (hash tables at most half full, feature rows and store
blocks beyond what is used), so the checkpoint keeps only what is in use and `load_state`
rebuilds the rest exactly:
  - hash tables as their keys in row order (re-inserting them in that order gives every key its
    row again; slots may differ from the original's, which no lookup or later insert can tell);
  - feature rows, their Adam moments and the voxel arrays up to their counts (unused feature rows
    get back their deterministic initial values);
  - the pair store's occupied blocks with their slot numbers.
A restored state equals the saved one leaf for leaf but for those slots (tested). `save_state` writes
one array at a time, on the CPU straight from the state's buffers: the save holds no copy of the map
(orbax, before, held 2.5 copies: +2.6 GB at the end of the long drive). `save_state_async` copies the
state on the device (asynchronously, before the next frame program takes its buffers) and writes that
copy in a background thread, so mapping goes on at once while it is written; the next save waits
for the previous one.

meta.json holds the config, the capacities and the per-frame timings so far; `arrays/` the tree, one
`.npy` per leaf (`state/`, an orbax tree, in earlier checkpoints: still read).
Each save is a new checkpoint `<frames mapped>/` of the checkpoint directory, checksummed, and the
last two are kept (`jaxmap.checkpoint`): `load_state` falls back to the older one when the newer is damaged.
"""
from __future__ import annotations

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxmap.checkpoint import SAVES, host_array, load, named_leaves, read_tree, save_arrays
from jaxmap.config import ConfigError, MapConfig, from_dict, to_dict
from jaxmap.errors import CheckpointError
from jaxmap.grid import hashing
from jaxmap.n3 import state as n3state

_STORE_BLOCK_FIELDS = ("pairs", "surface", "frame", "count", "received", "frames_seen", "voxel_of_slot", "coord",
                       "last_hit")


def _rows(x, n: int, copy: bool = True) -> np.ndarray:
    """The first n rows, padded to at least one (orbax stored no zero-size arrays; kept for one format)."""
    return host_array(x, slice(0, max(n, 1)), copy) if len(x) else np.zeros((1,) + x.shape[1:], x.dtype)


def _compact_fns(state: n3state.N3State, copy: bool) -> dict:
    """The part of the state in use as nested dicts of functions that each return one host array
    (`host_array`): the tables are fetched when their function is called, one at a time."""
    nv, nr = (int(x) for x in jax.device_get((state.voxels.count, state.corners.count)))
    st = state.store
    used = np.nonzero(np.asarray(jax.device_get(st.voxel_of_slot)) >= 0)[0].astype(np.int32)
    d = state.decoder_opt
    later = functools.partial
    rows = functools.partial(_rows, copy=copy)

    def value(x):  # a scalar, the decoder: small, always an own copy
        return later(host_array, x)

    def keys(table, n):
        return lambda: _rows(hashing.entries(table)[0], n, copy=False)  # entries are new arrays: no copy needed

    tree = {
        "n": {"voxels": later(np.int32, nv), "rows": later(np.int32, nr), "blocks": later(np.int32, len(used))},
        "voxel_keys": keys(state.voxels, nv), "corner_keys": keys(state.corners, nr),
        "voxel_coord": later(rows, state.voxel_coord, nv),
        "voxel_corner_rows": later(rows, state.voxel_corner_rows, nv),
        "voxels_with_corners": value(state.voxels_with_corners),
        "feature_table": later(rows, state.feature_table, nr),
        "feature_count": later(rows, state.feature_opt.count, nr),   # per-row Adam steps
        "feature_moments": later(rows, state.feature_opt.moments, nr),
        "decoder": jax.tree_util.tree_map(value, state.decoder),
        "decoder_opt": {"count": value(d.count), "mu": jax.tree_util.tree_map(value, d.mu),
                        "nu": jax.tree_util.tree_map(value, d.nu)},
        "store_slots": later(_rows, used, len(used), copy=False),  # `used` is this function's own array
        "store": {k: (later(rows, getattr(st, k), 0) if len(used) == 0 else later(host_array, getattr(st, k), used))
                  for k in _STORE_BLOCK_FIELDS},
        "slot_of_voxel": later(rows, st.slot_of_voxel, nv), "window_ids": value(st.window_ids),
        "window_n": value(st.window_n), "origin_vox": value(state.origin_vox), "key": value(state.key),
        "frame": value(state.frame),
        "hyper": {k: value(getattr(state.hyper, k)) for k in ("lr", "beta", "weight_e", "iters")},
    }
    if state.evidence is not None:  # free-space evidence, per voxel row
        tree["evidence"] = {"free_run": later(rows, state.evidence.free_run, nv),
                            "raised": later(rows, state.evidence.raised, nv)}
    if state.pool is not None:  # the replay / keyframe ablations: the pool's pairs in use
        npool = int(state.pool.n)
        tree["pool"] = {k: later(rows, getattr(state.pool, k), npool) for k in ("pairs", "surface", "frame", "voxel_row")}
        tree["n"]["pool"] = later(np.int32, npool)
    return tree


def compact(state: n3state.N3State) -> dict:
    """The part of the state in use, as nested dicts of host numpy arrays (own copies; counts under "n")."""
    return jax.tree_util.tree_map(lambda f: f(), _compact_fns(state, copy=True), is_leaf=callable)


def compact_leaves(state: n3state.N3State) -> list[tuple[str, callable]]:
    """(name, fn) of every leaf of `compact(state)`, "a/b" naming tree["a"]["b"]; `fn()` fetches the
    leaf then, as a view of the state's buffer where it can (write it before the state changes)."""
    return named_leaves(_compact_fns(state, copy=False))


def expand(static: n3state.N3Static, cfg: MapConfig, caps: n3state.Capacities, c: dict) -> n3state.N3State:
    """Inverse of `compact` (host side): the state at the saved capacities."""
    state = n3state.init_state(static, cfg, caps)
    nv, nr, nb = int(c["n"]["voxels"]), int(c["n"]["rows"]), int(c["n"]["blocks"])

    # Every size here is the checkpoint's own (a map of submaps restores one per submap): the keys are padded
    # to a power of two and the arrays filled on the host, so no program is compiled per count.
    def table(empty, keys):
        n = len(keys)
        if n == 0:
            return empty
        padded = np.zeros((1 << (n - 1).bit_length(), keys.shape[1]), np.int32)
        padded[:n] = keys
        t, rows, over = hashing.insert(empty, jnp.asarray(padded), jnp.asarray(np.arange(len(padded)) < n))
        if bool(over) or not np.array_equal(np.asarray(rows)[:n], np.arange(n)):
            raise RuntimeError("checkpoint: a hash table did not rebuild to its saved rows; please report this bug")
        return t

    st = state.store
    slots = np.asarray(c["store_slots"][:nb])
    saved = dict(c["store"])
    if "last_hit" not in saved:  # a checkpoint from before free-space carving: every block counts as just hit
        saved["last_hit"] = np.full((max(nb, 1),), int(np.asarray(c["frame"])) - 1, np.int32)
    blocks = {k: put_at(getattr(st, k), slots, saved[k][:nb]) for k in _STORE_BLOCK_FIELDS}
    store = st.replace(**blocks, slot_of_voxel=put(st.slot_of_voxel, c["slot_of_voxel"], nv),
                       window_ids=jnp.asarray(c["window_ids"]), window_n=jnp.asarray(c["window_n"]))
    as_j = functools.partial(jax.tree_util.tree_map, jnp.asarray)
    d = c["decoder_opt"]
    return state.replace(
        voxels=table(state.voxels, c["voxel_keys"][:nv]), corners=table(state.corners, c["corner_keys"][:nr]),
        voxel_coord=put(state.voxel_coord, c["voxel_coord"], nv),
        voxel_corner_rows=put(state.voxel_corner_rows, c["voxel_corner_rows"], nv),
        voxels_with_corners=jnp.asarray(c["voxels_with_corners"]),
        feature_table=put(state.feature_table, c["feature_table"], nr),
        feature_opt=state.feature_opt._replace(count=put(state.feature_opt.count, c["feature_count"], nr),
                                               moments=put(state.feature_opt.moments, c["feature_moments"], nr)),
        decoder=as_j(c["decoder"]),
        decoder_opt=optax.ScaleByAdamState(count=jnp.asarray(d["count"]), mu=as_j(d["mu"]), nu=as_j(d["nu"])),
        store=store, pool=_expand_pool(state.pool, c), evidence=_expand_evidence(state.evidence, c, nv),
        origin_vox=jnp.asarray(c["origin_vox"]),
        key=jnp.asarray(c["key"]),
        frame=jnp.asarray(c["frame"]),
        # (a checkpoint from before `iters` was in Hyper: the config's, which the empty state holds)
        hyper=state.hyper.replace(**as_j(c["hyper"])),
    )


def put(arr, vals, n: int):
    """arr [M, ...] (a device array) with its first n rows set to vals[:n], filled on the host."""
    return put_at(arr, slice(0, n), vals[:n]) if n else arr


def put_at(arr, rows, vals):
    """arr [M, ...] with rows (host ints [K], or a slice of K rows) set to vals [K, ...], filled on the host
    (an eager scatter would compile a program for every K)."""
    host = np.array(arr)
    host[rows] = np.asarray(vals, host.dtype)
    return jnp.asarray(host)


def _expand_evidence(empty, c: dict, nv: int):
    """The free-space evidence back (None when off; a checkpoint from before it: none seen yet)."""
    if empty is None or "evidence" not in c or nv == 0:
        return empty
    e = c["evidence"]
    return empty.replace(free_run=put(empty.free_run, e["free_run"], nv), raised=put(empty.raised, e["raised"], nv))


def _expand_pool(empty, c: dict):
    """The pool of a replay / keyframe checkpoint back at its saved capacity (None when not used)."""
    if empty is None:
        return None
    n = int(c["n"].get("pool", 0)) if "pool" in c else 0
    if n == 0:
        return empty
    return empty.replace(**{k: put(getattr(empty, k), c["pool"][k], n) for k in ("pairs", "surface", "frame", "voxel_row")},
                         n=jnp.int32(n))


def meta_of(cfg: MapConfig, state: n3state.N3State, timings: list, extra: dict | None = None) -> dict:
    """meta.json of a checkpoint: the config, frames mapped, layout, capacities and timings so far, and
    `extra` (a map of submaps: its index, "submaps")."""
    return {"config": to_dict(cfg), "frame": int(state.frame), "layout": "compact-1",
            "capacity": dataclasses.asdict(n3state.Capacities.of(state)), "timings": list(timings), **(extra or {})}


def save_state(path: str, cfg: MapConfig, state: n3state.N3State, timings: list, extra: dict | None = None,
               step: int | None = None) -> None:
    """Write the map as checkpoint `<step>` of directory `path` (default: the state's frames mapped),
    atomically (the two newest are kept), one array at a time: on the CPU straight from the state's
    buffers, with no copy. A map of submaps passes its frames in all submaps: the steps must grow, or the
    save prunes the checkpoints after it (`jaxmap.checkpoint.save_arrays`)."""
    wait_for_saves()
    _write(path, cfg, state, timings, extra, step)


def _write(path: str, cfg: MapConfig, state: n3state.N3State, timings: list, extra: dict | None = None,
           step: int | None = None) -> None:
    save_arrays(path, compact_leaves(state), meta_of(cfg, state, timings, extra),
                step=int(state.frame) if step is None else int(step))


# A copy of the whole state on the device, one program (leaf by leaf, the copies compiled one small
# program per shape the first time: 3 s of the main thread at the first checkpoint of a city run).
_snapshot = jax.jit(lambda state: jax.tree_util.tree_map(jnp.copy, state))


def save_state_async(path: str, cfg: MapConfig, state: n3state.N3State, timings: list, copy: bool = True,
                     extra: dict | None = None, step: int | None = None) -> None:
    """Like `save_state`, but written in a background thread (`SAVES`) from a copy of the state made on the
    device (`_snapshot`: asynchronous, in order before the next frame program, which donates the state's
    buffers), so the caller goes on at once; copy=False: from `state` itself, which nothing may change
    until it is written. Call `wait_for_saves()` before relying on the files."""
    wait_for_saves()
    snapshot, timings = _snapshot(state) if copy else state, list(timings)
    SAVES.start(lambda: _write(path, cfg, snapshot, timings, extra, step))


def saving() -> bool:
    """Is a background save still being written?"""
    return SAVES.busy()


def wait_for_saves() -> None:
    """Block until the background save (if any) is written; re-raise its error."""
    SAVES.wait()


def load_state(path: str) -> tuple[MapConfig, n3state.N3State, list]:
    """(config, state, timings) of the newest intact checkpoint in directory `path` (see `save_state`;
    `path` may also name one checkpoint `path/<step>`). Falls back to the older checkpoint with a
    warning when the newer is damaged; `jaxmap.errors.CheckpointError` when none is usable,
    `NoCheckpointError` when there is none."""
    wait_for_saves()
    return load(path, _build, "N3 map")


def load_state_meta(path: str) -> tuple[MapConfig, n3state.N3State, list, dict]:
    """`load_state`'s (config, state, timings) and the checkpoint's whole meta.json (a map of submaps
    keeps its index there)."""
    wait_for_saves()
    return load(path, lambda ckpt, meta: (*_build(ckpt, meta), meta), "N3 map")


def _build(ckpt: str, meta: dict) -> tuple[MapConfig, n3state.N3State, list]:
    """(config, state, timings) of one verified checkpoint directory; CheckpointError when unusable."""
    where = os.path.join(ckpt, "meta.json")
    try:
        cfg = from_dict(MapConfig, meta["config"], source=where)
        caps = n3state.Capacities(**meta["capacity"])
    except (KeyError, TypeError, ConfigError) as e:
        raise CheckpointError(f"{where}: not an N3 map checkpoint ({type(e).__name__}: {e})") from None
    static = n3state.N3Static.from_config(cfg)
    return cfg, expand(static, cfg, caps, read_tree(ckpt)), list(meta.get("timings", []))
