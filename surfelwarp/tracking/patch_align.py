"""Sub-pixel refinement of colour pairs: each previous-image patch aligned to the current image by
an affine warp, with gain, offset and a shading slope projected out (patch_appearance.py;
inverse compositional Lucas-Kanade; Baker & Matthews, "Lucas-Kanade 20 years on", part 1 for the
warp, part 3 for projecting out appearance).

Why: SIFT's keypoint positions and DIS's flow fall short of the true image motion, along it. On
`orbit` (a still life under a moving camera) both measured 4-5 % short of a 1 px motion
between frames, the same way every frame, and the tracker added that up into camera drift.
The causes, and what takes each out here:
- DIS stops early and smooths across its pyramid: the alignment is iterated to convergence;
- a patch that turns or shears: the warp is affine (on an 8 degree turn, translation-only LK
  on 13 px patches is off by 0.4 px in the median, this by 0.07);
- at a depth edge a patch follows the mean of two motions: only the patch pixels within
  depth_tol_m of its centre's depth count;
- a lamp that moves with the camera changes the shading of every patch, and across it on a
  curved surface: both patches are normalised (gain, and a plane in x and y for the offset,
  where the patch's texture survives the plane: SLOPE_KEEPS). On `orbit` (a still life, the
  lamp on the camera) gain and offset alone left the model's fused colour pulling the camera:
  mean EPE 0.81 mm against 0.43 for depth alone, and 0.44 with the lamp's shading turned off.
  On a soft texture (a ball's) the plane took what resolves the shift (tests/tracking/
  test_features.py: pairs within 1 px 95 -> 90 %), hence the gate. `orbit` 0.75 mm with it,
  0.62 with the model's colour relit as well (relight.py).

`align` is the compiled kernel; patch_reference.align_reference the numpy reference the tests
compare it with.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.tracking.patch_appearance import SUMS, centred, normalise, plane_basis, project_out

MIN_SURFACE_SHARE = 0.3      # of the window's weight on the centre's surface, or the pair is not aligned
CONVERGED_PX = 1e-2          # the iterations stop at a smaller step
ACCEPT_PX = 0.05             # an alignment whose last step was longer has not converged
NOISE_GREY = 2.0             # image noise (8-bit grey levels) and the precision a patch's texture
PLAIN_PX = 0.2               # must allow against it (its weakest gradient direction), or it is plain
ALIGNED, UNALIGNED, FAILED, PLAIN = 1, 0, -1, 2    # status: aligned; no say (too little of its surface);
                                                  # textured, but nothing matches near the start; no
                                                  # say (too little texture)
SLOPE_KEEPS = 0.4            # the share of the weakest direction's texture the shading's slope must
                             # leave for it to be projected out (else gain and offset alone)
TRANSLATION_ITERS = 20       # iterations of the shift alone, at most, before the affine ones
PRIOR_MIN_PX = CONVERGED_PX  # a motion prior that moves no patch pixel farther than the alignment
                             # resolves is not applied


@dataclass(frozen=True)
class MotionPrior:
    """The predicted rigid motion from the previous camera to the current one (points of the
    previous camera in the current one's frame). A patch on a curved surface does not move as a
    plane: its pixels move by their depth (parallax), which an affine warp can only average, and
    where the displacement bulges (an object the camera orbits) the average falls short of the
    centre's. Measured started at the truth, without noise: `orbit`'s frame turned 1-2 degrees
    about a point behind its objects, the pairs' median 0.4-0.7 % short (of 1.2-2.4 px); a bump
    3 cm high on a wall 1 m away, the camera moved 10 cm sideways (tests), 0.029 px short of 31 px
    on its crown, 0.004 with the true motion as prior. Given a prior, each patch pixel is moved
    first by its own predicted displacement less its centre's, and the affine warp fits only
    what the prior left."""
    intrinsics: Intrinsics
    T_previous_to_current: np.ndarray

    def packed(self, origin: np.ndarray) -> np.ndarray:
        """R row by row, t, fx, fy and the principal point less `origin` (x, y), as the kernel reads it."""
        T, k = np.asarray(self.T_previous_to_current, np.float64), self.intrinsics
        return np.concatenate([T[:3, :3].ravel(), T[:3, 3], [k.fx, k.fy, k.cx - origin[0], k.cy - origin[1]]])


@numba.njit(cache=True, inline="always")
def _sample(image, x, y):
    """Bilinear, the border replicated."""
    h, w = image.shape
    x = min(max(x, 0.0), w - 1.0)
    y = min(max(y, 0.0), h - 1.0)
    x0, y0 = min(int(x), w - 2), min(int(y), h - 2)
    fx, fy = x - x0, y - y0
    top = image[y0, x0] * (1.0 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1.0 - fx) + image[y0 + 1, x0 + 1] * fx
    return top * (1.0 - fy) + bottom * fy


@numba.njit(cache=True, inline="always")
def _blend(image, r0, r1, c0, c1, fx, fy):
    top = image[r0, c0] * (1.0 - fx) + image[r0, c1] * fx
    return top * (1.0 - fy) + (image[r1, c0] * (1.0 - fx) + image[r1, c1] * fx) * fy


@numba.njit(cache=True, inline="always")
def _cell(x0, y0, h, w):
    """Rows and columns of the 2x2 pixels from (x0, y0), the border replicated."""
    return min(max(y0, 0), h - 1), min(max(y0 + 1, 0), h - 1), min(max(x0, 0), w - 1), min(max(x0 + 1, 0), w - 1)


@numba.njit(cache=True, inline="always")
def _nearest_value(image, x, y):
    return image[int(round(min(max(y, 0.0), image.shape[0] - 1.0))), int(round(min(max(x, 0.0), image.shape[1] - 1.0)))]


@numba.njit(cache=True, inline="always")
def _weakest(xx, xy, yy):
    """The smaller eigenvalue of the symmetric 2x2 [[xx, xy], [xy, yy]]: a patch's texture in its
    weakest direction."""
    return 0.5 * (xx + yy) - np.sqrt(0.25 * (xx - yy) ** 2 + xy * xy)


@numba.njit(cache=True, fastmath=SUMS)
def _align_one(previous, gx, gy, current, depth, ax, ay, bx, by, ox, oy, window, iters, depth_tol_m, max_shift_px,
               prior, result):
    S = len(ox)
    h, wd = previous.shape
    # the patch's offsets are whole pixels: one set of bilinear weights for all its samples
    fx, fy = ax - np.floor(ax), ay - np.floor(ay)
    T = np.empty(S)
    w = np.empty(S)
    inner = np.empty(S)      # w away from depth edges, where the texture is the surface's own
    SD = np.empty((6, S))
    zc = abs(_nearest_value(depth, ax, ay))      # negative beside a depth edge (off_edges)
    kept = total = 0.0
    for s in range(S):
        x, y = ax + ox[s], ay + oy[s]
        r0, r1, c0, c1 = _cell(int(np.floor(x)), int(np.floor(y)), h, wd)
        T[s] = _blend(previous, r0, r1, c0, c1, fx, fy)
        SD[2, s] = _blend(gx, r0, r1, c0, c1, fx, fy)
        SD[5, s] = _blend(gy, r0, r1, c0, c1, fx, fy)
        w[s] = inner[s] = window[s]
        if depth_tol_m > 0:
            z = _nearest_value(depth, x, y)
            if z == 0 or abs(abs(z) - zc) >= depth_tol_m:
                w[s] = 0.0
            inner[s] = w[s] if z > 0 else 0.0
        kept += w[s]
        total += window[s]
    if kept < MIN_SURFACE_SHARE * total:
        result[0], result[1], result[2] = bx, by, UNALIGNED
        return
    E = plane_basis(w, ox, oy)
    Tn = np.empty(S)
    sd = normalise(T, w, E, Tn)
    gxx = gxy = gyy = ixx = ixy = iyy = 0.0
    for s in range(S):
        tx, ty = SD[2, s], SD[5, s]
        gxx += w[s] * tx * tx
        gxy += w[s] * tx * ty
        gyy += w[s] * ty * ty
        ixx += inner[s] * tx * tx
        ixy += inner[s] * tx * ty
        iyy += inner[s] * ty * ty
        tx, ty = tx / sd, ty / sd
        SD[0, s], SD[1, s], SD[2, s] = tx * ox[s], tx * oy[s], tx
        SD[3, s], SD[4, s], SD[5, s] = ty * ox[s], ty * oy[s], ty
    weakest = _weakest(gxx, gxy, gyy)
    if _weakest(ixx, ixy, iyy) <= (NOISE_GREY / PLAIN_PX) ** 2:
        result[0], result[1], result[2] = bx, by, PLAIN
        return
    raw = SD.copy()
    H = project_out(SD, w, E, Tn)
    # The slope is taken out only where the patch's texture, not its shading, carries the shift:
    # on a soft texture (a ball's) the plane takes most of what resolves it, and gain and offset
    # alone are the better model there.
    if _weakest(H[2, 2] * sd * sd, H[2, 5] * sd * sd, H[5, 5] * sd * sd) < SLOPE_KEEPS * weakest:
        E[1, :], E[2, :] = 0.0, 0.0
        scale = sd / normalise(T, w, E, Tn)
        for k in range(6):
            for s in range(S):
                SD[k, s] = raw[k, s] * scale
        H = project_out(SD, w, E, Tn)
    primed = S if len(prior) > 0 else 0          # no prior: no per-sample shifts to hold
    dx, dy = np.zeros(primed), np.zeros(primed)
    shifted = _prior_shifts(depth, ax, ay, ox, oy, w, zc, prior, dx, dy) if primed > 0 else 0.0
    # translation alone first (its 2x2 block), then the whole affine warp from there: from a
    # start a pixel off, the six parameters at once can settle in a wrong minimum; where the
    # affine warp does not converge, the shift alone is the answer
    det = H[2, 2] * H[5, 5] - H[2, 5] * H[5, 2]
    Htinv = np.array([[H[5, 5], -H[2, 5]], [-H[5, 2], H[2, 2]]]) / det
    sx, sy, sstep = _iterate(current, w, E, Tn, SD, Htinv, False, bx, by, bx, by, ox, oy, TRANSLATION_ITERS,
                             max_shift_px, shifted, dx, dy)
    result[0], result[1], result[2] = bx, by, FAILED
    if sstep < ACCEPT_PX:
        ax_, ay_, astep = _iterate(current, w, E, Tn, SD, np.linalg.inv(H), True, sx, sy, bx, by, ox, oy, iters,
                                   max_shift_px, shifted, dx, dy)
        if astep < ACCEPT_PX:
            result[0], result[1], result[2] = ax_, ay_, ALIGNED
        else:
            result[0], result[1], result[2] = sx, sy, ALIGNED


@numba.njit(cache=True, inline="always")
def _predicted(x, y, z, prior):
    """Where the prior's rigid motion takes the previous camera's point at pixel (x, y), depth z:
    (u, v), NaN where it goes behind the camera. prior: R (row by row), t, fx, fy, cx, cy."""
    px, py = (x - prior[14]) / prior[12] * z, (y - prior[15]) / prior[13] * z
    qx = prior[0] * px + prior[1] * py + prior[2] * z + prior[9]
    qy = prior[3] * px + prior[4] * py + prior[5] * z + prior[10]
    qz = prior[6] * px + prior[7] * py + prior[8] * z + prior[11]
    if qz <= 1e-6:
        return np.nan, np.nan
    return prior[12] * qx / qz + prior[14], prior[13] * qy / qz + prior[15]


@numba.njit(cache=True)
def _prior_shifts(depth, ax, ay, ox, oy, w, zc, prior, dx, dy):
    """(dx, dy) of each patch sample on the centre's surface (w > 0): its displacement under the
    prior less the centre's, the part of the motion an affine warp cannot follow (the depth's
    relief). Returns the largest |dx| or |dy|; 0 (all shifts 0) where the centre has no depth or
    leaves the view, or where no sample moves by PRIOR_MIN_PX (a still camera's pose jitters by
    a tenth of a millimetre a frame)."""
    if zc <= 0:
        return 0.0
    cu, cv = _predicted(ax, ay, zc, prior)
    if not (np.isfinite(cu) and np.isfinite(cv)):
        return 0.0
    largest = 0.0
    for s in range(len(ox)):
        if w[s] > 0:
            x, y = ax + ox[s], ay + oy[s]
            u, v = _predicted(x, y, abs(_nearest_value(depth, x, y)), prior)
            if np.isfinite(u) and np.isfinite(v):
                dx[s], dy[s] = (u - x) - (cu - ax), (v - y) - (cv - ay)
                largest = max(largest, abs(dx[s]), abs(dy[s]))
    if largest < PRIOR_MIN_PX:
        dx[:] = 0.0
        dy[:] = 0.0
        return 0.0
    return largest


@numba.njit(cache=True, inline="always")
def _sample_shifted(current, tx, ty, a00, a01, a10, a11, ox, oy, dx, dy, reach, extra, I):
    """I[s]: the current image at the affine warp of sample s, moved by (dx[s], dy[s]) (unclamped
    where the warped patch's box lies inside, as _iterate's affine samples)."""
    h, wd = current.shape
    rx, ry = reach * (abs(a00) + abs(a01)) + extra, reach * (abs(a10) + abs(a11)) + extra
    if tx - rx >= 0 and tx + rx < wd - 1 and ty - ry >= 0 and ty + ry < h - 1:
        for s in range(len(ox)):
            x, y = tx + a00 * ox[s] + a01 * oy[s] + dx[s], ty + a10 * ox[s] + a11 * oy[s] + dy[s]
            x0, y0 = int(x), int(y)
            I[s] = _blend(current, y0, y0 + 1, x0, x0 + 1, x - x0, y - y0)
    else:
        for s in range(len(ox)):
            I[s] = _sample(current, tx + a00 * ox[s] + a01 * oy[s] + dx[s], ty + a10 * ox[s] + a11 * oy[s] + dy[s])


@numba.njit(cache=True, fastmath=SUMS)
def _iterate(current, w, E, Tn, SD, Hinv, affine, tx, ty, bx, by, ox, oy, iters, max_shift_px, shifted, dx, dy):
    """Inverse compositional steps from the shift (tx, ty); (tx, ty, last step), the step inf
    where the warp degenerates or runs farther than max_shift_px from (bx, by). `shifted` > 0:
    each sample s also moved by (dx[s], dy[s]), at most `shifted` px (the prior's, _prior_shifts)."""
    S = len(ox)
    a00, a01, a10, a11 = 1.0, 0.0, 0.0, 1.0
    I = np.empty(S)
    In = np.empty(S)
    err = np.empty(S)
    step = np.inf
    d = np.zeros(6)
    r = np.zeros(6)
    h, wd = current.shape
    reach = max(np.abs(ox).max(), np.abs(oy).max())
    for _ in range(iters):
        if shifted > 0:
            _sample_shifted(current, tx, ty, a00, a01, a10, a11, ox, oy, dx, dy, reach, shifted, I)
        elif affine:
            # Away from the border (the warped patch's box inside), no sample needs clamping:
            # the same values as _sample's, a third faster.
            rx, ry = reach * (abs(a00) + abs(a01)), reach * (abs(a10) + abs(a11))
            if tx - rx >= 0 and tx + rx < wd - 1 and ty - ry >= 0 and ty + ry < h - 1:
                for s in range(S):
                    x, y = tx + a00 * ox[s] + a01 * oy[s], ty + a10 * ox[s] + a11 * oy[s]
                    x0, y0 = int(x), int(y)
                    I[s] = _blend(current, y0, y0 + 1, x0, x0 + 1, x - x0, y - y0)
            else:
                for s in range(S):
                    I[s] = _sample(current, tx + a00 * ox[s] + a01 * oy[s], ty + a10 * ox[s] + a11 * oy[s])
        else:       # a shift: one set of bilinear weights for the whole patch
            fx, fy = tx - np.floor(tx), ty - np.floor(ty)
            for s in range(S):
                r0, r1, c0, c1 = _cell(int(np.floor(tx + ox[s])), int(np.floor(ty + oy[s])), h, wd)
                I[s] = _blend(current, r0, r1, c0, c1, fx, fy)
        centred(I, w, E, In)
        if affine:
            for s in range(S):
                err[s] = w[s] * (In[s] - Tn[s])
            for k in range(6):
                acc = 0.0
                for s in range(S):
                    acc += SD[k, s] * err[s]
                r[k] = acc
            for i in range(6):
                d[i] = 0.0
                for j in range(6):
                    d[i] += Hinv[i, j] * r[j]
        else:
            r2 = r5 = 0.0
            for s in range(S):
                e = w[s] * (In[s] - Tn[s])
                r2 += SD[2, s] * e
                r5 += SD[5, s] * e
            d[2] = Hinv[0, 0] * r2 + Hinv[0, 1] * r5
            d[5] = Hinv[1, 0] * r2 + Hinv[1, 1] * r5
        # W <- W o W(d)^-1
        b00, b01, b10, b11 = 1.0 + d[0], d[1], d[3], 1.0 + d[4]
        det = b00 * b11 - b01 * b10
        if abs(det) < 1e-9:
            return tx, ty, np.inf
        i00, i01, i10, i11 = b11 / det, -b01 / det, -b10 / det, b00 / det
        a00, a01, a10, a11 = a00 * i00 + a01 * i10, a00 * i01 + a01 * i11, a10 * i00 + a11 * i10, a10 * i01 + a11 * i11
        tx -= a00 * d[2] + a01 * d[5]
        ty -= a10 * d[2] + a11 * d[5]
        step = max(abs(d[2]), abs(d[5]))
        if (tx - bx) ** 2 + (ty - by) ** 2 > max_shift_px ** 2:
            return tx, ty, np.inf          # run away: no match near the start
        if step < CONVERGED_PX:
            break
    return tx, ty, step


@numba.njit(cache=True, parallel=True)
def _align(previous, gx, gy, current, depth, pa, pb, ox, oy, window, iters, depth_tol_m, max_shift_px, prior):
    out = np.empty((len(pa), 3))
    for i in numba.prange(len(pa)):
        _align_one(previous, gx, gy, current, depth, pa[i, 0], pa[i, 1], pb[i, 0], pb[i, 1], ox, oy, window, iters,
                   depth_tol_m, max_shift_px, prior, out[i])
    return out


def _patch(radius_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets x, y of a (2r+1)^2 patch and its Gaussian window (sigma 0.6 r)."""
    o = np.arange(-radius_px, radius_px + 1, dtype=np.float64)
    ox, oy = (v.ravel() for v in np.meshgrid(o, o))
    return ox, oy, np.exp(-(ox ** 2 + oy ** 2) / (2.0 * (0.6 * radius_px) ** 2))


def _gradients(image: np.ndarray, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    depth = cv2.CV_32F if dtype == np.float32 else cv2.CV_64F
    return cv2.Scharr(image, depth, 1, 0) / dtype(32.0), cv2.Scharr(image, depth, 0, 1) / dtype(32.0)


def off_edges(depth: np.ndarray, depth_tol_m: float) -> np.ndarray:
    """(H, W) float64 `depth` (metres, 0: none) negated at the pixels beside a depth edge: those
    whose 3x3 neighbours with depth span depth_tol_m or more. Their gradient (Scharr's 3x3)
    mixes the colours of both surfaces, so whether a patch has texture is judged without them:
    a plain limb before a textured wall had textured patches along its outline, aligned on the
    wall's texture. They still count in the alignment of a textured patch (left out there too,
    `fast-wall`'s ball lost the outline's contrast: moving EPE seeds 0-2 1.49 / 2.58 / 2.35 ->
    2.16 / 3.69 / 3.32 mm)."""
    z = np.asarray(depth, np.float32)
    kernel = np.ones((3, 3), np.uint8)
    span = cv2.dilate(z, kernel) - cv2.erode(np.where(z > 0, z, np.float32(np.inf)), kernel)
    d = np.asarray(depth, np.float64)
    return np.where(span < depth_tol_m, d, -d)


def align(previous_grey: np.ndarray, current_grey: np.ndarray, pa: np.ndarray, pb: np.ndarray, radius_px: int,
          depth: np.ndarray | None = None, depth_tol_m: float = 0.03, max_shift_px: float = 2.0, iters: int = 10,
          prior: MotionPrior | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) where each patch of `previous_grey` around pa (x, y) lies in `current_grey`,
    searched from pb (pb where not aligned), and (n,) int8 status: ALIGNED; PLAIN or UNALIGNED
    where the patch cannot say (too little texture; too little of it on its centre's surface);
    FAILED where it is textured yet converges to nothing within max_shift_px of pb. `depth`
    (H, W) metres of the previous image (0: none) keeps the patch to the pixels within
    depth_tol_m of its centre's depth; None: every pixel. `prior` (with `depth`): the predicted
    motion of the previous camera's points, whose relief the warp then follows (MotionPrior)."""
    if len(pa) == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int8)
    pa, pb = np.asarray(pa, np.float64), np.asarray(pb, np.float64)
    # Only the box the patches can reach is read: the gradients of the whole image cost more
    # than the alignment of a thousand pairs (6 ms at 640x480). Within the box's margin (the
    # patch at up to twice its size, plus the farthest shift) the samples are the same.
    h, w = np.shape(previous_grey)
    margin = 2 * radius_px + int(np.ceil(max_shift_px)) + 3
    ends = np.concatenate([pa, pb])
    lo = np.clip(np.floor(np.nanmin(ends, axis=0)).astype(np.int64) - margin, 0, [w - 1, h - 1])
    hi = np.clip(np.ceil(np.nanmax(ends, axis=0)).astype(np.int64) + margin + 1, lo + 2, [w, h])
    box = (slice(lo[1], hi[1]), slice(lo[0], hi[0]))
    previous = np.asarray(previous_grey[box], np.float32)     # 8-bit grey: exact in float32
    gx, gy = _gradients(previous, np.float32)
    use_depth = depth is not None
    depth = off_edges(depth[box], depth_tol_m) if use_depth else np.zeros((1, 1))
    ox, oy, window = _patch(radius_px)
    packed = np.zeros(0) if prior is None or not use_depth else prior.packed(lo)
    out = _align(previous, gx, gy, np.asarray(current_grey[box], np.float32), depth, pa - lo, pb - lo, ox, oy,
                 window, iters, depth_tol_m if use_depth else 0.0, max_shift_px, packed)
    return out[:, :2] + lo, out[:, 2].astype(np.int8)
