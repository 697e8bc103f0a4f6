"""Appending unmatched depth surfels (SurfelWarp Sec. VI-B, VI-C and the gates of VI-D).

A depth surfel that fused into no live surfel is a candidate. It is skinned at the live frame
(Sec. VI-B: k nearest *live* node positions, then Eq. 6 drops neighbours whose distance to the
nearest node changed by more than a factor 1 +- epsilon between the reference and the live
frame), rejected if its unnormalised weight sum is below delta_nn or if the inverse warp is
compressive there (Eq. 7), and finally inverse-warped to the reference frame with that same
live skinning.

Design decisions:
- Shared skinning. The appended surfel keeps its live-frame N(s) and weights for S_ref and
  S_live alike (Sec. IV: one neighbour set shared by both). Then warp(inverse_warp(x)) == x
  exactly, so the new surfel sits where it was observed. It is not re-skinned at its reference
  position: warp_field.update_skinning recomputes reference-distance weights whenever nodes
  are added, and dropped Eq. 6 slots follow warp_field's padding convention (nearest node,
  weight 0, at the end), which update_skinning already treats as padding.
- Weight sum for delta_nn: sum over the *kept* nodes of exp(-d^2 / 2 sigma^2), d the live
  distance; node_0 is always kept, so it is at least node_0's own weight.
- Strain (Eq. 7). Differentiating the inverse warp with the candidate's own skinning held
  fixed is useless: with fixed weights x_ref is a rigid map of x_live (Jacobian a rotation),
  and with the Eq. 6-pruned nodes and recomputed weights it is still rigid wherever the field
  is compressed, because Eq. 6 has left node_0 alone there. Redoing the whole skinning at each
  perturbed point is discontinuous where the k-NN set or node_0 changes; with sigma = node
  spacing and k = 4 that alone flagged 15-35% of the points of a mild, nowhere-compressive
  warp of the DeepDeform shirt. So two smooth estimates are taken (inverse_strains) and a
  candidate is discarded if either exceeds 1 + epsilon:
    live side - the inverse warp at the live point blended over the k nearest live nodes
      *before* Eq. 6, weights recomputed at each perturbed point. This is what catches
      open-to-close contact, where live nodes from distant reference places meet (two sheets
      brought within 5 mm: 42% of the candidates got the other sheet's reference position,
      98.7% of those were flagged); but as live nodes coincide their weights become equal and
      the blend goes rigid again (1D squeeze to 0.1x: strain 1.11).
    reference side - 1 / smallest singular value of the forward warp's Jacobian at the
      tentative reference position (inverse function theorem), reference k-NN and recomputed
      weights: grows as the field collapses (0.1x squeeze: median 2.97), but cannot see
      contact, since the tentative position is then on one sheet, where the field is rigid.
- "Exceeds 1 + epsilon" means the largest singular value of the 3x3 Jacobian d x_ref / d x_live
  does: the largest stretch of any live direction, the 3D reading of |dx_ref / dx_live|, and
  independent of the rotation that the Jacobian also contains.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

from surfelwarp.deform.warp_field import WarpField, inverse_warp
from surfelwarp.geometry.dual_quaternion import dq_to_transform
from surfelwarp.methods.surfelwarp.appending_kernels import NO_NODE, strains
from surfelwarp.methods.surfelwarp.surfels import SurfelModel
from surfelwarp.preprocess import CameraObservation


@dataclass(frozen=True)
class AppendParams:
    intrinsic_epsilon: float = 0.2          # epsilon, SurfelWarp Table 1 (Eq. 6 and Eq. 7)
    # delta_nn on the unnormalised weight sum (no value in the paper). exp(-2) is the weight of
    # one node at 2 sigma: a candidate whose nearest node is within 2 sigma always passes; with
    # k = 4 kept nodes one farther than sigma * sqrt(2 ln(4 / exp(-2))) = 2.6 sigma from all of
    # them always fails. Node sampling puts every model point within sigma of a node, so this
    # lets new geometry grow up to ~2 sigma past the node graph per frame.
    min_weight_sum: float = float(np.exp(-2.0))
    # Central-difference step for Eq. 7; None: 0.1 sigma (2.5 mm at the default node radius).
    # The blend varies on the scale of sigma, so the truncation error is ~(0.1)^2 / 6 relative.
    strain_step_m: float | None = None

    ZERO_OK = {"intrinsic_epsilon", "min_weight_sum"}
    UNIT = {"min_weight_sum"}


@dataclass(frozen=True, eq=False)
class AppendResult:
    """Accepted candidates, all positions and normals in world coordinates."""
    pixel_rows: np.ndarray       # (A,) int64 depth pixel of each appended surfel
    pixel_cols: np.ndarray
    live_position: np.ndarray    # (A, 3) float32, the observation moved to world
    live_normal: np.ndarray      # (A, 3) float32
    radius: np.ndarray           # (A,) float32
    confidence: np.ndarray       # (A,) float32
    knn: np.ndarray              # (A, k) int32 live skinning after Eq. 6 (dropped: node_0, weight 0)
    weights: np.ndarray          # (A, k) float32, sum 1
    ref_position: np.ndarray     # (A, 3) float32, inverse-warped with knn/weights
    ref_normal: np.ndarray       # (A, 3) float32
    candidates: int              # unmatched valid depth pixels considered
    rejected_weight: int         # failed delta_nn
    rejected_compressive: int    # passed delta_nn, failed Eq. 7
    color: np.ndarray | None = None   # (A, 3) float32 RGB of each surfel's pixel; None without colour

    def __len__(self) -> int:
        return len(self.radius)

    def surfels(self, time: int, first_id: int) -> SurfelModel:
        """The accepted candidates as new surfels (t_init = t_observed = time); without colour
        their colour is 0 with weight 0 (SurfelModel.color_weight)."""
        n = len(self)
        t = np.full(n, time, np.int32)
        if self.color is None:
            color, color_weight = np.zeros((n, 3), np.float32), np.zeros(n, np.float32)
        else:
            color, color_weight = self.color, self.confidence.copy()
        return SurfelModel(self.ref_position, self.ref_normal, self.live_position, self.live_normal,
                           self.radius, self.confidence, t, t.copy(), self.knn, self.weights,
                           np.arange(first_id, first_id + n, dtype=np.uint32), color, color_weight)


def _sq_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distances over the last axis (einsum: ~3x faster than sum over a length-3 axis)."""
    d = a - b
    return np.einsum("...i,...i->...", d, d)


