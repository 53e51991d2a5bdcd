"""Fixed-capacity, open-addressing hash table of int32 voxel keys, as a pytree.

The table maps a key ``(x, y, z, level)`` (int32) to a *row*: a dense id handed out in insertion order
(0, 1, 2, ...). Rows index the feature table (``features[row]``) and never change, not even when the
table grows, so features never move. Slots are open-addressed over a power-of-two capacity with a
32-bit spatial hash and bounded linear probing.

Layout (read like mctx's ``Tree``: a frozen dataclass of arrays, ``-1`` / sentinel padding)::

    keys   [C, 4] int32   stored key per slot; an empty slot holds EMPTY in every column
    rows   [C]    int32   row of the key in that slot, -1 where empty
    count  []     int32   number of keys stored == the next row to hand out

Everything inside ``jit`` (``lookup``, ``insert``) has static shapes and no Python loop over keys:
probing runs in rounds of a ``lax.while_loop`` over the batch, which is compacted into smaller static
buffers as keys finish (most finish in one or two rounds; see ``compaction.staged_while``). ``insert`` claims empty slots
with a scatter-min of batch indices (the smallest index wins a contested slot), so a batch with
duplicate keys gives each distinct key exactly one row, in order of first occurrence. If a key
cannot be placed (probe bound, or a row capacity), ``insert`` reports ``overflow`` and leaves the
table exactly as it was, so nothing is ever lost silently. ``grow`` (outside ``jit``) rehashes into a
bigger table keeping every row; ``insert_grow`` is the host-side wrapper that grows and retries.

``jax_enable_x64`` is not needed: the hash (murmur3_32 of the 16 key bytes) is uint32 arithmetic with
wrap-around multiplication.
A key whose x equals ``EMPTY`` (INT32_MIN) is reserved: ``insert`` treats it as invalid and ``lookup``
returns -1 for it.
"""

from __future__ import annotations

import functools
import logging

import flax
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxmap.errors import CapacityError
from jaxmap.grid.compaction import prefix_sum, stage_sizes, staged_while

__all__ = [
    "EMPTY",
    "DEFAULT_MAX_PROBES",
    "HashTable",
    "create",
    "create_on_host",
    "hash_keys",
    "lookup",
    "insert",
    "insert_counted",
    "grow",
    "insert_grow",
    "entries",
]

_logger = logging.getLogger("jaxmap")

EMPTY = np.int32(np.iinfo(np.int32).min)  # sentinel key value of an empty slot (all 4 columns)
DEFAULT_MAX_PROBES = 64
MAX_CAPACITY = 1 << 30  # slot indices stay well inside int32

# 32-bit hash: murmur3_32 over the 4 key words (seed 0). The classic spatial hash
# x*p0 ^ y*p1 ^ z*p2 (Teschner et al. 2003 / instant-NGP) is *not* used: with negative coordinates
# (two's complement, high bits all set) it collapses, e.g. a 16^3 block around the origin maps to only
# 1296 distinct values out of 4096. murmur3 mixes every input bit into every output bit, so the low
# bits kept by the power-of-two mask are well spread for any coordinate sign.
_C1 = np.uint32(0xCC9E2D51)
_C2 = np.uint32(0x1B873593)
_N1 = np.uint32(0xE6546B64)
_FMIX1 = np.uint32(0x85EBCA6B)
_FMIX2 = np.uint32(0xC2B2AE35)


@flax.struct.dataclass
class HashTable:
    """Open-addressing hash table (a pytree). Capacity ``C`` (static, a power of two) is ``keys.shape[0]``."""

    keys: jax.Array  # [C, 4] int32: (x, y, z, level); EMPTY in every column where the slot is free
    rows: jax.Array  # [C] int32: dense row id of the key in that slot (insertion order), -1 where free
    count: jax.Array  # [] int32: number of keys stored == next row to hand out

    @property
    def capacity(self) -> int:
        """Number of slots ``C`` (static)."""
        return self.keys.shape[0]


def _check_capacity(capacity: int) -> int:
    capacity = int(capacity)
    if capacity < 2 or capacity & (capacity - 1):
        raise ValueError(f"hash table capacity must be a power of two >= 2, got {capacity}")
    if capacity > MAX_CAPACITY:
        raise CapacityError(f"hash table capacity {capacity} exceeds the maximum {MAX_CAPACITY}")
    return capacity


