"""The compiled blend warp against its numpy reference (dq_blend_indexed + apply_components)."""
import numpy as np
import pytest

from surfelwarp.geometry.dq_kernels import blend_apply
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
