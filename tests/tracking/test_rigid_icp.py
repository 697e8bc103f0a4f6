import time

import numpy as np
import pytest

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import invert, se3_exp, so3_log
from surfelwarp.io.sequence import open_sequence
from surfelwarp.preprocess import PreprocessParams, preprocess
from surfelwarp.tracking.rigid_icp import PointPairs, RigidParams, _weighted_median, along_held, halved, rigid_icp

from conftest import shared_data

INTR = Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240)


def pose_error(T, T_true) -> tuple[float, float]:
    """Translation error in metres and rotation error in degrees."""
    E = invert(T_true) @ T
    return float(np.linalg.norm(E[:3, 3])), float(np.rad2deg(np.linalg.norm(so3_log(E[:3, :3]))))


def scene_depth(T_camera_to_world: np.ndarray, intr: Intrinsics = INTR) -> np.ndarray:
    """Ray-cast depth of a room corner (tilted back wall, floor, side wall) with two spheres
    and a box, all in world coordinates; rays have unit z in the camera so t is the depth."""
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    d = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], -1)
    d = d @ T_camera_to_world[:3, :3].T
    o = T_camera_to_world[:3, 3]
    hits = []
    for n, c in [((0.15, 0.0, 1.0), 2.4), ((0.0, 1.0, 0.1), 0.7), ((1.0, 0.0, 0.2), -0.9)]:
        n = np.asarray(n) / np.linalg.norm(n)
        dn = d @ n
        t = (c - o @ n) / np.where(np.abs(dn) > 1e-9, dn, 1e-9)
        hits.append(np.where(t > 0, t, np.inf))
    for centre, r in [((0.3, 0.1, 1.6), 0.25), ((-0.45, -0.25, 1.9), 0.2)]:
        oc = o - np.asarray(centre)
        a, b, k = np.sum(d * d, -1), d @ oc, oc @ oc - r * r
        disc = b * b - a * k
        t = (-b - np.sqrt(np.maximum(disc, 0))) / a
        hits.append(np.where((disc > 0) & (t > 0), t, np.inf))
    lo, hi = np.array([0.05, -0.55, 1.3]), np.array([0.4, -0.2, 1.6])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    near = np.nanmax(np.minimum(t1, t2), -1)
    far = np.nanmin(np.maximum(t1, t2), -1)
    hits.append(np.where((near < far) & (near > 0), near, np.inf))
    depth = np.min(hits, axis=0)
    # Millimetre quantisation like a real sensor.
    return np.where(np.isfinite(depth), np.round(depth * 1000) / 1000, 0.0).astype(np.float32)


def world_maps(obs, T_camera_to_world):
    """An observation's vertex/normal maps moved to world, zero where invalid."""
    R, t = T_camera_to_world[:3, :3], T_camera_to_world[:3, 3]
    v = np.where(obs.valid[..., None], obs.vertex_map @ R.T + t, 0.0).astype(np.float32)
    n = np.where(obs.valid[..., None], obs.normal_map @ R.T, 0.0).astype(np.float32)
    return v, n


MOTION = se3_exp(np.concatenate([np.deg2rad(3.0) * np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5]),
                                 [0.02, -0.015, 0.016]]))


@pytest.fixture(scope="module")
def synthetic():
    first = preprocess(scene_depth(np.eye(4)), INTR, 0, 0)
    second = preprocess(scene_depth(MOTION), INTR, 1, 1)
    return first, second


def test_synthetic_motion_recovered(synthetic):
    first, second = synthetic
    assert np.linalg.norm(MOTION[:3, 3]) > 0.029 and pose_error(np.eye(4), MOTION)[1] > 2.9
    res = rigid_icp(first.vertex_map, first.normal_map, np.eye(4), second, np.eye(4))
    dt, dr = pose_error(res.T_camera_to_world, MOTION)
    print(f"synthetic: {dt * 1000:.3f} mm, {dr:.4f} deg, {res.iterations} iterations, rmse {res.rmse_m * 1000:.2f} mm")
    assert dt < 0.002 and dr < 0.1
    assert res.converged and res.inliers > 0.5 * second.num_valid
    assert res.rmse_m < 0.002 and res.energy == pytest.approx(res.rmse_m ** 2)


def test_world_frame_and_model_pose_are_respected(synthetic):
    # The same problem expressed in another world frame: model maps G v, model camera G,
    # start G; the answer must be G @ MOTION.
    first, second = synthetic
    G = se3_exp(np.array([0.3, -0.2, 0.5, 1.0, -2.0, 0.7]))
    v, n = world_maps(first, G)
    res = rigid_icp(v, n, G, second, G)
    dt, dr = pose_error(res.T_camera_to_world, G @ MOTION)
    assert dt < 0.002 and dr < 0.1


