"""Checkpoints that survive damage: the last two saves of a state pytree, each checksummed (orbax underneath).

Layout of a checkpoint directory (`RUN/checkpoint`), one subdirectory per save, named by its step (the
frames mapped, for N3), as orbax's CheckpointManager names them:

  <step>/state/          orbax PyTree checkpoint of the state (IMT: the latent map; N3 maps of earlier versions), or
  <step>/arrays/         the state as one `.npy` file per leaf, `arrays/<key>/<key>.npy` (N3: the compact
                         `jaxmap.n3.core.N3State`; `save_arrays`): written one leaf at a time, so a save
                         needs no second copy of the map in memory, where orbax holds ~1.4 copies more
  <step>/meta.json       what is needed to rebuild it: the config, capacities, per-frame timings so far
  <step>/manifest.json   the step and the size and SHA-256 of every other file of `<step>/`, written last

A save goes to `<step>.tmp` and is renamed into place once complete, so a save cut short (kill -9, a
full disk) never looks like a checkpoint. After each save the newest `KEEP` (2) checkpoints up to that
step are kept; older ones, and any of a later step (a damaged future the run went back from), are deleted.

Loading (`load`, `read_meta`) checks the newest checkpoint's files against its manifest first; when
one is missing, truncated or altered, it warns and falls back to the previous checkpoint. No
checkpoint at all is a `NoCheckpointError`, only damaged ones a `CheckpointError` naming each one's
fault. A directory written by jaxmap <= 0.1 (`state/` + `meta.json` directly in it, no manifest) is
still read, unchecked. The mappers' own modules (`jaxmap.n3.checkpoint`, the IMT mapper) build on
`save_tree` / `load` / `read_meta` / `read_tree`; this module imports none of them. A save written in
a background thread, while the next frames map, goes through `SAVES` (`BackgroundSaves`: one at a time).
"""
from __future__ import annotations

import concurrent.futures
import hashlib
import io
import json
import logging
import os
import shutil
import threading
from typing import Callable, Iterable, TypeVar

import jax
import jax.numpy as jnp
import numpy as np

from jaxmap.errors import CheckpointError, NoCheckpointError

log = logging.getLogger("jaxmap")

KEEP = 2
MANIFEST = "manifest.json"
ARRAYS = "arrays"
T = TypeVar("T")


def _checkpointer():
    import orbax.checkpoint as ocp

    logging.getLogger("absl").setLevel(logging.WARNING)  # orbax logs every rename at INFO

    return ocp.PyTreeCheckpointer()


def _sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _files(root: str) -> list[str]:
    """Every file under `root` but the manifest, as sorted paths relative to it."""
    out = []
    for d, _, names in os.walk(root):
        out += [os.path.relpath(os.path.join(d, n), root) for n in names]
    return sorted(f for f in out if f != MANIFEST)


def manifest(root: str, step: int, digests: dict[str, str] | None = None) -> dict:
    """{"step", "files": {relative path: {"size", "sha256"}}} of every file under `root`; `digests`:
    the SHA-256 of files already known (computed while they were written), the others are read."""
    files, digests = {}, digests or {}
    for rel in _files(root):
        p = os.path.join(root, rel)
        files[rel] = {"size": os.path.getsize(p), "sha256": digests.get(rel) or _sha256(p)}
    return {"step": int(step), "files": files}


def _write_npy(path: str, arr: np.ndarray, hasher: concurrent.futures.Executor) -> str:
    """Write `arr` as a .npy file (header 1.0, the data straight from its buffer) and return the file's
    SHA-256, computed from memory in `hasher` while the data is written (hashlib and file writes release
    the GIL), so a save need not read its files back for the manifest. Holds no copy of `arr`."""
    arr = arr if arr.flags.c_contiguous else np.ascontiguousarray(arr)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, np.lib.format.header_data_from_array_1_0(arr))
    h = hashlib.sha256(header.getvalue())
    hashed = hasher.submit(h.update, memoryview(arr.reshape(-1)).cast("B")) if arr.size else None
    with open(path, "wb") as f:
        f.write(header.getvalue())
        arr.tofile(f)
    if hashed is not None:
        hashed.result()
    return h.hexdigest()


