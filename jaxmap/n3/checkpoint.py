"""Checkpoints of an N3 map: the `core.N3State` in a compact form, plus the config that made it.

The state's arrays are sized for growth (hash tables at most half full, feature rows and store
blocks beyond what is used), so the checkpoint keeps only what is in use and `load_state`
rebuilds the rest exactly:
  - hash tables as their keys in row order (re-inserting them in that order gives every key its
    row again; slots may differ from the original's, which no lookup or later insert can tell);
  - feature rows, their Adam moments and the voxel arrays up to their counts (unused feature rows
    get back their deterministic initial values);
  - the pair store's occupied blocks with their slot numbers.
A restored state equals the saved one leaf for leaf but for those slots (tested). `save_state_async` copies the
compact tree to the host (one device->host copy) and writes it in a background thread, so mapping
goes on while orbax writes; the next save waits for the previous one.

meta.json holds the config, the capacities and the per-frame timings so far; `state/` the tree.
Each save is a new checkpoint `<frames mapped>/` of the checkpoint directory, checksummed, and the
last two are kept (`jaxmap.checkpoint`): `load_state` falls back to the older one when the newer is damaged.
"""
from __future__ import annotations

import dataclasses
import functools
import os
import threading

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.checkpoint import load, read_tree, save_tree
from jaxmap.config import ConfigError, MapConfig, from_dict, to_dict
from jaxmap.errors import CheckpointError
from jaxmap.grid import hashing
from jaxmap.n3 import core

_STORE_BLOCK_FIELDS = ("pairs", "surface", "frame", "count", "received", "frames_seen", "voxel_of_slot", "coord",
                       "last_hit")


def _rows(x, n: int) -> np.ndarray:
    """The first n rows, padded to at least one (orbax stores no zero-size arrays)."""
    x = np.asarray(x)
    return x[:max(n, 1)] if len(x) else np.zeros((1,) + x.shape[1:], x.dtype)


def compact(state: core.N3State) -> dict:
    """The part of the state in use, as nested dicts of host numpy arrays (counts under "n").

    Sliced and gathered on the device first, so only the used rows cross to the host (a full
    `device_get` would copy the whole capacity: hundreds of MB on the city).
    """
    nv, nr = (int(x) for x in jax.device_get((state.voxels.count, state.corners.count)))
    st = state.store
    used = np.nonzero(np.asarray(jax.device_get(st.voxel_of_slot)) >= 0)[0].astype(np.int32)
    used_j = jnp.asarray(used)
    vkeys, _ = hashing.entries(state.voxels)
    ckeys, _ = hashing.entries(state.corners)
    d = state.decoder_opt
    tree = {
        "n": {"voxels": np.int32(nv), "rows": np.int32(nr), "blocks": np.int32(len(used))},
        "voxel_keys": _rows(vkeys, nv), "corner_keys": _rows(ckeys, nr),
        "voxel_coord": _rows(state.voxel_coord[:max(nv, 1)], nv),
        "voxel_corner_rows": _rows(state.voxel_corner_rows[:max(nv, 1)], nv),
        "voxels_with_corners": state.voxels_with_corners,
        "feature_table": _rows(state.feature_table[:max(nr, 1)], nr),
        "feature_count": _rows(state.feature_opt.count[:max(nr, 1)], nr),   # per-row Adam steps
        "feature_moments": _rows(state.feature_opt.moments[:max(nr, 1)], nr),
        "decoder": state.decoder, "decoder_opt": {"count": d.count, "mu": d.mu, "nu": d.nu},
        "store_slots": _rows(used, len(used)),
        "store": {k: _rows(getattr(st, k)[used_j], len(used)) for k in _STORE_BLOCK_FIELDS},
        "slot_of_voxel": _rows(st.slot_of_voxel[:max(nv, 1)], nv), "window_ids": st.window_ids,
        "window_n": st.window_n, "origin_vox": state.origin_vox, "key": state.key, "frame": state.frame,
        "hyper": {"lr": state.hyper.lr, "beta": state.hyper.beta, "weight_e": state.hyper.weight_e},
    }
    if state.pool is not None:  # the replay / keyframe ablations: the pool's pairs in use
        npool = int(state.pool.n)
        tree["pool"] = {k: _rows(getattr(state.pool, k)[:max(npool, 1)], npool)
                        for k in ("pairs", "surface", "frame", "voxel_row")}
        tree["n"]["pool"] = np.int32(npool)
    # Own copies: on the CPU a device array may share its buffer with numpy, and the next frame's
    # donated step overwrites it while a background save is still writing.
    return jax.tree_util.tree_map(np.array, tree)