def test_no_overlap_returns_the_initial_guess(synthetic):
    first, second = synthetic
    T_init = se3_exp(np.array([0, 0, 0, 0.01, 0, 0]))
    empty = np.zeros_like(first.vertex_map)
    res = rigid_icp(empty, empty, np.eye(4), second, T_init)
    assert not res.converged and res.inliers == 0
    np.testing.assert_array_equal(res.T_camera_to_world, T_init)
    # A model seen from behind (every point behind the camera) also gives no pairs.
    flipped = se3_exp(np.array([0, np.pi, 0, 0, 0, 0]))
    res = rigid_icp(first.vertex_map, first.normal_map, flipped, second, np.eye(4))
    assert not res.converged and res.inliers < RigidParams().min_correspondences


def wall_depth(T_camera_to_world: np.ndarray) -> np.ndarray:
    """Depth of the plane z = 1.1 (world) filling the view."""
    u, v = np.meshgrid(np.arange(INTR.width), np.arange(INTR.height))
    d = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], -1) @ T_camera_to_world[:3, :3].T
    t = (1.1 - T_camera_to_world[2, 3]) / d[..., 2]
    return (np.round(t * 1000) / 1000).astype(np.float32)


WALL_SLIDE = se3_exp(np.array([0.0, 0.0, np.deg2rad(1.0), 0.02, -0.01, 0.0]))   # along the wall, about its normal


def wall_points(T_camera_to_world: np.ndarray, n=300, seed=0, noise_m=0.0):
    """Colour pairs on the wall: world points and where a camera at T_camera_to_world sees them."""
    rng = np.random.default_rng(seed)
    world = np.c_[rng.uniform(-0.4, 0.4, (n, 2)), np.full(n, 1.1)]
    camera = (world - T_camera_to_world[:3, 3]) @ T_camera_to_world[:3, :3]
    return world, camera + rng.normal(scale=noise_m, size=camera.shape)


def test_a_wall_alone_holds_the_pose_and_colour_pairs_move_it():
    """Depth of a flat wall fixes only the camera's distance and tilt: ICP holds the slide
    along it and the turn about its normal. Colour pairs on the wall give those back, and only
    those: pairs that disagree with the depth about the distance do not move it."""
    first = preprocess(wall_depth(np.eye(4)), INTR, 0, 0)
    second = preprocess(wall_depth(WALL_SLIDE), INTR, 1, 1)
    alone = rigid_icp(first.vertex_map, first.normal_map, np.eye(4), second, np.eye(4))
    assert alone.degenerate_directions == 3
    assert pose_error(alone.T_camera_to_world, np.eye(4))[0] < 1e-4       # held where it was
    world, camera = wall_points(WALL_SLIDE, noise_m=0.001)
    res = rigid_icp(first.vertex_map, first.normal_map, np.eye(4), second, np.eye(4),
                    pairs=PointPairs(camera, world, np.full(len(world), 10.0)))
    dt, dr = pose_error(res.T_camera_to_world, WALL_SLIDE)
    assert dt < 3e-4 and dr < 0.03, (dt, dr)
    assert res.degenerate_directions == 3 and res.inliers > 0.8 * alone.inliers and res.rmse_m < 0.001
    # The same pairs 5 cm farther away and tilted 3 degrees: depth still decides distance and tilt.
    tilt = se3_exp(np.array([np.deg2rad(3.0), 0.0, 0.0, 0.0, 0.0, 0.05]))
    res = rigid_icp(first.vertex_map, first.normal_map, np.eye(4), second, np.eye(4),
                    pairs=PointPairs(camera, world @ tilt[:3, :3].T + tilt[:3, 3], np.full(len(world), 10.0)))
    assert abs(res.T_camera_to_world[2, 3] - WALL_SLIDE[2, 3]) < 5e-4
    assert np.degrees(np.arccos(np.clip(res.T_camera_to_world[2, 2], -1, 1))) < 0.1
    # Without held directions the pairs change nothing.
    first, second = preprocess(scene_depth(np.eye(4)), INTR, 0, 0), preprocess(scene_depth(MOTION), INTR, 1, 1)
    world, camera = wall_points(np.eye(4))
    plain = rigid_icp(first.vertex_map, first.normal_map, np.eye(4), second, np.eye(4))
    paired = rigid_icp(first.vertex_map, first.normal_map, np.eye(4), second, np.eye(4),
                       pairs=PointPairs(camera, world, np.full(len(world), 10.0)))
    assert plain.degenerate_directions == 0
    np.testing.assert_array_equal(paired.T_camera_to_world, plain.T_camera_to_world)


