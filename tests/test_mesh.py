"""jaxmap.mesh.extract_mesh: accuracy, stitching of chunks, masking, orientation, watertightness."""
import numpy as np
import pytest
import trimesh

from jaxmap.mesh import extract_mesh, save_mesh

CENTER = np.array([0.31, -0.17, 0.23])
RADIUS = 0.5
RES = 0.05  # R = 10 lattice spacings
CELL = 0.2  # 4 lattice spacings per cell


def sphere_sdf(points):
    p = np.asarray(points, dtype=np.float64)
    return (np.linalg.norm(p - CENTER, axis=1) - RADIUS).astype(np.float32), np.ones(len(p), bool)


def box_cells(lo, hi, cell=CELL, origin=(0.0, 0.0, 0.0)):
    """All cells (integer coords) covering the world box [lo, hi]."""
    o = np.asarray(origin)
    a = np.floor((np.asarray(lo) - o) / cell).astype(int)
    b = np.floor((np.asarray(hi) - o) / cell).astype(int)
    g = np.meshgrid(*[np.arange(x, y + 1) for x, y in zip(a, b)], indexing="ij")
    return np.stack(g, axis=-1).reshape(-1, 3)


SPHERE_CELLS = box_cells(CENTER - RADIUS - 0.25, CENTER + RADIUS + 0.25)


@pytest.fixture(scope="module")
def sphere_mesh():
    return extract_mesh(sphere_sdf, SPHERE_CELLS, CELL, RES)


def test_sphere_vertices_on_surface(sphere_mesh):
    # Each vertex is the linear interpolation of the exact SDF along a lattice edge of length h = RES.
    # On a sphere of radius R the SDF along a line has curvature <= 1/R, so the root of the linear
    # interpolant is off by at most h^2 / (8 R) = h / 80 here (R = 10 h); float32 adds ~1e-7 m. The bound
    # h / 10 leaves 8x margin and fails for any misplaced lattice (an origin or half-cell offset moves
    # vertices by >= h / 2) or a wrong sign/scale of the interpolation.
    err = np.abs(np.linalg.norm(sphere_mesh.vertices - CENTER, axis=1) - RADIUS)
    assert len(sphere_mesh.faces) > 1000
    assert err.max() < RES / 10, err.max() / RES


def test_sphere_watertight_and_oriented_outwards(sphere_mesh):
    m = sphere_mesh
    assert m.is_watertight
    assert m.euler_number == 2
    # Normals towards positive sdf (outside): positive signed volume close to the sphere's.
    assert m.volume == pytest.approx(4.0 / 3.0 * np.pi * RADIUS**3, rel=0.01)
    radial = m.triangles_center - CENTER
    assert np.all(np.einsum("ij,ij->i", m.face_normals, radial) > 0)


@pytest.mark.parametrize("chunk_cells", [1, 3])
def test_chunked_equals_single_chunk(chunk_cells):
    # Origin chosen so all cells have non-negative coordinates: chunk_cells=16 puts them in one brick.
    origin = np.array([-0.6, -1.0, -0.6])
    cells = box_cells(CENTER - RADIUS - 0.25, CENTER + RADIUS + 0.25, origin=origin)
    assert cells.min() >= 0 and cells.max() < 16
    single = extract_mesh(sphere_sdf, cells, CELL, RES, origin=origin, chunk_cells=16)
    chunked = extract_mesh(sphere_sdf, cells, CELL, RES, origin=origin, chunk_cells=chunk_cells)
    assert len(chunked.vertices) == len(single.vertices)
    assert len(chunked.faces) == len(single.faces)
    # Same vertex set (to float32 rounding) ...
    from scipy.spatial import cKDTree

    dist, match = cKDTree(single.vertices).query(chunked.vertices)
    assert dist.max() < 1e-5
    assert len(np.unique(match)) == len(match)
    # ... and the same oriented triangles.
    def canon(f):
        r = np.argmin(f, axis=1)
        return {tuple(f[i, (r[i] + k) % 3] for k in range(3)) for i in range(len(f))}

    assert canon(match[chunked.faces]) == canon(np.asarray(single.faces))
    assert chunked.is_watertight


def test_invalid_samples_produce_no_triangles():
    x_cut = 0.33

    def half_valid(points):
        s, _ = sphere_sdf(points)
        return s, points[:, 0] < x_cut

    m = extract_mesh(half_valid, SPHERE_CELLS, CELL, RES, chunk_cells=2)
    assert len(m.faces) > 100
    # A triangle needs all 8 corners of its cube valid, so every vertex lies at or below the last lattice
    # plane x < x_cut.
    last_plane = np.floor(x_cut / RES - 1e-9) * RES
    assert m.vertices[:, 0].max() <= last_plane + 1e-9
    assert m.vertices[:, 0].max() > last_plane - RES  # and the valid half is meshed up to there
    assert not m.is_watertight  # the cut leaves an open boundary: nothing was invented beyond it


