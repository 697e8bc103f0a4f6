"""Rest anchors (tracking/anchors.py, tracking/terms/rest_anchors.py): their Jacobians (the nodes' and the common motion's), release in
the solve under a pose error, nodes out of the solve following the common motion, settling,
following the field's nodes, and factoring the camera motion out of the anchored nodes."""
import numpy as np
import pytest

from surfelwarp.tracking.anchors import (AnchorParams, AnchorTerm, NodeAnchors, anchor_residuals, deviation_m,
                                         follow_motion, seen_deviation_m, seen_directions)
from surfelwarp.deform.warp_field import WarpField, apply_update, extend, skin, to_global, to_local
from surfelwarp.geometry.camera import axial_noise_sigma_m
from surfelwarp.geometry.se3 import se3_exp
from surfelwarp.tracking.terms.rest_anchors import anchor_energy, anchor_terms, anchor_terms_reference, turn_about
from surfelwarp.tracking.tracker import factor_rigid_motion

from test_gauss_newton import INTR, T_CW, Problem, bend, solve_nonrigid


def sheet_field(n=400, seed=0):
    rng = np.random.default_rng(seed)
    return WarpField.from_points(rng.uniform(-0.3, 0.3, (n, 3)) * [1, 1, 0.1])


def test_anchor_blocks_and_gradient_match_finite_differences():
    rng = np.random.default_rng(1)
    field = apply_update(sheet_field(), rng.normal(size=(len(sheet_field().nodes), 6)) * 0.05)
    m = field.num_nodes
    rest = apply_update(field, rng.normal(size=(m, 6)) * 0.02).transforms
    term = AnchorTerm(rng.uniform(0.5, 2.0, m), rest, np.full(m, np.inf))
    blocks, g, border = anchor_terms(field, term)
    assert border is None
    h = 1e-6
    J = np.zeros((m, 4, 3, 6))
    for c in range(6):
        xi = np.zeros((m, 6))
        xi[:, c] = h               # nodes are independent: one pass per twist component
        plus = anchor_residuals(apply_update(field, xi).transforms, rest, field.sigma_m)[0]
        minus = anchor_residuals(apply_update(field, -xi).transforms, rest, field.sigma_m)[0]
        J[..., c] = (plus - minus) / (2 * h)
    r, _ = anchor_residuals(field.transforms, rest, field.sigma_m)
    mu = term.mu[:, None, None]
    numeric_blocks = mu * np.einsum("makc,makd->mcd", J, J)
    numeric_g = mu[:, :, 0] * np.einsum("makc,mak->mc", J, r)
    err_b = np.abs(blocks - numeric_blocks).max() / np.abs(numeric_blocks).max()
    err_g = np.abs(g - numeric_g).max() / np.abs(numeric_g).max()
    print(f"anchor Jacobian vs central differences: blocks {err_b:.1e}, gradient {err_g:.1e}")
    assert err_b < 1e-6 and err_g < 1e-6
    # The gradient is that of half the energy.
    xi = np.zeros((m, 6))
    xi[3, 4] = h
    dE = (anchor_energy(apply_update(field, xi), term) - anchor_energy(apply_update(field, -xi), term)) / (2 * h)
    assert abs(0.5 * dE - g[3, 4]) < 1e-6 * np.abs(g).max()


