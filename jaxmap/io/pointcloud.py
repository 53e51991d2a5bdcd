"""Point-cloud and mesh files: KITTI `.bin` scans, PLY (points or triangle meshes) and PCD.

All readers return float32 arrays in the coordinates stored in the file (no frame change here) and
raise `jaxmap.errors.DataError` with the file name and a fix when a file is missing, truncated or
malformed. Scans (`read_scan`) additionally drop NaN/inf points, logging how many were dropped.

PLY and uncompressed PCD are parsed with numpy alone, so the benchmarks also run where open3d is
not installed; open3d is imported lazily only for `binary_compressed` PCD files.
"""
from __future__ import annotations

import logging
import os
import re

import numpy as np

from jaxmap.errors import DataError

log = logging.getLogger("jaxmap")

SCAN_EXTENSIONS = (".bin", ".ply", ".pcd")

# ------------------------------------------------------------------------------------------------
# scans
# ------------------------------------------------------------------------------------------------


def check_file(path) -> str:
    """The path as a string, or a DataError when it is not a file."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DataError(f"{path}: file not found; check the path")
    return path


def drop_nonfinite(points: np.ndarray, path: str) -> np.ndarray:
    """Drop rows of `points` [N,3] with a NaN or inf coordinate; log a warning naming `path` if any."""
    good = np.isfinite(points).all(axis=1)
    n_bad = int(points.shape[0] - np.count_nonzero(good))
    if n_bad:
        log.warning("%s: dropped %d of %d points with NaN/inf coordinates", path, n_bad, points.shape[0])
        points = points[good]
    return points


def read_scan(path) -> np.ndarray:
    """Read one scan: `.bin` (KITTI float32 x,y,z,intensity), `.ply` or `.pcd`.

    Returns [N,3] float32 x,y,z in the file's (sensor) frame. Points with a NaN/inf coordinate are
    dropped and counted in a warning on the "jaxmap" logger. Raises DataError for a missing,
    truncated or unreadable file.
    """
    path = check_file(path)
    ext = os.path.splitext(path)[1].lower()
    if ext == ".bin":
        size = os.path.getsize(path)
        if size % 16:
            raise DataError(
                f"{path}: size {size} bytes is not a multiple of 16; the file is truncated or not KITTI "
                "float32 x,y,z,i (4 float32 per point); re-export or re-download the scan")
        pts = np.fromfile(path, dtype="<f4").reshape(-1, 4)[:, :3]
    elif ext == ".ply":
        pts = read_points_ply(path)
        _warn_if_mesh(path, len(pts))
    elif ext == ".pcd":
        pts = read_pcd(path)
    else:
        raise DataError(f"{path}: unsupported scan format '{ext}'; use .bin (KITTI), .ply or .pcd")
    pts = np.ascontiguousarray(pts, dtype=np.float32)
    return drop_nonfinite(pts, path)


_mesh_scan_dirs: set[str] = set()


def ply_face_count(path) -> int:
    """Faces a PLY file declares in its header (0 for a point cloud); reads the header only."""
    with open(os.fspath(path), "rb") as f:
        for _ in range(200):
            words = f.readline().split()
            if not words or words[0] == b"end_header":
                break
            if words[0] == b"element" and len(words) >= 3 and words[1] == b"face":
                try:
                    return int(words[2])
                except ValueError:
                    return 0
    return 0


def _warn_if_mesh(path: str, n_vertices: int) -> None:
    """A scan that is a triangle mesh is read as its vertices, with a warning (once per directory)."""
    faces = ply_face_count(path)
    d = os.path.dirname(os.path.abspath(path))
    if faces and d not in _mesh_scan_dirs:
        _mesh_scan_dirs.add(d)
        log.warning("%s: a triangle mesh (%d faces), not a point cloud: read as a scan of its %d vertices, which "
                    "samples the surface unevenly; export the LiDAR points instead (reported once for %s)",
                    path, faces, n_vertices, d)


def write_scan_bin(path, points, intensity=None) -> None:
    """Write a KITTI `.bin` scan: float32 x,y,z,intensity per point (little endian).

    points: [N,3] (cast to float32); intensity: [N] or None (zeros).
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise DataError(f"{path}: points must have shape [N,3], got {points.shape}")
    data = np.zeros((points.shape[0], 4), dtype="<f4")
    data[:, :3] = points
    if intensity is not None:
        intensity = np.asarray(intensity, dtype=np.float32).reshape(-1)
        if intensity.shape[0] != points.shape[0]:
            raise DataError(f"{path}: {intensity.shape[0]} intensities for {points.shape[0]} points")
        data[:, 3] = intensity
    makedirs_for(path)
    data.tofile(os.fspath(path))


