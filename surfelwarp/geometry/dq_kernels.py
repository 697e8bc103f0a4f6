"""Compiled (numba) forms of the dual quaternion blend warp: per point, the blend of its k nodes
(with the antipodal fix), then the blended transform or its inverse applied to the point and its
normal, in one pass with no (N, 8) or (3, N) temporaries.

numpy computes the same in dual_quaternion.dq_blend_indexed / apply_components (the reference
the tests compare these with): a few dozen whole-array operations per chunk, each a pass over
memory. Fused, the warp of 275k points with normals takes 15-20 ms instead of ~55 ms.
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _blend_one(dqs, knn, weights, i, signed, b):
    """Blend of point i into b (8,), its signed weights into signed[i] (antipodal fix as
    dq_blend_indexed: against the real part of the node with the largest weight)."""
    k = knn.shape[1]
    ref = knn[i, 0]
    best = weights[i, 0]
    for s in range(1, k):
        if weights[i, s] > best:
            best, ref = weights[i, s], knn[i, s]
    for j in range(8):
        b[j] = 0.0
    for s in range(k):
        node = knn[i, s]
        dot = dqs[node, 0] * dqs[ref, 0] + dqs[node, 1] * dqs[ref, 1] + dqs[node, 2] * dqs[ref, 2] \
            + dqs[node, 3] * dqs[ref, 3]
        ws = -weights[i, s] if dot < 0.0 else weights[i, s]
        signed[i, s] = ws
        for j in range(8):
            b[j] += ws * dqs[node, j]


@numba.njit(cache=True, nogil=True)
def _rotate(w, x, y, z, c, w2, x2, y2, z2, px, py, pz):
    d = x2 * px + y2 * py + z2 * pz
    return (c * px + d * x + w2 * (y * pz - z * py),
            c * py + d * y + w2 * (z * px - x * pz),
            c * pz + d * z + w2 * (x * py - y * px))


@numba.njit(cache=True, nogil=True, inline="always")
def rotation_of(b, inverse):
    """The blend b's (8,) rotation as _rotate's first nine arguments and its translation (R,
    t of the normalised blend; with inverse the rotation is R^T, the translation still t)."""
    w, x, y, z, we, xe, ye, ze = b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]
    inv = 1.0 / (w * w + x * x + y * y + z * z)
    c = (w * w - x * x - y * y - z * z) * inv
    w2, x2, y2, z2 = 2.0 * inv * w, 2.0 * inv * x, 2.0 * inv * y, 2.0 * inv * z
    tx = w2 * xe - we * x2 + (y2 * ze - z2 * ye)
    ty = w2 * ye - we * y2 + (z2 * xe - x2 * ze)
    tz = w2 * ze - we * z2 + (x2 * ye - y2 * xe)
    if inverse:
        # W^-1 p = R^T (p - t): R^T turns by the conjugate rotation.
        x, y, z, x2, y2, z2 = -x, -y, -z, -x2, -y2, -z2
    return (w, x, y, z, c, w2, x2, y2, z2), (tx, ty, tz)


@numba.njit(cache=True, nogil=True, inline="always")
def _moved(R, t, inverse, px, py, pz):
    """The point moved by rotation_of's R, t: R p + t, or R^T (p - t) with inverse."""
    tx, ty, tz = t
    if inverse:
        return _rotate(*R, px - tx, py - ty, pz - tz)
    qx, qy, qz = _rotate(*R, px, py, pz)
    return qx + tx, qy + ty, qz + tz


@numba.njit(cache=True, nogil=True, inline="always")
def apply_blend(b, inverse, px, py, pz):
    """The point moved by the blend b (8,), or by its inverse."""
    R, t = rotation_of(b, inverse)
    return _moved(R, t, inverse, px, py, pz)


CHUNK = 4096    # points per parallel task: each task allocates its scratch once


