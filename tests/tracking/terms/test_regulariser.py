"""The regulariser's compiled linearisation against its numpy reference (regulariser_blocks),
which the normal-equation tests check against explicit Jacobians; its Huber penalty's value
and gradient."""
import numpy as np
import pytest

from surfelwarp.deform.warp_field import WarpField, WarpFieldParams, apply_update
from surfelwarp.tracking.assembly import BlockPattern, NormalEquations
from surfelwarp.tracking.terms import Iterate
from surfelwarp.tracking.terms.regulariser import RegulariserTerm, reg_energy, reg_penalty, reg_residuals, regulariser_blocks


def bent_field(seed: int = 12) -> WarpField:
    rng = np.random.default_rng(seed)
    field = WarpField.from_points(rng.uniform(-0.2, 0.2, (3000, 3)).astype(np.float32))
    return apply_update(field, rng.normal(size=(field.num_nodes, 6)) * [0.3, 0.3, 0.3, 0.02, 0.02, 0.02])


def iterate(field: WarpField) -> Iterate:
    at = Iterate.__new__(Iterate)
    object.__setattr__(at, "field", field)
    return at


def edge_lengths(field: WarpField) -> np.ndarray:
    pattern = BlockPattern(field.num_nodes, field.graph, np.zeros((1, 4), np.int64))
    return np.linalg.norm(reg_residuals(field).reshape(-1, 3)[pattern.edge_real], axis=1)


@pytest.mark.parametrize("huber", ["none", "median"])
def test_compiled_linearize_adds_the_reference_blocks_into_the_system(huber):
    rng = np.random.default_rng(12)
    field = bent_field()
    huber_m = 0.0 if huber == "none" else float(np.median(edge_lengths(field)))   # half the edges past it
    knn = rng.integers(0, field.num_nodes, (500, 4))
    pattern = BlockPattern(field.num_nodes, field.graph, knn)
    assert pattern.edge_flip.any() and not pattern.edge_flip.all()      # both storage orders
    blocks, g = regulariser_blocks(field, pattern, huber_m)
    system = NormalEquations(pattern, np.ones(field.num_nodes, bool), None)
    earlier = rng.normal(size=(pattern.n_upper, 6, 6))
    system.add(np.ones((field.num_nodes, 6)), upper=earlier.copy())     # a term before it
    term = RegulariserTerm(3.0, huber_m)
    energy = term.linearize(iterate(field), system)
    assert np.abs(system.upper - (earlier + 3.0 * blocks)).max() < 1e-12 * np.abs(blocks).max()
    assert np.abs(system.gradient - (1.0 + 3.0 * g)).max() < 1e-12 * np.abs(g).max()
    assert energy == pytest.approx(term.energy(iterate(field)), rel=1e-12)
    if huber == "none":
        assert energy == pytest.approx(3.0 * np.sum(reg_residuals(field) ** 2), rel=1e-12)
    else:   # the reweighted blocks are not the plain ones
        assert np.abs(blocks - regulariser_blocks(field, pattern)[0]).max() > 0.1 * np.abs(blocks).max()


@pytest.mark.parametrize("huber", ["none", "median"])
def test_compiled_energy_equals_the_numpy_penalties(huber):
    field = bent_field()
    huber_m = 0.0 if huber == "none" else float(np.median(edge_lengths(field)))
    reference = np.sum(reg_penalty(reg_residuals(field), huber_m)[0])
    assert reg_energy(field, huber_m) == pytest.approx(reference, rel=1e-12)
    assert RegulariserTerm(3.0, huber_m).energy(iterate(field)) == pytest.approx(3.0 * reference, rel=1e-12)
    if huber == "median":
        assert reg_energy(field, huber_m) < 0.9 * reg_energy(field)


def test_huber_energy_of_a_stretched_edge():
    """Two nodes 2 cm apart, one moved 1 cm away from the other: each edge's residual is 1 cm,
    past a 2 mm corner, so each costs 2 * 2 mm * 1 cm - (2 mm)^2 where a square would cost 1 cm^2."""
    field = WarpField.identity(np.array([[0.0, 0, 1], [0.02, 0, 1]], np.float32), WarpFieldParams())
    field = apply_update(field, np.array([[0.0] * 6, [0, 0, 0, 0.01, 0, 0]]))
    lengths = edge_lengths(field)
    assert len(lengths) == 2 and np.allclose(lengths, 0.01)
    huber = 2 * 0.002 * 0.01 - 0.002 ** 2
    assert RegulariserTerm(5.0, 0.002).energy(iterate(field)) == pytest.approx(5.0 * 2 * huber)
    assert RegulariserTerm(5.0).energy(iterate(field)) == pytest.approx(5.0 * 2 * 0.01 ** 2)


def test_huber_gradient_matches_finite_differences():
    """The reweighted gradient is half the Huber energy's derivative (as J^T r is the square's)."""
    field = bent_field(seed=4)
    huber_m = float(np.median(edge_lengths(field)))
    pattern = BlockPattern(field.num_nodes, field.graph, np.zeros((1, 4), np.int64))
    system = NormalEquations(pattern, np.ones(field.num_nodes, bool), None)
    term = RegulariserTerm(1.0, huber_m)
    term.linearize(iterate(field), system)
    h, errors = 1e-7, []
    for j in np.linspace(0, field.num_nodes - 1, 12).astype(int):
        for c in range(6):
            xi = np.zeros((field.num_nodes, 6))
            xi[j, c] = h
            numeric = (term.energy(iterate(apply_update(field, xi))) -
                       term.energy(iterate(apply_update(field, -xi)))) / (2 * h)
            errors.append(abs(numeric - 2 * system.gradient.reshape(-1, 6)[j, c]) /
                          max(np.abs(system.gradient).max(), 1e-12))
    print(f"Huber regulariser gradient vs central differences: max error {max(errors):.1e} of the largest")
    assert max(errors) < 1e-5
