"""Non-rigid warp field estimation by Gauss-Newton (SurfelWarp Sec. VII Eq. 8-10, DynamicFusion Eq. 6-8).

E = sum_c rho(n_c . (W(v_c) v_c - d_c)) + lambda * sum_j sum_{i in N(j)} |T_i p_j - T_j p_j|^2

The model surfels v_c are warped into the live (world) frame, moved into the camera and paired
with the depth pixel they project to (projective association), gated by distance and normal
angle; d_c, n_c are that pixel's vertex and normal moved to world. With the node-local
convention of warp_field (T_j x = R_j (x - p_j) + p_j + t_j) the regulariser residual of edge
(j, i) is R_i (p_j - p_i) + p_i + t_i - p_j - t_j.

Edges have unit weight (DynamicFusion's alpha_ij = max(sigma_i, sigma_j) is a constant here).

Each node has a twist xi_j = (omega, v) that left-composes its node-local transform,
L_j <- exp(xi_j) L_j, i.e. x_live <- p_j + exp(xi_j) (x_live - p_j): the update turns the live
points of node j about the world point p_j, then shifts them by v. The data Jacobian is the
exact derivative of the dual quaternion blend (not a linear-blend approximation), so it matches
finite differences of the true residual at any field.

J^T W J is summed directly in 6x6 node blocks into a sparsity pattern fixed for the solve
(BlockPattern): the data Jacobian of a pair factors as (signed weight) x (node's 6x8 twist
derivative) x (pair's 8-vector derivative by the blend), so only the 36 distinct products of
that 8-vector are summed per node pair. The damped step is solved by conjugate gradients with a
block-Jacobi preconditioner to a relative residual of pcg_rtol, falling back to sparse LU
(SuperLU) when that does not converge; linear_solver='direct' always uses the LU.

With rest anchors the common motion G of the anchored nodes is one more 6-vector unknown,
coupled to every anchored node: the node system gets a border of one block row and column
(_Bordered), which the same PCG solves.

Each iteration re-associates, solves, and keeps the step only if it lowers the energy over the
same pairs; the solve stops on a step that is tiny or barely lowers the energy, on a step that
does not lower it, or after max_iterations.
"""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field, replace

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .alignment import Alignment, measure
from .anchor import (AnchorTerm, anchor_residuals, common_motion, deviation_m, follow_motion, seen_deviation_m,
                     seen_directions)
from .camera import Intrinsics
from .dual_quaternion import _components, apply_components, dq_blend_indexed, dq_multiply
from .se3 import invert, se3_exp
from .silhouette import FreeSpace, SilhouetteParams
from .warp_field import WarpField, warp

ROBUST = ("none", "huber", "tukey")
LINEAR_SOLVERS = ("pcg", "direct")


@dataclass(frozen=True)
class NonRigidParams:
    lambda_reg: float = 5.0            # SurfelWarp Table 1
    max_iterations: int = 10           # SurfelWarp Sec. VIII
    distance_gate_m: float = 0.03      # pairs farther apart than this are not correspondences
    min_normal_cos: float = 0.7        # normals within ~45 deg; looser than fusion's 0.85
                                       # because the field is still being corrected
    stop_motion_m: float = 1e-4        # the solve ends on an update that moves no node, nor (by
                                       # its rotation) any point sigma from a node, more than this,
    stop_energy_rel: float = 5e-3      # or that lowers the energy by less than this fraction
    max_step_m: float = 0.05           # a step moving a node (or, by its turn, a point sigma from
                                       # it) farther than this is shortened to it: directions
                                       # only the free-space term sees are steep and short
    robust: str = "none"               # data-term penalty: 'none' | 'huber' | 'tukey'
    robust_scale_m: float = 0.01       # Huber corner / Tukey cut-off
    damping: float = 1e-6              # mu = damping * mean(diag(J^T J)) added to the diagonal:
                                       # keeps directions no term constrains solvable
    min_correspondences: int = 16
    linear_solver: str = "pcg"         # 'pcg': block-Jacobi preconditioned conjugate gradients
                                       # (as the GPU solver of Dou et al. that SurfelWarp follows),
                                       # falling back to 'direct' (sparse LU) when it does not
                                       # reach pcg_rtol in pcg_max_iterations; 'direct': LU only
    pcg_rtol: float = 1e-4             # stop at |(H + mu I) x + g| <= pcg_rtol |g|: steps within
                                       # ~1e-3 of the exact one, final energies within ~1e-4
    pcg_max_iterations: int = 500
    free_rings: int | None = 2         # nodes more than this many graph edges from every node
                                       # skinning a solved (visible) surfel are held fixed
                                       # (None: none are). Out of view they only carry the
                                       # regulariser; on a room they are most of the graph and
                                       # make the system slow to solve by PCG.
    # Model points where the camera saw through them are pulled back (silhouette.py).
    silhouette: SilhouetteParams = dc_field(default_factory=SilhouetteParams)


