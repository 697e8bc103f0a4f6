"""Colour features: detection where depth is, matching with outlier removal on a known warp of a
textured image, and the local rigidity test."""
from dataclasses import replace

import cv2
import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from surfelwarp.config import range_problem
from surfelwarp.data_tools.texture import albedo
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.tracking.colour import common_shift
from surfelwarp.tracking.features import (CORRECTION_REACH_PX, FeatureMatches, FeatureParams, checked_pairs, detect,
                                          grey, match_frames, neighbours_correction,
                                          refine, surface_depth, where_image)
from surfelwarp.tracking.flow import flow_at, flow_pairs, grid_pixels
from surfelwarp.tracking.patch_align import ALIGNED, PLAIN, align
from surfelwarp.tracking.rigidity import locally_rigid, rigidity_votes
from surfelwarp.tracking.descriptors import nearest_both_ways

INTR = Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)


def textured_plane(material_offset=(0.0, 0.0)):
    """An RGB image of a textured plane 1 m away filling the view, its vertex map and validity;
    the texture is painted at the plane's points plus `material_offset` (x, y metres)."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width].astype(np.float64)
    vertex = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], -1)
    material = vertex.reshape(-1, 3) + [*material_offset, 0.0]
    rgb = (255 * albedo(material)).reshape(INTR.height, INTR.width, 3).astype(np.uint8)
    return rgb, vertex.astype(np.float32), np.ones(u.shape, bool)


def known_warp(rgb: np.ndarray, rng: np.random.Generator):
    """The image turned by 8 deg, shifted and waved (a smooth non-rigid warp) with 8-bit noise;
    returns it and the map from old to new pixel positions."""
    h, w = rgb.shape[:2]
    A = cv2.getRotationMatrix2D((w / 2, h / 2), 8.0, 1.0)
    A[:, 2] += (6.0, -4.0)

    def forward(p):
        q = p @ A[:, :2].T + A[:, 2]
        return q + np.stack([3.0 * np.sin(q[:, 1] / 60.0), 2.0 * np.sin(q[:, 0] / 80.0)], -1)

    # remap needs the inverse: solve forward(p) = q per pixel by fixed-point iterations
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    q = np.stack([u.ravel(), v.ravel()], -1)
    Ainv = cv2.invertAffineTransform(A)
    p = q.copy()
    for _ in range(20):
        p = (q - (forward(p) - (p @ A[:, :2].T + A[:, 2]))) @ Ainv[:, :2].T + Ainv[:, 2]
    maps = p.reshape(h, w, 2).astype(np.float32)
    out = cv2.remap(rgb, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    out = np.clip(out + rng.normal(0.0, 2.0, out.shape), 0, 255).astype(np.uint8)
    return out, forward


def test_where_image_is_numpy_where_on_images():
    rng = np.random.default_rng(3)
    mask = rng.random((48, 64)) < 0.4
    for a, b in [(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)),
                 (rng.random((48, 64)).astype(np.float32), rng.random((48, 64)).astype(np.float32)),
                 (rng.random((48, 64)), np.zeros(())), (rng.random((48, 64)).astype(np.float32), np.float32(-0.0)),
                 (rng.integers(0, 9, (48, 64), dtype=np.int64), np.int64(-1)),        # not OpenCV's: numpy's where
                 (rng.random((48, 64)) < 0.5, np.zeros((48, 64), bool)), (rng.random((48, 64, 6)), np.zeros(()))]:
        if a.dtype.kind == "f":
            a[0, 0, ...] = np.nan
        want = np.where(mask[..., None] if a.ndim == 3 else mask, a, b)
        got = where_image(mask, a, b)
        assert got.dtype == want.dtype and got.shape == want.shape
        assert np.array_equal(got.view(np.uint8), want.view(np.uint8))       # to the bit, NaN and -0 too
    # Known answer; the depth refine reads: the vertex map's z where valid, +0 elsewhere.
    vertex = np.zeros((2, 3, 3), np.float32)
    vertex[..., 2] = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    valid = np.array([[True, False, True], [False, True, False]])
    depth = surface_depth(vertex, valid)
    assert depth.dtype == np.float32 and depth.tolist() == [[1.0, 0.0, 3.0], [0.0, 5.0, 0.0]]
    assert not np.signbit(depth).any()


@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_matches_on_a_known_warp_are_correct(detector):
    rng = np.random.default_rng(0)
    rgb, vertex, valid = textured_plane()
    warped, forward = known_warp(rgb, rng)
    params = FeatureParams(detector=detector)
    a, b = detect(rgb, valid, params), detect(warped, valid, params)
    m = match_frames(a, b, vertex, valid, vertex, valid, np.eye(4), params)
    error = np.linalg.norm(forward(m.previous_pixels.astype(np.float64)) - m.current_pixels, axis=1)
    assert len(m) >= 200, len(m)
    # correct: within 4 px (ORB keypoints of coarse pyramid levels sit a few pixels off); a wrong
    # match lands tens of pixels away
    assert np.mean(error < 4.0) >= 0.95, (len(m), np.mean(error < 4.0), np.percentile(error, [50, 90, 99]))


def _nearest_reference(a, b, ratio):
    """Brute force in float64, one direction: the nearest row of b, or -1 failing the ratio test."""
    d = np.sqrt(((a[:, None, :].astype(np.float64) - b[None, :, :]) ** 2).sum(-1))
    two = np.sort(d, axis=1)[:, :2]
    return np.where(two[:, 0] < ratio * two[:, 1], np.argmin(d, axis=1), -1)


def test_nearest_both_ways_is_the_exact_nearest_with_the_ratio_test():
    rng = np.random.default_rng(5)
    # SIFT-like: non-negative, some rows near copies of others (ambiguous or clear matches).
    a = rng.integers(0, 60, (300, 128)).astype(np.float32)
    b = np.concatenate([a[:150] + rng.normal(0, 3, (150, 128)), rng.integers(0, 60, (120, 128))]).astype(np.float32)
    b[10] = b[11] + 0.5                                 # two near-equal candidates: fails the ratio test
    ab, ba = nearest_both_ways(a, b, 0.8)
    np.testing.assert_array_equal(ab, _nearest_reference(a, b, 0.8))
    np.testing.assert_array_equal(ba, _nearest_reference(b, a, 0.8))
    assert (ab[:150] == np.arange(150)).sum() >= 145 and ab[11] == -1 and 100 <= (ab >= 0).sum() < 300
    # One row on the other side has no second nearest (inf): it passes (match_descriptors asks
    # for two features a side).
    one_a, one_b = nearest_both_ways(a[:1], b, 0.8)
    assert one_a.tolist() == [0] and (one_b == 0).all()


def test_dense_flow_on_a_known_warp_is_correct():
    rng = np.random.default_rng(2)
    rgb, vertex, valid = textured_plane()
    warped, forward = known_warp(rgb, rng)
    params = FeatureParams()
    pa, pb = flow_pairs(rgb, warped, valid, valid, params)
    m = checked_pairs(pa, pb, vertex, valid, vertex, valid, np.eye(4), params)
    error = np.linalg.norm(forward(m.previous_pixels.astype(np.float64)) - m.current_pixels, axis=1)
    assert len(m) > 0.8 * (640 // 8) * (480 // 8), len(m)          # the grid, but for the border
    assert np.mean(error < 1.0) >= 0.95, np.percentile(error, [50, 90, 99])
    # each pair refined by aligning its patch: DIS alone has a median error of 0.23 px here
    assert np.median(error) < 0.1, np.percentile(error, [50, 90, 99])


def test_refinement_keeps_what_it_cannot_judge_and_drops_what_matches_nothing():
    rng = np.random.default_rng(2)
    rgb, vertex, valid = textured_plane()
    warped, forward = known_warp(rgb, rng)
    pa = np.array([[320.0, 240.0], [321.0, 200.0]], np.float32)
    truth = forward(pa.astype(np.float64))
    start = (truth + [[0.6, -0.4], [-0.5, 0.3]]).astype(np.float32)
    params = FeatureParams()
    refined, keep = refine(grey(rgb), grey(warped), pa, start, params)
    assert keep.all() and np.all(np.linalg.norm(refined - truth, axis=1) < 0.3 * np.linalg.norm(start - truth, axis=1))
    # a plain patch cannot say, and with no aligned pair around to say for it, it is dropped; a
    # textured one that matches nothing near: dropped
    plain = np.full_like(rgb, 128)
    moved, keep = refine(grey(plain), grey(warped), pa, start, params)
    assert not keep.any() and np.array_equal(moved, start)
    _, keep = refine(grey(rgb), grey(np.roll(warped, 40, axis=1)), pa, start, params)
    assert not keep.any()
    moved, keep = refine(grey(rgb), grey(warped), pa, start, replace(params, refine_radius_px=0))
    assert keep.all() and np.array_equal(moved, start)


def test_plain_pairs_take_their_aligned_neighbours_correction():
    """Every pair found 0.4 px short of a 3 px shift (as DIS falls short): the textured ones are
    aligned to the truth, the plain ones (in a flat square) take their neighbours' correction."""
    rgb, _, _ = textured_plane()
    rgb = rgb.copy()
    rgb[200:260, 280:340] = 128
    shifted = np.roll(rgb, (2, 3), axis=(0, 1))                  # the truth: 3 px right, 2 down
    y, x = np.mgrid[150:311:8, 230:391:8]
    pa = np.stack([x.ravel(), y.ravel()], -1).astype(np.float32)
    truth = pa + [3.0, 2.0]
    start = (truth - [0.4, 0.3]).astype(np.float32)
    _, status = align(grey(rgb), grey(shifted), pa, start, 6)
    plain = status == PLAIN
    refined, keep = refine(grey(rgb), grey(shifted), pa, start, FeatureParams())
    error = np.linalg.norm(refined - truth, axis=1)
    assert keep[~plain].all() and plain.sum() >= 40
    assert np.median(error[status == ALIGNED]) < 0.01
    # found 0.5 px off; the ones beside the square's edge, whose patches barely reach the texture,
    # hold their start, and the plain pairs nearest them move less; those farther than
    # CORRECTION_REACH_PX from three aligned ones (the square's middle) are dropped
    kept = plain & keep
    assert 30 <= kept.sum() < plain.sum()
    assert np.median(error[kept]) < 0.01 and np.mean(error[kept] < 0.05) > 0.6, np.percentile(error[kept], [50, 90])
    # the square 10 cm nearer than the plane: its aligned neighbours lie across a depth edge, and
    # their correction is not its pairs' (DIS's flow on a plain surface is carried over from the
    # textured ones around, whatever their motion): every pair in it is dropped
    depth = np.ones(rgb.shape[:2])
    depth[200:260, 280:340] = 0.9
    inside = (pa[:, 0] >= 280) & (pa[:, 0] < 340) & (pa[:, 1] >= 200) & (pa[:, 1] < 260)
    _, keep = refine(grey(rgb), grey(shifted), pa, start, FeatureParams(), depth)
    assert inside.sum() == 49 and not keep[inside].any() and keep[~inside].mean() > 0.99
    # at the plane's depth, as without depth
    _, keep_flat = refine(grey(rgb), grey(shifted), pa, start, FeatureParams(), np.ones(rgb.shape[:2]))
    assert np.array_equal(keep_flat, kept | ~plain)


