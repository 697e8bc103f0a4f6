"""A term added from outside the solver: a point-to-point prior pulling every node's live position
towards a target, w |p_j + t_j - target_j|^2. Registering it and naming it in the parameters is
all it takes; the Gauss-Newton loop is not touched."""
from dataclasses import replace

import numpy as np
import pytest

from surfelwarp.deform.warp_field import WarpField, WarpFieldParams, apply_update, skin
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.tracking.assembly import BlockPattern, NormalEquations, pair_blocks
from surfelwarp.tracking.gauss_newton import NonRigidParams, solve_nonrigid
from surfelwarp.tracking.terms import BaseTerm, build_terms, known_terms, register

INTR = Intrinsics(200.0, 200.0, 79.5, 59.5, 160, 120)
SHIFT = np.array([0.004, -0.003, 0.006])


class PointPrior(BaseTerm):
    def __init__(self, target: np.ndarray, weight: float):
        self.target, self.weight = target, weight

    def residuals(self, field: WarpField) -> tuple[np.ndarray, np.ndarray]:
        t = field.transforms[:, :3, 3]
        return field.nodes + t - self.target, t

    def energy(self, at) -> float:
        r, _ = self.residuals(at.field)
        return self.weight * float(np.sum(r * r))

    def linearize(self, at, system) -> float:
        # The node's live point p + t turns about p under the update: d/dxi = [-[t]x, I].
        r, t = self.residuals(at.field)
        system.add(self.weight * np.concatenate([np.cross(t, r), r], axis=1), diagonal=self.weight * pair_blocks(t, t))
        return self.energy(at)


@register("point_prior")
def build(problem):
    return PointPrior(problem.field.nodes + SHIFT, weight=100.0)


def plane_problem():
    """A plane 1 m in front of the camera seen by every pixel, its surfels and a warp field."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    vertex = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], -1)
    normal = np.broadcast_to([0.0, 0.0, -1.0], vertex.shape).copy()
    points = vertex.reshape(-1, 3)[::7]
    field = WarpField.from_points(points, WarpFieldParams(node_radius_m=0.05))
    knn, w = skin(points, field.nodes, field.params.k_skin, field.sigma_m)
    depth = (vertex, normal, np.ones(vertex.shape[:2], bool), INTR, np.eye(4))
    return field, (points, normal.reshape(-1, 3)[::7], knn, w), depth


def test_the_term_is_known_by_name():
    assert {"depth", "regulariser", "rest_anchors", "free_space", "point_prior"} <= set(known_terms())
    with pytest.raises(ValueError, match="unknown term"):
        build_terms(("depth", "no_such_term"), None)


def test_the_prior_alone_moves_every_node_to_its_target():
    """Known answer: the regulariser has no say in a common translation, so with the prior and
    the regulariser only the nodes end at their targets."""
    field, model, depth = plane_problem()
    params = replace(NonRigidParams(), terms=("regulariser", "point_prior"), silhouette=replace(
        NonRigidParams().silhouette, weight=0.0))
    solved, result = solve_nonrigid(field, *model, *depth, params)
    moved = solved.transforms[:, :3, 3]
    assert np.abs(moved - SHIFT).max() < 1e-5, np.abs(moved - SHIFT).max()
    assert result.term_energies["point_prior"] < 1e-8 and result.converged


def test_the_prior_pulls_against_the_depth():
    """With the depth term too, the plane follows the prior where the depth cannot see it (x, y:
    a plane slides freely) and along its normal (z) goes where the two balance: a common shift
    d costs N d^2 (N depth pairs) + w M (d - s)^2 (M nodes), least at d = w M s / (N + w M);
    the nodes at the edge, with fewer pairs, go a little further."""
    field, model, depth = plane_problem()
    params = replace(NonRigidParams(), terms=("depth", "regulariser", "point_prior"))
    solved, result = solve_nonrigid(field, *model, *depth, params)
    moved = solved.transforms[:, :3, 3]
    assert np.abs(moved[:, :2] - SHIFT[:2]).max() < 1e-4
    wm = 100.0 * field.num_nodes
    expected = wm * SHIFT[2] / (result.correspondences + wm)
    assert 0 < moved[:, 2].min() and moved[:, 2].max() < SHIFT[2]
    assert abs(moved[:, 2].mean() - expected) < 0.05 * expected, (moved[:, 2].mean(), expected)
    assert set(result.term_energies) == {"depth", "regulariser", "point_prior"}


def test_the_gradient_matches_finite_differences():
    field, _, _ = plane_problem()
    rng = np.random.default_rng(3)
    field = apply_update(field, rng.normal(scale=0.02, size=(field.num_nodes, 6)))
    term = PointPrior(field.nodes + SHIFT, 3.0)

    class At:
        def __init__(self, f):
            self.field = f

    pattern = BlockPattern(field.num_nodes, field.graph, np.zeros((1, 1), np.int64))
    system = NormalEquations(pattern, np.ones(field.num_nodes, bool), None)
    term.linearize(At(field), system)
    h = 1e-6
    for j in (0, field.num_nodes // 2):
        for a in range(6):
            xi = np.zeros((field.num_nodes, 6))
            xi[j, a] = h
            dE = (term.energy(At(apply_update(field, xi))) - term.energy(At(apply_update(field, -xi)))) / (2 * h)
            assert dE == pytest.approx(2 * system.gradient[j, a], rel=1e-5, abs=1e-9)
        H = system.upper[pattern.diag[j]]
        assert np.allclose(H, H.T) and np.linalg.eigvalsh(H).min() > -1e-12
