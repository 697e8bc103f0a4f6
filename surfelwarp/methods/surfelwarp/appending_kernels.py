"""Compiled (numba) form of appending's strain estimates (Eq. 7): per candidate, the twelve
perturbed dual quaternion blends of both sides, their central differences and the Jacobians'
extreme singular values, in one pass with no (6, N, k) or (6, N, 4, 4) temporaries.
appending._strains_reference computes the same in numpy (the reference the tests compare this
with, to rounding: the sums here run in another order). A room's ~3.7k candidates a frame
(7-Scenes, captured calls) took 26-32 ms in numpy, ~6 ms here with the inverse warp and the
reference nodes' tree (~2 of it)."""
from __future__ import annotations

import numba
import numpy as np

from surfelwarp.geometry.dq_kernels import apply_blend

NO_NODE = -1


@numba.njit(cache=True, inline="always", error_model="numpy")
def _weights(x0, x1, x2, nodes, idx, count, inv, w):
    """Normalised Gaussian weights of the point (x0, x1, x2) over its `count` nodes nodes[idx[:count]]
    into w[:count], relative to the nearest so that far points do not underflow."""
    nearest = np.inf
    for s in range(count):
        node = idx[s]
        if node == NO_NODE:
            w[s] = np.inf
            continue
        d0, d1, d2 = x0 - nodes[node, 0], x1 - nodes[node, 1], x2 - nodes[node, 2]
        w[s] = d0 * d0 + d1 * d1 + d2 * d2
        nearest = min(nearest, w[s])
    total = 0.0
    for s in range(count):
        w[s] = np.exp(-(w[s] - nearest) * inv)
        total += w[s]
    for s in range(count):
        w[s] /= total


@numba.njit(cache=True, inline="always", error_model="numpy")
def _signs(dqs, idx, count, w, signs):
    """+-1 per slot: each node's dual quaternion flipped into the hemisphere of the heaviest
    slot's (warp_field.blend's antipodal fix)."""
    best = 0
    for s in range(1, count):
        if w[s] > w[best]:
            best = s
    pivot = idx[best]
    for s in range(count):
        node = idx[s] if idx[s] != NO_NODE else pivot
        dot = dqs[node, 0] * dqs[pivot, 0] + dqs[node, 1] * dqs[pivot, 1] + dqs[node, 2] * dqs[pivot, 2] + \
            dqs[node, 3] * dqs[pivot, 3]
        signs[s] = -1.0 if dot < 0.0 else 1.0


@numba.njit(cache=True, inline="always", error_model="numpy")
def _warped(x0, x1, x2, dqs, idx, count, w, signs, inverse, out, a, b):
    """The blend (into b (8,)) of the slots' dual quaternions with weights w applied to the
    point, or its inverse (R^T (x - t)), into out[a] (3,): the warp's own arithmetic
    (dq_kernels.apply_blend)."""
    b[:] = 0.0
    for s in range(count):
        node = idx[s]
        if node == NO_NODE or w[s] == 0.0:
            continue
        ws = w[s] * signs[s]
        for j in range(8):
            b[j] += ws * dqs[node, j]
    out[a, 0], out[a, 1], out[a, 2] = apply_blend(b, inverse, x0, x1, x2)


@numba.njit(cache=True, inline="always", error_model="numpy")
def _jacobian(x, nodes, dqs, idx, count, inv, h, inverse, J, w, signs, y, b):
    """J (3, 3) [output, axis]: the central differences with step h of the blend warp (or its
    inverse) at x, the weights following the moved point, the slots' signs fixed at x."""
    _weights(x[0], x[1], x[2], nodes, idx, count, inv, w)
    _signs(dqs, idx, count, w, signs)
    for a in range(6):
        axis, sign = a % 3, 1.0 if a < 3 else -1.0
        x0 = x[0] + (sign * h if axis == 0 else 0.0)
        x1 = x[1] + (sign * h if axis == 1 else 0.0)
        x2 = x[2] + (sign * h if axis == 2 else 0.0)
        _weights(x0, x1, x2, nodes, idx, count, inv, w)
        _warped(x0, x1, x2, dqs, idx, count, w, signs, inverse, y, a, b)
    for i in range(3):
        for axis in range(3):
            J[i, axis] = (y[axis, i] - y[axis + 3, i]) / (2.0 * h)


@numba.njit(cache=True, inline="always", error_model="numpy")
def _extreme_singular_values(J):
    """Smallest and largest singular values of J (3, 3): the closed-form (trigonometric)
    eigenvalues of J^T J."""
    a00 = J[0, 0] * J[0, 0] + J[1, 0] * J[1, 0] + J[2, 0] * J[2, 0]
    a01 = J[0, 0] * J[0, 1] + J[1, 0] * J[1, 1] + J[2, 0] * J[2, 1]
    a02 = J[0, 0] * J[0, 2] + J[1, 0] * J[1, 2] + J[2, 0] * J[2, 2]
    a11 = J[0, 1] * J[0, 1] + J[1, 1] * J[1, 1] + J[2, 1] * J[2, 1]
    a12 = J[0, 1] * J[0, 2] + J[1, 1] * J[1, 2] + J[2, 1] * J[2, 2]
    a22 = J[0, 2] * J[0, 2] + J[1, 2] * J[1, 2] + J[2, 2] * J[2, 2]
    q = (a00 + a11 + a22) / 3.0
    off = a01 ** 2 + a02 ** 2 + a12 ** 2
    dev = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2
    p = np.sqrt((dev + 2.0 * off) / 6.0)
    scale = p if p > 0 else 1.0
    b00, b01, b02 = (a00 - q) / scale, a01 / scale, a02 / scale
    b10, b11, b12 = b01, (a11 - q) / scale, a12 / scale
    b20, b21, b22 = b02, b12, (a22 - q) / scale
    det = b00 * (b11 * b22 - b12 * b21) - b01 * (b10 * b22 - b12 * b20) + b02 * (b10 * b21 - b11 * b20)
    r = min(max(0.5 * det, -1.0), 1.0)
    phi = np.arccos(r) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return np.sqrt(max(smallest, 0.0)), np.sqrt(max(largest, 0.0))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def strains(x, idx, live_nodes, x_ref, ref_idx, nodes, dqs, sigma, h, live_side, ref_side):
    """appending._strains_reference per candidate: live_side[i] the largest singular value of
    the inverse warp's Jacobian at x[i] over its live nodes idx[i] (NO_NODE: an empty slot),
    ref_side[i] 1 / the smallest of the forward warp's at x_ref[i] over its reference nodes
    ref_idx[i]. On one thread: on two a room's candidates took 2.5 instead of 4 ms, but the
    kernel 11 s to compile instead of 4.5 (once, into numba's cache). Divisions by zero give
    inf or nan, as in numpy (a nan strain is not compressive), never an exception."""
    inv = 1.0 / (2.0 * sigma * sigma)
    k = max(idx.shape[1], ref_idx.shape[1])
    w, signs, y, J, b = np.empty(k), np.empty(k), np.empty((6, 3)), np.empty((3, 3)), np.empty(8)
    for i in range(len(x)):
        _jacobian(x[i], live_nodes, dqs, idx[i], idx.shape[1], inv, h, True, J, w, signs, y, b)
        live_side[i] = _extreme_singular_values(J)[1]
        _jacobian(x_ref[i], nodes, dqs, ref_idx[i], ref_idx.shape[1], inv, h, False, J, w, signs, y, b)
        smallest = _extreme_singular_values(J)[0]
        ref_side[i] = 1.0 / smallest if smallest > 0 else np.inf