def test_neighbours_correction_is_the_median_of_the_aligned_ones_within_reach():
    aligned = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0], [5.0, 12.0]])
    correction = np.array([[0.2, -0.1], [0.3, -0.1], [0.2, 0.0], [0.25, -0.2], [5.0, 5.0]])   # one wild
    points = np.array([[5.0, 5.0], [5.0 + CORRECTION_REACH_PX + 20, 5.0], [-CORRECTION_REACH_PX + 1, 0.0]])
    out, vouched = neighbours_correction(points, aligned, correction)
    np.testing.assert_allclose(out[0], [0.25, -0.1])               # the median of all five
    np.testing.assert_array_equal(out[1], [0.0, 0.0])               # none within reach
    np.testing.assert_array_equal(out[2], [0.0, 0.0])               # one only: too few to say
    assert vouched.tolist() == [True, False, False]
    out, vouched = neighbours_correction(points, aligned[:2], correction[:2])
    assert out.tolist() == [[0.0, 0.0]] * 3 and not vouched.any()
    out, vouched = neighbours_correction(np.zeros((0, 2)), aligned, correction)
    assert out.shape == (0, 2) and vouched.shape == (0,)
    # on their surface only: with the point 5 cm nearer than three of the five, two remain
    depths = (np.array([1.0, 1.0, 1.0]), np.array([1.0, 1.0, 1.05, 1.05, 1.05]))
    out, vouched = neighbours_correction(points, aligned, correction, depths, 0.03)
    assert not vouched[0] and np.array_equal(out[0], [0.0, 0.0])
    out, vouched = neighbours_correction(points, aligned, correction, (depths[0], np.ones(5)), 0.03)
    assert vouched[0] and np.allclose(out[0], [0.25, -0.1])


