"""Atomic checkpoints of a state pytree plus a small JSON of metadata (orbax underneath).

Layout of a checkpoint directory:
  state/        orbax PyTree checkpoint of the state (N3: `jaxmap.n3.core.N3State`; IMT: the latent map)
  meta.json     what is needed to rebuild it: the config, capacities, per-frame timings so far
Writes go to a temporary directory that is renamed into place, so an interrupted save never
leaves a half-written checkpoint behind. The mappers' own modules (`jaxmap.n3.checkpoint`, the
IMT mapper) build on `save_tree` / `read_meta`; this module imports none of them.
"""
from __future__ import annotations

import json
import os
import shutil

import jax

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


def read_tree(path: str):
    """The `state/` tree of checkpoint directory `path` (written by `save_tree`) as numpy arrays, in
    the nested dicts orbax stores; the caller rebuilds its own types."""
    return _checkpointer().restore(os.path.join(os.path.abspath(path), "state"))


def read_meta(path: str, what: str = "jaxmap") -> tuple[str, dict]:
    """`(absolute path, meta.json contents)` of a checkpoint written by `save_tree`; a clear error
    when `path` is not one (`what` names the kind of checkpoint expected)."""
    path = os.path.abspath(path)
    meta_path = os.path.join(path, "meta.json")
    if not os.path.isfile(meta_path):
        raise DataError(f"{path}: not a {what} checkpoint (no meta.json); pass RUN_DIR/checkpoint")
    with open(meta_path) as f:
        return path, json.load(f)
