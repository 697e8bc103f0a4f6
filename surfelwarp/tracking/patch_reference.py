"""The numpy reference of patch_align's kernel: every pair at once, as the tests compare it with
`align` (same warp, appearance projection, stopping rules and motion prior)."""
from __future__ import annotations

import numpy as np

from surfelwarp.tracking.features import bilinear
from surfelwarp.tracking.patch_align import (ACCEPT_PX, ALIGNED, CONVERGED_PX, FAILED, MIN_SURFACE_SHARE, NOISE_GREY,
                                             PLAIN, PLAIN_PX, PRIOR_MIN_PX, SLOPE_KEEPS, TRANSLATION_ITERS, UNALIGNED,
                                             MotionPrior, _gradients, _patch)


def _nearest(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h, w = image.shape
    return image[np.rint(np.clip(y, 0, h - 1)).astype(np.int64), np.rint(np.clip(x, 0, w - 1)).astype(np.int64)]


def steepest_descent(image: np.ndarray, pa: np.ndarray, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
    """(n, S, 6): the derivative of the image sampled at pa + A (ox, oy) + t by the warp's
    parameters (A - I row by row, interleaved with t: a00, a01, tx, a10, a11, ty) at A = I, t = 0."""
    X, Y = pa[:, :1] + ox, pa[:, 1:] + oy
    gx, gy = (bilinear(g, X, Y) for g in _gradients(np.asarray(image, np.float64)))
    return np.stack([gx * ox, gx * oy, gx, gy * ox, gy * oy, gy], -1)


def align_reference(previous_grey: np.ndarray, current_grey: np.ndarray, pa: np.ndarray, pb: np.ndarray,
                    radius_px: int, depth: np.ndarray | None = None, depth_tol_m: float = 0.03,
                    max_shift_px: float = 2.0, iters: int = 10, prior: MotionPrior | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """`align` in numpy, all pairs at once (the reference its tests compare it with)."""
    previous, current = np.asarray(previous_grey, np.float64), np.asarray(current_grey, np.float64)
    pa, pb = np.asarray(pa, np.float64), np.asarray(pb, np.float64)
    ox, oy, window = _patch(radius_px)
    X, Y = pa[:, :1] + ox, pa[:, 1:] + oy
    w = np.repeat(window[None], len(pa), 0)
    shifts = np.zeros((2,) + X.shape)
    inner = w      # w away from depth edges (off_edges): the texture test's
    if depth is not None:
        depth = _off_edges(np.asarray(depth, np.float64), depth_tol_m)
        signed = _nearest(depth, X, Y)
        z, zc = np.abs(signed), np.abs(_nearest(depth, pa[:, 0], pa[:, 1]))[:, None]
        w = w * ((z > 0) & (np.abs(z - zc) < depth_tol_m))
        inner = w * (signed > 0)
        if prior is not None:
            shifts = _prior_shifts_reference(prior, X, Y, z, pa, zc, w)
    gradients = steepest_descent(previous, pa, ox, oy)

    def weakest_texture(weight):
        G = np.einsum("ns,nsi,nsj->nij", weight, gradients[..., [2, 5]], gradients[..., [2, 5]])
        return np.linalg.eigvalsh(G)[:, 0]

    weakest = weakest_texture(w)
    textured = weakest_texture(inner) > (NOISE_GREY / PLAIN_PX) ** 2
    basis = _plane_basis(w, ox, oy)
    Tn, sd, SD, H = _projected(previous, X, Y, w, basis, gradients)
    # where the slope leaves less than SLOPE_KEEPS of the weakest direction's texture: gain and
    # offset alone
    kept = np.linalg.eigvalsh(H[:, [2, 5]][:, :, [2, 5]] * sd[:, :, None] ** 2)[:, 0] >= SLOPE_KEEPS * weakest
    basis = np.where(kept[:, None, None], basis, basis * np.array([1.0, 0.0, 0.0])[:, None])
    Tn, sd, SD, H = _projected(previous, X, Y, w, basis, gradients)
    common = (current, w, basis, Tn, SD, pb, ox, oy, shifts, max_shift_px)
    shift, shift_step = _iterate_reference(*common, np.linalg.inv(H[:, [2, 5]][:, :, [2, 5]]), False, pb,
                                           TRANSLATION_ITERS)
    warped, warped_step = _iterate_reference(*common, np.linalg.inv(H), True, shift, iters)
    surface = w.sum(1) >= MIN_SURFACE_SHARE * window.sum()
    aligned = surface & textured & (shift_step < ACCEPT_PX)
    moved = np.where((aligned & (warped_step < ACCEPT_PX))[:, None], warped, np.where(aligned[:, None], shift, pb))
    status = np.where(aligned, ALIGNED, np.where(surface & textured, FAILED, np.where(surface, PLAIN, UNALIGNED)))
    return moved, status.astype(np.int8)


def _off_edges(depth: np.ndarray, depth_tol_m: float) -> np.ndarray:
    """Negated where the depths of a pixel's 3x3 neighbours (those with depth) span depth_tol_m
    or more."""
    around = np.lib.stride_tricks.sliding_window_view(np.pad(depth, 1, mode="edge"), (3, 3))
    high = np.where(around > 0, around, -np.inf).max(axis=(-2, -1))
    low = np.where(around > 0, around, np.inf).min(axis=(-2, -1))
    return np.where(high - low < depth_tol_m, depth, -depth)


def _projected(previous, X, Y, w, basis, gradients):
    """The template normalised off the basis, its scale, the steepest descent images projected off
    the basis and the template, their Gauss-Newton matrix."""
    Tn, sd = _normalised(bilinear(previous, X, Y), w, basis)
    SD = gradients / sd[..., None]
    SD = np.stack([_off_plane(SD[..., k], w, basis) for k in range(6)], -1)
    along = (w[..., None] * SD * Tn[..., None]).sum(1) / np.maximum((w * Tn * Tn).sum(1), 1e-12)[:, None]
    SD -= along[:, None, :] * Tn[..., None]
    return Tn, sd, SD, np.einsum("ns,nsi,nsj->nij", w, SD, SD) + 1e-6 * np.eye(6)


def _plane_basis(w: np.ndarray, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
    """(n, 3, S): 1, x and y over each pair's patch, orthonormal under its weights (Gram-Schmidt,
    as the kernel)."""
    E = np.repeat(np.stack(np.broadcast_arrays(np.ones_like(ox), ox, oy))[None], len(w), 0).astype(np.float64)
    for k in range(3):
        for j in range(k):
            E[:, k] -= (w * E[:, k] * E[:, j]).sum(1)[:, None] * E[:, j]
        norm = np.sqrt((w * E[:, k] ** 2).sum(1))[:, None]
        E[:, k] = np.where(norm > 1e-9, E[:, k] / np.maximum(norm, 1e-300), 0.0)
    return E


def _off_plane(v: np.ndarray, w: np.ndarray, E: np.ndarray) -> np.ndarray:
    """(n, S) v less each row's weighted least-squares plane over the patch."""
    out = np.array(v, np.float64)
    for k in range(3):
        out -= (w * out * E[:, k]).sum(1)[:, None] * E[:, k]
    return out


def _normalised(v: np.ndarray, w: np.ndarray, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sw = np.maximum(w.sum(1, keepdims=True), 1e-12)
    r = _off_plane(v, w, basis)
    sd = np.maximum(np.sqrt((w * r ** 2).sum(1, keepdims=True) / sw), 1e-6)
    return r / sd, sd


def _centred(v: np.ndarray, w: np.ndarray, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(v - mean) / std of v less its plane: the kernel's current patch (its plane moves no step)."""
    sw = np.maximum(w.sum(1, keepdims=True), 1e-12)
    m = (w * v).sum(1, keepdims=True) / sw
    sd = np.maximum(np.sqrt((w * _off_plane(v, w, basis) ** 2).sum(1, keepdims=True) / sw), 1e-6)
    return (v - m) / sd, sd


def _prior_shifts_reference(prior: MotionPrior, X, Y, z, pa, zc, w) -> np.ndarray:
    """_prior_shifts for every pair at once: (2, n, S)."""
    k, T = prior.intrinsics, np.asarray(prior.T_previous_to_current, np.float64)

    def predicted(x, y, depth):
        p = np.stack([(x - k.cx) / k.fx * depth, (y - k.cy) / k.fy * depth, depth], -1)
        q = p @ T[:3, :3].T + T[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([k.fx * q[..., 0] / q[..., 2] + k.cx, k.fy * q[..., 1] / q[..., 2] + k.cy])
        return np.where(q[..., 2] > 1e-6, uv, np.nan)

    centre = predicted(pa[:, :1], pa[:, 1:], zc) - np.stack([pa[:, :1], pa[:, 1:]])
    shifts = predicted(X, Y, z) - np.stack([X, Y]) - centre
    usable = (w > 0) & np.isfinite(shifts).all(0) & (zc > 0) & np.isfinite(centre).all(0)
    shifts = np.where(usable, shifts, 0.0)
    return np.where(np.abs(shifts).max(axis=(0, 2))[:, None] < PRIOR_MIN_PX, 0.0, shifts)


def _iterate_reference(current, w, basis, Tn, SD, pb, ox, oy, shifts, max_shift_px, Hinv, affine, start, iters):
    """_iterate for every pair at once: (n, 2) shifts and (n,) last steps."""
    n = len(start)
    A, t = np.repeat(np.eye(2)[None], n, 0), np.array(start, np.float64)
    step, active = np.full(n, np.inf), np.ones(n, bool)
    for _ in range(iters):
        i = np.flatnonzero(active)
        if len(i) == 0:
            break
        In, _ = _centred(bilinear(current, t[i, :1] + A[i, 0, :1] * ox + A[i, 0, 1:] * oy + shifts[0, i],
                                     t[i, 1:] + A[i, 1, :1] * ox + A[i, 1, 1:] * oy + shifts[1, i]), w[i], basis[i])
        r = np.einsum("nsj,ns->nj", SD[i], w[i] * (In - Tn[i]))
        d = np.zeros((len(i), 6))
        if affine:
            d = np.einsum("nij,nj->ni", Hinv[i], r)
        else:
            d[:, [2, 5]] = np.einsum("nij,nj->ni", Hinv[i], r[:, [2, 5]])
        B = np.stack([np.stack([1 + d[:, 0], d[:, 1]], -1), np.stack([d[:, 3], 1 + d[:, 4]], -1)], 1)
        degenerate = np.abs(np.linalg.det(B)) < 1e-9
        B[degenerate] = np.eye(2)
        A[i] = A[i] @ np.linalg.inv(B)
        t[i] -= np.where(degenerate[:, None], 0.0, np.einsum("nij,nj->ni", A[i], d[:, [2, 5]]))
        step[i] = np.abs(d[:, [2, 5]]).max(1)
        away = np.linalg.norm(t[i] - pb[i], axis=1) > max_shift_px
        step[i[degenerate | away]] = np.inf
        active[i[degenerate | away | (step[i] < CONVERGED_PX)]] = False
    return t, step
