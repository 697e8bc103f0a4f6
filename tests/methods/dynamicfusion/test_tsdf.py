import numpy as np
import pytest

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import invert, se3_exp, transform_points
from surfelwarp.methods.dynamicfusion.tsdf import (TSDFParams, TSDFVolume, extract_mesh, fuse, node_distance_weight)

K = Intrinsics(400.0, 400.0, 159.5, 119.5, 320, 240)
P = TSDFParams()
CENTRE = np.array([0.0, 0.0, 0.4])
RADIUS = 0.08


def look_at(eye, target, up=(0.0, -1.0, 0.0)):
    """T_world_to_camera of a camera at `eye` whose optical axis points at `target`."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])
    T[:3, 3] = -T[:3, :3] @ eye
    return T


def rays(intr):
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    return np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], -1)


def sphere_depth(T_world_to_camera, centre=CENTRE, radius=RADIUS, intr=K, max_view_deg=75.0):
    """Analytic depth (z, metres) of a sphere, 0 where the ray misses it. Like a real sensor (and
    PreprocessParams.max_view_angle_deg), no depth where the view is more grazing than
    max_view_deg: nearest-pixel projective distances are biased there, by up to 2.6 mm here."""
    d = rays(intr)
    c = transform_points(T_world_to_camera, centre[None])[0]
    a = (d * d).sum(-1)
    b = d @ c
    disc = b * b - a * (c @ c - radius ** 2)
    t = (b - np.sqrt(np.maximum(disc, 0))) / a
    normal = (d * t[..., None] - c) / radius
    cos_view = -(normal * d).sum(-1) / np.sqrt(a)
    return np.where((disc > 0) & (cos_view > np.cos(np.radians(max_view_deg))), t * 1.0, 0).astype(np.float32)


def sphere_volume():
    return TSDFVolume.empty(CENTRE - 0.12, (61, 61, 61), 0.004)


def six_views():
    dirs = [(0, 0, -1), (0, 0, 1), (1, 0, 0), (-1, 0, 0), (0, 1, 0.01), (0, -1, 0.01)]
    return [look_at(CENTRE + 0.4 * np.asarray(d, float) / np.linalg.norm(d), CENTRE) for d in dirs]


def radial_error(vertices):
    return np.abs(np.linalg.norm(vertices - CENTRE, axis=1) - RADIUS)


def test_six_views_reconstruct_the_sphere_within_a_millimetre():
    vol = sphere_volume()
    views = six_views()
    assert np.allclose(views[0], np.eye(4))   # the first camera is the world frame
    for T in views:
        res = fuse(vol, vol.voxel_centres(), np.ones(vol.num_voxels, np.float32), T, sphere_depth(T), K, P)
        assert res.updated > 10_000
    v, f, n = extract_mesh(vol)
    err = radial_error(v)
    assert err.mean() < 0.2e-3 and np.percentile(err, 99) < 0.8e-3 and err.max() < 1e-3
    # Closed and complete: the area matches the sphere's, and every normal points outward.
    tri = v[f].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    assert area == pytest.approx(4 * np.pi * RADIUS ** 2, rel=0.01)
    outward = ((v - CENTRE) / np.linalg.norm(v - CENTRE, axis=1, keepdims=True) * n).sum(1)
    assert outward.min() > 0.94 and np.median(outward) > 0.998
    # Faces wind counter-clockwise seen from outside.
    geometric = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert ((geometric * (tri.mean(1) - CENTRE)).sum(1) > 0).all()


def test_single_moved_view_faces_its_camera_and_leaves_deep_voxels_alone():
    T = look_at(CENTRE + 0.4 * np.array([0.6, -0.3, -0.74]) / np.linalg.norm([0.6, -0.3, -0.74]), CENTRE)
    vol = sphere_volume()
    fuse(vol, None, 1.0, T, sphere_depth(T), K, P)
    v, f, n = extract_mesh(vol)
    assert radial_error(v).max() < 1.5e-3 and np.percentile(radial_error(v), 95) < 0.5e-3
    eye = invert(T)[:3, 3]
    to_eye = (eye - v) / np.linalg.norm(eye - v, axis=1, keepdims=True)
    true_normal = (v - CENTRE) / np.linalg.norm(v - CENTRE, axis=1, keepdims=True)
    cos_view = (to_eye * true_normal).sum(1)
    # Normals face the camera; away from the rim of the seen cap (view angle < 60 deg) they are
    # within 6 deg of the truth. The cap's last voxel ring has one-sided, cruder gradients.
    inner = cos_view > 0.5
    assert inner.sum() > 0.6 * len(v)
    assert ((n * true_normal).sum(1)[inner] > 0.995).all() and ((n * to_eye).sum(1)[inner] > 0.45).all()
    assert np.percentile((n * true_normal).sum(1), 95) > 0.99
    # Only the seen cap: nothing on the far side of the sphere.
    assert (((v - CENTRE) @ (eye - CENTRE)) > 0).all()
    # Inside the sphere, voxels deeper than tau behind the seen surface are untouched.
    centres = vol.voxel_centres().astype(np.float64)
    depth_behind = RADIUS - np.linalg.norm(centres - CENTRE, axis=1)
    deep = depth_behind > P.truncation_m + 0.004
    assert deep.sum() > 10_000
    assert (vol.weight.reshape(-1)[deep] == 0).all() and (vol.tsdf.reshape(-1)[deep] == 1).all()


def test_camera_motion_equals_pre_warped_centres_and_a_warp_is_undone():
    T = se3_exp(np.array([0.05, -0.1, 0.03, 0.02, 0.01, -0.03]))
    centres = sphere_volume().voxel_centres()
    depth = sphere_depth(T)
    # A moved camera and an identity camera with the motion folded into the warp are the same.
    a, b = sphere_volume(), sphere_volume()
    fuse(a, centres, np.full(len(centres), 0.5, np.float32), T, depth, K, P)
    fuse(b, transform_points(T, centres.astype(np.float64)).astype(np.float32), 0.5, np.eye(4), depth, K, P)
    assert np.abs(a.tsdf - b.tsdf).max() < 1e-4 and np.array_equal(a.weight > 0, b.weight > 0)
    # Warped use: the live sphere is the canonical one moved by M; fusing with warped centres
    # M x_c must rebuild the canonical sphere, not the live one.
    M = se3_exp(np.array([0.2, 0.1, -0.1, 0.03, -0.02, 0.04]))
    live = sphere_volume()
    for view in six_views()[:3]:
        fuse(live, transform_points(M, centres.astype(np.float64)).astype(np.float32), 1.0, view,
             sphere_depth(view, centre=transform_points(M, CENTRE[None])[0]), K, P)
    v, _, _ = extract_mesh(live)
    assert len(v) > 1000 and np.percentile(radial_error(v), 99) < 1e-3


def plane_volume():
    # 0.4 x 0.4 m wide, wider than the view at 0.5 m (0.4 x 0.3 m), z from 0.44 to 0.56 m.
    # Origin off the round numbers: no voxel projects exactly onto a half-pixel (rounding ties).
    return TSDFVolume.empty((-0.2013, -0.2017, 0.4402), (101, 101, 31), 0.004)


def test_update_rule_matches_equation_5_and_weights_saturate():
    vol = plane_volume()
    centres = vol.voxel_centres()
    z = centres[:, 2].astype(np.float64)
    uv = K.project(centres.astype(np.float64))
    inside = (uv[:, 0] > -0.5) & (uv[:, 0] < K.width - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < K.height - 0.5)
    depth = np.full((K.height, K.width), 0.5, np.float32)
    tau = P.truncation_m

    res = fuse(vol, centres, np.full(len(centres), 0.5, np.float32), np.eye(4), depth, K, P)
    t1, w1 = vol.tsdf.reshape(-1).copy(), vol.weight.reshape(-1).copy()
    front = inside & (z < 0.5 - tau - 1e-4)
    band = inside & (np.abs(z - 0.5) < tau - 1e-4)
    behind = z > 0.5 + tau + 1e-4
    assert band.sum() > 1000 and front.sum() > 1000 and behind.sum() > 1000 and (~inside).sum() > 1000
    assert res.visible == inside.sum() and res.updated == (inside & (z < 0.5 + tau)).sum()
    assert (t1[front] == 1).all() and (w1[front] == 0.5).all()
    assert np.abs(t1[band] - (0.5 - z[band]) / tau).max() < 1e-4 and (w1[band] == 0.5).all()
    assert (t1[behind] == 1).all() and (w1[behind] == 0).all()
    assert (t1[~inside] == 1).all() and (w1[~inside] == 0).all()

    # Second observation 5 mm further, weight 1.5: weighted average of the two truncated values.
    fuse(vol, centres, 1.5, np.eye(4), depth + 0.005, K, P)
    t2, w2 = vol.tsdf.reshape(-1), vol.weight.reshape(-1)
    both = inside & (z > 0.5 - tau + 1e-4) & (z < 0.5 + tau - 1e-4)
    f1 = np.clip((0.5 - z) / tau, -1, 1)
    f2 = np.minimum((0.505 - z) / tau, 1)
    assert np.abs(t2[both] - (0.5 * f1[both] + 1.5 * f2[both]) / 2.0).max() < 1e-4
    assert (w2[both] == 2.0).all()
    only_second = inside & (z > 0.5 + tau + 1e-4) & (z < 0.505 + tau - 1e-4)
    assert only_second.sum() > 0
    assert np.abs(t2[only_second] - f2[only_second]).max() < 1e-4 and (w2[only_second] == 1.5).all()

    # Saturation: the weight stops at w_max, and the value keeps a running average after it.
    for _ in range(70):
        fuse(vol, centres, 1.5, np.eye(4), depth, K, P)
    assert vol.weight.max() == P.max_weight
    sat = both & (vol.weight.reshape(-1) == P.max_weight)
    assert sat.sum() == both.sum()
    before = vol.tsdf.reshape(-1)[sat].copy()
    fuse(vol, centres, 1.5, np.eye(4), depth + 0.005, K, P)
    expected = (before * P.max_weight + f2[sat] * 1.5) / (P.max_weight + 1.5)
    assert np.abs(vol.tsdf.reshape(-1)[sat] - expected).max() < 1e-5
    assert (vol.weight.reshape(-1)[sat] == P.max_weight).all()


def test_invalid_depth_and_zero_weight_leave_voxels_untouched():
    vol = plane_volume()
    depth = np.full((K.height, K.width), 0.5, np.float32)
    depth[:, : K.width // 2] = 0           # no measurement on the left half
    depth[:10] = np.nan
    weights = np.ones(vol.num_voxels, np.float32)
    centres = vol.voxel_centres()
    weights[centres[:, 1] > 0.05] = 0      # caller says: no confidence in the warp there
    fuse(vol, centres, weights, np.eye(4), depth, K, P)
    touched = vol.weight.reshape(-1) > 0
    uv = K.project(centres.astype(np.float64))
    assert touched.sum() > 10_000
    assert (uv[touched, 0] >= K.width // 2 - 0.5).all() and (uv[touched, 1] >= 9.5).all()
    assert (centres[touched, 1] <= 0.05).all()
    assert (vol.tsdf.reshape(-1)[~touched] == 1).all()


def test_mesh_of_one_view_has_no_sheet_behind_the_surface():
    vol = plane_volume()
    depth = np.full((K.height, K.width), 0.5, np.float32)
    fuse(vol, None, 1.0, np.eye(4), depth, K, P)
    v, f, n = extract_mesh(vol)
    # Without the observed-voxel test a second sheet appears where the observed -1 values meet
    # the untouched +1 values, tau behind the plane.
    assert len(f) > 1000
    assert np.abs(v[:, 2] - 0.5).max() < 1e-4
    assert np.allclose(n, [0, 0, -1], atol=1e-3)
    assert extract_mesh(plane_volume())[0].shape == (0, 3)


def test_from_points_bounds_order_and_coarsening():
    rng = np.random.default_rng(1)
    pts = rng.uniform([-0.15, -0.1, 0.5], [0.1, 0.12, 0.8], (1000, 3))
    pts[0] = np.nan
    vol = TSDFVolume.from_points(pts, P)
    c = vol.voxel_centres()
    good = pts[1:]
    assert (c.min(0) <= good.min(0) - P.margin_m + 1e-6).all()
    assert (c.max(0) >= good.max(0) + P.margin_m - 1e-6).all()
    assert (c.max(0) - c.min(0) < good.max(0) - good.min(0) + 2 * P.margin_m + 2 * P.voxel_size_m).all()
    assert vol.voxel_size == P.voxel_size_m and vol.tsdf.dtype == np.float32
    assert vol.nbytes == 8 * vol.num_voxels
    # Flat order: voxel (i, j, k) at flat index of tsdf.ravel().
    i, j, k = 7, 11, 13
    flat = np.ravel_multi_index((i, j, k), vol.dims)
    assert np.allclose(c[flat], vol.origin + vol.voxel_size * np.array([i, j, k]), atol=1e-6)
    assert np.allclose(vol.voxel_centres(flat, flat + 40), c[flat:flat + 40])
    small = TSDFVolume.from_points(pts, TSDFParams(max_voxels=200_000))
    assert small.num_voxels <= 200_000 and small.voxel_size > P.voxel_size_m


def test_node_distance_weight_matches_reference():
    rng = np.random.default_rng(2)
    nodes = rng.uniform(-0.1, 0.1, (40, 3)).astype(np.float32)
    x = rng.uniform(-0.15, 0.15, (500, 3)).astype(np.float32)
    knn = np.argsort(np.linalg.norm(x[:, None] - nodes[None], axis=2), axis=1)[:, :4].astype(np.int32)
    knn[:50, 2:] = -1
    knn[50:60] = -1
    radius = rng.uniform(0.02, 0.03, 40).astype(np.float32)
    w = node_distance_weight(x, nodes, knn, radius, chunk=128)
    ref = np.zeros(500)
    for r in range(500):
        ids = knn[r][knn[r] >= 0]
        if len(ids):
            dbar = np.mean(np.linalg.norm(nodes[ids] - x[r], axis=1) / radius[ids])
            ref[r] = np.exp(-0.5 * dbar ** 2)
    assert np.abs(w - ref).max() < 1e-5 and (w[50:60] == 0).all()
    # Decreasing with distance from the nodes: on a node ~1, three radii away ~0.01.
    one = np.zeros((1, 1), np.int32)
    near_far = node_distance_weight(np.array([[0, 0, 0], [0.075, 0, 0]], np.float32), np.zeros((1, 3)),
                                    np.zeros((2, 1), np.int32), 0.025)
    assert near_far[0] == pytest.approx(1.0) and near_far[1] == pytest.approx(np.exp(-4.5), rel=1e-4)
    assert node_distance_weight(np.zeros((1, 3)), np.zeros((0, 3)), one, 0.025)[0] == 0


def test_fusing_a_voxel_subset_updates_exactly_those_voxels():
    vol = plane_volume()
    centres = vol.voxel_centres()
    rng = np.random.default_rng(2)
    ids = np.sort(rng.choice(vol.num_voxels, vol.num_voxels // 3, replace=False))
    weights = rng.uniform(0.5, 1.5, vol.num_voxels).astype(np.float32)
    depth = np.full((K.height, K.width), 0.5, np.float32)
    full, part = plane_volume(), plane_volume()
    fuse(full, centres, weights, np.eye(4), depth, K, P)
    res = fuse(part, centres[ids], weights[ids], np.eye(4), depth, K, P, voxels=ids)
    t_full, t_part = full.tsdf.reshape(-1), part.tsdf.reshape(-1)
    w_full, w_part = full.weight.reshape(-1), part.weight.reshape(-1)
    assert np.array_equal(t_part[ids], t_full[ids]) and np.array_equal(w_part[ids], w_full[ids])
    rest = np.setdiff1d(np.arange(vol.num_voxels), ids)
    assert (w_part[rest] == 0).all() and (t_part[rest] == 1).all()
    assert res.updated == np.count_nonzero(w_part) > 10_000
    with pytest.raises(ValueError):
        fuse(part, None, 1.0, np.eye(4), depth, K, P, voxels=ids)
    with pytest.raises(ValueError):
        fuse(part, centres[ids], weights, np.eye(4), depth, K, P, voxels=ids)