def test_along_held_without_usable_pairs_keeps_the_pose():
    first = preprocess(wall_depth(np.eye(4)), INTR, 0, 0)
    second = preprocess(wall_depth(WALL_SLIDE), INTR, 1, 1)
    held = rigid_icp(first.vertex_map, first.normal_map, np.eye(4), second, np.eye(4)).held
    world, camera = wall_points(WALL_SLIDE)
    T = se3_exp(np.array([0.0, 0.0, 0.01, 0.001, 0.0, 0.0]))
    for pairs in (PointPairs(camera, world, np.zeros(len(world))), PointPairs(camera[:2], world[:2], np.ones(2))):
        np.testing.assert_array_equal(along_held(T, held, pairs), T)


def test_halved_intrinsics_match_subsampled_pixels():
    points = np.array([[0.3, -0.2, 1.5], [-0.7, 0.4, 2.0]])
    fine, coarse = INTR.project(points), halved(INTR).project(points)
    np.testing.assert_allclose(coarse * 2, fine)
    assert (halved(INTR).width, halved(INTR).height) == (160, 120)


@pytest.fixture(scope="module")
def office():
    seq = open_sequence(shared_data("rigid-7scenes"), max_frames=31)
    params = PreprocessParams(clip_far_m=4.0)
    wanted = set(range(0, 31, 3)) | {10}
    obs, poses = {}, {}
    for frame in seq.files:
        if frame.index in wanted:
            obs[frame.index] = preprocess(seq.read_depth(frame), seq.intrinsics, frame.index, frame.index, params)
            poses[frame.index] = seq.read_pose(frame)
    return obs, poses


def test_7scenes_pair_against_ground_truth(office):
    obs, poses = office
    truth = invert(poses[0]) @ poses[10]
    before = pose_error(np.eye(4), truth)
    times = []
    for _ in range(3):
        start = time.perf_counter()
        res = rigid_icp(obs[0].vertex_map, obs[0].normal_map, np.eye(4), obs[10], np.eye(4))
        times.append(time.perf_counter() - start)
    dt, dr = pose_error(res.T_camera_to_world, truth)
    print(f"7scenes 0->10: motion {before[0] * 100:.2f} cm {before[1]:.2f} deg; error {dt * 1000:.2f} mm "
          f"{dr:.3f} deg; {res.iterations} iterations, rmse {res.rmse_m * 1000:.2f} mm, "
          f"{res.inliers} inliers, {min(times) * 1000:.0f} ms per call")
    assert dt < 0.015 and dr < 1.0
    assert dt < 0.7 * before[0] and dr < 0.5 * before[1]
    assert res.converged and res.rmse_m < 0.006
    # A larger motion (about 5 cm), aligned directly.
    truth = invert(poses[0]) @ poses[30]
    res = rigid_icp(obs[0].vertex_map, obs[0].normal_map, np.eye(4), obs[30], np.eye(4))
    dt, dr = pose_error(res.T_camera_to_world, truth)
    print(f"7scenes 0->30: motion {np.linalg.norm(truth[:3, 3]) * 100:.2f} cm; error {dt * 1000:.2f} mm {dr:.3f} deg")
    assert dt < 0.01 and dr < 0.5


def test_7scenes_frame_to_frame_chain_drift(office):
    obs, poses = office
    T, prev = np.eye(4), obs[0]
    for i in range(3, 31, 3):
        v, n = world_maps(prev, T)
        res = rigid_icp(v, n, T, obs[i], T)
        assert res.inliers > 100_000
        T, prev = res.T_camera_to_world, obs[i]
    truth = invert(poses[0]) @ poses[30]
    dt, dr = pose_error(T, truth)
    print(f"7scenes chain 0..30 step 3: motion {np.linalg.norm(truth[:3, 3]) * 100:.2f} cm, "
          f"drift {dt * 100:.2f} cm {dr:.3f} deg")
    assert dt < 0.03 and dr < 1.2


