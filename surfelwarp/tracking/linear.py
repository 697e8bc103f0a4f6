"""The damped Gauss-Newton step: (H + mu I) x = -g, mu = damping * mean(diag H).

By conjugate gradients with a block-Jacobi (per-node 6x6) preconditioner, as the GPU solver of
Dou et al. that SurfelWarp follows, plus a coarse level when the system has cells (coarse.py:
cells of nodes moving rigidly, solved exactly; 7-Scenes frames take ~105 iterations instead of
~380), compiled and run on the system's upper blocks as they are (_pcg; solve_step_pcg is the
block-Jacobi form in numpy on an assembled matrix), falling back to sparse LU (SuperLU) when it
does not reach its tolerance; with rest anchors the system is bordered by one
more 6-variable block (Bordered). Nodes held out of the solve get a zero step (masked in the
compiled PCG, removed from the matrix for LU by restrict).
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from surfelwarp.tracking.assembly import NormalEquations
from surfelwarp.tracking.coarse import NO_COARSE, CoarseFactor, correct, factor

LINEAR_SOLVERS = ("pcg", "direct")


class Bordered:
    """H bordered by one extra 6-variable block (the anchors' common motion): [[H, B], [B^T, C]]
    with B given as (M, 6, 6) row blocks; as much of a matrix as the step solvers use."""

    def __init__(self, H: sp.spmatrix, B: np.ndarray, C: np.ndarray):
        self.H, self.B, self.C = H, B, C
        n = H.shape[0] + 6
        self.shape = (n, n)

    def diagonal(self) -> np.ndarray:
        return np.concatenate([self.H.diagonal(), np.diag(self.C)])

    def __matmul__(self, p: np.ndarray) -> np.ndarray:
        x, z = p[:-6], p[-6:]
        out = np.empty_like(p)
        out[:-6] = self.H @ x
        out[:-6] += np.einsum("mij,j->mi", self.B, z).reshape(-1)
        out[-6:] = np.einsum("mij,mi->j", self.B, x.reshape(-1, 6)) + self.C @ z
        return out

    def tosparse(self) -> sp.csr_matrix:
        m = len(self.B)
        Bs = sp.bsr_matrix((self.B, np.zeros(m, np.int64), np.arange(m + 1)), shape=(6 * m, 6)).tocsr()
        return sp.bmat([[self.H, Bs], [Bs.T, sp.csr_matrix(self.C)]], format="csr")


@dataclass(frozen=True)
class Step:
    xi: np.ndarray          # (M, 6) node twists (zero for the nodes held out)
    zeta: np.ndarray        # (6,) the border's twist (zeros without a border)
    lu_fallback: bool       # PCG did not converge and sparse LU solved the step
    iterations: int = 0     # PCG's iterations (0 for LU)
    coarse: CoarseFactor | None = None  # the PCG preconditioner's coarse factor, if it had one


def solve_system(system: NormalEquations, damping: float, linear_solver: str = "pcg", pcg_rtol: float = 1e-4,
                 pcg_max_iterations: int = 500, coarse: CoarseFactor | None = None) -> Step:
    """The damped Gauss-Newton step of the system's free nodes, and of its border if it has one.
    `coarse`: an earlier step's coarse factor (Step.coarse) to precondition with, if it was made
    on the same cells and border: a preconditioner need not be exact, and within one solve
    the coarse system changes little (7-Scenes: 1-3 PCG iterations more, ~18 ms less a
    factor; tube-wall: the factor costs as much as the PCG's iterations)."""
    pattern, free, border = system.pattern, system.free, system.border
    if linear_solver == "pcg":
        step = _pcg_on_blocks(system, damping, pcg_rtol, pcg_max_iterations, coarse)
        if step is not None:
            return step
    H, g = pattern.matrix(system.upper), system.gradient.reshape(-1)
    if not free.all():
        H, g, _ = restrict(H, g, system.upper[pattern.diag], free)
    if border is not None:
        H, g = Bordered(H, border.B[free], border.C), np.concatenate([g, border.g])
    xi = solve_step(H.tosparse() if border is not None else H, g, damping)
    zeta = np.zeros(6)
    if border is not None:
        xi, zeta = xi[:-6], xi[-6:]
    if not free.all():
        xi = _expand(xi, free)
    return Step(xi.reshape(-1, 6), zeta, linear_solver == "pcg")


def _pcg_on_blocks(system: NormalEquations, damping: float, rtol: float, max_iterations: int,
                   reuse: CoarseFactor | None = None) -> Step | None:
    """solve_step_pcg on the system's upper blocks as they are (no matrix built, held nodes
    masked instead of removed, the border as node M): compiled, each iteration
    reads the blocks once for both triangles. None if it does not converge."""
    pattern, free, border = system.pattern, system.free, system.border
    diag = system.upper[pattern.diag]
    m = pattern.num_nodes
    g = np.zeros((m + 1, 6))
    g[:m][free] = system.gradient[free]
    diag_sum = np.trace(diag[free], axis1=1, axis2=2).sum()
    count = 6 * int(free.sum())
    if border is not None:
        B, C = np.ascontiguousarray(border.B * free[:, None, None]), border.C
        g[m] = border.g
        diag_sum, count = diag_sum + np.trace(C), count + 6
    else:
        B, C = np.zeros((1, 6, 6)), np.eye(6)
    mu = damping * max(diag_sum / max(count, 1), 1e-12)
    blocks = np.concatenate([diag, C[None]]) + mu * np.eye(6)
    Minv = np.empty_like(blocks)
    if not _cholesky_inverses(blocks, Minv):
        try:
            Minv = np.linalg.inv(blocks)
        except np.linalg.LinAlgError:
            return None
    Minv[:m][~free] = 0.0
    if border is None:
        Minv[m] = 0.0
    upper = np.ascontiguousarray(system.upper)
    coarse, f = NO_COARSE, None
    if system.coarse is not None and system.coarse.num_cells > 0:
        if reuse is not None and reuse.space is system.coarse and reuse.bordered == (border is not None):
            f = reuse
        else:
            f = factor(system.coarse, upper, pattern.lo, pattern.hi, mu, B if border is not None else None, C)
        if f is not None:
            coarse = f.arrays()
    x = np.zeros((m + 1, 6))
    iterations = _pcg(upper, pattern.indptr_upper, pattern.hi, free, Minv, coarse, B, C, border is not None, mu, g,
                      rtol, max_iterations, x)
    if iterations < 0:
        return None
    return Step(x[:m], x[m] if border is not None else np.zeros(6), False, iterations, f)


@numba.njit(cache=True, nogil=True, parallel=True)
def _cholesky_inverses(blocks, out):
    """out[i] = blocks[i]^-1 of symmetric 6x6 blocks, by Cholesky; False if one is not positive
    definite. numpy's batched inv takes ~1 us a block (6.5 ms a 7-Scenes system), this ~0.1,
    in two halves on numba's threads (each block alone: the same bits on any thread count)."""
    half = (len(blocks) + 1) // 2
    ok = np.ones(2, np.bool_)
    for task in numba.prange(2):
        ok[task] = _cholesky_range(blocks, out, task * half, min(len(blocks), (task + 1) * half))
    return ok[0] and ok[1]


@numba.njit(cache=True, nogil=True)
def _cholesky_range(blocks, out, start, stop):
    """_cholesky_inverses of blocks start..stop."""
    n = blocks.shape[1]
    L, Li = np.zeros((n, n)), np.zeros((n, n))
    for i in range(start, stop):
        A = blocks[i]
        for j in range(n):
            s = A[j, j]
            for k in range(j):
                s -= L[j, k] * L[j, k]
            if not s > 0.0:
                return False
            L[j, j] = np.sqrt(s)
            for r in range(j + 1, n):
                s = A[r, j]
                for k in range(j):
                    s -= L[r, k] * L[j, k]
                L[r, j] = s / L[j, j]
        for j in range(n):      # Li = L^-1, lower triangular
            Li[j, j] = 1.0 / L[j, j]
            for r in range(j + 1, n):
                s = 0.0
                for k in range(j, r):
                    s -= L[r, k] * Li[k, j]
                Li[r, j] = s / L[r, r]
        for r in range(n):      # A^-1 = Li^T Li
            for c in range(r, n):
                s = 0.0
                for k in range(c, n):
                    s += Li[k, r] * Li[k, c]
                out[i, r, c] = out[i, c, r] = s
    return True


@numba.njit(cache=True, nogil=True, parallel=True)
def _matvec(upper, indptr, hi, free, B, C, bordered, mu, p, out, split, parts):
    """out = (H + mu I) p on the free nodes (and the border, as row m): the rows before `split`
    and those after on numba's two threads, each into its own part (a row's transposed blocks
    land in the other half's rows too), then the parts summed: the same sums on any schedule.
    Two 7-Scenes systems of 60k blocks: 0.93-1.03 ms on one thread, 0.51-0.73 on two."""
    m = len(free)
    for t in numba.prange(2):
        _matvec_rows(upper, indptr, hi, free, B, bordered, mu, p, parts[t], split if t else 0, m if t else split)
    for a in range(m + 1):
        for j in range(6):
            out[a, j] = parts[0, a, j] + parts[1, a, j]
    if bordered:
        for i in range(6):
            acc = mu * p[m, i]
            for j in range(6):
                acc += C[i, j] * p[m, j]
            out[m, i] += acc


@numba.njit(cache=True, nogil=True, fastmath=True)
def _matvec_rows(upper, indptr, hi, free, B, bordered, mu, p, out, start, stop):
    """out = the products of the rows start..stop of H + mu I with p (the blocks of each row and
    their transposes, and the border's), out zeroed first. Row by row, a node's sums and its p
    in registers."""
    m = len(free)
    out[:] = 0.0
    for a in range(start, stop):
        if not free[a]:
            continue
        q0, q1, q2, q3, q4, q5 = p[a, 0], p[a, 1], p[a, 2], p[a, 3], p[a, 4], p[a, 5]
        s0, s1, s2, s3, s4, s5 = mu * q0, mu * q1, mu * q2, mu * q3, mu * q4, mu * q5
        for n in range(indptr[a], indptr[a + 1]):
            b = hi[n]
            if not free[b]:
                continue
            U = upper[n]
            r0, r1, r2, r3, r4, r5 = p[b, 0], p[b, 1], p[b, 2], p[b, 3], p[b, 4], p[b, 5]
            s0 += U[0, 0] * r0 + U[0, 1] * r1 + U[0, 2] * r2 + U[0, 3] * r3 + U[0, 4] * r4 + U[0, 5] * r5
            s1 += U[1, 0] * r0 + U[1, 1] * r1 + U[1, 2] * r2 + U[1, 3] * r3 + U[1, 4] * r4 + U[1, 5] * r5
            s2 += U[2, 0] * r0 + U[2, 1] * r1 + U[2, 2] * r2 + U[2, 3] * r3 + U[2, 4] * r4 + U[2, 5] * r5
            s3 += U[3, 0] * r0 + U[3, 1] * r1 + U[3, 2] * r2 + U[3, 3] * r3 + U[3, 4] * r4 + U[3, 5] * r5
            s4 += U[4, 0] * r0 + U[4, 1] * r1 + U[4, 2] * r2 + U[4, 3] * r3 + U[4, 4] * r4 + U[4, 5] * r5
            s5 += U[5, 0] * r0 + U[5, 1] * r1 + U[5, 2] * r2 + U[5, 3] * r3 + U[5, 4] * r4 + U[5, 5] * r5
            if b != a:
                for j in range(6):
                    out[b, j] += U[0, j] * q0 + U[1, j] * q1 + U[2, j] * q2 + U[3, j] * q3 + U[4, j] * q4 \
                        + U[5, j] * q5
        out[a, 0] += s0
        out[a, 1] += s1
        out[a, 2] += s2
        out[a, 3] += s3
        out[a, 4] += s4
        out[a, 5] += s5
    if bordered:
        for a in range(start, stop):
            for i in range(6):
                acc = 0.0
                for j in range(6):
                    acc += B[a, i, j] * p[m, j]
                    out[m, j] += B[a, i, j] * p[a, i]
                out[a, i] += acc


@numba.njit(cache=True, nogil=True)
def _precondition(Minv, coarse, r, z):
    """z = D^-1 r, plus the coarse level's correction if it has cells (coarse.py)."""
    for a in range(len(r)):
        for i in range(6):
            acc = 0.0
            for j in range(6):
                acc += Minv[a, i, j] * r[a, j]
            z[a, i] = acc
    cell, offset, num_cells, Lp, Li, Lx, Linv, Up, Ui, Ux, Uinv, perm_r, perm_c = coarse
    if num_cells > 0:
        correct(cell, offset, num_cells, Lp, Li, Lx, Linv, Up, Ui, Ux, Uinv, perm_r, perm_c, r, z)


@numba.njit(cache=True, nogil=True)
def _pcg(upper, indptr, hi, free, Minv, coarse, B, C, bordered, mu, g, rtol, max_iterations, x):
    """Preconditioned CG on (H + mu I) x = -g from x = 0 (as solve_step_pcg), the vector
    updates fused into single passes. Returns the iterations taken, -1 if it did not converge."""
    r = -g
    z = np.empty_like(g)
    Hp = np.empty_like(g)
    parts = np.empty((2,) + g.shape)
    split = np.searchsorted(indptr, indptr[len(free)] // 2)      # half the blocks each
    target = rtol * np.sqrt(np.sum(g * g))
    _precondition(Minv, coarse, r, z)
    p = z.copy()
    rz = np.sum(r * z)
    rr = np.sum(r * r)
    for it in range(max_iterations + 1):
        if np.sqrt(rr) <= target:
            return it
        if it == max_iterations:
            return -1
        _matvec(upper, indptr, hi, free, B, C, bordered, mu, p, Hp, split, parts)
        pHp = 0.0
        for a in range(len(p)):
            for i in range(6):
                pHp += p[a, i] * Hp[a, i]
        if not pHp > 0:
            return -1
        alpha = rz / pHp
        rr = 0.0
        for a in range(len(p)):
            for i in range(6):
                x[a, i] += alpha * p[a, i]
                r[a, i] -= alpha * Hp[a, i]
                rr += r[a, i] * r[a, i]
        _precondition(Minv, coarse, r, z)
        rz_old, rz = rz, 0.0
        for a in range(len(p)):
            for i in range(6):
                rz += r[a, i] * z[a, i]
        beta = rz / rz_old
        for a in range(len(p)):
            for i in range(6):
                p[a, i] = z[a, i] + beta * p[a, i]
    return -1


def restrict(H: sp.bsr_matrix, g: np.ndarray, diag_blocks: np.ndarray, keep: np.ndarray):
    """The system of the nodes `keep` (bool (M,)) with the others held at zero step: H's 6x6
    blocks between kept nodes, their gradient and diagonal blocks."""
    m = len(keep)
    rows = np.repeat(np.arange(m), np.diff(H.indptr))
    sel = keep[rows] & keep[H.indices]
    new = np.cumsum(keep) - 1
    counts = np.bincount(new[rows[sel]], minlength=int(keep.sum()))
    indptr = np.concatenate([[0], np.cumsum(counts)])
    n = 6 * int(keep.sum())
    Hk = sp.bsr_matrix((H.data[sel], new[H.indices[sel]], indptr), shape=(n, n))
    return Hk, g.reshape(m, 6)[keep].reshape(-1), diag_blocks[keep]


def _expand(xi: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(M, 6) steps, zero for the nodes held fixed."""
    full = np.zeros((len(free), 6))
    full[free] = np.reshape(xi, (-1, 6))
    return full


def _damping(H: sp.spmatrix, damping: float) -> float:
    return damping * max(float(np.mean(H.diagonal())), 1e-12)


def solve_step(H: sp.spmatrix, g: np.ndarray, damping: float) -> np.ndarray:
    """The damped Gauss-Newton step by sparse LU: (H + mu I) x = -g, mu = damping * mean(diag H)."""
    A = (H + sp.identity(H.shape[0], format="csr") * _damping(H, damping)).tocsc()
    # The damped matrix is symmetric positive definite: symmetric mode without pivoting keeps
    # the fill-reducing ordering intact (about 10x faster than the default pivoting LU), and
    # minimum degree on A^T + A suits its symmetric pattern (2-3x faster than COLAMD at 4k nodes).
    lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    return lu.solve(-np.asarray(g, np.float64))


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    # einsum rather than BLAS: threaded ddot on short vectors is slow on a busy machine.
    return float(np.einsum("i,i->", a, b))


def solve_step_pcg(H: sp.spmatrix, g: np.ndarray, damping: float, rtol: float = 1e-4, max_iterations: int = 500,
                   diag_blocks: np.ndarray | None = None) -> tuple[np.ndarray, int, bool]:
    """The damped Gauss-Newton step by conjugate gradients with a block-Jacobi (per-node 6x6)
    preconditioner, from x = 0, until |residual| <= rtol |g|. Returns (x, iterations, converged);
    diag_blocks (M, 6, 6) are H's diagonal blocks if known."""
    g = np.asarray(g, np.float64)
    n = len(g)
    m = n // 6
    mu = _damping(H, damping)
    if diag_blocks is None:
        Hb = H if isinstance(H, sp.bsr_matrix) and H.blocksize == (6, 6) else sp.bsr_matrix(H, blocksize=(6, 6))
        rows = np.repeat(np.arange(m), np.diff(Hb.indptr))
        on = Hb.indices == rows
        diag_blocks = np.zeros((m, 6, 6))
        diag_blocks[rows[on]] = Hb.data[on]
    try:
        Minv = np.linalg.inv(diag_blocks + mu * np.eye(6))
    except np.linalg.LinAlgError:
        return np.zeros(n), 0, False
    x = np.zeros(n)
    r = -g
    target = rtol * np.sqrt(_dot(g, g))
    z = np.einsum("nij,nj->ni", Minv, r.reshape(m, 6)).reshape(-1)
    p = z.copy()
    rz = _dot(r, z)
    for it in range(max_iterations + 1):
        if np.sqrt(_dot(r, r)) <= target:
            return x, it, True
        if it == max_iterations:
            break
        Hp = H @ p + mu * p
        pHp = _dot(p, Hp)
        if not pHp > 0:
            break
        alpha = rz / pHp
        x += alpha * p
        r -= alpha * Hp
        z = np.einsum("nij,nj->ni", Minv, r.reshape(m, 6)).reshape(-1)
        rz, rz_old = _dot(r, z), rz
        p *= rz / rz_old
        p += z
    return x, it, False