@pytest.mark.parametrize("bordered", [False, True])
def test_compiled_anchor_terms_equal_the_numpy_reference(bordered):
    """The compiled sums against anchor_terms_reference (which the finite-difference tests
    also pass): the nodes' blocks and gradient and the border's, a third of the nodes free."""
    rng = np.random.default_rng(7)
    field = apply_update(sheet_field(), rng.normal(size=(len(sheet_field().nodes), 6)) * 0.05)
    m = field.num_nodes
    rest = apply_update(field, rng.normal(size=(m, 6)) * 0.02).transforms
    term = AnchorTerm(rng.uniform(0.5, 2.0, m) * (rng.random(m) > 1 / 3), rest, np.full(m, np.inf))
    G, center = se3_exp(np.array([0.01, -0.02, 0.005, 0.003, 0.0, -0.004])), np.array([0.05, -0.1, 1.0])
    args = (field, term, G, center if bordered else None)
    blocks, g, border = anchor_terms(*args)
    ref_blocks, ref_g, ref_border = anchor_terms_reference(*args)
    assert (term.mu == 0).sum() > m / 5 and np.all(blocks[term.mu == 0] == 0)
    for got, want in [(blocks, ref_blocks), (g, ref_g)] + (list(zip(border, ref_border)) if bordered else []):
        assert got.shape == want.shape and np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    assert (border is None) == (not bordered)


def test_common_motion_terms_match_finite_differences():
    """The blocks coupling node twists to the common motion's twist zeta, zeta's own block and
    gradient, against central differences of the residuals L_j y_a - G Rest_j y_a."""
    rng = np.random.default_rng(2)
    field = sheet_field(60)
    m = field.num_nodes
    field = apply_update(field, rng.normal(size=(m, 6)) * 0.05)
    rest = apply_update(field, rng.normal(size=(m, 6)) * 0.02).transforms
    term = AnchorTerm(rng.uniform(0.5, 2.0, m), rest, np.full(m, np.inf))
    G = se3_exp(np.array([0.03, -0.02, 0.05, 0.01, 0.02, -0.01]))
    center = np.array([0.1, -0.05, 0.9])
    _, _, (border, own, gz) = anchor_terms(field, term, G, center)

    def residuals(transforms, motion):
        return anchor_residuals(transforms, follow_motion(rest, field.nodes, motion), field.sigma_m)[0]

    h = 1e-6
    Jz = np.zeros((m, 4, 3, 6))
    Jn = np.zeros((m, 4, 3, 6))
    for c in range(6):
        e = np.zeros(6)
        e[c] = h
        Jz[..., c] = (residuals(field.transforms, turn_about(center, e) @ G)
                      - residuals(field.transforms, turn_about(center, -e) @ G)) / (2 * h)
        xi = np.tile(e, (m, 1))
        Jn[..., c] = (residuals(apply_update(field, xi).transforms, G)
                      - residuals(apply_update(field, -xi).transforms, G)) / (2 * h)
    r = residuals(field.transforms, G)
    mu = term.mu
    numeric = (np.einsum("m,makc,makd->mcd", mu, Jn, Jz), np.einsum("m,makc,makd->cd", mu, Jz, Jz),
               np.einsum("m,makc,mak->c", mu, Jz, r))
    errors = [np.abs(a - b).max() / np.abs(b).max() for a, b in zip((border, own, gz), numeric)]
    print("common motion terms vs central differences: " + ", ".join(f"{e:.1e}" for e in errors))
    assert max(errors) < 1e-6


def half_bend(p):
    """The sheet's left half rolls away (up to ~9 cm), its right half stays where it was."""
    return np.where((p[..., 0] < 0)[..., None], bend(p, shift=(0.0, 0.0, 0.0)), p)


# A camera pose error: the whole scene appears moved by this (6 mm, 0.3 deg).
POSE_ERROR = se3_exp(np.array([0.0, 0.005, 0.0, 0.006, 0.0, -0.002]))


def seen_off_pose(p):
    return p @ POSE_ERROR[:3, :3].T + POSE_ERROR[:3, 3]


def half_bend_seen_off_pose(p):
    return seen_off_pose(half_bend(p))


