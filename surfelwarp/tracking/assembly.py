"""J^T W J summed directly in 6x6 node blocks into a sparsity pattern fixed for one solve.

BlockPattern holds the pattern (diagonal, graph edges, node pairs sharing a skinned surfel);
point_blocks sums the blocks of point-to-plane-like residuals of skinned surfels in factored form
(only the 36 distinct products of the pair's 8-vector derivative are summed per node pair);
pair_blocks is the form of every residual that moves a point by [-[y]x, I] xi.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np
import scipy.sparse as sp

from surfelwarp.geometry.dual_quaternion import _components
from surfelwarp.geometry.se3 import skew
from surfelwarp.tracking.assembly_kernels import point_sums_split, sandwich
from surfelwarp.tracking.blend_jacobian import residual_rows
from surfelwarp.tracking.coarse import CoarseSpace, counting_order


class BlockPattern:
    """The 6x6-block sparsity of J^T W J: the diagonal, graph edges, and node pairs that share a
    skinned surfel. Symmetric; the blocks are summed for the upper triangle (lo <= hi) only and
    mirrored. Built once per solve (the graph and the skinning are fixed within one), so the
    data and regulariser blocks of every iteration are sums into fixed slots instead of a
    general sparse product."""

    def __init__(self, num_nodes: int, graph: np.ndarray, knn: np.ndarray):
        m = self.num_nodes = int(num_nodes)
        knn = np.ascontiguousarray(np.asarray(knn, np.int64).reshape(len(knn), -1))
        n, k = knn.shape
        graph = np.ascontiguousarray(np.asarray(graph, np.int64).reshape(m, -1))
        # Upper pattern rows in compiled code (each node's partners from the surfels it skins
        # and its graph edges, marked once): the sparse K^T K product with sorting it replaces
        # took 1.7x as long (59 against 35 ms for 120k surfels).
        # Every surfel's unordered slot pairs s <= t: their upper block (slots), and whether
        # both orders (s, t), (t, s) fall in that block (s < t on one node: a diagonal block).
        self.knn = knn
        self.pair_s, self.pair_t = np.triu_indices(k)
        self.indptr_upper, self.hi, self.slots, self.double = _upper_rows(m, knn, graph, self.pair_s, self.pair_t)
        self.lo = np.repeat(np.arange(m), np.diff(self.indptr_upper))
        self.n_upper = len(self.lo)
        self.diag = self.keys(np.arange(m), np.arange(m))
        # Regulariser edges (self slots of the graph are padding): blocks (i,i), (j,j), (i,j).
        j, i = np.repeat(np.arange(m), graph.shape[1]), graph.reshape(-1)
        real = self.edge_real = i != j
        self.edge_j, self.edge_i = j[real], i[real]
        ej, ei = self.edge_j, self.edge_i
        self.edge_flip = ei > ej
        self.reg_slots = np.stack([self.keys(ei, ei), self.keys(ej, ej),
                                   self.keys(np.minimum(ei, ej), np.maximum(ei, ej))])

    @cached_property
    def reg_writes(self) -> tuple:
        """The regulariser's writes (terms/regulariser.py) grouped by destination, each group in
        the order of one pass over the edges: where each block's writes start (n_upper + 1), the
        writes 3 e + k into block reg_slots[k, e]; where each node's gradient writes start, the
        writes 2 e + 0 into the row of edge_i[e] and 2 e + 1 into that of edge_j[e]."""
        blocks = np.ascontiguousarray(self.reg_slots.T, np.int64).reshape(-1)
        nodes = np.stack([self.edge_i, self.edge_j], 1).reshape(-1)
        return (counting_order(blocks, np.arange(len(blocks)), self.n_upper)
                + counting_order(nodes, np.arange(len(nodes)), self.num_nodes))

    def keys(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Upper block index of node pairs lo <= hi (which must be in the pattern; -1 if not)."""
        lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
        out = np.empty(lo.shape, np.int64)
        _find(self.indptr_upper, self.hi, lo.reshape(-1), hi.reshape(-1), out.reshape(-1))
        return out

    def sum_blocks(self, slots: np.ndarray, weights: np.ndarray, values: np.ndarray) -> np.ndarray:
        """(n_upper, V): sum over rows c of weights[c, p] * values[c] into slot slots[c, p]
        (one sparse-times-dense product: a scatter-add in compiled code)."""
        c, p = slots.shape
        P = sp.csc_matrix((weights.reshape(-1), slots.reshape(-1), np.arange(c + 1) * p), shape=(self.n_upper, c))
        return P @ values

    def reg_blocks(self, values: np.ndarray) -> np.ndarray:
        """The regulariser edges' (i,i), (j,j), (i,j) block parts (3 * edges, V) summed into their
        slots, (i,j) negated (the numpy form: the solve sums its edges in compiled code)."""
        slots = self.reg_slots.reshape(-1)
        sign = np.repeat([1.0, 1.0, -1.0], len(self.edge_i))
        return sp.csc_matrix((sign, slots, np.arange(len(slots) + 1)), shape=(self.n_upper, len(slots))) @ values

    def matrix(self, upper: np.ndarray) -> sp.bsr_matrix:
        """The symmetric (6M, 6M) BSR matrix of upper blocks (n_upper, 6, 6)."""
        off = self.lo != self.hi            # off-diagonal blocks appear mirrored too
        rows = np.concatenate([self.lo, self.hi[off]])
        cols = np.concatenate([self.hi, self.lo[off]])
        blocks = np.concatenate([upper, upper[off].transpose(0, 2, 1)])
        order = np.lexsort((cols, rows))
        indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=self.num_nodes))])
        n = 6 * self.num_nodes
        return sp.bsr_matrix((blocks[order], cols[order], indptr), shape=(n, n))


