"""Non-rigid warp field estimation by Gauss-Newton (SurfelWarp Sec. VII Eq. 8-10, DynamicFusion Eq. 6-8).

E = sum_c rho(n_c . (W(v_c) v_c - d_c)) + lambda * sum_j sum_{i in N(j)} |T_i p_j - T_j p_j|^2
    (+ rest anchors, + free space; tracking/terms/, one file per term)

Each node has a twist xi_j = (omega, v) that left-composes its node-local transform (L_j <-
exp(xi_j) L_j, blend_jacobian.py). Each iteration re-associates the warped surfels with the depth
(association.py), has every term add its 6x6 blocks of J^T W J and J^T W r into a sparsity pattern
fixed for the solve (assembly.py), solves the damped step by PCG or LU (linear.py), and keeps it
only if it lowers the energy over the same pairs (halved twice at most); the solve stops on a
step that is tiny or barely lowers the energy, on a step that does not lower it, or after
max_iterations. With rest anchors the common motion G of the anchored nodes is one more
6-vector unknown bordering the node system.
"""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field, replace

import numpy as np
import scipy.sparse as sp

from surfelwarp.deform.warp_field import WarpField, apply_update
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.dq_kernels import blend_apply
from surfelwarp.geometry.dual_quaternion import _components
from surfelwarp.tracking.alignment import Alignment, measure
from surfelwarp.tracking.anchors import AnchorTerm, node_information
from surfelwarp.tracking.assembly import BlockPattern, NormalEquations, dense_point_blocks
from surfelwarp.tracking.association import DepthTargets, associate_components
from surfelwarp.tracking.blend_jacobian import twist_dual_quaternions
from surfelwarp.tracking.coarse import MIN_FREE_NODES, CoarseSpace, coarse_space
from surfelwarp.tracking.features import AnchoredMatches
from surfelwarp.tracking.free_space import FreeSpace, SilhouetteParams
from surfelwarp.tracking.linear import LINEAR_SOLVERS, solve_system
from surfelwarp.tracking.terms import ROBUST, Iterate, Problem, build_terms, known_terms
from surfelwarp.tracking.terms.regulariser import reg_energy, regulariser_blocks