def test_the_solve_releases_moving_nodes_and_holds_the_still_ones():
    """Under a pose error the still half moves rigidly with the anchors' common motion and stays
    anchored; the rolling half is released. Anchored to rest itself, the still half would be
    released too (the pose error moves it beyond 2 sigma)."""
    prob = Problem(moved=half_bend_seen_off_pose)
    m = prob.field.num_nodes
    release = 2 * axial_noise_sigma_m(1.0)
    anchor = AnchorTerm(np.ones(m), prob.field.transforms.copy(), np.full(m, release))
    field, res = solve_nonrigid(prob.field, prob.points, prob.normals, prob.knn, prob.weights, *prob.maps,
                                INTR, T_CW, anchor=anchor)
    nodes = prob.field.nodes.astype(np.float64)
    moves = np.linalg.norm(half_bend(nodes) - nodes, axis=1)
    err = prob.error(field)
    still = nodes[:, 0] > 0.1
    followed = deviation_m(field.transforms[still], follow_motion(anchor.rest[still], nodes[still], POSE_ERROR),
                           field.sigma_m)
    print(f"half bend off pose: {res.released.sum()} of {m} nodes released; error mean {err.mean() * 1000:.2f} mm;"
          f" still nodes within {followed.max() * 1000:.2f} mm of the pose error")
    assert res.released[moves > 0.01].all()
    assert not res.released[still].any()
    assert followed.max() < 3e-4
    assert err.mean() < 0.003
    # Every iteration's energy includes the common motion: converged, the last one is the
    # returned field's (an energy without it would stay well above the final one).
    assert res.converged and abs(res.energies[-1] - res.energies[-2]) < 0.05 * res.energies[-1]
    absolute = AnchorTerm(anchor.mu, anchor.rest, anchor.release_m, common_motion=False)
    _, res_abs = solve_nonrigid(prob.field, prob.points, prob.normals, prob.knn, prob.weights, *prob.maps,
                                INTR, T_CW, anchor=absolute)
    assert res_abs.released[still].mean() > 0.9
    # Nodes without that much support of their own are never released.
    gated = AnchorTerm(anchor.mu, anchor.rest, anchor.release_m, release_support=np.inf)
    _, res_gated = solve_nonrigid(prob.field, prob.points, prob.normals, prob.knn, prob.weights, *prob.maps,
                                  INTR, T_CW, anchor=gated)
    assert not res_gated.released.any()
    # With everything anchored and nothing released the bend could not be followed.
    stiff = AnchorTerm(np.full(m, 1e3), anchor.rest, np.full(m, np.inf))
    held, _ = solve_nonrigid(prob.field, prob.points, prob.normals, prob.knn, prob.weights, *prob.maps,
                             INTR, T_CW, anchor=stiff)
    assert prob.error(held).mean() > 5 * err.mean()


def test_the_release_step_is_solved_to_its_own_tolerance(monkeypatch):
    """The release test's free step is solved to release_step_rtol, not the solve's pcg_rtol:
    fewer PCG iterations; the moving nodes released and the still ones held as at the full
    tolerance, a few at the threshold apart, and the bend followed as closely."""
    import surfelwarp.tracking.terms.rest_anchors as rest_anchors
    solve_system, calls = rest_anchors.solve_system, []

    def recording(system, damping, linear_solver, rtol, max_iterations):
        step = solve_system(system, damping, linear_solver, rtol, max_iterations)
        calls.append((rtol, step.iterations))
        return step

    monkeypatch.setattr(rest_anchors, "solve_system", recording)
    prob = Problem(moved=half_bend_seen_off_pose)
    m = prob.field.num_nodes
    release = np.full(m, 2 * axial_noise_sigma_m(1.0))
    runs = {}
    for rtol in (None, 1e-2):
        anchor = AnchorTerm(np.ones(m), prob.field.transforms.copy(), release, release_step_rtol=rtol)
        calls.clear()
        runs[rtol] = solve_nonrigid(prob.field, prob.points, prob.normals, prob.knn, prob.weights, *prob.maps,
                                    INTR, T_CW, anchor=anchor) + (calls[0],)
    (full, res_full, (rtol_full, it_full)), (loose, res_loose, (rtol_loose, it_loose)) = runs[None], runs[1e-2]
    print(f"release step: {it_full} PCG iterations at {rtol_full}, {it_loose} at {rtol_loose}; "
          f"{res_full.released.sum()} and {res_loose.released.sum()} of {m} released")
    nodes = prob.field.nodes.astype(np.float64)
    moving, still = np.linalg.norm(half_bend(nodes) - nodes, axis=1) > 0.01, nodes[:, 0] > 0.1
    apart = res_loose.released != res_full.released
    print(f"  {apart.sum()} released at one tolerance only; error {prob.error(full).mean() * 1000:.3f} and "
          f"{prob.error(loose).mean() * 1000:.3f} mm")
    assert rtol_full == 1e-4 and rtol_loose == 1e-2
    assert it_loose < 0.5 * it_full
    assert res_loose.released[moving].all() and not res_loose.released[still].any()
    assert apart.sum() <= 0.02 * m and not apart[moving | still].any()
    assert prob.error(loose).mean() < 1.05 * prob.error(full).mean()
    term = NodeAnchors.at_rest(prob.field).term(AnchorParams(release_step_rtol=0.03), np.ones(m), m)
    assert term.release_step_rtol == 0.03


