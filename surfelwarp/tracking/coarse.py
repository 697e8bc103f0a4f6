"""The coarse level of the PCG's preconditioner: nodes grouped by cells, each cell moving rigidly.

Block-Jacobi alone carries a correction one graph edge per iteration, so a wide, smooth step
(a room's nodes turning together, the anchors' trial step) takes hundreds of iterations. The
two-level (additive Schwarz) preconditioner adds the exact solve of the system on piecewise
rigid motions: M^-1 r = D^-1 r + P (P^T A P)^-1 P^T r, symmetric positive definite, so CG keeps
its guarantees. A cell's motion y = (omega, v) about its centre c is, for node j at p_j with
d = p_j - c, the twist (omega, v + omega x d) about the node (node twists turn about their node,
blend_jacobian.py; exactly, as exp's left Jacobian V has V [omega]x = R - I):
P_j = [[I, 0], [-[d]x, I]]. The coarse matrix is factored by sparse LU (SuperLU, as solve_step)
and the factors are applied in compiled code inside the PCG.

Cells of 6 node radii on 7-Scenes (6.7k nodes, 510 cells): 64-72 instead of 200-290 iterations
for the anchors' trial step, 17-24 instead of 39-66 for the bordered steps; ~18 ms to factor a
system, 0.25 ms a correction against 0.7 ms for a product with the system.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from surfelwarp.geometry.surfel_mesh import unique_rows


# Below this many free nodes block-Jacobi's iterations cost less than the coarse factor (~1 ms
# of SuperLU and set-up): the sheet's 229 nodes take 30-58 iterations at ~0.03 ms each.
MIN_FREE_NODES = 500


@dataclass(frozen=True)
class CoarseSpace:
    """Cells of one solve's free nodes and the upper coarse blocks their node pairs sum into."""
    cell: np.ndarray        # (M,) int64 each node's cell, -1 for nodes held out of the solve
    offset: np.ndarray      # (M, 3) each node's position less its cell's centre
    num_cells: int
    slot: np.ndarray        # (n_upper,) the upper coarse block of each node block (-1: not both free)
    flip: np.ndarray        # (n_upper,) bool: that block lands transposed (its cells are in lower order)
    diag: np.ndarray        # (num_cells,) each cell's own block
    clo: np.ndarray         # (n_coarse,) cells of the upper coarse blocks, clo <= chi
    chi: np.ndarray


