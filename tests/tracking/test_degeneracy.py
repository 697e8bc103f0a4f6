"""Rigid motion only along the directions the data constrains (degeneracy.py), and rigid ICP
that holds a still camera in front of a wall while a part of the scene moves."""
import numpy as np
import pytest

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import se3_exp, se3_log
from surfelwarp.preprocess import preprocess
from surfelwarp.tracking.degeneracy import Parametrisation, RigidInformation, _information
from surfelwarp.tracking.rigid_icp import RigidParams, rigid_icp

INTR = Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240)


def plane_pairs(n=2000, seed=0):
    """Points on the plane z = 1 (normal +z), as components (3, n)."""
    rng = np.random.default_rng(seed)
    p = np.stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.4, 0.4, n), np.ones(n)])
    return p, np.tile([[0.0], [0.0], [1.0]], (1, n))


def test_plane_holds_its_in_plane_motions_and_solves_the_rest():
    p, n = plane_pairs()
    info = RigidInformation.of_pairs(p, n)
    held = info.held(1e-6)
    assert len(held) == 3
    # The held directions, as world twists, are the shifts along x, y and the turn about z
    # (about any point): none of them moves a point of the plane off it.
    for x in held.basis.T:
        xi = info.frame.to_world(x)
        moved = se3_exp(1e-3 * xi)
        assert np.abs((moved[:3, :3] @ p + moved[:3, 3:])[2] - 1.0).max() < 1e-9
    # The plane z = 1.003 + 0.01 x - 0.02 y: the step reaches it (to first order) by a shift along
    # the normal and two tilts, and moves nothing along the plane.
    target = 1.003 + 0.01 * p[0] - 0.02 * p[1]
    info, g = _information(p, n, None, p[2] - target)
    xi = info.solve(g, 1e-6)
    T = se3_exp(xi)
    after = T[:3, :3] @ p + T[:3, 3:]
    np.testing.assert_allclose(after[2], 1.003 + 0.01 * after[0] - 0.02 * after[1], atol=2e-5)
    c = p.mean(axis=1)
    np.testing.assert_allclose((T[:3, :3] @ c + T[:3, 3])[:2], c[:2], atol=5e-5)
    assert abs(xi[2]) < 1e-10                     # no turn about the normal


def test_three_planes_constrain_everything():
    rng = np.random.default_rng(1)
    parts = []
    for axis, normal in enumerate(np.eye(3)):
        p = rng.uniform(-0.5, 0.5, (3, 800))
        p[axis] = 1.5
        parts.append((p, np.tile(normal[:, None], (1, 800))))
    p = np.concatenate([a for a, _ in parts], 1)
    n = np.concatenate([b for _, b in parts], 1)
    info = RigidInformation.of_pairs(p, n)
    assert info.ratios()[0][0] > 0.02 and len(info.held(0.01)) == 0


def test_parametrisation_round_trip_and_projection():
    frame = Parametrisation(np.array([0.3, -0.2, 1.1]), 0.4)
    xi = np.array([0.01, 0.02, -0.03, 0.1, -0.2, 0.05])
    np.testing.assert_allclose(frame.to_world(frame.to_local(xi)), xi, atol=1e-15)
    # A twist about a point c is the world twist (omega, v - omega x c): M maps it like to_local.
    c = np.array([0.1, 0.5, 0.9])
    zeta = np.array([0.02, -0.01, 0.03, 0.005, 0.002, -0.004])
    world = np.concatenate([zeta[:3], zeta[3:] - np.cross(zeta[:3], c)])
    np.testing.assert_allclose(frame.from_twist_about(c) @ zeta, frame.to_local(world), atol=1e-15)


def test_held_directions_project_motions_and_constrain_twists():
    p, n = plane_pairs()
    held = RigidInformation.of_pairs(p, n).held(1e-6)
    T = se3_exp(np.array([0.003, -0.006, 0.01, 0.004, -0.005, 0.006]))
    kept = held.project(T)
    # What is left moves no point along the plane, and all of the plane's motion along its
    # normal stays (to second order in the turn that was removed).
    x = held.frame.to_local(se3_log(kept))
    assert np.abs(held.basis.T @ x).max() < 1e-12
    np.testing.assert_allclose((kept[:3, :3] @ p + kept[:3, 3:])[2], (T[:3, :3] @ p + T[:3, 3:])[2], atol=1e-4)
    c = np.array([0.2, 0.1, 0.8])
    zeta = np.array([0.0, 0.0, 0.01, 0.003, 0.0, 0.0])     # a turn about z and a shift along x: all held
    assert np.linalg.norm(held.rows(c) @ zeta) == pytest.approx(np.linalg.norm(held.frame.from_twist_about(c) @ zeta))
    assert np.abs(held.rows(c) @ np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.01])).max() < 1e-12


