"""Descriptor matching: each descriptor's exact nearest neighbour on the other side, with
Lowe's ratio test (features.match_descriptors adds the mutual check)."""
from __future__ import annotations

import numba
import numpy as np


def nearest_both_ways(a: np.ndarray, b: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact nearest neighbours of the rows of a (n, d) among those of b (m, d) and of b's among
    a's (Euclidean): (n,) and (m,) indices, -1 where the nearest is not below `ratio` times the
    second nearest. All n x m distances from one matrix product, read once for both directions:
    on a twist-limb frame (1700 SIFT features a side) 10-13 ms against 44 ms for FLANN's
    approximate neighbours both ways, which found the same pairs but one of 1534; and
    deterministic, where FLANN's random trees differ from one build to the next."""
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    row_d2, row_index = np.full((2, len(a)), np.inf, np.float32), np.full(len(a), -1, np.int64)
    col_d2, col_index = np.full((2, len(b)), np.inf, np.float32), np.full(len(b), -1, np.int64)
    _two_nearest(a @ b.T, np.einsum("ij,ij->i", a, a), np.einsum("ij,ij->i", b, b), row_d2, row_index, col_d2,
                 col_index)
    r2 = np.float32(ratio * ratio)     # d0 < ratio d1 on squared distances
    return (np.where(row_d2[0] < r2 * row_d2[1], row_index, -1),
            np.where(col_d2[0] < r2 * col_d2[1], col_index, -1))


@numba.njit(cache=True, nogil=True)
def _two_nearest(inner, norm_a, norm_b, row_d2, row_index, col_d2, col_index):
    """The two smallest squared distances |a_i|^2 + |b_j|^2 - 2 a_i.b_j of every row and every
    column, and where the smallest is (inputs at inf and -1)."""
    n, m = inner.shape
    for i in range(n):
        best, second, k = np.inf, np.inf, -1
        for j in range(m):
            d = norm_a[i] + norm_b[j] - 2 * inner[i, j]
            if d < best:
                best, second, k = d, best, j
            elif d < second:
                second = d
            if d < col_d2[1, j]:
                if d < col_d2[0, j]:
                    col_d2[1, j], col_d2[0, j], col_index[j] = col_d2[0, j], d, i
                else:
                    col_d2[1, j] = d
        row_d2[0, i], row_d2[1, i], row_index[i] = best, second, k
