import numpy as np
import pytest

from surfelwarp.geometry.dual_quaternion import (dq_blend, dq_from_transform, dq_multiply, dq_normalize, dq_rotate,
                                                 dq_to_transform, dq_transform_points, quat_conjugate,
                                                 quat_from_matrix, quat_multiply, quat_to_matrix)
from surfelwarp.geometry.se3 import se3_exp, so3_exp


def random_twists(n, rng, max_angle=np.pi):
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, max_angle, size=(n, 1))
    return np.concatenate([axis * angle, rng.normal(scale=0.5, size=(n, 3))], axis=1)


def hard_rotations(rng):
    """Rotations at pi, just below and above it, about random and coordinate axes, and tiny ones."""
    axes = np.concatenate([np.eye(3), rng.normal(size=(5, 3))])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.array([np.pi, np.pi - 1e-9, np.pi - 1e-4, 1e-12, 1e-7, 0.0])
    return (axes[:, None, :] * angles[None, :, None]).reshape(-1, 3)


def test_quaternion_product_composes_rotations():
    rng = np.random.default_rng(0)
    w1, w2 = random_twists(200, rng)[:, :3], random_twists(200, rng)[:, :3]
    q1, q2 = quat_from_matrix(so3_exp(w1)), quat_from_matrix(so3_exp(w2))
    assert np.allclose(quat_to_matrix(quat_multiply(q1, q2)), so3_exp(w1) @ so3_exp(w2), atol=1e-12)
    assert np.allclose(quat_multiply(q1, quat_conjugate(q1)), [1, 0, 0, 0], atol=1e-12)
    # (w, x, y, z): a quarter turn about z.
    assert np.allclose(quat_from_matrix(so3_exp([0, 0, np.pi / 2])), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)])


def test_quaternion_matrix_round_trip_including_near_pi_and_tiny():
    rng = np.random.default_rng(1)
    omega = np.concatenate([random_twists(500, rng)[:, :3], hard_rotations(rng)])
    R = so3_exp(omega)
    q = quat_from_matrix(R)
    assert np.all(q[:, 0] >= 0)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-14)
    err = np.abs(quat_to_matrix(q) - R).max()
    print(f"quaternion round trip max error {err:.2e}")
    assert err < 1e-12
    # Non-unit quaternions give the same rotation.
    assert np.allclose(quat_to_matrix(3.7 * q), R, atol=1e-12)


def test_dual_quaternion_transform_round_trip_and_product():
    rng = np.random.default_rng(2)
    xi = random_twists(500, rng)
    xi_hard = np.concatenate([hard_rotations(rng), rng.normal(size=(48, 3))], axis=1)
    T = se3_exp(np.concatenate([xi, xi_hard]))
    dq = dq_from_transform(T)
    err = np.abs(dq_to_transform(dq) - T).max()
    print(f"dual quaternion round trip max error {err:.2e}")
    assert err < 1e-12
    # Unit: |real| = 1 and real . dual = 0.
    assert np.allclose(np.linalg.norm(dq[:, :4], axis=1), 1.0)
    assert np.allclose(np.sum(dq[:, :4] * dq[:, 4:], axis=1), 0.0, atol=1e-14)
    T2 = se3_exp(random_twists(len(T), rng))
    assert np.allclose(dq_to_transform(dq_multiply(dq, dq_from_transform(T2))), T @ T2, atol=1e-12)
    # Scaling does not change the transform; dq_normalize recovers the unit form (up to sign).
    assert np.allclose(dq_to_transform(-2.5 * dq), T, atol=1e-12)
    assert np.allclose(dq_normalize(-2.5 * dq), -dq, atol=1e-12)


def test_applying_to_points_and_normals():
    rng = np.random.default_rng(3)
    T = se3_exp(random_twists(100, rng))
    p, n = rng.normal(size=(100, 3)), rng.normal(size=(100, 3))
    dq = 0.3 * dq_from_transform(T)
    assert np.allclose(dq_transform_points(dq, p), (T[:, :3, :3] @ p[..., None])[..., 0] + T[:, :3, 3], atol=1e-12)
    assert np.allclose(dq_rotate(dq, n), (T[:, :3, :3] @ n[..., None])[..., 0], atol=1e-12)


def test_blend_of_identical_transforms_is_that_transform_whatever_the_signs():
    rng = np.random.default_rng(4)
    T = se3_exp(np.concatenate([random_twists(50, rng), np.concatenate([hard_rotations(rng), np.ones((48, 3))], 1)]))
    dq = dq_from_transform(T)
    k = 4
    copies = np.repeat(dq[:, None, :], k, axis=1) * rng.choice([-1.0, 1.0], size=(len(dq), k, 1))
    w = rng.uniform(0.01, 1.0, size=(len(dq), k))
    blended = dq_blend(copies, w)
    assert np.allclose(dq_to_transform(blended), T, atol=1e-12)
    assert np.allclose(np.linalg.norm(blended[:, :4], axis=1), 1.0)
    # Without the sign fix [q, -q] with equal weights would cancel to zero.
    half = dq_blend(np.stack([dq, -dq], 1), np.full((len(dq), 2), 0.5))
    assert np.allclose(dq_to_transform(half), T, atol=1e-12)


def test_blend_midpoint_agrees_with_se3_exp():
    """Equal-weight DQB of the identity and exp(xi) is exactly exp(xi / 2) (screw midpoint)."""
    rng = np.random.default_rng(5)
    xi = random_twists(300, rng, max_angle=np.pi - 0.05)
    pair = np.stack([dq_from_transform(np.tile(np.eye(4), (len(xi), 1, 1))), dq_from_transform(se3_exp(xi))], 1)
    mid = dq_to_transform(dq_blend(pair, np.full((len(xi), 2), 0.5)))
    err = np.abs(mid - se3_exp(xi / 2)).max()
    print(f"DQB midpoint vs se3_exp(xi/2): {err:.2e}")
    assert err < 1e-10


def test_blend_across_pi_keeps_the_shared_axis():
    """Rotations of pi -/+ 0.01 about one axis land in opposite hemispheres; the blend is the pi turn."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    T1, T2 = se3_exp(np.r_[axis * (np.pi - 0.01), 0.1, 0, 0]), se3_exp(np.r_[axis * (np.pi + 0.01), 0.1, 0, 0])
    dq = np.stack([dq_from_transform(T1), dq_from_transform(T2)])
    assert np.dot(dq[0, :4], dq[1, :4]) < 0   # the case the antipodal fix exists for
    T = dq_to_transform(dq_blend(dq, np.array([0.5, 0.5])))
    assert np.allclose(T, se3_exp(np.r_[axis * np.pi, 0.1, 0, 0]), atol=1e-4)


@pytest.mark.parametrize("angle", [1e-9, 0.5, 2.0])
def test_weighted_blend_is_close_to_screw_interpolation(angle):
    """DQB with weights (1-s, s) deviates from exp(s xi) only at second order in the angle."""
    xi = np.r_[np.array([0.0, 0.6, 0.8]) * angle, 0.05, -0.02, 0.1]
    s = np.linspace(0, 1, 11)
    pair = np.stack([dq_from_transform(np.eye(4)), dq_from_transform(se3_exp(xi))])
    T = dq_to_transform(dq_blend(np.broadcast_to(pair, (len(s), 2, 8)), np.stack([1 - s, s], 1)))
    err = np.abs(T - se3_exp(s[:, None] * xi)).max()
    assert err < 0.1 * angle ** 2 + 1e-12