def create(capacity: int) -> HashTable:
    """An empty table with ``capacity`` slots (a power of two).

    Returns a ``HashTable`` with keys ``[C, 4]`` = EMPTY, rows ``[C]`` = -1, count ``[]`` = 0.
    """
    capacity = _check_capacity(capacity)
    return HashTable(
        keys=jnp.full((capacity, 4), EMPTY, dtype=jnp.int32),  # [C, 4]
        rows=jnp.full((capacity,), -1, dtype=jnp.int32),  # [C]
        count=jnp.zeros((), dtype=jnp.int32),  # []
    )


def create_on_host(capacity: int) -> HashTable:
    """``create``, filled on the host and copied to the device (outside ``jit`` only): ``jnp.full`` compiles
    a fill program for every new capacity, which a map that grew would otherwise compile when it is first
    emptied (a remap's rebuild)."""
    capacity = _check_capacity(capacity)
    keys, rows, count = jax.device_put(
        (np.full((capacity, 4), EMPTY, np.int32), np.full((capacity,), -1, np.int32), np.int32(0)), may_alias=False
    )  # [C, 4], [C], []: copies the device owns (a frame program may donate them); `jnp.asarray` compiles a copy
    return HashTable(keys=keys, rows=rows, count=count)


def _rotl(x: jax.Array, r: int) -> jax.Array:
    return (x << np.uint32(r)) | (x >> np.uint32(32 - r))


def _fmix32(h: jax.Array) -> jax.Array:
    """murmur3 32-bit finaliser (a bijection of uint32 with good avalanche)."""
    h = h ^ (h >> np.uint32(16))
    h = h * _FMIX1
    h = h ^ (h >> np.uint32(13))
    h = h * _FMIX2
    h = h ^ (h >> np.uint32(16))
    return h


@jax.jit
def hash_keys(keys: jax.Array) -> jax.Array:
    """32-bit spatial hash of int32 keys: murmur3_32 of the 16 bytes ``(x, y, z, level)``, seed 0.

    Args:
      keys: ``[N, 4]`` int32 ``(x, y, z, level)``.
    Returns:
      ``[N]`` uint32 hash (wrap-around uint32 arithmetic; no x64 needed).
    """
    k = lax.bitcast_convert_type(jnp.asarray(keys, jnp.int32), jnp.uint32)  # [N, 4]
    h = jnp.zeros(k.shape[:1], jnp.uint32)  # [N]
    for c in range(4):
        w = _rotl(k[:, c] * _C1, 15) * _C2
        h = _rotl(h ^ w, 13) * np.uint32(5) + _N1
    return _fmix32(h ^ np.uint32(16))


def _slot(h: jax.Array, probe: jax.Array, capacity: int) -> jax.Array:
    """Slot of probe number ``probe`` (linear probing): ``(h + probe) mod C`` as int32."""
    mask = np.uint32(capacity - 1)
    return ((h + probe.astype(jnp.uint32)) & mask).astype(jnp.int32)


@functools.partial(jax.jit, static_argnames=("max_probes",))
def lookup(table: HashTable, keys: jax.Array, *, max_probes: int = DEFAULT_MAX_PROBES) -> jax.Array:
    """Rows of ``keys``, or -1 for keys not in the table.

    Probing runs in rounds (probe ``p`` of every unfinished key per round); a key finishes on its key
    (found) or on an empty slot (absent). The batch is compacted as keys finish (``compaction.staged_while``).

    Args:
      table: the hash table (capacity ``C``).
      keys: ``[N, 4]`` int32 query keys.
      max_probes: static probe bound; must be the one used by ``insert`` (a key is never stored further
        than ``max_probes - 1`` slots from its hash slot).
    Returns:
      ``[N]`` int32 row per key, -1 where absent.
    """
    keys = jnp.asarray(keys, jnp.int32)  # [N, 4]
    capacity = table.capacity
    n = keys.shape[0]
    const = (keys, hash_keys(keys))  # [N, 4], [N] uint32
    state = (keys[:, 0] == EMPTY, jnp.full((n,), -1, jnp.int32))  # done [N] (reserved keys: at once), rows [N]

    def live(const, state, probe):
        return ~state[0]

    def body(const, state, probe):
        k, h = const
        done, rows = state
        slot = _slot(h, probe, capacity)  # [n]
        cur = table.keys[slot]  # [n, 4]
        empty = cur[:, 0] == EMPTY  # [n]
        same = jnp.all(cur == k, axis=-1)  # [n]
        rows = jnp.where(~done & same, table.rows[slot], rows)
        return (done | same | empty, rows), probe + 1

    def kill(const, state, ok):
        return const, (state[0] | ~ok, state[1])

    (_, rows), _ = staged_while(
        lambda probe: probe < max_probes, live, body, kill, const, state, jnp.int32(0), stage_sizes(n)
    )
    return rows