def steps(path: str) -> list[int]:
    """Steps of the complete checkpoints in directory `path`, newest first (unfinished `.tmp` saves left out)."""
    if not os.path.isdir(path):
        return []
    return sorted((int(n) for n in os.listdir(path) if n.isdigit() and os.path.isdir(os.path.join(path, n))),
                  reverse=True)


def save_tree(path: str, tree, meta: dict, step: int | None = None, keep: int = KEEP) -> str:
    """Write `tree` (an orbax PyTree, under `state/`) and `meta` (`meta.json`) as checkpoint `step` of
    directory `path` (default: one past the newest there), with its manifest; keep the newest `keep`.
    Returns the checkpoint's directory `path/<step>`."""
    return _save(path, meta, step, keep,
                 lambda tmp: _checkpointer().save(os.path.join(tmp, "state"), jax.device_get(tree)))


def save_arrays(path: str, leaves: Iterable[tuple[str, Callable[[], np.ndarray]]], meta: dict,
                step: int | None = None, keep: int = KEEP) -> str:
    """Like `save_tree`, but the state is `leaves`: (name, fn) pairs, `fn()` giving the leaf as a host
    array. Each leaf is fetched and written (`arrays/<name>.npy`, "/" in a name makes folders) before
    the next is fetched, so the save holds one leaf at a time. Names are of nested dict keys, as
    `read_tree` gives them back."""
    def write(tmp):
        digests = {}
        with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="jaxmap-sha256") as hasher:
            for name, fn in leaves:
                rel = os.path.join(ARRAYS, name + ".npy")
                f = os.path.join(tmp, rel)
                os.makedirs(os.path.dirname(f), exist_ok=True)
                digests[rel] = _write_npy(f, np.asarray(fn()), hasher)
        return digests

    return _save(path, meta, step, keep, write)


def _save(path: str, meta: dict, step: int | None, keep: int, write: Callable[[str], dict | None]) -> str:
    """The atomic part of a save: `write(tmp)` fills `path/<step>.tmp` (and may return the SHA-256 of the
    files it wrote, by relative path), then meta.json and the manifest
    are written and the folder renamed to `path/<step>`; the newest `keep` are kept."""
    path = os.path.abspath(path)  # orbax only takes absolute paths
    if step is None:
        have = steps(path)
        step = have[0] + 1 if have else 0
    os.makedirs(path, exist_ok=True)
    final, tmp = os.path.join(path, str(int(step))), os.path.join(path, f"{int(step)}.tmp")
    if os.path.exists(tmp):
        shutil.rmtree(tmp)
    os.makedirs(tmp)
    digests = write(tmp)
    with open(os.path.join(tmp, "meta.json"), "w") as f:
        json.dump({**meta, "step": int(step)}, f)
    with open(os.path.join(tmp, MANIFEST), "w") as f:
        json.dump(manifest(tmp, step, digests), f)
    if os.path.exists(final):  # the same step saved again (e.g. a finished run resumed): replace it
        old = final + ".old"
        shutil.rmtree(old, ignore_errors=True)
        os.replace(final, old)
        os.replace(tmp, final)
        shutil.rmtree(old)
    else:
        os.replace(tmp, final)
    _prune(path, int(step), keep)
    return final


def _prune(path: str, step: int, keep: int) -> None:
    """Delete checkpoints beyond the newest `keep` up to `step`, those after `step`, and stale `.tmp`/`.old`."""
    kept = [s for s in steps(path) if s <= step][:keep]
    for name in os.listdir(path):
        full = os.path.join(path, name)
        if (name.isdigit() and int(name) not in kept) or name.endswith((".tmp", ".old")):
            shutil.rmtree(full, ignore_errors=True)


