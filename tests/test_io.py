"""jaxmap.io: KITTI and depth sequences, scans, poses, calibration, PLY/PCD, and the errors a user sees."""
import logging
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxmap.errors import DataError
from jaxmap.geometry import PoseError, random_rotation, se3_inverse
from jaxmap.io import (SensorFrame, open_sequence, read_calib, read_depth_png, read_intrinsics, read_mesh_ply,
                       read_points_ply, read_poses, read_scan, write_calib, write_depth_png, write_intrinsics,
                       write_mesh_ply, write_points_ply, write_poses, write_scan_bin)


def random_poses(n, seed=0, scale=50.0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        T[i, :3, :3] = random_rotation(rng)
        T[i, :3, 3] = rng.normal(size=3) * scale
    return T


def tr_matrix(seed=7):
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = random_rotation(rng)
    T[:3, 3] = rng.normal(size=3)
    return T


def make_kitti(root, n=6, seed=0, calib=True, n_poses=None, ext="bin"):
    """Write a KITTI sequence with random scans; returns (scans [n][N,4] float32, cam poses, Tr)."""
    rng = np.random.default_rng(seed)
    os.makedirs(root / "velodyne", exist_ok=True)
    scans = []
    for i in range(n):
        pts = (rng.normal(size=(100 + 13 * i, 4)) * [20, 20, 3, 1]).astype(np.float32)
        pts[0, :3] = [np.float32(1e-30), np.float32(-3.4e38), np.float32(np.pi)]  # extreme finite values
        scans.append(pts)
        if ext == "bin":
            write_scan_bin(root / "velodyne" / f"{i:06d}.bin", pts[:, :3], pts[:, 3])
        else:
            write_points_ply(root / "velodyne" / f"{i:06d}.ply", pts[:, :3])
    poses = random_poses(n if n_poses is None else n_poses, seed=seed + 1)
    write_poses(root / "poses.txt", poses)
    Tr = tr_matrix()
    if calib:
        write_calib(root / "calib.txt", Tr)
    return scans, poses, Tr


# ------------------------------------------------------------------------------------------------
# KITTI round trip and the pose convention
# ------------------------------------------------------------------------------------------------


def test_kitti_roundtrip_points_bitwise_and_lidar_poses(tmp_path):
    scans, poses_cam, Tr = make_kitti(tmp_path)
    seq = open_sequence(tmp_path)
    assert seq.kind == "kitti" and len(seq) == len(scans)
    np.testing.assert_array_equal(read_poses(tmp_path / "poses.txt"), poses_cam)  # exact round trip
    np.testing.assert_array_equal(read_calib(tmp_path / "calib.txt"), Tr)
    expected = np.linalg.inv(Tr) @ poses_cam @ Tr  # SHINE / N3 convention
    np.testing.assert_allclose(seq.poses, expected, rtol=0, atol=1e-12)
    for i, frame in enumerate(seq):
        assert isinstance(frame, SensorFrame) and frame.index == i
        assert frame.points.dtype == np.float32 and frame.points.shape == (len(scans[i]), 3)
        assert frame.points.tobytes() == np.ascontiguousarray(scans[i][:, :3]).tobytes()
        assert frame.pose.dtype == np.float64 and frame.pose.shape == (4, 4)
        np.testing.assert_allclose(frame.pose, expected[i], rtol=0, atol=1e-12)
    # the chain the convention encodes: LiDAR point -> camera frame (Tr) -> camera world (pose) ->
    # LiDAR-aligned world (Tr^-1); and it differs from taking poses.txt as LiDAR poses
    p_s = np.array([3.0, -2.0, 0.5, 1.0])
    np.testing.assert_allclose(seq.poses[2] @ p_s, se3_inverse(Tr) @ (poses_cam[2] @ (Tr @ p_s)), atol=1e-9)
    assert np.linalg.norm(seq.poses[2] @ p_s - poses_cam[2] @ p_s) > 0.1


def test_scan_bin_intensity_layout(tmp_path):
    p = tmp_path / "s.bin"
    pts = np.arange(12, dtype=np.float32).reshape(4, 3)
    write_scan_bin(p, pts, intensity=np.array([9, 8, 7, 6]))
    raw = np.fromfile(p, dtype="<f4").reshape(-1, 4)
    np.testing.assert_array_equal(raw[:, :3], pts)
    np.testing.assert_array_equal(raw[:, 3], [9, 8, 7, 6])
    write_scan_bin(p, pts)
    assert np.fromfile(p, dtype="<f4").reshape(-1, 4)[:, 3].tolist() == [0, 0, 0, 0]


def test_calib_ignores_other_lines_and_missing_calib_is_identity(tmp_path, caplog):
    scans, poses_cam, Tr = make_kitti(tmp_path, n=3, calib=False)
    with caplog.at_level(logging.INFO, logger="jaxmap"):
        seq = open_sequence(tmp_path)
        open_sequence(tmp_path)
    np.testing.assert_array_equal(seq.poses, poses_cam)  # Tr = identity
    assert sum("no calib.txt" in r.getMessage() for r in caplog.records) == 1  # logged once
    p0 = "P0: 7.188560000000e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0\n"
    (tmp_path / "calib.txt").write_text(p0 + "P1: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: "
                                        + " ".join(repr(float(v)) for v in Tr[:3].ravel()) + "\n")
    np.testing.assert_array_equal(read_calib(tmp_path / "calib.txt"), Tr)
    np.testing.assert_allclose(open_sequence(tmp_path).poses, np.linalg.inv(Tr) @ poses_cam @ Tr, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(1e-6, 1e6))
def test_poses_roundtrip_exact_property(tmp_path_factory, seed, scale):
    d = tmp_path_factory.mktemp("poses")
    poses = random_poses(5, seed=seed, scale=scale)
    write_poses(d / "poses.txt", poses)
    np.testing.assert_array_equal(read_poses(d / "poses.txt"), poses)
    write_calib(d / "calib.txt", poses[0])
    np.testing.assert_array_equal(read_calib(d / "calib.txt"), poses[0])


def test_ply_and_pcd_scans(tmp_path):
    import open3d as o3d

    scans, poses, _ = make_kitti(tmp_path, n=2, ext="ply")
    seq = open_sequence(tmp_path)
    assert seq.frame(1).points.tobytes() == np.ascontiguousarray(scans[1][:, :3]).tobytes()
    pts = np.random.default_rng(3).normal(size=(500, 3)).astype(np.float32)
    for name, kw in [("a.pcd", dict(write_ascii=True)), ("b.pcd", dict(write_ascii=False)),
                     ("c.pcd", dict(write_ascii=False, compressed=True)), ("d.ply", dict(write_ascii=True)),
                     ("e.ply", dict(write_ascii=False))]:
        pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts))
        assert o3d.t.io.write_point_cloud(str(tmp_path / name), pc, **kw)
        np.testing.assert_allclose(read_scan(tmp_path / name), pts, atol=1e-5, err_msg=name)