@numba.njit(cache=True, nogil=True)
def _upper_rows(m, knn, graph, pair_s, pair_t):
    """CSR rows (indptr, sorted columns) of the upper pattern - for each node a: itself, the
    nodes b > a sharing a surfel with it, and its graph neighbours (either direction) - and
    each surfel's slot pairs' blocks and whether both orders of the pair fall in that block (two
    slots on one node), both (n, len(pair_s)). The pairs are bucketed by lower node in
    the surfels' order (random reads of the surfels per node cost 4x more), each with the slot
    it came from; a row, once sorted, gives its pairs their blocks by a lookup of the column's
    place. A binary search of the row per pair took twice as long (7-Scenes: 45 -> 23 ms)."""
    n, k = knn.shape
    g, npairs = graph.shape[1], len(pair_s)
    start = np.zeros(m + 1, np.int64)
    for c in range(n):
        for p in range(npairs):
            u, v = knn[c, pair_s[p]], knn[c, pair_t[p]]
            if u != v:
                start[min(u, v) + 1] += 1
    for j in range(m):
        for t in range(g):
            if graph[j, t] != j:
                start[min(graph[j, t], j) + 1] += 1
    start = np.cumsum(start)
    fill = start[:-1].copy()
    upper = np.empty(start[m], np.int64)
    origin = np.empty(start[m], np.int64)     # the pair's flat slot index; -1 for a graph edge
    for c in range(n):
        for p in range(npairs):
            u, v = knn[c, pair_s[p]], knn[c, pair_t[p]]
            if u != v:
                a = min(u, v)
                upper[fill[a]], origin[fill[a]] = max(u, v), c * npairs + p
                fill[a] += 1
    for j in range(m):
        for t in range(g):
            if graph[j, t] != j:
                a = min(graph[j, t], j)
                upper[fill[a]], origin[fill[a]] = max(graph[j, t], j), -1
                fill[a] += 1
    slots = np.empty(n * npairs, np.int64)
    mark = np.full(m, -1, np.int64)
    place = np.empty(m, np.int64)
    indptr = np.zeros(m + 1, np.int64)
    cols = np.empty(m + start[m], np.int64)
    row = np.empty(m, np.int64)
    total = 0
    for a in range(m):
        width = 1
        row[0] = a
        for q in range(start[a], start[a + 1]):
            b = upper[q]
            if mark[b] != a:
                mark[b] = a
                row[width] = b
                width += 1
        for i in range(1, width):                 # insertion sort: rows are short
            v = row[i]
            j = i - 1
            while j >= 0 and row[j] > v:
                row[j + 1] = row[j]
                j -= 1
            row[j + 1] = v
        for i in range(width):
            place[row[i]] = total + i
        for q in range(start[a], start[a + 1]):
            if origin[q] >= 0:
                slots[origin[q]] = place[upper[q]]
        cols[total:total + width] = row[:width]
        total += width
        indptr[a + 1] = total
    double = np.zeros(n * npairs, np.bool_)
    for c in range(n):                            # a node with itself: its row's first block
        for p in range(npairs):
            u = knn[c, pair_s[p]]
            if u == knn[c, pair_t[p]]:
                slots[c * npairs + p] = indptr[u]
                double[c * npairs + p] = pair_s[p] < pair_t[p]
    return indptr, cols[:total].copy(), slots.reshape(n, npairs), double.reshape(n, npairs)