def test_a_wrong_match_breaks_local_rigidity():
    rng = np.random.default_rng(1)
    previous = rng.uniform(-0.2, 0.2, (400, 3)) * [1, 1, 0.1] + [0, 0, 1]
    turn = cv2.Rodrigues(np.array([0.0, 0.3, 0.1]))[0]
    current = previous @ turn.T + [0.02, 0.0, 0.01]        # rigid: every distance kept
    wrong = rng.choice(len(previous), 40, replace=False)
    current[wrong] += rng.normal(0.0, 0.03, (40, 3)) + 0.02
    keep = locally_rigid(previous, current, FeatureParams())
    right = np.setdiff1d(np.arange(len(previous)), wrong)
    assert not keep[wrong].any()
    assert keep[right].mean() > 0.95


def test_matches_without_neighbours_within_the_radius_are_not_kept():
    rng = np.random.default_rng(2)
    cluster = rng.uniform(-0.02, 0.02, (60, 3)) + [0, 0, 1]
    lone = np.array([[0.5, 0.0, 1.0], [-0.5, 0.0, 1.0], [0.0, 0.5, 1.2]])   # 0.5 m from any other
    previous = np.vstack([cluster, lone]).astype(np.float32)               # float32 in, as lifted maps
    current = previous + np.float32([0.01, 0.0, 0.0])
    keep = locally_rigid(previous, current, FeatureParams())
    assert keep[:60].all() and not keep[60:].any()
    assert not locally_rigid(previous[:1], current[:1], FeatureParams()).any()