def _associate_numpy(level, T, T_world_to_model, min_normal_cos):
    """The projective pairing of rigid_icp._associate in whole-array numpy: its reference."""
    R, t = T[:3, :3].astype(np.float32), T[:3, 3:].astype(np.float32)
    p = R @ level.obs_vertex[level.obs_valid].T + t
    q = T_world_to_model[:3, :3].astype(np.float32) @ p + T_world_to_model[:3, 3:].astype(np.float32)
    intr = level.intrinsics
    front = q[2] > 1e-6
    inv_z = 1.0 / np.where(front, q[2], 1.0)
    u = np.rint(intr.fx * q[0] * inv_z + intr.cx).astype(np.int64)
    v = np.rint(intr.fy * q[1] * inv_z + intr.cy).astype(np.int64)
    inside = front & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
    pixel = np.where(inside, v * intr.width + u, 0)
    vm, nm = level.model_vertex.reshape(-1, 3)[pixel].T, level.model_normal.reshape(-1, 3)[pixel].T
    d = p - vm
    keep = (inside & (np.sum(nm * nm, 0) > 0.25) & (np.sum(d * d, 0) < level.gate_m ** 2)
            & (np.sum((R @ level.obs_normal[level.obs_valid].T) * nm, 0) > min_normal_cos))
    w = None if level.model_weight is None else level.model_weight.reshape(-1)[pixel][keep]
    return p[:, keep], nm[:, keep], np.sum(nm * d, 0)[keep], w


def _pyramid_levels(synthetic):
    """Every level of the pyramid of the synthetic pair, without and with model weights, and a
    pose near the truth to pair them at."""
    from surfelwarp.tracking.rigid_icp import _levels
    first, second = synthetic
    mv, mn = world_maps(first, np.eye(4))
    weight = np.random.default_rng(2).random(first.valid.shape).astype(np.float32)
    T = se3_exp(np.array([0.01, -0.02, 0.005, 0.01, 0.0, -0.01])) @ MOTION
    return [level for w in (None, weight) for level in _levels(mv, mn, w, second, INTR, RigidParams())], T


def test_compiled_pairing_equals_the_numpy_reference(synthetic):
    from surfelwarp.tracking.rigid_icp import _associate
    levels, T = _pyramid_levels(synthetic)
    cos = RigidParams().min_normal_cos
    for level in levels:
        got, ref = _associate(level, T, np.eye(4), cos), _associate_numpy(level, T, np.eye(4), cos)
        assert len(got[2]) > 100 and len(got[2]) == len(ref[2])
        for a, b in zip(got, ref):
            assert (a is None) == (b is None)
            if a is not None:
                assert np.allclose(a, b, rtol=0, atol=2e-6)
        # Without the points (what the median residual reads): the same residuals and weights.
        p, n, r, w = _associate(level, T, np.eye(4), cos, points=False)
        assert p is None and n is None
        assert np.array_equal(r, got[2])
        assert (w is None) == (got[3] is None) and (w is None or np.array_equal(w, got[3]))


def test_pair_moments_equal_the_sums_of_the_written_pairs(synthetic):
    """The ICP's one-pass sums give the information and gradient of the pairs it writes out."""
    from surfelwarp.tracking.degeneracy import _information, information_from
    from surfelwarp.tracking.rigid_icp import _associate, _moments_of_pairs
    levels, T = _pyramid_levels(synthetic)
    cos = RigidParams().min_normal_cos
    for level in levels:
        p, n, r, w = _associate(level, T, np.eye(4), cos)
        moments, count, squares = _moments_of_pairs(level, T, np.eye(4), cos)
        assert count == len(r) > 100
        assert squares == pytest.approx(np.sum(r.astype(np.float64) ** 2), rel=1e-9)
        (info, g), (ref, ref_g) = information_from(moments), _information(p, n, w, r)
        assert np.allclose(info.frame.centre, ref.frame.centre, rtol=0, atol=1e-9)
        assert info.frame.length_m == pytest.approx(ref.frame.length_m, rel=1e-9)
        assert np.allclose(info.H, ref.H, rtol=1e-9, atol=1e-9 * np.abs(ref.H).max())
        assert np.allclose(g, ref_g, rtol=1e-7, atol=1e-9 * np.abs(ref_g).max())


def test_the_weighted_median_is_sortings():
    rng = np.random.default_rng(3)
    for a, w in [(rng.exponential(0.01, 300_000), rng.uniform(0, 1, 300_000)),
                 (np.round(rng.uniform(0, 0.02, 5000), 4), rng.uniform(0, 1, 5000)),     # ties
                 (np.r_[np.zeros(900), rng.uniform(0, 1, 100)], np.ones(1000)),        # one value holds the median
                 (np.full(7, 0.3), np.ones(7)), (np.array([0.2, 0.1]), np.array([0.0, 0.0]))]:
        order = np.argsort(a, kind="stable")
        cumulative = np.cumsum(w[order])
        expected = a[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])]
        assert _weighted_median(a, w) == expected
    assert _weighted_median(np.array([1.0, 2.0, 3.0]), np.array([1.0, 1.0, 5.0])) == 3.0
    assert _weighted_median(np.array([1.0, np.inf, 3.0, np.nan]), np.ones(4)) == 3.0