def coarse_space(nodes: np.ndarray, free: np.ndarray, lo: np.ndarray, hi: np.ndarray, cell_m: float) -> CoarseSpace:
    """Cells of side cell_m over the free nodes, and where each upper block (lo, hi) of the
    pattern lands among the cells' blocks."""
    nodes = np.asarray(nodes, np.float64)[: len(free)]
    cell = np.full(len(free), -1, np.int64)
    _, cell[free] = unique_rows(np.floor(nodes[free] / cell_m).astype(np.int64), return_inverse=True)
    k = int(cell.max()) + 1
    centre = np.zeros((max(k, 1), 3))
    for axis in range(3):
        centre[:, axis] = np.bincount(cell[free], nodes[free, axis], minlength=k)
    centre /= np.maximum(np.bincount(cell[free], minlength=k), 1)[:, None]
    offset = np.where(free[:, None], nodes - centre[np.maximum(cell, 0)], 0.0)
    both = free[lo] & free[hi]
    ca, cb = cell[lo], cell[hi]
    first, second = (np.concatenate([f(ca, cb)[both], np.arange(k)]) for f in (np.minimum, np.maximum))
    pairs, inverse = unique_pairs(first, second, k)
    slot = np.full(len(lo), -1, np.int64)
    slot[both] = inverse[: int(both.sum())]
    diag = np.searchsorted(pairs, np.arange(k) * (k + 1))
    return CoarseSpace(cell, offset, k, slot, both & (ca > cb), diag, pairs // k, pairs % k)


def unique_pairs(first: np.ndarray, second: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(first * k + second, return_inverse=True) for 0 <= first, second < k, by two
    counting sorts (a room's 60k pairs: np.unique 3.7 ms, this 0.6)."""
    first, second = (np.ascontiguousarray(a, np.int64) for a in (first, second))
    unique, inverse = np.empty(len(first), np.int64), np.empty(len(first), np.int64)
    n = _unique_pairs(first, second, int(k), unique, inverse)
    return unique[:n], inverse


@numba.njit(cache=True, nogil=True)
def _unique_pairs(first, second, k, unique, inverse):
    # Two stable counting sorts (by second, then by first): the pairs in np.unique's order.
    _, by_second = counting_order(second, np.arange(len(second)), k)
    _, order = counting_order(first, by_second, k)
    n = 0
    for i in order:
        key = first[i] * k + second[i]
        if n == 0 or unique[n - 1] != key:
            unique[n] = key
            n += 1
        inverse[i] = n - 1
    return n


@numba.njit(cache=True, nogil=True)
def counting_order(values, items, k):
    """(where each value's items start (k + 1), items stably sorted by values[items]), for
    0 <= values < k."""
    start = np.zeros(k + 1, np.int64)
    for i in items:
        start[values[i] + 1] += 1
    for a in range(k):
        start[a + 1] += start[a]
    fill = start[:-1].copy()
    out = np.empty(len(items), np.int64)
    for i in items:
        out[fill[values[i]]] = i
        fill[values[i]] += 1
    return start, out


@dataclass(frozen=True)
class CoarseFactor:
    """The coarse system's sparse LU factors as the compiled PCG reads them:
    Pr A Pc = L U, CSC arrays with the diagonals apart."""
    space: CoarseSpace
    L: tuple
    U: tuple
    perm_r: np.ndarray
    perm_c: np.ndarray
    bordered: bool = False      # the border is a cell of it

    def arrays(self) -> tuple:
        """What the compiled PCG's correction takes (its coarse argument)."""
        return (self.space.cell, self.space.offset, self.space.num_cells) + self.L + self.U + (self.perm_r,
                                                                                                self.perm_c)


# The coarse argument of a PCG without cells.
NO_COARSE = (np.zeros(0, np.int64), np.zeros((0, 3)), 0) + \
    (np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0)) * 2 + \
    (np.zeros(0, np.int64), np.zeros(0, np.int64))


def factor(space: CoarseSpace, upper: np.ndarray, lo: np.ndarray, hi: np.ndarray, mu: float,
           B: np.ndarray | None, C: np.ndarray | None) -> CoarseFactor | None:
    """P^T (H + mu I) P of the bordered system (B (M, 6, 6), C (6, 6); None without a border;
    the border is a cell of its own) factored; None if it is singular."""
    k = space.num_cells
    blocks = np.zeros((len(space.clo), 6, 6))
    _coarse_blocks(upper, lo, hi, space.cell, space.offset, space.slot, space.flip, space.diag, mu, blocks)
    clo, chi = space.clo, space.chi
    if B is not None:
        column = np.zeros((k + 1, 6, 6))
        _border_blocks(B, space.cell, space.offset, column[:k])
        column[k] = C + mu * np.eye(6)
        blocks = np.concatenate([blocks, column])
        clo, chi = np.concatenate([clo, np.arange(k + 1)]), np.concatenate([chi, np.full(k + 1, k)])
    n = 6 * (k + (B is not None))
    rows = (6 * clo[:, None, None] + np.arange(6)[None, :, None]).repeat(6, axis=2)
    cols = (6 * chi[:, None, None] + np.arange(6)[None, None, :]).repeat(6, axis=1)
    off = clo != chi
    A = sp.coo_matrix((np.concatenate([blocks.ravel(), blocks[off].ravel()]),
                       (np.concatenate([rows.ravel(), cols[off].ravel()]),
                        np.concatenate([cols.ravel(), rows[off].ravel()]))), shape=(n, n)).tocsc()
    try:
        lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    except RuntimeError:        # exactly singular
        return None
    parts = []
    for T in (lu.L, lu.U):
        T = T.tocsc()
        diag = T.diagonal()
        if not np.all(np.isfinite(diag)) or np.any(diag == 0):
            return None
        T.setdiag(0.0)
        T.eliminate_zeros()
        parts.append((T.indptr.astype(np.int64), T.indices.astype(np.int64), T.data, 1.0 / diag))
    return CoarseFactor(space, parts[0], parts[1], lu.perm_r.astype(np.int64), lu.perm_c.astype(np.int64),
                        B is not None)


@numba.njit(cache=True, nogil=True)
def _left(Sa, X, Y):
    """Y = P_a^T X: X's first three rows plus S_a X[3:]."""
    for j in range(6):
        x3, x4, x5 = X[3, j], X[4, j], X[5, j]
        for i in range(3):
            Y[i, j] = X[i, j] + Sa[i, 0] * x3 + Sa[i, 1] * x4 + Sa[i, 2] * x5
        Y[3, j], Y[4, j], Y[5, j] = x3, x4, x5


@numba.njit(cache=True, nogil=True)
def _sandwich(U, Sa, Sb, X, Y):
    """Y = P_a^T U P_b; X is scratch (6, 6)."""
    for i in range(6):                            # X = U P_b: the first three columns less U[:, 3:] S_b
        for c in range(3):
            X[i, c] = U[i, c] - U[i, 3] * Sb[0, c] - U[i, 4] * Sb[1, c] - U[i, 5] * Sb[2, c]
        for c in range(3, 6):
            X[i, c] = U[i, c]
    _left(Sa, X, Y)


@numba.njit(cache=True, nogil=True)
def _skews(cell, offset):
    S = np.zeros((len(cell), 3, 3))
    for a in range(len(cell)):
        if cell[a] >= 0:
            d = offset[a]
            S[a, 0, 1], S[a, 0, 2], S[a, 1, 2] = -d[2], d[1], -d[0]
            S[a, 1, 0], S[a, 2, 0], S[a, 2, 1] = d[2], -d[1], d[0]
    return S


@numba.njit(cache=True, nogil=True, parallel=True)
def _coarse_blocks(upper, lo, hi, cell, offset, slot, flip, diag, mu, out):
    """out[slot] += P_lo^T U P_hi of each node block (and mu's), on numba's two threads, each
    summing the coarse blocks of its half of the slots over every node block in order: the
    same sums as one thread (7-Scenes, ~60k node blocks: ~5.5 ms on one)."""
    S = _skews(cell, offset)
    half = (len(out) + 1) // 2
    for t in numba.prange(2):
        _coarse_range(upper, lo, hi, cell, S, slot, flip, diag, mu, out, t * half, min(len(out), (t + 1) * half))


@numba.njit(cache=True, nogil=True)
def _coarse_range(upper, lo, hi, cell, S, slot, flip, diag, mu, out, first, stop):
    """_coarse_blocks' sums into the coarse blocks first..stop."""
    X, Y = np.empty((6, 6)), np.empty((6, 6))
    for n in range(len(lo)):
        s = slot[n]
        if s < first or s >= stop:
            continue
        a, b = lo[n], hi[n]
        _sandwich(upper[n], S[a], S[b], X, Y)
        mirror = a != b and cell[a] == cell[b]     # its mirror lands on the same cell
        for i in range(6):
            for j in range(6):
                if mirror:
                    out[s, i, j] += Y[i, j] + Y[j, i]
                elif flip[n]:
                    out[s, i, j] += Y[j, i]
                else:
                    out[s, i, j] += Y[i, j]
    eye = mu * np.eye(6)
    for a in range(len(cell)):
        if cell[a] >= 0 and first <= diag[cell[a]] < stop:
            _sandwich(eye, S[a], S[a], X, Y)
            out[diag[cell[a]]] += Y


@numba.njit(cache=True, nogil=True)
def _border_blocks(B, cell, offset, out):
    S = _skews(cell, offset)
    Y = np.empty((6, 6))
    for a in range(len(cell)):
        if cell[a] >= 0:
            _left(S[a], B[a], Y)
            out[cell[a]] += Y


@numba.njit(cache=True, nogil=True)
def restrict(cell, offset, num_cells, r, rc):
    """rc = P^T r (rc zeroed first; rows past the cells' are left to the caller)."""
    rc[:] = 0.0
    for a in range(len(cell)):
        c = cell[a]
        if c < 0:
            continue
        d = offset[a]
        rv0, rv1, rv2 = r[a, 3], r[a, 4], r[a, 5]
        rc[c, 0] += r[a, 0] + d[1] * rv2 - d[2] * rv1          # omega: r_omega + d x r_v
        rc[c, 1] += r[a, 1] + d[2] * rv0 - d[0] * rv2
        rc[c, 2] += r[a, 2] + d[0] * rv1 - d[1] * rv0
        rc[c, 3] += rv0
        rc[c, 4] += rv1
        rc[c, 5] += rv2


@numba.njit(cache=True, nogil=True)
def prolong(cell, offset, yc, z):
    """z += P yc: each node takes its cell's twist (omega, v + omega x d)."""
    for a in range(len(cell)):
        c = cell[a]
        if c < 0:
            continue
        d = offset[a]
        w0, w1, w2 = yc[c, 0], yc[c, 1], yc[c, 2]
        z[a, 0] += w0
        z[a, 1] += w1
        z[a, 2] += w2
        z[a, 3] += yc[c, 3] + w1 * d[2] - w2 * d[1]
        z[a, 4] += yc[c, 4] + w2 * d[0] - w0 * d[2]
        z[a, 5] += yc[c, 5] + w0 * d[1] - w1 * d[0]


@numba.njit(cache=True, nogil=True)
def lu_solve(Lp, Li, Lx, Linv, Up, Ui, Ux, Uinv, perm_r, perm_c, b, x):
    """x = A^-1 b from Pr A Pc = L U (CSC factors without their diagonals, given inverted)."""
    n = len(b)
    y = np.empty(n)
    for i in range(n):
        y[perm_r[i]] = b[i]
    for j in range(n):
        y[j] *= Linv[j]
        for t in range(Lp[j], Lp[j + 1]):
            y[Li[t]] -= Lx[t] * y[j]
    for j in range(n - 1, -1, -1):
        y[j] *= Uinv[j]
        for t in range(Up[j], Up[j + 1]):
            y[Ui[t]] -= Ux[t] * y[j]
    for i in range(n):
        x[i] = y[perm_c[i]]


@numba.njit(cache=True, nogil=True)
def correct(cell, offset, num_cells, Lp, Li, Lx, Linv, Up, Ui, Ux, Uinv, perm_r, perm_c, r, z):
    """z += P A_c^-1 P^T r, the border (r's last row) as one more cell if the factors have it."""
    n = len(perm_r)
    rc = np.zeros((n // 6, 6))
    restrict(cell, offset, num_cells, r, rc)
    if n > 6 * num_cells:
        rc[num_cells] = r[len(r) - 1]
    yc = np.empty((n // 6, 6))
    lu_solve(Lp, Li, Lx, Linv, Up, Ui, Ux, Uinv, perm_r, perm_c, rc.reshape(-1), yc.reshape(-1))
    prolong(cell, offset, yc, z)
    if n > 6 * num_cells:
        z[len(z) - 1] += yc[num_cells]
