"""Dense colour pairs: optical flow (OpenCV's DIS) read on a grid of pixels, each pair refined by
aligning its patch (features.refine): correspondences where a surface has too little texture
for features (cloth). colour.py runs it from the model's fused colour drawn at the last pose.
"""
from __future__ import annotations

import cv2
import numpy as np

from surfelwarp.tracking.features import FeatureParams, bounding_box, grey, refine
from surfelwarp.tracking.patch_align import MotionPrior
from surfelwarp.tracking.relight import ModelShading, Relight, relit


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
    `relight`: the previous image is the model's colour there, relit (relight.py) for DIS to the
    last frame's shading (if the last frame is given) and for the pairs' alignment to the
    current frame's, fitted through DIS's flow."""
    rows, cols = bounding_box(np.asarray(window, bool))
    h, w = rows.stop - rows.start, cols.stop - cols.start
    inside = np.zeros(len(pixels), bool)
    if h < 16 or w < 16 or len(pixels) == 0:
        return pixels.copy(), inside
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    previous, current = grey(previous_color), grey(current_color)
    origin = (rows.start, cols.start)
    shading = None if relight is None else ModelShading(previous[rows, cols], origin, relight)
    source = previous[rows, cols]
    if shading is not None and relight.last is not None:
        # DIS matches brightness: its source is the model's colour relit to the last frame's
        # shading, which a lamp on the camera changes little in a frame (orbit: mean EPE 0.62
        # -> 0.54 mm); the model's colour averages the shading of all the frames it was fused in.
        coef = shading.ratio(relight.last, relight.last_valid)
        if coef is not None:
            source = np.clip(np.rint(relit(source, coef, origin, relight)), 0, 255).astype(np.uint8)
    # DIS's search starts at zero motion: given a common motion, the current box is moved by it.
    s = np.zeros(2, int) if shift_px is None else np.rint(shift_px).astype(int)
    r0, c0 = rows.start + s[1], cols.start + s[0]
    if not (0 <= r0 <= current.shape[0] - h and 0 <= c0 <= current.shape[1] - w):
        s, r0, c0 = np.zeros(2, int), rows.start, cols.start
    flow = dis.calc(np.ascontiguousarray(source), np.ascontiguousarray(current[r0:r0 + h, c0:c0 + w]),
                    None) + s.astype(np.float32)
    local = pixels - np.float32([cols.start, rows.start])
    inside = (local[:, 0] >= 0) & (local[:, 0] <= w - 1) & (local[:, 1] >= 0) & (local[:, 1] <= h - 1)
    coef = None if shading is None else shading.ratio(current, relight.current_valid, flow)
    if coef is not None:
        previous = previous.astype(np.float32)
        previous[rows, cols] = relit(previous[rows, cols], coef, origin, relight)
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
