"""The compiled sums of the depth-like terms' normal equations (assembly.point_blocks): each
correspondence's 8x8 product summed into its node pairs' slots, and the slots' blocks D A D^T.
A correspondence has G rows (normals (G, n, 3), residuals (G, n)), all on its surfel's blend and
summed into one 8x8 product before its node pairs': a colour feature's three axes cost one pass
over the pairs, not three. assembly.point_blocks_reference is the numpy form the tests compare
them with (one row a correspondence). Also the kernels of one 6x6 block J_u^T J_v and gradient
(add_pair, add_gradient) that the regulariser's and the rest anchors' compiled sums share."""
from __future__ import annotations

import numba
import numpy as np

from surfelwarp.tracking.blend_jacobian import residual_row


@numba.njit(cache=True, nogil=True, parallel=True)
def point_sums_split(sel, b, signed, points, normals, r, w, knn, slots, double, pair_s, pair_t, compact, A, e,
                     tasks, by_rows):
    """_point_sums on `tasks` threads. by_rows: the rows of A and e split into `tasks` ranges, a
    thread each walking all of sel in order, so every sum is made in sel's order (one thread's
    bits); else `tasks` consecutive parts of sel, each into its own sums, added in order. The
    correspondences' derivative rows are made first, a part of sel a thread."""
    n = len(sel)
    R = np.empty((n, normals.shape[0], 8))
    for t in numba.prange(tasks):
        for c in range(n * t // tasks, n * (t + 1) // tasks):
            i = sel[c]
            for h in range(normals.shape[0]):
                residual_row(b[i], points[0, i], points[1, i], points[2, i], normals[h, c, 0], normals[h, c, 1],
                             normals[h, c, 2], R[c, h])
    if by_rows:
        rows_A, rows_e = A.shape[0], e.shape[0]
        for t in numba.prange(tasks):
            _point_sums(sel, signed, R, r, w, knn, slots, double, pair_s, pair_t, compact, A, e,
                        rows_A * t // tasks, rows_A * (t + 1) // tasks, rows_e * t // tasks, rows_e * (t + 1) // tasks)
        return
    more_A = np.zeros((tasks - 1, A.shape[0], A.shape[1]))
    more_e = np.zeros((tasks - 1, e.shape[0], e.shape[1]))
    for t in numba.prange(tasks):
        lo, hi = n * t // tasks, n * (t + 1) // tasks
        out_A, out_e = (A, e) if t == 0 else (more_A[t - 1], more_e[t - 1])
        _point_sums(sel[lo:hi], signed, R[lo:hi], r[:, lo:hi], w[lo:hi], knn, slots, double, pair_s, pair_t,
                    compact, out_A, out_e, 0, A.shape[0], 0, e.shape[0])
    for t in range(tasks - 1):
        A += more_A[t]
        e += more_e[t]


@numba.njit(cache=True, nogil=True, parallel=True)
def sandwich(D, lo, hi, A, sym, out, chunk):
    """Blocks D_lo A D_hi^T into out, `chunk` node pairs a task: each block alone, so the split
    over threads changes no bit of the output."""
    for t in numba.prange((len(lo) + chunk - 1) // chunk):
        _sandwich_range(D, lo, hi, A, sym, out, t * chunk, min(len(lo), (t + 1) * chunk))


@numba.njit(cache=True, nogil=True)
def _sandwich_range(D, lo, hi, A, sym, out, start, end):
    # A's row unpacked to a full 8x8 first: read through `sym` inside the product, the inner
    # loop gathered and did not vectorise. A twist's translation moves only the dual part, so
    # D's rows 3-5 are zero in the real part (columns 0-3: blend_jacobian.twist_dual_quaternions)
    # and those products are skipped: their sums only added zeros to 0.0, so the same bits for
    # finite D and A. 7-Scenes, 46k node pairs: 7.1 -> 5.0 ms a call.
    DA = np.empty((6, 8))
    F = np.empty((8, 8))
    for n in range(start, end):
        for m in range(8):
            for j in range(8):
                F[m, j] = A[n, sym[m, j]]
        Da, Db, block = D[lo[n]], D[hi[n]], out[n]
        for i in range(6):
            first = 0 if i < 3 else 4
            for j in range(8):
                acc = 0.0
                for m in range(first, 8):
                    acc += Da[i, m] * F[m, j]
                DA[i, j] = acc
        for i in range(6):
            for j in range(6):
                first = 0 if j < 3 else 4
                acc = 0.0
                for m in range(first, 8):
                    acc += DA[i, m] * Db[j, m]
                block[i, j] = acc


@numba.njit(cache=True, nogil=True)
def _point_sums(sel, signed, R, r, w, knn, slots, double, pair_s, pair_t, compact, A, e, A_lo, A_hi, e_lo, e_hi):
    """A[slot] and e[node] summed over the surfels sel, each with its G derivative rows R
    (len(sel), G, 8), into the rows A_lo:A_hi of A and e_lo:e_hi of e alone; `compact` maps
    slots to rows of A (empty: the slots are the rows)."""
    groups = R.shape[1]
    Q = np.empty(36)
    k = knn.shape[1]
    # The row lengths as the arrays give them, not the constants 36 and 8: LLVM unrolls a loop of
    # a known short count into scalar code, while one of a count known at run time it vectorises
    # (numba's SLP vectoriser, which would take the unrolled code, is off: numba #8705). The
    # same operations per element, so the same bits; tube-wall's 118k pairs 41 -> 31 ms.
    row_36, row_8 = A.shape[1], e.shape[1]
    for c in range(len(sel)):
        i = sel[c]
        rows = R[c]
        q = 0
        for a in range(8):
            for a2 in range(a, 8):
                Q[q] = rows[0, a] * rows[0, a2]
                for h in range(1, groups):
                    Q[q] += rows[h, a] * rows[h, a2]
                q += 1
        for p in range(len(pair_s)):
            slot = slots[i, p]
            if len(compact):
                slot = compact[slot]
            if slot < A_lo or slot >= A_hi:
                continue
            coef = w[c] * signed[i, pair_s[p]] * signed[i, pair_t[p]]
            if double[i, p]:
                coef *= 2.0
            out = A[slot]
            for q in range(row_36):
                out[q] += coef * Q[q]
        for h in range(groups):
            wr = w[c] * r[h, c]
            row = rows[h]
            for s in range(k):
                node = knn[i, s]
                if node < e_lo or node >= e_hi:
                    continue
                g = signed[i, s] * wr
                out = e[node]
                for a in range(row_8):
                    out[a] += g * row[a]


@numba.njit(cache=True, nogil=True, inline="always")
def add_gradient(g, u, r, scale):
    """g += scale * (u x r, r)."""
    g[0] += scale * (u[1] * r[2] - u[2] * r[1])
    g[1] += scale * (u[2] * r[0] - u[0] * r[2])
    g[2] += scale * (u[0] * r[1] - u[1] * r[0])
    for c in range(3):
        g[3 + c] += scale * r[c]


@numba.njit(cache=True, nogil=True, inline="always")
def add_pair(block, u, v, scale):
    """block += scale * [[(u.v) I - v u^T, [u]x], [-[v]x, I]]."""
    uv = u[0] * v[0] + u[1] * v[1] + u[2] * v[2]
    for r in range(3):
        for c in range(3):
            block[r, c] += scale * ((uv if r == c else 0.0) - v[r] * u[c])
        block[3 + r, 3 + r] += scale
    block[0, 4] -= scale * u[2]
    block[0, 5] += scale * u[1]
    block[1, 3] += scale * u[2]
    block[1, 5] -= scale * u[0]
    block[2, 3] -= scale * u[1]
    block[2, 4] += scale * u[0]
    block[3, 1] += scale * v[2]
    block[3, 2] -= scale * v[1]
    block[4, 0] -= scale * v[2]
    block[4, 2] += scale * v[0]
    block[5, 0] += scale * v[1]
    block[5, 1] -= scale * v[0]