def _live_neighbours(live_points: np.ndarray, field: WarpField, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(A, k) int64 nearest live nodes, nearest first, and their squared live distances
    (float64); slots beyond the node count repeat the nearest with distance inf."""
    if field.num_nodes == 0:
        raise ValueError("live skinning needs at least one node")
    pts = np.asarray(live_points, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros((0, k), np.int64), np.zeros((0, k))
    live_nodes = field.live_nodes()
    j = min(k, field.num_nodes)
    _, idx = KDTree(live_nodes.astype(np.float32)).query(pts.astype(np.float32), k=j)
    idx = idx.reshape(len(pts), j).astype(np.int64)
    d2 = _sq_dist(pts[:, None, :], live_nodes[idx])
    if j < k:
        idx = np.concatenate([idx, np.repeat(idx[:, :1], k - j, 1)], 1)
        d2 = np.concatenate([d2, np.full((len(pts), k - j), np.inf)], 1)
    return idx, d2


def _gaussian(d2: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Normalised weights (inf distance: 0) and the unnormalised sum, over the last axis (k
    slots; reduced slot by slot, which numpy does ~5x faster than a reduce over a short axis)."""
    inv = 1.0 / (2.0 * sigma * sigma)
    slots = np.moveaxis(d2, -1, 0)
    nearest = slots[0].copy()
    for s in slots[1:]:
        np.minimum(nearest, s, out=nearest)
    # Relative to the nearest slot, so that points far from every node do not underflow.
    w = np.exp(-(d2 - nearest[..., None]) * inv)
    norm = np.moveaxis(w, -1, 0).sum(axis=0)
    return w / norm[..., None], norm * np.exp(-nearest * inv)


def _consistent(knn: np.ndarray, field: WarpField, epsilon: float) -> np.ndarray:
    """(A, k) bool Eq. 6: slot i keeps its node if its live distance to node_0 is within a factor
    1 +- epsilon of the reference distance. Slot 0 is always kept; repeats of node_0 never."""
    live_nodes, ref_nodes = field.live_nodes(), field.nodes.astype(np.float64)
    d_live = np.sqrt(_sq_dist(live_nodes[knn], live_nodes[knn[:, :1]]))
    d_ref = np.sqrt(_sq_dist(ref_nodes[knn], ref_nodes[knn[:, :1]]))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = d_live / d_ref
    keep = (d_ref > 0) & (ratio > 1.0 - epsilon) & (ratio < 1.0 + epsilon)
    keep[:, 0] = True
    return keep


def _prune(idx: np.ndarray, d2: np.ndarray, field: WarpField, params: "AppendParams"):
    """skin_live from the k nearest live nodes and their squared distances."""
    keep = _consistent(idx, field, params.intrinsic_epsilon) & np.isfinite(d2)
    # Kept slots first (stable, so still nearest first); dropped ones become padding.
    order = np.argsort(~keep, axis=1, kind="stable")
    keep = np.take_along_axis(keep, order, 1)
    knn = np.where(keep, np.take_along_axis(idx, order, 1), idx[:, :1])
    w, total = _gaussian(np.where(keep, np.take_along_axis(d2, order, 1), np.inf), field.sigma_m)
    return knn.astype(np.int32), w.astype(np.float32), total


def skin_live(live_points: np.ndarray, field: WarpField, k: int,
              params: AppendParams = AppendParams()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sec. VI-B live skinning of world-frame live points.

    Returns knn (A, k) int32 (nearest live node first, Eq. 6 survivors next, dropped slots
    filled with node_0), weights (A, k) float32 from live distances, normalised over the kept
    nodes (dropped: 0), and the unnormalised weight sum over the kept nodes (A,) float64.
    """
    return _prune(*_live_neighbours(live_points, field, k), field, params)


def _signed_dqs(field: WarpField, knn: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N, k, 8) node dual quaternions of each point, flipped into the hemisphere of its
    heaviest node (warp_field.blend's antipodal fix), so that perturbed blends can reuse them."""
    q = field.dual_quaternions()[knn]
    pivot = np.take_along_axis(q[..., :4], np.argmax(weights, axis=1)[:, None, None].repeat(4, -1), 1)
    return q * np.where(np.einsum("nki,nki->nk", q[..., :4], pivot) < 0, -1.0, 1.0)[..., None]


def _perturbed_transforms(x: np.ndarray, h: float, node_pos: np.ndarray, active: np.ndarray,
                          sigma: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points x (N, 3) moved by +-h along each axis, (6, N, 3) in the order +x +y +z -x -y -z,
    and the DQB transforms there (6, N, 4, 4): the nodes (N, k, 3) and their signed dual
    quaternions q stay, the Gaussian weights follow the moved point (inactive slots: 0).
    Same blend as warp_field.blend, without re-gathering node data for every perturbation."""
    offsets = np.concatenate([h * np.eye(3), -h * np.eye(3)])
    xs = x[None, :, :] + offsets[:, None, :]
    d2 = _sq_dist(xs[:, :, None, :], node_pos[None])
    w, _ = _gaussian(np.where(active[None], d2, np.inf), sigma)
    return xs, dq_to_transform(np.einsum("snk,nki->sni", w, q))


def _central_difference(y: np.ndarray, h: float) -> np.ndarray:
    """(N, 3, 3) Jacobian [point, output, axis] from outputs (6, N, 3) at x+-h e_axis."""
    return np.moveaxis((y[:3] - y[3:]) / (2.0 * h), 0, -1)


def _singular_values(J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest singular values of (N, 3, 3): closed-form (trigonometric) eigenvalues
    of the symmetric J^T J, ~10x faster than batched LAPACK on 3x3s."""
    A = np.einsum("nji,njk->nik", J, J)
    q = np.trace(A, axis1=1, axis2=2) / 3.0
    off = A[:, 0, 1] ** 2 + A[:, 0, 2] ** 2 + A[:, 1, 2] ** 2
    dev = (A[:, 0, 0] - q) ** 2 + (A[:, 1, 1] - q) ** 2 + (A[:, 2, 2] - q) ** 2
    p = np.sqrt((dev + 2.0 * off) / 6.0)
    B = (A - q[:, None, None] * np.eye(3)) / np.where(p > 0, p, 1.0)[:, None, None]
    r = np.clip(0.5 * np.linalg.det(B), -1.0, 1.0)
    phi = np.arccos(r) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return np.sqrt(np.maximum(smallest, 0.0)), np.sqrt(np.maximum(largest, 0.0))


def _strains(x: np.ndarray, knn: np.ndarray, weights: np.ndarray, idx: np.ndarray, d2: np.ndarray,
             field: WarpField, params: "AppendParams") -> tuple[np.ndarray, np.ndarray]:
    """inverse_strains, given the unpruned live neighbours idx / d2 of _live_neighbours, in
    compiled code (appending_kernels.py; _strains_reference is its numpy form)."""
    n, h = len(x), _strain_step(field, params)
    x_ref, ref_idx = _reference_neighbours(x, knn, weights, idx.shape[1], field)
    live_side, ref_side = np.empty(n), np.empty(n)
    strains(np.ascontiguousarray(x, np.float64), np.where(np.isfinite(d2), idx, NO_NODE), field.live_nodes(),
            np.ascontiguousarray(x_ref, np.float64), ref_idx, field.nodes.astype(np.float64),
            field.dual_quaternions(), float(field.sigma_m), float(h), live_side, ref_side)
    return live_side, ref_side


def _strain_step(field: WarpField, params: "AppendParams") -> float:
    """Eq. 7's central-difference step."""
    return 0.1 * field.sigma_m if params.strain_step_m is None else params.strain_step_m


def _reference_neighbours(x: np.ndarray, knn: np.ndarray, weights: np.ndarray, k: int, field: WarpField
                          ) -> tuple[np.ndarray, np.ndarray]:
    """The candidates' tentative reference positions (inverse warp) and their k nearest
    reference nodes (N, min(k, nodes)) int64."""
    x_ref, _ = inverse_warp(x, None, knn, weights, field)
    j = min(k, field.num_nodes)
    _, ref_idx = KDTree(field.nodes).query(x_ref.astype(np.float32), k=j)
    return x_ref, ref_idx.reshape(len(x), j).astype(np.int64)


def _strains_reference(x: np.ndarray, knn: np.ndarray, weights: np.ndarray, idx: np.ndarray, d2: np.ndarray,
                       field: WarpField, params: "AppendParams") -> tuple[np.ndarray, np.ndarray]:
    """_strains in numpy: the reference its compiled form is tested on."""
    n, sigma, h = len(x), field.sigma_m, _strain_step(field, params)

    # Live side: inverse warp x_ref = R^T (x - t) over the unpruned live neighbours.
    w0, _ = _gaussian(d2, sigma)
    xs, T = _perturbed_transforms(x, h, field.live_nodes()[idx], np.isfinite(d2), sigma,
                                  _signed_dqs(field, idx, w0))
    J_inv = _central_difference(np.einsum("snji,snj->sni", T[..., :3, :3], xs - T[..., :3, 3]), h)

    # Reference side: forward warp R x + t around the tentative reference position.
    x_ref, ref_idx = _reference_neighbours(x, knn, weights, idx.shape[1], field)
    ref_pos = field.nodes.astype(np.float64)[ref_idx]
    w0, _ = _gaussian(_sq_dist(x_ref[:, None, :], ref_pos), sigma)
    xs, T = _perturbed_transforms(x_ref, h, ref_pos, np.ones(ref_idx.shape, bool), sigma,
                                  _signed_dqs(field, ref_idx, w0))
    J_fwd = _central_difference(np.einsum("snij,snj->sni", T[..., :3, :3], xs) + T[..., :3, 3], h)

    smallest, largest = _singular_values(np.concatenate([J_inv, J_fwd]))
    with np.errstate(divide="ignore"):
        return largest[:n], 1.0 / smallest[n:]


def inverse_strains(live_points: np.ndarray, knn: np.ndarray, weights: np.ndarray, field: WarpField,
                    params: AppendParams = AppendParams()) -> tuple[np.ndarray, np.ndarray]:
    """Two estimates of the largest singular value of d x_ref / d x_live (Eq. 7), (A,) each,
    by central differences with step strain_step_m.

    live side: the inverse warp at the live point, blended over its k nearest live nodes before
        Eq. 6 with weights recomputed at each perturbed position.
    reference side: 1 / the smallest singular value of the forward warp's Jacobian at the
        candidate's tentative reference position (its inverse warp with knn/weights), the
        forward warp blending the k nearest reference nodes with recomputed weights.
    knn/weights: the candidates' skin_live output. See the module docstring for why both.
    """
    x = np.asarray(live_points, np.float64).reshape(-1, 3)
    if len(x) == 0:
        return np.zeros(0), np.zeros(0)
    knn = np.asarray(knn)
    return _strains(x, knn, weights, *_live_neighbours(x, field, knn.shape[1]), field, params)


def compressive_mask(live_points: np.ndarray, knn: np.ndarray, weights: np.ndarray, field: WarpField,
                     params: AppendParams = AppendParams()) -> np.ndarray:
    """(A,) bool Eq. 7: either strain estimate (inverse_strains) exceeds 1 + epsilon."""
    return _exceeds(*inverse_strains(live_points, knn, weights, field, params), params)


def _exceeds(live_side: np.ndarray, ref_side: np.ndarray, params: AppendParams) -> np.ndarray:
    return np.maximum(live_side, ref_side) > 1.0 + params.intrinsic_epsilon


def append_candidates(obs: CameraObservation, unmatched_pixel_mask: np.ndarray, T_camera_to_world: np.ndarray,
                      field: WarpField, k: int, params: AppendParams = AppendParams()) -> AppendResult:
    """Sec. VI-D: the unmatched valid depth surfels that pass delta_nn and Eq. 7, skinned live
    (Sec. VI-B) and inverse-warped to the reference frame with that skinning."""
    rows, cols = np.nonzero(np.asarray(unmatched_pixel_mask, bool) & obs.valid)
    T = np.asarray(T_camera_to_world, np.float64)
    R = T[:3, :3]
    position = obs.vertex_map[rows, cols].astype(np.float64) @ R.T + T[:3, 3]
    normal = obs.normal_map[rows, cols].astype(np.float64) @ R.T

    idx, d2 = _live_neighbours(position, field, k)
    knn, w, total = _prune(idx, d2, field, params)
    s = np.flatnonzero(total >= params.min_weight_sum)
    compressive = np.zeros(0, bool)
    if len(s):
        compressive = _exceeds(*_strains(position[s], knn[s], w[s], idx[s], d2[s], field, params), params)
    keep = s[~compressive]

    ref, ref_n = inverse_warp(position[keep], normal[keep], knn[keep], w[keep], field)
    f32 = np.float32
    return AppendResult(rows[keep], cols[keep], position[keep].astype(f32), normal[keep].astype(f32),
                        obs.radius_map[rows[keep], cols[keep]].astype(f32),
                        obs.confidence_map[rows[keep], cols[keep]].astype(f32),
                        knn[keep], w[keep], ref.astype(f32), ref_n.astype(f32),
                        candidates=len(rows), rejected_weight=int(len(rows) - len(s)),
                        rejected_compressive=int(compressive.sum()),
                        color=None if obs.color is None else obs.color[rows[keep], cols[keep]].astype(f32))
