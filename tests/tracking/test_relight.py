"""Relighting the flow's source image (tracking/relight.py): the shading ratio a + b . n fitted
through a known flow and against the last frame where it stands, the image scaled by it where
lit, the cases with too little to fit, and the flow's pairs on a shaded pair of images."""
from dataclasses import replace

import cv2
import numpy as np

from surfelwarp.tracking.features import FeatureParams
from surfelwarp.tracking.flow import flow_at, grid_pixels
from surfelwarp.tracking.relight import MIN_PIXELS, SCALE_RANGE, ModelShading, Relight, relit

from test_patch_align import texture


def bowl_normals(h, w, reach_px=150.0):
    """(h, w, 3) unit normals of a bowl facing the camera: each 13 px patch turns ~5 degrees."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    n = np.stack([(u - w / 2) / reach_px, (v - h / 2) / reach_px, -np.ones_like(u)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def shading_ratio(previous, current, flow, origin, relight):
    """The fit of `current` against the model's `previous` box at `origin` through `flow`."""
    return ModelShading(previous, origin, relight).ratio(current, relight.current_valid, flow)


COEF = np.float32([1.0, 0.4, 0.25, 0.0])      # a, b: the ratio spans 0.62-1.38 over the image


def shaded_shift(a, normals, dx=3, dy=-2):
    """The image shaded by COEF's ratio and moved by whole pixels, and where it has content."""
    h, w = a.shape
    truth = COEF[0] + normals @ COEF[1:]
    out, valid = np.zeros_like(a, np.float32), np.zeros((h, w), bool)
    rows, cols = slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0))
    out[rows, cols] = (a * truth)[max(-dy, 0):h - max(dy, 0), max(-dx, 0):w - max(dx, 0)]
    valid[rows, cols] = True
    return out, valid, truth


def test_known_shading_ratio_is_recovered_and_applied_where_lit():
    a = texture().astype(np.float32)
    h, w = a.shape
    n = bowl_normals(h, w)
    current, valid, truth = shaded_shift(a, n)
    lit = np.ones((h, w), bool)
    lit[:, :40] = False                        # not the model's colour there: left as it is
    relight = Relight(n, lit, valid)
    coef = shading_ratio(a, current, np.tile(np.float32([3, -2]), (h, w, 1)), (0, 0), relight)
    fit = coef[0] + n @ coef[1:]
    assert np.sqrt(np.mean((fit - truth) ** 2)) < 0.003 and np.abs(fit - truth).max() < 0.01, coef
    out = relit(a, coef, (0, 0), relight)
    assert out.dtype == np.float32 and np.array_equal(out[:, :40], a[:, :40])
    np.testing.assert_allclose(out[:, 40:], (a * fit)[:, 40:], rtol=1e-5)
    # A box of the image at an origin reads the normals and masks at that box.
    box = (slice(30, 130), slice(60, 200))
    sub = shading_ratio(a[box], current, np.tile(np.float32([3, -2]), (100, 140, 1)), (30, 60), relight)
    np.testing.assert_allclose(sub[0] + n[box] @ sub[1:], truth[box], atol=0.02)   # a third of the pixels
    np.testing.assert_allclose(relit(a[box], sub, (30, 60), relight), a[box] * (sub[0] + n[box] @ sub[1:]), rtol=1e-5)


def test_too_little_to_fit_is_not_relit():
    a = texture().astype(np.float32)
    h, w = a.shape
    n = bowl_normals(h, w)
    current, valid, _ = shaded_shift(a, n)
    flow = np.zeros((h, w, 2), np.float32)
    small = np.zeros((h, w), bool)
    small[100:110, 100:110] = True              # fewer than MIN_PIXELS once eroded
    assert small.sum() < MIN_PIXELS
    assert shading_ratio(a, current, flow, (0, 0), Relight(n, small, valid)) is None
    everywhere = np.ones((h, w), bool)
    assert shading_ratio(a, current, flow, (0, 0), Relight(n, everywhere, ~everywhere)) is None   # no depth there
    assert shading_ratio(a, current, flow, (0, 0), Relight(np.zeros_like(n), everywhere, valid)) is None  # no normals
    far = np.tile(np.float32([1000.0, 0.0]), (h, w, 1))                     # the flow leaves the image
    assert shading_ratio(a, current, far, (0, 0), Relight(n, everywhere, valid)) is None


