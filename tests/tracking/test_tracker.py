"""Template tracking (`--no-fusion`) end to end: synthetic scenes scored with `surfelwarp eval`;
and how the tracker moves the warp field's common motion into the pose and starts from far pairs.

Reduced size (320x240) and length keep this quick; the full-size figures are in the README.
"""
import json

import numpy as np
import pytest

from surfelwarp.cli import main
from surfelwarp.data_tools import evaluate, synth
from surfelwarp.deform.warp_field import WarpField, to_local
from surfelwarp.geometry.se3 import invert, se3_exp, transform_points
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.preprocess import preprocess
from surfelwarp.tracking.gauss_newton import NonRigidResult
from surfelwarp.tracking.features import AnchoredMatches
from surfelwarp.tracking.free_space import FreeSpace
from surfelwarp.tracking.anchors import AnchorParams
from surfelwarp.tracking.tracker import SurfelSet, Tracker, TrackingParams, factor_rigid_motion

from conftest import shared_data, sphere_depth_mm
from test_gauss_newton import INTR as SMALL, T_CW, Problem, reference_surface, render



def track(tmp_path, scene, frames, size=(320, 240), *flags, seq=None):
    seq = synth.generate(scene, tmp_path / scene, frames=frames, size=size) if seq is None else seq
    out = tmp_path / f"{scene}_run{'_'.join(flags)}"
    assert main(["run", str(seq), "--out", str(out), "--method", "surfelwarp", "--no-fusion",
                 "--no-progress", "--save-every", "5", *flags]) == 0
    return evaluate.evaluate(out, seq)


@pytest.mark.slow
def test_waving_sheet(tmp_path):
    # Full size: with a quarter of the pixels the fixed lambda = 5 weighs 4x more against the
    # data term, the field lags the folding and the sheet slides up to 15 mm (mean 6 mm).
    # Measured: mean 5.9 mm, at most 7.9 mm (the rest anchors hold each node until the data
    # moves it 2 sigma from rest; with them off, under 4 and 7 mm).
    res = track(tmp_path, "sheet", 20, size=(640, 480))
    avg = res["average"]
    assert avg["epe_mean_mm"] < 7.0 and max(r["epe_mean_mm"] for r in res["frames"][1:]) < 9.0
    assert avg["accuracy_median_mm"] < 1.5


@pytest.mark.slow
def test_fast_object(tmp_path):
    res = track(tmp_path, "fast", 20)      # up to ~4.5 cm and ~3 deg per frame
    assert res["average"]["epe_mean_mm"] < 8.0
    assert res["frames"][-1]["epe_under_2cm_pct"] > 95


@pytest.mark.slow
def test_static_camera_keeps_the_identity_and_the_field_takes_the_motion(tmp_path):
    """--camera static: every pose is the identity; the fast ball (4.5 cm a frame) is still
    tracked, rigid ICP's motion being the solve's second start."""
    res = track(tmp_path, "fast", 12, (320, 240), "--camera", "static")
    metrics = json.loads((tmp_path / "fast_run--camera_static" / "metrics.json").read_text())
    assert all(np.array_equal(f["camera_to_world"], np.eye(4)) for f in metrics["frames"])
    assert metrics["config"]["method"]["tracking"]["camera"] == "static"
    assert res["average"]["epe_mean_mm"] < 8.0


@pytest.mark.slow
def test_twisting_cylinder(tmp_path):
    res = track(tmp_path, "twist", 30)     # tangential motion
    assert res["average"]["epe_mean_mm"] < 5.0


@pytest.mark.slow
def test_camera_orbit_gives_the_trajectory(tmp_path):
    res = track(tmp_path, "orbit", 30)     # 1 deg per frame around a still life
    assert res["trajectory"]["frames"] == 30 and res["trajectory"]["ate_cm"] < 1.0
    assert res["average"]["epe_mean_mm"] < 5.0


