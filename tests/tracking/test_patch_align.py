"""Patch alignment (affine Lucas-Kanade with gain and offset projected out): the compiled kernel
against its numpy reference, known affine warps, the Jacobian by finite differences, the depth
mask at an edge, the motion prior on a bulging surface, and its error cases."""
import cv2
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import se3_exp, se3_log
from surfelwarp.tracking.features import bilinear
from surfelwarp.tracking.patch_align import ALIGNED, FAILED, PLAIN, UNALIGNED, MotionPrior, _patch, align
from surfelwarp.tracking.patch_reference import align_reference, steepest_descent


def texture(h=240, w=320, seed=0):
    """Smooth random texture (blobs of ~6 px), 8-bit."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)), (0, 0), 2.5)
    return np.clip(128 + 3.0 * (img - img.mean()), 0, 255).astype(np.uint8)


def affine_pair(angle_deg=8.0, scale=1.04, shift=(0.37, -0.61), gain=1.3, offset=-20.0, seed=0):
    """An image and its affine warp (plus gain/offset and 8-bit noise); the map old -> new pixel."""
    a = texture(seed=seed)
    h, w = a.shape
    A = cv2.getRotationMatrix2D((w / 2, h / 2), angle_deg, scale)
    A[:, 2] += shift
    b = cv2.warpAffine(a.astype(np.float64), A, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    b = gain * b + offset + np.random.default_rng(seed + 1).normal(0.0, 1.0, b.shape)
    return a, np.clip(np.rint(b), 0, 255).astype(np.uint8), lambda p: p @ A[:, :2].T + A[:, 2]


def grid(h=240, w=320, margin=24, step=12):
    y, x = np.mgrid[margin:h - margin:step, margin:w - margin:step]
    return np.stack([x.ravel(), y.ravel()], -1).astype(np.float64)


def test_smoke_shapes_and_empty_input():
    a = texture()
    moved, aligned = align(a, a, np.zeros((0, 2)), np.zeros((0, 2)), 6)
    assert moved.shape == (0, 2) and aligned.shape == (0,)
    pa = grid()[:5]
    moved, status = align(a, a, pa, pa + 0.3, 6)
    assert moved.shape == (5, 2) and np.all(status == ALIGNED)
    assert np.abs(moved - pa).max() < 0.01          # the same image: back to where it started


def test_known_affine_warp_with_gain_is_recovered():
    a, b, forward = affine_pair()
    pa = grid()
    truth = forward(pa)
    start = truth + np.random.default_rng(3).uniform(-1.0, 1.0, truth.shape)   # a flow estimate 1 px off
    moved, status = align(a, b, pa, start, 6)
    error = np.linalg.norm(moved - truth, axis=1)
    assert np.mean(status == ALIGNED) > 0.97
    assert np.median(error) < 0.03, np.percentile(error, [50, 90])
    assert np.mean(error < 0.1) > 0.95, np.percentile(error, [50, 90, 99])
    # translation alone on the same patches does far worse under the turn: what the affine warp buys
    lk, _, _ = cv2.calcOpticalFlowPyrLK(a, b, pa.astype(np.float32).reshape(-1, 1, 2),
                                        start.astype(np.float32).reshape(-1, 1, 2), winSize=(13, 13), maxLevel=0,
                                        flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    assert np.median(np.linalg.norm(lk.reshape(-1, 2) - truth, axis=1)) > 3 * np.median(error)


def test_compiled_kernel_equals_the_numpy_reference():
    a, b, forward = affine_pair(angle_deg=3.0, seed=4)
    pa = np.vstack([grid(), [[1.0, 2.0], [318.5, 238.2]]])          # two patches over the border
    start = forward(pa) + 0.5
    depth = np.where(np.arange(320)[None, :] < 160, 1.0, 1.5) * np.ones((240, 1))
    # all pairs, and a few in the middle alone (align then reads only the box around them)
    middle = np.flatnonzero((np.abs(pa[:, 0] - 150) < 30) & (np.abs(pa[:, 1] - 120) < 30))
    for d in (None, depth):
        for sel in (slice(None), middle):
            moved, status = align(a, b, pa[sel], start[sel], 5, d)
            ref, ref_status = align_reference(a, b, pa[sel], start[sel], 5, d)
            assert np.array_equal(status, ref_status) and 0.5 < np.mean(status == ALIGNED)
            assert sel is middle or np.mean(status == ALIGNED) < 1.0       # the border patches are not
            assert np.allclose(moved, ref, atol=1e-7), np.abs(moved - ref).max()


def test_steepest_descent_images_match_finite_differences():
    y, x = np.mgrid[0:120, 0:160].astype(np.float64)
    smooth = 120 + 60 * np.sin(x / 9.0) * np.cos(y / 11.0) + 30 * np.sin((x + y) / 13.0)
    pa = np.array([[60.3, 50.7], [90.0, 70.2]])
    ox, oy, _ = _patch(4)
    sd = steepest_descent(smooth, pa, ox, oy)
    eps = 1e-3
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps

        def sample(sign):
            a00, a01, tx, a10, a11, ty = sign * d
            return bilinear(smooth, pa[:, :1] + (1 + a00) * ox + a01 * oy + tx,
                            pa[:, 1:] + a10 * ox + (1 + a11) * oy + ty)
        numeric = (sample(1) - sample(-1)) / (2 * eps)
        scale = np.abs(numeric).max()
        # Scharr's smoothed derivative against the bilinear image's: a few per cent on this texture
        assert np.abs(sd[..., k] - numeric).max() < 0.04 * scale, (k, np.abs(sd[..., k] - numeric).max(), scale)


def test_depth_mask_keeps_the_patch_on_its_surface():
    """Left half moves 2 px right, right half (farther) stays: a patch across the edge follows
    its centre's surface only when the depth masks the other."""
    a = texture(seed=5)
    h, w = a.shape
    b = a.copy()
    b[:, 162:] = a[:, 160:-2]      # the near (right) half moved 2 px right
    depth = np.where(np.arange(w)[None, :] >= 160, 1.0, 2.0) * np.ones((h, 1))
    pa = np.stack([np.full(15, 163.0), np.linspace(30, 210, 15)], -1)      # centres 3 px into the moving half
    truth = pa + [2.0, 0.0]
    masked, status = align(a, b, pa, pa + [1.0, 0.0], 6, depth, 0.1)
    plain, _ = align(a, b, pa, pa + [1.0, 0.0], 6)
    assert np.all(status == ALIGNED)
    assert np.abs(masked - truth).max() < 0.05
    assert np.median(np.abs(plain - truth)[:, 0]) > 0.2          # mixing the two motions


