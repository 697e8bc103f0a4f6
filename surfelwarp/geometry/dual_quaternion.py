"""Quaternions and dual quaternions for blending rigid transforms (Kavan et al.; SurfelWarp Eq. 1).

Quaternions are (..., 4) arrays in (w, x, y, z) order, scalar first. A dual quaternion is an
(..., 8) array (real part w, x, y, z, then dual part w, x, y, z); the rigid transform (R, t)
is q_r + eps * 0.5 * (0, t) * q_r with q_r the rotation quaternion.

Blended dual quaternions are not unit. Every function that turns one back into a transform
uses R = rotation of q_r / |q_r| and t = vector part of 2 q_d conj(q_r) / |q_r|^2, so the
dual part's component along q_r (which a blend introduces) is ignored and callers never need
to normalise first. All functions are batched over leading dimensions.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions with w >= 0.

    Each candidate formula divides by the component it solves for; taking the candidate whose
    component is largest (Shepperd) stays accurate at rotations near pi, where w -> 0.
    """
    R = np.asarray(R, np.float64)
    m = {(i, j): R[..., i, j] for i in range(3) for j in range(3)}
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    # 4 * component^2 for w, x, y, z; pick the largest.
    sq = np.stack([1 + tr, 1 + 2 * m[0, 0] - tr, 1 + 2 * m[1, 1] - tr, 1 + 2 * m[2, 2] - tr], -1)
    best = np.argmax(sq, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(sq, best[..., None], -1)[..., 0], 1e-300))
    a01, s01 = m[0, 1] - m[1, 0], m[0, 1] + m[1, 0]
    a02, s02 = m[0, 2] - m[2, 0], m[0, 2] + m[2, 0]
    a12, s12 = m[1, 2] - m[2, 1], m[1, 2] + m[2, 1]
    cands = np.stack([
        np.stack([s / 4, -a12 / s, a02 / s, -a01 / s], -1),
        np.stack([-a12 / s, s / 4, s01 / s, s02 / s], -1),
        np.stack([a02 / s, s01 / s, s / 4, s12 / s], -1),
        np.stack([-a01 / s, s02 / s, s12 / s, s / 4], -1)], -2)
    q = np.take_along_axis(cands, best[..., None, None].repeat(4, -1), -2)[..., 0, :]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4), any non-zero norm -> rotation matrices (..., 3, 3)."""
    q = np.asarray(q, np.float64)
    w, x, y, z = np.moveaxis(q, -1, 0)
    s = 2.0 / np.sum(q * q, axis=-1)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - s * (y * y + z * z)
    R[..., 0, 1] = s * (x * y - w * z)
    R[..., 0, 2] = s * (x * z + w * y)
    R[..., 1, 0] = s * (x * y + w * z)
    R[..., 1, 1] = 1 - s * (x * x + z * z)
    R[..., 1, 2] = s * (y * z - w * x)
    R[..., 2, 0] = s * (x * z - w * y)
    R[..., 2, 1] = s * (y * z + w * x)
    R[..., 2, 2] = 1 - s * (x * x + y * y)
    return R


def _pure(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], axis=-1)


def dq_from_transform(T: np.ndarray) -> np.ndarray:
    """Rigid transforms (..., 4, 4) -> unit dual quaternions (..., 8), real part with w >= 0."""
    T = np.asarray(T, np.float64)
    real = quat_from_matrix(T[..., :3, :3])
    dual = 0.5 * quat_multiply(_pure(T[..., :3, 3]), real)
    return np.concatenate([real, dual], axis=-1)


def dq_translation(dq: np.ndarray) -> np.ndarray:
    """Translation (..., 3) of (not necessarily unit) dual quaternions."""
    dq = np.asarray(dq, np.float64)
    real, dual = dq[..., :4], dq[..., 4:]
    n2 = np.sum(real * real, axis=-1, keepdims=True)
    return 2.0 * quat_multiply(dual, quat_conjugate(real))[..., 1:] / n2


def dq_to_transform(dq: np.ndarray) -> np.ndarray:
    """Dual quaternions (..., 8), any non-zero real part -> rigid transforms (..., 4, 4)."""
    dq = np.asarray(dq, np.float64)
    T = np.zeros(dq.shape[:-1] + (4, 4))
    T[..., :3, :3] = quat_to_matrix(dq[..., :4])
    T[..., :3, 3] = dq_translation(dq)
    T[..., 3, 3] = 1.0
    return T


def dq_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Product a * b, the dual quaternion of the transform T_a @ T_b."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    real = quat_multiply(a[..., :4], b[..., :4])
    dual = quat_multiply(a[..., :4], b[..., 4:]) + quat_multiply(a[..., 4:], b[..., :4])
    return np.concatenate([real, dual], axis=-1)


def dq_normalize(dq: np.ndarray) -> np.ndarray:
    """The unit dual quaternion of the same transform: real part unit, dual part orthogonal to it."""
    dq = np.asarray(dq, np.float64)
    real = dq[..., :4] / np.linalg.norm(dq[..., :4], axis=-1, keepdims=True)
    dual = 0.5 * quat_multiply(_pure(dq_translation(dq)), real)
    return np.concatenate([real, dual], axis=-1)


def dq_blend(dqs: np.ndarray, weights: np.ndarray, normalize: bool = True) -> np.ndarray:
    """Dual quaternion blending (DQB): (..., k, 8) with weights (..., k) -> (..., 8).

    q and -q are the same transform; each input is first flipped into the hemisphere of the one
    with the largest weight (the antipodal fix), otherwise blends of nearby rotations could cancel.
    normalize=False returns the raw weighted sum, which every function here accepts as it is.
    """
    dqs, weights = np.asarray(dqs, np.float64), np.asarray(weights, np.float64)
    pivot = np.argmax(weights, axis=-1)[..., None, None]
    ref = np.take_along_axis(dqs[..., :4], pivot.repeat(4, -1), -2)
    sign = np.where(np.einsum("...i,...i->...", dqs[..., :4], ref) < 0, -1.0, 1.0)
    blended = np.einsum("...k,...ki->...i", weights * sign, dqs)
    return dq_normalize(blended) if normalize else blended


def dq_blend_indexed(dqs: np.ndarray, knn: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dq_blend(dqs[knn], weights, normalize=False) without the (N, k, 8) gather.

    dqs (M, 8), knn (N, k) indices into it, weights (N, k). Returns the raw blends (N, 8) and
    the signed weights (N, k) they were summed with (the antipodal fix folded into the weight),
    so that blend = sum_s signed[:, s] * dqs[knn[:, s]].
    """
    dqs = np.asarray(dqs, np.float64)
    knn = np.asarray(knn, np.int64)
    signed = np.array(weights, np.float64)
    n, k = knn.shape
    # Two rotations turning by less than 90 degrees each are less than 180 degrees apart, so
    # their real parts have a positive dot product and no sign fix is needed: only the points
    # that have a node turning further (margin for rounding) are checked.
    real = dqs[:, :4]
    calm = real[:, 0] > 0.7072 * np.sqrt(np.einsum("ij,ij->i", real, real))
    check = np.flatnonzero(~np.all(calm[knn], axis=1)) if n else np.zeros(0, np.int64)
    if len(check):
        sub = knn[check]
        ref = real[sub[np.arange(len(check)), np.argmax(signed[check], axis=1)]]
        flip = np.einsum("csi,ci->cs", real[sub], ref) < 0
        signed[check] = np.where(flip, -signed[check], signed[check])
    # The blend as a sparse (N, M) times dense (M, 8) product: no per-slot gathers.
    K = sp.csr_matrix((signed.reshape(-1), knn.reshape(-1), np.arange(n + 1) * k), shape=(n, len(dqs)))
    return K @ dqs, signed