def test_points_and_mesh_ply_roundtrip_and_interop(tmp_path):
    import open3d as o3d
    import trimesh

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(1000, 3)).astype(np.float32)
    nrm = rng.normal(size=(1000, 3)).astype(np.float32)
    write_points_ply(tmp_path / "p.ply", pts, nrm)
    p2, n2 = read_points_ply(tmp_path / "p.ply", return_normals=True)
    assert p2.tobytes() == pts.tobytes() and n2.tobytes() == nrm.tobytes()
    assert read_points_ply(tmp_path / "p.ply").tobytes() == pts.tobytes()
    np.testing.assert_array_equal(o3d.t.io.read_point_cloud(str(tmp_path / "p.ply")).point.positions.numpy(), pts)
    box = trimesh.creation.box(extents=[1, 2, 3])
    write_mesh_ply(tmp_path / "m.ply", box.vertices, box.faces)
    v, f = read_mesh_ply(tmp_path / "m.ply")
    np.testing.assert_array_equal(v, box.vertices.astype(np.float32))
    np.testing.assert_array_equal(f, box.faces)
    back = trimesh.load(tmp_path / "m.ply", force="mesh", process=False)
    assert back.is_watertight and abs(back.volume - 6.0) < 1e-5
    m = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    assert len(m.triangles) == 12
    # meshes written by trimesh (ascii and binary) read back too
    for enc in ("ascii", "binary"):
        (tmp_path / f"t_{enc}.ply").write_bytes(trimesh.exchange.ply.export_ply(box, encoding=enc))
        v, f = read_mesh_ply(tmp_path / f"t_{enc}.ply")
        np.testing.assert_allclose(v, box.vertices, atol=1e-6)
        np.testing.assert_array_equal(f, box.faces)