def _votes_reference(dist, nb, idx, current, radius, tolerance, floor_m, min_neighbours, min_agreement):
    dist, nb = np.where(np.isfinite(dist), dist, radius), idx[np.minimum(nb, len(idx) - 1)]
    near = (dist < radius) & (nb != np.arange(len(dist))[:, None])
    after = np.linalg.norm(current[:, None, :] - current[nb], axis=-1)
    agree = np.abs(after - dist) <= np.maximum(tolerance * dist, floor_m)
    count = near.sum(axis=1)
    share = (agree & near).sum(axis=1) / np.maximum(count, 1)
    return (count >= min_neighbours) & (share >= min_agreement)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_rigidity_votes_are_numpys(dtype):
    rng = np.random.default_rng(3)
    previous = rng.uniform(-0.1, 0.1, (3000, 3)) + [0, 0, 1]
    # moved rigidly, with noise near the tolerance so that votes fall on both sides of it
    current = (previous + [0.01, 0.0, 0.0] + rng.normal(0, 0.004, previous.shape)).astype(dtype)
    idx = np.flatnonzero(rng.uniform(size=len(previous)) < 0.8)        # a second pass: some left out
    radius = 0.02                                                     # some beyond it: inf, len(idx)
    dist, nb = KDTree(previous[idx]).query(previous, k=9, distance_upper_bound=radius)
    assert np.isinf(dist).any() and (nb == len(idx)).any()
    args = (radius, 0.1, 0.006, 2, 0.6)
    keep = rigidity_votes(dist, nb.astype(np.int64), idx, current, *args)
    expected = _votes_reference(dist, nb, idx, current, *args)
    np.testing.assert_array_equal(keep, expected)
    assert 0.2 < keep.mean() < 0.9, keep.mean()                      # both answers occur
    # a known answer: three points, one moved off its two neighbours' distances
    three = np.array([[0, 0, 1], [0.01, 0, 1], [0, 0.01, 1]], float)
    moved = three + [[0, 0, 0], [0, 0, 0], [0.03, 0, 0]]
    d, n = KDTree(three).query(three, k=3, distance_upper_bound=0.06)
    assert rigidity_votes(d, n.astype(np.int64), np.arange(3), three, 0.06, 0.1, 0.006, 2, 0.6).all()
    assert not rigidity_votes(d, n.astype(np.int64), np.arange(3), moved, 0.06, 0.1, 0.006, 2, 0.6).any()


