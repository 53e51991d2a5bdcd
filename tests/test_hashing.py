"""Fixed-capacity hash table: agreement with a Python dict, collisions, growth, overflow, jit-ability."""

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxmap.grid import hashing as H

B = 64  # every batch is padded to this size (valid mask) so compiled functions are shared by all tests


def np_hash(keys: np.ndarray) -> np.ndarray:
    """Obviously-correct scalar reference: murmur3_32 of the 4 little-endian int32 words, seed 0."""
    m = 0xFFFFFFFF

    def rotl(x, r):
        return ((x << r) | (x >> (32 - r))) & m

    out = []
    for key in np.asarray(keys, np.int32).view(np.uint32):
        h = 0
        for word in key:
            k = rotl((int(word) * 0xCC9E2D51) & m, 15) * 0x1B873593 & m
            h = (rotl(h ^ k, 13) * 5 + 0xE6546B64) & m
        h ^= 16
        h ^= h >> 16
        h = (h * 0x85EBCA6B) & m
        h ^= h >> 13
        h = (h * 0xC2B2AE35) & m
        h ^= h >> 16
        out.append(h)
    return np.array(out, np.uint32)


def pad(keys, valid=None):
    """Pad a list of keys to a [B, 4] batch with a [B] validity mask."""
    n = len(keys)
    out = np.zeros((B, 4), np.int32)
    if n:
        out[:n] = np.asarray(keys, np.int32)
    v = np.zeros(B, bool)
    v[:n] = True if valid is None else np.asarray(valid, bool)
    return jnp.asarray(out), jnp.asarray(v)


def check_table_invariants(table, model):
    """Rows are dense 0..count-1, one slot per key, and the stored mapping equals the model dict."""
    keys, rows = H.entries(table)
    assert int(table.count) == len(model)
    np.testing.assert_array_equal(rows, np.arange(len(model)))
    assert {tuple(int(v) for v in k): int(r) for k, r in zip(keys, rows)} == model
    tab_rows = np.asarray(table.rows)
    tab_keys = np.asarray(table.keys)
    empty = tab_keys[:, 0] == H.EMPTY
    assert np.all(tab_rows[empty] == -1) and np.all(tab_keys[empty] == H.EMPTY)


def crafted_colliding_keys(capacity: int, n: int, seed: int = 0) -> np.ndarray:
    """n distinct keys whose hashes all fall in the same bucket of a `capacity`-slot table."""
    rng = np.random.default_rng(seed)
    cand = np.unique(rng.integers(-1000, 1000, size=(60_000, 4)).astype(np.int32), axis=0)
    # the jax hash is checked against the scalar reference in test_hash_matches_numpy_reference
    bucket = np.asarray(H.hash_keys(jnp.asarray(cand))) & np.uint32(capacity - 1)
    top = np.bincount(bucket).argmax()
    same = cand[bucket == top]
    assert len(same) >= n
    return same[:n]


def test_hash_matches_numpy_reference():
    rng = np.random.default_rng(1)
    keys = rng.integers(np.iinfo(np.int32).min, np.iinfo(np.int32).max, size=(1000, 4), dtype=np.int64)
    keys = np.concatenate([keys.astype(np.int32), [[0, 0, 0, 0], [-1, -1, -1, -1], [1, 2, 3, 2]]]).astype(np.int32)
    got = np.asarray(H.hash_keys(jnp.asarray(keys)))
    assert got.dtype == np.uint32
    np.testing.assert_array_equal(got, np_hash(keys))
    # neighbouring voxels and levels do not collide in the full 32 bits
    grid = np.stack(np.meshgrid(*[np.arange(-8, 8)] * 3, np.arange(3), indexing="ij"), -1).reshape(-1, 4)
    assert len(np.unique(np_hash(grid))) == len(grid)


def test_create_validates_capacity():
    t = H.create(8)
    assert t.capacity == 8 and int(t.count) == 0
    for bad in (0, 1, 3, 12):
        with pytest.raises(ValueError):
            H.create(bad)


