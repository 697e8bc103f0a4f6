"""DynamicFusion's deformation tree (deform/hierarchy.py), as the shared tracker uses it."""
import numpy as np
from pykdtree.kdtree import KDTree

from surfelwarp.deform.hierarchy import build_hierarchy, with_hierarchy
from surfelwarp.deform.warp_field import WarpField, skin, warp, warp_transforms_at
from surfelwarp.geometry.se3 import se3_exp
from surfelwarp.tracking.terms.regulariser import reg_residuals


def bent(nodes, curvature):
    """The identity field on `nodes` bent smoothly: a rotation about y growing with x."""
    xi = np.zeros((len(nodes), 6))
    xi[:, 1] = curvature * nodes[:, 0]
    xi[:, 5] = 0.1 * nodes[:, 0] ** 2
    return WarpField.identity(nodes).with_transforms(se3_exp(xi))


def test_hierarchy_links_each_level_to_its_nearest_coarser_nodes():
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.25, 0.25, (4000, 3)) * [1, 1, 0.2]
    nodes = WarpField.from_points(points).nodes
    eps, beta, k = 0.025, 2.0, 3
    tree = build_hierarchy(nodes, eps, levels=4, beta=beta, k=k)
    assert len(tree.levels) == 4 and np.array_equal(tree.levels[0], np.arange(len(nodes)))
    assert np.array_equal(tree.nodes[:len(nodes)], nodes)
    sizes = [len(level) for level in tree.levels]
    assert sizes == sorted(sizes, reverse=True) and sizes[-1] >= 1
    # Edges as (fine, coarse) pairs, read back from the graph rows (stored at the coarse end).
    j = np.repeat(np.arange(len(tree.nodes)), tree.graph.shape[1])
    i = tree.graph.reshape(-1)
    real = i != j
    edges = set(zip(i[real].tolist(), j[real].tolist()))
    for level in range(1, 4):
        coarse = tree.nodes[tree.levels[level]]
        gaps = np.linalg.norm(coarse[:, None] - coarse[None], axis=-1) + np.eye(len(coarse))
        assert gaps.min() >= eps * beta ** level * (1 - 1e-6)
        fine = tree.levels[level - 1]
        _, nearest = KDTree(coarse).query(tree.nodes[fine], k=min(k, len(coarse)))
        expected = {(int(f), int(tree.levels[level][c])) for f, row in zip(fine, nearest.reshape(len(fine), -1))
                    for c in row}
        assert expected <= edges
    assert len(edges) == sum(sizes[l] * min(k, sizes[l + 1]) for l in range(3))   # no sibling edges


def test_hierarchy_field_starts_at_the_current_warp():
    rng = np.random.default_rng(4)
    nodes = WarpField.from_points(rng.uniform(-0.2, 0.2, (3000, 3)) * [1, 1, 0.3]).nodes
    field = bent(nodes, 2.0)
    tree = build_hierarchy(nodes, 0.025, 4, 4.0, 4)
    full = with_hierarchy(field, tree)
    assert np.array_equal(full.transforms[:len(nodes)], field.transforms)
    extra = tree.nodes[len(nodes):]
    # Each regularisation node moves its own position where the warp field moves it.
    moved = full.live_nodes()[len(nodes):]
    knn, w = skin(extra, nodes, 4, field.sigma_m)
    expected, _ = warp(extra.astype(np.float64), None, knn, w, field)
    np.testing.assert_allclose(moved, expected, atol=1e-9)
    np.testing.assert_allclose(warp_transforms_at(field, nodes[:5])[:, :3, 3] + nodes[:5],
                               warp(nodes[:5].astype(np.float64), None, *skin(nodes[:5], nodes, 4, field.sigma_m),
                                    field)[0], atol=1e-9)


def rolled(nodes, radius_m):
    """The field that rolls the plane z = 0 onto a cylinder of radius_m about an axis parallel
    to y: each node turns by x / radius about y and moves to its place on the cylinder, so
    neighbours agree to second order in their distance (a smooth bend, not a tear)."""
    x, z = nodes[:, 0].astype(np.float64), nodes[:, 2].astype(np.float64)
    theta = x / radius_m
    c, s = np.cos(theta), np.sin(theta)
    T = np.tile(np.eye(4), (len(nodes), 1, 1))
    T[:, 0, 0], T[:, 0, 2], T[:, 2, 0], T[:, 2, 2] = c, -s, s, c      # tangent x -> (cos, 0, sin)
    T[:, 0, 3] = (radius_m - z) * s - x
    T[:, 2, 3] = radius_m - (radius_m - z) * c - z
    return WarpField.identity(nodes).with_transforms(T)


def test_a_smooth_bend_costs_more_through_the_tree():
    """The point of the tree: a bend spread over many nodes is nearly free for the k-nearest-node
    graph (each short edge barely stretches, second order in its length) but not for the long
    links to coarse nodes."""
    rng = np.random.default_rng(5)
    nodes = WarpField.from_points(rng.uniform(-0.4, 0.4, (20000, 3)) * [1, 1, 0]).nodes
    field = rolled(nodes, 1.0)
    graph = np.sum(reg_residuals(field) ** 2)
    tree = np.sum(reg_residuals(with_hierarchy(field, build_hierarchy(nodes, 0.025, 4, 4.0, 4))) ** 2)
    # The rolled plane really is a smooth isometric bend: per edge the graph residual is tiny.
    edges = np.count_nonzero(field.graph != np.arange(len(nodes))[:, None])
    assert np.sqrt(graph / edges) < 1e-3        # about curvature x length^2 / 2
    assert tree > 100 * graph


def test_keep_graph_adds_the_warp_nodes_edges_to_the_tree():
    """keep_graph: the regulariser is the k-nearest-node graph's among the warp nodes plus the
    tree's links, residual for residual."""
    rng = np.random.default_rng(6)
    nodes = WarpField.from_points(rng.uniform(-0.3, 0.3, (8000, 3)) * [1, 1, 0]).nodes
    field = rolled(nodes, 0.5)
    tree = build_hierarchy(nodes, 0.025, 4, 4.0, 4)
    both = with_hierarchy(field, tree, keep_graph=True)
    only_tree = with_hierarchy(field, tree)
    assert np.array_equal(both.transforms, only_tree.transforms)
    e_graph = np.sum(reg_residuals(field) ** 2)
    e_tree = np.sum(reg_residuals(only_tree) ** 2)
    e_both = np.sum(reg_residuals(both) ** 2)
    assert e_graph > 0 and e_tree > 0
    np.testing.assert_allclose(e_both, e_graph + e_tree, rtol=1e-9)
    m = len(nodes)
    np.testing.assert_array_equal(both.graph[:m, :field.graph.shape[1]], field.graph)
