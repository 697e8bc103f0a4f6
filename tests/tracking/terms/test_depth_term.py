"""The data term's point-to-plane residuals: the compiled pass against numpy's."""
import numpy as np
import pytest

from surfelwarp.tracking.terms.depth import CHUNK, point_to_plane, point_to_plane_reference


def pairs(count: int, surfels: int = 1000, seed: int = 0):
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(3, surfels)), np.sort(rng.integers(0, surfels, count)), rng.normal(size=(count, 3)),
            rng.normal(size=(count, 3)))


@pytest.mark.parametrize("count", [0, 5, CHUNK + 17, 3 * CHUNK])
def test_point_to_plane_is_numpys(count):
    """Both the compiled pass (CHUNK pairs or more) and the small calls give numpy's residuals
    (with this numpy, bit for bit: the kernel sums in einsum's order)."""
    args = pairs(count)
    got, ref = point_to_plane(*args), point_to_plane_reference(*args)
    assert got.shape == (count,) and got.dtype == np.float64
    np.testing.assert_allclose(got, ref, rtol=1e-14, atol=1e-15)


def test_point_to_plane_known_answer():
    """A point 2 cm in front of a plane along its normal, one 3 cm beside it (no residual)."""
    live = np.array([[0.0, 0.03], [0.0, 0.0], [1.02, 1.0]])
    index = np.repeat([0, 1], CHUNK)
    points = np.tile([0.0, 0.0, 1.0], (len(index), 1))
    normals = np.tile([0.0, 0.0, 1.0], (len(index), 1))
    r = point_to_plane(live, index, points, normals)
    assert np.allclose(r[:CHUNK], 0.02, rtol=0, atol=1e-15) and np.all(r[CHUNK:] == 0.0)