def verify(ckpt: str) -> dict:
    """meta.json of checkpoint directory `ckpt` (`path/<step>`) once every file matches its manifest;
    CheckpointError naming the first file that is missing, truncated or altered."""
    mpath = os.path.join(ckpt, MANIFEST)
    if not os.path.isfile(mpath):
        raise CheckpointError(f"{ckpt}: no {MANIFEST} (an unfinished or foreign save)")
    try:
        with open(mpath) as f:
            files = json.load(f)["files"]
    except (OSError, ValueError, KeyError, TypeError):
        raise CheckpointError(f"{mpath}: unreadable (truncated or altered)") from None
    for rel, want in files.items():
        p = os.path.join(ckpt, rel)
        if not os.path.isfile(p):
            raise CheckpointError(f"{p}: missing")
        if os.path.getsize(p) != want["size"]:
            raise CheckpointError(f"{p}: {os.path.getsize(p)} bytes, {want['size']} when saved (truncated)")
        if _sha256(p) != want["sha256"]:
            raise CheckpointError(f"{p}: checksum mismatch (the file was altered after the save)")
    return _read_json(os.path.join(ckpt, "meta.json"))


def _read_json(path: str) -> dict:
    try:
        with open(path) as f:
            return json.load(f)
    except FileNotFoundError:
        raise CheckpointError(f"{path}: missing") from None
    except (OSError, ValueError) as e:
        raise CheckpointError(f"{path}: unreadable ({e})") from None


def _is_single(path: str) -> bool:
    """Is `path` itself one checkpoint (a `<step>` directory, or jaxmap <= 0.1's unnumbered layout)?"""
    return os.path.isfile(os.path.join(path, MANIFEST)) or os.path.isfile(os.path.join(path, "meta.json"))


def candidates(path: str, what: str = "jaxmap") -> list[str]:
    """Checkpoint directories of `path`, newest first; NoCheckpointError when there is none."""
    path = os.path.abspath(path)
    if _is_single(path):
        return [path]
    found = [os.path.join(path, str(s)) for s in steps(path)]
    if not found:
        where = "does not exist" if not os.path.exists(path) else "holds no checkpoint"
        raise NoCheckpointError(f"{path}: {where}; no {what} checkpoint was saved there")
    return found


def load(path: str, build: Callable[[str, dict], T], what: str = "jaxmap") -> T:
    """`build(checkpoint dir, meta)` of the newest checkpoint in `path` that passes `verify` and builds
    (`build` raises CheckpointError when its contents are unusable). Falls back to an older one with
    a warning; CheckpointError listing every checkpoint's fault when none is usable."""
    faults = []
    for ckpt in candidates(path, what):
        try:
            meta = verify(ckpt) if os.path.isfile(os.path.join(ckpt, MANIFEST)) else _read_json(
                os.path.join(ckpt, "meta.json"))  # jaxmap <= 0.1: no manifest to check against
            out = build(ckpt, meta)
        except CheckpointError as e:
            faults.append(str(e))
            continue
        if faults:
            log.warning("%s; using the previous checkpoint %s (step %s) instead", "; ".join(faults), ckpt,
                        meta.get("step", meta.get("frame", "?")))
        return out
    err = CheckpointError(f"no usable {what} checkpoint in {os.path.abspath(path)}: " + "; ".join(faults))
    err.faults = faults  # what is wrong with each one, newest first (for callers that word the error themselves)
    raise err


def read_meta(path: str, what: str = "jaxmap") -> tuple[str, dict]:
    """`(checkpoint directory, meta.json contents)` of the newest intact checkpoint in `path` (see `load`);
    read its state with `read_tree(checkpoint directory)`."""
    return load(path, lambda ckpt, meta: (ckpt, meta), what)