@dataclass(frozen=True)
class NonRigidParams:
    lambda_reg: float = 5.0            # SurfelWarp Table 1
    reg_huber_m: float = 0.002         # the regulariser's Huber corner (DynamicFusion's psi_reg;
                                       # 0: SurfelWarp's square): beyond it two nodes may part
                                       # (fingers, a sheet's fold) at a bounded cost, so that the
                                       # colour pairs at their own weight can move them (touch,
                                       # seeds 0-2: 2.87 / 2.29 / 1.74 mm at feature_weight 10 with
                                       # the square, 0.69 / 0.68 / 0.66 with a 2 mm corner; 1 mm:
                                       # 0.56 on seed 0, release 4.95 against 4.01)
    max_iterations: int = 10           # SurfelWarp Sec. VIII
    distance_gate_m: float = 0.03      # pairs farther apart than this are not correspondences
    min_normal_cos: float = 0.7        # normals within ~45 deg; looser than fusion's 0.85
                                       # because the field is still being corrected
    stop_motion_m: float = 1e-4        # the solve ends on an update that moves no node, nor (by
                                       # its rotation) any point sigma from a node, more than this,
    stop_energy_rel: float = 1e-2      # or that lowers the energy by less than this fraction
                                       # (5e-3: a third step on 27 of 59 7-Scenes frames, the
                                       # solve ~8 % longer, the figures the same within their
                                       # seeds' spread: README, Speed, "Twenty-fifth round")
    max_step_m: float = 0.05           # a step moving a node (or, by its turn, a point sigma from
                                       # it) farther than this is shortened to it: directions
                                       # only the free-space term sees are steep and short
    robust: str = "none"               # data-term penalty: 'none' | 'huber' | 'tukey'
    robust_scale_m: float = 0.01       # Huber corner / Tukey cut-off
    damping: float = 1e-6              # mu = damping * mean(diag(J^T J)) added to the diagonal:
                                       # keeps directions no term constrains solvable
    min_correspondences: int = 16
    linear_solver: str = "pcg"         # 'pcg': block-Jacobi preconditioned conjugate gradients
                                       # (as the GPU solver of Dou et al. that SurfelWarp follows),
                                       # falling back to 'direct' (sparse LU) when it does not
                                       # reach pcg_rtol in pcg_max_iterations; 'direct': LU only
    pcg_rtol: float = 1e-4             # stop at |(H + mu I) x + g| <= pcg_rtol |g_1|, g_1 the
                                       # solve's first gradient: the first step within ~1e-3 of
                                       # the exact one, final energies within ~1e-4. A later
                                       # step (inexact Gauss-Newton) is only a correction of
                                       # the first: to a tolerance in the solve's units, not
                                       # its own (7-Scenes: its |g| ~1 % of the first's, its
                                       # PCG 28-30 -> 11-13 iterations)
    pcg_max_rtol: float = 1e-2         # ... but never looser than this fraction of its own |g|
                                       # (as the rest anchors' release step; = pcg_rtol: every
                                       # step to pcg_rtol of its own)
    pcg_max_iterations: int = 500
    pcg_cell_radii: float = 6.0        # the PCG preconditioner's coarse level (coarse.py) on graphs
                                       # of 500 free nodes or more: nodes grouped by cells of this
                                       # many node radii, each moving rigidly (7-Scenes: ~105
                                       # instead of ~380 iterations a frame); 0: block-Jacobi alone
    feature_weight: float = 10.0       # a colour feature (terms/features.py) against a depth pixel's
                                       # weight of 1: their inverse variances (a pair's ends differ
                                       # by 0.3-0.45 mm along each axis on orbit, a depth pixel by
                                       # ~1.4 mm along its ray) make it ~12. At 100 the still
                                       # orbit drifted more (EPE 1.76 against 1.06 mm at 10) and
                                       # twist-limb's limb lagged (1.93 against 1.50); 0: off
    feature_huber_m: float = 0.01      # its Huber corner
    feature_normal_share: float = 0.1  # its weight along the surface normal, where depth is the
                                       # better judge, against along the surface (1: a distance)
    free_rings: int | None = 2         # nodes more than this many graph edges from every node
                                       # skinning a solved (visible) surfel are held fixed
                                       # (None: none are). Out of view they only carry the
                                       # regulariser; on a room they are most of the graph and
                                       # make the system slow to solve by PCG.
    # Model points where the camera saw through them are pulled back (free_space.py).
    silhouette: SilhouetteParams = dc_field(default_factory=SilhouetteParams)
    # The energy's terms, summed in this order (tracking/terms/: one file each). The rest
    # anchors' release test sees the terms before it; a term that is off for a solve (anchors
    # without an anchor state, free space at weight 0) is left out.
    terms: tuple[str, ...] = ("depth", "features", "regulariser", "rest_anchors", "free_space")

    ZERO_OK = {"lambda_reg", "reg_huber_m", "max_iterations", "min_normal_cos", "stop_motion_m", "stop_energy_rel",
               "damping", "feature_weight", "feature_normal_share", "free_rings", "pcg_cell_radii"}
    UNIT = {"min_normal_cos", "stop_energy_rel", "pcg_rtol", "pcg_max_rtol", "feature_normal_share"}

    def __post_init__(self):
        if self.robust not in ROBUST:
            raise ValueError(f"robust must be one of {', '.join(ROBUST)}, got {self.robust!r}")
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(f"linear_solver must be one of {', '.join(LINEAR_SOLVERS)}, got {self.linear_solver!r}")

    CHOICES = {"robust": ROBUST, "linear_solver": LINEAR_SOLVERS}

    def problems(self) -> dict[str, str | bool]:
        unknown = [n for n in self.terms if n not in known_terms()]
        return {"terms": unknown and f"unknown term(s) {', '.join(unknown)}; known: {', '.join(known_terms())}"}