@numba.njit(cache=True, nogil=True, parallel=True)
def _blend_apply(dqs, knn, weights, points, normals, with_normals, blends, signed, live, live_n, inverse):
    # Every point is computed alone, so the split over threads changes no bit of the output.
    n = knn.shape[0]
    for task in numba.prange((n + CHUNK - 1) // CHUNK):
        _blend_range(dqs, knn, weights, points, normals, with_normals, blends, signed, live, live_n, inverse,
                     task * CHUNK, min(n, (task + 1) * CHUNK))


@numba.njit(cache=True, nogil=True)
def _blend_range(dqs, knn, weights, points, normals, with_normals, blends, signed, live, live_n, inverse,
                 start, end):
    b = np.empty(8)
    for i in range(start, end):
        _blend_one(dqs, knn, weights, i, signed, b)
        for j in range(8):
            blends[i, j] = b[j]
        R, t = rotation_of(b, inverse)
        live[0, i], live[1, i], live[2, i] = _moved(R, t, inverse, points[0, i], points[1, i], points[2, i])
        if with_normals:
            live_n[0, i], live_n[1, i], live_n[2, i] = _rotate(*R, normals[0, i], normals[1, i], normals[2, i])


def blend_apply(dqs: np.ndarray, knn: np.ndarray, weights: np.ndarray, points: np.ndarray,
                normals: np.ndarray | None = None, inverse: bool = False):
    """Warp points and normals given as components (3, N) by the blend of their nodes' dual
    quaternions dqs (M, 8) with knn/weights (N, k). Returns the raw blends (N, 8), the signed
    weights (N, k) and the moved points and normals (3, N) (normals None if not given); with
    inverse, the blend's inverse is applied (reference from live positions)."""
    dqs = np.ascontiguousarray(dqs, np.float64)
    knn = np.ascontiguousarray(knn, np.int64)
    weights = np.ascontiguousarray(weights, np.float64)
    points = np.ascontiguousarray(points, np.float64)
    n, k = knn.shape
    if points.shape != (3, n) or weights.shape != (n, k):
        raise ValueError("points must be (3, N) and weights (N, k) for knn (N, k)")
    with_normals = normals is not None
    normals = np.ascontiguousarray(normals, np.float64) if with_normals else points
    blends, signed = np.empty((n, 8)), np.empty((n, k))
    live = np.empty((3, n))
    live_n = np.empty((3, n)) if with_normals else live
    _blend_apply(dqs, knn, weights, points, normals, with_normals, blends, signed, live, live_n, inverse)
    return blends, signed, live, (live_n if with_normals else None)


@numba.njit(cache=True, nogil=True)
def _dq_from_transforms(T, out):
    """dual_quaternion.dq_from_transform per transform, each operation in numpy's order (the
    same bits): Shepperd's quaternion of R, normalised, w >= 0, then the dual part 0.5 (0, t) q."""
    for i in range(T.shape[0]):
        m00, m01, m02 = T[i, 0, 0], T[i, 0, 1], T[i, 0, 2]
        m10, m11, m12 = T[i, 1, 0], T[i, 1, 1], T[i, 1, 2]
        m20, m21, m22 = T[i, 2, 0], T[i, 2, 1], T[i, 2, 2]
        tr = m00 + m11 + m22
        sq0, sq1, sq2, sq3 = 1 + tr, 1 + 2 * m00 - tr, 1 + 2 * m11 - tr, 1 + 2 * m22 - tr
        best, top = 0, sq0
        if sq1 > top:
            best, top = 1, sq1
        if sq2 > top:
            best, top = 2, sq2
        if sq3 > top:
            best, top = 3, sq3
        s = 2.0 * np.sqrt(max(top, 1e-300))
        a01, s01 = m01 - m10, m01 + m10
        a02, s02 = m02 - m20, m02 + m20
        a12, s12 = m12 - m21, m12 + m21
        if best == 0:
            w, x, y, z = s / 4, -a12 / s, a02 / s, -a01 / s
        elif best == 1:
            w, x, y, z = -a12 / s, s / 4, s01 / s, s02 / s
        elif best == 2:
            w, x, y, z = a02 / s, s01 / s, s / 4, s12 / s
        else:
            w, x, y, z = -a01 / s, s02 / s, s12 / s, s / 4
        norm = np.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        if w < 0:
            w, x, y, z = -w, -x, -y, -z
        tx, ty, tz = T[i, 0, 3], T[i, 1, 3], T[i, 2, 3]
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = w, x, y, z
        out[i, 4] = 0.5 * (0.0 * w - tx * x - ty * y - tz * z)
        out[i, 5] = 0.5 * (0.0 * x + tx * w + ty * z - tz * y)
        out[i, 6] = 0.5 * (0.0 * y - tx * z + ty * w + tz * x)
        out[i, 7] = 0.5 * (0.0 * z + tx * y - ty * x + tz * w)


def dq_from_transforms(T: np.ndarray) -> np.ndarray:
    """(M, 8) dual_quaternion.dq_from_transform of rigid transforms (M, 4, 4), compiled: the
    same bits, ~20x faster on a room's 10k nodes."""
    T = np.ascontiguousarray(T, np.float64)
    out = np.empty((len(T), 8))
    _dq_from_transforms(T, out)
    return out