def makedirs_for(path) -> None:
    """Create the directory that will hold the file `path` (nothing to do for a bare file name)."""
    d = os.path.dirname(os.fspath(path))
    if d:
        os.makedirs(d, exist_ok=True)


# ------------------------------------------------------------------------------------------------
# PLY
# ------------------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _ply_type(name: str, path: str) -> str:
    if name not in _PLY_TYPES:
        raise DataError(f"{path}: unknown PLY property type '{name}'; the file is corrupt or not PLY")
    return _PLY_TYPES[name]


def parse_ply(path: str, want_faces: bool):
    """Parse a PLY file into {element name: {property: array}} for 'vertex' (and 'face').

    Supports ascii, binary_little_endian and binary_big_endian; list properties are read for
    faces (all faces must have the same vertex count in binary files).
    """
    path = check_file(path)
    with open(path, "rb") as f:
        fmt, elements = ply_header(f, path)
        body = f.read()
    wanted = {"vertex"} | ({"face"} if want_faces else set())
    if fmt == "ascii":
        out = _ply_ascii_body(body, elements, wanted, path)
    else:
        out = _ply_binary_body(body, elements, wanted, "<" if fmt == "binary_little_endian" else ">", path)
    if "vertex" not in out:
        raise DataError(f"{path}: PLY has no 'vertex' element; not a point cloud or mesh")
    for c in "xyz":
        if c not in out["vertex"]:
            raise DataError(f"{path}: PLY vertices lack property '{c}'")
    return out


def ply_header(f, path: str):
    """Read a PLY header from the open binary file f, leaving f at the body: (format, elements), elements
    [[name, count, [(prop, dtype) or (prop, ("list", count_dtype, item_dtype))]]] in file order."""
    magic = f.readline().strip()
    if magic != b"ply":
        raise DataError(f"{path}: not a PLY file (first line is not 'ply'); re-export it as PLY")
    fmt = None
    elements = []
    while True:
        line = f.readline()
        if not line:
            raise DataError(f"{path}: PLY header has no 'end_header'; the file is truncated or corrupt")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append([words[1], int(words[2]), []])
            elif words[0] == "property":
                if not elements:
                    raise ValueError("property before any element")
                if words[1] == "list":
                    elements[-1][2].append((words[4], ("list", _ply_type(words[2], path),
                                                       _ply_type(words[3], path))))
                else:
                    elements[-1][2].append((words[2], _ply_type(words[1], path)))
            else:
                raise ValueError(f"unexpected header line {line!r}")
        except (IndexError, ValueError) as e:
            raise DataError(f"{path}: malformed PLY header ({e}); re-export the file") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DataError(f"{path}: unsupported PLY format {fmt!r}; use ascii or binary_little_endian")
    return fmt, elements


def _ply_ascii_body(body: bytes, elements, wanted: set, path: str) -> dict:
    """The `wanted` elements of an ASCII PLY body: {name: {property: array}}."""
    lines = body.decode("ascii", errors="replace").splitlines()
    lines = [ln for ln in lines if ln.strip()]
    out = {}
    pos = 0
    for name, count, props in elements:
        chunk = lines[pos:pos + count]
        pos += count
        if name not in wanted:
            continue
        if len(chunk) < count:
            raise DataError(f"{path}: PLY declares {count} '{name}' rows, file has {len(chunk)}; truncated")
        out[name] = _ascii_rows(chunk, props, path, name)
    return out