def test_a_solve_factors_its_coarse_level_once_per_kind_of_system(monkeypatch):
    """The PCG's coarse factor is made once for the release test's free step and once for the
    bordered steps, however many Gauss-Newton iterations follow (the first is reused); the
    field as without the coarse level (block-Jacobi alone): each PCG stops at 1e-4 of its own
    gradient (pcg_max_rtol: the later steps too), and over six iterations two nodes' turns
    differ by 3e-5."""
    import surfelwarp.tracking.gauss_newton as gauss_newton
    import surfelwarp.tracking.linear as linear
    made = []
    factor = linear.factor
    monkeypatch.setattr(linear, "factor", lambda *a: made.append(a[5] is not None) or factor(*a))
    monkeypatch.setattr(gauss_newton, "MIN_FREE_NODES", 100)
    prob = Problem(moved=half_bend_seen_off_pose)
    m = prob.field.num_nodes
    anchor = AnchorTerm(np.ones(m), prob.field.transforms.copy(), np.full(m, 2 * axial_noise_sigma_m(1.0)))
    fields = {}
    for radii in (6.0, 0.0):
        params = gauss_newton.NonRigidParams(pcg_cell_radii=radii, pcg_max_rtol=1e-4)
        fields[radii], res = solve_nonrigid(prob.field, prob.points, prob.normals, prob.knn, prob.weights,
                                            *prob.maps, INTR, T_CW, params=params, anchor=anchor)
        if radii:
            print(f"{res.iterations} Gauss-Newton iterations, coarse factors made: {made}")
            assert res.iterations >= 3 and made == [False, True]
    assert made == [False, True]
    np.testing.assert_allclose(fields[6.0].transforms, fields[0.0].transforms, atol=1e-4)
    assert abs(prob.error(fields[6.0]).mean() - prob.error(fields[0.0]).mean()) < 0.01 * prob.error(fields[0.0]).mean()