@pytest.mark.slow
def test_deepdeform_shirt_large_motion(tmp_path):
    """Frames 0 -> 110: a motion of ~23 cm, a known hard case for projective trackers. With
    depth alone the template moves only part of the way (170 mm against 231 mm standing
    still); the colour's dense flow takes it most of the way (16.9 mm measured, median 11.0;
    Neural Non-Rigid Tracking reports 26 mm on the DeepDeform test pairs)."""
    data = shared_data("deepdeform-shirt-pair")
    out = tmp_path / "shirt"
    assert main(["run", str(data), "--out", str(out), "--method", "surfelwarp", "--no-fusion", "--no-progress"]) == 0
    row = evaluate.evaluate(out, data)["frames"][0]
    assert row["points"] > 30000
    assert row["epe_mean_mm"] < 30.0 and row["epe_median_mm"] < 20.0, row


def test_factoring_fits_the_common_motion_to_the_supported_nodes():
    """Half the nodes (the ones the depth sees) moved rigidly by A, the others did not: weighted by
    support the factored motion is A and the seen nodes end at rest; over every node alike it is
    a partial motion that leaves part of A in the seen nodes."""
    rng = np.random.default_rng(2)
    nodes = WarpField.from_points(rng.uniform(-0.5, 0.5, (5000, 3)) * [1, 1, 0.3]).nodes
    seen = nodes[:, 0] < 0
    A = se3_exp(np.array([0.02, -0.03, 0.01, 0.01, 0.004, -0.006]))
    G = np.tile(np.eye(4), (len(nodes), 1, 1))
    G[seen] = A
    field = WarpField.identity(nodes).with_transforms(to_local(G, nodes))
    support = np.where(seen, rng.uniform(0.5, 2.0, len(nodes)), 0.0)
    rest, B = factor_rigid_motion(field, support)
    np.testing.assert_allclose(B, A, atol=1e-9)
    np.testing.assert_allclose(rest.live_nodes()[seen], nodes[seen], atol=1e-6)
    partial, _ = factor_rigid_motion(field)
    left = np.linalg.norm(partial.live_nodes()[seen] - nodes[seen], axis=1)
    assert left.mean() > 3e-3


def test_factoring_by_information_leaves_a_slide_the_depth_cannot_see_in_the_field():
    """Nodes on a wall (z = 1 m) that depth sees along its normal, all moved by the camera's
    error A (a tilt and a step towards the wall) and slid 1 cm along the wall besides (the
    regulariser's or a colour pair's pull: depth does not see it). Fitted by information the
    pose takes A and the slide stays in the nodes; fitted by support it takes the slide too."""
    rng = np.random.default_rng(3)
    nodes = WarpField.from_points(np.column_stack([rng.uniform(-0.6, 0.6, (4000, 2)), np.ones(4000)])).nodes
    centre = np.eye(4)
    centre[2, 3] = 1.0          # the tilt about the wall's middle: the nodes do not slide by it
    A = centre @ se3_exp(np.array([0.01, -0.02, 0.0, 0.0, 0.0, 0.01])) @ invert(centre)
    slide = se3_exp(np.array([0.0, 0.0, 0.0, 0.01, 0.0, 0.0]))
    field = WarpField.identity(nodes).with_transforms(to_local(np.tile(A @ slide, (len(nodes), 1, 1)), nodes))
    support = rng.uniform(0.5, 2.0, len(nodes))
    wall = np.array([0.0, 0.0, 1.0])
    informed, B = factor_rigid_motion(field, support[:, None, None] * np.outer(wall, wall))
    # What the depth sees is in the pose: B moves each node as far along the normal as it moved.
    np.testing.assert_allclose((transform_points(B, nodes) - field.live_nodes()) @ wall, 0.0, atol=1e-6)
    left = informed.live_nodes() - nodes
    np.testing.assert_allclose(np.median(left[:, 0]), 0.01, atol=5e-4)   # the slide is not
    _, C = factor_rigid_motion(field, support)
    np.testing.assert_allclose(C, A @ slide, atol=1e-9)
    assert abs((B - C)[0, 3]) > 5e-3