def _ply_binary_body(body: bytes, elements, wanted: set, endian: str, path: str) -> dict:
    """The `wanted` elements of a binary PLY body (endian "<" or ">"): {name: {property: array}}."""
    out = {}
    offset = 0
    for name, count, props in elements:
        has_list = any(isinstance(t, tuple) for _, t in props)
        if not has_list:
            dt = np.dtype([(p, endian + t) for p, t in props])
            nbytes = dt.itemsize * count
            if offset + nbytes > len(body):
                raise DataError(f"{path}: PLY declares {count} '{name}' rows ({nbytes} bytes) but the file "
                                f"has only {len(body) - offset} bytes left; the file is truncated")
            if name in wanted:
                arr = np.frombuffer(body, dtype=dt, count=count, offset=offset)
                out[name] = {p: arr[p] for p, _ in props}
            offset += nbytes
            continue
        if count == 0:
            out[name] = {p: np.zeros((0, 3)) for p, _ in props}
            continue
        # A list element: only the common case (one list property, same length each row) is vectorised.
        if len(props) != 1:
            if name in wanted:
                raise DataError(f"{path}: PLY element '{name}' mixes list and scalar properties; "
                                "re-export with only vertex_indices")
            break  # nothing after an unsupported element is needed
        pname, (_, ct, it) = props[0]
        first = int(np.frombuffer(body, dtype=endian + ct, count=1, offset=offset)[0])
        dt = np.dtype([("n", endian + ct), ("v", endian + it, (first,))])
        nbytes = dt.itemsize * count
        if offset + nbytes > len(body):
            raise DataError(f"{path}: PLY '{name}' rows are truncated or have mixed lengths; "
                            "only meshes with one polygon size (e.g. triangles) are supported")
        arr = np.frombuffer(body, dtype=dt, count=count, offset=offset)
        if np.any(arr["n"] != first):
            raise DataError(f"{path}: PLY '{name}' rows have mixed lengths; triangulate the mesh first")
        if name in wanted:
            out[name] = {pname: arr["v"]}
        offset += nbytes
    return out


def _ascii_rows(rows, props, path, name):
    if any(isinstance(t, tuple) for _, t in props):
        if len(props) != 1:
            raise DataError(f"{path}: PLY element '{name}' mixes list and scalar properties")
        try:
            vals = [[int(w) for w in r.split()] for r in rows]
        except ValueError:
            raise DataError(f"{path}: non-integer entry in PLY '{name}' rows") from None
        if any(len(v) != v[0] + 1 for v in vals if v) or len({v[0] for v in vals}) > 1:
            raise DataError(f"{path}: PLY '{name}' rows have mixed lengths; triangulate the mesh first")
        arr = np.array([v[1:] for v in vals], dtype=np.int64).reshape(len(rows), -1)
        return {props[0][0]: arr}
    try:
        arr = np.array(" ".join(rows).split(), dtype=np.float64)
        arr = arr.reshape(len(rows), len(props))
    except ValueError:
        raise DataError(f"{path}: malformed ascii PLY '{name}' rows (expected {len(props)} numbers each)") from None
    return {p: arr[:, i] for i, (p, _) in enumerate(props)}


def read_points_ply(path, return_normals: bool = False, return_classes: bool = False):
    """Read the vertices of a PLY file (point cloud or mesh) as [N,3] float32.

    With `return_normals=True` returns (points [N,3], normals [N,3] float32 or None if the file has
    no nx,ny,nz); with `return_classes=True` also (last) the per-point semantic class [N] uint8 (the
    `class` property of `jaxmap synth`'s gt_points.ply) or None. Raises DataError for a missing or
    unreadable file.
    """
    path = os.fspath(path)
    pts, nrm, cls = vertex_arrays(parse_ply(path, want_faces=False)["vertex"])
    if not return_normals and not return_classes:
        return pts
    return (pts,) + ((nrm,) if return_normals else ()) + ((cls,) if return_classes else ())


