"""The exact derivative of the dual quaternion blend (DQB) warp of a surfel by its nodes' twists.

Each node has a twist xi_j = (omega, v) that left-composes its node-local transform,
L_j <- exp(xi_j) L_j, i.e. x_live <- p_j + exp(xi_j) (x_live - p_j): the update turns the live
points of node j about the world point p_j, then shifts them by v. The Jacobian of a
point-to-plane residual n . (W(v) v - d) is the exact derivative of the blend (not a linear-blend
approximation), so it matches finite differences of the true residual at any field. It factors as
J[c, s] = signed[c, s] D[knn[c, s]] rows[c]: the node's 6x8 twist derivative D times the pair's
8-vector derivative by the blend.
"""
from __future__ import annotations

import numba
import numpy as np

from surfelwarp.deform.warp_field import WarpField, warp
from surfelwarp.geometry.dual_quaternion import _components, dq_blend_indexed, dq_multiply


def data_residuals(field: WarpField, ref_points: np.ndarray, knn: np.ndarray, weights: np.ndarray,
                   target_points: np.ndarray, target_normals: np.ndarray) -> np.ndarray:
    """(C,) n . (W(v) v - d) with the true dual quaternion warp."""
    live, _ = warp(np.asarray(ref_points, np.float64), None, knn, weights, field)
    return np.einsum("ij,ij->i", np.asarray(target_normals, np.float64), live - target_points)


def residual_rows(b, x, n) -> np.ndarray:
    """(C, 8) derivative of n . y(b) with respect to the 8 entries of the unnormalised blend b,
    where y(b) = [vec(b0 x b0*) + 2 vec(be b0*)] / |b0|^2 is the blended transform applied to x.

    With b0 = (w, v), be = (w', v'): |b0|^2 n . y = F = (w^2 - |v|^2) n.x + 2 (v.x)(v.n)
    + 2 w n.(v x x) + 2 w n.v' - 2 w' n.v + 2 n.(v x v'), differentiated by hand (no quaternion
    products per entry); the quotient rule adds -2 (n . y) (w, v). b (8, C), x and n (3, C)
    are given as components.
    """
    w, vx, vy, vz, we, ex, ey, ez = b
    px, py, pz = x
    nx, ny, nz = n
    inv = 1.0 / (w * w + vx * vx + vy * vy + vz * vz)
    nx_dot = nx * px + ny * py + nz * pz                       # n . x
    vx_dot = vx * px + vy * py + vz * pz                       # v . x
    vn_dot = vx * nx + vy * ny + vz * nz                       # v . n
    ne_dot = nx * ex + ny * ey + nz * ez                       # n . v'
    xn = (py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx)      # x x n
    en = (ey * nz - ez * ny, ez * nx - ex * nz, ex * ny - ey * nx)      # v' x n
    nv = (ny * vz - nz * vy, nz * vx - nx * vz, nx * vy - ny * vx)      # n x v
    v = (vx, vy, vz)
    vxx_n = vx * xn[0] + vy * xn[1] + vz * xn[2]               # n . (v x x) = v . (x x n)
    ven = vx * en[0] + vy * en[1] + vz * en[2]                 # n . (v x v') = v . (v' x n)
    F = ((w * w - vx * vx - vy * vy - vz * vz) * nx_dot + 2 * vx_dot * vn_dot + 2 * w * vxx_n
         + 2 * w * ne_dot - 2 * we * vn_dot + 2 * ven)
    s = F * inv                                                # n . y
    out = np.empty((8,) + w.shape)
    out[0] = (2 * w * nx_dot + 2 * vxx_n + 2 * ne_dot - 2 * w * s) * inv
    for i, (ni, pi) in enumerate(zip((nx, ny, nz), (px, py, pz))):
        out[1 + i] = (2 * (vn_dot * pi + vx_dot * ni + w * xn[i] - we * ni + en[i] - (nx_dot + s) * v[i])) * inv
        out[5 + i] = 2 * (w * ni + nv[i]) * inv
    out[4] = -2 * vn_dot * inv
    return np.ascontiguousarray(out.T)


@numba.njit(cache=True, nogil=True)
def residual_row(b, px, py, pz, nx, ny, nz, out):
    """residual_rows of one pair (b (8,), x and n as scalars) into out (8,), compiled: the
    same expressions, for the assembly kernel."""
    w, vx, vy, vz, we, ex, ey, ez = b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]
    inv = 1.0 / (w * w + vx * vx + vy * vy + vz * vz)
    nx_dot = nx * px + ny * py + nz * pz
    vx_dot = vx * px + vy * py + vz * pz
    vn_dot = vx * nx + vy * ny + vz * nz
    ne_dot = nx * ex + ny * ey + nz * ez
    xn0, xn1, xn2 = py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx
    en0, en1, en2 = ey * nz - ez * ny, ez * nx - ex * nz, ex * ny - ey * nx
    nv0, nv1, nv2 = ny * vz - nz * vy, nz * vx - nx * vz, nx * vy - ny * vx
    vxx_n = vx * xn0 + vy * xn1 + vz * xn2
    ven = vx * en0 + vy * en1 + vz * en2
    F = ((w * w - vx * vx - vy * vy - vz * vz) * nx_dot + 2 * vx_dot * vn_dot + 2 * w * vxx_n
         + 2 * w * ne_dot - 2 * we * vn_dot + 2 * ven)
    s = F * inv
    out[0] = (2 * w * nx_dot + 2 * vxx_n + 2 * ne_dot - 2 * w * s) * inv
    out[1] = (2 * (vn_dot * px + vx_dot * nx + w * xn0 - we * nx + en0 - (nx_dot + s) * vx)) * inv
    out[2] = (2 * (vn_dot * py + vx_dot * ny + w * xn1 - we * ny + en1 - (nx_dot + s) * vy)) * inv
    out[3] = (2 * (vn_dot * pz + vx_dot * nz + w * xn2 - we * nz + en2 - (nx_dot + s) * vz)) * inv
    out[4] = -2 * vn_dot * inv
    out[5] = 2 * (w * nx + nv0) * inv
    out[6] = 2 * (w * ny + nv1) * inv
    out[7] = 2 * (w * nz + nv2) * inv


