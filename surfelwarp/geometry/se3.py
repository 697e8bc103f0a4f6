"""Rigid transforms as 4x4 matrices and twists.

Twist order, fixed for the whole package: xi = (omega, v), rotation first.
exp(xi) = [[R, J v], [0, 1]] with R = exp([omega]x) and J the left Jacobian of SO(3).
Transforms are named by direction: T_a_to_b maps points in frame a to frame b.
All functions accept a leading batch dimension.
"""
from __future__ import annotations

import numpy as np

_SMALL = 1e-8


def skew(w: np.ndarray) -> np.ndarray:
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def point_jacobian(p: np.ndarray) -> np.ndarray:
    """(n, 3, 6) derivative of exp(xi) p by the twist xi = (omega, v) at xi = 0: (-[p]x, I)."""
    return np.concatenate([-skew(p), np.broadcast_to(np.eye(3), (len(p), 3, 3))], axis=-1)


def _coefficients(theta: np.ndarray):
    """sin(t)/t, (1-cos t)/t^2, (t - sin t)/t^3 with Taylor series near zero."""
    t2 = theta * theta
    small = theta < 1e-4
    ts = np.where(small, 1.0, theta)
    a = np.where(small, 1 - t2 / 6, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24, (1 - np.cos(ts)) / (ts * ts))
    c = np.where(small, 1 / 6 - t2 / 120, (ts - np.sin(ts)) / (ts ** 3))
    return a, b, c


def so3_exp(omega: np.ndarray) -> np.ndarray:
    omega = np.asarray(omega, dtype=np.float64)
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    a, b, _ = _coefficients(theta)
    W = skew(omega)
    return np.eye(3) + a * W + b * (W @ W)


def so3_log(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(cos)
    vee = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = np.sin(theta)
    near_pi = theta > np.pi - 1e-3
    scale = np.where(theta < 1e-6, 0.5 + theta ** 2 / 12, theta / (2 * np.where(np.abs(sin) < _SMALL, 1.0, sin)))
    omega = scale[..., None] * vee
    if np.any(near_pi):
        # Near pi the antisymmetric part vanishes; take the axis from the symmetric part.
        Rp = R[near_pi]
        B = (Rp + np.swapaxes(Rp, -1, -2)) / 2 - np.eye(3) * np.cos(theta[near_pi])[..., None, None]
        col = np.argmax(np.stack([B[..., 0, 0], B[..., 1, 1], B[..., 2, 2]], -1), axis=-1)
        axis = np.take_along_axis(B, col[..., None, None].repeat(3, -1), axis=-2)[..., 0, :]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        sign = np.where(np.sum(axis * vee[near_pi], -1) < 0, -1.0, 1.0)
        omega[near_pi] = axis * (sign * theta[near_pi])[..., None]
    return omega


def so3_left_jacobian(omega: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    _, b, c = _coefficients(theta)
    W = skew(omega)
    return np.eye(3) + b * W + c * (W @ W)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Twist (..., 6) = (omega, v) -> transform (..., 4, 4): so3_exp and so3_left_jacobian's
    products, their angle, coefficients and [omega]x^2 made once for both (a room's 10k node
    twists, ~3 times a frame: 3.6 -> 2.6 ms a call, the same bits)."""
    xi = np.asarray(xi, dtype=np.float64)
    omega = xi[..., :3]
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    a, b, c = _coefficients(theta)
    W = skew(omega)
    WW = W @ W
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = np.eye(3) + a * W + b * WW
    T[..., :3, 3] = ((np.eye(3) + b * W + c * WW) @ xi[..., 3:, None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    omega = so3_log(T[..., :3, :3])
    v = np.linalg.solve(so3_left_jacobian(omega), T[..., :3, 3:])[..., 0]
    return np.concatenate([omega, v], axis=-1)


def invert(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply one 4x4 transform to (N, 3) points, in their precision: float32 points stay
    float32 (upcasting 100k points to float64 cost several times the product itself)."""
    points = np.asarray(points)
    dtype = points.dtype if points.dtype in (np.float32, np.float64) else np.dtype(np.float64)
    T = np.asarray(T)
    out = points @ np.ascontiguousarray(T[:3, :3].T, dtype)
    for i in range(3):      # a column at a time: broadcasting a (3,) row over (N, 3) is ~3x slower
        out[:, i] += T[i, 3].astype(dtype)
    return out


def fit_rigid(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The rigid T minimising sum w |T source - target|^2 over (N, 3) point pairs (Kabsch)."""
    a, b = np.asarray(source, np.float64), np.asarray(target, np.float64)
    w = np.ones(len(a)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    ca, cb = w @ a, w @ b
    U, _, Vt = np.linalg.svd(((a - ca) * w[:, None]).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    T = np.eye(4)
    T[:3, :3] = Vt.T @ D @ U.T
    T[:3, 3] = cb - T[:3, :3] @ ca
    return T


MIN_INFORMATION = 1e-6     # fit_rigid_informed's floor, relative to the best-measured direction


def solve_measured(H: np.ndarray, g: np.ndarray, min_ratio: float) -> np.ndarray:
    """H^-1 g within the eigen-directions of the symmetric H above min_ratio of its largest
    eigenvalue; zero along the others (what the data does not measure is not moved)."""
    values, vectors = np.linalg.eigh(H)
    keep = values > min_ratio * max(values[-1], 0.0)
    return vectors[:, keep] @ (vectors[:, keep].T @ g / values[keep])


def fit_rigid_informed(source: np.ndarray, target: np.ndarray, information: np.ndarray,
                       iterations: int = 5) -> np.ndarray:
    """The rigid T minimising sum (T a - b)^T S (T a - b) over (N, 3) point pairs, each with an
    (N, 3, 3) positive semi-definite S: a pair counts along the directions its S measures only
    (a point that depth sees on a plane: along the plane's normal). A motion that no S measures
    (every point on one plane, sliding along it) is not in T, which fit_rigid, with S = w I,
    would take whole. Gauss-Newton from the identity about the information-weighted centroid;
    directions measured below MIN_INFORMATION of the best one count as unmeasured."""
    a, b = np.asarray(source, np.float64), np.asarray(target, np.float64)
    S = np.asarray(information, np.float64)
    w = np.trace(S, axis1=1, axis2=2)
    C = np.eye(4)
    if w.sum() > 0:
        C[:3, 3] = w @ a / w.sum()
    a, b = a - C[:3, 3], b - C[:3, 3]
    T = np.eye(4)
    for _ in range(iterations):
        p = transform_points(T, a)
        J = point_jacobian(p)
        SJ = np.matmul(S, J).reshape(-1, 6)
        xi = solve_measured(J.reshape(-1, 6).T @ SJ, SJ.T @ (b - p).reshape(-1), MIN_INFORMATION)
        T = se3_exp(xi) @ T
        if np.abs(xi).max() < 1e-6:      # converging quadratically: the next step would be ~1e-12
            break
    return C @ T @ invert(C)


def transform_surfels(T: np.ndarray, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions and normals moved by the rigid transform T, as float32."""
    R = np.asarray(T)[:3, :3].astype(np.float32)
    return (transform_points(T, np.asarray(points, np.float32)),
            np.asarray(normals, np.float32) @ R.T)