@numba.njit(cache=True, nogil=True)
def _search(indptr, cols, lo, hi):
    """Index of (lo, hi) in the CSR rows by binary search of row lo's sorted columns; -1 if
    the pair is not in the pattern."""
    a, b = indptr[lo], indptr[lo + 1]
    while a < b:
        mid = (a + b) // 2
        if cols[mid] < hi:
            a = mid + 1
        else:
            b = mid
    return a if a < indptr[lo + 1] and cols[a] == hi else -1


@numba.njit(cache=True, nogil=True)
def _find(indptr, cols, lo, hi, out):
    for i in range(len(lo)):
        out[i] = _search(indptr, cols, lo[i], hi[i])


_IU8 = np.triu_indices(8)
_SYM8 = np.zeros((8, 8), np.int64)
_SYM8[_IU8] = np.arange(len(_IU8[0]))
_SYM8 = np.maximum(_SYM8, _SYM8.T).reshape(-1)        # (8, 8) entry -> index of its upper entry


def pair_blocks(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(E, 6, 6) [S_u, I]^T [S_v, I] with S_y = -[y]x, the form of the regulariser's Jacobians
    (J_i = [S_a, I], J_j = -[S_t_j, I]): [[(u.v) I - v u^T, [u]x], [-[v]x, I]]."""
    out = np.empty((len(u), 6, 6))
    out[:, :3, :3] = -v[:, :, None] * u[:, None, :]
    out[:, [0, 1, 2], [0, 1, 2]] += np.einsum("ei,ei->e", u, v)[:, None]
    out[:, :3, 3:] = skew(u)
    out[:, 3:, :3] = -skew(v)
    out[:, 3:, 3:] = np.eye(3)
    return out


def pair_block_parts(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(E, 16): v u^T, u, v and 1, which pair_blocks(u, v) is linear in: a weighted sum of many
    pair blocks is the blocks of the summed parts (blocks_from_parts), 16 numbers summed per
    residual instead of 36."""
    return np.concatenate([(v[:, :, None] * u[:, None, :]).reshape(-1, 9), u, v, np.ones((len(u), 1))], axis=1)


def blocks_from_parts(parts: np.ndarray) -> np.ndarray:
    """(N, 6, 6) pair blocks of summed pair_block_parts (N, 16)."""
    vu = parts[:, :9].reshape(-1, 3, 3)
    out = np.empty((len(parts), 6, 6))
    out[:, :3, :3] = -vu
    out[:, [0, 1, 2], [0, 1, 2]] += np.trace(vu, axis1=1, axis2=2)[:, None]
    out[:, :3, 3:] = skew(parts[:, 9:12])
    out[:, 3:, :3] = -skew(parts[:, 12:15])
    out[:, 3:, 3:] = parts[:, 15, None, None] * np.eye(3)
    return out


CHUNK = 1 << 15     # correspondences / surfels per batch: keeps the temporaries in cache


def point_blocks(pattern, sel, b, signed, points, normals, D, r, w):
    """point_blocks_reference in one compiled pass over the correspondences (numba): the 36
    products of each pair's 8-vector derivative are summed into its node pairs' slots as they are
    formed. On tube-wall (120k pairs) 13 ms instead of ~47 ms a call."""
    A = np.zeros((pattern.n_upper, 36))
    e = _sums_into(pattern, sel, b, signed, points, normals, r, w, _EVERY_SLOT, A)
    return _blocks_from_sums(pattern.lo, pattern.hi, D, A, e)


def sparse_point_blocks(pattern, sel, b, signed, points, normals, D, r, w):
    """point_blocks on the node pairs the surfels `sel` touch alone: (their slots, their blocks
    (len(slots), 6, 6), the gradient); normals (G, n, 3) and r (G, n) give each correspondence G
    rows (a feature's three axes). For the sparse terms (features, free space): on a room
    they touch a few % of ~50k pairs, and pattern-sized arrays (zeroed, sandwiched, added:
    ~12 ms a call on 7-Scenes) cost them more than their sums."""
    touched = np.zeros(pattern.n_upper, bool)
    touched[pattern.slots[np.asarray(sel, np.int64)]] = True
    slots = np.flatnonzero(touched)
    compact = np.full(pattern.n_upper, -1, np.int64)
    compact[slots] = np.arange(len(slots))
    A = np.zeros((len(slots), 36))
    e = _sums_into(pattern, sel, b, signed, points, normals, r, w, compact, A)
    return (slots, *_blocks_from_sums(pattern.lo[slots], pattern.hi[slots], D, A, e))


_EVERY_SLOT = np.zeros(0, np.int64)     # point_sums' slot map meaning "as they are"
# Calls of CHUNK or more correspondences sum TASKS parts apart, a thread each, then add them.
# Fixed, so that the order of the sums (every bit of the blocks) does not depend on the cores.
# Calls of MIN_SPLIT up to CHUNK split the rows of the sums between TASKS threads instead, each
# walking every correspondence: the bits of one thread (a sheet's 29k pairs: ~20 -> ~13 ms).
TASKS = 2
MIN_SPLIT = 4096
BLOCKS_CHUNK = 2048     # node pairs a thread's task in the blocks D A D^T


def _sums_into(pattern, sel, b, signed, points, normals, r, w, compact, A):
    """normals (n, 3) and r (n,): a row a correspondence; (G, n, 3) and (G, n): G rows each."""
    e = np.zeros((pattern.num_nodes, 8))
    groups = 1 if np.ndim(r) == 1 else len(r)
    point_sums_split(np.ascontiguousarray(sel, np.int64), np.ascontiguousarray(b, np.float64),
                     np.ascontiguousarray(signed, np.float64), np.ascontiguousarray(points, np.float64),
                     np.ascontiguousarray(np.reshape(normals, (groups, len(sel), 3)), np.float64),
                     np.ascontiguousarray(np.reshape(r, (groups, len(sel))), np.float64),
                     np.ascontiguousarray(w, np.float64), pattern.knn, pattern.slots, pattern.double,
                     pattern.pair_s, pattern.pair_t, compact, A, e, TASKS if len(sel) >= MIN_SPLIT else 1,
                     len(sel) < CHUNK)
    return e


def _blocks_from_sums(lo, hi, D, A, e):
    """Blocks D_lo A D_hi^T of the summed symmetric 8x8 products A (one row per pair lo, hi)
    and the gradient D e: compiled, as numpy's batched 6x8x8 products cost as much as the sums."""
    blocks = np.empty((len(lo), 6, 6))
    sandwich(np.ascontiguousarray(D, np.float64), lo, hi, A, _SYM8.reshape(8, 8), blocks, BLOCKS_CHUNK)
    return blocks, np.einsum("nij,nj->ni", D, e)


def point_blocks_reference(pattern, sel, b, signed, points, normals, D, r, w):
    """Data blocks and gradient of the surfels sel (into pattern.knn and the per-surfel blends b,
    signed weights and reference points, the points as components (3, N)) with depth normals
    (C, 3), residuals and weights per pair.

    The Jacobian factors as J[c, s] = signed[c, s] D[knn[c, s]] rows[c] (residual_rows), so
    block (n1, n2) = D_n1 [sum w_c signed_s signed_t rows_c rows_c^T] D_n2^T: the sum over slot
    pairs runs on the 36 distinct entries of the symmetric 8x8 rows_c rows_c^T."""
    A = np.zeros((pattern.n_upper, 36))
    e = np.zeros((pattern.num_nodes, 8))
    k = pattern.knn.shape[1]
    for start in range(0, len(sel), CHUNK):
        part = slice(start, start + CHUNK)
        idx = sel[part]
        # np.take: several times faster than fancy indexing for row gathers of 2-D arrays.
        rows = residual_rows(_components(np.take(b, idx, axis=0)), np.take(points, idx, axis=1),
                             _components(normals[part]))
        sg, wc = np.take(signed, idx, axis=0), w[part]
        pw = np.take(sg, pattern.pair_s, axis=1) * np.take(sg, pattern.pair_t, axis=1)
        pw *= wc[:, None]
        pw[np.take(pattern.double, idx, axis=0)] *= 2.0
        Q = np.take(rows, _IU8[0], axis=1) * np.take(rows, _IU8[1], axis=1)      # C-ordered (c, 36)
        A += pattern.sum_blocks(np.take(pattern.slots, idx, axis=0), pw, Q)
        c = len(idx)
        Kt = sp.csc_matrix((sg.reshape(-1), np.take(pattern.knn, idx, axis=0).reshape(-1), np.arange(c + 1) * k),
                           shape=(pattern.num_nodes, c))
        e += Kt @ ((wc * r[part])[:, None] * rows)
    return _blocks_from_sums(pattern.lo, pattern.hi, D, A, e)


def dense_point_blocks(pattern, J, r, w):
    """Data blocks and gradient from per-slot Jacobians (C, k, 6) of all the pattern's surfels."""
    knn, s, t = pattern.knn, pattern.pair_s, pattern.pair_t
    a, b = knn[:, s], knn[:, t]
    X = np.einsum("cpi,cpj->cpij", J[:, s], J[:, t])
    upper = np.where((a < b)[..., None, None], X, X.transpose(0, 1, 3, 2))
    upper += np.where(pattern.double[..., None, None], X, 0.0)
    p = len(s)
    blocks = pattern.sum_blocks(pattern.slots.reshape(-1, 1), np.repeat(w, p), upper.reshape(-1, 36))
    m = pattern.num_nodes
    g = np.bincount((6 * knn[:, :, None] + np.arange(6)).reshape(-1), ((w * r)[:, None, None] * J).reshape(-1),
                    minlength=6 * m)
    return blocks.reshape(-1, 6, 6), g.reshape(m, 6)


@dataclass(frozen=True)
class Border:
    """One extra 6-variable block bordering the node system (the rest anchors' common motion)."""
    B: np.ndarray      # (M, 6, 6) coupling of each node's twist to the border's
    C: np.ndarray      # (6, 6) the border's own block
    g: np.ndarray      # (6,) its gradient


@dataclass(eq=False)
class NormalEquations:
    """J^T W J and J^T W r of one Gauss-Newton iteration, summed term by term."""
    pattern: BlockPattern
    free: np.ndarray              # (M,) bool: the nodes solved (the others keep a zero step)
    D: np.ndarray                 # (M, 6, 8) each node's dual quaternion by its twist
    upper: np.ndarray | None = None     # (n_upper, 6, 6) the pattern's upper blocks (None: zero)
    gradient: np.ndarray | None = None  # (M, 6)
    border: Border | None = None
    coarse: CoarseSpace | None = None   # the PCG preconditioner's cells (coarse.py), if it uses them

    def gradient_norm(self) -> float:
        """|g| of the variables solved: the free nodes' gradient and the border's."""
        g = self.gradient[self.free]
        return float(np.sqrt(np.sum(g * g) + (np.sum(self.border.g ** 2) if self.border is not None else 0.0)))

    def blocks(self) -> np.ndarray:
        """The upper blocks (n_upper, 6, 6) to add into in place, and with them a gradient
        (M, 6) to add into (both zeros if no term added yet)."""
        if self.upper is None:
            self.upper = np.zeros((self.pattern.n_upper, 6, 6))
        if self.gradient is None:
            self.gradient = np.zeros((self.pattern.num_nodes, 6))
        return self.upper

    def add(self, gradient: np.ndarray, upper: np.ndarray | None = None, diagonal: np.ndarray | None = None,
            slots: np.ndarray | None = None) -> None:
        """Add a term's gradient (M, 6) and its blocks: on the whole pattern (n_upper, 6, 6), on
        the pattern's `slots` only (len(slots), 6, 6; distinct slots) or on the node diagonal
        only (M, 6, 6). The first term's arrays are taken over, not copied: on a room the
        pattern holds ~10^5 blocks, a pass over them costs a few % of a frame."""
        self.gradient = gradient if self.gradient is None else self.gradient + gradient
        if upper is not None and slots is not None:
            self.blocks()[slots] += upper
        elif upper is not None:
            self.upper = upper if self.upper is None else self.upper + upper
        if diagonal is not None:
            if self.upper is None:
                self.upper = np.zeros((self.pattern.n_upper, 6, 6))
            self.upper[self.pattern.diag] += diagonal