def test_flow_pairs_on_a_shaded_image_align_as_on_an_unshaded_one():
    """The current image shaded by a ratio that changes across each patch (a bowl under a lamp),
    moved 2.3 px: relit first, the pairs land as they do without the shading (p90 0.091 px);
    aligned as they are, patch normalisation leaves p90 0.117 px."""
    a = texture()
    h, w = a.shape
    n = bowl_normals(h, w)
    shift = np.float32([2.3, -1.4])
    rgb = lambda g: np.repeat(g[..., None], 3, -1)                           # noqa: E731
    mask = np.ones((h, w), bool)
    pa = grid_pixels(mask, 8)
    p90 = {}
    for shaded in (False, True):
        ratio = COEF[0] + n @ COEF[1:] if shaded else np.ones((h, w), np.float32)
        moved = cv2.warpAffine(a.astype(np.float32) * ratio, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (w, h),
                               flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        b = np.clip(np.rint(moved + np.random.default_rng(1).normal(0, 1, moved.shape)), 0, 255).astype(np.uint8)
        for relight in (None, Relight(n, mask, mask)):
            pb, found = flow_at(rgb(a), rgb(b), mask, pa, FeatureParams(), relight=relight)
            assert found.mean() > 0.99
            p90[shaded, relight is not None] = np.percentile(np.linalg.norm(pb - pa - shift, axis=1)[found], 90)
    assert p90[True, False] > 1.2 * p90[False, False], p90
    assert p90[True, True] < 1.1 * p90[False, False], p90
    assert abs(p90[False, True] - p90[False, False]) < 0.005, p90             # unshaded: relighting moves little


def test_the_scale_is_held_where_the_fit_extrapolates():
    """A fit made on nearly one normal (a wall) can put any b on the others: the scale stays in
    SCALE_RANGE."""
    a = np.full((40, 50), 100.0, np.float32)
    n = np.zeros((40, 50, 3), np.float32)
    n[..., 2] = -1.0
    n[:, 25:] = [0.8, 0.0, -0.6]                 # a surface turned 53 degrees, left out of the fit
    out = relit(a, np.array([1.0, 30.0, 0.0, 0.0]), (0, 0), Relight(n, np.ones((40, 50), bool), n[..., 2] < 0))
    assert np.allclose(out[:, :25], 100.0) and np.allclose(out[:, 25:], 100.0 * SCALE_RANGE[1])
    out = relit(a, np.array([1.0, -30.0, 0.0, 0.0]), (0, 0), Relight(n, np.ones((40, 50), bool), n[..., 2] < 0))
    assert np.allclose(out[:, 25:], 100.0 * SCALE_RANGE[0])


def noisy(image, seed):
    return np.clip(np.rint(image + np.random.default_rng(seed).normal(0, 1, image.shape)), 0, 255).astype(np.uint8)


def test_the_last_frames_shading_is_fitted_where_it_stands_and_relights_the_flows_source():
    """The model's colour unshaded, the last frame and the current one (moved 2.3 px) under the
    bowl's shading: the last frame, seen from the pose the model is drawn at, gives the ratio
    without a flow, and DIS on the model's colour relit by it lands closer (its flow alone: p90
    0.100 -> 0.072 px); the aligned pairs are no worse."""
    a = texture()
    h, w = a.shape
    n = bowl_normals(h, w)
    ratio = COEF[0] + n @ COEF[1:]
    last = noisy(a.astype(np.float32) * ratio, 2)
    shift = np.float32([2.3, -1.4])
    b = noisy(cv2.warpAffine(a.astype(np.float32) * ratio, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (w, h),
                             flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT), 1)
    mask = np.ones((h, w), bool)
    coef = ModelShading(a.astype(np.float32), (0, 0), Relight(n, mask, mask)).ratio(last, mask)
    fit = coef[0] + n @ coef[1:]
    assert np.sqrt(np.mean((fit - ratio) ** 2)) < 0.001, coef
    rgb = lambda g: np.repeat(g[..., None], 3, -1)                           # noqa: E731
    pa = grid_pixels(mask, 8)
    p90, aligned = {}, FeatureParams().refine_radius_px
    for radius in (0, aligned):                                              # DIS's flow alone, then aligned
        for with_last in (False, True):
            relight = Relight(n, mask, mask, last if with_last else None, mask if with_last else None)
            pb, found = flow_at(rgb(a), rgb(b), mask, pa, replace(FeatureParams(), refine_radius_px=radius),
                                relight=relight)
            assert found.mean() > 0.99
            p90[radius, with_last] = np.percentile(np.linalg.norm(pb - pa - shift, axis=1)[found], 90)
    assert p90[0, True] < 0.8 * p90[0, False], p90
    assert p90[aligned, True] < 1.05 * p90[aligned, False], p90
