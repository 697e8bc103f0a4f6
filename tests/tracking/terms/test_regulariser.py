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


def _one_pass(field, pattern, lam, huber_m, upper, grad):
    """The regulariser's sums as one pass over the edges makes them, in Python (the order the
    compiled sums, grouped by block and node on two threads, must reproduce to the bit)."""
    from surfelwarp.tracking.assembly_kernels import add_gradient, add_pair
    from surfelwarp.tracking.terms.regulariser import _edge, _penalty
    p, L = field.nodes.astype(np.float64), field.transforms
    total = 0.0
    for e in range(len(pattern.edge_j)):
        j, i = pattern.edge_j[e], pattern.edge_i[e]
        a, t, r = np.empty(3), np.empty(3), np.empty(3)
        cost, w = _penalty(_edge(p, L, j, i, a, t, r), huber_m, lam)
        total += cost
        s0, s1, s2 = pattern.reg_slots[:, e]
        add_pair(upper[s0], a, a, w)
        add_pair(upper[s1], t, t, w)
        add_pair(upper[s2], *((t, a) if pattern.edge_flip[e] else (a, t)), -w)
        add_gradient(grad[i], a, r, w)
        add_gradient(grad[j], t, r, -w)
    return total


@pytest.mark.parametrize("threads", [1, 2])
def test_compiled_sums_are_one_pass_over_the_edges_on_any_thread_count(threads):
    from conftest import numba_threads
    rng = np.random.default_rng(4)
    field = bent_field(5)
    pattern = BlockPattern(field.num_nodes, field.graph, rng.integers(0, field.num_nodes, (300, 4)))
    huber_m = float(np.median(edge_lengths(field)))
    start = rng.normal(size=(pattern.n_upper, 6, 6)), rng.normal(size=(field.num_nodes, 6))
    expected_upper, expected_grad = start[0].copy(), start[1].copy()
    expected = _one_pass(field, pattern, 3.0, huber_m, expected_upper, expected_grad)
    system = NormalEquations(pattern, np.ones(field.num_nodes, bool), None)
    system.add(start[1].copy(), upper=start[0].copy())
    with numba_threads(threads):
        energy = RegulariserTerm(3.0, huber_m).linearize(iterate(field), system)
    assert np.array_equal(system.upper, expected_upper) and np.array_equal(system.gradient, expected_grad)
    assert energy == 3.0 * expected
