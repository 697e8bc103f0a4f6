"""DynamicFusion's hierarchical deformation tree (Newcombe et al. 2015, Sec. 3.3.2, 3.4).

Coarser levels of regularisation nodes sit above the warp nodes; each node links only to its k
nearest nodes of the next level (no links between siblings), so a smooth bend over many warp
nodes stretches the coarse links and costs far more than under the k-nearest-node graph, where
it is nearly free. The solver sees one field of all levels (with_hierarchy); only the warp nodes
(level 0) skin surfels, the others only regularise. With keep_graph the warp nodes also keep
SurfelWarp's k-nearest-node edges: local stiffness as with the graph alone, plus the tree's
resistance to the wide, smooth bends that let a static room drift.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

from surfelwarp.deform.warp_field import WarpField, sample_nodes, warp_transforms_at


@dataclass(frozen=True)
class HierarchyParams:
    enabled: bool = False    # regularise through the tree instead of the k-nearest-node graph
    levels: int = 4          # L, counting the warp nodes as level 0 (DynamicFusion Sec. 4)
    beta: float = 4.0        # level l is decimated at epsilon * beta^l, epsilon = node_radius_m
    k: int = 4               # links from each node to its k nearest of the next level
    keep_graph: bool = False # also keep the k-nearest-node graph among the warp nodes
                             # (SurfelWarp Eq. 10) beside the tree's links

    AT_MOST = {"levels": 8, "k": 16}


@dataclass(frozen=True)
class Hierarchy:
    """Regularisation nodes above the warp nodes: levels[l] = global indices of level l's nodes
    in `nodes` (level 0 = the warp nodes, first). Each node of level l links to its k nearest
    nodes of level l+1 (siblings are not linked); `graph` stores every link at its coarse end,
    as solve_nonrigid's graph expects: row j lists the finer nodes i linked to j, so the edge's
    residual is T_i p_j - T_j p_j, DynamicFusion Eq. 8 with j in E(i). Unused slots hold j."""
    nodes: np.ndarray       # (M_total, 3) float32
    graph: np.ndarray       # (M_total, max in-degree) int32
    levels: tuple[np.ndarray, ...]

    @property
    def num_warp_nodes(self) -> int:
        return len(self.levels[0])


def build_hierarchy(warp_nodes: np.ndarray, epsilon_m: float, levels: int, beta: float, k: int) -> Hierarchy:
    """DynamicFusion Sec. 3.4: level l subsamples level l-1 at radius epsilon * beta^l (stopping
    early once a level has a single node); each node links to its k nearest nodes of level l+1."""
    layers = [np.asarray(warp_nodes, np.float32).reshape(-1, 3)]
    for level in range(1, levels):
        if len(layers[-1]) <= 1:
            break
        layers.append(sample_nodes(layers[-1], epsilon_m * beta ** level))
    nodes = np.concatenate(layers)
    starts = np.cumsum([0] + [len(a) for a in layers])
    fine, coarse = [], []
    for level in range(len(layers) - 1):
        j = min(k, len(layers[level + 1]))
        _, idx = KDTree(layers[level + 1]).query(layers[level], k=j)
        fine.append(np.repeat(np.arange(starts[level], starts[level + 1]), j))
        coarse.append(idx.reshape(-1).astype(np.int64) + starts[level + 1])
    fine = np.concatenate(fine) if fine else np.zeros(0, np.int64)
    coarse = np.concatenate(coarse) if coarse else np.zeros(0, np.int64)
    # Links grouped by their coarse end; each gets a slot number within its group.
    order = np.argsort(coarse, kind="stable")
    fine, coarse = fine[order], coarse[order]
    degree = np.bincount(coarse, minlength=len(nodes))
    slot = np.arange(len(coarse)) - np.repeat(np.cumsum(degree) - degree, degree)
    graph = np.repeat(np.arange(len(nodes), dtype=np.int32)[:, None], max(int(degree.max(initial=0)), 1), axis=1)
    graph[coarse, slot] = fine
    return Hierarchy(nodes, graph, tuple(np.arange(starts[i], starts[i + 1]) for i in range(len(layers))))


def with_hierarchy(field: WarpField, tree: Hierarchy, keep_graph: bool = False) -> WarpField:
    """The warp field plus the regularisation nodes (transforms from the current warp) and the
    tree's edges: solve_nonrigid optimises them all, the data term only touches level 0. With
    keep_graph the warp nodes keep their k-nearest-node edges too."""
    extra = tree.nodes[tree.num_warp_nodes:]
    transforms = np.concatenate([field.transforms, warp_transforms_at(field, extra)]) if len(extra) \
        else field.transforms
    graph = tree.graph
    if keep_graph:
        # The tree stores its links at their coarse end, so the warp nodes' rows are free.
        m, k = field.graph.shape
        graph = np.repeat(np.arange(len(tree.nodes), dtype=np.int32)[:, None], max(k, tree.graph.shape[1]), axis=1)
        graph[m:, :tree.graph.shape[1]] = tree.graph[m:]
        graph[:m, :k] = field.graph
    return WarpField(tree.nodes, transforms, graph, field.params)