def test_only_given_cells_are_meshed():
    keep = SPHERE_CELLS[SPHERE_CELLS[:, 2] <= 0]  # cells below z = CELL (world), i.e. z index <= 0
    m = extract_mesh(sphere_sdf, keep, CELL, RES)
    assert len(m.faces) > 100
    assert m.vertices[:, 2].max() <= CELL + 1e-9
    # Cells with a hole: drop one cell on the surface; no vertex strictly inside it.
    full = extract_mesh(sphere_sdf, SPHERE_CELLS, CELL, RES)
    c = np.floor((CENTER + [RADIUS, 0, 0]) / CELL).astype(int)  # cell holding the +x pole
    holed = SPHERE_CELLS[~np.all(SPHERE_CELLS == c, axis=1)]
    mh = extract_mesh(sphere_sdf, holed, CELL, RES)
    lo, hi = c * CELL, (c + 1) * CELL
    inside = np.all((mh.vertices > lo + 1e-9) & (mh.vertices < hi - 1e-9), axis=1)
    assert not inside.any()
    assert len(mh.faces) < len(full.faces)


def test_empty_and_no_surface():
    m = extract_mesh(sphere_sdf, np.zeros((0, 3), int), CELL, RES)
    assert isinstance(m, trimesh.Trimesh) and len(m.faces) == 0 and len(m.vertices) == 0
    far = box_cells([5, 5, 5], [6, 6, 6])
    assert len(extract_mesh(sphere_sdf, far, CELL, RES).faces) == 0
    none_valid = extract_mesh(lambda p: (sphere_sdf(p)[0], np.zeros(len(p), bool)), SPHERE_CELLS, CELL, RES)
    assert len(none_valid.faces) == 0


def test_cell_size_must_be_multiple_of_resolution():
    with pytest.raises(ValueError, match="integer multiple"):
        extract_mesh(sphere_sdf, SPHERE_CELLS, 0.2, 0.03)


def test_batches_are_bounded_powers_of_two_and_jax_outputs_work():
    import jax.numpy as jnp

    sizes = []

    def jax_sdf(points):
        sizes.append(len(points))
        p = jnp.asarray(points)
        return jnp.linalg.norm(p - jnp.asarray(CENTER, dtype=jnp.float32), axis=1) - RADIUS, jnp.ones(len(p), bool)

    m = extract_mesh(jax_sdf, SPHERE_CELLS, CELL, RES, max_points_per_call=8192)
    assert m.is_watertight
    assert all(s <= 8192 and (s & (s - 1)) == 0 for s in sizes)
    assert len(set(sizes)) <= 2  # 4096 and 8192 at most: a jitted sdf_fn compiles few shapes


def test_min_component_faces_drops_small_parts():
    small_c, small_r = np.array([1.6, 0.0, 0.0]), 0.08

    def two_spheres(points):
        p = np.asarray(points, dtype=np.float64)
        a = np.linalg.norm(p - CENTER, axis=1) - RADIUS
        b = np.linalg.norm(p - small_c, axis=1) - small_r
        return np.minimum(a, b).astype(np.float32), np.ones(len(p), bool)

    cells = box_cells([-0.5, -0.8, -0.5], [1.8, 0.5, 0.8])
    both = extract_mesh(two_spheres, cells, CELL, RES)
    big_only = extract_mesh(two_spheres, cells, CELL, RES, min_component_faces=200)
    assert len(both.split(only_watertight=False)) == 2
    assert len(big_only.split(only_watertight=False)) == 1
    assert np.abs(big_only.vertices - small_c).sum(axis=1).min() > 0.5


def test_save_mesh_roundtrip(tmp_path, sphere_mesh):
    from jaxmap.io import read_mesh_ply

    path = save_mesh(sphere_mesh, tmp_path / "sub" / "sphere.ply")
    v, f = read_mesh_ply(path)
    assert len(f) == len(sphere_mesh.faces)
    np.testing.assert_allclose(v, sphere_mesh.vertices, atol=1e-6)
    empty = save_mesh(extract_mesh(sphere_sdf, np.zeros((0, 3), int), CELL, RES), tmp_path / "empty.ply")
    assert trimesh.load(empty, force="mesh").faces.shape[0] == 0