def test_a_plain_surface_before_a_textured_one_stays_plain():
    """A flat grey limb (near) before a textured wall (far), its outline slanting: the limb's
    patches beside it have no texture of their own, but Scharr's gradient at the outline mixes
    in the wall's. Counted as theirs, 31 of these 240 patches (three textures) were aligned on
    the wall's texture or failed; now each is plain. The wall's own patches beside the outline
    still align."""
    statuses, wall = [], []
    for seed in range(3):
        a = texture(seed=seed)
        h, w = a.shape
        y, x = np.mgrid[0:h, 0:w]
        near = x < 160 + 0.5 * (y - 120)
        a = np.where(near, 100, a).astype(np.uint8)
        b = np.clip(a + np.random.default_rng(seed).normal(0.0, 1.0, a.shape), 0, 255).astype(np.uint8)
        depth = np.where(near, 1.0, 1.5)
        ys = np.linspace(30, 210, 40)
        for offset in (-2.0, -3.0, 3.0):
            pa = np.stack([160 + 0.5 * (ys - 120) + offset, ys], -1)
            moved, status = align(a, b, pa, pa + 0.3, 6, depth)
            (wall if offset > 0 else statuses).append(status)
            if offset > 0:
                assert np.median(np.linalg.norm(moved - pa, axis=1)) < 0.1
    statuses, wall = np.concatenate(statuses), np.concatenate(wall)
    assert np.all(statuses == PLAIN), np.bincount(statuses + 1)
    assert np.mean(wall == ALIGNED) > 0.95


