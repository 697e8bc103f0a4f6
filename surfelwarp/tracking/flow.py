"""Dense colour pairs: optical flow (OpenCV's DIS) read on a grid of pixels, each pair refined by
aligning its patch (features.refine): correspondences where a surface has too little texture
for features (cloth). colour.py runs it from the model's fused colour drawn at the last pose.
"""
from __future__ import annotations

import cv2
import numpy as np

from surfelwarp.tracking.features import FeatureParams, bounding_box, grey, refine
from surfelwarp.tracking.patch_align import MotionPrior
from surfelwarp.tracking.relight import Relight, relit, shading_ratio


def grid_pixels(mask: np.ndarray, stride_px: int) -> np.ndarray:
    """(n, 2) float32 pixel centres (x, y) of a stride_px grid where `mask` holds, away from its
    edges (flow there mixes the surface with what is behind it)."""
    inner = cv2.erode(np.asarray(mask, np.uint8), np.ones((5, 5), np.uint8))
    s = stride_px
    rows, cols = np.nonzero(inner[s // 2::s, s // 2::s])
    return np.stack([cols * s + s // 2, rows * s + s // 2], -1).astype(np.float32)


def flow_at(previous_color: np.ndarray, current_color: np.ndarray, window: np.ndarray, pixels: np.ndarray,
            params: FeatureParams, previous_depth: np.ndarray | None = None, prior: MotionPrior | None = None,
            shift_px: np.ndarray | None = None, relight: Relight | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Dense optical flow (OpenCV's DIS) from the previous to the current image, computed on the
    box around `window` and read bilinearly at sub-pixel `pixels` (x, y): (where they go, whether
    they are inside the box). No forward-backward check: on the DeepDeform shirt (20 cm of
    motion) it kept 25 of the 713 good pairs at 8 px; local rigidity (checked_pairs) removes the
    wrong ones. `shift_px` (x, y): a motion to start the search from (the features' common
    motion: `fast`'s ball, 25 px a frame, was found by DIS from zero on some frames only).
    `relight`: the previous image is the model's colour there, relit by the flow before the
    pairs are aligned (relight.py)."""
    rows, cols = bounding_box(np.asarray(window, bool))
    h, w = rows.stop - rows.start, cols.stop - cols.start
    inside = np.zeros(len(pixels), bool)
    if h < 16 or w < 16 or len(pixels) == 0:
        return pixels.copy(), inside
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    previous, current = grey(previous_color), grey(current_color)
    # DIS's search starts at zero motion: given a common motion, the current box is moved by it.
    s = np.zeros(2, int) if shift_px is None else np.rint(shift_px).astype(int)
    r0, c0 = rows.start + s[1], cols.start + s[0]
    if not (0 <= r0 <= current.shape[0] - h and 0 <= c0 <= current.shape[1] - w):
        s, r0, c0 = np.zeros(2, int), rows.start, cols.start
    flow = dis.calc(np.ascontiguousarray(previous[rows, cols]), np.ascontiguousarray(current[r0:r0 + h, c0:c0 + w]),
                    None) + s.astype(np.float32)
    local = pixels - np.float32([cols.start, rows.start])
    inside = (local[:, 0] >= 0) & (local[:, 0] <= w - 1) & (local[:, 1] >= 0) & (local[:, 1] <= h - 1)
    coef = None if relight is None else shading_ratio(previous[rows, cols], current, flow, (rows.start, cols.start),
                                                      relight)
    if coef is not None:
        previous = previous.astype(np.float32)
        previous[rows, cols] = relit(previous[rows, cols], coef, (rows.start, cols.start), relight)
    maps = np.ascontiguousarray(local.reshape(-1, 1, 2), np.float32)
    moved = cv2.remap(flow, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    target, keep = refine(previous, current, pixels, pixels + moved.reshape(-1, 2), params, previous_depth, prior)
    inside &= keep
    full_h, full_w = window.shape
    inside &= (target[:, 0] >= 0) & (target[:, 0] <= full_w - 1) & (target[:, 1] >= 0) & (target[:, 1] <= full_h - 1)
    return target, inside


def flow_pairs(previous_color: np.ndarray, current_color: np.ndarray, previous_valid: np.ndarray,
               current_valid: np.ndarray, params: FeatureParams, previous_depth: np.ndarray | None = None,
               prior: MotionPrior | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixel pairs (x, y) of dense flow on a grid of the previous frame's depth pixels: dense
    correspondences where a surface has too little texture for features (cloth)."""
    pa = grid_pixels(previous_valid, params.flow_stride_px)
    pb, inside = flow_at(previous_color, current_color, np.asarray(previous_valid, bool) | current_valid, pa, params,
                         previous_depth, prior)
    return pa[inside], pb[inside]
