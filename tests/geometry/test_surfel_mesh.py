"""The surfel mesher: accuracy on a known sphere, coverage, no faces across gaps, chunk seams."""
import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from surfelwarp.data_tools.geometry import TriangleMesh
from surfelwarp.geometry.surfel_mesh import mesh_surfels, voxel_size_for


def sphere_surfels(radius=0.1, spacing=0.0015, centre=(0.0, 0.0, 1.0)):
    """Points about `spacing` apart on a sphere (Fibonacci lattice), outward normals."""
    n = int(4 * np.pi * radius ** 2 / spacing ** 2)
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    normals = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    return np.asarray(centre) + radius * normals, normals


def plate(x0, x1, spacing=0.0015, z=1.0, y=(-0.05, 0.05)):
    xs, ys = np.meshgrid(np.arange(x0, x1, spacing), np.arange(*y, spacing))
    points = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], 1)
    return points, np.tile([0.0, 0.0, -1.0], (len(points), 1))


def test_sphere_vertices_lie_on_it_and_cover_it():
    points, normals = sphere_surfels()
    mesh = mesh_surfels(points, normals, voxel_m=0.002)
    r = np.linalg.norm(mesh.vertices - [0, 0, 1], axis=1)
    assert np.median(np.abs(r - 0.1)) < 2e-4 and np.abs(r - 0.1).max() < 1e-3
    # every surfel has mesh within 1 mm (the faces cover what the surfels cover)
    near = TriangleMesh(mesh.vertices.astype(np.float64), mesh.faces).query(points)
    assert np.mean(near.distance < 1e-3) > 0.99
    # normals from the surfels, faces wound about them
    assert np.median(np.einsum("ij,ij->i", mesh.normals, (mesh.vertices - [0, 0, 1]) / r[:, None])) > 0.999
    tri = mesh.vertices[mesh.faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.mean(np.einsum("ij,ij->i", face_n, tri.mean(1) - [0, 0, 1]) > 0) > 0.99


@pytest.mark.parametrize("gap_m", [0.021, 0.03])
def test_no_faces_across_a_gap(gap_m):
    a, na = plate(-0.05, -gap_m / 2)
    b, nb = plate(gap_m / 2 + 1e-9, 0.05)
    mesh = mesh_surfels(np.concatenate([a, b]), np.concatenate([na, nb]), voxel_m=0.002)
    inside = np.abs(mesh.vertices[:, 0]) < gap_m / 2 - 0.004
    assert len(mesh.faces) > 1000 and not inside.any()
    # no triangle joins the two plates
    x = mesh.vertices[mesh.faces][..., 0]
    assert not np.any((x.min(1) < 0) & (x.max(1) > 0))


def test_chunk_seams_are_merged():
    points, normals = sphere_surfels(radius=0.05)
    whole = mesh_surfels(points, normals, voxel_m=0.002, chunk=256)
    cut = mesh_surfels(points, normals, voxel_m=0.002, chunk=7)
    assert len(cut.vertices) == len(whole.vertices) and len(cut.faces) == len(whole.faces)
    d, _ = KDTree(whole.vertices).query(cut.vertices, k=1)
    assert d.max() < 1e-6
    # closed: every edge in exactly two faces
    edges = np.sort(np.concatenate([cut.faces[:, [0, 1]], cut.faces[:, [1, 2]], cut.faces[:, [2, 0]]]), 1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)


def test_colours_and_degenerate_input():
    a, na = plate(-0.05, 0.0)
    b, nb = plate(0.0, 0.05)
    colors = np.concatenate([np.tile([255, 0, 0], (len(a), 1)), np.tile([0, 0, 255], (len(b), 1))])
    mesh = mesh_surfels(np.concatenate([a, b]), np.concatenate([na, nb]), 0.002, colors)
    left, right = mesh.vertices[:, 0] < -0.01, mesh.vertices[:, 0] > 0.01
    assert np.all(mesh.colors[left] == [255, 0, 0]) and np.all(mesh.colors[right] == [0, 0, 255])
    # damaged surfels (NaN, a kilometre away) are left out, the rest meshed as before
    junk = np.array([[np.nan, 0, 1], [1e30, 0, 1], [0, 0, 2e3]])
    noisy = mesh_surfels(np.concatenate([a, b, junk]), np.concatenate([na, nb, na[:3]]), 0.002,
                         np.concatenate([colors, colors[:3]]))
    assert np.array_equal(noisy.faces, mesh.faces) and np.array_equal(noisy.vertices, mesh.vertices)
    empty = mesh_surfels(a[:3], na[:3], 0.002, colors[:3])
    assert empty.faces.shape == (0, 3) and empty.colors.shape == (0, 3)
    assert voxel_size_for(np.array([0.001, 0.002, 0.003, np.nan])) == 0.002
    assert voxel_size_for(np.array([])) == 0.004


def test_cells_near_are_the_64_neighbours_of_every_surfels_cell_once_in_order():
    from surfelwarp.geometry.surfel_mesh import _cells_near
    rng = np.random.default_rng(2)
    base = rng.integers(-40, 40, size=(3000, 3))
    base[1000:1500] = base[:500]                       # cells shared by several surfels
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    expected = np.unique((base[:, None, :] + offsets[None]).reshape(-1, 3), axis=0)
    assert np.array_equal(_cells_near(base), expected)
    assert np.array_equal(_cells_near(np.array([[5, -7, 0]])), np.unique(offsets + [5, -7, 0], axis=0))


@pytest.mark.parametrize("options", [{}, {"return_inverse": True}, {"return_index": True, "return_inverse": True}])
def test_unique_rows_are_numpys_unique_by_rows(options):
    from surfelwarp.geometry.surfel_mesh import unique_rows
    rng = np.random.default_rng(3)
    for rows in (rng.integers(-9, 9, size=(5000, 3)), rng.integers(0, 3, size=(1, 3)), np.zeros((0, 3), np.int64),
                 np.array([[-2**40, 0, 2**40], [2**40, 0, -2**40], [-2**40, 0, 2**40]])):   # too wide to pack
        expected, got = np.unique(rows, axis=0, **options), unique_rows(rows, **options)
        expected, got = (expected, got) if options else ((expected,), (got,))
        assert len(got) == len(expected)
        for a, b in zip(expected, got):
            assert a.shape == b.shape and np.array_equal(a, b)