@dataclass(frozen=True)
class NonRigidResult:
    iterations: int                # Gauss-Newton steps solved
    energy: float                  # total E at the returned field (freshly associated)
    reg_energy: float              # the regulariser's penalties summed (squares within its Huber
                                   # corner), m^2 (before lambda)
    correspondences: int           # at the returned field
    energies: tuple[float, ...]    # total E at the start of every iteration, then the final one
    converged: bool                # ended on a tiny update or energy decrease (not on the
                                   # iteration limit, an energy rise or too few pairs)
    node_information: np.ndarray | None = None   # (M, 3, 3) what the final depth pairs measure of
                                                 # each node's motion (anchors.node_information)
    released: np.ndarray | None = None       # (M,) anchored nodes this solve set free (anchors.py)
    silhouette_points: int = 0               # model points the camera saw through, at the result
    alignment: Alignment | None = None       # model and depth explaining each other, at the result
    lu_fallbacks: int = 0                    # steps PCG did not converge on, solved by sparse LU
    term_energies: dict[str, float] = dc_field(default_factory=dict)   # each term's, at the result

    @property
    def data_energy(self) -> float:
        """Sum of rho(point-to-plane residual), m^2."""
        return self.term_energies.get("depth", 0.0)

    @property
    def silhouette_energy(self) -> float:
        """Weight * sum of Huber(r) of the free-space term, m^2."""
        return self.term_energies.get("free_space", 0.0)

    @property
    def data_rmse_m(self) -> float:
        return float(np.sqrt(self.data_energy / self.correspondences)) if self.correspondences else float("nan")


def free_nodes(graph: np.ndarray, supported: np.ndarray, rings: int) -> np.ndarray:
    """(M,) bool: the supported nodes and those within `rings` graph edges of one (either
    direction of an edge counts)."""
    free = np.asarray(supported, bool).copy()
    graph = np.asarray(graph, np.int64)
    for _ in range(max(rings, 0)):
        grown = free | free[graph].any(axis=1)
        grown[graph[free].reshape(-1)] = True
        if np.array_equal(grown, free):
            break
        free = grown
    return free


def normal_equations(field: WarpField, J_data: np.ndarray, knn: np.ndarray, r_data: np.ndarray,
                     w_data: np.ndarray, lambda_reg: float) -> tuple[sp.bsr_matrix, np.ndarray]:
    """J^T W J (sparse 6x6-block, 6M x 6M) and J^T W r of the data rows (C, k, 6) and the
    regulariser, from explicit Jacobians: the reference the solve's factored sums are tested on."""
    pattern = BlockPattern(field.num_nodes, field.graph, knn)
    w = np.asarray(w_data, np.float64)
    bd, gd = dense_point_blocks(pattern, np.asarray(J_data, np.float64), np.asarray(r_data, np.float64), w)
    br, gr = regulariser_blocks(field, pattern)
    return pattern.matrix(bd + lambda_reg * br), (gd + lambda_reg * gr).reshape(-1)


def warp_state(field, ref_points, ref_normals, knn, weights):
    """Everything one field gives the surfels (reference points and normals as components
    (3, N)): node dual quaternions, blends (N, 8), signed weights (N, k), live points and
    normals (3, N)."""
    dq = field.dual_quaternions()
    b, signed, live, live_n = blend_apply(dq, knn, weights, ref_points, ref_normals)
    return dq, b, signed, live, live_n