def test_no_texture_and_no_depth_give_no_features():
    flat = np.full((480, 640, 3), 128, np.uint8)
    _, _, valid = textured_plane()
    assert len(detect(flat, valid, FeatureParams()).pixels) == 0
    rgb, _, _ = textured_plane()
    assert len(detect(rgb, np.zeros_like(valid), FeatureParams()).pixels) == 0


def test_a_motion_beyond_the_bound_is_dropped():
    rgb, vertex, valid = textured_plane()
    params = FeatureParams()
    kp = detect(rgb, valid, params)
    far = np.eye(4)
    far[2, 3] = 0.5                                        # the camera says the scene moved 50 cm
    assert len(match_frames(kp, kp, vertex, valid, vertex, valid, np.eye(4), params)) > 100
    assert len(match_frames(kp, kp, vertex, valid, vertex, valid, far, params)) == 0
    assert len(match_frames(kp, kp, vertex, valid, vertex, valid, far, replace(params, max_motion_m=0.6))) > 100


def test_the_motion_bound_follows_the_pairs_around_each_one():
    """A still room (1 mm off the prediction) with a ball that moved 6 cm and a few lone wrong
    pairs 6 cm off: the bound from all pairs' median drops the ball with the wrong pairs; the
    bound from each pair's neighbours keeps the ball and still drops the lone ones."""
    from surfelwarp.tracking.features import near_prediction
    rng = np.random.default_rng(5)
    room = np.c_[rng.uniform(-1, 1, (400, 2)), rng.uniform(2, 3, 400)]
    ball = [0.3, 0.2, 1.5] + rng.normal(0, 0.04, (40, 3))
    points = np.r_[room, ball]
    deviation = np.r_[rng.uniform(0, 0.002, 400), 0.06 + rng.uniform(-0.005, 0.005, 40)]
    wrong = np.arange(0, 400, 80)
    deviation[wrong] = 0.06
    candidate = np.ones(len(points), bool)
    candidate[7] = False
    params = FeatureParams()
    whole = near_prediction(deviation, candidate, params)
    local = near_prediction(deviation, candidate, params, points)
    assert not whole[400:].any() and not whole[wrong].any()
    assert local[400:].all() and not local[wrong].any() and not local[7]
    assert whole[:400].sum() == local[:400].sum() == 400 - len(wrong) - 1      # index 7: no candidate
    assert not near_prediction(deviation, np.zeros(len(points), bool), params, points).any()


def test_combine_keeps_one_match_a_surfel_the_first_sets():
    from surfelwarp.tracking.features import AnchoredMatches, combine

    a = AnchoredMatches(np.array([3, 5]), np.ones((2, 3)), np.zeros((2, 3)), np.ones(2))
    b = AnchoredMatches(np.array([5, 7]), 2 * np.ones((2, 3)), np.zeros((2, 3)), np.full(2, 0.5))
    m = combine(a, b)
    np.testing.assert_array_equal(m.index, [3, 5, 7])
    np.testing.assert_array_equal(m.ref_points[:, 0], [1, 1, 2])       # surfel 5 from the first set
    np.testing.assert_array_equal(m.weights, [1, 1, 0.5])
    assert len(combine()) == 0


def test_parameter_ranges_are_named():
    for name in ("ratio", "min_agreement", "flow_stride_px"):
        assert range_problem(FeatureParams(), name) is None
    assert "(0, 1]" in range_problem(FeatureParams(ratio=1.5), "ratio")
    assert "[0, 1]" in range_problem(FeatureParams(min_agreement=-0.1), "min_agreement")
    assert "(0, 256]" in range_problem(FeatureParams(flow_stride_px=0), "flow_stride_px")


