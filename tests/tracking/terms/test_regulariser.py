"""The regulariser's compiled linearisation against its numpy reference (regulariser_blocks),
which the normal-equation tests check against explicit Jacobians."""
import numpy as np
import pytest

from surfelwarp.deform.warp_field import WarpField, apply_update
from surfelwarp.tracking.assembly import BlockPattern, NormalEquations
from surfelwarp.tracking.terms import Iterate
from surfelwarp.tracking.terms.regulariser import RegulariserTerm, reg_residuals, regulariser_blocks


def test_compiled_linearize_adds_the_reference_blocks_into_the_system():
    rng = np.random.default_rng(12)
    pts = rng.uniform(-0.2, 0.2, (3000, 3)).astype(np.float32)
    field = WarpField.from_points(pts)
    field = apply_update(field, rng.normal(size=(field.num_nodes, 6)) * [0.3, 0.3, 0.3, 0.02, 0.02, 0.02])
    knn = rng.integers(0, field.num_nodes, (500, 4))
    pattern = BlockPattern(field.num_nodes, field.graph, knn)
    assert pattern.edge_flip.any() and not pattern.edge_flip.all()      # both storage orders
    blocks, g = regulariser_blocks(field, pattern)
    system = NormalEquations(pattern, np.ones(field.num_nodes, bool), None)
    earlier = rng.normal(size=(pattern.n_upper, 6, 6))
    system.add(np.ones((field.num_nodes, 6)), upper=earlier.copy())     # a term before it
    at = Iterate.__new__(Iterate)
    object.__setattr__(at, "field", field)
    energy = RegulariserTerm(3.0).linearize(at, system)
    assert np.abs(system.upper - (earlier + 3.0 * blocks)).max() < 1e-12 * np.abs(blocks).max()
    assert np.abs(system.gradient - (1.0 + 3.0 * g)).max() < 1e-12 * np.abs(g).max()
    assert energy == pytest.approx(3.0 * np.sum(reg_residuals(field) ** 2), rel=1e-12)