# ------------------------------------------------------------------------------------------------
# selection
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("begin,end,every,expect", [
    (0, -1, 1, list(range(10))),
    (2, -1, 1, list(range(2, 10))),
    (0, 5, 1, [0, 1, 2, 3, 4]),
    (1, 8, 3, [1, 4, 7]),
    (3, -1, 4, [3, 7]),
    (0, 100, 5, [0, 5]),  # end past the last frame is clamped
    (9, -1, 1, [9]),
])
def test_frame_selection(tmp_path, begin, end, every, expect):
    scans, poses_cam, Tr = make_kitti(tmp_path, n=10)
    seq = open_sequence(tmp_path, begin_frame=begin, end_frame=end, every_frame=every)
    assert len(seq) == len(expect)
    assert [f.index for f in seq] == expect
    assert seq.indices.tolist() == expect
    full = np.linalg.inv(Tr) @ poses_cam @ Tr
    np.testing.assert_allclose(seq.poses, full[expect], atol=1e-12)
    for i, idx in enumerate(expect):
        fr = seq.frame(i)
        assert fr.index == idx and fr.points.shape[0] == len(scans[idx])
    assert seq.frame(-1).index == expect[-1]
    with pytest.raises(IndexError):
        seq.frame(len(expect))


@pytest.mark.parametrize("kw,msg", [(dict(begin_frame=10), "no frames selected"),
                                    (dict(begin_frame=5, end_frame=5), "no frames selected"),
                                    (dict(every_frame=0), "every_frame"),
                                    (dict(begin_frame=-1), "begin_frame")])
def test_bad_selection(tmp_path, kw, msg):
    make_kitti(tmp_path, n=10)
    with pytest.raises(DataError, match=msg):
        open_sequence(tmp_path, **kw)


def test_iteration_is_lazy(tmp_path):
    make_kitti(tmp_path, n=4)
    seq = open_sequence(tmp_path)
    os.remove(tmp_path / "velodyne" / "000003.bin")  # only read when frame 3 is reached
    it = iter(seq)
    assert next(it).index == 0
    with pytest.raises(DataError, match="000003.bin"):
        list(it)


# ------------------------------------------------------------------------------------------------
# errors a user can act on
# ------------------------------------------------------------------------------------------------


def test_missing_directory(tmp_path):
    with pytest.raises(DataError, match="nope"):
        open_sequence(tmp_path / "nope")
    for kind in ("kitti", "depth"):
        with pytest.raises(DataError, match="nope"):
            open_sequence(tmp_path / "nope", kind=kind)


def test_unknown_layout_names_both(tmp_path):
    with pytest.raises(DataError) as e:
        open_sequence(tmp_path)
    assert str(tmp_path) in str(e.value) and "velodyne" in str(e.value) and "depth" in str(e.value)


def test_missing_poses(tmp_path):
    make_kitti(tmp_path, n=2)
    os.remove(tmp_path / "poses.txt")
    with pytest.raises(DataError, match="poses.txt"):
        open_sequence(tmp_path)


def test_no_scans(tmp_path):
    (tmp_path / "velodyne").mkdir()
    (tmp_path / "velodyne" / "readme.txt").write_text("x")
    write_poses(tmp_path / "poses.txt", random_poses(2))
    with pytest.raises(DataError, match="no scans found"):
        open_sequence(tmp_path)


