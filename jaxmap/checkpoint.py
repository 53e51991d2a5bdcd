"""Orbax save/restore of a whole N3 map (state pytree + the small metadata needed to rebuild it).

Layout of a checkpoint directory:
  state/        orbax PyTree checkpoint of `N3State` (hash tables, features, Adam moments,
                decoder, pair store, PRNG key, frame counter)
  meta.json     config, map origin (float64), capacities, per-frame timings so far
Writes go to a temporary directory that is renamed into place, so an interrupted save never
leaves a half-written checkpoint behind.
"""
from __future__ import annotations

import json
import os
import shutil

import jax
import numpy as np

from jaxmap.config import MapConfig, from_dict, to_dict
from jaxmap.errors import DataError


def _checkpointer():
    import logging

    import orbax.checkpoint as ocp

    logging.getLogger("absl").setLevel(logging.WARNING)  # orbax logs every rename at INFO

    return ocp.PyTreeCheckpointer()


def save_tree(path: str, tree, meta: dict) -> None:
    """Write `tree` (an orbax PyTree, under `state/`) and `meta` (`meta.json`) to directory `path`
    atomically: into `path.tmp`, renamed over any older checkpoint only once complete."""
    path = os.path.abspath(path)  # orbax only takes absolute paths
    tmp = path + ".tmp"
    if os.path.exists(tmp):
        shutil.rmtree(tmp)
    os.makedirs(tmp)
    _checkpointer().save(os.path.join(tmp, "state"), jax.device_get(tree))
    with open(os.path.join(tmp, "meta.json"), "w") as f:
        json.dump(meta, f)
    if os.path.exists(path):
        shutil.rmtree(path)
    os.replace(tmp, path)


def read_meta(path: str, what: str = "jaxmap") -> tuple[str, dict]:
    """`(absolute path, meta.json contents)` of a checkpoint written by `save_tree`; a clear error
    when `path` is not one (`what` names the kind of checkpoint expected)."""
    path = os.path.abspath(path)
    meta_path = os.path.join(path, "meta.json")
    if not os.path.isfile(meta_path):
        raise DataError(f"{path}: not a {what} checkpoint (no meta.json); pass RUN_DIR/checkpoint")
    with open(meta_path) as f:
        return path, json.load(f)


def save_mapper(mapper, path: str) -> None:
    """Write `mapper` (an N3Mapper) to directory `path` atomically (replacing an older one)."""
    s = mapper.state
    meta = {
        "config": to_dict(mapper.cfg),
        "origin": None if mapper.origin is None else [float(x) for x in mapper.origin],
        "frame": int(s.frame),
        "capacity": {
            "voxel_table": int(s.voxels.keys.shape[0]), "corner_table": int(s.corners.keys.shape[0]),
            "voxel_rows": int(s.voxel_coord.shape[0]), "feature_rows": int(s.features.shape[0]),
            "store_blocks": int(s.store.n_slots),
        },
        "timings": mapper.timings,
    }
    save_tree(path, s, meta)


def load_mapper(path: str):
    """Rebuild an N3Mapper saved by `save_mapper`."""
    from jaxmap.grid import hashing
    from jaxmap.n3 import window
    from jaxmap.n3.mapper import N3Mapper

    path, meta = read_meta(path)
    cfg = from_dict(MapConfig, meta["config"], source=os.path.join(path, "meta.json"))
    m = N3Mapper(cfg)
    cap = meta["capacity"]
    s = m.state
    # A template with the saved capacities, so the restored arrays keep their exact structure.
    import jax.numpy as jnp

    d = s.features.shape[-1]
    template = s.replace(
        voxels=hashing.create(cap["voxel_table"]), corners=hashing.create(cap["corner_table"]),
        voxel_coord=jnp.zeros((cap["voxel_rows"], 3), jnp.int32),
        voxel_corner_rows=jnp.zeros((cap["voxel_rows"], s.voxel_corner_rows.shape[1]), jnp.int32),
        features=jnp.zeros((cap["feature_rows"], 4, d), jnp.float32),
        store=window.create(cap["store_blocks"], cfg.window.pairs_per_voxel, cap["voxel_rows"]),
    )
    restored = _checkpointer().restore(os.path.join(path, "state"), item=jax.device_get(template))
    m.state = jax.tree_util.tree_map(jnp.asarray, restored)
    m.origin = None if meta["origin"] is None else np.asarray(meta["origin"], np.float64)
    m.timings = list(meta.get("timings", []))
    return m
