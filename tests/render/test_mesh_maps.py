import numpy as np
import pytest

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.render.mesh_maps import render_mesh_maps

K = Intrinsics(400.0, 410.0, 159.5, 119.5, 320, 240)


pytestmark = pytest.mark.usefixtures("gl")     # every test here renders


def pixel_rays(intr=K):
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    return np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], -1)


def uv_sphere(centre, radius, n_lon, n_lat):
    theta = np.linspace(0, np.pi, n_lat + 1)
    phi = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    normals = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    i, j = np.arange(n_lat)[:, None], np.arange(n_lon)[None, :]
    a, b = i * n_lon + j, i * n_lon + (j + 1) % n_lon
    c, d = a + n_lon, b + n_lon
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return (centre + radius * normals).astype(np.float32), normals.astype(np.float32), faces.astype(np.int32)


def plane_grid(origin, e1, e2, step, n1, n2):
    """Vertex (i, j) = origin + step (i e1 + j e2), index i * (n2 + 1) + j; cell (i, j) is cut
    along its diagonal from (i, j) to (i+1, j+1)."""
    i, j = np.meshgrid(np.arange(n1 + 1), np.arange(n2 + 1), indexing="ij")
    verts = origin + step * (i[..., None] * e1 + j[..., None] * e2)
    vid = lambda a, b: a * (n2 + 1) + b   # noqa: E731
    ci, cj = np.meshgrid(np.arange(n1), np.arange(n2), indexing="ij")
    a, b, c, d = vid(ci, cj), vid(ci + 1, cj), vid(ci, cj + 1), vid(ci + 1, cj + 1)
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    verts = verts.reshape(-1, 3).astype(np.float32)
    normals = np.tile(np.cross(e1, e2), (len(verts), 1)).astype(np.float32)
    return verts, normals, faces.astype(np.int32)


def test_sphere_maps_match_ray_cast():
    centre, radius = np.array([0.02, -0.01, 0.45]), 0.12
    verts, normals, faces = uv_sphere(centre, radius, 200, 120)
    maps = render_mesh_maps(verts, normals, faces, K)
    d = pixel_rays()
    a, b = (d * d).sum(-1), d @ centre
    disc = b * b - a * (centre @ centre - radius ** 2)
    t = (b - np.sqrt(np.maximum(disc, 0))) / a
    hit = disc > 0
    point = d * t[..., None]
    drawn = maps.index >= 0
    rim = np.abs(disc) < 0.02 * radius ** 2 * a          # a pixel or two along the silhouette
    assert (drawn == hit)[~rim].all() and hit.sum() > 20_000
    interior = hit & ~rim
    err = np.abs(maps.vertex[..., 2] - point[..., 2])[interior]
    assert err.max() < 0.5e-3 and err.mean() < 0.05e-3
    # The vertex is where the pixel centre ray meets a facet: on the ray to float precision.
    off_ray = np.linalg.norm(np.cross(maps.vertex[drawn].astype(np.float64), d[drawn]), axis=1) \
        / np.linalg.norm(d[drawn], axis=1)
    assert off_ray.max() < 1e-6
    cos = (maps.normal * (point - centre) / radius).sum(-1)[interior]
    assert cos.min() > np.cos(np.radians(0.5))
    # The index is a corner of the hit facet: within one edge length of the surface point.
    edge = np.linalg.norm(verts[faces] - verts[np.roll(faces, 1, axis=1)], axis=2).max()
    dist = np.linalg.norm(verts[maps.index[drawn]] - maps.vertex[drawn], axis=1)
    assert dist.max() < edge
    assert (maps.vertex[~drawn] == 0).all() and (maps.normal[~drawn] == 0).all()
    assert maps.index.dtype == np.int32 and maps.index.shape == (K.height, K.width)