def test_seen_directions_of_a_plane_a_cylinder_and_a_ball():
    """Known answers: pairs on a plane see its normal only, on a cylinder all but its axis, on a
    ball every direction; a node without pairs sees none. The release distance then counts a
    slide along the plane as nothing and a move along its normal in full."""
    rng = np.random.default_rng(3)
    c = 600
    ball = rng.normal(size=(c, 3))
    angle = rng.uniform(0, 2 * np.pi, c)
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (c, 1)),
                              np.stack([np.cos(angle), np.sin(angle), np.zeros(c)], 1),
                              ball / np.linalg.norm(ball, axis=1, keepdims=True)])
    knn = np.repeat([[0, 0], [1, 1], [2, 2]], c, axis=0)       # node 3 has no pairs
    weights = rng.uniform(0.1, 1.0, (3 * c, 2))
    seen = seen_directions(4, knn, weights, normals)
    np.testing.assert_allclose(seen[0], np.diag([0.0, 0.0, 1.0]), atol=1e-12)
    np.testing.assert_allclose(seen[1], np.diag([1.0, 1.0, 0.0]), atol=0.15)
    np.testing.assert_allclose(seen[2], np.eye(3), atol=0.2)
    np.testing.assert_array_equal(seen[3], 0.0)
    for e in seen[:3]:
        assert np.isclose(np.linalg.eigvalsh(e)[-1], 1.0)
    sigma = 0.02
    rest = np.tile(np.eye(4), (4, 1, 1))
    slide, lift = rest.copy(), rest.copy()
    slide[:, :3, 3] = [0.01, -0.02, 0.0]
    lift[:, :3, 3] = [0.0, 0.0, 0.01]
    assert seen_deviation_m(slide, rest, sigma, seen)[0] < 1e-9
    np.testing.assert_allclose(seen_deviation_m(lift, rest, sigma, seen)[[0, 2]], 0.01, rtol=0.2)
    np.testing.assert_allclose(deviation_m(slide, rest, sigma), np.hypot(0.01, 0.02))
    assert seen_deviation_m(slide, rest, sigma, seen)[3] == 0.0


def test_seen_directions_sum_as_bincount_does():
    """The compiled sums equal, to the bit, np.bincount's over the raveled pairs (their numpy
    form): random nodes, weights and normals, nodes repeated within a pair."""
    rng = np.random.default_rng(6)
    m, c, k = 30, 5000, 4
    knn = rng.integers(0, m - 2, (c, k))                        # the last two nodes see nothing
    weights = rng.uniform(0, 1, (c, k)).astype(np.float32)
    normals = rng.normal(size=(c, 3))
    nn = (normals[:, :, None] * normals[:, None, :]).reshape(-1, 9)
    w = weights.astype(np.float64).ravel()
    S = np.stack([np.bincount(knn.ravel(), w * np.repeat(nn[:, e], k), minlength=m) for e in range(9)], 1)
    S = S.reshape(-1, 3, 3)
    top = np.linalg.eigvalsh(S)[:, -1]
    expected = S / np.where(top > 0, top, 1.0)[:, None, None]
    assert np.array_equal(seen_directions(m, knn, weights, normals), expected)


def test_nodes_outside_the_solve_follow_the_common_motion():
    """A still sheet seen under a pose error, with part of the field 1 m to the side, out of
    view and out of the solve: its nodes move with the common motion as the seen ones do (as
    rigid ICP would have moved them), the anchored ones to rest, a released one as it was."""
    prob = Problem(moved=seen_off_pose)
    s, t = np.meshgrid(np.arange(1.0, 1.3, 0.01), np.arange(-0.2, 0.2, 0.01))
    aside = np.stack([s, t, np.ones_like(s)], -1).reshape(-1, 3)
    field = WarpField.from_points(np.concatenate([prob.points, aside]).astype(np.float32))
    knn, weights = skin(prob.points, field.nodes, 4, field.sigma_m)
    m = field.num_nodes
    out = field.nodes[:, 0] > 0.9
    loose = np.flatnonzero(out)[0]                      # released in an earlier frame
    mu = np.ones(m)
    mu[loose] = 0.0
    start = field.transforms.copy()
    start[loose] = se3_exp(np.array([0.0, 0.0, 0.1, 0.01, 0.0, 0.0]))
    anchor = AnchorTerm(mu, field.transforms.copy(), np.full(m, 2 * axial_noise_sigma_m(1.0)))
    solved, res = solve_nonrigid(field.with_transforms(start), prob.points, prob.normals, knn, weights, *prob.maps,
                                 INTR, T_CW, anchor=anchor)
    nodes = field.nodes.astype(np.float64)
    held = out & (mu > 0)
    rest_err = deviation_m(solved.transforms[held], follow_motion(anchor.rest[held], nodes[held], POSE_ERROR),
                           field.sigma_m)
    loose_err = deviation_m(solved.transforms[[loose]], follow_motion(start[[loose]], nodes[[loose]], POSE_ERROR),
                            field.sigma_m)
    print(f"{held.sum()} anchored nodes out of the solve within {rest_err.max() * 1000:.2f} mm of the pose error,"
          f" the released one within {loose_err[0] * 1000:.2f} mm")
    assert not res.released.any()
    assert rest_err.max() < 3e-4 and loose_err[0] < 3e-4
    # The summary is of the returned field: the nodes that moved last skin no solved surfel, so
    # the solve's last warp and pairs stand; associated afresh, the same figures to the bit.
    import surfelwarp.tracking.gauss_newton as gauss_newton
    fresh = lambda solve, current, field: solve.at(field)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(gauss_newton, "_finished", fresh)
        again, res_fresh = solve_nonrigid(field.with_transforms(start), prob.points, prob.normals, knn, weights,
                                          *prob.maps, INTR, T_CW, anchor=anchor)
    np.testing.assert_array_equal(again.transforms, solved.transforms)
    assert (res.energy, res.correspondences, res.alignment) == (res_fresh.energy, res_fresh.correspondences,
                                                                res_fresh.alignment)
    np.testing.assert_array_equal(res.node_information, res_fresh.node_information)


