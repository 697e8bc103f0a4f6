"""The compiled blend warp against its numpy reference (dq_blend_indexed + apply_components)."""
import numpy as np
import pytest

from surfelwarp.geometry.dq_kernels import blend_apply, dq_from_transforms
from surfelwarp.geometry.dual_quaternion import _components, apply_components, dq_blend_indexed, dq_from_transform
from surfelwarp.geometry.se3 import se3_exp


@pytest.fixture
def blend_case():
    rng = np.random.default_rng(4)
    m, n, k = 40, 10000, 4     # 10000: three of blend_apply's parallel tasks, the last one partial
    xi = rng.normal(size=(m, 6)) * [0.3, 0.3, 0.3, 0.05, 0.05, 0.05]
    xi[::3, 2] += np.pi * 0.95            # turns near 180 degrees: the antipodal fix flips signs
    dqs = dq_from_transform(se3_exp(xi))
    knn = rng.integers(0, m, size=(n, k))
    weights = rng.random((n, k))
    points, normals = rng.normal(size=(3, n)), rng.normal(size=(3, n))
    return dqs, knn, weights, points, normals


def test_blend_apply_equals_the_numpy_warp(blend_case):
    dqs, knn, weights, points, normals = blend_case
    blends, signed, live, live_n = blend_apply(dqs, knn, weights, points, normals)
    b_ref, s_ref = dq_blend_indexed(dqs, knn, weights)
    p_ref, n_ref = apply_components(_components(b_ref), points, normals)
    assert np.mean(s_ref < 0) > 0.05                    # the sign fix was exercised
    assert np.array_equal(signed, s_ref)
    assert np.allclose(blends, b_ref, rtol=0, atol=1e-14)
    assert np.allclose(live, np.array(p_ref), rtol=0, atol=1e-12)
    assert np.allclose(live_n, np.array(n_ref), rtol=0, atol=1e-12)


def test_inverse_blend_apply_undoes_the_warp(blend_case):
    dqs, knn, weights, points, normals = blend_case
    _, _, live, live_n = blend_apply(dqs, knn, weights, points, normals)
    _, _, back, back_n = blend_apply(dqs, knn, weights, live, live_n, inverse=True)
    assert np.abs(back - points).max() < 1e-12 and np.abs(back_n - normals).max() < 1e-12


def test_blend_apply_without_normals_and_shape_errors(blend_case):
    dqs, knn, weights, points, _ = blend_case
    _, _, live, live_n = blend_apply(dqs, knn, weights, points)
    assert live_n is None and live.shape == points.shape
    with pytest.raises(ValueError):
        blend_apply(dqs, knn, weights, points.T)
    with pytest.raises(ValueError):
        blend_apply(dqs, knn, weights[:, :2], points)


def test_dq_from_transforms_is_the_numpy_form_to_the_bit():
    """The compiled conversion gives dq_from_transform's bits for every branch of Shepperd's
    choice: small and large turns, turns within 1e-9 of 180 degrees about random axes (w ~ 0,
    another component the largest), the identity; and an empty batch."""
    rng = np.random.default_rng(6)
    axis = rng.normal(size=(300, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    near_pi = axis * (np.pi - 10.0 ** rng.uniform(-9, -1, (300, 1)))
    xi = np.concatenate([np.concatenate([rng.normal(size=(900, 3)) * np.repeat([1e-6, 0.3, 3.0], 300)[:, None],
                                         near_pi]), rng.normal(size=(1200, 3))], 1)
    T = np.concatenate([se3_exp(xi), np.eye(4)[None]])
    expect = dq_from_transform(T)
    assert np.array_equal(dq_from_transforms(T), expect)
    assert len(set(np.argmax(np.abs(expect[:, :4]), axis=1))) == 4       # every branch taken
    assert dq_from_transforms(np.zeros((0, 4, 4))).shape == (0, 8)
