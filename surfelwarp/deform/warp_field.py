"""The node-graph warp field (SurfelWarp Sec. III, VI; DynamicFusion Sec. 3.1, 3.4).

Convention (DynamicFusion's node-local form): node j sits at p_j in the reference frame and
holds a rigid transform L_j = [R_j, t_j] that moves a reference point x to

    x_live = R_j (x - p_j) + p_j + t_j,

so the identity means "no motion" and t_j is the displacement of the node itself. The same
motion written in world coordinates is G_j = Tr(p_j) L_j Tr(-p_j); the dense warp W(x) is the
dual quaternion blend of the G_j of the k nearest nodes (Eq. 1/2), and the inverse warp (Eq. 3)
inverts that blended transform. Live points are in the world frame.

Skinning weights are w = exp(-|x - p|^2 / (2 sigma^2)), stored normalised to sum 1 per point:
DQB normalises the blend anyway, and the normalisation keeps points far from every node from
underflowing to all-zero weights. Slots beyond the number of nodes (fewer than k nodes) repeat
the nearest node with weight 0.
"""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from surfelwarp.deform.skinning_kernels import may_change, near_cells, neighbours_but_self, occupancy
from surfelwarp.geometry.dq_kernels import blend_apply, dq_from_transforms
from surfelwarp.geometry.dual_quaternion import dq_blend_indexed, dq_to_transform
from surfelwarp.geometry.se3 import se3_exp

_CHUNK = 1 << 16   # points per warp batch: bounds the float64 copies of float32 inputs


@dataclass(frozen=True)
class WarpFieldParams:
    node_radius_m: float = 0.025      # node sampling spacing, SurfelWarp Table 1 / DynamicFusion epsilon
    sigma_m: float | None = None      # skinning weight radius; None: node_radius_m, so a point is
                                      # "covered" (DynamicFusion Sec. 3.4) within one node spacing
    k_skin: int = 4                   # nearest nodes blended per point
    graph_k: int = 8                  # regularisation neighbours per node

    AT_MOST = {"k_skin": 16, "graph_k": 64}

    @property
    def sigma(self) -> float:
        return self.node_radius_m if self.sigma_m is None else self.sigma_m


@dataclass(frozen=True, eq=False)
class WarpField:
    nodes: np.ndarray        # (M, 3) float32 reference positions p_j
    transforms: np.ndarray   # (M, 4, 4) float64 node-local L_j (see module docstring)
    graph: np.ndarray        # (M, graph_k) int32 neighbours; missing ones are the node itself
    params: WarpFieldParams = dc_field(default_factory=WarpFieldParams)

    @classmethod
    def identity(cls, nodes: np.ndarray, params: WarpFieldParams = WarpFieldParams()) -> "WarpField":
        nodes = np.asarray(nodes, np.float32).reshape(-1, 3)
        return cls(nodes, np.tile(np.eye(4), (len(nodes), 1, 1)), build_graph(nodes, params.graph_k), params)

    @classmethod
    def from_points(cls, points: np.ndarray, params: WarpFieldParams = WarpFieldParams()) -> "WarpField":
        """Nodes sub-sampled from reference points (SurfelWarp Sec. VI-E), identity transforms."""
        return cls.identity(sample_nodes(points, params.node_radius_m), params)

    @property
    def num_nodes(self) -> int:
        return len(self.nodes)

    @property
    def sigma_m(self) -> float:
        return self.params.sigma

    def with_transforms(self, transforms: np.ndarray) -> "WarpField":
        return WarpField(self.nodes, np.asarray(transforms, np.float64), self.graph, self.params)

    def global_transforms(self) -> np.ndarray:
        """(M, 4, 4) G_j = Tr(p_j) L_j Tr(-p_j): the node motions in world coordinates."""
        return to_global(self.transforms, self.nodes)

    def dual_quaternions(self) -> np.ndarray:
        """(M, 8) unit dual quaternions of the G_j, made once a field (read-only): a frame asks
        the same field for them several times (the solve's iterate and its Jacobian, the warp,
        the inverse warps of fusion and appending)."""
        dqs = self.__dict__.get("_dual_quaternions")
        if dqs is None:
            dqs = dq_from_transforms(self.global_transforms())
            dqs.flags.writeable = False
            object.__setattr__(self, "_dual_quaternions", dqs)   # frozen: set once, as a cache
        return dqs

    def __getstate__(self) -> dict:
        """A checkpoint's copy leaves the dual quaternions out: made again when asked."""
        return {k: v for k, v in self.__dict__.items() if k != "_dual_quaternions"}

    def live_nodes(self) -> np.ndarray:
        """(M, 3) node positions warped by their own transforms, p_j + t_j."""
        return self.nodes + self.transforms[:, :3, 3]