def _claim(table_keys: jax.Array, keys: jax.Array, h: jax.Array, active: jax.Array, max_probes: int):
    """Place every active key in its probe sequence, in rounds (the core of ``insert`` and ``grow``).

    Each round, every unresolved key looks at its current probe slot:
      * the slot holds the same key -> resolved there (already stored, or claimed by a duplicate);
      * the slot holds another key -> advance to the next probe;
      * the slot is empty -> propose; a scatter-min of batch indices picks one winner per slot, which
        writes its key; losers stay put and re-read the slot next round (resolving if the winner was a
        duplicate of theirs, advancing otherwise).
    Duplicates of one key move in lockstep, so the first occurrence in the batch is the one that wins.
    Every key resolves or advances at least every second round, hence at most ``2 * max_probes + 1``
    rounds. A slot is proposed for in one round only (it is occupied afterwards), so the scatter-min
    target ``claim [C]`` is filled once per call, not per round (the batch shrinks: ``staged_while``).

    Args:
      table_keys: ``[C, 4]`` int32 slot keys.
      keys: ``[N, 4]`` int32 keys to place.
      h: ``[N]`` uint32 their hashes.
      active: ``[N]`` bool, keys to place (others are ignored).
      max_probes: static probe bound.
    Returns:
      table_keys ``[C, 4]`` with the winners written, slot ``[N]`` int32 (meaningful where ``placed``),
      won ``[N]`` bool (this key took a previously empty slot), placed ``[N]`` bool (key is in the table).
    """
    capacity = table_keys.shape[0]
    n = keys.shape[0]
    max_rounds = 2 * max_probes + 2
    const = (keys, h, jnp.arange(n, dtype=jnp.int32), active)  # [N, 4], [N], [N] batch index, [N]
    state = (jnp.zeros((n,), jnp.int32), jnp.zeros((n,), bool), jnp.zeros((n,), bool))  # probe, placed, won
    shared = (jnp.int32(0), table_keys, jnp.full((capacity,), n, jnp.int32))  # round, keys [C, 4], claim [C]

    def live(const, state, shared):
        probe, placed, _ = state
        return const[3] & ~placed & (probe < max_probes)

    def body(const, state, shared):
        k, hh, idx, _ = const
        probe, placed, won = state
        rnd, tk, claim = shared
        lv = live(const, state, shared)  # [m]
        slot = _slot(hh, probe, capacity)  # [m]
        cur = tk[slot]  # [m, 4]
        empty = cur[:, 0] == EMPTY  # [m]
        same = jnp.all(cur == k, axis=-1)  # [m]
        propose = lv & empty  # [m]
        claim = claim.at[jnp.where(propose, slot, capacity)].min(idx, mode="drop")  # [C] out of range: no write
        win = propose & (claim[slot] == idx)  # [m]
        tk = tk.at[jnp.where(win, slot, capacity)].set(k, mode="drop")  # [C, 4]
        placed = placed | (lv & same) | win
        probe = jnp.where(lv & ~empty & ~same, probe + 1, probe)
        return (probe, placed, won | win), (rnd + 1, tk, claim)

    def kill(const, state, ok):
        k, hh, idx, act = const
        return (k, hh, idx, act & ok), state

    (probe, placed, won), (_, table_keys, _) = staged_while(
        lambda shared: shared[0] < max_rounds, live, body, kill, const, state, shared, stage_sizes(n)
    )
    return table_keys, _slot(h, probe, capacity), won, placed