def read_tree(ckpt: str):
    """The state of checkpoint directory `ckpt` (from `read_meta` / `load`) as numpy arrays in nested
    dicts: an `arrays/` save (memory-mapped, read-only: copy what you keep) or orbax's `state/`. The
    caller rebuilds its own types. CheckpointError if it cannot be read."""
    arrays = os.path.join(os.path.abspath(ckpt), ARRAYS)
    if os.path.isdir(arrays):
        return _read_arrays(arrays)
    state = os.path.join(os.path.abspath(ckpt), "state")
    if not os.path.isdir(state):
        raise CheckpointError(f"{state}: missing")
    try:
        return _checkpointer().restore(state)
    except Exception as e:  # orbax/tensorstore raise many types for damaged files
        first = str(e).strip().splitlines()[0][:200] if str(e).strip() else ""
        raise CheckpointError(f"{state}: unreadable ({type(e).__name__}: {first})") from None


def _read_arrays(root: str) -> dict:
    tree: dict = {}
    for rel in _files(root):
        if not rel.endswith(".npy"):
            continue
        *keys, leaf = rel[:-len(".npy")].split(os.sep)
        node = tree
        for k in keys:
            node = node.setdefault(k, {})
        try:
            node[leaf] = np.load(os.path.join(root, rel), mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as e:
            raise CheckpointError(f"{os.path.join(root, rel)}: unreadable ({e})") from None
    return tree


# ---------------------------------------------------------------------------------------------
# a state's leaves on the host, one at a time
# ---------------------------------------------------------------------------------------------


def in_host_memory(x) -> bool:
    """Is `x` a numpy array or a jax array held in host memory (the CPU backend)?"""
    devices = getattr(x, "devices", None)
    return devices is None or all(d.platform == "cpu" for d in devices())


def host_array(x, rows=None, copy: bool = True) -> np.ndarray:
    """`x`, or its `rows` (a slice or an index array; None = all), as a host array.

    In host memory the rows are read straight out of a view of the buffer; elsewhere they are sliced
    or gathered on the device first, so only the used rows cross to the host (a full `device_get`
    would copy the whole capacity). Slicing on the CPU device too would hold the used rows twice
    (2 GB more at the end of the long drive). `copy`: an own copy, needed when the state's buffers
    may change before the array is written (the next frame's donated step overwrites them while a
    background save writes); without it, a slice of a host buffer is a view of it."""
    if rows is None:  # a scalar or a decoder leaf: small, always an own copy
        return np.array(x)
    if in_host_memory(x):
        v = np.asarray(x)[rows]
        return np.array(v) if copy and isinstance(rows, slice) else v  # an index array gathers a new array
    return np.array(x[jnp.asarray(rows) if isinstance(rows, np.ndarray) else rows])


def named_leaves(tree) -> list[tuple[str, object]]:
    """(name, leaf) of a tree of nested dicts, "a/b" naming tree["a"]["b"] (as `read_tree` nests them);
    callables are leaves (functions that fetch a leaf when it is written, see `save_arrays`)."""
    flat, _ = jax.tree_util.tree_flatten_with_path(tree, is_leaf=callable)
    return [("/".join(str(k.key) for k in path), x) for path, x in flat]


class BackgroundSaves:
    """The checkpoint being written in a background thread, at most one at a time (a save waits for the one
    before), and the error it raised, re-raised in the thread that waits for it. One per process (`SAVES`):
    both maps' background saves (`jaxmap.n3.checkpoint.save_state_async`, `ImtMapper.save`) go through it."""

    def __init__(self):
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def start(self, work) -> None:
        """Run `work()` in a background thread, once the save before it is written."""
        self.wait()

        def run():
            try:
                work()
            except BaseException as e:  # noqa: BLE001 - re-raised by wait() in the caller's thread
                self._error = e

        self._thread = threading.Thread(target=run, name="jaxmap-checkpoint", daemon=True)
        self._thread.start()

    def busy(self) -> bool:
        """Is a save still being written?"""
        return self._thread is not None and self._thread.is_alive()

    def wait(self) -> None:
        """Block until the save (if any) is written; re-raise its error (once)."""
        if self._thread is None:
            return
        self._thread.join()
        err, self._thread, self._error = self._error, None, None
        if err is not None:
            raise err


# This process's background checkpoint writes (either map's): the one mutable state of this module.
SAVES = BackgroundSaves()