def test_truncated_bin(tmp_path):
    make_kitti(tmp_path, n=3)
    p = tmp_path / "velodyne" / "000001.bin"
    p.write_bytes(p.read_bytes()[:-5])
    seq = open_sequence(tmp_path)
    with pytest.raises(DataError, match=r"000001\.bin.*multiple of 16.*truncated or not KITTI float32 x,y,z,i"):
        seq.frame(1)


def test_fewer_poses_than_scans(tmp_path):
    make_kitti(tmp_path, n=5, n_poses=3)
    with pytest.raises(DataError, match=r"poses\.txt: 3 poses for 5 scans"):
        open_sequence(tmp_path)


def test_more_poses_than_scans_warns(tmp_path, caplog):
    make_kitti(tmp_path, n=3, n_poses=5)
    with caplog.at_level(logging.WARNING, logger="jaxmap"):
        assert len(open_sequence(tmp_path)) == 3
    assert "5 poses for 3 scans" in caplog.text


def test_pose_line_with_11_numbers(tmp_path):
    make_kitti(tmp_path, n=4)
    lines = (tmp_path / "poses.txt").read_text().splitlines()
    lines[2] = " ".join(lines[2].split()[:11])
    (tmp_path / "poses.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"poses\.txt line 3: expected 12 numbers.*found 11"):
        open_sequence(tmp_path)


def test_pose_line_not_a_number(tmp_path):
    make_kitti(tmp_path, n=2)
    lines = (tmp_path / "poses.txt").read_text().splitlines()
    lines[1] = lines[1].replace(lines[1].split()[3], "abc", 1)
    (tmp_path / "poses.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"poses\.txt line 2: not a number"):
        read_poses(tmp_path / "poses.txt")


def test_non_orthonormal_rotation(tmp_path):
    make_kitti(tmp_path, n=3)
    poses = read_poses(tmp_path / "poses.txt")
    poses[1, :3, :3] *= 1.1  # a scaled rotation
    write_poses(tmp_path / "poses.txt", poses)
    with pytest.raises(PoseError, match=r"poses\.txt line 2.*not orthonormal"):
        open_sequence(tmp_path)
    Tr = tr_matrix()
    Tr[0, 0] += 0.2
    write_calib(tmp_path / "calib.txt", Tr)
    write_poses(tmp_path / "poses.txt", random_poses(3))
    with pytest.raises(PoseError, match=r"calib\.txt line 1"):
        open_sequence(tmp_path)


def test_calib_without_tr(tmp_path):
    make_kitti(tmp_path, n=2)
    (tmp_path / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DataError, match=r"calib\.txt: no 'Tr:' line"):
        open_sequence(tmp_path)


def test_nan_points_dropped_with_warning(tmp_path, caplog):
    make_kitti(tmp_path, n=2)
    pts = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    pts[[3, 7, 8], 1] = np.nan
    pts[11, 0] = np.inf
    pts[20, 2] = -np.inf
    write_scan_bin(tmp_path / "velodyne" / "000001.bin", pts)
    seq = open_sequence(tmp_path)
    with caplog.at_level(logging.WARNING, logger="jaxmap"):
        fr = seq.frame(1)
    assert fr.points.shape == (45, 3) and np.isfinite(fr.points).all()
    np.testing.assert_array_equal(fr.points, np.delete(pts, [3, 7, 8, 11, 20], axis=0))
    warn = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warn) == 1 and "000001.bin" in warn[0].getMessage() and "dropped 5 of 50" in warn[0].getMessage()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="jaxmap"):
        seq.frame(0)
    assert not caplog.records