def vertex_arrays(rows) -> tuple:
    """(points [N,3] float32, normals [N,3] float32 or None, classes [N] uint8 or None) of PLY vertex rows
    (a {property: array} dict or a structured array with x, y, z; nx, ny, nz and class when it has them)."""
    names = rows.dtype.names if hasattr(rows, "dtype") else tuple(rows)
    return (np.stack([rows["x"], rows["y"], rows["z"]], axis=1).astype(np.float32),
            np.stack([rows["nx"], rows["ny"], rows["nz"]], axis=1).astype(np.float32)
            if all(k in names for k in ("nx", "ny", "nz")) else None,
            np.asarray(rows["class"]).astype(np.uint8) if "class" in names else None)


def read_mesh_ply(path):
    """Read a triangle mesh PLY: (vertices [V,3] float32, faces [F,3] int32)."""
    path = os.fspath(path)
    d = parse_ply(path, want_faces=True)
    v = d["vertex"]
    verts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    if "face" not in d or not d["face"]:
        raise DataError(f"{path}: PLY has no 'face' element; expected a triangle mesh")
    faces = next(iter(d["face"].values()))
    faces = np.asarray(faces).reshape(len(faces), -1) if len(faces) else np.zeros((0, 3), np.int64)
    if faces.shape[1] != 3:
        raise DataError(f"{path}: faces have {faces.shape[1]} vertices; triangulate the mesh first")
    if faces.size and (faces.min() < 0 or faces.max() >= len(verts)):
        raise DataError(f"{path}: face indices out of range [0, {len(verts)}); the file is corrupt")
    return verts, faces.astype(np.int32)