def test_too_little_of_the_surface_is_not_aligned():
    a = texture()
    depth = np.zeros(a.shape)
    depth[100:103, 100:103] = 1.0          # the centre's surface is a 3x3 island
    moved, status = align(a, a, np.array([[101.0, 101.0]]), np.array([[101.5, 101.0]]), 6, depth)
    assert status[0] == UNALIGNED and np.allclose(moved, [[101.5, 101.0]])


def test_plain_patches_cannot_say_and_textured_ones_that_match_nothing_fail():
    a = texture()
    pa = grid()
    plain = np.full(a.shape, 100, np.uint8)
    moved, status = align(plain, a, pa[:20], pa[:20] + 0.5, 6)
    assert np.all(status == PLAIN) and np.array_equal(moved, pa[:20] + 0.5)
    # The match is 40 px away. On the whole grid (368 patches; 20 before the shading's plane was
    # projected out, 1 then 3 of them aligned somewhere wrong): 5.2 % aligned with gain and
    # offset alone, 7.6 % with the plane (where kept), which explains a little more of a wrong patch.
    moved, status = align(a, np.roll(a, 40, axis=1), pa, pa + 0.5, 6)
    assert np.mean(status == FAILED) > 0.9 and np.array_equal(moved[status == FAILED], (pa + 0.5)[status == FAILED])


def test_a_shading_slope_across_the_patch_does_not_move_it():
    """A lamp beside the camera shades a curved surface unevenly: the current image gains a
    slope (0.4 grey levels a pixel) on top of the gain and offset. With gain and offset alone the
    patches slid towards the slope's rise by a median 0.08 px; with the plane projected out too
    0.034 (0.028 without the slope)."""
    a, b, forward = affine_pair()
    h, w = b.shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    sloped = np.clip(np.rint(b + 0.4 * ((x - w / 2) + 0.5 * (y - h / 2))), 0, 255).astype(np.uint8)
    pa = grid()
    truth = forward(pa)
    start = truth + np.random.default_rng(3).uniform(-1.0, 1.0, truth.shape)
    moved, status = align(a, sloped, pa, start, 6)
    error = np.linalg.norm(moved - truth, axis=1)
    assert np.mean(status == ALIGNED) > 0.97
    assert np.median(error) < 0.04, np.percentile(error, [50, 90])


BUMP_CAMERA = Intrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)


def bump_pair(height_m=0.03, sigma_px=15.0, shift_m=0.1):
    """A textured surface 1 m away with a Gaussian bump towards the camera at the image centre,
    seen before and after the camera moves shift_m to its left: (float images a, b, depth of a,
    the true displacement of each pixel of a, the motion of a's points into b's camera). The
    texture is a sum of cosines painted exactly where each pixel of b looks (no resampling)."""
    rng = np.random.default_rng(1)
    freq, phase = rng.uniform(-0.6, 0.6, (40, 2)), rng.uniform(0, 2 * np.pi, 40)
    y, x = np.mgrid[0:240, 0:320].astype(np.float64)

    def paint(u):
        return 128 + 20 * np.cos(u[..., None] * freq[:, 0] + y[..., None] * freq[:, 1] + phase).sum(-1)

    def displacement(u):       # of a's pixel (u, y): the points move by shift_m along x, in depth z(u, y)
        z = 1.0 - height_m * np.exp(-((u - 160) ** 2 + (y - 120) ** 2) / (2 * sigma_px ** 2))
        return BUMP_CAMERA.fx * shift_m / z, z

    seen = x - BUMP_CAMERA.fx * shift_m
    for _ in range(60):         # the pixel of a that each pixel of b sees: seen + displacement(seen) = x
        seen = x - displacement(seen)[0]
    T = np.eye(4)
    T[0, 3] = shift_m
    d, z = displacement(x)
    return paint(x), paint(seen), z, np.stack([d, 0 * d], -1), T