key_st = st.tuples(st.integers(-3, 3), st.integers(-3, 3), st.integers(-3, 3), st.integers(0, 2))
op_st = st.one_of(
    st.tuples(st.just("insert"), st.lists(st.tuples(key_st, st.booleans()), max_size=B)),
    st.tuples(st.just("lookup"), st.lists(key_st, max_size=B)),
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=st.lists(op_st, min_size=1, max_size=8), dup=st.integers(0, 3))
def test_agrees_with_dict(ops, dup):
    """Random inserts (many duplicates, tiny start capacity => collisions and growth) and lookups."""
    table = H.create(8)
    model: dict[tuple, int] = {}
    for kind, items in ops:
        if kind == "insert":
            # duplicate the first few entries inside the batch
            items = (items + items[:dup])[:B]
            keys = [k for k, _ in items]
            valid = [v for _, v in items]
            kb, vb = pad(keys, valid)
            before = int(table.count)
            table, rows = H.insert_grow(table, kb, vb, max_load=0.5, log=False)
            rows = np.asarray(rows)
            expect = []
            for k, v in items:
                if v and k not in model:
                    model[k] = len(model)  # first occurrence in the batch gets the next row
                expect.append(model[k] if v else -1)
            expect += [-1] * (B - len(items))  # padding is invalid
            np.testing.assert_array_equal(rows, expect)
            assert int(table.count) - before == len(model) - before
            assert int(table.count) <= 0.5 * table.capacity
        else:
            kb, _ = pad(items)
            rows = np.asarray(H.lookup(table, kb))[: len(items)]
            np.testing.assert_array_equal(rows, [model.get(k, -1) for k in items])
        check_table_invariants(table, model)
    # re-inserting everything returns the same rows and changes nothing
    if model:
        all_keys = np.array(list(model), np.int32)
        for i in range(0, len(all_keys), B):
            chunk = all_keys[i : i + B]
            kb, vb = pad(chunk)
            count = int(table.count)
            table, rows = H.insert_grow(table, kb, vb, log=False)
            np.testing.assert_array_equal(np.asarray(rows)[: len(chunk)], [model[tuple(k)] for k in chunk])
            assert int(table.count) == count


def rows_of(table, keys):
    """lookup of up to B keys (padded batch)."""
    kb, _ = pad(keys)
    return np.asarray(H.lookup(table, kb))[: len(keys)]


def insert_padded(table, keys, valid=None, **kw):
    kb, vb = pad(keys, valid)
    table, rows, overflow = H.insert(table, kb, vb, **kw)
    return table, np.asarray(rows)[: len(keys)], bool(overflow)


