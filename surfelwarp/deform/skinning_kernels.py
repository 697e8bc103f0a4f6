"""The compiled screens of warp_field.update_skinning: which points a new node may come nearer
than their farthest current neighbour. Most points of a large model are far from every new node;
only the few the screens keep have their skinning made again. And build_graph's last step."""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, inline="always")
def _reach(pts, nodes, knn, i):
    """Point i's squared distance to its farthest current neighbour (float32) and whether a
    padding slot repeats a node."""
    reach, padded = np.float32(0.0), False
    for s in range(knn.shape[1]):
        a = knn[i, s]
        d0, d1, d2 = nodes[a, 0] - pts[i, 0], nodes[a, 1] - pts[i, 1], nodes[a, 2] - pts[i, 2]
        reach = max(reach, d0 * d0 + d1 * d1 + d2 * d2)
        for t in range(s):
            if knn[i, t] == a:
                padded = True
    return reach, padded


@numba.njit(cache=True, nogil=True)
def may_change(pts, nodes, knn, new, nearest):
    """(N,) points whose skinning a new node may change: a padding slot (a node repeated), or
    a new node nearer than the farthest current neighbour (float32, with a margin). `nearest`:
    each point's squared distance to its nearest new node; None: found here among all of `new`."""
    n = len(knn)
    out = np.zeros(n, np.bool_)
    for i in range(n):
        reach, out[i] = _reach(pts, nodes, knn, i)
        if out[i]:
            continue
        if nearest is None:
            near = np.inf
            for j in range(len(new)):
                d0, d1, d2 = new[j, 0] - pts[i, 0], new[j, 1] - pts[i, 1], new[j, 2] - pts[i, 2]
                near = min(near, float(d0) * d0 + float(d1) * d1 + float(d2) * d2)
        else:
            near = nearest[i]
        out[i] = near < reach * (1 + 1e-4) + 1e-12
    return out


def occupancy(new: np.ndarray, cell_m: float, max_cells: int = 1 << 22) -> tuple[np.ndarray, np.ndarray, float]:
    """The cells within one of a cell holding a new node (a dense boolean grid, its origin and
    side), a cell's side at least cell_m and grown until the grid has at most max_cells (new
    nodes strewn over a large scene). The grid keeps a cell's margin about those cells: a point
    outside it is farther than a cell's side from every new node."""
    new = np.asarray(new, np.float64)
    lo, extent = new.min(axis=0), np.ptp(new, axis=0)
    cell_m = max(float(cell_m), float(np.max(extent)) / (max_cells ** (1 / 3) - 5), 1e-9)   # sides <= extent / cell + 5
    origin = lo - 2 * cell_m
    ijk = np.floor((new - origin) / cell_m).astype(np.int64)
    held = np.zeros(tuple(ijk.max(axis=0) + 3), np.bool_)
    held[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    for axis in range(3):       # dilated by a cell along each axis in turn: the 27 about each
        g = np.moveaxis(held, axis, 0)
        wide = g.copy()
        wide[1:] |= g[:-1]
        wide[:-1] |= g[1:]
        held = np.moveaxis(wide, 0, axis)
    return np.ascontiguousarray(held), origin, cell_m


@numba.njit(cache=True, nogil=True)
def near_cells(pts, nodes, knn, grid, origin, cell_m):
    """(N,) a superset of may_change's points: a padding slot, a farthest current neighbour
    about a cell away or farther, or a cell the grid (occupancy) marks as within one of a new
    node's: any new node within that neighbour's distance is in one of the 27 cells about the
    point's. The rest keep their skinning."""
    n = len(knn)
    gx, gy, gz = grid.shape
    limit = (cell_m * (1 - 1e-6)) ** 2
    out = np.zeros(n, np.bool_)
    for i in range(n):
        reach, out[i] = _reach(pts, nodes, knn, i)
        if out[i] or not reach * (1 + 1e-4) + 1e-12 < limit:
            out[i] = True
            continue
        x = int(np.floor((pts[i, 0] - origin[0]) / cell_m))
        y = int(np.floor((pts[i, 1] - origin[1]) / cell_m))
        z = int(np.floor((pts[i, 2] - origin[2]) / cell_m))
        if 0 <= x < gx and 0 <= y < gy and 0 <= z < gz:
            out[i] = grid[x, y, z]
    return out


@numba.njit(cache=True, nogil=True)
def neighbours_but_self(idx, k, out):
    """out[i] (k,): the first k entries of row i of idx that are not i, in their order, padded
    with i (build_graph's neighbours from a tree's query of every node; numpy's stable sort of
    the rows by "is the node itself" took ~4 of its 10 ms on 9k nodes)."""
    for i in range(idx.shape[0]):
        c = 0
        for j in range(idx.shape[1]):
            if c == k:
                break
            if idx[i, j] != i:
                out[i, c] = idx[i, j]
                c += 1
        for j in range(c, k):
            out[i, j] = i