def test_unreadable_ply_and_pcd(tmp_path):
    (tmp_path / "bad.ply").write_bytes(b"not a ply at all\n")
    (tmp_path / "bad.pcd").write_bytes(b"garbage\x00\x01")
    (tmp_path / "x.xyz").write_text("1 2 3\n")
    for name, msg in [("bad.ply", "not a PLY"), ("bad.pcd", "PCD"), ("x.xyz", "unsupported scan format"),
                      ("missing.bin", "not found")]:
        with pytest.raises(DataError, match=name.replace(".", r"\.") + ".*" + msg):
            read_scan(tmp_path / name)
    write_points_ply(tmp_path / "t.ply", np.zeros((100, 3), np.float32))
    raw = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(raw[:-7])
    with pytest.raises(DataError, match=r"t\.ply.*truncated"):
        read_scan(tmp_path / "t.ply")
    hdr = b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 10\nHEIGHT 1\n" \
          b"POINTS 10\nDATA binary\n"
    (tmp_path / "t.pcd").write_bytes(hdr + b"\x00" * 40)
    with pytest.raises(DataError, match=r"t\.pcd.*truncated"):
        read_scan(tmp_path / "t.pcd")


# ------------------------------------------------------------------------------------------------
# depth sequences
# ------------------------------------------------------------------------------------------------


def make_depth(root, n=3, W=8, H=6, seed=0):
    rng = np.random.default_rng(seed)
    depths = []
    for i in range(n):
        d = rng.integers(1, 65535, size=(H, W)).astype(np.uint16)
        d[0, 0] = 0  # no return
        d[H - 1, W - 2] = 0
        write_depth_png(root / "depth" / f"{i:06d}.png", d)
        depths.append(d)
    write_intrinsics(root / "intrinsics.txt", 5.0, 6.0, 3.5, 2.5)
    poses = random_poses(n, seed=seed + 1)
    write_poses(root / "poses.txt", poses)
    return depths, poses


def test_depth_sequence_backprojection(tmp_path):
    depths, poses = make_depth(tmp_path)
    seq = open_sequence(tmp_path)
    assert seq.kind == "depth" and len(seq) == 3
    np.testing.assert_array_equal(seq.poses, poses)  # T_world_camera, no calibration
    assert read_intrinsics(tmp_path / "intrinsics.txt") == (5.0, 6.0, 3.5, 2.5, 1000.0)
    fr = seq.frame(1)
    d = depths[1]
    np.testing.assert_array_equal(read_depth_png(tmp_path / "depth" / "000001.png"), d)  # 16-bit round trip
    assert fr.points.shape == (d.size - 2, 3) and fr.points.dtype == np.float32
    # pixel (u=col, v=row) with depth z -> ((u - cx) z / fx, (v - cy) z / fy, z), row-major order
    v, u = 4, 7
    z = d[v, u] / 1000.0
    k = v * d.shape[1] + u - 1  # one invalid pixel (0, 0) precedes it
    np.testing.assert_allclose(fr.points[k], [(u - 3.5) * z / 5.0, (v - 2.5) * z / 6.0, z], rtol=1e-6)
    assert (fr.points[:, 2] > 0).all()


def test_depth_scale_and_errors(tmp_path):
    make_depth(tmp_path, n=2)
    (tmp_path / "intrinsics.txt").write_text("5 6 3.5 2.5 5000\n")  # TUM-style units
    seq = open_sequence(tmp_path, kind="depth")
    d = read_depth_png(tmp_path / "depth" / "000000.png")
    np.testing.assert_allclose(seq.frame(0).points[:, 2], d.ravel()[d.ravel() > 0] / 5000.0, rtol=1e-6)
    (tmp_path / "intrinsics.txt").write_text("5 6 3.5\n")
    with pytest.raises(DataError, match=r"intrinsics\.txt.*expected 4 numbers"):
        open_sequence(tmp_path)
    os.remove(tmp_path / "intrinsics.txt")
    with pytest.raises(DataError, match=r"intrinsics\.txt: missing"):
        open_sequence(tmp_path)
    write_intrinsics(tmp_path / "intrinsics.txt", 5, 6, 3.5, 2.5)
    write_poses(tmp_path / "poses.txt", random_poses(1))
    with pytest.raises(DataError, match=r"poses\.txt: 1 poses for 2 depth images"):
        open_sequence(tmp_path)
    write_poses(tmp_path / "poses.txt", random_poses(2))
    from PIL import Image

    Image.fromarray(np.zeros((6, 8), np.uint8)).save(tmp_path / "depth" / "000001.png")
    with pytest.raises(DataError, match=r"000001\.png.*16-bit"):
        open_sequence(tmp_path).frame(1)
    os.remove(tmp_path / "poses.txt")
    with pytest.raises(DataError, match=r"poses\.txt: missing"):
        open_sequence(tmp_path)
    for p in (tmp_path / "depth").iterdir():
        os.remove(p)
    with pytest.raises(DataError, match="no depth images"):
        open_sequence(tmp_path)