def test_plane_reaching_behind_the_camera_depth_and_nearest_corner():
    # A tilted plane z = 0.5 + 0.6 y (camera frame) whose upper part passes behind the camera:
    # triangles there must be clipped in clip space, not divided by a negative z and smeared
    # over the image.
    e1 = np.array([1.0, 0.0, 0.0])
    e2 = np.array([0.0, 1.0, 0.6]) / np.linalg.norm([0.0, 1.0, 0.6])
    origin = np.array([-0.7, -1.3, 0.5 - 0.6 * 1.3]) + 1e-4 * np.array([0.37, 0.0, 0.0])
    step, n1, n2 = 0.02, 70, 120
    verts, normals, faces = plane_grid(origin, e1, e2, step, n1, n2)
    assert verts[:, 2].min() < -0.1
    maps = render_mesh_maps(verts, normals, faces, K)
    d = pixel_rays()
    nrm = np.cross(e1, e2)
    t = (origin @ nrm) / (d @ nrm)
    point = d * t[..., None]
    alpha = (point - origin) @ e1 / step
    beta = (point - origin) @ e2 / step
    on = (alpha > 0) & (alpha < n1) & (beta > 0) & (beta < n2) & (t > 0)
    drawn = maps.index >= 0
    assert on.sum() > 0.9 * on.size
    edge = (np.minimum(alpha % 1, 1 - alpha % 1) < 1e-3) | (np.minimum(beta % 1, 1 - beta % 1) < 1e-3)
    assert (drawn == on)[~edge].all()
    err = np.abs(maps.vertex - point)[on]
    assert err.max() < 2e-6
    assert np.allclose(maps.normal[on], nrm, atol=1e-6)
    # Expected index: the corner of the containing triangle nearest to the point. Corner offsets
    # (di, dj) in the cell: (0, 0), (1, 1) and (1, 0) above the diagonal or (0, 1) below it.
    ci, cj = np.floor(alpha).astype(int), np.floor(beta).astype(int)
    fa, fb = alpha - ci, beta - cj
    upper = fa >= fb
    zero, one = np.zeros(fa.shape, int), np.ones(fa.shape, int)
    di = np.stack([zero, one, upper.astype(int)], -1)
    dj = np.stack([zero, one, (~upper).astype(int)], -1)
    dist = (fa[..., None] - di) ** 2 + (fb[..., None] - dj) ** 2
    best = np.argmin(dist, -1)[..., None]
    expected = ((ci + np.take_along_axis(di, best, -1)[..., 0]) * (n2 + 1)
                + cj + np.take_along_axis(dj, best, -1)[..., 0])
    gap = np.sort(dist, -1)
    clear = on & ~edge & (np.abs(fa - fb) > 1e-3) & (gap[..., 1] - gap[..., 0] > 1e-3)
    assert clear.sum() > 0.9 * on.sum()
    assert (maps.index[clear] == expected[clear]).all()


def test_nearer_mesh_wins_and_inputs_are_checked():
    verts_p, normals_p, faces_p = plane_grid(np.array([-0.5, -0.4, 0.8]), np.array([1.0, 0, 0]),
                                             np.array([0, 1.0, 0]), 0.05, 20, 16)
    verts_s, normals_s, faces_s = uv_sphere(np.array([0.0, 0.0, 0.5]), 0.08, 64, 32)
    offset = len(verts_p)
    verts = np.concatenate([verts_p, verts_s])
    normals = np.concatenate([normals_p, normals_s])
    # Sphere faces first: draw order must not matter, the depth test decides.
    faces = np.concatenate([faces_s + offset, faces_p])
    maps = render_mesh_maps(verts, normals, faces, K)
    on_sphere = maps.index >= offset
    assert on_sphere.sum() > 5000 and (maps.index >= 0).all()
    assert (maps.vertex[on_sphere][:, 2] < 0.58 + 1e-6).all()
    assert np.abs(maps.vertex[~on_sphere][:, 2] - 0.8).max() < 1e-6
    with pytest.raises(ValueError):
        render_mesh_maps(verts, normals, faces + len(verts), K)
    with pytest.raises(ValueError):
        render_mesh_maps(verts, normals[:-1], faces, K)
    empty = render_mesh_maps(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3), np.int32), K)
    assert (empty.index == -1).all() and (empty.vertex == 0).all()
