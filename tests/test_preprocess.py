import cv2
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.io.sequence import open_sequence
from surfelwarp.preprocess import PreprocessParams, bilateral_filter, preprocess, radius_map

from conftest import shared_data


def plane_depth(intr: Intrinsics, normal, offset):
    """Depth of the plane n.x = offset seen by every pixel."""
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], -1)
    return (offset / (rays @ normal)).astype(np.float32)


def test_plane_normals_vertices_and_radii():
    intr = Intrinsics(500, 500, 159.5, 119.5, 320, 240)
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    depth = plane_depth(intr, n, -1.2 * -n[2])
    obs = preprocess(depth, intr, 0, 0)
    assert obs.valid.sum() > 0.8 * 320 * 240
    # The bilateral window is one-sided within its radius of a hole, which tilts the normal there.
    v = cv2.erode(obs.valid.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    np.testing.assert_allclose(obs.normal_map[v], np.broadcast_to(n, (v.sum(), 3)), atol=1e-3)
    # Vertices lie on the plane (the bilateral filter keeps a plane a plane).
    np.testing.assert_allclose(obs.vertex_map[v] @ n, n[2] * -1.2 * -1, atol=2e-4)
    expected_r = np.sqrt(2) * obs.depth_m[v] / (500 * abs(n[2]))
    np.testing.assert_allclose(obs.radius_map[v], expected_r, rtol=1e-3)


def test_clipping_and_crop():
    intr = Intrinsics(500, 500, 159.5, 119.5, 320, 240)
    depth = np.full((240, 320), 2.0, np.float32)
    depth[:, 200:] = 5.0
    obs = preprocess(depth, intr, 0, 0, PreprocessParams(clip_far_m=3.0, boundary_crop_px=7))
    assert not obs.valid[:, 199:].any() and not obs.valid[:8].any() and not obs.valid[:, :8].any()
    assert obs.valid[8:-8, 8:199].all()


def test_snoopy_frame0_within_paper_ranges():
    seq = open_sequence(shared_data("snoopy-pair"))
    frame, depth = next(seq.frames())
    obs = preprocess(depth, seq.intrinsics, frame.index, 0)
    v = obs.valid
    assert v.sum() > 50_000
    normals = obs.normal_map[v]
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    # Normals face the camera.
    assert (np.sum(normals * obs.vertex_map[v], axis=1) <= 0).all()
    # c = exp(-gamma^2 / (2 * 0.6^2)) with gamma in [0, 1].
    c = obs.confidence_map[v]
    assert c.min() >= np.exp(-1 / (2 * 0.36)) - 1e-6 and c.max() <= 1.0
    # r = sqrt(2) d / (f |n_z|), |n_z| clamped at cos 75 deg.
    ratio = obs.radius_map[v] * seq.intrinsics.focal_px / (np.sqrt(2) * obs.depth_m[v])
    assert ratio.min() >= 1 - 1e-5 and ratio.max() <= 1 / np.cos(np.deg2rad(75)) + 1e-4
    assert (ratio > 1 / np.cos(np.deg2rad(74))).any(), "some grazing views should be clamped"
    # Depth is clipped to the default range and invalid pixels carry no surfel.
    assert obs.depth_m[v].min() >= 0.1 and obs.depth_m[v].max() <= 3.0
    assert (obs.radius_map[~v] == 0).all() and (obs.confidence_map[~v] == 0).all()


def _bilateral_reference(depth, params):
    """The filter as written in the paper, one output pixel at a time (valid neighbours only)."""
    r = params.bilateral_diameter_px // 2
    h, w = depth.shape
    out = np.zeros_like(depth)
    for y, x in zip(*np.nonzero(depth > 0)):
        num = den = 0.0
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                yy, xx = y + dy, x + dx
                if 0 <= yy < h and 0 <= xx < w and depth[yy, xx] > 0:
                    wgt = np.exp(-(dx * dx + dy * dy) / (2 * params.bilateral_sigma_space_px ** 2)
                                 - (depth[yy, xx] - depth[y, x]) ** 2 / (2 * params.bilateral_sigma_depth_m ** 2))
                    num, den = num + wgt * depth[yy, xx], den + wgt
        out[y, x] = num / den
    return out


def test_bilateral_filter_matches_the_per_pixel_definition():
    rng = np.random.default_rng(3)
    depth = (1.0 + 0.01 * rng.standard_normal((24, 30))).astype(np.float32)
    depth[:, 18:] += 0.2                       # an edge the range weight keeps
    depth[rng.random(depth.shape) < 0.15] = 0  # holes, and the image border, take no part
    params = PreprocessParams()
    out = bilateral_filter(depth, params)
    np.testing.assert_allclose(out, _bilateral_reference(depth, params), atol=2e-6)
    assert (out[depth == 0] == 0).all()


def test_bilateral_filter_keeps_a_constant_surface_beside_holes():
    depth = np.full((20, 20), 1.5, np.float32)
    depth[5:9, 5:9] = 0
    out = bilateral_filter(depth, PreprocessParams())
    np.testing.assert_allclose(out[depth > 0], 1.5, rtol=1e-6)


def _normal_map_numpy(vertex_map, depth_m):
    """normal_map in whole-image numpy: its reference."""
    h, w = depth_m.shape
    valid = np.zeros((h, w), dtype=bool)
    d = depth_m > 0
    valid[1:-1, 1:-1] = d[1:-1, 1:-1] & d[1:-1, 2:] & d[1:-1, :-2] & d[2:, 1:-1] & d[:-2, 1:-1]
    v = np.asarray(vertex_map, np.float32)
    du = [v[1:-1, 2:, i] - v[1:-1, :-2, i] for i in range(3)]
    dv = [v[2:, 1:-1, i] - v[:-2, 1:-1, i] for i in range(3)]
    n = [du[1] * dv[2] - du[2] * dv[1], du[2] * dv[0] - du[0] * dv[2], du[0] * dv[1] - du[1] * dv[0]]
    length = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    inner = valid[1:-1, 1:-1] & (length > 0)
    centre = v[1:-1, 1:-1]
    toward = n[0] * centre[..., 0] + n[1] * centre[..., 1] + n[2] * centre[..., 2]
    scale = np.where(inner, np.float32(1.0) / np.maximum(length, np.float32(1e-20)), np.float32(0.0))
    scale = np.where(toward > 0, -scale, scale)
    normals = np.zeros((h, w, 3), np.float32)
    for i in range(3):
        normals[1:-1, 1:-1, i] = n[i] * scale
    valid[1:-1, 1:-1] = inner
    return normals, valid


def test_compiled_normal_map_equals_the_numpy_reference():
    from surfelwarp.preprocess import normal_map
    rng = np.random.default_rng(5)
    depth = (1.0 + 0.2 * rng.random((60, 80))).astype(np.float32)
    depth[rng.random(depth.shape) < 0.1] = 0.0                       # holes
    intr = Intrinsics(70.0, 70.0, 39.5, 29.5, 80, 60)
    vertex = intr.backproject(depth)
    normals, valid = normal_map(vertex, depth)
    ref_n, ref_valid = _normal_map_numpy(vertex, depth)
    assert valid.sum() > 1000 and np.array_equal(valid, ref_valid)
    assert np.abs(normals - ref_n).max() < 1e-6


def test_the_filter_s_exp_is_exp_to_float32_precision():
    from surfelwarp.preprocess import _exp
    x = np.linspace(-20, 0, 4001).astype(np.float32)
    got = np.array([_exp(v) for v in x], np.float64)
    error = np.abs(got / np.exp(x.astype(np.float64)) - 1)
    assert error[x > -3].max() < 2e-6 and error.max() < 5e-4, (error[x > -3].max(), error.max())


def test_radius_map_is_the_whole_image_formula_to_the_bit():
    """The compiled pass against Eq. 4 as numpy computes it (float64, then float32)."""
    rng = np.random.default_rng(5)
    intr = Intrinsics(525.0, 523.5, 319.5, 239.5, 64, 48)
    depth = rng.uniform(0.3, 3.0, (48, 64)).astype(np.float32)
    normals = rng.normal(size=(48, 64, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    valid = rng.random((48, 64)) < 0.7
    nz = np.maximum(np.abs(normals[..., 2]), np.cos(np.deg2rad(75.0)))
    formula = (np.sqrt(2.0) * depth / (intr.focal_px * nz)).astype(np.float32)
    assert np.array_equal(radius_map(depth, normals, intr, 75.0), formula)
    assert np.array_equal(radius_map(depth, normals, intr, 75.0, valid), np.where(valid, formula, 0))
    # float64 inputs stay float64 until the result, and a NaN normal gives NaN as numpy does.
    normals[0, 0] = np.nan
    depth64, normals64 = depth.astype(np.float64) + 1e-9, normals.astype(np.float64)
    nz = np.maximum(np.abs(normals64[..., 2]), np.cos(np.deg2rad(75.0)))
    formula = (np.sqrt(2.0) * depth64 / (intr.focal_px * nz)).astype(np.float32)
    assert np.array_equal(radius_map(depth64, normals64, intr, 75.0), formula, equal_nan=True)
    assert np.isnan(formula[0, 0])