def test_the_tracker_factors_by_what_the_solves_depth_pairs_measure():
    """Tracker.factor fits the pose's share to the solve's node information: the wall's nodes,
    slid along it, leave the camera where it was; only their step towards the wall moves it."""
    intr = Intrinsics(150.0, 150.0, 80.0, 60.0, 160, 120)
    tracker = Tracker(intr, TrackingParams(anchor=AnchorParams(weight=0.0)))
    empty = np.zeros((120, 160, 3), np.float32)
    tracker.rigid(empty, empty, preprocess(sphere_depth_mm(0, (160, 120), 150.0) / 1000.0, intr, 0, 0))
    rng = np.random.default_rng(8)
    nodes = WarpField.from_points(np.column_stack([rng.uniform(-0.6, 0.6, (3000, 2)), np.ones(3000)])).nodes
    moved = se3_exp(np.array([0.0, 0.0, 0.0, 0.01, -0.02, 0.005]))      # slid 2.2 cm, 5 mm nearer
    field = WarpField.identity(nodes).with_transforms(to_local(np.tile(moved, (len(nodes), 1, 1)), nodes))
    result = NonRigidResult(iterations=1, energy=0.0, reg_energy=0.0, correspondences=len(nodes), energies=(),
                            converged=True, node_information=np.tile(np.diag([0.0, 0.0, 1.0]), (len(nodes), 1, 1)))
    tracker.factor(field, result)
    np.testing.assert_allclose(tracker.T_camera_to_world[:3, 3], [0.0, 0.0, -0.005], atol=1e-6)
    np.testing.assert_allclose(tracker.T_camera_to_world[:3, :3], np.eye(3), atol=1e-6)


def test_rigid_icp_without_pairs_keeps_the_pose_and_says_so():
    """No model drawn (nothing to pair with): the pose stays, and the frame's counts say so."""
    intr = Intrinsics(150.0, 150.0, 80.0, 60.0, 160, 120)
    obs = preprocess(sphere_depth_mm(0, (160, 120), 150.0) / 1000.0, intr, 0, 0)
    tracker = Tracker(intr)
    T0 = se3_exp(np.array([0.1, 0.0, 0.05, 0.02, 0.0, -0.01]))
    tracker.T_camera_to_world = T0
    unsolved = NonRigidResult(iterations=0, energy=0.0, reg_energy=0.0, correspondences=0, energies=(),
                              converged=False)
    empty = np.zeros((120, 160, 3), np.float32)
    result = tracker.rigid(empty, empty, obs)
    assert np.array_equal(tracker.T_camera_to_world, T0)
    counts = tracker.counts(result, unsolved)
    assert counts.rigid_pose_kept and counts.lu_fallbacks == 0
    # The observation itself drawn as the model (in world, zero where invalid): pairs, a pose.
    valid = obs.valid[..., None]
    vertex = np.where(valid, obs.vertex_map @ T0[:3, :3].T + T0[:3, 3], 0).astype(np.float32)
    normal = np.where(valid, obs.normal_map @ T0[:3, :3].T, 0).astype(np.float32)
    assert obs.valid.sum() > 1000 and not tracker.counts(tracker.rigid(vertex, normal, obs), unsolved).rigid_pose_kept


@pytest.mark.parametrize("lead_motion_m", [0.015, 10.0])
def test_far_pairs_lead_the_solve(lead_motion_m):
    """Known answer: the bumpy sheet slid 10 cm along itself, 13 colour pairs on it. Past its
    3 cm gate the depth term's pairs hold the sheet on the wrong bumps; the pairs at their weight
    of 10 do not outweigh them, and the solve stays 6 cm off. A first solve led by the pairs
    (they lie 10 cm off, past lead_motion_m) starts it on the right ones; with lead_motion_m
    past them it does not fire."""
    slid = np.array([0.1, 0.0, 0.0])
    problem = Problem(moved=lambda p: p + slid)
    s, t = np.meshgrid(np.arange(-0.3, 0.3, 0.001), np.arange(-0.22, 0.22, 0.001))
    obs = preprocess(render(reference_surface(s, t) + slid), SMALL, 1, 1)
    index = np.arange(0, len(problem.points), 2011)
    matches = AnchoredMatches(index, problem.points[index].astype(np.float64),
                              transform_points(invert(T_CW), problem.truth[index]), np.ones(len(index)))
    tracker = Tracker(SMALL, TrackingParams(lead_motion_m=lead_motion_m))
    tracker.T_camera_to_world = T_CW.copy()
    field, _ = tracker.nonrigid(problem.field, SurfelSet(problem.points, problem.normals, problem.knn,
                                                         problem.weights), obs, matches)
    error = problem.error(field)
    print(f"lead_motion_m {lead_motion_m}: error mean {error.mean() * 1000:.2f} mm")
    if lead_motion_m < 0.1:
        assert error.mean() < 0.0005 and np.percentile(error, 99) < 0.001
    else:
        assert error.mean() > 0.03


