"""The model's colour relit to a frame's shading before the flow runs and its pairs are aligned.

A lamp that moves with the camera (a flash, a projector read as colour) shades every surface
anew each frame, and the model's colour was fused under its earlier directions: a patch drawn
from the model differs from the frame by a shading ratio that varies across it, which patch
normalisation (gain, offset, slope) holds only in part and which slides the alignment towards
the light. Under a distant lamp a Lambertian surface's shading is a + b . n in the camera frame
(the lamp beside the camera or in the room alike), so the ratio of a frame's colour to the
model's is, to first order, one such function of the model's normals, fitted from the local
means of both images (ModelShading). Twice a frame: against the last frame, which shows each
model pixel's surface at that pixel (the model is drawn at its pose), for the image DIS reads;
then against the current frame through DIS's flow, for the image the pairs are aligned on.
`orbit` (a still life, the lamp on the camera): mean EPE 0.75 -> 0.62 mm (the second fit alone)
-> 0.54, ATE 0.235 -> 0.192 -> 0.183 cm; with the lamp's shading off 0.44 [0.163].
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from surfelwarp.tracking.features import bilinear

SIGMA_PX = 4.0          # the local means' Gaussian: wider than the texture's blobs, narrower than the shading
MIN_PIXELS = 500        # fewer model pixels than this with a place in the frame: not relit
ERODE_PX = 9            # both masks shrunk by this box: the means near an edge mix in what is beyond it
STRIDE_PX = 3           # the fit reads every third pixel a side: the shading is smooth, the means too
SCALE_RANGE = (0.5, 2.0)  # the scale is held to this: where the normals barely vary (a wall) the fit's
                          # b is poorly set, and it is extrapolated to pixels the fit left out
_KERNEL = np.ones((ERODE_PX, ERODE_PX), np.uint8)


@dataclass(frozen=True)
class Relight:
    """What relighting the flow's source image reads: (H, W, 3) normals of the model drawn there
    (camera frame, zero where none), the pixels `lit` that show the model's colour (the rest are
    left as they are), where the current frame has depth, and optionally the last frame (grey)
    and where it had depth: seen from the pose the model is drawn at, it shows each model pixel's
    surface at that pixel, so its shading is fitted without a flow."""
    normals: np.ndarray
    lit: np.ndarray
    current_valid: np.ndarray
    last: np.ndarray | None = None
    last_valid: np.ndarray | None = None


def _local_mean(image: np.ndarray, mask: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The Gaussian mean of `image` over the pixels of `mask` (normalised convolution) at the
    points (x, y) inside it: made at half resolution (the shading is smooth; a quarter of the
    pixels to blur) and read bilinearly."""
    h, w = mask.shape
    size = ((w + 1) // 2, (h + 1) // 2)
    m = mask.astype(np.float32)
    num = cv2.GaussianBlur(cv2.resize(image * m, size, interpolation=cv2.INTER_AREA), (0, 0), SIGMA_PX / 2)
    den = cv2.GaussianBlur(cv2.resize(m, size, interpolation=cv2.INTER_AREA), (0, 0), SIGMA_PX / 2)
    mean = num / np.maximum(den, 1e-6)
    u = np.clip((x + 0.5) * size[0] / w - 0.5, 0, size[0] - 1.001)
    v = np.clip((y + 0.5) * size[1] / h - 0.5, 0, size[1] - 1.001)
    return bilinear(mean, u, v)


class ModelShading:
    """The model's side of the shading fit on the `previous` image's box at `origin` (row,
    column): the pixels the fit reads (lit, with a normal, away from the edges, every
    STRIDE_PX-th a side), their normals and their local means; made once, fitted against
    each image the model's colour is compared with (ratio)."""

    def __init__(self, previous: np.ndarray, origin: tuple[int, int], relight: Relight):
        h, w = previous.shape
        r0, c0 = self.origin = origin
        box = (slice(r0, r0 + h), slice(c0, c0 + w))
        normals = np.asarray(relight.normals[box], np.float32)
        drawn = normals[..., 0] ** 2 + normals[..., 1] ** 2 + normals[..., 2] ** 2 > 0.25   # einsum took 3x longer
        lit = np.asarray(relight.lit[box], bool) & drawn
        rows, cols = np.nonzero(cv2.erode(lit.astype(np.uint8), _KERNEL)[::STRIDE_PX, ::STRIDE_PX])
        self.rows, self.cols = rows * STRIDE_PX, cols * STRIDE_PX
        self.enough = len(rows) * STRIDE_PX ** 2 >= MIN_PIXELS
        self.normals = normals[self.rows, self.cols]
        self.here = _local_mean(np.asarray(previous, np.float32), lit, self.cols, self.rows) if self.enough else None

    def ratio(self, current: np.ndarray, current_valid: np.ndarray, flow: np.ndarray | None = None
              ) -> np.ndarray | None:
        """(4,) a, b of the ratio a + b . n of the `current` grey image (full) to the model's, at
        the pixels `flow` (the box's, (h, w, 2) x, y) takes the fit's pixels to (None: where they
        are) that land on `current_valid`; None with too few of them."""
        if not self.enough:
            return None
        (r0, c0), rows, cols = self.origin, self.rows, self.cols
        x, y = cols + c0, rows + r0
        if flow is not None:
            x, y = x + flow[rows, cols, 0], y + flow[rows, cols, 1]
        # The current frame's means only on the box the points reach (plus the Gaussian's reach).
        H, W = np.shape(current)
        m = int(np.ceil(3 * SIGMA_PX)) + ERODE_PX
        y0, y1 = max(int(np.floor(y.min())) - m, 0), min(int(np.ceil(y.max())) + m + 1, H)
        x0, x1 = max(int(np.floor(x.min())) - m, 0), min(int(np.ceil(x.max())) + m + 1, W)
        if y1 - y0 < 2 or x1 - x0 < 2:
            return None
        reach = (slice(y0, y1), slice(x0, x1))
        valid = np.asarray(current_valid[reach], bool)
        x, y = x - x0, y - y0
        inside = (x >= 0) & (x <= x1 - x0 - 1) & (y >= 0) & (y <= y1 - y0 - 1)
        xi, yi = np.clip(x, 0, x1 - x0 - 1.001), np.clip(y, 0, y1 - y0 - 1.001)
        keep = inside & (cv2.erode(valid.astype(np.uint8), _KERNEL)[np.rint(yi).astype(int),
                                                                    np.rint(xi).astype(int)] > 0)
        if keep.sum() * STRIDE_PX ** 2 < MIN_PIXELS:
            return None
        there = _local_mean(np.asarray(current[reach], np.float32), valid, xi, yi)
        ratio = there[keep] / np.maximum(self.here[keep], 1.0)
        X = np.concatenate([np.ones((int(keep.sum()), 1)), self.normals[keep]], axis=1)
        coef, *_ = np.linalg.lstsq(X, ratio.astype(np.float64), rcond=None)
        return coef


def relit(previous: np.ndarray, coef: np.ndarray, origin: tuple[int, int], relight: Relight) -> np.ndarray:
    """The `previous` box (grey, float32) scaled by a + b . n (held to SCALE_RANGE) where it shows
    the model's colour."""
    h, w = previous.shape
    box = (slice(origin[0], origin[0] + h), slice(origin[1], origin[1] + w))
    scale = np.clip(coef[0] + np.asarray(relight.normals[box], np.float32) @ np.asarray(coef[1:], np.float32),
                    *SCALE_RANGE)
    return np.where(np.asarray(relight.lit[box], bool), previous * scale, previous).astype(np.float32)
