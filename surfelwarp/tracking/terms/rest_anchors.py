"""Rest anchors (tracking/anchors.py): anchored nodes held at rest up to one rigid motion G they
share, solved with them as the border of the node system.

E_anchor = mu sum_a |L_j y_a - G Rest_j y_a|^2. In the first iteration of a solve the nodes the
data and regulariser alone would move farther than their release distance are released (their
mu set to 0); the solve's other iterations keep that set. Nodes held out of the solve follow G
at the end (finish).
"""
from __future__ import annotations

from dataclasses import replace

import numba
import numpy as np

from surfelwarp.deform.warp_field import WarpField, apply_update
from surfelwarp.geometry.se3 import se3_exp
from surfelwarp.tracking.anchors import (AnchorTerm, anchor_residuals, common_motion, deviation_m, follow_motion,
                                         seen_deviation_m, seen_directions)
from surfelwarp.tracking.assembly import Border, NormalEquations, blocks_from_parts, pair_block_parts
from surfelwarp.tracking.assembly_kernels import add_gradient, add_pair
from surfelwarp.tracking.linear import solve_system
from surfelwarp.tracking.terms import BaseTerm, Iterate, Problem, register


def _residuals(field: WarpField, anchor: AnchorTerm, G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(anchor residuals, anchor points z) (anchors.anchor_residuals) of the rest followed by G."""
    return anchor_residuals(field.transforms, follow_motion(anchor.rest, field.nodes, G), field.sigma_m)


def anchor_terms(field: WarpField, anchor: AnchorTerm, G: np.ndarray = np.eye(4), center: np.ndarray | None = None,
                 residuals: tuple[np.ndarray, np.ndarray] | None = None):
    """The anchor energy's terms (anchors.py), its rest transforms followed by the common motion G:
    the diagonal blocks (M, 6, 6) and gradient (M, 6) of the node twists (the anchor point
    z = L_j y moves by [-[z]x, I] xi_j under the update, the form pair_blocks sums), and, given
    a `center`, the border of G's twist zeta (rotation about center, G <- exp(zeta) G): the
    blocks (M, 6, 6) coupling each node's twist to zeta, zeta's own block (6, 6) and its
    gradient (6,); else None. The rest point q = G Rest_j y_a moves by [-[q - c]x, I] zeta and
    enters the residual with a minus sign. Summed in compiled code (anchor_terms_reference is
    the numpy form): numpy's per-point block parts took ~17 ms a call on 9k nodes. `residuals`:
    _residuals' of the same field, anchors and G, if already made."""
    res, z = _residuals(field, anchor, G) if residuals is None else residuals
    m, bordered = field.num_nodes, center is not None
    q = field.nodes[:, None, :] + z - res - center if bordered else z
    blocks, g = np.zeros((m, 6, 6)), np.zeros((m, 6))
    coupling, own, gz = np.zeros((m if bordered else 0, 6, 6)), np.zeros((6, 6)), np.zeros(6)
    _anchor_sums(np.ascontiguousarray(anchor.mu, np.float64), z, res, np.ascontiguousarray(q, np.float64), bordered,
                 blocks, g, coupling, own, gz)
    return blocks, g, ((coupling, own, gz) if bordered else None)


@numba.njit(cache=True, nogil=True)
def _anchor_sums(mu, z, res, q, bordered, blocks, g, coupling, own, gz):
    """Per anchored node and anchor point a: blocks += mu pair(z, z), g += mu (z x r, r) and,
    bordered, coupling -= mu pair(z, q), own += mu pair(q, q), gz -= mu (q x r, r)."""
    for j in range(len(mu)):
        w = mu[j]
        if w == 0.0:
            continue
        for a in range(z.shape[1]):
            add_pair(blocks[j], z[j, a], z[j, a], w)
            add_gradient(g[j], z[j, a], res[j, a], w)
            if bordered:
                add_pair(coupling[j], z[j, a], q[j, a], -w)
                add_pair(own, q[j, a], q[j, a], w)
                add_gradient(gz, q[j, a], res[j, a], -w)


def anchor_terms_reference(field: WarpField, anchor: AnchorTerm, G: np.ndarray = np.eye(4),
                           center: np.ndarray | None = None):
    """anchor_terms in numpy, the form the tests check the compiled sums with."""
    res, z = _residuals(field, anchor, G)
    m = field.num_nodes
    mu = anchor.mu[:, None, None]
    blocks = blocks_from_parts(pair_block_parts(z.reshape(-1, 3), z.reshape(-1, 3)).reshape(m, 4, 16).sum(axis=1))
    g = np.concatenate([np.cross(z, res), res], axis=-1).sum(axis=1)
    border = None
    if center is not None:
        q = (field.nodes[:, None, :] + z - res - center).reshape(-1, 3)
        coupling = -mu * blocks_from_parts(pair_block_parts(z.reshape(-1, 3), q).reshape(m, 4, 16).sum(axis=1))
        own = blocks_from_parts((np.repeat(anchor.mu, 4)[:, None] * pair_block_parts(q, q)).sum(axis=0)[None])[0]
        gz = -np.einsum("m,mai->i", anchor.mu, np.concatenate([np.cross(q.reshape(m, 4, 3), res), res], axis=-1))
        border = (coupling, own, gz)
    return mu * blocks, anchor.mu[:, None] * g, border


def anchor_energy(field: WarpField, anchor: AnchorTerm | None, G: np.ndarray = np.eye(4),
                  residuals: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    if anchor is None:
        return 0.0
    res, _ = _residuals(field, anchor, G) if residuals is None else residuals
    return float(np.sum(anchor.mu * np.sum(res ** 2, axis=(1, 2))))


def turn_about(center: np.ndarray, zeta: np.ndarray) -> np.ndarray:
    """The world rigid motion x -> c + exp(zeta) (x - c)."""
    T = se3_exp(np.asarray(zeta, np.float64))
    T[:3, 3] += center - T[:3, :3] @ center
    return T


def release(field: WarpField, system: NormalEquations, anchor: AnchorTerm, support: np.ndarray, seen, solver):
    """(M,) anchored nodes the data and regulariser alone (`system`) would move in one step
    farther than their release distance from rest, measured with the metric seen (M, 3, 3) (the
    directions their pairs see, anchors.py; None: every direction alike); the common motion G
    (4, 4) the rest follows: the one the still supported nodes share (identity unless
    anchor.common_motion); and whether the step fell back to LU. solver(system) -> Step."""
    step = solver(system)
    stepped = apply_update(field, step.xi).transforms
    anchored = anchor.mu > 0
    G = np.eye(4)
    if anchor.common_motion:
        G = common_motion(stepped, anchor.rest, field.nodes, field.sigma_m, support * anchored, anchor.release_m)
    rest = follow_motion(anchor.rest, field.nodes, G)
    moved = deviation_m(stepped, rest, field.sigma_m) if seen is None else \
        seen_deviation_m(stepped, rest, field.sigma_m, seen)
    return anchored & (support >= anchor.release_support) & (moved > anchor.release_m), G, step.lu_fallback


class RestAnchorTerm(BaseTerm):
    """The anchor term of one solve, with the state it carries across iterations: the anchors
    after the first iteration's release, the common motion G and its centre of rotation."""

    def __init__(self, anchor: AnchorTerm, knn: np.ndarray, weights: np.ndarray, solver):
        self.anchor, self.knn, self.weights, self.solver = anchor, knn, weights, solver
        self.G, self.center, self.held_rows = np.eye(4), None, None
        self.released: np.ndarray | None = None     # (M,) set by the first iteration
        self.at_rest: np.ndarray | None = None
        self.lu_fallbacks = 0

    def _motion(self, at: Iterate) -> np.ndarray:
        if self.center is None or at.border_step is None:
            return self.G
        return turn_about(self.center, at.border_step) @ self.G

    def energy(self, at: Iterate) -> float:
        return anchor_energy(at.field, self.anchor, self._motion(at))

    def accept(self, at: Iterate) -> None:
        self.G = self._motion(at)

    def _release(self, at: Iterate, system: NormalEquations) -> None:
        field, idx, anchor = at.field, at.pairs.index, self.anchor
        # Nodes held out of the solve do not see the depth: they neither release nor pull on
        # the common motion (they follow it at the end).
        solved = replace(anchor, mu=anchor.mu * system.free)
        knn, weights = np.take(self.knn, idx, axis=0), np.take(self.weights, idx, axis=0)
        support = np.bincount(knn.ravel(), weights.ravel(), minlength=field.num_nodes)
        u = anchor.release_unseen_weight
        seen = None if u >= 1 else (1 - u) * seen_directions(
            field.num_nodes, knn, weights, at.pairs.normals) + u * np.eye(3)
        released, G, fell_back = release(field, system, solved, support, seen, self.solver)
        self.lu_fallbacks += fell_back
        self.released, self.G = released, G
        self.at_rest = (anchor.mu > 0) & ~released
        self.anchor = replace(solved, mu=np.where(released, 0.0, solved.mu))
        if self.anchor.common_motion and self.anchor.mu.any():
            self.center = np.average(field.live_nodes(), axis=0, weights=self.anchor.mu)
            if self.anchor.held is not None and len(self.anchor.held):
                # G goes into the camera pose: not along what rigid ICP held.
                self.G = self.anchor.held.project(self.G)
                self.held_rows = self.anchor.held.rows(self.center)

    def linearize(self, at: Iterate, system: NormalEquations) -> float:
        if self.released is None:
            self._release(at, system)
        # One set of residuals for the blocks and the energy (~2 ms each on 9k nodes).
        residuals = _residuals(at.field, self.anchor, self.G)
        blocks, g, border = anchor_terms(at.field, self.anchor, self.G, self.center, residuals)
        if border is not None:
            B, C, gz = border
            if self.held_rows is not None and len(self.held_rows):
                C = C + 1e4 * max(np.trace(C) / 6, 1e-12) * self.held_rows.T @ self.held_rows
            system.border = Border(B, C, gz)
        system.add(g, diagonal=blocks)
        return anchor_energy(at.field, self.anchor, self.G, residuals)

    def finish(self, field: WarpField, free: np.ndarray) -> WarpField:
        """The nodes the solve held out follow the common motion of those it solved, as rigid
        ICP's motion would move them: the anchored ones at rest, the others as they are."""
        if self.center is None or free.all():
            return field
        out = ~free
        rest = out & self.at_rest
        transforms = field.transforms.copy()
        transforms[out] = follow_motion(transforms[out], field.nodes[out], self.G)
        transforms[rest] = follow_motion(self.anchor.rest[rest], field.nodes[rest], self.G)
        return field.with_transforms(transforms)


@register("rest_anchors")
def build(problem: Problem) -> RestAnchorTerm | None:
    if problem.anchor is None:
        return None
    p, rtol = problem.params, problem.anchor.release_step_rtol
    rtol = p.pcg_rtol if rtol is None else rtol
    return RestAnchorTerm(problem.anchor, problem.knn, problem.weights,
                          lambda system: solve_system(system, p.damping, p.linear_solver, rtol, p.pcg_max_iterations))