def _components(a: np.ndarray) -> np.ndarray:
    """(..., c) -> contiguous (c, ...) so that every component is one flat run in memory."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(a, np.float64), -1, 0))


def dq_apply(dq: np.ndarray, points: np.ndarray | None = None,
             normals: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(..., 8) dual quaternions (any non-zero real part) applied to (..., 3) points and normals.

    Same values as dq_to_transform, without building 4x4 matrices. Either input may be None
    (then so is its output).
    """
    p, n = apply_components(_components(dq), None if points is None else _components(points),
                            None if normals is None else _components(normals))
    return (None if p is None else np.stack(p, axis=-1)), (None if n is None else np.stack(n, axis=-1))


def apply_components(dq, points=None, normals=None):
    """dq_apply on components: dq the 8 arrays w, x, y, z, w', x', y', z' (any broadcastable
    shapes), points/normals 3 arrays each or None; returns lists of 3 arrays (or None).

    The rotation acts as (w^2 - |v|^2) x + 2 (v . x) v + 2 w v x x, over |q_r|^2, with
    q_r = (w, v); the translation is the vector part of 2 q_d conj(q_r) / |q_r|^2.
    """
    w, x, y, z, we, xe, ye, ze = dq
    inv = 1.0 / (w * w + x * x + y * y + z * z)
    c = (w * w - x * x - y * y - z * z) * inv
    w2, x2, y2, z2 = (2.0 * inv) * w, (2.0 * inv) * x, (2.0 * inv) * y, (2.0 * inv) * z

    def rotate(v):
        px, py, pz = v
        d = x2 * px + y2 * py + z2 * pz
        return [c * px + d * x + w2 * (y * pz - z * py),
                c * py + d * y + w2 * (z * px - x * pz),
                c * pz + d * z + w2 * (x * py - y * px)]

    out_p = out_n = None
    if points is not None:
        out_p = rotate(points)
        out_p[0] += w2 * xe - we * x2 + (y2 * ze - z2 * ye)
        out_p[1] += w2 * ye - we * y2 + (z2 * xe - x2 * ze)
        out_p[2] += w2 * ze - we * z2 + (x2 * ye - y2 * xe)
    if normals is not None:
        out_n = rotate(normals)
    return out_p, out_n


def dq_rotate(dq: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Rotate (..., 3) vectors (normals) by the rotation of (..., 8) dual quaternions."""
    return dq_apply(dq, None, vectors)[1]


def dq_transform_points(dq: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply (..., 8) dual quaternions to (..., 3) points."""
    return dq_apply(dq, points)[0]
