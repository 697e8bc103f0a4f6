import time
from dataclasses import replace

import cv2
import numpy as np
import pytest

from surfelwarp.deform.warp_field import WarpField, WarpFieldParams, apply_update, skin, warp
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import invert, se3_exp
from surfelwarp.preprocess import normal_map, preprocess
from surfelwarp.tracking.association import associate
from surfelwarp.tracking.blend_jacobian import data_jacobian, data_residuals
from surfelwarp.tracking.free_space import SilhouetteParams
from surfelwarp.tracking.gauss_newton import NonRigidParams, free_nodes, normal_equations, solve_nonrigid
from surfelwarp.tracking.linear import _cholesky_inverses, restrict, solve_step
from surfelwarp.tracking.terms import robust as _robust
from surfelwarp.tracking.terms.regulariser import reg_jacobian, reg_residuals

from conftest import numba_threads, shared_data

INTR = Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240)
T_CW = se3_exp(np.array([0.03, -0.05, 0.02, 0.05, -0.03, 0.02]))   # a camera not at the world origin


def reference_surface(s, t):
    """A bumpy sheet about 1 m in front of the camera (world frame); the bumps pin tangential sliding."""
    h = 0.015 * np.sin(2 * np.pi * s / 0.2) * np.cos(2 * np.pi * t / 0.25)
    return np.stack([s, t, 1.0 + h], -1)


def bend(p, radius=0.5, shift=(0.0, 0.005, -0.01)):
    """Roll the sheet onto a cylinder of the given radius (axis along y, behind the sheet) and
    shift it: a smooth, locally almost rigid motion of up to 8 cm."""
    x, y, h = p[..., 0], p[..., 1], p[..., 2] - 1.0
    a = x / radius
    out = np.stack([(radius - h) * np.sin(a), y, 1.0 + radius - (radius - h) * np.cos(a)], -1)
    return out + np.asarray(shift)