@functools.partial(jax.jit, static_argnames=("max_probes", "row_capacity"))
def insert_counted(table: HashTable, keys: jax.Array, valid: jax.Array, max_probes: int, row_capacity: int | None):
    """``insert`` with a static ``row_capacity`` and its diagnostics (jit-able, as the frame program calls it).
    Returns (table, rows [N], overflow [], n_new [] distinct new keys placed, probe_fail [])."""
    capacity = table.capacity
    keys = jnp.asarray(keys, jnp.int32)  # [N, 4]
    active = jnp.asarray(valid, bool) & (keys[:, 0] != EMPTY)  # [N]
    h = hash_keys(keys)  # [N]
    new_keys, slot, won, placed = _claim(table.keys, keys, h, active, max_probes)

    n_new = jnp.sum(won, dtype=jnp.int32)  # [] distinct new keys placed
    probe_fail = jnp.any(active & ~placed)  # [] some key found no slot within max_probes
    limit = capacity if row_capacity is None else min(int(row_capacity), capacity)
    overflow = probe_fail | (table.count + n_new > limit)  # []

    # Commit or revert touching only the N claimed slots, never the whole [C] table: inside a
    # donated frame program a select or cond over the table would copy it every call.
    # On overflow the table is left exactly as it was: no claimed slot, no row, no count.
    undo = jnp.where(won & overflow, slot, capacity)  # [N] slots this call claimed, if reverting
    keys_tab = new_keys.at[undo].set(EMPTY, mode="drop")  # [C, 4]
    # New rows in batch order of the winners (== first occurrences): count, count + 1, ...
    new_row = table.count + prefix_sum(won.astype(jnp.int32)) - 1  # [N]
    rows_tab = table.rows.at[jnp.where(won & ~overflow, slot, capacity)].set(new_row, mode="drop")  # [C]
    rows = jnp.where(placed & active & ~overflow, rows_tab[slot], -1)  # [N]
    out = HashTable(keys=keys_tab, rows=rows_tab, count=jnp.where(overflow, table.count, table.count + n_new))
    return out, rows, overflow, n_new, probe_fail


@functools.partial(jax.jit, static_argnames=("max_probes",))
def _count_new(table: HashTable, keys: jax.Array, valid: jax.Array, max_probes: int) -> jax.Array:
    """Exact number of distinct valid keys of the batch not yet in the table ([] int32), by sorting."""
    keys = jnp.asarray(keys, jnp.int32)  # [N, 4]
    missing = jnp.asarray(valid, bool) & (keys[:, 0] != EMPTY)
    missing = missing & (lookup(table, keys, max_probes=max_probes) < 0)  # [N]
    k = jnp.where(missing[:, None], keys, EMPTY)  # [N, 4] the rest collapse onto one EMPTY key
    order = jnp.lexsort((k[:, 3], k[:, 2], k[:, 1], k[:, 0]))  # [N]
    ks, ms = k[order], missing[order]
    first = jnp.concatenate([jnp.ones((1,), bool), jnp.any(ks[1:] != ks[:-1], axis=-1)])  # [N]
    return jnp.sum(ms & first, dtype=jnp.int32)


def insert(
    table: HashTable,
    keys: jax.Array,
    valid: jax.Array | None = None,
    *,
    max_probes: int = DEFAULT_MAX_PROBES,
    row_capacity: int | None = None,
) -> tuple[HashTable, jax.Array, jax.Array]:
    """Batched insert (jit-able; shapes static).

    Keys already present return their row; each new distinct key gets one new row, handed out as
    ``count, count + 1, ...`` in order of its first occurrence in the batch. Invalid keys return -1.

    Args:
      table: the hash table (capacity ``C``).
      keys: ``[N, 4]`` int32.
      valid: ``[N]`` bool mask (``None``: all valid).
      max_probes: static probe bound (must match ``lookup``).
      row_capacity: static bound on ``count`` after the insert (e.g. the feature table's rows, or a
        load-factor limit); ``None`` means ``C``.
    Returns:
      ``(table, rows, overflow)``: the new table, ``[N]`` int32 rows (-1 where invalid), and a ``[]``
      bool. If ``overflow`` is True (a key could not be placed within ``max_probes`` probes, or the
      rows would exceed ``row_capacity``), the returned table is the input table unchanged and every
      row is -1: the caller must grow and retry (see ``insert_grow``). Nothing is dropped silently.
    """
    keys = jnp.asarray(keys, jnp.int32)
    if valid is None:
        valid = jnp.ones(keys.shape[:1], bool)
    out, rows, overflow, _, _ = insert_counted(table, keys, valid, max_probes, row_capacity)
    return out, rows, overflow


@functools.partial(jax.jit, static_argnames=("capacity", "max_probes"))
def _rehash(old: HashTable, capacity: int, max_probes: int):
    """Re-insert every stored key of ``old`` into a fresh ``capacity``-slot table, keeping rows."""
    fresh = create(capacity)
    active = old.keys[:, 0] != EMPTY  # [C_old]
    h = hash_keys(old.keys)  # [C_old]
    keys, slot, _, placed = _claim(fresh.keys, old.keys, h, active, max_probes)
    rows = fresh.rows.at[jnp.where(active, slot, capacity)].set(old.rows, mode="drop")  # [C]
    ok = jnp.all(placed | ~active)
    return HashTable(keys=keys, rows=rows, count=old.count), ok


