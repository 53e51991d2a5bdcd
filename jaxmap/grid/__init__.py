"""Sparse multi-level feature grid: a fixed-capacity hash table of corner keys and trilinear features."""

from jaxmap.grid import compaction, features, hashing
from jaxmap.grid.features import (
    allocate_corners,
    corner_keys,
    corner_weights,
    init_feature_rows,
    init_features,
    interpolate,
    leaf_voxel,
    level_voxels,
    query_features,
)
from jaxmap.grid.hashing import (
    HashTable,
    create,
    entries,
    grow,
    hash_keys,
    insert,
    insert_counted,
    insert_grow,
    lookup,
)

__all__ = [
    "compaction",
    "features",
    "hashing",
    "HashTable",
    "create",
    "hash_keys",
    "lookup",
    "insert",
    "insert_counted",
    "grow",
    "insert_grow",
    "entries",
    "leaf_voxel",
    "level_voxels",
    "corner_keys",
    "corner_weights",
    "interpolate",
    "init_features",
    "init_feature_rows",
    "allocate_corners",
    "query_features",
]