def to_global(local: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    p = np.asarray(nodes, np.float64)
    G = np.array(local, np.float64)
    G[..., :3, 3] += p - (G[..., :3, :3] @ p[..., None])[..., 0]
    return G


def to_local(G: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    p = np.asarray(nodes, np.float64)
    L = np.array(G, np.float64)
    L[..., :3, 3] += (L[..., :3, :3] @ p[..., None])[..., 0] - p
    return L


def _cell_representatives(points: np.ndarray, cell: float) -> np.ndarray:
    """Per occupied voxel of size `cell`, the index of the point nearest the voxel's centroid."""
    keys = np.floor(points / cell).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    _, group, counts = np.unique(flat, return_inverse=True, return_counts=True)
    centroid = np.stack([np.bincount(group, points[:, i]) for i in range(3)], -1) / counts[:, None]
    dist = np.sum((points - centroid[group]) ** 2, axis=1)
    order = np.lexsort((dist, group))
    first = np.ones(len(order), bool)
    first[1:] = group[order[1:]] != group[order[:-1]]
    return order[first]


def _thin(points: np.ndarray, radius: float) -> np.ndarray:
    """Indices of a maximal subset with pairwise distance >= radius (greedy in a fixed random
    priority order, computed in parallel rounds): every dropped point lies within radius of a
    kept one."""
    n = len(points)
    pairs = cKDTree(points).query_pairs(radius * (1 - 1e-9), output_type="ndarray")
    a, b = pairs[:, 0], pairs[:, 1]
    priority = np.random.default_rng(0).permutation(n)
    state = np.zeros(n, np.int8)       # 0 undecided, 1 kept, -1 dropped
    while np.any(state == 0):
        undecided = state == 0
        live = undecided[a] & undecided[b]
        la, lb = a[live], b[live]
        beaten = np.zeros(n, bool)
        b_wins = priority[lb] > priority[la]
        beaten[la[b_wins]] = True
        beaten[lb[~b_wins]] = True
        kept = undecided & ~beaten
        state[kept] = 1
        drop = np.concatenate([lb[kept[la]], la[kept[lb]]])
        state[drop] = -1
    return np.flatnonzero(state == 1)


def sample_nodes(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """(N, 3) points -> (M, 3) float32 nodes, a subset of the points, pairwise at least
    spacing_m apart and within spacing_m of every point.

    Voxel representatives at half the spacing are thinned to a maximal spaced subset; the few
    points that end up farther than spacing_m from every node are sampled again (their nodes
    are then farther than spacing_m from the earlier ones too).
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    nodes = np.zeros((0, 3))
    todo = pts
    while len(todo):
        cand = todo[_cell_representatives(todo, 0.5 * spacing_m)]
        nodes = np.concatenate([nodes, cand[_thin(cand, spacing_m)]])
        d, _ = KDTree(nodes).query(todo, k=1)
        todo = todo[d > spacing_m]
    return nodes.astype(np.float32)


def build_graph(nodes: np.ndarray, k: int) -> np.ndarray:
    """(M, k) int32 k nearest other nodes of every node; the node itself fills missing slots."""
    nodes = np.asarray(nodes, np.float32).reshape(-1, 3)
    m = len(nodes)
    if m == 0:
        return np.zeros((0, k), np.int32)
    _, idx = KDTree(nodes).query(nodes, k=min(k + 1, m))
    # Drop the node itself wherever the tree put it (ties may reorder), keep the first k others.
    out = np.empty((m, k), np.int32)
    neighbours_but_self(idx.reshape(m, -1).astype(np.int64), k, out)
    return out


def _finish(d2: np.ndarray, idx: np.ndarray, k: int, sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, k) int32 neighbours and normalised Gaussian weights from (N, j) squared distances
    sorted ascending (infinite: padding). Short rows are padded with the nearest node at weight 0."""
    n, j = idx.shape
    if j < k:
        d2 = np.concatenate([d2, np.full((n, k - j), np.inf)], 1)
        idx = np.concatenate([idx, np.repeat(idx[:, :1], k - j, 1)], 1)
    # Relative to the nearest node, so that points far from every node do not underflow.
    w = np.exp(-(d2 - d2[:, :1]) / (2.0 * sigma_m * sigma_m))
    w /= np.sum(w, axis=1, keepdims=True)
    return idx.astype(np.int32), w.astype(np.float32)


def skin(points: np.ndarray, nodes: np.ndarray, k: int, sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest nodes (N, k) int32, nearest first, and normalised weights (N, k) float32."""
    nodes = np.asarray(nodes, np.float32).reshape(-1, 3)
    if len(nodes) == 0:
        raise ValueError("skinning needs at least one node")
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    j = min(k, len(nodes))
    d, idx = KDTree(nodes).query(pts, k=j)
    d, idx = d.reshape(len(pts), j).astype(np.float64), idx.reshape(len(pts), j).astype(np.int64)
    return _finish(d * d, idx, k, sigma_m)


_FEW_NEW_NODES = 32     # up to this many new nodes the skinning screen tries them all
_SCREEN_CELL_RADII = 2.5    # the cells of the screen by new nodes' cells, in node radii: a
                            # point's farthest of 4 nodes is mostly within 2 radii


def _nearest_new(tree: KDTree, pts: np.ndarray) -> np.ndarray:
    """Squared distance of each point to its nearest new node (float64)."""
    nearest, _ = tree.query(pts, k=1)
    return nearest.reshape(-1).astype(np.float64) ** 2


def update_skinning(knn: np.ndarray, weights: np.ndarray, points: np.ndarray, field: WarpField,
                    first_new_node: int) -> tuple[np.ndarray, np.ndarray]:
    """Skinning after nodes first_new_node.. were appended (SurfelWarp Sec. VI-D): each point's
    current neighbours compete only with the nearest of the new nodes. Points that no new node
    comes nearer than their farthest current neighbour keep their skinning as it is (on a large
    model that is nearly all of them)."""
    new = field.nodes[first_new_node:]
    knn = np.asarray(knn).astype(np.int32)
    weights = np.asarray(weights, np.float32)
    if len(new) == 0:
        return knn, weights
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    k = knn.shape[1]
    tree = KDTree(new)
    # A float32 screen of the farthest current neighbour (with a margin over its rounding) picks
    # the few points a new node may come nearer; their distances are then taken in float64.
    # With few new nodes the screen tries them all; with more, the tree's nearest new node is
    # found only for the points whose cell neighbours a new node's (a room's 270k surfels and
    # ~90 new nodes: ~4 ms for the cells, ~2.5 for the tree on the 14 % they keep, instead of
    # 15-28 ms for the tree on every point).
    nodes32, new32 = np.asarray(field.nodes, np.float32), np.asarray(new, np.float32)
    if len(new) <= _FEW_NEW_NODES:
        rows, nearest = np.flatnonzero(may_change(pts, nodes32, knn, new32, None)), None
    else:
        grid, origin, cell_m = occupancy(new, _SCREEN_CELL_RADII * field.params.node_radius_m)
        near = np.flatnonzero(near_cells(pts, nodes32, knn, grid, origin, cell_m))
        nearest = _nearest_new(tree, pts[near])
        changes = may_change(pts[near], nodes32, knn[near], new32, nearest)
        rows, nearest = near[changes], nearest[changes]
    old = knn[rows].astype(np.int64)
    d2_old = np.sum((pts[rows, None, :].astype(np.float64) - field.nodes[old]) ** 2, axis=-1)
    # Padding slots repeat an earlier node: they must not be kept twice.
    for s in range(1, k):
        d2_old[:, s][np.any(old[:, :s] == old[:, s:s + 1], axis=1)] = np.inf
    reach = np.max(np.where(np.isfinite(d2_old), d2_old, -1.0), axis=1)
    full = np.isinf(d2_old).any(axis=1)            # a padding slot: any new node is nearer
    nearest = _nearest_new(tree, pts[rows]) if nearest is None else nearest
    sub = np.flatnonzero(full | (nearest < reach))
    hit, d2_old, old = rows[sub], d2_old[sub], old[sub]
    if len(hit) == 0:
        return knn, weights
    j = min(k, len(new))
    d, idx = tree.query(pts[hit], k=j)
    d2_new = d.reshape(len(hit), j).astype(np.float64) ** 2
    idx_new = idx.reshape(len(hit), j).astype(np.int64) + first_new_node
    d2 = np.concatenate([d2_old, d2_new], 1)
    idx = np.concatenate([old, idx_new], 1)
    order = np.argsort(d2, axis=1, kind="stable")[:, :k]
    d2, idx = np.take_along_axis(d2, order, 1), np.take_along_axis(idx, order, 1)
    # Replace infinite (padding) slots by the nearest node again, weight 0.
    idx = np.where(np.isfinite(d2), idx, idx[:, :1])
    weights = weights.copy()     # knn is a fresh copy (astype); weights may be the caller's
    knn[hit], weights[hit] = _finish(d2, idx, k, field.sigma_m)
    return knn, weights


def blend(knn: np.ndarray, weights: np.ndarray, field: WarpField) -> np.ndarray:
    """(N, 8) blended, unnormalised dual quaternions W(x) of skinned points."""
    return dq_blend_indexed(field.dual_quaternions(), knn, weights)[0]


def _out_dtype(a: np.ndarray):
    return a.dtype if np.issubdtype(a.dtype, np.floating) else np.float32


def warp(points: np.ndarray, normals: np.ndarray | None, knn: np.ndarray, weights: np.ndarray,
         field: WarpField) -> tuple[np.ndarray, np.ndarray | None]:
    """Reference points/normals -> live points/normals (SurfelWarp Eq. 2), in the points' dtype."""
    points = np.asarray(points)
    out_p, out_n = np.empty(points.shape, _out_dtype(points)), None
    if normals is not None:
        normals = np.asarray(normals)
        out_n = np.empty(normals.shape, _out_dtype(normals))
    dqs = field.dual_quaternions()
    for s in range(0, len(points), _CHUNK):
        part = slice(s, s + _CHUNK)
        _, _, p, n = blend_apply(dqs, knn[part], weights[part], points[part].T,
                                 None if normals is None else normals[part].T)
        out_p[part] = p.T
        if normals is not None:
            out_n[part] = n.T
    return out_p, out_n


def inverse_warp(live_points: np.ndarray, live_normals: np.ndarray | None, knn: np.ndarray,
                 weights: np.ndarray, field: WarpField) -> tuple[np.ndarray, np.ndarray | None]:
    """Live points/normals -> reference ones (SurfelWarp Eq. 3); knn/weights are those of the
    reference positions."""
    live_points = np.asarray(live_points)
    ref_p, ref_n = np.empty(live_points.shape, _out_dtype(live_points)), None
    if live_normals is not None:
        live_normals = np.asarray(live_normals)
        ref_n = np.empty(live_normals.shape, _out_dtype(live_normals))
    dqs = field.dual_quaternions()
    for s in range(0, len(live_points), _CHUNK):
        part = slice(s, s + _CHUNK)
        _, _, p, n = blend_apply(dqs, knn[part], weights[part], live_points[part].T,
                                 None if live_normals is None else live_normals[part].T, inverse=True)
        ref_p[part] = p.T
        if live_normals is not None:
            ref_n[part] = n.T
    return ref_p, ref_n


def warp_transforms_at(field: WarpField, points: np.ndarray) -> np.ndarray:
    """(n, 4, 4) node-local transforms at `points` equal to the current warp there (DQB)."""
    knn, w = skin(points, field.nodes, field.params.k_skin, field.sigma_m)
    return to_local(dq_to_transform(blend(knn, w, field)), points)


def extend(field: WarpField, new_ref_points: np.ndarray) -> tuple[WarpField, int]:
    """Add nodes for reference points farther than sigma from every node (DynamicFusion Sec. 3.4).

    The uncovered points are sub-sampled at the node spacing; each new node starts with the
    current warp at its position (DQB of the existing nodes). The graph is rebuilt. Returns the
    new field and the index of its first new node (== old node count; no new nodes: the same
    field).
    """
    pts = np.asarray(new_ref_points, np.float32).reshape(-1, 3)
    m = field.num_nodes
    if m == 0:
        return WarpField.from_points(pts, field.params), 0
    if len(pts) == 0:
        return field, m
    d, _ = KDTree(field.nodes).query(pts, k=1)
    uncovered = pts[d > field.sigma_m]
    if len(uncovered) == 0:
        return field, m
    new_nodes = sample_nodes(uncovered, field.params.node_radius_m)
    nodes = np.concatenate([field.nodes, new_nodes])
    transforms = np.concatenate([field.transforms, warp_transforms_at(field, new_nodes)])
    return WarpField(nodes, transforms, build_graph(nodes, field.params.graph_k), field.params), m


def apply_update(field: WarpField, xi: np.ndarray) -> WarpField:
    """L_j <- exp(xi_j) L_j for (M, 6) twists."""
    return field.with_transforms(se3_exp(np.asarray(xi, np.float64).reshape(-1, 6)) @ field.transforms)