def assert_same_table(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_crafted_collisions_and_probe_overflow():
    cap = 256
    keys = crafted_colliding_keys(cap, 70)
    assert len(set(np_hash(keys[:5]) & np.uint32(cap - 1))) == 1
    table = H.create(cap)

    # 30 keys sharing one bucket (a chain of 30 probes), each twice in one batch, second time reversed
    table, rows, overflow = insert_padded(table, np.concatenate([keys[:30], keys[:30][::-1]]))
    assert not overflow
    np.testing.assert_array_equal(rows, np.concatenate([np.arange(30), np.arange(30)[::-1]]))
    # present keys are found; absent keys of the same bucket walk the whole chain and miss
    np.testing.assert_array_equal(rows_of(table, keys[:64]), [*range(30)] + [-1] * 34)

    # 40 more keys of the same bucket: the chain would need 70 > max_probes = 64 probes
    new_table, rows, overflow = insert_padded(table, keys[30:70])
    assert overflow
    np.testing.assert_array_equal(rows, -1)
    assert_same_table(new_table, table)  # returned unchanged: nothing half-inserted, nothing lost

    # insert_grow recovers: grows (the bucket splits at the larger capacity) and places every key
    kb, vb = pad(keys[30:70])
    table2, rows2 = H.insert_grow(table, kb, vb, log=False)
    np.testing.assert_array_equal(np.asarray(rows2)[:40], np.arange(30, 70))
    assert table2.capacity > cap
    np.testing.assert_array_equal(rows_of(table2, keys[:64]), np.arange(64))
    np.testing.assert_array_equal(rows_of(table2, keys[64:]), np.arange(64, 70))


def test_full_table_and_row_capacity_overflow():
    table = H.create(16)
    keys = np.array([[i, -i, 2 * i, i % 3] for i in range(17)], np.int32)
    # 17 distinct keys cannot fit 16 slots
    t, rows, overflow = insert_padded(table, keys)
    assert overflow and int(t.count) == 0
    assert_same_table(t, table)
    np.testing.assert_array_equal(rows, -1)
    # exactly 16 fit (100% load, wrap-around probing)
    t, rows, overflow = insert_padded(table, keys[:16])
    assert not overflow and int(t.count) == 16
    np.testing.assert_array_equal(rows, np.arange(16))
    np.testing.assert_array_equal(rows_of(t, keys), [*range(16), -1])
    # a full table still resolves its own keys (re-insert, reversed) without overflow
    t2, rows, overflow = insert_padded(t, keys[:16][::-1])
    assert not overflow
    np.testing.assert_array_equal(rows, np.arange(16)[::-1])
    # ... and overflows, unchanged, as soon as one new key comes
    t2, rows, overflow = insert_padded(t, keys[10:])
    assert overflow
    assert_same_table(t2, t)
    # row capacity: 12 new keys into room for 10 rows
    t3, rows, overflow = insert_padded(table, keys[:12], row_capacity=10)
    assert overflow and int(t3.count) == 0
    t3, rows, overflow = insert_padded(table, keys[:12], np.arange(12) < 10, row_capacity=10)
    assert not overflow and int(t3.count) == 10
    np.testing.assert_array_equal(rows, [*range(10), -1, -1])
    # insert_grow never drops: all 17 keys end up in a grown table
    kb, vb = pad(keys)
    t4, rows = H.insert_grow(table, kb, vb, log=False)
    np.testing.assert_array_equal(np.asarray(rows)[:17], np.arange(17))
    assert t4.capacity >= 64


def test_growth_preserves_rows_and_continues_numbering():
    rng = np.random.default_rng(3)
    keys = np.unique(rng.integers(-50, 50, size=(200, 4)).astype(np.int32), axis=0)
    rng.shuffle(keys)
    chunks = [keys[i : i + B] for i in range(0, len(keys), B)]
    table = H.create(512)
    for c in chunks:
        table, rows, overflow = insert_padded(table, c)
        assert not overflow
    for cap in (512, 2048):
        g = H.grow(table, cap)
        assert g.capacity == cap and int(g.count) == len(keys)
        found = np.concatenate([rows_of(g, c) for c in chunks])
        np.testing.assert_array_equal(found, np.arange(len(keys)))
        ek, er = H.entries(g)
        np.testing.assert_array_equal(ek, keys)
        np.testing.assert_array_equal(er, np.arange(len(keys)))
    with pytest.raises(ValueError):
        H.grow(table, 256)
    # after growth, new keys continue the row numbering; old ones keep theirs
    more = np.array([[1000 + i, 0, 0, 0] for i in range(5)] + [list(keys[0])], np.int32)
    g, rows, overflow = insert_padded(g, more)
    np.testing.assert_array_equal(rows, [len(keys) + i for i in range(5)] + [0])


def test_invalid_and_reserved_keys():
    table = H.create(16)
    keys = np.array([[1, 1, 1, 0], [H.EMPTY, 0, 0, 0], [2, 2, 2, 0], [1, 1, 1, 0]], np.int32)
    table, rows, overflow = insert_padded(table, keys, [True, True, False, True])
    np.testing.assert_array_equal(rows, [0, -1, -1, 0])
    assert int(table.count) == 1
    np.testing.assert_array_equal(rows_of(table, keys), [0, -1, -1, 0])


def test_insert_and_lookup_inside_user_jit():
    @jax.jit
    def step(table, keys, valid):
        table, rows, overflow = H.insert(table, keys, valid)
        return table, rows, overflow, H.lookup(table, keys)

    keys, valid = pad(np.array([[i % 5, 0, 0, 0] for i in range(12)], np.int32))
    table, rows, overflow, found = step(H.create(16), keys, valid)
    assert not bool(overflow)
    np.testing.assert_array_equal(np.asarray(rows)[:12], np.arange(12) % 5)
    np.testing.assert_array_equal(np.asarray(found)[:12], np.arange(12) % 5)
    # the table is a pytree: it can be a jit argument and a scan carry
    assert [x.shape for x in jax.tree_util.tree_leaves(table)] == [(16, 4), (16,), ()]


def test_insert_grow_logs_growth(caplog):
    kb, vb = pad(np.array([[i, i, i, 0] for i in range(20)], np.int32))
    with caplog.at_level(logging.INFO, logger="jaxmap"):
        table, rows = H.insert_grow(H.create(8), kb, vb, max_load=0.5)
    assert table.capacity == 64  # smallest doubling holding 20 keys at load <= 0.5, in one step
    np.testing.assert_array_equal(np.asarray(rows)[:20], np.arange(20))
    assert [r.getMessage().split(" slots")[0] for r in caplog.records] == ["hash table: growing 8 -> 64"]


def test_staged_compaction_large_batch():
    """Batches >= 4096 keys run the probing in compacted stages; results equal a dict's."""
    rng = np.random.default_rng(5)
    n = 6000
    keys = rng.integers(-12, 12, size=(n, 4)).astype(np.int32)  # many duplicates, ~4500 distinct
    keys[:, 3] = rng.integers(0, 3, n)
    valid = rng.random(n) < 0.9
    table, rows, overflow = H.insert(H.create(8192), jnp.asarray(keys), jnp.asarray(valid))
    assert not bool(overflow)
    model: dict[tuple, int] = {}
    expect = []
    for k, v in zip(map(tuple, keys.tolist()), valid):
        if v and k not in model:
            model[k] = len(model)
        expect.append(model[k] if v else -1)
    np.testing.assert_array_equal(np.asarray(rows), expect)
    check_table_invariants(table, model)
    found = np.asarray(H.lookup(table, jnp.asarray(keys)))
    np.testing.assert_array_equal(found, [model.get(k, -1) for k in map(tuple, keys.tolist())])
