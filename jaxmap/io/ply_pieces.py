"""A PLY point cloud read in pieces (`read_points_ply_chunks`): what the evaluation holds of a long drive's
ground truth (~2 GB of points) is one piece at a time.
"""
from __future__ import annotations

import os

import numpy as np

from jaxmap.errors import DataError
from jaxmap.io.pointcloud import check_file, parse_ply, ply_header, vertex_arrays


def read_points_ply_chunks(path, chunk: int = 2_000_000):
    """The vertices of a PLY file (point cloud or mesh) in pieces of at most `chunk` rows, in file order:
    yields (points [n,3] float32, normals [n,3] float32 or None, classes [n] uint8 or None), as
    `read_points_ply(..., return_normals=True, return_classes=True)` would return them, sliced.

    A binary file whose elements before the vertices have fixed-size rows is read a piece at a time, so
    what is held is one piece, not the file (a long drive's gt_points.ply is ~2 GB; a memory map would
    count every page read in the process's resident memory); any other file is parsed whole, then sliced."""
    path = check_file(path)
    with open(path, "rb") as f:
        fmt, elements = ply_header(f, path)
        layout = _vertex_rows(path, fmt, elements, f.tell())
        if layout is None:  # ascii, or a list element before the vertices: parse it whole
            v = parse_ply(path, want_faces=False)["vertex"]
            names, n = tuple(v), len(v["x"])
            pieces = ({k: np.asarray(x)[a:a + chunk] for k, x in v.items()} for a in range(0, n, chunk))
        else:
            dt, offset, n = layout
            names = dt.names
            f.seek(offset)
            pieces = (np.fromfile(f, dtype=dt, count=min(chunk, n - a)) for a in range(0, n, chunk))
        for c in "xyz":
            if c not in names:
                raise DataError(f"{path}: PLY vertices lack property '{c}'")
        for r in pieces:
            yield vertex_arrays(r)


def _vertex_rows(path: str, fmt: str, elements, body_at: int):
    """(row dtype, byte offset, count) of the vertex rows of a binary PLY, or None when they cannot be
    read a piece at a time (ascii, or an element of list rows before the vertices)."""
    if fmt == "ascii":
        return None
    endian = "<" if fmt == "binary_little_endian" else ">"
    offset = body_at
    for name, count, props in elements:
        if any(isinstance(t, tuple) for _, t in props):
            return None
        dt = np.dtype([(p, endian + t) for p, t in props])
        if name == "vertex":
            if offset + dt.itemsize * count > os.path.getsize(path):
                raise DataError(f"{path}: PLY declares {count} 'vertex' rows but the file is shorter; "
                                "the file is truncated")
            return dt, offset, count
        offset += dt.itemsize * count
    raise DataError(f"{path}: PLY has no 'vertex' element; not a point cloud or mesh")