@dataclass(frozen=True)
class NonRigidResult:
    iterations: int                # Gauss-Newton steps solved
    energy: float                  # total E at the returned field (freshly associated)
    data_energy: float             # sum of rho(point-to-plane residual), m^2
    reg_energy: float              # sum of squared regulariser residuals, m^2 (before lambda)
    correspondences: int           # at the returned field
    energies: tuple[float, ...]    # total E at the start of every iteration, then the final one
    converged: bool                # ended on a tiny update or energy decrease (not on the
                                   # iteration limit, an energy rise or too few pairs)
    node_support: np.ndarray | None = None   # (M,) skinning weight of the final pairs per node
    released: np.ndarray | None = None       # (M,) anchored nodes this solve set free (anchor.py)
    silhouette_energy: float = 0.0           # weight * sum of Huber(r) of the free-space term, m^2
    silhouette_points: int = 0               # model points the camera saw through, at the result
    alignment: Alignment | None = None       # model and depth explaining each other, at the result

    @property
    def data_rmse_m(self) -> float:
        return float(np.sqrt(self.data_energy / self.correspondences)) if self.correspondences else float("nan")


@dataclass(frozen=True)
class Correspondences:
    index: np.ndarray     # (C,) into the surfel arrays
    points: np.ndarray    # (C, 3) float64 depth vertices, world
    normals: np.ndarray   # (C, 3) float64 depth normals, world


class _Targets:
    """The depth maps of one solve in world coordinates, as flat components (3, H*W), so that
    association gathers 1-D arrays and transforms nothing per iteration."""

    def __init__(self, depth_vertex_map, depth_normal_map, depth_valid, intrinsics, T_camera_to_world):
        T_cw = np.asarray(T_camera_to_world, np.float64)
        self.T_wc = invert(T_cw)
        self.intrinsics = intrinsics
        self.shape = np.shape(depth_valid)
        self.valid = np.asarray(depth_valid, bool).reshape(-1)
        R, t = T_cw[:3, :3], T_cw[:3, 3]
        with np.errstate(invalid="ignore", over="ignore"):      # invalid pixels are never read
            self.vertex = np.array(_rigid(R, t, np.asarray(depth_vertex_map, np.float64).reshape(-1, 3).T))
            self.normal = np.array(_rigid(R, np.zeros(3), np.asarray(depth_normal_map, np.float64).reshape(-1, 3).T))


def _rigid(R: np.ndarray, t: np.ndarray, p) -> list[np.ndarray]:
    """R p + t on components (3 arrays), element-wise: as a matrix product BLAS would run this
    tall, thin product multi-threaded, which is several times slower on a busy machine."""
    return [p[0] * R[i, 0] + p[1] * R[i, 1] + p[2] * R[i, 2] + t[i] for i in range(3)]


def _associate(live, live_n, targets: _Targets, params: NonRigidParams) -> Correspondences:
    """associate() on world live surfels given as components (3, N)."""
    intr = targets.intrinsics
    qx, qy, qz = _rigid(targets.T_wc[:3, :3], targets.T_wc[:3, 3], live)
    h, w = targets.shape
    front = qz > 1e-6
    z = np.where(front, qz, 1.0)
    u = np.rint(intr.fx * qx / z + intr.cx)
    v = np.rint(intr.fy * qy / z + intr.cy)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    index = np.flatnonzero(inside)
    pixel = v[index].astype(np.int64) * w + u[index].astype(np.int64)
    ok = targets.valid[pixel]
    index, pixel = index[ok], pixel[ok]
    dv, dn = targets.vertex[:, pixel], targets.normal[:, pixel]
    diff = live[:, index] - dv
    keep = (np.einsum("ic,ic->c", diff, diff) < params.distance_gate_m ** 2) & \
           (np.einsum("ic,ic->c", live_n[:, index], dn) > params.min_normal_cos)
    return Correspondences(index[keep], dv[:, keep].T, dn[:, keep].T)    # (C, 3) views of (3, C) arrays


def associate(live_points: np.ndarray, live_normals: np.ndarray, depth_vertex_map: np.ndarray,
              depth_normal_map: np.ndarray, depth_valid: np.ndarray, intrinsics: Intrinsics,
              T_camera_to_world: np.ndarray, params: NonRigidParams = NonRigidParams()) -> Correspondences:
    """Projective association of world-frame live surfels with the camera-frame depth maps."""
    targets = _Targets(depth_vertex_map, depth_normal_map, depth_valid, intrinsics, T_camera_to_world)
    return _associate(_components(live_points), _components(live_normals), targets, params)


def apply_update(field: WarpField, xi: np.ndarray) -> WarpField:
    """L_j <- exp(xi_j) L_j for (M, 6) twists."""
    return field.with_transforms(se3_exp(np.asarray(xi, np.float64).reshape(-1, 6)) @ field.transforms)


# ---------------------------------------------------------------- data term

def data_residuals(field: WarpField, ref_points: np.ndarray, knn: np.ndarray, weights: np.ndarray,
                   target_points: np.ndarray, target_normals: np.ndarray) -> np.ndarray:
    """(C,) n . (W(v) v - d) with the true dual quaternion warp."""
    live, _ = warp(np.asarray(ref_points, np.float64), None, knn, weights, field)
    return np.einsum("ij,ij->i", np.asarray(target_normals, np.float64), live - target_points)


def _residual_rows(b, x, n) -> np.ndarray:
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