def test_free_space_built_ahead_is_the_observations_own():
    """`ahead` builds an observation's free space before its frame; the frame gets the one of
    its own observation (of the last two seen), at its pose, as if built then."""
    intr = Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
    a, b, c = (preprocess(sphere_depth_mm(i, (160, 120), 150.0) / 1000.0, intr, i, i) for i in (0, 6, 12))
    tracker = Tracker(intr)
    T = se3_exp(np.array([0.02, -0.01, 0.03, 0.05, 0.0, -0.02]))
    for obs in (a, b, c):
        tracker.ahead(obs)
    assert tracker._spaces_ahead.observations() == [b, c]          # the last two only
    for obs in (b, c):
        got = tracker.free_space(obs, T)
        want = FreeSpace(obs.depth_m, intr, T, tracker.params.nonrigid.silhouette, obs.beyond)
        for name in ("depth", "empty", "judged", "_reach", "R_wc", "t_wc", "centre"):
            assert np.array_equal(getattr(got, name), getattr(want, name)), name
    assert not np.array_equal(tracker.free_space(b, T).depth, tracker.free_space(c, T).depth)
    rng = np.random.default_rng(0)
    camera = rng.uniform([-0.3, -0.2, 0.4], [0.3, 0.2, 2.0], (300, 3))     # in and behind the view's surfaces
    world = np.ascontiguousarray(transform_points(T, camera).T)
    got = tracker.free_space(c, T).residuals(world)[0]
    want = FreeSpace(c.depth_m, intr, T, tracker.params.nonrigid.silhouette, c.beyond).residuals(world)[0]
    assert np.array_equal(got, want) and (got > 0).sum() > 30


@pytest.mark.parametrize("k", [4, 3])
def test_the_stillness_map_is_the_stillness_of_the_shown_points(k):
    """The compiled map (four nodes a point) and numpy's (any other k) against point_stillness
    of the shown rows, bit for bit: empty pixels NaN, nodes born since the anchors still."""
    from surfelwarp.tracking.stillness import point_stillness, stillness_map
    rng = np.random.default_rng(4)
    n, m = 5000, 60
    knn = rng.integers(0, m + 5, (n, k)).astype(np.int32)          # 5 nodes born since
    weights = rng.random((n, k)).astype(np.float32)
    node = np.where(rng.random(m) < 0.3, 0.0, rng.random(m)).astype(np.float32)
    index = rng.integers(-1, n, (48, 64)).astype(np.int32)
    got = stillness_map(index, knn, weights, node)
    hit = index >= 0
    want = np.full(index.shape, np.nan, np.float32)
    want[hit] = point_stillness(knn[index[hit]], weights[index[hit]], node)
    assert np.isnan(got[~hit]).all() and np.array_equal(got[hit], want[hit])
    # known answer: a point on one still node (1) and three released (0), weights 0.1 .. 0.4
    one = stillness_map(np.zeros((1, 1), np.int32), np.array([[0, 1, 1, 1][:k]], np.int32),
                        np.array([[0.1, 0.2, 0.3, 0.4][:k]], np.float32), np.array([1, 0], np.float32))
    assert one[0, 0] == np.float32(0.1)


