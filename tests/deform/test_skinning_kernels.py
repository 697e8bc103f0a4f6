import numpy as np
import pytest

import surfelwarp.deform.warp_field as warp_field
from surfelwarp.deform.skinning_kernels import may_change, near_cells, occupancy
from surfelwarp.deform.warp_field import WarpField, WarpFieldParams, extend, skin, update_skinning


def _cloud(seed, n=20000, spread=1.0):
    rng = np.random.default_rng(seed)
    return (rng.random((n, 3)) * spread).astype(np.float32)


@pytest.mark.parametrize("cell_m", [0.002, 0.03, 0.08, 5.0])
def test_near_cells_keeps_every_point_a_new_node_may_change(cell_m):
    pts = _cloud(0)
    nodes = _cloud(1, 8000)
    knn, _ = skin(pts, nodes, 4, 0.05)
    knn[::97, 3] = knn[::97, 0]                    # padding slots
    new = np.concatenate([_cloud(2, 30, 0.3), _cloud(3, 30, 0.2) + 0.7])
    exact = may_change(pts, nodes, knn, new, None)
    grid, origin, side = occupancy(new, cell_m)
    kept = near_cells(pts, nodes, knn, grid, origin, side)
    assert exact.sum() > 100
    assert not np.any(exact & ~kept)               # a superset: nothing that may change is screened out
    if cell_m == 0.08:
        assert kept.mean() < 0.5                   # and a screen: most far points are not kept
        assert exact[knn[:, 3] == knn[:, 0]].all() and kept[knn[:, 3] == knn[:, 0]].all()


def test_near_cells_known_answer():
    nodes = np.array([[0.0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.01]], np.float32)
    knn = np.array([[0, 1, 2, 3]] * 3, np.int32)
    pts = np.array([[0.0, 0, 0], [0.3, 0, 0], [0.0, 0, 0.6]], np.float32)   # reach 1 cm, ~30 cm, ~60 cm
    new = np.array([[0.05, 0.0, 0.0]])
    grid, origin, side = occupancy(new, 0.03)
    assert side == pytest.approx(0.03)
    kept = near_cells(pts, nodes, knn, grid, origin, side)
    # The first: its cell is two cells from the new node's, its neighbours within 1 cm. The
    # others: their farthest neighbour is farther than a cell, so they are kept for the exact test.
    assert kept.tolist() == [False, True, True]
    grid, origin, side = occupancy(np.array([[0.005, 0.0, 0.0]]), 0.03)
    assert near_cells(pts[:1], nodes, knn[:1], grid, origin, side)[0]


def test_occupancy_grows_its_cells_for_strewn_nodes():
    for new in (np.array([[0.0, 0, 0], [100.0, 0, 0], [0, 50.0, 3.0]]), np.array([[0.0, 0, 0], [80.0, 80, 80], [40, 10, 70]])):
        grid, origin, side = occupancy(new, 0.01, max_cells=30000)
        assert grid.size <= 30000 and side > 0.01
        ijk = np.floor((new - origin) / side).astype(int)
        assert grid[tuple(ijk.T)].all()
        for axis in range(3):       # a cell's margin about the dilated cells
            assert not np.take(grid, 0, axis).any() and not np.take(grid, -1, axis).any()


@pytest.mark.parametrize("start", ["part", "padded"])
def test_update_skinning_by_cells_equals_by_all_new_nodes_to_the_bit(start, monkeypatch):
    s, t = np.meshgrid(np.arange(-0.3, 0.3, 0.004), np.arange(-0.22, 0.22, 0.004))
    pts = np.stack([s, t, 1.0 + 0.02 * np.sin(10 * s)], -1).reshape(-1, 3).astype(np.float32)
    params = WarpFieldParams()
    if start == "part":
        field = WarpField.from_points(pts[pts[:, 0] < 0.0], params)
    else:
        field = WarpField.from_points(pts[:40], params)
    knn, w = skin(pts, field.nodes, 4, field.sigma_m)
    new_field, first = extend(field, pts)
    assert new_field.num_nodes - first > warp_field._FEW_NEW_NODES
    by_cells = update_skinning(knn, w, pts, new_field, first)
    monkeypatch.setattr(warp_field, "_FEW_NEW_NODES", 10 ** 6)
    by_all = update_skinning(knn, w, pts, new_field, first)
    for a, b in zip(by_cells, by_all):
        assert np.array_equal(a, b)
    assert not np.array_equal(by_cells[0], knn)