class Solve:
    """One solve's fixed inputs: the surfels, the depth targets and the terms."""

    def __init__(self, problem: Problem):
        self.problem, p = problem, problem.params
        self.targets = DepthTargets(problem.depth_vertex_map, problem.depth_normal_map, problem.depth_valid,
                                    problem.intrinsics, problem.T_camera_to_world)
        self.terms = build_terms(p.terms, problem)
        self.pattern = None
        self.coarse = None
        self.coarse_factor = None
        self.first_gradient_norm = None

    def at(self, field: WarpField, pairs=None, state=None, border_step=None) -> Iterate:
        """The iterate of `field` (its warp state given or computed), associated afresh unless
        the iteration's pairs are given."""
        pb = self.problem
        state = warp_state(field, pb.ref_points, pb.ref_normals, pb.knn, pb.weights) if state is None else state
        if pairs is None:
            pairs = associate_components(state[3], state[4], self.targets, pb.params.distance_gate_m,
                                         pb.params.min_normal_cos)
        return Iterate(field, *state, pairs, border_step)

    def candidate(self, at: Iterate, field: WarpField, border_step) -> Iterate:
        """A candidate field of the iteration at `at`, over the same pairs."""
        return self.at(field, at.pairs, border_step=border_step)

    def energy(self, at: Iterate) -> float:
        return sum(term.energy(at) for term in self.terms)

    def pattern_for(self, field: WarpField) -> BlockPattern:
        """The block pattern, built once per solve (the graph and the skinning are fixed in one)."""
        if self.pattern is None:
            self.pattern = BlockPattern(field.num_nodes, field.graph, self.problem.knn)
        return self.pattern

    def coarse_for(self, field: WarpField, free: np.ndarray) -> CoarseSpace | None:
        """The preconditioner's cells, built once per solve (the nodes and the free ones are
        fixed in one); none for a small graph."""
        radii = self.problem.params.pcg_cell_radii
        if self.coarse is None and radii > 0 and free.sum() >= MIN_FREE_NODES:
            pattern = self.pattern_for(field)
            self.coarse = coarse_space(field.nodes, free, pattern.lo, pattern.hi, radii * field.params.node_radius_m)
        return self.coarse

    def linearize(self, at: Iterate, free: np.ndarray) -> tuple[float, NormalEquations]:
        """The energy at `at` and the normal equations of every term there."""
        system = NormalEquations(self.pattern_for(at.field), free, twist_dual_quaternions(at.field, at.dq),
                                 coarse=self.coarse_for(at.field, free))
        return sum(term.linearize(at, system) for term in self.terms), system

    def step(self, system: NormalEquations):
        """The iteration's step, preconditioned with the solve's first coarse factor, to
        pcg_rtol of the solve's first gradient (NonRigidParams.pcg_max_rtol)."""
        p = self.problem.params
        norm = system.gradient_norm()
        if self.first_gradient_norm is None:
            self.first_gradient_norm = norm
        rtol = p.pcg_rtol
        if norm > 0:
            rtol = max(p.pcg_rtol, min(p.pcg_max_rtol, p.pcg_rtol * self.first_gradient_norm / norm))
        step = solve_system(system, p.damping, p.linear_solver, rtol, p.pcg_max_iterations, self.coarse_factor)
        if self.coarse_factor is None:
            self.coarse_factor = step.coarse
        return step


def _motion(field: WarpField, stepped: WarpField, xi: np.ndarray) -> float:
    """The largest distance the step xi (field -> stepped) moves a node, or by its turn a point
    sigma from one."""
    moved = np.linalg.norm(stepped.transforms[:, :3, 3] - field.transforms[:, :3, 3], axis=1)
    return float(np.max(moved + field.sigma_m * np.linalg.norm(xi[:, :3], axis=1)))