def test_the_rigid_weight_map_is_numpys_weighting_of_the_shown_pixels():
    """rigid_weight_map against numpy's float32 weighting, bit for bit, and nanmean's share;
    no weights where every shown pixel is still (or none is shown)."""
    from surfelwarp.tracking.stillness import rigid_weight, rigid_weight_map
    rng = np.random.default_rng(5)
    s = np.where(rng.random((48, 64)) < 0.4, np.nan, rng.random((48, 64))).astype(np.float32)
    floor = 0.05
    weight, share = rigid_weight_map(s, floor)
    want = np.where(np.isnan(s), 0.0, floor + (1.0 - floor) * s).astype(np.float32)
    assert weight.dtype == np.float32 and np.array_equal(weight, want)
    assert np.array_equal(weight[~np.isnan(s)], rigid_weight(s[~np.isnan(s)], floor))      # the colour pairs' weights
    assert share == pytest.approx(float(np.nanmean(s)), rel=1e-6)
    # known answer: one released pixel (0), one still (1), the rest empty
    two = np.full((2, 3), np.nan, np.float32)
    two[0, 0], two[1, 2] = 0.0, 1.0
    weight, share = rigid_weight_map(two, 0.25)
    assert share == 0.5 and weight[0, 0] == np.float32(0.25) and weight[1, 2] == 1.0 and weight.sum() == 1.25
    for still in (np.where(np.isnan(s), np.nan, 1.0), np.full((4, 4), np.nan)):
        assert rigid_weight_map(still.astype(np.float32), floor) == (None, 1.0)


def test_covered_share_is_the_weight_within_reach_of_the_pairs():
    from surfelwarp.tracking.stillness import COVER_CELL_PX, COVER_REACH_PX, covered_share
    weight = np.ones((480, 640), np.float32)
    y, x = np.mgrid[0:480:16, 0:320:16]
    left = np.stack([x.ravel(), y.ravel()], -1) + 0.5
    # pairs in the cells 0-38 of each row and those within 3 cells: 42 of 80; moved right by
    # 320 px, cells 40-78 and 37-79: 43
    assert COVER_CELL_PX == 8 and COVER_REACH_PX == 24
    assert covered_share(weight, left) == pytest.approx(42 / 80)
    assert covered_share(weight, left + [320.0, 0.0]) == pytest.approx(43 / 80)
    weight[:, 336:] = 0.0                  # only what is within reach of them weighs
    assert covered_share(weight, left) == pytest.approx(1.0)
    assert covered_share(weight, np.zeros((0, 2))) == 0.0 and covered_share(np.zeros((48, 64)), left) == 0.0
    assert covered_share(weight, np.array([[-50.0, 10.0], [900.0, 10.0]])) == 0.0     # outside the map
    odd = np.ones((20, 29), np.float32)    # sizes not a multiple of the cell: 3 x 4 cells, all within reach
    assert covered_share(odd, np.array([[12.0, 10.0]])) == pytest.approx(1.0)


def test_colour_pairs_move_the_pose_only_where_they_cover_the_still_surface():
    """A flat wall's slide is colour's to say (test_rigid_icp), but pairs on a small part of the
    still surface in view may lie on something sliding along it that the anchors have not seen
    move (a textured limb before a plain wall): below colour_pose_min_cover of it they are
    not used, and the pose is held where depth alone holds it."""
    from surfelwarp.tracking.rigid_icp import PointPairs
    from test_rigid_icp import INTR as WALL, WALL_SLIDE, pose_error, wall_depth, wall_points
    first, second = preprocess(wall_depth(np.eye(4)), WALL, 0, 0), preprocess(wall_depth(WALL_SLIDE), WALL, 1, 1)
    still = np.ones(first.valid.shape, np.float32)
    world, camera = wall_points(WALL_SLIDE)

    def pose(keep, params=TrackingParams()):
        tracker = Tracker(WALL, params)
        pairs = PointPairs(camera[keep], world[keep], np.ones(int(keep.sum())))
        tracker.rigid(first.vertex_map, first.normal_map, second, still, pairs)
        return tracker.T_camera_to_world

    corner = (world[:, 0] < -0.2) & (world[:, 1] < -0.1)
    assert corner.sum() >= 20
    assert pose_error(pose(np.ones(len(world), bool)), WALL_SLIDE)[0] < 3e-4
    assert pose_error(pose(corner), np.eye(4))[0] < 1e-4
    assert pose_error(pose(corner, TrackingParams(colour_pose_min_cover=0.0)), WALL_SLIDE)[0] < 3e-4
