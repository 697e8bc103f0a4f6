import numpy as np
import pytest

from surfelwarp.geometry.se3 import (fit_rigid, fit_rigid_informed, point_jacobian, se3_exp, se3_log, so3_exp,
                                     so3_left_jacobian, so3_log, transform_points)


def test_point_jacobian_matches_finite_differences():
    p = np.random.default_rng(2).normal(size=(5, 3))
    J, eps = point_jacobian(p), 1e-6
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = eps
        plus, minus = se3_exp(xi), se3_exp(-xi)
        numeric = ((p @ plus[:3, :3].T + plus[:3, 3]) - (p @ minus[:3, :3].T + minus[:3, 3])) / (2 * eps)
        np.testing.assert_allclose(J[:, :, k], numeric, atol=1e-8)


def test_se3_exp_known_answer_and_round_trip():
    """A quarter turn about z with a translation along x: R = Rz(90), t = V v with V's closed
    form for a turn about z; se3_log undoes se3_exp from tiny to large angles (the Taylor branch
    below 1e-4 rad and the trigonometric one)."""
    T = se3_exp(np.array([0.0, 0.0, np.pi / 2, 1.0, 0.0, 0.0]))
    a = np.pi / 2
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], [np.sin(a) / a, (1 - np.cos(a)) / a, 0.0], atol=1e-15)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    rng = np.random.default_rng(7)
    for scale in (1e-7, 1e-5, 1e-2, 0.6):         # turns below pi: se3_log's principal range
        xi = rng.normal(size=(50, 6)) * scale
        np.testing.assert_allclose(se3_log(se3_exp(xi)), xi, rtol=0, atol=1e-12 * max(scale, 1e-3))


def test_se3_exp_is_so3_exp_and_its_left_jacobian_to_the_bit():
    """se3_exp shares the angle, coefficients and [omega]x^2 of its two parts: each part the
    same bits as its own function, batched and alone."""
    rng = np.random.default_rng(8)
    xi = rng.normal(size=(400, 6)) * np.repeat([1e-6, 1e-3, 0.3, 2.5], 100)[:, None]
    T = se3_exp(xi)
    assert np.array_equal(T[:, :3, :3], so3_exp(xi[:, :3]))
    assert np.array_equal(T[:, :3, 3], (so3_left_jacobian(xi[:, :3]) @ xi[:, 3:, None])[..., 0])
    assert np.array_equal(se3_exp(xi[5]), T[5]) and np.array_equal(se3_exp(xi[399]), T[399])


@pytest.fixture
def cloud():
    return np.random.default_rng(5).uniform(-0.5, 0.5, (300, 3)) + [0.2, -0.1, 1.5]


def test_fit_rigid_recovers_a_rigid_motion(cloud):
    T = se3_exp(np.array([0.1, -0.2, 0.05, 0.03, 0.1, -0.2]))
    np.testing.assert_allclose(fit_rigid(cloud, transform_points(T, cloud)), T, atol=1e-12)


def test_informed_fit_with_isotropic_information_is_the_weighted_kabsch_fit(cloud):
    """S = w I counts every direction alike: the weighted least squares of fit_rigid, here on
    pairs that no rigid motion fits exactly and a turn of ~14 degrees."""
    rng = np.random.default_rng(6)
    T = se3_exp(np.array([0.1, -0.2, 0.05, 0.03, 0.1, -0.2]))
    target = transform_points(T, cloud) + rng.normal(0, 0.01, cloud.shape)
    w = rng.uniform(0.1, 2.0, len(cloud))
    informed = fit_rigid_informed(cloud, target, w[:, None, None] * np.eye(3), iterations=10)
    np.testing.assert_allclose(informed, fit_rigid(cloud, target, w), atol=1e-9)


def test_informed_fit_leaves_out_a_slide_along_a_plane_it_cannot_measure():
    """Points on the plane z = 1 seen along its normal (S = n n^T), tilted and lifted and also
    slid and spun within the plane: the fit takes the tilt and the lift, which the normal
    measures (every point's height as moved), and none of the slide or spin (the fitted motion
    keeps the centroid's x, y and turns about no axis along the normal); Kabsch takes it all."""
    rng = np.random.default_rng(7)
    plane = np.column_stack([rng.uniform(-0.4, 0.4, (400, 2)), np.ones(400)])
    n = np.array([0.0, 0.0, 1.0])
    slide = se3_exp(np.array([0.0, 0.0, 0.02, 0.01, -0.015, 0.0]))
    tilt = se3_exp(np.array([0.004, -0.003, 0.0, 0.0, 0.0, 0.002]))
    target = transform_points(tilt @ slide, plane)
    T = fit_rigid_informed(plane, target, np.broadcast_to(np.outer(n, n), (len(plane), 3, 3)))
    np.testing.assert_allclose((transform_points(T, plane) - target) @ n, 0.0, atol=1e-9)
    centre = plane.mean(axis=0)
    moved = transform_points(T, centre[None])[0] - centre
    assert np.abs(moved[:2]).max() < 1e-5
    assert abs(so3_log(T[:3, :3]) @ n) < 1e-5
    kabsch = fit_rigid(plane, target)
    assert np.abs(transform_points(kabsch, centre[None])[0] - centre)[:2].max() > 5e-3


def test_informed_fit_without_information_is_the_identity(cloud):
    assert np.array_equal(fit_rigid_informed(cloud, cloud + 0.1, np.zeros((len(cloud), 3, 3))), np.eye(4))