def depth_of(box_shift_x=0.0, camera_shift_x=0.0, wall=True, seed=0):
    """A wall at 1.2 m filling the view with a sphere (r 8 cm) at 1.0 m in front of it; or
    without the wall, three spheres alone. The camera and the sphere shift along x; depth
    noise of 1.5 mm, rounded to millimetres."""
    u, v = np.meshgrid(np.arange(INTR.width), np.arange(INTR.height))
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], -1)
    depth = np.full(u.shape, 1.2 if wall else np.inf)
    centres = [(0.0, 0.0, 1.0)] if wall else [(-0.2, 0.05, 1.0), (0.05, -0.1, 0.9), (0.2, 0.1, 1.05)]
    radius = 0.08 if wall else 0.12
    for c in centres:
        c = np.asarray(c) + [box_shift_x - camera_shift_x, 0.0, 0.0]
        a, b, k = np.sum(rays * rays, -1), rays @ c, c @ c - radius ** 2
        disc = b * b - a * k
        t = (b - np.sqrt(np.maximum(disc, 0))) / a
        depth = np.where(disc > 0, np.minimum(depth, t), depth)
    depth = np.where(np.isfinite(depth), depth + np.random.default_rng(seed).normal(0, 0.0015, u.shape), 0.0)
    return preprocess((np.round(depth * 1000) / 1000).astype(np.float32), INTR, 0, 0)


def align(model, obs, params=RigidParams()):
    v = np.where(model.valid[..., None], model.vertex_map, 0).astype(np.float32)
    n = np.where(model.valid[..., None], model.normal_map, 0).astype(np.float32)
    return rigid_icp(v, n, np.eye(4), obs, np.eye(4), params)


def test_icp_holds_a_still_camera_when_a_part_moves_along_the_wall():
    """Only the sphere constrains a shift along the wall; it moves 6 mm: a minority moving,
    the camera stays. Least squares everywhere (the papers' ICP) follows it part of the way."""
    res = align(depth_of(), depth_of(box_shift_x=0.006, seed=1))
    assert abs(res.T_camera_to_world[0, 3]) < 0.0003 and res.degenerate_directions >= 2
    free = align(depth_of(), depth_of(box_shift_x=0.006, seed=1), RigidParams(min_eigen_ratio=0.0, weak_eigen_ratio=0.0))
    assert free.T_camera_to_world[0, 3] < -0.001


def test_icp_follows_weak_directions_that_the_whole_view_moves_along():
    """Three spheres alone, the camera moves 6 mm: every pair agrees, so the camera follows
    although shifts and turns of spheres are weakly constrained."""
    model, obs = depth_of(wall=False), depth_of(camera_shift_x=0.006, wall=False, seed=1)
    res = align(model, obs)
    assert res.T_camera_to_world[0, 3] == pytest.approx(0.006, abs=0.0005)


def test_compiled_sums_equal_the_whole_array_products():
    """H and g summed pair by pair equal (J w) J^T and J (w r) of the explicit rows."""
    rng = np.random.default_rng(8)
    p, n = rng.normal(size=(3, 500)) + [[0.2], [0.1], [1.5]], rng.normal(size=(3, 500))
    w, r = rng.random(500), rng.normal(size=500) * 0.01
    info, g = _information(p, n, w, r)
    c = p @ w / w.sum()
    q = p - c[:, None]
    L = np.sqrt(np.einsum("ij,ij,j->", q, q, w) / w.sum())
    J = np.concatenate([np.cross(q.T, n.T).T / L, n])
    assert np.allclose(info.frame.centre, c) and info.frame.length_m == pytest.approx(L)
    assert np.allclose(info.H, (J * w) @ J.T, rtol=1e-12, atol=1e-12)
    assert np.allclose(g, J @ (w * r), rtol=1e-12, atol=1e-14)