def grow(table: HashTable, new_capacity: int, *, max_probes: int = DEFAULT_MAX_PROBES) -> HashTable:
    """Rehash every key into a table of ``new_capacity`` slots (host-side, outside ``jit``).

    Rows are preserved (``lookup`` of every stored key returns the same row before and after). If the
    keys cannot all be placed within ``max_probes`` (adversarial clustering), the capacity is doubled
    again until they can.

    Args:
      table: the table to grow (capacity ``C``).
      new_capacity: power of two ``>= C``.
    Returns:
      A ``HashTable`` of capacity ``>= new_capacity`` with the same key -> row mapping and count.
    """
    new_capacity = _check_capacity(new_capacity)
    if new_capacity < table.capacity:
        raise ValueError(f"grow: new capacity {new_capacity} is smaller than the current {table.capacity}")
    while True:
        out, ok = _rehash(table, new_capacity, max_probes)
        if bool(ok):
            return out
        _logger.warning("hash table: rehash into %d slots exceeded %d probes; doubling", new_capacity, max_probes)
        new_capacity = _check_capacity(new_capacity * 2)


def insert_grow(
    table: HashTable,
    keys: jax.Array,
    valid: jax.Array | None = None,
    max_load: float = 0.5,
    log: bool = True,
    *,
    max_probes: int = DEFAULT_MAX_PROBES,
) -> tuple[HashTable, jax.Array]:
    """Insert that never drops keys: grows the table (doubling) to keep ``count <= max_load * C``.

    The insert runs with ``row_capacity = floor(max_load * C)``; if it reports overflow (the load limit
    would be passed, or probing failed), the table, which ``insert`` left unchanged, is grown to the
    smallest doubling of ``C`` that holds ``count + n_new`` keys under ``max_load`` (at least one
    doubling; ``n_new`` is the exact number of distinct new keys, counted by a sort when probing
    failed) and the insert is retried. The result is as if the table had been grown before the
    insert, without over-growing on batches full of duplicates. Growth is logged on the ``"jaxmap"``
    logger. Host-side (not jit-able): it reads ``overflow``.

    Args:
      table: the hash table.
      keys: ``[N, 4]`` int32.
      valid: ``[N]`` bool (``None``: all valid).
      max_load: load factor limit in ``(0, 1]``.
      log: log growth at INFO level.
    Returns:
      ``(table, rows)``, rows ``[N]`` int32 (-1 exactly where invalid).
    Raises:
      CapacityError: the table would have to exceed ``MAX_CAPACITY`` slots.
    """
    if not 0.0 < max_load <= 1.0:
        raise ValueError(f"max_load must be in (0, 1], got {max_load}")
    keys = jnp.asarray(keys, jnp.int32)
    if valid is None:
        valid = jnp.ones(keys.shape[:1], bool)
    while True:
        capacity = table.capacity
        limit = max(1, int(max_load * capacity))
        out, rows, overflow, n_new, probe_fail = insert_counted(table, keys, valid, max_probes, limit)
        if not bool(overflow):
            return out, rows
        if bool(probe_fail):  # n_new only counts the keys placed before probing failed: count exactly
            n_new = _count_new(table, keys, valid, max_probes)
        need = int(table.count) + int(n_new)
        new_capacity = capacity * 2
        while need > max_load * new_capacity:
            new_capacity *= 2
        if new_capacity > MAX_CAPACITY:
            raise CapacityError(
                f"hash table needs more than {MAX_CAPACITY} slots for {need} keys at max_load={max_load}"
            )
        if log:
            _logger.info("hash table: growing %d -> %d slots (%d keys + %d new, max_load %.2f%s)", capacity,
                         new_capacity, int(table.count), int(n_new), max_load,
                         ", probe bound hit" if bool(probe_fail) else "")
        table = grow(table, new_capacity, max_probes=max_probes)


def entries(table: HashTable) -> tuple[np.ndarray, np.ndarray]:
    """Stored keys ordered by row (host-side).

    Returns:
      ``(keys [count, 4] int32, rows [count] int32)`` as numpy arrays; ``rows == arange(count)`` for a
      table built by ``insert``.
    """
    keys = np.asarray(table.keys)
    rows = np.asarray(table.rows)
    occupied = keys[:, 0] != EMPTY
    keys, rows = keys[occupied], rows[occupied]
    n = len(rows)
    if n and rows.min() >= 0 and rows.max() < n:  # rows 0 .. n-1 (an `insert` table): invert, O(n)
        order = np.full(n, -1, np.int64)
        order[rows] = np.arange(n)
        if order.min() >= 0:  # every row once
            return keys[order], rows[order]
    order = np.argsort(rows, kind="stable")
    return keys[order], rows[order]
