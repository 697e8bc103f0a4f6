"""How still the points a map shows are: their skinning weights over their nodes' stillness (the
rest anchors': 1 at rest, 0 released), the weight rigid ICP gives each model pixel
(tracker.Tracker.stillness_map, rigid_weight_map)."""
from __future__ import annotations

import cv2
import numba
import numpy as np


def point_stillness(knn: np.ndarray, weights: np.ndarray, node: np.ndarray) -> np.ndarray:
    """(N,) float32 stillness of points skinned by knn/weights (N, k): their weights over the
    nodes' stillness `node` (M,) float32; nodes born since (index >= M) are still."""
    knn = np.asarray(knn)
    still = np.where(knn < len(node), node[np.minimum(knn, len(node) - 1)], 1.0)
    return np.einsum("nk,nk->n", np.asarray(weights, np.float32), still.astype(np.float32))


def stillness_map(index_map: np.ndarray, knn: np.ndarray, weights: np.ndarray, node: np.ndarray) -> np.ndarray:
    """(H, W) point_stillness of the points a map shows (`index_map`, -1: none, NaN), in one
    compiled pass for the usual four nodes a point (numpy gathered the shown rows and their
    nodes' stillness first: 20 -> ~5 ms a frame on tube-wall's 640x480 map)."""
    weights, node = np.ascontiguousarray(weights, np.float32), np.asarray(node, np.float32)
    if knn.shape[1] != 4:
        hit = index_map >= 0
        out = np.full(index_map.shape, np.nan, np.float32)
        shown = index_map[hit]
        # np.take: row gathers several times faster than fancy indexing.
        out[hit] = point_stillness(np.take(knn, shown, axis=0), np.take(weights, shown, axis=0), node)
        return out
    out = np.empty(index_map.shape, np.float32)
    _stillness_map(np.ascontiguousarray(index_map), np.ascontiguousarray(knn), weights, node, out)
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def _stillness_map(index, knn, weights, node, out):
    # each pixel alone, its rows on numba's threads
    for v in numba.prange(index.shape[0]):
        for u in range(index.shape[1]):
            i = index[v, u]
            if i < 0:
                out[v, u] = np.float32(np.nan)
                continue
            # einsum's order for four float32 terms
            out[v, u] = (_weighed(weights, knn, node, i, 0) + _weighed(weights, knn, node, i, 1)) + \
                (_weighed(weights, knn, node, i, 2) + _weighed(weights, knn, node, i, 3))


@numba.njit(cache=True, nogil=True, inline="always")
def _weighed(weights, knn, node, i, s):
    j = knn[i, s]
    return weights[i, s] * (node[j] if j < len(node) else np.float32(1.0))


def rigid_weight(stillness: np.ndarray, floor: float) -> np.ndarray:
    """A point's weight in rigid ICP by its stillness (0-1): a released point (0) keeps `floor`
    (released_rigid_weight); rigid_weight_map makes the same weights for a model map."""
    return floor + (1.0 - floor) * stillness


def rigid_weight_map(stillness: np.ndarray, floor: float) -> tuple[np.ndarray | None, float]:
    """(rigid ICP's (H, W) float32 weight of each model pixel, the still share): rigid_weight's,
    0 where the map is empty (NaN), and the mean stillness of the shown pixels; (None, 1.0)
    where every shown pixel is still. One compiled pass: numpy's nanmin,
    nanmean and weighted where took 1.1-1.5 ms of a 640x480 map in `touch` runs, this ~0.5."""
    s = np.ascontiguousarray(stillness, np.float32)
    out = np.empty(s.shape, np.float32)
    share, moving = _weight_map(s.reshape(-1), np.float32(floor), np.float32(1.0 - floor), out.reshape(-1))
    return (out, share) if moving else (None, 1.0)


@numba.njit(cache=True, nogil=True)
def _weight_map(s, floor, scale, out):
    """numpy's float32 arithmetic for each weight (floor + scale * s); the share summed in float64."""
    total, count, moving = 0.0, 0, False
    for p in range(len(s)):
        x = s[p]
        if np.isnan(x):
            out[p] = np.float32(0.0)
            continue
        out[p] = floor + scale * x
        total += x
        count += 1
        moving |= x < np.float32(1.0)
    return (total / count if count else 1.0), moving


COVER_CELL_PX = 8           # the share is counted on cells of this many pixels a side
COVER_REACH_PX = 24         # a pair covers the surface within this distance


def covered_share(weight: np.ndarray, pixels: np.ndarray) -> float:
    """The share of a model map's weight (H, W; 0 where empty) within COVER_REACH_PX of any of
    the pixels (n, 2) (x, y), counted on cells of COVER_CELL_PX pixels: how much of the still
    surface rigid ICP weighs colour pairs lie on."""
    cell = COVER_CELL_PX
    h, w = weight.shape
    padded = np.zeros((-(-h // cell) * cell, -(-w // cell) * cell), np.float32)
    padded[:h, :w] = weight
    # rows of cells, then columns: numpy's sum over axes (1, 3) at once took 0.7 ms of a 640x480
    # map, this 0.13
    rows = padded.reshape(padded.shape[0] // cell, cell, padded.shape[1]).sum(axis=1)
    cells = rows.reshape(rows.shape[0], rows.shape[1] // cell, cell).sum(axis=2)
    total = float(cells.sum())
    if total <= 0 or len(pixels) == 0:
        return 0.0
    at = np.floor(np.asarray(pixels, np.float64) / cell).astype(np.int64)
    inside = (at[:, 0] >= 0) & (at[:, 0] < cells.shape[1]) & (at[:, 1] >= 0) & (at[:, 1] < cells.shape[0])
    marked = np.zeros(cells.shape, np.uint8)
    marked[at[inside, 1], at[inside, 0]] = 1
    reach = COVER_REACH_PX // cell
    marked = cv2.dilate(marked, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1)))
    return float((cells * marked).sum()) / total