def write_points_ply(path, points, normals=None, classes=None) -> None:
    """Write a binary little-endian PLY point cloud: float32 x,y,z (+ nx,ny,nz if normals given)
    (+ a uchar `class` per point if classes [N] given: a semantic class id, 0-255)."""
    points = np.asarray(points, dtype="<f4")
    if points.ndim != 2 or points.shape[1] != 3:
        raise DataError(f"{path}: points must have shape [N,3], got {points.shape}")
    cols = [points]
    props = ["x", "y", "z"]
    if normals is not None:
        normals = np.asarray(normals, dtype="<f4")
        if normals.shape != points.shape:
            raise DataError(f"{path}: normals shape {normals.shape} != points shape {points.shape}")
        cols.append(normals)
        props += ["nx", "ny", "nz"]
    data = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4")
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {points.shape[0]}"]
    header += [f"property float {p}" for p in props]
    if classes is not None:
        classes = np.asarray(classes)
        if classes.shape != (points.shape[0],) or (classes.size and (classes.min() < 0 or classes.max() > 255)):
            raise DataError(f"{path}: classes must be [N] integers in 0..255, got shape {classes.shape}")
        rec = np.empty(points.shape[0], dtype=[("f", "<f4", (data.shape[1],)), ("c", "u1")])
        rec["f"], rec["c"] = data, classes
        data = rec
        header.append("property uchar class")
    header.append("end_header")
    makedirs_for(path)
    with open(os.fspath(path), "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())


def write_mesh_ply(path, vertices, faces) -> None:
    """Write a binary little-endian PLY triangle mesh: vertices [V,3] float32, faces [F,3] int32.

    Readable by open3d, trimesh and MeshLab.
    """
    vertices = np.ascontiguousarray(vertices, dtype="<f4")
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise DataError(f"{path}: expected vertices [V,3] and faces [F,3], got {vertices.shape}, {faces.shape}")
    fdt = np.dtype([("n", "u1"), ("v", "<i4", (3,))])
    frec = np.empty(faces.shape[0], dtype=fdt)
    frec["n"] = 3
    frec["v"] = faces
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {vertices.shape[0]}",
              "property float x", "property float y", "property float z",
              f"element face {faces.shape[0]}", "property list uchar int vertex_indices", "end_header"]
    makedirs_for(path)
    with open(os.fspath(path), "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vertices.tobytes())
        f.write(frec.tobytes())


# ------------------------------------------------------------------------------------------------
# PCD
# ------------------------------------------------------------------------------------------------

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def read_pcd(path) -> np.ndarray:
    """Read x,y,z of a PCD file ([N,3] float32). ascii and binary are parsed with numpy;
    binary_compressed goes through open3d (imported lazily). Non-finite points are kept here."""
    path = check_file(path)
    with open(path, "rb") as f:
        raw = f.read()
    hdr = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise DataError(f"{path}: PCD header has no DATA line; the file is truncated or not PCD")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, _, rest = line.partition(" ")
        hdr[key.upper()] = rest.split()
        if key.upper() == "DATA":
            break
        if len(hdr) > 20:
            raise DataError(f"{path}: not a PCD file (no DATA line in the header)")
    try:
        fields = hdr["FIELDS"]
        sizes = [int(s) for s in hdr["SIZE"]]
        types = hdr["TYPE"]
        counts = [int(c) for c in hdr.get("COUNT", ["1"] * len(fields))]
        npts = int(hdr["POINTS"][0]) if "POINTS" in hdr else int(hdr["WIDTH"][0]) * int(hdr["HEIGHT"][0])
        data_kind = hdr["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as e:
        raise DataError(f"{path}: malformed PCD header ({e!r}); re-export the scan") from None
    if not all(c in fields for c in "xyz"):
        raise DataError(f"{path}: PCD has no x,y,z fields (fields: {fields})")
    if data_kind == "ascii":
        txt = raw[pos:].decode("ascii", errors="replace").split()
        ncol = sum(counts)
        try:
            arr = np.array(txt[: npts * ncol], dtype=np.float64)
            arr = arr.reshape(npts, ncol)
        except ValueError:
            raise DataError(f"{path}: PCD ascii data is truncated or malformed (expected {npts} rows of "
                            f"{ncol} numbers)") from None
        starts = np.cumsum([0] + counts)
        cols = [arr[:, starts[fields.index(c)]] for c in "xyz"]
        return np.stack(cols, axis=1).astype(np.float32)
    if data_kind == "binary":
        try:
            dt = np.dtype([(f"{name}_{i}" if cnt > 1 else name, "<" + _PCD_TYPES[(t.upper(), s)])
                           for name, s, t, cnt in zip(fields, sizes, types, counts) for i in range(cnt)])
        except KeyError:
            raise DataError(f"{path}: unsupported PCD field type/size in {list(zip(types, sizes))}") from None
        if len(raw) - pos < dt.itemsize * npts:
            raise DataError(f"{path}: PCD declares {npts} points ({dt.itemsize * npts} bytes) but has "
                            f"{len(raw) - pos} bytes of data; the file is truncated")
        arr = np.frombuffer(raw, dtype=dt, count=npts, offset=pos)
        return np.stack([arr[c] for c in "xyz"], axis=1).astype(np.float32)
    if data_kind == "binary_compressed":
        return _read_pcd_open3d(path, npts)
    raise DataError(f"{path}: unknown PCD DATA kind '{data_kind}'")


def _read_pcd_open3d(path: str, npts: int) -> np.ndarray:
    try:
        import open3d as o3d
    except ImportError:  # pragma: no cover - depends on the machine
        raise DataError(f"{path}: binary_compressed PCD needs open3d; install it or re-save the scan "
                        "as binary PCD") from None
    pc = o3d.t.io.read_point_cloud(path)
    if "positions" not in pc.point or (pc.point.positions.shape[0] == 0 and npts > 0):
        raise DataError(f"{path}: open3d could not read this PCD file; it is corrupt or truncated")
    return pc.point.positions.numpy().astype(np.float32)


def is_scan_file(name: str) -> bool:
    return os.path.splitext(name)[1].lower() in SCAN_EXTENSIONS


def natural_key(name: str):
    """Sort key: by name, with digit runs compared as numbers (so 2.bin < 10.bin)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


__all__ = ["read_scan", "write_scan_bin", "read_points_ply", "write_points_ply", "read_mesh_ply",
           "write_mesh_ply", "read_pcd", "drop_nonfinite", "SCAN_EXTENSIONS"]