def test_released_nodes_settle_after_staying_put():
    field = sheet_field()
    m = field.num_nodes
    params = AnchorParams(settle_sigmas=1.0, settle_frames=3)
    depth = np.ones(m)
    sigma = axial_noise_sigma_m(1.0)
    state = NodeAnchors.at_rest(field).release(np.arange(m) < m // 2)
    rng = np.random.default_rng(3)
    moved = se3_exp(np.tile([0, 0, 0, 0.02, 0, 0], (m, 1))) @ field.transforms
    drifting = np.arange(m) < m // 8            # keeps moving 2 sigma a frame
    # Creeping 0.6 sigma a frame: under 1 sigma from frame to frame, but not near one place.
    creeping = (np.arange(m) >= m // 8) & (np.arange(m) < m // 4)
    for frame in range(4):     # frame 0 arrives 2 cm away; frames 1-3 stay (or drift on)
        jitter = np.zeros((m, 6))
        jitter[:, 3:] = rng.uniform(-0.1, 0.1, (m, 3)) * sigma
        walk = np.zeros((m, 6))
        walk[drifting, 5] = 2 * sigma * (frame + 1)
        walk[creeping, 5] = 0.6 * sigma * (frame + 1)
        current = field.with_transforms(se3_exp(jitter + walk) @ moved)
        state = state.settle(current, depth, params)
        if frame < 3:
            assert state.released[: m // 2].all()
    assert state.released[drifting | creeping].all()
    back = (np.arange(m) >= m // 4) & (np.arange(m) < m // 2)
    assert not state.released[back].any()
    np.testing.assert_allclose(state.rest[back], current.transforms[back])
    np.testing.assert_allclose(state.rest[m // 2:], field.transforms[m // 2:])


def test_released_nodes_back_within_their_release_distance_are_anchored_at_rest():
    """A false release (the node ends the frame within release_sigmas of rest) is undone at once,
    at rest; a node that ends it farther stays released, whatever it does after."""
    field = sheet_field()
    m = field.num_nodes
    params = AnchorParams()                       # release_sigmas 2
    depth = np.ones(m)
    sigma = axial_noise_sigma_m(1.0)
    state = NodeAnchors.at_rest(field).release(np.ones(m, bool))
    offset = np.zeros((m, 6))
    near = np.arange(m) < m // 2
    offset[near, 5] = 1.5 * sigma                 # inside the release distance
    offset[~near, 5] = 2.5 * sigma                # outside it
    current = field.with_transforms(se3_exp(offset) @ field.transforms)
    state = state.settle(current, depth, params)
    assert not state.released[near].any() and state.released[~near].all()
    np.testing.assert_allclose(state.rest, field.transforms)     # at rest, not where they are
    assert (state.stillness[near] > 0).all() and (state.stillness[~near] == 0).all()


def test_anchors_follow_extension_and_restart_on_a_new_field():
    field = sheet_field()
    m = field.num_nodes
    left = field.nodes[:, 0] < 0
    state = NodeAnchors.at_rest(field).release(left)
    assert state.follow(field) is state
    grown, first = extend(field, np.array([[-0.45, 0.0, 0.0], [0.45, 0.0, 0.0]], np.float32))
    assert grown.num_nodes == m + 2 and first == m
    followed = state.follow(grown)
    assert not followed.released[m:].any() and followed.released[:m].sum() == left.sum()
    np.testing.assert_allclose(followed.rest[m:], grown.transforms[m:])
    fresh = state.follow(sheet_field(seed=9))
    assert not fresh.released.any()


def test_factoring_against_rest_moves_the_camera_motion_into_the_pose():
    """Anchored nodes rest bent (their rest transforms) and all moved by A, the released ones
    moved anyhow: fitted from the rest positions of the anchored nodes the factor is A and they
    return to rest; fitted from the nodes themselves their rest bend would leak into it."""
    rng = np.random.default_rng(4)
    field = sheet_field(2000)
    m = field.num_nodes
    rest = apply_update(field, np.hstack([np.zeros((m, 3)), rng.normal(size=(m, 3)) * 0.01])).transforms
    released = field.nodes[:, 0] < -0.1
    A = se3_exp(np.array([0.02, -0.03, 0.01, 0.01, 0.004, -0.006]))
    G = A @ to_global(rest, field.nodes)
    G[released] = to_global(apply_update(field, rng.normal(size=(m, 6)) * 0.1).transforms, field.nodes)[released]
    moved = field.with_transforms(to_local(G, field.nodes))
    support = np.where(released, 0.0, rng.uniform(0.5, 2.0, m))
    factored, B = factor_rigid_motion(moved, support, field.nodes + rest[:, :3, 3])
    np.testing.assert_allclose(B, A, atol=1e-9)
    assert deviation_m(factored.transforms[~released], rest[~released], field.sigma_m).max() < 1e-6
    _, C = factor_rigid_motion(moved, support)
    assert np.abs(C - A).max() > 1e-3


def test_common_motion_is_the_still_parts_and_leaves_the_moving_part_out():
    """Known answer: nodes at rest moved by one rigid motion G, a twentieth of them also moved
    5 cm (a limb): common_motion returns G (the limb drags the first fit by ~2.5 mm, the refits
    on the nodes within the inlier distance drop it)."""
    from surfelwarp.tracking.anchors import common_motion, follow_motion
    rng = np.random.default_rng(5)
    m, sigma = 400, 0.025
    nodes = rng.uniform(-0.5, 0.5, (m, 3))
    rest = np.tile(np.eye(4), (m, 1, 1))
    rest[:, :3, 3] = rng.normal(0, 1e-3, (m, 3))
    G = se3_exp(np.array([0.02, -0.01, 0.03, 0.01, -0.02, 0.005]))
    moved = follow_motion(rest, nodes, G)
    limb = np.arange(m) < m // 20
    moved[limb, :3, 3] += [0.05, 0.0, 0.0]
    inlier = np.full(m, 0.004)
    found = common_motion(moved, rest, nodes, sigma, np.ones(m), inlier)
    np.testing.assert_allclose(found, G, atol=1e-9)
    one_round = common_motion(moved, rest, nodes, sigma, np.ones(m), inlier, rounds=1)
    assert np.abs(one_round[:3, 3] - G[:3, 3]).max() > 1e-3
    # the still nodes on G's rest, the limb's 5 cm off it (deviation_m, what the refits test)
    dev = deviation_m(moved, follow_motion(rest, nodes, G), sigma)
    assert dev[~limb].max() < 1e-9 and dev[limb].min() > 0.04
