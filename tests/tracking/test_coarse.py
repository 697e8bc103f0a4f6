"""The PCG preconditioner's coarse level: cells of nodes moving rigidly (tracking/coarse.py)."""
import numpy as np
import pytest

from surfelwarp.deform.warp_field import WarpField, WarpFieldParams, apply_update
from surfelwarp.geometry.se3 import se3_exp
from surfelwarp.tracking.assembly import BlockPattern, Border, NormalEquations
from surfelwarp.tracking.coarse import coarse_space, correct, factor, prolong
from surfelwarp.tracking.linear import solve_system
from surfelwarp.tracking.terms.regulariser import regulariser_blocks


def sheet(nx=24, ny=16, spacing=0.025, seed=0):
    """A wavy sheet of nodes, its k-nearest-node graph and each node skinning itself."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(nx) * spacing, np.arange(ny) * spacing)
    z = 0.05 * np.sin(6 * x) + 0.002 * rng.normal(size=x.shape)
    nodes = np.stack([x, y, z + 1.0], -1).reshape(-1, 3)
    field = WarpField.identity(nodes, WarpFieldParams(node_radius_m=spacing))
    return field, BlockPattern(field.num_nodes, field.graph, np.arange(field.num_nodes)[:, None])


def system(data=1e-3, held=False, bordered=False, cell_m=0.15, seed=1, size=(24, 16)):
    """The regulariser's blocks plus weak per-node data: a graph Laplacian-like system, slow for
    block-Jacobi alone."""
    rng = np.random.default_rng(seed)
    field, pattern = sheet(*size)
    m = field.num_nodes
    upper, g = regulariser_blocks(field, pattern)
    J = rng.normal(size=(m, 6, 6))
    upper[pattern.diag] += data * J @ J.transpose(0, 2, 1)
    free = rng.random(m) > 0.1 if held else np.ones(m, bool)
    border = None
    if bordered:            # nodes anchored to one common motion zeta: |xi_a - zeta|^2
        anchored = rng.random(m) < 0.3
        upper[pattern.diag[anchored]] += np.eye(6)
        B = -np.eye(6) * anchored[:, None, None]
        border = Border(B, (anchored.sum() + 1.0) * np.eye(6), rng.normal(size=6))
    coarse = coarse_space(field.nodes, free, pattern.lo, pattern.hi, cell_m) if cell_m else None
    return field, NormalEquations(pattern, free, np.zeros((m, 6, 8)), upper, g + rng.normal(size=(m, 6)), border,
                                  coarse)


def dense_prolongation(space):
    """P (6M, 6K) from the cells, by its definition: node twist (omega, v + omega x d)."""
    m, k = len(space.cell), space.num_cells
    P = np.zeros((m, 6, k, 6))
    for a in np.flatnonzero(space.cell >= 0):
        c, d = space.cell[a], space.offset[a]
        P[a, :, c, :] = np.eye(6)
        P[a, 3:, c, :3] = -np.array([[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]])
    return P.reshape(6 * m, 6 * k)


def test_cells_smoke():
    field, s = system(held=True)
    space = s.coarse
    assert space.num_cells == len(np.unique(space.cell[s.free]))
    assert np.all(space.cell[~s.free] == -1) and np.all(space.cell[s.free] >= 0)
    assert 10 < space.num_cells < field.num_nodes / 5
    # offsets are from each cell's centroid
    for c in range(space.num_cells):
        assert np.allclose(space.offset[space.cell == c].mean(axis=0), 0, atol=1e-12)


def test_prolonged_twists_move_the_nodes_as_their_cell():
    """A rigid motion y of a cell, prolonged to its nodes' twists, moves the points near each
    node as the motion itself turning about the cell's centre: exactly, as the left Jacobian V
    of the exponential has V [omega]x = R - I."""
    field, s = system(cell_m=0.1)
    space = s.coarse
    rng = np.random.default_rng(3)
    for eps in (1e-1, 1e-3):
        y = rng.normal(size=(space.num_cells, 6)) * eps
        xi = np.zeros((field.num_nodes, 6))
        prolong(space.cell, space.offset, y, xi)
        moved = apply_update(field, xi).transforms
        near = field.nodes + 0.01                       # a point 1.7 cm from its node
        got = field.nodes + np.einsum("nij,nj->ni", moved[:, :3, :3], near - field.nodes) + moved[:, :3, 3]
        centre = field.nodes - space.offset
        T = se3_exp(y[space.cell])
        want = centre + np.einsum("nij,nj->ni", T[:, :3, :3], near - centre) + T[:, :3, 3]
        err, motion = np.abs(got - want).max(), np.abs(want - near).max()
        print(f"eps {eps:.0e}: motion {motion:.1e} m, error {err:.1e} m")
        assert err < 1e-12 and motion > eps


@pytest.mark.parametrize("held, bordered", [(False, False), (True, False), (True, True)])
def test_correction_equals_the_dense_coarse_solve(held, bordered):
    """z = P (P^T A P)^-1 P^T r with A = H + mu I (bordered, held nodes out), from dense numpy."""
    field, s = system(held=held, bordered=bordered)
    space, pattern, m, mu = s.coarse, s.pattern, field.num_nodes, 0.3
    B = s.border.B * s.free[:, None, None] if bordered else None
    f = factor(space, s.upper, pattern.lo, pattern.hi, mu, B, s.border.C if bordered else None)
    keep = np.repeat(s.free, 6)
    H = pattern.matrix(s.upper).toarray()
    A = (H + mu * np.eye(6 * m)) * np.outer(keep, keep)
    P = dense_prolongation(space)
    if bordered:
        Bd = B.reshape(6 * m, 6)
        A = np.block([[A, Bd], [Bd.T, s.border.C + mu * np.eye(6)]])
        P = np.block([[P, np.zeros((6 * m, 6))], [np.zeros((6, P.shape[1])), np.eye(6)]])
    r = np.random.default_rng(5).normal(size=(m + 1, 6))
    if not bordered:
        r[m] = 0
    want = P @ np.linalg.solve(P.T @ A @ P, P.T @ r.reshape(-1)[: len(A)])
    z = np.zeros((m + 1, 6))
    correct(*f.arrays(), r, z)
    assert np.abs(z.reshape(-1)[: len(A)] - want).max() < 1e-9 * np.abs(want).max()
    assert not np.any(z[:m][~s.free])


@pytest.mark.parametrize("held, bordered", [(False, False), (True, False), (True, True)])
def test_pcg_with_cells_equals_the_direct_solve(held, bordered):
    _, s = system(held=held, bordered=bordered)
    direct = solve_system(s, 1e-6, "direct")
    two_level = solve_system(s, 1e-6, "pcg", pcg_rtol=1e-10, pcg_max_iterations=5000)
    scale = np.abs(direct.xi).max()
    assert not two_level.lu_fallback and np.abs(two_level.xi - direct.xi).max() < 1e-6 * scale
    assert np.abs(two_level.zeta - direct.zeta).max() < 1e-6 * scale
    assert not np.any(two_level.xi[~s.free])


def test_cells_cut_the_iterations_of_a_smooth_system():
    """On this Laplacian-like system (weak data) block-Jacobi alone needs 151 iterations to
    1e-4, with the cells 30."""
    _, s = system()
    _, plain = system(cell_m=None)
    its = [solve_system(x, 1e-6, "pcg", pcg_rtol=1e-4, pcg_max_iterations=5000).iterations for x in (plain, s)]
    print(f"iterations to 1e-4: block-Jacobi {its[0]}, with cells {its[1]}")
    assert its[1] * 3 < its[0]


def test_singular_coarse_system_leaves_block_jacobi():
    """Cells whose nodes have no blocks and no damping: no factor; the PCG runs without it."""
    field, s = system(data=0.0)
    s.upper[:] = 0.0
    assert factor(s.coarse, s.upper, s.pattern.lo, s.pattern.hi, 0.0, None, None) is None
    s.upper[s.pattern.diag] = np.eye(6)
    step = solve_system(s, 1e-6, "pcg")
    assert not step.lu_fallback and np.allclose(step.xi, -s.gradient / (1 + 1e-6), rtol=1e-5)


def test_an_earlier_coarse_factor_preconditions_a_changed_system(monkeypatch):
    """A step's coarse factor (Step.coarse) reused on the next system of the same cells and
    border: no new factor, the same solution, a few iterations more at most; a factor of
    other cells or without the border is not used."""
    import dataclasses
    import surfelwarp.tracking.linear as linear
    made = []
    monkeypatch.setattr(linear, "factor", lambda *a: made.append(1) or factor(*a))
    _, first = system(bordered=True)
    rng = np.random.default_rng(5)
    m = first.pattern.num_nodes
    J = rng.normal(size=(m, 6, 6))
    upper = first.upper.copy()
    upper[first.pattern.diag] += 2e-3 * J @ J.transpose(0, 2, 1)       # the next iteration's data
    changed = dataclasses.replace(first, upper=upper, gradient=first.gradient + rng.normal(size=(m, 6)))
    earlier = solve_system(first, 1e-6, "pcg")
    assert earlier.coarse is not None and earlier.coarse.bordered and len(made) == 1
    fresh = solve_system(changed, 1e-6, "pcg", pcg_rtol=1e-10, pcg_max_iterations=5000)
    reused = solve_system(changed, 1e-6, "pcg", pcg_rtol=1e-10, pcg_max_iterations=5000, coarse=earlier.coarse)
    direct = solve_system(changed, 1e-6, "direct")
    print(f"iterations to 1e-10: a fresh factor {fresh.iterations}, the earlier one {reused.iterations}")
    assert len(made) == 2 and reused.coarse is earlier.coarse
    scale = np.abs(direct.xi).max()
    assert np.abs(reused.xi - direct.xi).max() < 1e-6 * scale and np.abs(reused.zeta - direct.zeta).max() < 1e-6 * scale
    assert reused.iterations <= 1.2 * fresh.iterations + 2
    unbordered = solve_system(dataclasses.replace(first, border=None), 1e-6, "pcg")
    assert len(made) == 3 and not unbordered.coarse.bordered
    assert solve_system(changed, 1e-6, "pcg", coarse=unbordered.coarse).coarse is not unbordered.coarse
    _, other_cells = system(bordered=True)
    assert solve_system(other_cells, 1e-6, "pcg", coarse=earlier.coarse).coarse is not earlier.coarse
    assert len(made) == 5


@pytest.mark.parametrize("k, n", [(1, 50), (7, 0), (7, 3000), (600, 60000)])
def test_unique_pairs_are_numpys_unique(k, n):
    from surfelwarp.tracking.coarse import unique_pairs
    rng = np.random.default_rng(k + n)
    first, second = rng.integers(0, k, n), rng.integers(0, k, n)
    unique, inverse = unique_pairs(first, second, k)
    expected, expected_inverse = np.unique(first * k + second, return_inverse=True)
    np.testing.assert_array_equal(unique, expected)
    np.testing.assert_array_equal(inverse, expected_inverse)