def render(surface, intr=INTR, T_camera_to_world=T_CW):
    """Depth image of a densely sampled surface grid (A, B, 3), world frame: each pixel takes the
    sample projecting nearest its centre and cuts its ray with that sample's tangent plane."""
    T = invert(T_camera_to_world)
    q = surface @ T[:3, :3].T + T[:3, 3]
    n = np.cross(np.gradient(q, axis=1), np.gradient(q, axis=0)).reshape(-1, 3)
    q = q.reshape(-1, 3)
    u = intr.fx * q[:, 0] / q[:, 2] + intr.cx
    v = intr.fy * q[:, 1] / q[:, 2] + intr.cy
    ui, vi = np.rint(u).astype(int), np.rint(v).astype(int)
    ok = (ui >= 0) & (ui < intr.width) & (vi >= 0) & (vi < intr.height)
    pix = (vi * intr.width + ui)[ok]
    order = np.lexsort((((u - ui) ** 2 + (v - vi) ** 2)[ok], pix))
    first = np.ones(len(order), bool)
    first[1:] = pix[order[1:]] != pix[order[:-1]]
    idx, pix = np.flatnonzero(ok)[order[first]], pix[order[first]]
    ray = np.stack([(pix % intr.width - intr.cx) / intr.fx, (pix // intr.width - intr.cy) / intr.fy,
                    np.ones(len(pix))], -1)
    depth = np.zeros(intr.height * intr.width, np.float32)
    depth[pix] = np.sum(n[idx] * q[idx], 1) / np.sum(n[idx] * ray, 1)
    return depth.reshape(intr.height, intr.width)


def depth_maps(depth, intr=INTR):
    """Camera-frame vertex map, central-difference normals and validity."""
    vertex = intr.backproject(depth)
    normals, valid = normal_map(vertex, depth)
    return vertex, normals, valid


class Problem:
    """Reference surfels seen by the camera, the depth maps of the bent surface, the truth."""

    def __init__(self, moved=bend, node_radius_m=0.025):
        s, t = np.meshgrid(np.arange(-0.3, 0.3, 0.001), np.arange(-0.22, 0.22, 0.001))
        grid = reference_surface(s, t)
        v0, n0, ok0 = depth_maps(render(grid))
        R, tr = T_CW[:3, :3], T_CW[:3, 3]
        self.points = (v0[ok0] @ R.T + tr).astype(np.float32)
        self.normals = (n0[ok0] @ R.T).astype(np.float32)
        self.maps = depth_maps(render(moved(grid)))
        self.truth = moved(self.points.astype(np.float64))
        self.field = WarpField.from_points(self.points, WarpFieldParams(node_radius_m=node_radius_m))
        self.knn, self.weights = skin(self.points, self.field.nodes, 4, self.field.sigma_m)

    def solve(self, params=NonRigidParams(), field=None):
        return solve_nonrigid(self.field if field is None else field, self.points, self.normals, self.knn,
                              self.weights, *self.maps, INTR, T_CW, params)

    def error(self, field):
        live, _ = warp(self.points.astype(np.float64), None, self.knn, self.weights, field)
        return np.linalg.norm(live - self.truth, axis=1)


@pytest.fixture(scope="module")
def problem():
    return Problem()


def random_field(problem, scale=1.0, seed=0):
    """The problem's field with random node motions (rotations ~0.3 rad)."""
    rng = np.random.default_rng(seed)
    xi = rng.normal(size=(problem.field.num_nodes, 6)) * np.array([0.3, 0.3, 0.3, 0.02, 0.02, 0.02]) * scale
    return apply_update(problem.field, xi)


def scatter(J_slots, knn, m):
    """(C, k, 6) per-slot Jacobians -> dense (C, m, 6)."""
    out = np.zeros((len(knn), m, 6))
    for s in range(knn.shape[1]):
        np.add.at(out, (np.arange(len(knn)), knn[:, s]), J_slots[:, s])
    return out


def test_data_jacobian_matches_finite_differences_of_the_true_warp(problem):
    rng = np.random.default_rng(1)
    field = random_field(problem)
    sel = rng.choice(len(problem.points), 25, replace=False)
    p, knn, w = problem.points[sel].astype(np.float64), problem.knn[sel], problem.weights[sel].astype(np.float64)
    n = rng.normal(size=(25, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = p + rng.normal(scale=0.01, size=p.shape)
    nodes = np.unique(knn)
    analytic = scatter(data_jacobian(field, p, knn, w, n), knn, field.num_nodes)[:, nodes]
    numeric = np.zeros_like(analytic)
    h = 1e-6
    for a, j in enumerate(nodes):
        for m in range(6):
            xi = np.zeros((field.num_nodes, 6))
            xi[j, m] = h
            numeric[:, a, m] = (data_residuals(apply_update(field, xi), p, knn, w, d, n)
                                - data_residuals(apply_update(field, -xi), p, knn, w, d, n)) / (2 * h)
    rel = np.linalg.norm(analytic - numeric) / np.linalg.norm(numeric)
    print(f"data Jacobian vs central differences ({len(nodes)} nodes): relative error {rel:.1e}")
    assert rel < 1e-6
    assert np.abs(analytic - numeric).max() < 1e-6 * np.abs(numeric).max()


def test_twist_dual_quaternions_compiled_equal_numpy_to_the_bit(problem):
    from surfelwarp.tracking.blend_jacobian import twist_dual_quaternions, twist_dual_quaternions_reference
    for seed in range(3):
        field = random_field(problem, seed=seed)
        q = field.dual_quaternions().copy()
        q[0] = [np.inf, 0, 0, 0, 0, 0, 0, 0]       # a run-away node: the zeros' products are NaN
        q[1] = -q[1]                               # either sign of a node's quaternion
        D, ref = twist_dual_quaternions(field, q), twist_dual_quaternions_reference(field, q)
        assert D.shape == (field.num_nodes, 6, 8)
        assert np.array_equal(D.view(np.uint64), ref.view(np.uint64))
    # Known answer: at the identity, turning about x at node p moves the real part by (0, 1/2, 0, 0)
    # and the dual part by p x e_x / 2; a shift along y is (0, 0, 1/2, 0) in the dual part.
    p = problem.field.nodes[3].astype(np.float64)
    D = twist_dual_quaternions(problem.field)[3]
    np.testing.assert_array_equal(D[0], [0, 0.5, 0, 0, 0, 0, 0.5 * p[2], -0.5 * p[1]])
    np.testing.assert_array_equal(D[4], [0, 0, 0, 0, 0, 0, 0.5, 0])
    # A shift moves only the dual part: the blocks' products skip these zeros (sandwich).
    assert np.all(twist_dual_quaternions(random_field(problem, seed=4))[:, 3:, :4] == 0)


def test_sandwich_has_the_full_products_bits(problem):
    """The blocks D_lo A D_hi^T as the plain triple loop over every product gives them, to the
    bit: the products the kernel skips (D's zeros) add nothing."""
    from surfelwarp.tracking.assembly import _SYM8
    from surfelwarp.tracking.assembly_kernels import sandwich
    from surfelwarp.tracking.blend_jacobian import twist_dual_quaternions
    rng = np.random.default_rng(3)
    D = twist_dual_quaternions(random_field(problem, seed=5))
    lo = rng.integers(0, len(D), 40)
    hi = rng.integers(0, len(D), 40)
    A = rng.normal(size=(40, 36))
    sym = _SYM8.reshape(8, 8)
    out = np.empty((40, 6, 6))
    sandwich(D, lo, hi, A, sym, out, 7)
    for n in range(40):
        F = A[n][sym]
        DA = [[sum((D[lo[n], i, m] * F[m, j] for m in range(8)), 0.0) for j in range(8)] for i in range(6)]
        ref = [[sum((DA[i][m] * D[hi[n], j, m] for m in range(8)), 0.0) for j in range(6)] for i in range(6)]
        assert np.array_equal(out[n], np.array(ref))


def test_reg_jacobian_matches_finite_differences(problem):
    field = random_field(problem, seed=2)
    m = field.num_nodes
    Ji, Jj = reg_jacobian(field)
    graph = field.graph
    nodes = np.arange(0, m, 7)                       # a spread subset keeps the test fast
    rel_errors = []
    h = 1e-6
    for j in nodes:
        for c in range(6):
            xi = np.zeros((m, 6))
            xi[j, c] = h
            numeric = (reg_residuals(apply_update(field, xi)) - reg_residuals(apply_update(field, -xi))) / (2 * h)
            analytic = np.zeros_like(numeric)
            analytic += np.where((graph == j)[..., None], Ji[..., c], 0.0)
            analytic[j] += Jj[j, :, :, c]
            rel_errors.append(np.abs(analytic - numeric).max() / max(np.abs(numeric).max(), 1e-12))
    print(f"regulariser Jacobian vs central differences: max relative error {max(rel_errors):.1e}")
    assert max(rel_errors) < 1e-6


def test_normal_equations_equal_the_dense_product(problem):
    rng = np.random.default_rng(3)
    patch = problem.points[np.all(np.abs(problem.points[:, :2] - [0.05, 0.0]) < 0.06, axis=1)]
    field = WarpField.from_points(patch)
    m = field.num_nodes
    field = apply_update(field, rng.normal(size=(m, 6)) * np.array([0.1, 0.1, 0.1, 0.01, 0.01, 0.01]))
    knn, w = skin(patch, field.nodes, 4, field.sigma_m)
    c = len(patch)
    n = rng.normal(size=(c, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    r, rw = rng.normal(size=c) * 0.01, rng.uniform(0.2, 1.0, c)
    J = data_jacobian(field, patch, knn, w, n)
    H, g = normal_equations(field, J, knn, r, rw, 5.0)
    Jd = scatter(J, knn, m).reshape(c, 6 * m)
    Ji, Jj = reg_jacobian(field)
    edges = field.graph.size
    Jr = np.zeros((edges, 3, m, 6))
    jj = np.repeat(np.arange(m), field.graph.shape[1])
    Jr[np.arange(edges), :, field.graph.reshape(-1)] += Ji.reshape(edges, 3, 6)
    Jr[np.arange(edges), :, jj] += Jj.reshape(edges, 3, 6)
    Jr = Jr.reshape(3 * edges, 6 * m)
    H_dense = Jd.T @ (rw[:, None] * Jd) + 5.0 * Jr.T @ Jr
    g_dense = Jd.T @ (rw * r) + 5.0 * Jr.T @ reg_residuals(field).reshape(-1)
    assert m > 10 and H.shape == (6 * m, 6 * m)
    assert np.allclose(H.toarray(), H_dense, atol=1e-9 * np.abs(H_dense).max())
    assert np.allclose(g, g_dense, atol=1e-9 * np.abs(g_dense).max())


@pytest.mark.parametrize("kind", ["none", "huber", "tukey"])
def test_robust_weights_are_the_derivative_of_the_cost(kind):
    r = np.linspace(-0.03, 0.03, 601)
    r = r[np.abs(np.abs(r) - 0.01) > 1e-4]          # away from the kinks
    cost, weight = _robust(r, kind, 0.01)
    h = 1e-7
    slope = (_robust(r + h, kind, 0.01)[0] - _robust(r - h, kind, 0.01)[0]) / (2 * h)
    assert np.allclose(weight * 2 * r, slope, atol=1e-6)
    small = np.abs(r) < 0.002
    assert np.allclose(cost[small], r[small] ** 2, rtol=0.05)
    if kind == "tukey":
        assert np.all(weight[np.abs(r) > 0.01] == 0)


def test_recovers_a_bend(problem):
    before = problem.error(problem.field)
    t0 = time.perf_counter()
    field, res = problem.solve()
    elapsed = time.perf_counter() - t0
    after = problem.error(field)
    print(f"bend: {len(problem.points)} surfels, {problem.field.num_nodes} nodes; error mean {before.mean() * 1000:.1f}"
          f" -> {after.mean() * 1000:.2f} mm (max {before.max() * 1000:.1f} -> {after.max() * 1000:.2f} mm); "
          f"{res.iterations} iterations, {res.correspondences} pairs, rmse {res.data_rmse_m * 1000:.2f} mm, "
          f"energies {np.round(res.energies, 4)}, {elapsed:.2f} s")
    assert before.mean() > 0.02
    assert after.mean() < 0.003 and np.percentile(after, 99) < 0.005
    assert res.converged and res.iterations <= 10
    assert res.correspondences > 0.95 * len(problem.points)
    assert res.energy == pytest.approx(res.data_energy + 5.0 * res.reg_energy)
    assert res.energies[-1] == res.energy and res.energies[0] > 10 * res.energy
    assert res.data_rmse_m < 0.001


def test_the_solve_says_what_its_depth_pairs_measure_of_each_node(problem):
    """node_information: each node's skinning-weighted sum of its pairs' n n^T. Its trace sums
    to the pairs' weights (each pair's weights sum to 1); on the bumpy sheet (depth normals
    near the view axis) a node's pairs measure mostly one direction, near the sheet's normal."""
    _, result = problem.solve()
    S = result.node_information
    assert S.shape == (problem.field.num_nodes, 3, 3)
    np.testing.assert_allclose(np.trace(S, axis1=1, axis2=2).sum(), result.correspondences, rtol=1e-6)
    values, vectors = np.linalg.eigh(S[np.trace(S, axis1=1, axis2=2) > 0])
    assert np.median(values[:, 0] / values[:, 2]) < 0.02
    assert np.median(np.abs(vectors[:, :, 2] @ T_CW[:3, 2])) > 0.9


def test_tukey_still_recovers_the_bend(problem):
    """Residuals start far beyond the Tukey cut-off; the regulariser drags those parts along.
    Without the free-space term: with it, the sheet's edges, which the bend pulls in, are led
    by it alone while Tukey ignores their depth, and the solve stalls at 19.5 mm."""
    field, res = problem.solve(NonRigidParams(robust="tukey", robust_scale_m=0.01,
                                              silhouette=SilhouetteParams(weight=0.0)))
    after = problem.error(field)
    print(f"tukey: error mean {after.mean() * 1000:.2f} mm in {res.iterations} iterations")
    assert after.mean() < 0.003


def test_robust_penalty_resists_outliers():
    """A patch of the depth map pushed 2 cm forward: Tukey ignores it, plain least squares follows it."""
    prob = Problem(moved=lambda p: bend(p, radius=1e6))      # no motion apart from the shift
    vertex, normals, valid = prob.maps
    depth = vertex[..., 2].copy()
    depth[90:150, 130:190] -= 0.02 * (depth[90:150, 130:190] > 0)
    prob.maps = depth_maps(depth)
    uv = np.rint(INTR.project(prob.truth @ invert(T_CW)[:3, :3].T + invert(T_CW)[:3, 3])).astype(int)
    hit = (uv[:, 1] >= 90) & (uv[:, 1] < 150) & (uv[:, 0] >= 130) & (uv[:, 0] < 190)
    plain = prob.error(prob.solve(NonRigidParams(robust="none"))[0])
    tukey = prob.error(prob.solve(NonRigidParams(robust="tukey", robust_scale_m=0.01))[0])
    print(f"outlier patch: mean error of the points under it, plain {plain[hit].mean() * 1000:.1f} mm, "
          f"Tukey {tukey[hit].mean() * 1000:.1f} mm")
    assert plain[hit].mean() > 0.01
    assert tukey[hit].mean() < 0.003


def test_no_motion_gives_identity_in_one_iteration():
    prob = Problem(moved=lambda p: p)
    field, res = prob.solve()
    moved = np.abs(field.transforms - np.eye(4)).max()
    print(f"no motion: {res.iterations} iteration, largest transform change {moved:.1e}, energy {res.energy:.1e}")
    assert res.iterations == 1 and res.converged
    assert moved < 1e-6
    assert res.correspondences > 0.99 * len(prob.points)


def test_association_gates_pairs(problem):
    live, live_n = warp(problem.points, problem.normals, problem.knn, problem.weights, problem.field)
    vertex, normals, valid = problem.maps
    # Identity: the reference surfels are the depth vertices of the rendered reference.
    same = depth_maps(render(reference_surface(*np.meshgrid(np.arange(-0.3, 0.3, 0.001),
                                                             np.arange(-0.22, 0.22, 0.001)))))
    corr = associate(live, live_n, *same, INTR, T_CW)
    assert len(corr.index) == len(problem.points)
    assert np.abs(np.einsum("ij,ij->i", corr.normals, live[corr.index] - corr.points)).max() < 1e-5
    tight = associate(live, live_n, vertex, normals, valid, INTR, T_CW, distance_gate_m=0.01)
    loose = associate(live, live_n, vertex, normals, valid, INTR, T_CW, distance_gate_m=0.1)
    gap = np.linalg.norm(live[tight.index] - tight.points, axis=1)
    assert gap.max() < 0.01 and len(tight.index) < 0.9 * len(loose.index)
    upright = associate(live, live_n, vertex, normals, valid, INTR, T_CW, min_normal_cos=0.99)
    assert np.all(np.einsum("ij,ij->i", live_n[upright.index], upright.normals) > 0.99)


def test_compiled_association_equals_the_numpy_reference(problem):
    """Live surfels jittered about both gates (2 cm, cos 0.7) and partly behind the camera or
    out of view: the compiled pass pairs exactly what associate_reference does, on one thread
    and on two."""
    from surfelwarp.tracking.association import DepthTargets, associate_components, associate_reference
    rng = np.random.default_rng(8)
    live, live_n = warp(problem.points, problem.normals, problem.knn, problem.weights, problem.field)
    live = live + rng.normal(0, 0.012, live.shape)
    live[:200, 2] = -live[:200, 2]
    live[200:400, 0] += 5.0
    live_n = live_n + rng.normal(0, 0.5, live_n.shape)
    live_n /= np.linalg.norm(live_n, axis=1, keepdims=True)
    targets = DepthTargets(*problem.maps, INTR, T_CW)
    args = (np.ascontiguousarray(live.T), np.ascontiguousarray(live_n.T), targets, 0.02, 0.7)
    got, ref = associate_components(*args), associate_reference(*args)
    assert 0.2 * len(live) < len(ref.index) < 0.8 * len(live)
    assert np.array_equal(got.index, ref.index)
    assert np.array_equal(got.points, ref.points) and np.array_equal(got.normals, ref.normals)
    # In the same layout too: numpy sums differently laid out arrays in another order.
    assert got.points.strides == ref.points.strides and got.normals.strides == ref.normals.strides
    # The surfels are picked on numba's threads: on one thread the same pairs.
    with numba_threads(1):
        one = associate_components(*args)
    assert np.array_equal(one.index, got.index) and np.array_equal(one.points, got.points)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_depth_targets_equal_the_numpy_reference(problem, dtype):
    """The depth pixels moved to world in one compiled pass: the same columns and the same bits
    as pack_reference's numpy passes, for maps of either precision and a turned, shifted camera."""
    from surfelwarp.tracking.association import DepthTargets, pack_reference
    vertex, normals, valid = (np.asarray(m, dtype) if m.dtype != bool else m for m in problem.maps)
    assert 0.1 * valid.size < valid.sum() < valid.size
    targets = DepthTargets(vertex, normals, valid, INTR, T_CW)
    column, packed = pack_reference(vertex, normals, valid, T_CW)
    assert np.array_equal(targets.column, column)
    assert np.array_equal(targets.packed, packed)
    assert np.array_equal(targets.vertex, packed[:, :3].T) and np.array_equal(targets.normal, packed[:, 3:].T)


def test_one_iteration_with_500_nodes_and_20k_pairs():
    """Printed, not asserted, time: speed goals live in bench_nonrigid (the machine may be shared)."""
    prob = Problem(node_radius_m=0.0195)
    field = random_field(prob, 0.1)
    idx = np.random.default_rng(4).choice(len(prob.points), 20000, replace=False)
    p, knn, w = prob.points[idx].astype(np.float64), prob.knn[idx], prob.weights[idx].astype(np.float64)
    d, n = prob.truth[idx], prob.normals[idx].astype(np.float64)
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        r = data_residuals(field, p, knn, w, d, n)
        J = data_jacobian(field, p, knn, w, n)
        H, g = normal_equations(field, J, knn, r, np.ones_like(r), 5.0)
        xi = solve_step(H, g, 1e-6)
        best = min(best, time.perf_counter() - t0)
    print(f"{field.num_nodes} nodes, {len(idx)} pairs: residual + Jacobian + J^T J + sparse solve {best * 1000:.0f} ms")
    assert 450 <= field.num_nodes <= 600
    assert np.all(np.isfinite(xi)) and np.abs(xi).max() > 0


def test_real_camera_motion_on_7scenes():
    """Frame 0 -> 10 of 7-Scenes (real Kinect depth; the scene is rigid, the camera moves ~1 cm):
    the field must take up the motion of the near surfaces (< 1.6 m) with the camera pose left
    at the identity."""
    root = shared_data("rigid-7scenes")
    intr = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)

    def observe(i):
        depth = cv2.imread(str(root / f"frame-{i:06d}.depth.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000
        return preprocess(np.where(depth < 65.0, depth, 0.0), intr, i, i)

    first, second = observe(0), observe(10)
    M = invert(np.loadtxt(root / "frame-000010.pose.txt")) @ np.loadtxt(root / "frame-000000.pose.txt")
    sel = first.valid & (first.depth_m < 1.6)
    sel[::2] = False
    sel[:, ::2] = False
    pts, nrm = first.vertex_map[sel], first.normal_map[sel]
    field = WarpField.from_points(pts)
    knn, w = skin(pts, field.nodes, 4, field.sigma_m)
    args = (pts, nrm, knn, w, second.vertex_map, second.normal_map, second.valid, intr, np.eye(4))
    _, start = solve_nonrigid(field, *args, NonRigidParams(max_iterations=0))
    solved, res = solve_nonrigid(field, *args)
    truth = pts @ M[:3, :3].T + M[:3, 3]
    true_n = nrm @ M[:3, :3].T
    live, _ = warp(pts.astype(np.float64), None, knn, w, solved)
    err, err0 = live - truth, pts - truth
    along = np.abs(np.einsum("ij,ij->i", err, true_n)).mean()
    along0 = np.abs(np.einsum("ij,ij->i", err0, true_n)).mean()
    e, e0 = np.linalg.norm(err, axis=1).mean(), np.linalg.norm(err0, axis=1).mean()
    print(f"7-Scenes 0->10: {len(pts)} surfels, {field.num_nodes} nodes; rmse {start.data_rmse_m * 1000:.2f} -> "
          f"{res.data_rmse_m * 1000:.2f} mm in {res.iterations} iterations; error to ground truth {e0 * 1000:.1f} -> "
          f"{e * 1000:.1f} mm, along the normal {along0 * 1000:.2f} -> {along * 1000:.2f} mm")
    assert res.data_rmse_m < 0.002 and res.data_rmse_m < 0.5 * start.data_rmse_m
    assert along < 0.002 and along < 0.5 * along0
    # Sliding along the (mostly flat) near surfaces is unobservable from depth: only require progress.
    assert e < 0.7 * e0


def test_rejects_unknown_robust_penalty(problem):
    with pytest.raises(ValueError):
        problem.solve(NonRigidParams(robust="cauchy"))


# ---------------------------------------------------------------- fast paths (block pattern, PCG)

def turned_field(problem, seed=5):
    """The problem's field with node rotations near +-170 degrees about one axis, so that the
    blend's antipodal fix flips the sign of many neighbours, plus small random motion."""
    rng = np.random.default_rng(seed)
    m = problem.field.num_nodes
    xi = rng.normal(size=(m, 6)) * np.array([0.05, 0.05, 0.05, 0.01, 0.01, 0.01])
    xi[:, 2] += np.where(rng.random(m) < 0.5, -1, 1) * np.radians(170)
    return apply_update(problem.field, xi)


def test_indexed_blend_equals_dq_blend_with_sign_flips(problem):
    from surfelwarp.geometry.dual_quaternion import dq_blend, dq_blend_indexed
    for field in (random_field(problem), turned_field(problem)):
        q = field.dual_quaternions()
        ref = dq_blend(q[problem.knn], problem.weights, normalize=False)
        blended, signed = dq_blend_indexed(q, problem.knn, problem.weights)
        assert np.abs(blended - ref).max() < 1e-12
        assert np.allclose(np.abs(signed), problem.weights)
    assert np.mean(signed < 0) > 0.05                   # the flips were exercised


def test_block_pattern_is_the_sparsity_of_the_normal_equations(problem):
    """The compiled pattern equals the upper triangle of K^T K + E + E^T + I (surfel-shared node
    pairs, graph edges, diagonal), and each surfel's slots name the blocks of its node pairs."""
    import scipy.sparse as sp
    from surfelwarp.tracking.assembly import BlockPattern
    rng = np.random.default_rng(3)
    field = problem.field
    m = field.num_nodes
    sel = rng.choice(len(problem.knn), 500, replace=False)
    knn = problem.knn[sel].astype(np.int64)
    knn[:7, 1] = knn[:7, 0]                               # repeated nodes in a surfel
    pattern = BlockPattern(m, field.graph, knn)
    n, k = knn.shape
    K = sp.csr_matrix((np.ones(n * k), knn.reshape(-1), np.arange(n + 1) * k), shape=(n, m))
    j = np.repeat(np.arange(m), field.graph.shape[1])
    E = sp.csr_matrix((np.ones(j.size), (j, field.graph.reshape(-1))), shape=(m, m))
    S = sp.triu(K.T @ K + E + E.T + sp.identity(m)).tocsr()
    S.sort_indices()
    rows = np.repeat(np.arange(m), np.diff(S.indptr))
    assert np.array_equal(pattern.lo, rows) and np.array_equal(pattern.hi, S.indices)
    a, b = knn[:, pattern.pair_s], knn[:, pattern.pair_t]
    assert np.array_equal(pattern.lo[pattern.slots], np.minimum(a, b))
    assert np.array_equal(pattern.hi[pattern.slots], np.maximum(a, b))
    assert np.array_equal(pattern.double, (a == b) & (pattern.pair_s < pattern.pair_t))   # a node twice
    assert pattern.double[:7].any()
    assert np.array_equal(pattern.keys(pattern.hi[:5], pattern.lo[:5] + m), -np.ones(5))   # absent pairs


def _sparse_as_dense(pattern, *args):
    """sparse_point_blocks' blocks put into the whole pattern's, through NormalEquations.add."""
    from surfelwarp.tracking.assembly import NormalEquations, sparse_point_blocks
    slots, blocks, g = sparse_point_blocks(pattern, *args)
    assert len(np.unique(slots)) == len(slots) < pattern.n_upper       # only the pairs touched
    system = NormalEquations(pattern, np.ones(pattern.num_nodes, bool), args[-3])
    system.add(g, upper=blocks, slots=slots)
    return system.upper, system.gradient


@pytest.mark.parametrize("assembly", ["point_blocks", "point_blocks_reference", "sparse", "split", "sparse split"])
def test_factored_normal_equations_equal_the_generic_ones(problem, assembly, monkeypatch):
    from surfelwarp.geometry.dual_quaternion import _components, dq_blend_indexed
    from surfelwarp.tracking import assembly as assembly_module
    from surfelwarp.tracking.assembly import BlockPattern
    # compiled, its numpy reference, the compiled one on the touched pairs alone, and both with
    # the pairs summed in three parts (as large calls are, in TASKS parts) and the blocks formed
    # in tasks of 7
    if "split" in assembly:
        monkeypatch.setattr(assembly_module, "CHUNK", 64)
        monkeypatch.setattr(assembly_module, "TASKS", 3)
        monkeypatch.setattr(assembly_module, "BLOCKS_CHUNK", 7)
    name = assembly.replace("split", "point_blocks")
    point_blocks = _sparse_as_dense if "sparse" in assembly else getattr(assembly_module, name)
    from surfelwarp.tracking.blend_jacobian import twist_dual_quaternions
    from surfelwarp.tracking.terms.regulariser import regulariser_blocks
    rng = np.random.default_rng(6)
    field = turned_field(problem)
    knn, w = problem.knn.astype(np.int64), problem.weights.astype(np.float64)
    sel = np.sort(rng.choice(len(knn), 300 if "sparse" in assembly else 3000, replace=False))
    n = rng.normal(size=(len(sel), 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    r, rw = rng.normal(size=len(sel)) * 0.01, rng.uniform(0.2, 1.0, len(sel))
    p = problem.points.astype(np.float64)
    pattern = BlockPattern(field.num_nodes, field.graph, knn)
    dq = field.dual_quaternions()
    b, signed = dq_blend_indexed(dq, knn, w)
    bd, gd = point_blocks(pattern, sel, b, signed, _components(p), n, twist_dual_quaternions(field, dq), r, rw)
    br, gr = regulariser_blocks(field, pattern)
    upper, g = bd + 5.0 * br, gd + 5.0 * gr
    H, g, diag = pattern.matrix(upper), g.reshape(-1), upper[pattern.diag]
    J = data_jacobian(field, p[sel], knn[sel], w[sel], n)
    H_ref, g_ref = normal_equations(field, J, knn[sel], r, rw, 5.0)
    H, H_ref = H.toarray(), H_ref.toarray()
    assert np.allclose(H, H_ref, atol=1e-10 * np.abs(H_ref).max())
    assert np.allclose(g, g_ref, atol=1e-10 * np.abs(g_ref).max())
    m = field.num_nodes
    assert np.allclose(diag, H.reshape(m, 6, m, 6)[np.arange(m), :, np.arange(m)])


def test_sums_split_by_rows_have_one_threads_bits(problem, monkeypatch):
    """Calls below CHUNK split the rows of the sums between threads, each walking every
    correspondence: the blocks and gradient are one thread's to the bit (three rows a
    correspondence, as colour features have, and one)."""
    from surfelwarp.geometry.dual_quaternion import _components, dq_blend_indexed
    from surfelwarp.tracking import assembly as assembly_module
    from surfelwarp.tracking.assembly import BlockPattern
    from surfelwarp.tracking.blend_jacobian import twist_dual_quaternions
    rng = np.random.default_rng(11)
    field = turned_field(problem)
    knn, w = problem.knn.astype(np.int64), problem.weights.astype(np.float64)
    pattern = BlockPattern(field.num_nodes, field.graph, knn)
    dq = field.dual_quaternions()
    b, signed = dq_blend_indexed(dq, knn, w)
    D = twist_dual_quaternions(field, dq)
    for groups in (1, 3):
        sel = np.sort(rng.choice(len(knn), 2000, replace=False))
        n = rng.normal(size=(groups, len(sel), 3))
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        r, rw = rng.normal(size=(groups, len(sel))) * 0.01, rng.uniform(0.2, 1.0, len(sel))
        if groups == 1:
            n, r = n[0], r[0]
        args = (pattern, sel, b, signed, _components(problem.points.astype(np.float64)), n, D, r, rw)
        monkeypatch.undo()
        monkeypatch.setattr(assembly_module, "TASKS", 1)
        one = assembly_module.point_blocks(*args)
        monkeypatch.setattr(assembly_module, "TASKS", 3)
        monkeypatch.setattr(assembly_module, "MIN_SPLIT", 16)
        split = assembly_module.point_blocks(*args)
        assert one[0].tobytes() == split[0].tobytes() and one[1].tobytes() == split[1].tobytes()
        assert np.abs(one[0]).max() > 0
        # Parts summed apart (the large calls' split) round differently: the test can tell.
        monkeypatch.setattr(assembly_module, "CHUNK", 64)
        parts = assembly_module.point_blocks(*args)
        assert np.allclose(parts[0], one[0], rtol=0, atol=1e-12 * np.abs(one[0]).max())
        assert parts[0].tobytes() != one[0].tobytes()


@pytest.mark.parametrize("assembly", ["point_blocks", "sparse", "sparse split"])
def test_grouped_rows_equal_the_rows_one_by_one(problem, assembly, monkeypatch):
    """Three rows a correspondence (a colour feature's axes), summed into one product before its
    node pairs', give the numpy reference's blocks of the same rows as separate correspondences."""
    from surfelwarp.geometry.dual_quaternion import _components, dq_blend_indexed
    from surfelwarp.tracking import assembly as assembly_module
    from surfelwarp.tracking.assembly import BlockPattern, point_blocks_reference
    from surfelwarp.tracking.blend_jacobian import twist_dual_quaternions
    if "split" in assembly:
        monkeypatch.setattr(assembly_module, "CHUNK", 64)
        monkeypatch.setattr(assembly_module, "TASKS", 3)
    point_blocks = _sparse_as_dense if "sparse" in assembly else assembly_module.point_blocks
    rng = np.random.default_rng(8)
    field = turned_field(problem)
    knn, w = problem.knn.astype(np.int64), problem.weights.astype(np.float64)
    sel = np.sort(rng.choice(len(knn), 300, replace=False))
    n = rng.normal(size=(3, len(sel), 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    r, rw = rng.normal(size=(3, len(sel))) * 0.01, rng.uniform(0.2, 1.0, len(sel))
    pattern = BlockPattern(field.num_nodes, field.graph, knn)
    dq = field.dual_quaternions()
    b, signed = dq_blend_indexed(dq, knn, w)
    args = (b, signed, _components(problem.points.astype(np.float64)))
    D = twist_dual_quaternions(field, dq)
    blocks, g = point_blocks(pattern, sel, *args, n, D, r, rw)
    blocks_ref, g_ref = point_blocks_reference(pattern, np.tile(sel, 3), *args, n.reshape(-1, 3), D, r.reshape(-1),
                                               np.tile(rw, 3))
    assert np.abs(blocks_ref).max() > 0
    assert np.allclose(blocks, blocks_ref, rtol=0, atol=1e-12 * np.abs(blocks_ref).max())
    assert np.allclose(g, g_ref, rtol=0, atol=1e-12 * np.abs(g_ref).max())
    blocks, g = point_blocks(pattern, sel[:0], *args, n[:, :0], D, r[:, :0], rw[:0])     # no correspondence
    assert not np.any(blocks) and not np.any(g)


def test_pcg_step_agrees_with_the_direct_solve(problem):
    from surfelwarp.tracking.linear import solve_step_pcg
    rng = np.random.default_rng(7)
    field = random_field(problem, 0.1)
    idx = rng.choice(len(problem.points), 20000, replace=False)
    p, knn, w = problem.points[idx].astype(np.float64), problem.knn[idx], problem.weights[idx].astype(np.float64)
    d, n = problem.truth[idx], problem.normals[idx].astype(np.float64)
    r = data_residuals(field, p, knn, w, d, n)
    H, g = normal_equations(field, data_jacobian(field, p, knn, w, n), knn, r, np.ones_like(r), 5.0)
    exact = solve_step(H, g, 1e-6)
    A = H.toarray() + 1e-6 * np.mean(H.diagonal()) * np.eye(H.shape[0])
    for rtol in (1e-4, 1e-8):
        x, its, ok = solve_step_pcg(H, g, 1e-6, rtol=rtol, max_iterations=2000)
        residual = np.linalg.norm(A @ x + g) / np.linalg.norm(g)
        err = np.linalg.norm(x - exact) / np.linalg.norm(exact)
        print(f"PCG rtol {rtol:.0e}: {its} iterations, residual {residual:.1e}, step error vs LU {err:.1e}")
        assert ok and residual <= rtol * (1 + 1e-6)
        assert err < (1e-2 if rtol == 1e-4 else 1e-6)
    x, its, ok = solve_step_pcg(H, g, 1e-6, rtol=1e-8, max_iterations=3)
    assert not ok and its == 3
    x, its, ok = solve_step_pcg(H, np.zeros_like(g), 1e-6)
    assert ok and its == 0 and not np.any(x)


def test_pcg_solve_matches_the_direct_solve_and_falls_back(problem):
    """Whole solves: PCG (default), PCG that cannot converge (so every step falls back to sparse
    LU) and sparse LU end at the same field."""
    direct, res_d = problem.solve(NonRigidParams(linear_solver="direct"))
    pcg, res_p = problem.solve()
    fallback, res_f = problem.solve(NonRigidParams(pcg_max_iterations=1))
    for field, res in ((pcg, res_p), (fallback, res_f)):
        diff = problem.error(field) - problem.error(direct)
        print(f"vs direct: {res.iterations} vs {res_d.iterations} iterations, energy {res.energy:.6g} vs "
              f"{res_d.energy:.6g}, largest difference in point error {np.abs(diff).max() * 1e6:.2f} um")
        assert res.iterations == res_d.iterations and res.converged == res_d.converged
        assert res.energy == pytest.approx(res_d.energy, rel=1e-4)
        assert np.abs(diff).max() < 1e-5
    assert res_f.energies == pytest.approx(res_d.energies, rel=1e-9)


def test_the_block_jacobi_inverses_are_numpys():
    rng = np.random.default_rng(2)
    J = rng.normal(size=(50, 9, 6)) * np.geomspace(1e-3, 1e3, 6)      # badly scaled, as twists are
    blocks = np.einsum("nki,nkj->nij", J, J) + 1e-6 * np.eye(6)
    out = np.empty_like(blocks)
    assert _cholesky_inverses(blocks, out)
    np.testing.assert_allclose(out, np.linalg.inv(blocks), rtol=1e-7, atol=0)
    np.testing.assert_allclose(np.einsum("nij,njk->nik", out, blocks), np.broadcast_to(np.eye(6), blocks.shape),
                               atol=1e-7)
    # Two halves of the blocks on numba's threads: on one thread the same bits.
    alone = np.empty_like(blocks)
    with numba_threads(1):
        assert _cholesky_inverses(blocks, alone)
    assert np.array_equal(alone, out)
    for bad in (7, 40):         # not positive definite, in either half: numpy's inverse takes over
        broken = blocks.copy()
        broken[bad, 2, 2] = -1.0
        assert not _cholesky_inverses(broken, out)


def test_rejects_unknown_linear_solver(problem):
    with pytest.raises(ValueError):
        problem.solve(NonRigidParams(linear_solver="cholesky"))


def test_free_nodes_grow_by_graph_rings_in_both_directions():
    graph = np.minimum(np.arange(10) + 1, 9)[:, None]      # a chain: node j lists j + 1 only
    ring = lambda *seeds: np.flatnonzero(free_nodes(graph, np.isin(np.arange(10), seeds), 2)).tolist()
    assert ring(0) == [0, 1, 2]           # along the edges
    assert ring(9) == [7, 8, 9]           # against them
    assert ring(4, 5) == [2, 3, 4, 5, 6, 7]
    assert np.flatnonzero(free_nodes(graph, np.arange(10) == 3, 0)).tolist() == [3]


def test_restricted_system_is_the_kept_block(problem):
    rng = np.random.default_rng(3)
    field = random_field(problem, 0.1)
    idx = rng.choice(len(problem.points), 5000, replace=False)
    p, knn, w = problem.points[idx].astype(np.float64), problem.knn[idx], problem.weights[idx].astype(np.float64)
    n = problem.normals[idx].astype(np.float64)
    r = data_residuals(field, p, knn, w, problem.truth[idx], n)
    H, g = normal_equations(field, data_jacobian(field, p, knn, w, n), knn, r, np.ones_like(r), 5.0)
    m = field.num_nodes
    keep = rng.random(m) < 0.6
    dense = H.toarray()
    diag = np.stack([dense[6 * j:6 * j + 6, 6 * j:6 * j + 6] for j in range(m)])
    Hk, gk, dk = restrict(H, g, diag, keep)
    dofs = (6 * np.flatnonzero(keep)[:, None] + np.arange(6)).reshape(-1)
    np.testing.assert_array_equal(Hk.toarray(), dense[np.ix_(dofs, dofs)])
    np.testing.assert_array_equal(gk, g[dofs])
    np.testing.assert_array_equal(dk, diag[keep])


def test_nodes_far_from_the_view_stay_fixed(problem):
    """Only the left third of the surface is solved: with free_rings=1 the nodes more than one
    graph edge from its nodes keep their transforms, the left third still fits, and with every
    node free the far ones do move (pulled by the regulariser)."""
    left = np.flatnonzero(problem.points[:, 0] < problem.points[:, 0].min() + 0.2)
    def solve(rings):
        return solve_nonrigid(problem.field, problem.points[left], problem.normals[left], problem.knn[left],
                              problem.weights[left], *problem.maps, INTR, T_CW, NonRigidParams(free_rings=rings))
    in_view = np.zeros(problem.field.num_nodes, bool)
    in_view[problem.knn[left].reshape(-1)] = True
    far = ~free_nodes(problem.field.graph, in_view, 1)
    assert far.sum() > 0.3 * len(far)
    held, res = solve(1)
    assert res.converged
    np.testing.assert_array_equal(held.transforms[far], problem.field.transforms[far])
    assert not np.allclose(held.transforms[~far], problem.field.transforms[~far])
    assert problem.error(held)[left].mean() < 0.003
    loose, _ = solve(None)
    moved = np.linalg.norm(loose.transforms[far, :3, 3] - problem.field.transforms[far, :3, 3], axis=1)
    assert moved.max() > 1e-3


@pytest.mark.parametrize("held, bordered", [(False, False), (True, False), (True, True)])
def test_compiled_pcg_equals_the_direct_solve(problem, held, bordered):
    """The compiled PCG on the upper blocks (held nodes masked, the border as one more node)
    gives the sparse LU step of the restricted, bordered system; when it cannot converge, the
    step is LU's and says so."""
    from surfelwarp.tracking.assembly import Border, NormalEquations, BlockPattern
    from surfelwarp.tracking.linear import solve_system
    from surfelwarp.tracking.terms.regulariser import regulariser_blocks
    rng = np.random.default_rng(11)
    field = random_field(problem, 0.1)
    m = field.num_nodes
    pattern = BlockPattern(m, field.graph, problem.knn[:4000])
    upper, g = regulariser_blocks(field, pattern)
    J = rng.normal(size=(m, 6, 6)) * 0.3
    upper[pattern.diag] += J @ J.transpose(0, 2, 1) + 0.1 * np.eye(6)
    free = rng.random(m) > 0.2 if held else np.ones(m, bool)
    border = None
    if bordered:
        B = rng.normal(size=(m, 6, 6)) * 0.01
        border = Border(B, 50.0 * np.eye(6) + np.abs(B).sum() * 0.01 * np.eye(6), rng.normal(size=6))
    system = NormalEquations(pattern, free, np.zeros((m, 6, 8)), upper, g + rng.normal(size=(m, 6)), border)
    direct = solve_system(system, 1e-4, "direct")
    pcg = solve_system(system, 1e-4, "pcg", pcg_rtol=1e-10, pcg_max_iterations=5000)
    scale = np.abs(direct.xi).max()
    assert not pcg.lu_fallback and np.abs(pcg.xi - direct.xi).max() < 1e-6 * scale
    assert np.abs(pcg.zeta - direct.zeta).max() < 1e-6 * max(scale, 1e-12)
    assert not np.any(pcg.xi[~free])
    short = solve_system(system, 1e-4, "pcg", pcg_rtol=1e-10, pcg_max_iterations=2)
    assert short.lu_fallback and np.abs(short.xi - direct.xi).max() < 1e-9 * scale


def test_gradient_norm_counts_the_free_nodes_and_the_border():
    from surfelwarp.tracking.assembly import Border, BlockPattern, NormalEquations
    graph = np.array([[0, 1], [1, 0], [2, 1]])
    pattern = BlockPattern(3, graph, np.array([[0, 1], [1, 2]]))
    g = np.arange(18, dtype=np.float64).reshape(3, 6)
    free = np.array([True, False, True])
    system = NormalEquations(pattern, free, np.zeros((3, 6, 8)), None, g)
    assert system.gradient_norm() == pytest.approx(np.sqrt(np.sum(g[[0, 2]] ** 2)))
    system.border = Border(np.zeros((3, 6, 6)), np.eye(6), np.full(6, 2.0))
    assert system.gradient_norm() == pytest.approx(np.sqrt(np.sum(g[[0, 2]] ** 2) + 24.0))


def test_later_steps_are_solved_to_the_first_gradients_tolerance(problem, monkeypatch):
    """Inexact Gauss-Newton: the first step to pcg_rtol of its |g|, a later one to pcg_rtol of the
    first |g| but never looser than pcg_max_rtol of its own; the field ends where the solve with
    every step to pcg_rtol ends (pcg_max_rtol = pcg_rtol), to a fraction of the error."""
    import surfelwarp.tracking.gauss_newton as gn
    from surfelwarp.tracking.linear import solve_system
    calls = []

    def recording(system, damping, linear_solver, rtol, *args):
        calls.append((rtol, system.gradient_norm()))
        return solve_system(system, damping, linear_solver, rtol, *args)

    monkeypatch.setattr(gn, "solve_system", recording)
    field = random_field(problem, 0.05, seed=3)
    params = NonRigidParams(pcg_rtol=1e-4, pcg_max_rtol=1e-1, stop_energy_rel=1e-6)
    loose, res = problem.solve(params, field)
    steps = list(calls)
    calls.clear()
    tight, res_t = problem.solve(replace(params, pcg_max_rtol=1e-4), field)
    print(f"steps (rtol, |g|): {[(f'{r:.1e}', f'{n:.2e}') for r, n in steps]}; tight: {len(calls)} steps")
    first = steps[0][1]
    assert steps[0][0] == 1e-4 and len(steps) >= 3
    for rtol, norm in steps[1:]:
        assert rtol == pytest.approx(min(1e-1, max(1e-4, 1e-4 * first / norm)))
    assert any(rtol > 1e-3 for rtol, _ in steps[1:])
    assert all(rtol == 1e-4 for rtol, _ in calls)
    err_loose, err_tight = problem.error(loose), problem.error(tight)
    print(f"error mean {err_tight.mean() * 1e3:.3f} (tight) vs {err_loose.mean() * 1e3:.3f} mm (loose); energy "
          f"{res_t.energy:.6g} vs {res.energy:.6g}")
    assert res.converged and res_t.converged
    assert err_loose.mean() < 1.05 * err_tight.mean() + 1e-5
    assert res.energy == pytest.approx(res_t.energy, rel=1e-3)