def test_motion_prior_follows_the_relief_of_a_bulging_surface():
    """On the bump's crown the displacement (30 px) is largest at the centre: an affine warp
    averages it over the patch and falls short; moved first by the prior, the patch lands on the
    centre's displacement. Without relief (height 0) the prior changes nothing."""
    yy, xx = np.mgrid[108:133:2, 148:173:2]
    pa = np.stack([xx.ravel(), yy.ravel()], -1).astype(np.float64)
    for height, short_by in ((0.03, 0.02), (0.0, None)):
        a, b, depth, shift, T = bump_pair(height)
        truth = pa + shift[yy.ravel(), xx.ravel()]
        plain, status = align(a, b, pa, truth + 0.3, 6, depth, 0.1)
        primed, primed_status = align(a, b, pa, truth + 0.3, 6, depth, 0.1, prior=MotionPrior(BUMP_CAMERA, T))
        assert np.all(status == ALIGNED) and np.all(primed_status == ALIGNED)
        err, primed_err = (plain - truth)[:, 0].mean(), (primed - truth)[:, 0].mean()
        if short_by is None:
            assert abs(err) < 1e-4 and abs(primed_err) < 1e-4
        else:
            assert err < -short_by, err
            assert abs(primed_err) < 0.25 * abs(err), (err, primed_err)
            # twice the motion as prior overshoots: the prior is what moves the patch
            twice = MotionPrior(BUMP_CAMERA, se3_exp(2 * se3_log(T)))
            doubled, _ = align(a, b, pa, truth + 0.3, 6, depth, 0.1, prior=twice)
            assert (doubled - truth)[:, 0].mean() > abs(err) / 2


def test_compiled_kernel_with_a_prior_equals_the_numpy_reference():
    a, b, depth, shift, T = bump_pair()
    pa = np.vstack([grid(margin=30, step=9), [[1.0, 2.0], [318.5, 238.2]]])
    start = pa + shift[np.rint(pa[:, 1]).astype(int), np.rint(pa[:, 0]).astype(int)] + 0.4
    depth = depth.copy()
    depth[:, :40] = 0.0                              # no depth: no prior there
    turned = se3_exp(np.array([0.01, -0.02, 0.005, 0.03, 0.0, -0.02])) @ T      # any rigid motion
    for prior in (MotionPrior(BUMP_CAMERA, T), MotionPrior(BUMP_CAMERA, turned)):
        moved, status = align(a, b, pa, start, 5, depth, 0.1, prior=prior)
        ref, ref_status = align_reference(a, b, pa, start, 5, depth, 0.1, prior=prior)
        assert np.array_equal(status, ref_status) and np.mean(status == ALIGNED) > 0.5
        assert np.allclose(moved, ref, atol=1e-7), np.abs(moved - ref).max()
    # without depth the prior cannot say where the patch's pixels go: the plain alignment
    assert np.array_equal(align(a, b, pa, start, 5, prior=prior)[0], align(a, b, pa, start, 5)[0])


def test_a_prior_that_moves_no_pixel_is_not_applied():
    """A still camera's pose jitters by hundredths of a millimetre from frame to frame: a prior
    that moves no patch pixel by PRIOR_MIN_PX leaves the alignment as it was without one, to the
    bit (the primed path samples each pixel on its own and rounds differently)."""
    a, b, depth, shift, T = bump_pair()
    pa = grid(margin=30, step=9)
    start = pa + shift[np.rint(pa[:, 1]).astype(int), np.rint(pa[:, 0]).astype(int)] + 0.4
    jitter = np.eye(4)
    jitter[:3, 3] = [2e-5, -1e-5, 3e-5]
    plain = align(a, b, pa, start, 6, depth, 0.1)
    for aligned in (align, align_reference):    # each against itself (the kernels agree: above)
        without = aligned(a, b, pa, start, 6, depth, 0.1)
        still = aligned(a, b, pa, start, 6, depth, 0.1, prior=MotionPrior(BUMP_CAMERA, jitter))
        assert np.array_equal(still[1], without[1]) and np.allclose(still[0], without[0], rtol=0, atol=1e-7)
    assert np.array_equal(align(a, b, pa, start, 6, depth, 0.1, prior=MotionPrior(BUMP_CAMERA, jitter))[0], plain[0])
    moved = align(a, b, pa, start, 6, depth, 0.1, prior=MotionPrior(BUMP_CAMERA, T))[0]
    assert not np.allclose(moved, plain[0], rtol=0, atol=1e-3)         # a real motion does move them
