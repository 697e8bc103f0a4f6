"""Rest anchors (anchor.py): their Jacobian, release in the solve, settling, following the
field's nodes, and factoring the camera motion out of the anchored nodes."""
import numpy as np

from surfelwarp.anchor import AnchorParams, AnchorTerm, NodeAnchors, anchor_residuals, deviation_m
from surfelwarp.camera import axial_noise_sigma_m
from surfelwarp.nonrigid import anchor_energy, anchor_terms, apply_update
from surfelwarp.se3 import se3_exp
from surfelwarp.tracking import factor_rigid_motion
from surfelwarp.warp_field import WarpField, extend, to_global, to_local

from test_nonrigid import INTR, T_CW, Problem, bend, random_field, solve_nonrigid


def sheet_field(n=400, seed=0):
    rng = np.random.default_rng(seed)
    return WarpField.from_points(rng.uniform(-0.3, 0.3, (n, 3)) * [1, 1, 0.1])


def test_anchor_blocks_and_gradient_match_finite_differences():
    rng = np.random.default_rng(1)
    field = apply_update(sheet_field(), rng.normal(size=(len(sheet_field().nodes), 6)) * 0.05)
    m = field.num_nodes
    rest = apply_update(field, rng.normal(size=(m, 6)) * 0.02).transforms
    term = AnchorTerm(rng.uniform(0.5, 2.0, m), rest, np.full(m, np.inf))
    blocks, g = anchor_terms(field, term)
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


def half_bend(p):
    """The sheet's left half rolls away (up to ~9 cm), its right half stays where it was."""
    return np.where((p[..., 0] < 0)[..., None], bend(p, shift=(0.0, 0.0, 0.0)), p)


def test_the_solve_releases_moving_nodes_and_holds_the_still_ones():
    prob = Problem(moved=half_bend)
    m = prob.field.num_nodes
    release = 2 * axial_noise_sigma_m(1.0)
    anchor = AnchorTerm(np.ones(m), prob.field.transforms.copy(), np.full(m, release))
    field, res = solve_nonrigid(prob.field, prob.points, prob.normals, prob.knn, prob.weights, *prob.maps,
                                INTR, T_CW, anchor=anchor)
    nodes = prob.field.nodes.astype(np.float64)
    moves = np.linalg.norm(half_bend(nodes) - nodes, axis=1)
    err = prob.error(field)
    print(f"half bend: {res.released.sum()} of {m} nodes released; error mean {err.mean() * 1000:.2f} mm")
    assert res.released[moves > 0.01].all()
    still = nodes[:, 0] > 0.1
    assert not res.released[still].any()
    assert deviation_m(field.transforms[still], anchor.rest[still], field.sigma_m).max() < 1e-4
    assert err.mean() < 0.003
    # With everything anchored and nothing released the bend could not be followed.
    stiff = AnchorTerm(np.full(m, 1e3), anchor.rest, np.full(m, np.inf))
    held, _ = solve_nonrigid(prob.field, prob.points, prob.normals, prob.knn, prob.weights, *prob.maps,
                             INTR, T_CW, anchor=stiff)
    assert prob.error(held).mean() > 5 * err.mean()


def test_released_nodes_settle_after_staying_put():
    field = sheet_field()
    m = field.num_nodes
    params = AnchorParams(settle_sigmas=1.0, settle_frames=3)
    depth = np.ones(m)
    sigma = axial_noise_sigma_m(1.0)
    state = NodeAnchors.at_rest(field).release(np.arange(m) < m // 2)
    rng = np.random.default_rng(3)
    moved = se3_exp(np.tile([0, 0, 0, 0.02, 0, 0], (m, 1))) @ field.transforms
    drifting = np.arange(m) < m // 4            # keeps moving 2 sigma a frame
    for frame in range(4):     # frame 0 arrives 2 cm away; frames 1-3 stay (or drift on)
        jitter = np.zeros((m, 6))
        jitter[:, 3:] = rng.uniform(-0.2, 0.2, (m, 3)) * sigma
        walk = np.zeros((m, 6))
        walk[drifting, 5] = 2 * sigma * (frame + 1)
        current = field.with_transforms(se3_exp(jitter + walk) @ moved)
        state = state.settle(current, depth, params)
        if frame < 3:
            assert state.released[: m // 2].all()
    assert state.released[drifting].all()
    back = (np.arange(m) >= m // 4) & (np.arange(m) < m // 2)
    assert not state.released[back].any()
    np.testing.assert_allclose(state.rest[back], current.transforms[back])
    np.testing.assert_allclose(state.rest[m // 2:], field.transforms[m // 2:])


def test_anchors_follow_extension_and_restart_on_a_new_field():
    field = sheet_field()
    m = field.num_nodes
    left = field.nodes[:, 0] < 0
    state = NodeAnchors.at_rest(field).release(left)
    assert state.follow(field) is state
    grown, first = extend(field, np.array([[-0.45, 0.0, 0.0], [0.45, 0.0, 0.0]], np.float32))
    assert grown.num_nodes == m + 2 and first == m
    followed = state.follow(grown)
    assert followed.released.tolist()[m:] == [True, False]
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