def _twist_dual_quaternions(field: WarpField, q: np.ndarray | None = None) -> np.ndarray:
    """(M, 6, 8): derivative of node j's world dual quaternion with respect to its twist.

    L_j <- exp(xi) L_j is the world motion G_j <- exp(xi') G_j with xi' = (omega, v + p_j x omega),
    and d(exp(xi') G_j) = (0, omega'/2) + eps (0, v'/2), times the dual quaternion of G_j.
    """
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


def _jacobian_factors(field: WarpField, ref_points: np.ndarray, knn: np.ndarray, weights: np.ndarray,
                      target_normals: np.ndarray):
    """The data Jacobian in factored form: J[c, s] = signed[c, s] * D[knn[c, s]] @ rows[c]."""
    q = field.dual_quaternions()
    b, signed = dq_blend_indexed(q, knn, weights)
    rows = _residual_rows(_components(b), _components(ref_points), _components(target_normals))
    return signed, rows, _twist_dual_quaternions(field, q)


def _expand_jacobian(signed: np.ndarray, rows: np.ndarray, D: np.ndarray, knn: np.ndarray) -> np.ndarray:
    out = np.empty(knn.shape + (6,))
    for s in range(knn.shape[1]):
        out[:, s] = signed[:, s, None] * np.einsum("cmi,ci->cm", D[knn[:, s]], rows)
    return out


def data_jacobian(field: WarpField, ref_points: np.ndarray, knn: np.ndarray, weights: np.ndarray,
                  target_normals: np.ndarray) -> np.ndarray:
    """(C, k, 6): d residual_c / d xi of node knn[c, s] (zero for zero-weight padding slots)."""
    knn = np.asarray(knn)
    return _expand_jacobian(*_jacobian_factors(field, ref_points, knn, weights, target_normals), knn)


# ---------------------------------------------------------------- regulariser

def _edges(field: WarpField) -> tuple[np.ndarray, np.ndarray]:
    j = np.repeat(np.arange(field.num_nodes), field.graph.shape[1])
    i = field.graph.reshape(-1).astype(np.int64)
    return j, i


def _neighbour_motion(field: WarpField) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per edge (j, i): a = L_i (p_j - p_i) (rotation and translation of L_i), t_j and the residual."""
    j, i = _edges(field)
    p, L = field.nodes.astype(np.float64), field.transforms
    a = np.einsum("eab,eb->ea", L[i, :3, :3], p[j] - p[i]) + L[i, :3, 3]
    t_j = L[j, :3, 3]
    return a, t_j, p[i] + a - p[j] - t_j


def reg_residuals(field: WarpField) -> np.ndarray:
    """(M, K, 3): T_i p_j - T_j p_j for every node j and graph neighbour i (zero for self slots)."""
    return _neighbour_motion(field)[2].reshape(field.num_nodes, -1, 3)


def _skew(v: np.ndarray) -> np.ndarray:
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def reg_jacobian(field: WarpField) -> tuple[np.ndarray, np.ndarray]:
    """d reg_residuals / d xi_i (neighbour) and d xi_j (node), each (M, K, 3, 6).

    d(exp(xi) y)/dxi at 0 is [-[y]x, I]; the neighbour moves a = L_i (p_j - p_i), the node t_j.
    """
    a, t_j, _ = _neighbour_motion(field)
    eye = np.broadcast_to(np.eye(3), a.shape[:-1] + (3, 3))
    Ji = np.concatenate([-_skew(a), eye], axis=-1)
    Jj = -np.concatenate([-_skew(t_j), eye], axis=-1)
    shape = (field.num_nodes, -1, 3, 6)
    return Ji.reshape(shape), Jj.reshape(shape)


# ---------------------------------------------------------------- solver

def _robust(r: np.ndarray, kind: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-residual cost rho(r) (~ r^2 near 0) and IRLS weight rho'(r) / (2 r)."""
    a = np.abs(r)
    if kind == "none":
        return r * r, np.ones_like(r)
    if kind == "huber":
        inside = a <= scale
        return np.where(inside, r * r, 2 * scale * a - scale * scale), np.where(inside, 1.0, scale / np.maximum(a, 1e-300))
    if kind == "tukey":
        s = np.clip(1 - (r / scale) ** 2, 0.0, None)
        return scale * scale / 3 * (1 - s ** 3), s * s
    raise ValueError(f"robust must be one of {ROBUST}, got {kind!r}")