def twist_dual_quaternions(field: WarpField, q: np.ndarray | None = None) -> np.ndarray:
    """(M, 6, 8): derivative of node j's world dual quaternion with respect to its twist.

    L_j <- exp(xi) L_j is the world motion G_j <- exp(xi') G_j with xi' = (omega, v + p_j x omega),
    and d(exp(xi') G_j) = (0, omega'/2) + eps (0, v'/2), times the dual quaternion of G_j.
    Compiled (twist_dual_quaternions_reference is the numpy form, to the bit): numpy's products
    of the (M, 6, 8) derivatives took ~11 ms a call on a room's 9k nodes.
    """
    q = field.dual_quaternions() if q is None else q
    out = np.empty((len(q), 6, 8))
    _twist_dual_quaternions(np.ascontiguousarray(q, np.float64), np.ascontiguousarray(field.nodes, np.float64), out)
    return out


def twist_dual_quaternions_reference(field: WarpField, q: np.ndarray | None = None) -> np.ndarray:
    """twist_dual_quaternions in numpy: the derivatives as dual quaternions times q."""
    q = field.dual_quaternions() if q is None else q
    p = field.nodes.astype(np.float64)
    m = len(q)
    delta = np.zeros((m, 6, 8))
    for a in range(3):
        e = np.zeros(3)
        e[a] = 1.0
        delta[:, a, 1 + a] = 0.5
        delta[:, a, 5:] = 0.5 * np.cross(p, e)
        delta[:, 3 + a, 5 + a] = 0.5
    return dq_multiply(delta, q[:, None, :])


@numba.njit(cache=True, nogil=True, inline="always")
def _quat_multiply(a0, a1, a2, a3, b0, b1, b2, b3):
    """quat_multiply's sums, in its order."""
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3, a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1, a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


@numba.njit(cache=True, nogil=True)
def _twist_dual_quaternions(q, p, out):
    """The reference's products term by term, zeros included (0 * x is not 0 for x inf or NaN,
    and the signs of zeros follow the same sums)."""
    d, e = np.zeros(8), np.eye(3)
    for j in range(len(q)):
        p0, p1, p2 = p[j, 0], p[j, 1], p[j, 2]
        for a in range(6):
            d[:] = 0.0
            if a < 3:
                d[1 + a] = 0.5
                e0, e1, e2 = e[a, 0], e[a, 1], e[a, 2]
                d[5] = 0.5 * (p1 * e2 - p2 * e1)        # np.cross(p, e), its order
                d[6] = 0.5 * (p2 * e0 - p0 * e2)
                d[7] = 0.5 * (p0 * e1 - p1 * e0)
            else:
                d[2 + a] = 0.5
            r = _quat_multiply(d[0], d[1], d[2], d[3], q[j, 0], q[j, 1], q[j, 2], q[j, 3])
            s = _quat_multiply(d[0], d[1], d[2], d[3], q[j, 4], q[j, 5], q[j, 6], q[j, 7])
            t = _quat_multiply(d[4], d[5], d[6], d[7], q[j, 0], q[j, 1], q[j, 2], q[j, 3])
            for i in range(4):
                out[j, a, i] = r[i]
                out[j, a, 4 + i] = s[i] + t[i]


def jacobian_factors(field: WarpField, ref_points: np.ndarray, knn: np.ndarray, weights: np.ndarray,
                      target_normals: np.ndarray):
    """The data Jacobian in factored form: J[c, s] = signed[c, s] * D[knn[c, s]] @ rows[c]."""
    q = field.dual_quaternions()
    b, signed = dq_blend_indexed(q, knn, weights)
    rows = residual_rows(_components(b), _components(ref_points), _components(target_normals))
    return signed, rows, twist_dual_quaternions(field, q)


def expand_jacobian(signed: np.ndarray, rows: np.ndarray, D: np.ndarray, knn: np.ndarray) -> np.ndarray:
    out = np.empty(knn.shape + (6,))
    for s in range(knn.shape[1]):
        out[:, s] = signed[:, s, None] * np.einsum("cmi,ci->cm", D[knn[:, s]], rows)
    return out


def data_jacobian(field: WarpField, ref_points: np.ndarray, knn: np.ndarray, weights: np.ndarray,
                  target_normals: np.ndarray) -> np.ndarray:
    """(C, k, 6): d residual_c / d xi of node knn[c, s] (zero for zero-weight padding slots)."""
    knn = np.asarray(knn)
    return expand_jacobian(*jacobian_factors(field, ref_points, knn, weights, target_normals), knn)