def test_the_flow_is_primed_by_the_cameras_predicted_motion():
    """The prior of the flow's patch alignment is the predicted motion from the last camera to
    this one (points of the last camera in this one's frame)."""
    from surfelwarp.geometry.se3 import se3_exp
    from surfelwarp.tracking.colour import ColourMatcher

    matcher = ColourMatcher(INTR)
    T_last = se3_exp(np.array([0.1, -0.2, 0.05, 0.3, 0.1, -0.4]))
    assert matcher._prior(T_last, None) is None
    assert np.allclose(matcher._prior(T_last, T_last.copy()).T_previous_to_current, np.eye(4))
    step = se3_exp(np.array([0.0, 0.02, 0.0, 0.015, 0.0, 0.001]))         # the camera's last motion
    prior = matcher._prior(T_last, T_last @ step)
    point = np.array([0.1, -0.05, 0.9, 1.0])              # seen by the last camera
    world = T_last @ point
    assert np.allclose(prior.T_previous_to_current @ point, np.linalg.inv(T_last @ step) @ world)
    assert prior.intrinsics == INTR


def moving_blob(shift, radius=50, blur=4.0, seed=4):
    """Two frames of a softly textured disk (a ball's view) on a plain background, the second
    moved by `shift` (x, y) pixels, and the disk's masks."""
    rng = np.random.default_rng(seed)
    rgb = cv2.GaussianBlur(textured_plane()[0], (0, 0), blur)
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    frames, masks = [], []
    for offset in (np.zeros(2), np.asarray(shift, np.float64)):
        mask = (u - 280 - offset[0]) ** 2 + (v - 220 - offset[1]) ** 2 < radius ** 2
        moved = cv2.warpAffine(rgb, np.float32([[1, 0, offset[0]], [0, 1, offset[1]]]), (INTR.width, INTR.height))
        image = np.where(mask[..., None], moved, 60) + rng.normal(0.0, 2.0, rgb.shape)
        frames.append(np.clip(image, 0, 255).astype(np.uint8))
        masks.append(mask)
    return frames, masks


def test_the_flow_starts_from_a_common_shift():
    """A 100 px ball moving 40 px a frame: DIS from zero motion finds it for a minority of the
    grid; started from the features' common motion (2.9 px off here), for all of it."""
    shift = np.array([40.0, 6.0])
    (a, b), masks = moving_blob(shift)
    pa = grid_pixels(masks[0], 8)
    plain = flow_at(a, b, masks[0] | masks[1], pa, FeatureParams())
    assert plain[1].mean() < 0.6
    pb, found = flow_at(a, b, masks[0] | masks[1], pa, FeatureParams(), shift_px=shift + [2.5, -1.5])
    error = np.linalg.norm(pb - pa - shift, axis=1)[found]
    assert found.mean() > 0.95 and np.median(error) < 0.5 and np.mean(error < 1.0) > 0.9, \
        (found.mean(), np.percentile(error, [50, 90]))
    # A shift that would take the box out of the image is not used.
    out = flow_at(a, b, masks[0] | masks[1], pa, FeatureParams(), shift_px=np.array([-400.0, 0.0]))
    assert all(np.array_equal(x, y) for x, y in zip(out, plain))


def test_common_shift_is_the_median_motion_beyond_a_bound():
    rng = np.random.default_rng(5)
    before = rng.uniform(0, 600, (20, 2)).astype(np.float32)
    motion = np.tile(np.float32([12.0, -5.0]), (20, 1))
    motion[:6] = rng.uniform(-50, 50, (6, 2))                 # a minority moves otherwise
    points = np.zeros((20, 3))
    m = FeatureMatches(before, before + motion, points, points)
    np.testing.assert_allclose(common_shift(m, 8.0), [12.0, -5.0], atol=1e-5)
    assert common_shift(m, 14.0) is None                     # |(12, -5)| = 13 px
    assert common_shift(m, 0.0) is None                      # 0: off
    assert common_shift(m.select(np.arange(7)), 8.0) is None  # too few to tell


def test_bilinear_reads_a_plane_exactly_and_clamps_to_the_image():
    from surfelwarp.tracking.features import bilinear
    v, u = np.mgrid[0:5, 0:7].astype(np.float64)
    image = 2.0 * u + 3.0 * v + 1.0                # bilinear interpolation is exact on a plane
    x, y = np.array([0.0, 2.25, 5.5, 6.0]), np.array([0.0, 1.75, 3.5, 4.0])
    np.testing.assert_allclose(bilinear(image, x, y), 2 * x + 3 * y + 1, atol=1e-12)
    # outside: the border's value (the last row and column are reached, not read past)
    np.testing.assert_allclose(bilinear(image, np.array([-3.0, 9.0]), np.array([-1.0, 7.0])), [1.0, 25.0])