class BlockPattern:
    """The 6x6-block sparsity of J^T W J: the diagonal, graph edges, and node pairs that share a
    skinned surfel. Symmetric; the blocks are summed for the upper triangle (lo <= hi) only and
    mirrored. Built once per solve (the graph and the skinning are fixed within one), so the
    data and regulariser blocks of every iteration are sums into fixed slots instead of a
    general sparse product."""

    _LUT_MAX = 1 << 23     # node pairs looked up in a dense table up to this many (32 MB)

    def __init__(self, num_nodes: int, graph: np.ndarray, knn: np.ndarray):
        m = self.num_nodes = int(num_nodes)
        knn = np.asarray(knn, np.int64)
        knn = knn.reshape(len(knn), -1)
        n, k = knn.shape
        K = sp.csr_matrix((np.ones(n * k), knn.reshape(-1), np.arange(n + 1) * k), shape=(n, m))
        j = np.repeat(np.arange(m), np.shape(graph)[1] if m else 0)
        i = np.asarray(graph, np.int64).reshape(-1)
        E = sp.csr_matrix((np.ones(len(i)), (j, i)), shape=(m, m))
        S = (K.T @ K + E + E.T + sp.identity(m)).tocsr()     # all entries > 0: no cancellation
        S.sum_duplicates()
        S.sort_indices()
        rows = np.repeat(np.arange(m), np.diff(S.indptr))
        cols = S.indices.astype(np.int64)
        upper = rows <= cols
        self.lo, self.hi = rows[upper], cols[upper]
        self.n_upper = len(self.lo)
        if m * m <= self._LUT_MAX:
            self._lut = np.full(m * m, -1, np.int32)
            self._lut[self.lo * m + self.hi] = np.arange(self.n_upper)
        else:
            self._lut = None
            self._table = sp.csr_array((np.arange(1, self.n_upper + 1), (self.lo, self.hi)), shape=(m, m))
        self.indptr, self.indices = S.indptr, S.indices
        # Every surfel's unordered slot pairs s <= t: their upper block, and whether both orders
        # (s, t), (t, s) fall in that block (s < t on one node: a diagonal block).
        self.knn = knn
        self.pair_s, self.pair_t = np.triu_indices(k)
        a, b = knn[:, self.pair_s], knn[:, self.pair_t]
        self.slots = self.keys(np.minimum(a, b), np.maximum(a, b))
        self.double = (a == b) & (self.pair_s < self.pair_t)
        self.up = self.keys(np.minimum(rows, cols), np.maximum(rows, cols))   # full block -> upper block
        self.transposed = rows > cols
        self.diag = self.keys(np.arange(m), np.arange(m))
        # Regulariser edges (self slots of the graph are padding): blocks (i,i), (j,j), (i,j).
        real = self.edge_real = i != j
        self.edge_j, self.edge_i = j[real], i[real]
        ej, ei = self.edge_j, self.edge_i
        self.edge_flip = ei > ej
        slots = np.concatenate([self.keys(ei, ei), self.keys(ej, ej),
                                self.keys(np.minimum(ei, ej), np.maximum(ei, ej))])
        sign = np.repeat([1.0, 1.0, -1.0], len(ei))
        self._reg_scatter = sp.csc_matrix((sign, slots, np.arange(len(slots) + 1)), shape=(self.n_upper, len(slots)))

    def keys(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Upper block index of node pairs lo <= hi (which must be in the pattern)."""
        lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
        if self._lut is not None:
            return self._lut[lo * self.num_nodes + hi]
        return (np.asarray(self._table[lo.reshape(-1), hi.reshape(-1)]) - 1).reshape(lo.shape)

    def sum_blocks(self, slots: np.ndarray, weights: np.ndarray, values: np.ndarray) -> np.ndarray:
        """(n_upper, V): sum over rows c of weights[c, p] * values[c] into slot slots[c, p]
        (one sparse-times-dense product: a scatter-add in compiled code)."""
        c, p = slots.shape
        P = sp.csc_matrix((weights.reshape(-1), slots.reshape(-1), np.arange(c + 1) * p), shape=(self.n_upper, c))
        return P @ values

    def reg_blocks(self, values: np.ndarray) -> np.ndarray:
        return self._reg_scatter @ values

    def matrix(self, upper: np.ndarray) -> sp.bsr_matrix:
        """The symmetric (6M, 6M) BSR matrix of upper blocks (n_upper, 6, 6)."""
        full = upper[self.up]
        full[self.transposed] = full[self.transposed].transpose(0, 2, 1)
        n = 6 * self.num_nodes
        return sp.bsr_matrix((full, self.indices, self.indptr), shape=(n, n))


_IU8 = np.triu_indices(8)
_SYM8 = np.zeros((8, 8), np.int64)
_SYM8[_IU8] = np.arange(len(_IU8[0]))
_SYM8 = np.maximum(_SYM8, _SYM8.T).reshape(-1)        # (8, 8) entry -> index of its upper entry


def _pair_blocks(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(E, 6, 6) [S_u, I]^T [S_v, I] with S_y = -[y]x, the form of the regulariser's Jacobians
    (J_i = [S_a, I], J_j = -[S_t_j, I]): [[(u.v) I - v u^T, [u]x], [-[v]x, I]]."""
    out = np.empty((len(u), 6, 6))
    out[:, :3, :3] = -v[:, :, None] * u[:, None, :]
    out[:, [0, 1, 2], [0, 1, 2]] += np.einsum("ei,ei->e", u, v)[:, None]
    out[:, :3, 3:] = _skew(u)
    out[:, 3:, :3] = -_skew(v)
    out[:, 3:, 3:] = np.eye(3)
    return out


def _reg_terms(field: WarpField, pattern: BlockPattern) -> tuple[np.ndarray, np.ndarray]:
    """Upper blocks (n_upper, 6, 6) of J_r^T J_r and J_r^T r_r (M, 6) of the regulariser."""
    m = field.num_nodes
    a, t, rr = (v[pattern.edge_real] for v in _neighbour_motion(field))
    flip = pattern.edge_flip[:, None]
    # Blocks (i, i), (j, j) and (i, j) = J_i^T J_j = -pair(a, t), stored as (j, i) = -pair(t, a)
    # where j < i (the minus sign is in the scatter matrix).
    u = np.concatenate([a, t, np.where(flip, t, a)])
    v = np.concatenate([a, t, np.where(flip, a, t)])
    blocks = pattern.reg_blocks(_pair_blocks(u, v).reshape(-1, 36)).reshape(-1, 6, 6)
    nodes = np.concatenate([pattern.edge_i, pattern.edge_j])
    gv = np.concatenate([np.concatenate([np.cross(a, rr), rr], 1), -np.concatenate([np.cross(t, rr), rr], 1)])
    g = np.bincount((6 * nodes[:, None] + np.arange(6)).reshape(-1), gv.reshape(-1), minlength=6 * m)
    return blocks, g.reshape(m, 6)


_CHUNK = 1 << 15     # correspondences / surfels per batch: keeps the temporaries in cache


def _data_terms_factored(pattern, sel, b, signed, points, normals, D, r, w):
    """Data blocks and gradient of the surfels sel (into pattern.knn and the per-surfel blends b,
    signed weights and reference points, the points as components (3, N)) with depth normals
    (C, 3), residuals and weights per pair.

    The Jacobian factors as J[c, s] = signed[c, s] D[knn[c, s]] rows[c] (_residual_rows), so
    block (n1, n2) = D_n1 [sum w_c signed_s signed_t rows_c rows_c^T] D_n2^T: the sum over slot
    pairs runs on the 36 distinct entries of the symmetric 8x8 rows_c rows_c^T."""
    A = np.zeros((pattern.n_upper, 36))
    e = np.zeros((pattern.num_nodes, 8))
    k = pattern.knn.shape[1]
    for start in range(0, len(sel), _CHUNK):
        part = slice(start, start + _CHUNK)
        idx = sel[part]
        rows = _residual_rows(_components(b[idx]), points[:, idx], _components(normals[part]))
        sg, wc = signed[idx], w[part]
        pw = np.take(sg, pattern.pair_s, axis=1) * np.take(sg, pattern.pair_t, axis=1)
        pw *= wc[:, None]
        pw[pattern.double[idx]] *= 2.0
        Q = np.take(rows, _IU8[0], axis=1) * np.take(rows, _IU8[1], axis=1)      # C-ordered (c, 36)
        A += pattern.sum_blocks(pattern.slots[idx], pw, Q)
        c = len(idx)
        Kt = sp.csc_matrix((sg.reshape(-1), pattern.knn[idx].reshape(-1), np.arange(c + 1) * k),
                           shape=(pattern.num_nodes, c))
        e += Kt @ ((wc * r[part])[:, None] * rows)
    A = A[:, _SYM8].reshape(-1, 8, 8)
    blocks = (D[pattern.lo] @ A) @ D[pattern.hi].transpose(0, 2, 1)
    return blocks, np.einsum("nij,nj->ni", D, e)


def _data_terms_dense(pattern, J, r, w):
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


def normal_equations(field: WarpField, J_data: np.ndarray, knn: np.ndarray, r_data: np.ndarray,
                     w_data: np.ndarray, lambda_reg: float) -> tuple[sp.bsr_matrix, np.ndarray]:
    """J^T W J (sparse 6x6-block, 6M x 6M) and J^T W r of the data rows (C, k, 6) and the regulariser."""
    pattern = BlockPattern(field.num_nodes, field.graph, knn)
    w = np.asarray(w_data, np.float64)
    bd, gd = _data_terms_dense(pattern, np.asarray(J_data, np.float64), np.asarray(r_data, np.float64), w)
    br, gr = _reg_terms(field, pattern)
    return pattern.matrix(bd + lambda_reg * br), (gd + lambda_reg * gr).reshape(-1)


def _normal_blocks(field, pattern, sel, b, signed, points, normals, D, r, w, lambda_reg):
    """normal_equations for the surfels sel, from their blends (see _data_terms_factored), as
    the pattern's upper blocks (n_upper, 6, 6) and the gradient (M, 6)."""
    bd, gd = _data_terms_factored(pattern, sel, b, signed, points, normals, D, r, w)
    br, gr = _reg_terms(field, pattern)
    return bd + lambda_reg * br, gd + lambda_reg * gr


def anchor_terms(field: WarpField, anchor: AnchorTerm, G: np.ndarray = np.eye(4), center: np.ndarray | None = None):
    """The anchor energy's terms (anchor.py), its rest transforms followed by the common motion G:
    the diagonal blocks (M, 6, 6) and gradient (M, 6) of the node twists (the anchor point
    z = L_j y moves by [-[z]x, I] xi_j under the update, the form _pair_blocks sums), and, given
    a `center`, the border of G's twist zeta (rotation about center, G <- exp(zeta) G): the
    blocks (M, 6, 6) coupling each node's twist to zeta, zeta's own block (6, 6) and its
    gradient (6,); else None. The rest point q = G Rest_j y_a moves by [-[q - c]x, I] zeta and
    enters the residual with a minus sign."""
    res, z = anchor_residuals(field.transforms, follow_motion(anchor.rest, field.nodes, G), field.sigma_m)
    m = field.num_nodes
    mu = anchor.mu[:, None, None]
    blocks = _pair_blocks(z.reshape(-1, 3), z.reshape(-1, 3)).reshape(m, 4, 6, 6).sum(axis=1)
    g = np.concatenate([np.cross(z, res), res], axis=-1).sum(axis=1)
    border = None
    if center is not None:
        q = (field.nodes[:, None, :] + z - res - center).reshape(-1, 3)
        coupling = -mu * _pair_blocks(z.reshape(-1, 3), q).reshape(m, 4, 6, 6).sum(axis=1)
        own = np.einsum("m,mij->ij", anchor.mu, _pair_blocks(q, q).reshape(m, 4, 6, 6).sum(axis=1))
        gz = -np.einsum("m,mai->i", anchor.mu, np.concatenate([np.cross(q.reshape(m, 4, 3), res), res], axis=-1))
        border = (coupling, own, gz)
    return mu * blocks, anchor.mu[:, None] * g, border


def anchor_energy(field: WarpField, anchor: AnchorTerm | None, G: np.ndarray = np.eye(4)) -> float:
    if anchor is None:
        return 0.0
    res, _ = anchor_residuals(field.transforms, follow_motion(anchor.rest, field.nodes, G), field.sigma_m)
    return float(np.sum(anchor.mu * np.sum(res ** 2, axis=(1, 2))))


def turn_about(center: np.ndarray, zeta: np.ndarray) -> np.ndarray:
    """The world rigid motion x -> c + exp(zeta) (x - c)."""
    T = se3_exp(np.asarray(zeta, np.float64))
    T[:3, 3] += center - T[:3, :3] @ center
    return T


class _Bordered:
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
        top = self.H @ x + (self.B @ z).reshape(-1)
        return np.concatenate([top, np.einsum("mij,mi->j", self.B, x.reshape(-1, 6)) + self.C @ z])

    def tosparse(self) -> sp.csr_matrix:
        m = len(self.B)
        Bs = sp.bsr_matrix((self.B, np.zeros(m, np.int64), np.arange(m + 1)), shape=(6 * m, 6)).tocsr()
        return sp.bmat([[self.H, Bs], [Bs.T, sp.csr_matrix(self.C)]], format="csr")


def _solve_step(pattern, upper, g, free, params, border=None) -> tuple[np.ndarray, np.ndarray]:
    """The damped Gauss-Newton step (M, 6) of the nodes `free` (the others keep 0), and that of
    the anchors' common motion (6,) when its `border` (from anchor_terms) is given (else zeros)."""
    H, g, diag = pattern.matrix(upper), g.reshape(-1), upper[pattern.diag]
    if not free.all():
        H, g, diag = restrict(H, g, diag, free)
    if border is not None:
        B, C, gz = border
        H, g, diag = _Bordered(H, B[free], C), np.concatenate([g, gz]), np.concatenate([diag, C[None]])
    ok = False
    if params.linear_solver == "pcg":
        xi, _, ok = solve_step_pcg(H, g, params.damping, params.pcg_rtol, params.pcg_max_iterations, diag)
    if not ok:
        xi = solve_step(H.tosparse() if border is not None else H, g, params.damping)
    zeta = np.zeros(6)
    if border is not None:
        xi, zeta = xi[:-6], xi[-6:]
    if not free.all():
        xi = _expand(xi, free)
    return xi.reshape(-1, 6), zeta


def free_nodes(graph: np.ndarray, supported: np.ndarray, rings: int) -> np.ndarray:
    """(M,) bool: the supported nodes and those within `rings` graph edges of one (either
    direction of an edge counts)."""
    free = np.asarray(supported, bool).copy()
    graph = np.asarray(graph, np.int64)
    for _ in range(max(rings, 0)):
        grown = free | free[graph].any(axis=1)
        grown[graph[free].reshape(-1)] = True
        if np.array_equal(grown, free):
            break
        free = grown
    return free


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


def _warp_state(field, ref_points, ref_normals, knn, weights):
    """Everything one field gives the surfels (reference points and normals as components
    (3, N)): node dual quaternions, blends (N, 8), signed weights (N, k), live points and
    normals (3, N)."""
    dq = field.dual_quaternions()
    n = len(knn)
    b, signed, live, live_n = np.empty((n, 8)), np.empty(knn.shape), np.empty((3, n)), np.empty((3, n))
    for start in range(0, n, _CHUNK):
        part = slice(start, start + _CHUNK)
        b[part], signed[part] = dq_blend_indexed(dq, knn[part], weights[part])
        p, pn = apply_components(_components(b[part]), ref_points[:, part], ref_normals[:, part])
        for i in range(3):
            live[i, part], live_n[i, part] = p[i], pn[i]
    return dq, b, signed, live, live_n


def _energy(field, corr, live, params, anchor=None, G=np.eye(4)):
    """(total, data, reg, residuals, IRLS weights) at `field` over the pairs corr, given the
    field's live points (3, N); the total includes the anchor energy (rest followed by G)."""
    r = np.einsum("ci,ic->c", corr.normals, live[:, corr.index] - corr.points.T)
    cost, w = _robust(r, params.robust, params.robust_scale_m)
    data, reg = float(np.sum(cost)), float(np.sum(reg_residuals(field) ** 2))
    return data + params.lambda_reg * reg + anchor_energy(field, anchor, G), data, reg, r, w


def _silhouette(free_space: FreeSpace | None, live: np.ndarray, live_n: np.ndarray, params: NonRigidParams):
    """(energy, points, residuals, gradients (3, S), IRLS weights) of the free-space term at
    the live points and normals (3, N): the points the camera saw through and theirs."""
    if free_space is None:
        return 0.0, np.zeros(0, np.int64), np.zeros(0), np.zeros((3, 0)), np.zeros(0)
    r, grad = free_space.residuals(live)
    sel = np.flatnonzero(r > 0)
    sel = sel[free_space.facing(live[:, sel], live_n[:, sel])]
    cost, w = _robust(r[sel], "huber", params.silhouette.huber_m)
    weight = params.silhouette.weight
    return weight * float(np.sum(cost)), sel, r[sel], grad[:, sel], weight * w


def _release(field, pattern, upper, g, free, anchor, support, seen, params) -> tuple[np.ndarray, np.ndarray]:
    """(M,) anchored nodes the data and regulariser alone would move in one step farther than
    their release distance from rest, measured with the metric seen (M, 3, 3) (the directions
    their pairs see, anchor.py; None: every direction alike), and the common motion G (4, 4)
    the rest follows: the one the still supported nodes share (identity unless
    anchor.common_motion)."""
    stepped = apply_update(field, _solve_step(pattern, upper, g, free, params)[0]).transforms
    anchored = anchor.mu > 0
    G = np.eye(4)
    if anchor.common_motion:
        G = common_motion(stepped, anchor.rest, field.nodes, field.sigma_m, support * anchored, anchor.release_m)
    rest = follow_motion(anchor.rest, field.nodes, G)
    moved = deviation_m(stepped, rest, field.sigma_m) if seen is None else \
        seen_deviation_m(stepped, rest, field.sigma_m, seen)
    return anchored & (support >= anchor.release_support) & (moved > anchor.release_m), G


def solve_nonrigid(field: WarpField, ref_points: np.ndarray, ref_normals: np.ndarray, knn: np.ndarray,
                   weights: np.ndarray, depth_vertex_map: np.ndarray, depth_normal_map: np.ndarray,
                   depth_valid: np.ndarray, intrinsics: Intrinsics, T_camera_to_world: np.ndarray,
                   params: NonRigidParams = NonRigidParams(),
                   anchor: AnchorTerm | None = None,
                   depth_beyond: np.ndarray | None = None) -> tuple[WarpField, NonRigidResult]:
    """Gauss-Newton on Eq. 8 starting from `field`; returns the improved field and a summary.

    ref_points/ref_normals (N, 3) are the reference positions of the model surfels to use (the
    visible ones), knn/weights their skinning; the depth maps are the observation's, camera frame.
    With an anchor term (anchor.py), its nodes are held at rest up to one rigid motion G they
    share, solved with them, except those the first iteration releases; nodes held out of the
    solve follow G at the end. depth_beyond (H, W), if given, marks pixels measured past the far
    clip, free space for the free-space term (silhouette.py).
    """
    if params.robust not in ROBUST:
        raise ValueError(f"robust must be one of {ROBUST}, got {params.robust!r}")
    if params.linear_solver not in LINEAR_SOLVERS:
        raise ValueError(f"linear_solver must be one of {LINEAR_SOLVERS}, got {params.linear_solver!r}")
    ref_points = _components(np.reshape(ref_points, (-1, 3)))          # (3, N) throughout
    ref_normals = _components(np.reshape(ref_normals, (-1, 3)))
    knn = np.asarray(knn, np.int64)
    weights = np.asarray(weights, np.float64)
    targets = _Targets(depth_vertex_map, depth_normal_map, depth_valid, intrinsics, T_camera_to_world)
    free_space = None
    if params.silhouette.weight > 0:
        free_space = FreeSpace(np.asarray(depth_vertex_map)[..., 2], intrinsics, T_camera_to_world, params.silhouette,
                               depth_beyond)
    pattern = None

    def warped(f):
        return _warp_state(f, ref_points, ref_normals, knn, weights)

    current, state, energies, steps, converged = field, None, [], 0, False
    released, G, center, border, held_rows = None, np.eye(4), None, None, None
    free = np.ones(field.num_nodes, bool) if params.free_rings is None else None
    for _ in range(params.max_iterations):
        state = warped(current) if state is None else state
        dq, b, signed, live, live_n = state
        corr = _associate(live, live_n, targets, params)
        if len(corr.index) < params.min_correspondences:
            break
        idx = corr.index
        total, _, _, r, w = _energy(current, corr, live, params, anchor, G)
        if pattern is None:
            pattern = BlockPattern(current.num_nodes, current.graph, knn)
        D = _twist_dual_quaternions(current, dq)
        upper, g = _normal_blocks(current, pattern, idx, b, signed, ref_points, corr.normals, D, r, w,
                                  params.lambda_reg)
        if free is None:
            in_view = np.zeros(current.num_nodes, bool)
            in_view[knn.reshape(-1)] = True
            free = free_nodes(current.graph, in_view, params.free_rings)
        if anchor is not None:
            if released is None:
                # Nodes held out of the solve do not see the depth: they neither release nor
                # pull on the common motion (they follow it at the end).
                solved = replace(anchor, mu=anchor.mu * free)
                support = np.bincount(knn[idx].ravel(), weights[idx].ravel(), minlength=current.num_nodes)
                u = anchor.release_unseen_weight
                seen = None if u >= 1 else (1 - u) * seen_directions(
                    current.num_nodes, knn[idx], weights[idx], corr.normals) + u * np.eye(3)
                released, G = _release(current, pattern, upper, g, free, solved, support, seen, params)
                held = replace(solved, mu=np.where(released, 0.0, solved.mu))
                total += anchor_energy(current, held, G) - anchor_energy(current, anchor)
                at_rest, anchor = (anchor.mu > 0) & ~released, held
                if anchor.common_motion and anchor.mu.any():
                    center = np.average(current.live_nodes(), axis=0, weights=anchor.mu)
                    if anchor.held is not None and len(anchor.held):
                        # G goes into the camera pose: not along what rigid ICP held.
                        G = anchor.held.project(G)
                        held_rows = anchor.held.rows(center)
            blocks, ga, border = anchor_terms(current, anchor, G, center)
            if held_rows is not None and len(held_rows):
                B, C, gz = border
                border = (B, C + 1e4 * max(np.trace(C) / 6, 1e-12) * held_rows.T @ held_rows, gz)
            upper[pattern.diag] += blocks
            g = g + ga
        e_sil, sel, r_sil, grad_sil, w_sil = _silhouette(free_space, live, live_n, params)
        if len(sel):
            # The term's Jacobian is the data term's with the residual's gradient for a normal.
            # (Added after the release test: its pull at an edge is not a node's own motion.)
            bs, gs = _data_terms_factored(pattern, sel, b, signed, ref_points, grad_sil.T, D, r_sil, w_sil)
            upper, g, total = upper + bs, g + gs, total + e_sil
        energies.append(total)
        xi, zeta = _solve_step(pattern, upper, g, free, params, border)
        steps += 1
        if not (np.all(np.isfinite(xi)) and np.all(np.isfinite(zeta))):
            break
        candidate, G_candidate = apply_update(current, xi), turn_about(center, zeta) @ G if center is not None else G
        moved = np.linalg.norm(candidate.transforms[:, :3, 3] - current.transforms[:, :3, 3], axis=1)
        turned = np.linalg.norm(xi[:, :3], axis=1)
        if np.max(moved + current.sigma_m * turned) < params.stop_motion_m:
            current, state, G, converged = candidate, None, G_candidate, True
            break
        # The candidate's warp gives its energy and, if it is kept, the next association. A
        # step that raises it is halved (twice at most): the free-space term is far from
        # linear over a long step.
        longest = min(1.0, params.max_step_m / np.max(moved + current.sigma_m * turned))
        for scale in (longest, 0.5 * longest, 0.25 * longest):
            if scale < 1.0:
                candidate = apply_update(current, scale * xi)
                G_candidate = turn_about(center, scale * zeta) @ G if center is not None else G
            cand_state = warped(candidate)
            e_new = (_energy(candidate, corr, cand_state[3], params, anchor, G_candidate)[0]
                     + _silhouette(free_space, cand_state[3], cand_state[4], params)[0])
            if e_new < total:
                break
        if not e_new < total:
            break
        current, state, G = candidate, cand_state, G_candidate
        if total - e_new < params.stop_energy_rel * total:
            converged = True
            break

    if center is not None and not free.all():
        # The nodes the solve held out follow the common motion of those it solved, as rigid
        # ICP's motion would move them: the anchored ones at rest, the others as they are.
        out, rest = ~free, ~free & at_rest
        transforms = current.transforms.copy()
        transforms[out] = follow_motion(transforms[out], current.nodes[out], G)
        transforms[rest] = follow_motion(anchor.rest[rest], current.nodes[rest], G)
        current, state = current.with_transforms(transforms), None
    state = warped(current) if state is None else state
    corr = _associate(state[3], state[4], targets, params)
    total, data, reg, _, _ = _energy(current, corr, state[3], params, anchor, G)
    e_sil, sel = _silhouette(free_space, state[3], state[4], params)[:2]
    total += e_sil
    energies.append(total)
    support = np.bincount(knn[corr.index].ravel(), weights[corr.index].ravel(), minlength=current.num_nodes)
    vertex = np.asarray(depth_vertex_map)
    alignment = measure(state[3].T, state[4].T, T_camera_to_world, vertex[..., 2], vertex, depth_valid, intrinsics)
    return current, NonRigidResult(steps, total, data, reg, len(corr.index), tuple(energies), converged, support,
                                   released, e_sil, len(sel), alignment)