def test_gt_paths(tmp_path):
    make_kitti(tmp_path, n=2)
    seq = open_sequence(tmp_path)
    assert seq.gt_points_path is None and seq.gt_mesh_path is None
    write_points_ply(tmp_path / "gt_points.ply", np.zeros((3, 3)))
    seq = open_sequence(tmp_path)
    assert seq.gt_points_path == os.path.join(str(tmp_path), "gt_points.ply") and seq.gt_mesh_path is None


def test_ply_points_read_in_pieces_are_the_whole_file_in_order(tmp_path):
    """`read_points_ply_chunks`: a binary file (memory-mapped, also big-endian and with an element before
    the vertices) and an ascii one (parsed whole) give, piece after piece, exactly what `read_points_ply`
    gives, with normals and classes; pieces are at most `chunk` rows."""
    import trimesh

    from jaxmap.io import read_points_ply_chunks

    rng = np.random.default_rng(3)
    pts = rng.normal(size=(1003, 3)).astype(np.float32)
    nrm = rng.normal(size=(1003, 3)).astype(np.float32)
    cls = rng.integers(0, 8, 1003).astype(np.uint8)
    write_points_ply(tmp_path / "p.ply", pts, nrm, cls)
    body = (tmp_path / "p.ply").read_bytes()
    head, data = body.split(b"end_header\n", 1)
    # big-endian, with a fixed-row element before the vertices
    rows = np.frombuffer(data, np.dtype([("p", "<f4", 6), ("c", "u1")]))
    big = np.zeros(len(rows), np.dtype([("p", ">f4", 6), ("c", "u1")]))
    big["p"], big["c"] = rows["p"], rows["c"]
    (tmp_path / "b.ply").write_bytes(
        head.replace(b"binary_little_endian", b"binary_big_endian").replace(
            b"element vertex", b"element extra 2\nproperty double t\nelement vertex") + b"end_header\n"
        + np.array([1.0, 2.0], ">f8").tobytes() + big.tobytes())
    cloud = trimesh.PointCloud(pts)
    (tmp_path / "a.ply").write_bytes(trimesh.exchange.ply.export_ply(cloud, encoding="ascii"))
    for name, with_extras in (("p.ply", True), ("b.ply", True), ("a.ply", False)):
        pieces = list(read_points_ply_chunks(tmp_path / name, chunk=100))
        assert [len(p) for p, _, _ in pieces] == [100] * 10 + [3], name
        whole_p, whole_n, whole_c = read_points_ply(tmp_path / name, return_normals=True, return_classes=True)
        np.testing.assert_array_equal(np.concatenate([p for p, _, _ in pieces]), whole_p)
        np.testing.assert_allclose(whole_p, pts, atol=1e-6)
        if with_extras:
            np.testing.assert_array_equal(np.concatenate([n for _, n, _ in pieces]), nrm)
            np.testing.assert_array_equal(np.concatenate([c for _, _, c in pieces]), cls)
        else:
            assert all(n is None and c is None for _, n, c in pieces)
    (tmp_path / "t.ply").write_bytes(body[:-50])
    with pytest.raises(DataError, match="truncated"):
        next(read_points_ply_chunks(tmp_path / "t.ply"))