def expand(static: core.N3Static, cfg: MapConfig, caps: core.Capacities, c: dict) -> core.N3State:
    """Inverse of `compact` (host side): the state at the saved capacities."""
    import optax

    state = core.init_state(static, cfg, caps)
    nv, nr, nb = int(c["n"]["voxels"]), int(c["n"]["rows"]), int(c["n"]["blocks"])

    def table(empty, keys):
        if len(keys) == 0:
            return empty
        t, rows, over = hashing.insert(empty, jnp.asarray(keys))
        if bool(over) or not np.array_equal(np.asarray(rows), np.arange(len(keys))):
            raise RuntimeError("checkpoint: a hash table did not rebuild to its saved rows; please report this bug")
        return t

    def put(arr, vals, n):
        return arr.at[:n].set(jnp.asarray(vals[:n])) if n else arr

    st = state.store
    slots = jnp.asarray(c["store_slots"][:nb])
    saved = dict(c["store"])
    if "last_hit" not in saved:  # a checkpoint from before free-space carving: every block counts as just hit
        saved["last_hit"] = np.full((max(nb, 1),), int(np.asarray(c["frame"])) - 1, np.int32)
    blocks = {k: getattr(st, k).at[slots].set(jnp.asarray(saved[k][:nb])) for k in _STORE_BLOCK_FIELDS}
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
        store=store, pool=_expand_pool(state.pool, c), origin_vox=jnp.asarray(c["origin_vox"]),
        key=jnp.asarray(c["key"]),
        frame=jnp.asarray(c["frame"]), hyper=core.Hyper(**as_j(c["hyper"])),
    )


def _expand_pool(empty, c: dict):
    """The pool of a replay / keyframe checkpoint back at its saved capacity (None when not used)."""
    if empty is None:
        return None
    n = int(c["n"].get("pool", 0)) if "pool" in c else 0
    if n == 0:
        return empty
    return empty.replace(**{k: getattr(empty, k).at[:n].set(jnp.asarray(c["pool"][k][:n]))
                            for k in ("pairs", "surface", "frame", "voxel_row")}, n=jnp.int32(n))


def _meta(cfg: MapConfig, state: core.N3State, timings: list) -> dict:
    return {"config": to_dict(cfg), "frame": int(state.frame), "layout": "compact-1",
            "capacity": dataclasses.asdict(core.Capacities.of(state)), "timings": list(timings)}


def save_state(path: str, cfg: MapConfig, state: core.N3State, timings: list) -> None:
    """Write the map as checkpoint `<frames mapped>` of directory `path`, atomically (the two newest are kept)."""
    wait_for_saves()
    save_tree(path, compact(state), _meta(cfg, state, timings), step=int(state.frame))


_PENDING: list = []  # the one background save in flight: [thread, error or None]


def save_state_async(path: str, cfg: MapConfig, state: core.N3State, timings: list) -> None:
    """Like `save_state`, but the write happens in a background thread after one device->host copy
    of the compact state; call `wait_for_saves()` before relying on the files."""
    wait_for_saves()
    tree, meta = compact(state), _meta(cfg, state, timings)
    slot = [None, None]

    def work():
        try:
            save_tree(path, tree, meta, step=meta["frame"])
        except BaseException as e:  # noqa: BLE001 - re-raised by wait_for_saves in the caller's thread
            slot[1] = e

    slot[0] = threading.Thread(target=work, name="jaxmap-checkpoint", daemon=True)
    slot[0].start()
    _PENDING.append(slot)


def saving() -> bool:
    """Is a background save still being written?"""
    return any(t.is_alive() for t, _ in _PENDING)


def wait_for_saves() -> None:
    """Block until the background save (if any) is written; re-raise its error."""
    while _PENDING:
        thread, _ = _PENDING[0]
        thread.join()
        _, err = _PENDING.pop(0)
        if err is not None:
            raise err


def load_state(path: str) -> tuple[MapConfig, core.N3State, list]:
    """(config, state, timings) of the newest intact checkpoint in directory `path` (see `save_state`;
    `path` may also name one checkpoint `path/<step>`). Falls back to the older checkpoint with a
    warning when the newer is damaged; `jaxmap.errors.CheckpointError` when none is usable,
    `NoCheckpointError` when there is none."""
    wait_for_saves()
    return load(path, _build, "N3 map")


def _build(ckpt: str, meta: dict) -> tuple[MapConfig, core.N3State, list]:
    """(config, state, timings) of one verified checkpoint directory; CheckpointError when unusable."""
    where = os.path.join(ckpt, "meta.json")
    try:
        cfg = from_dict(MapConfig, meta["config"], source=where)
        caps = core.Capacities(**meta["capacity"])
    except (KeyError, TypeError, ConfigError) as e:
        raise CheckpointError(f"{where}: not an N3 map checkpoint ({type(e).__name__}: {e})") from None
    static = core.N3Static.from_config(cfg)
    return cfg, expand(static, cfg, caps, read_tree(ckpt)), list(meta.get("timings", []))
