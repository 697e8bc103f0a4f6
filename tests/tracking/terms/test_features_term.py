"""The colour feature term: point to point from a feature's reference point to where the frame
sees it; its gradient against finite differences and a known answer on a sliding plane."""
from dataclasses import replace

import numpy as np
import pytest

from surfelwarp.deform.warp_field import apply_update
from surfelwarp.geometry.dual_quaternion import _components
from surfelwarp.tracking.assembly import NormalEquations
from surfelwarp.tracking.blend_jacobian import twist_dual_quaternions
from surfelwarp.tracking.features import AnchoredMatches
from surfelwarp.tracking.gauss_newton import NonRigidParams, Problem, Solve, solve_nonrigid
from tests.tracking.terms.test_point_prior import plane_problem

SLIDE = np.array([0.006, -0.004, 0.0])       # along the plane: depth cannot see it


def matches_on(points: np.ndarray, every: int = 5, offset=SLIDE) -> AnchoredMatches:
    index = np.arange(0, len(points), every)
    return AnchoredMatches(index, points[index], points[index] + offset, np.ones(len(index)))


def test_the_gradient_and_blocks_match_finite_differences():
    field, model, depth = plane_problem()
    rng = np.random.default_rng(5)
    field = apply_update(field, rng.normal(scale=0.01, size=(field.num_nodes, 6)))
    points = model[0]
    # a feature off its surfel (1 mm) and some far beyond the Huber corner (5 cm)
    matches = AnchoredMatches(np.arange(0, len(points), 9), points[::9] + [0.0, 0.001, 0.0],
                              points[::9] + np.where(np.arange(len(points[::9]))[:, None] % 4 == 0, 0.05, 0.004),
                              np.linspace(0.5, 2.0, len(points[::9])))
    params = replace(NonRigidParams(), terms=("features",), feature_weight=3.0)
    comps = [_components(np.asarray(a, np.float64)) for a in model[:2]]
    solve = Solve(Problem(field, *comps, model[2].astype(np.int64), model[3].astype(np.float64), *depth, params,
                          matches=matches))
    (term,) = solve.terms
    at = solve.at(field)
    system = NormalEquations(solve.pattern_for(field), np.ones(field.num_nodes, bool),
                             twist_dual_quaternions(field, at.dq))
    energy = term.linearize(at, system)
    assert energy == pytest.approx(term.energy(at)) and energy > 0
    h = 1e-6
    for j in (0, field.num_nodes // 3, field.num_nodes - 1):
        for a in range(6):
            xi = np.zeros((field.num_nodes, 6))
            xi[j, a] = h
            dE = (term.energy(solve.at(apply_update(field, xi), at.pairs)) -
                  term.energy(solve.at(apply_update(field, -xi), at.pairs))) / (2 * h)
            assert dE == pytest.approx(2 * system.gradient[j, a], rel=1e-4, abs=1e-9)
    H = system.pattern.matrix(system.upper).toarray()
    assert np.allclose(H, H.T) and np.linalg.eigvalsh(H).min() > -1e-9


def test_features_slide_a_plane_depth_cannot_see_slide():
    """Known answer: the plane's depth is the same after any slide along it, so with the depth
    term alone the nodes stay; with features at +SLIDE every node follows them."""
    field, model, depth = plane_problem()
    matches = matches_on(model[0])
    off = replace(NonRigidParams(), terms=("depth", "regulariser"))
    still, _ = solve_nonrigid(field, *model, *depth, off, matches=matches)
    assert np.abs(still.transforms[:, :3, 3]).max() < 1e-6
    on = replace(NonRigidParams(), terms=("depth", "features", "regulariser"), feature_weight=10.0)
    solved, result = solve_nonrigid(field, *model, *depth, on, matches=matches)
    moved = solved.transforms[:, :3, 3]
    assert np.abs(moved - SLIDE).max() < 2e-4, np.abs(moved - SLIDE).max()
    assert result.term_energies["features"] < 1e-6


def test_the_term_is_off_without_matches_or_weight():
    field, model, depth = plane_problem()
    for params, matches in ((NonRigidParams(), None), (replace(NonRigidParams(), feature_weight=0.0),
                                                       matches_on(model[0]))):
        _, result = solve_nonrigid(field, *model, *depth, params, matches=matches)
        assert "features" not in result.term_energies