def solve_nonrigid(field: WarpField, ref_points: np.ndarray, ref_normals: np.ndarray, knn: np.ndarray,
                   weights: np.ndarray, depth_vertex_map: np.ndarray, depth_normal_map: np.ndarray,
                   depth_valid: np.ndarray, intrinsics: Intrinsics, T_camera_to_world: np.ndarray,
                   params: NonRigidParams = NonRigidParams(),
                   anchor: AnchorTerm | None = None,
                   depth_beyond: np.ndarray | None = None,
                   free_space: FreeSpace | None = None,
                   matches: AnchoredMatches | None = None) -> tuple[WarpField, NonRigidResult]:
    """Gauss-Newton on Eq. 8 and the other terms of params.terms, starting from `field`; returns
    the improved field and a summary.

    ref_points/ref_normals (N, 3) are the reference positions of the model surfels to use (the
    visible ones), knn/weights their skinning; the depth maps are the observation's, camera frame.
    With an anchor term (anchors.py), its nodes are held at rest up to one rigid motion G they
    share, solved with them, except those the first iteration releases; nodes held out of the
    solve follow G at the end. depth_beyond (H, W), if given, marks pixels measured past the far
    clip, free space for the free-space term (free_space.py); `free_space`, if given, is that
    term's view of this observation (at any pose), reused instead of built again. `matches`, if
    given, are colour features on the solved surfels (the feature term).
    """
    knn = np.asarray(knn, np.int64)
    points, normals = (_components(np.reshape(a, (-1, 3))) for a in (ref_points, ref_normals))
    solve = Solve(Problem(field, points, normals, knn, np.asarray(weights, np.float64), depth_vertex_map,
                          depth_normal_map, depth_valid, intrinsics, T_camera_to_world, params, anchor, depth_beyond,
                          free_space, matches))
    free = np.ones(field.num_nodes, bool)
    if params.free_rings is not None:
        in_view = np.zeros(field.num_nodes, bool)
        in_view[knn.reshape(-1)] = True
        free = free_nodes(field.graph, in_view, params.free_rings)
    current, energies, steps, converged, fallbacks = solve.at(field), [], 0, False, 0
    for _ in range(params.max_iterations):
        if len(current.pairs.index) < params.min_correspondences:
            break
        total, system = solve.linearize(current, free)
        energies.append(total)
        step = solve.step(system)
        steps, fallbacks = steps + 1, fallbacks + step.lu_fallback
        if not (np.all(np.isfinite(step.xi)) and np.all(np.isfinite(step.zeta))):
            break
        stepped = apply_update(current.field, step.xi)
        longest = _motion(current.field, stepped, step.xi)
        if longest < params.stop_motion_m:
            candidate = solve.at(stepped, border_step=step.zeta)
            for term in solve.terms:
                term.accept(candidate)
            current, converged = replace(candidate, border_step=None), True   # the step is taken
            break
        # The candidate's energy is over the iteration's pairs. A step that raises it is halved
        # (twice at most): the free-space term is far from linear over a long step.
        scale = min(1.0, params.max_step_m / longest)
        for scale in (scale, 0.5 * scale, 0.25 * scale):
            trial = stepped if scale == 1.0 else apply_update(current.field, scale * step.xi)
            candidate = solve.candidate(current, trial, scale * step.zeta)
            e_new = solve.energy(candidate)
            if e_new < total:
                break
        if not e_new < total:
            break
        for term in solve.terms:
            term.accept(candidate)
        current = solve.at(candidate.field, state=(candidate.dq, candidate.blends, candidate.signed,
                                                   candidate.live, candidate.live_normals))
        if total - e_new < params.stop_energy_rel * total:
            converged = True
            break
    return _result(solve, current, free, steps, energies, converged, fallbacks)


def _finished(solve: Solve, current: Iterate, field: WarpField) -> Iterate:
    """The iterate of the finished field: the current one's warp and pairs if finishing moved
    no node that skins a solved surfel (the rest anchors move only the nodes held out of the
    solve), else warped and associated afresh."""
    if field is current.field:
        return current
    moved = np.any(field.transforms != current.field.transforms, axis=(1, 2))
    if moved[solve.problem.knn].any():
        return solve.at(field)
    return replace(current, field=field, dq=field.dual_quaternions())


def _result(solve: Solve, current: Iterate, free: np.ndarray, steps: int, energies: list, converged: bool,
            fallbacks: int) -> tuple[WarpField, NonRigidResult]:
    """The returned field (after every term's finish) and the summary of it: its solved
    surfels' warp and depth pairs (_finished), its energies by term."""
    field = current.field
    for term in solve.terms:
        field = term.finish(field, free)
    final = _finished(solve, current, field)
    named = {term.name: term for term in solve.terms}
    anchors, free_space = named.get("rest_anchors"), named.get("free_space")
    seen = free_space.seen_through(final) if free_space else None      # its energy and points at once
    by_term = {term.name: seen[0] if term is free_space else term.energy(final) for term in solve.terms}
    total = sum(by_term.values())
    energies.append(total)
    pb, pairs = solve.problem, final.pairs
    information = node_information(field.num_nodes, pb.knn[pairs.index], pb.weights[pairs.index], pairs.normals)
    vertex = np.asarray(pb.depth_vertex_map)
    alignment = measure(final.live.T, final.live_normals.T, pb.T_camera_to_world, vertex[..., 2], vertex,
                        pb.depth_valid, pb.intrinsics)
    return field, NonRigidResult(
        iterations=steps, energy=total,
        reg_energy=reg_energy(field, pb.params.reg_huber_m),
        correspondences=len(pairs.index), energies=tuple(energies), converged=converged,
        node_information=information,
        released=anchors.released if anchors else None, silhouette_points=len(seen[1]) if seen else 0,
        alignment=alignment, lu_fallbacks=fallbacks + (anchors.lu_fallbacks if anchors else 0),
        term_energies=by_term)
