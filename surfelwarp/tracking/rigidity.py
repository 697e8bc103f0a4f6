"""The local rigidity test of colour pairs: a pair whose distances to the nearby pairs change by
more than a small tolerance between the two frames is an outlier (a locally rigid consensus, in
place of a global RANSAC that a deforming scene would fail; features.py runs it on every set of
pairs)."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numba
import numpy as np
from pykdtree.kdtree import KDTree

if TYPE_CHECKING:
    from surfelwarp.tracking.features import FeatureParams


def locally_rigid(previous: np.ndarray, current: np.ndarray, params: FeatureParams) -> np.ndarray:
    """(n,) bool: matches whose distances to their neighbours (within rigidity_radius_m in the
    previous frame) mostly keep their length. Twice: the first pass's outliers no longer vote."""
    previous = np.ascontiguousarray(previous, np.float64)
    keep = np.ones(len(previous), bool)
    k = min(9, len(previous))
    if k < 2:
        return np.zeros(len(previous), bool)
    for _ in range(2):
        idx = np.flatnonzero(keep)
        if len(idx) < 2:
            return np.zeros(len(previous), bool)
        # Neighbours beyond the radius do not vote, so the search stops there (pykdtree: those
        # come back at an infinite distance). On a twist-limb frame's three calls (1.4k, 1.5k
        # and 4.1k matches) 26 -> 15 ms against scipy's unbounded search, the same matches.
        radius = params.rigidity_radius_m
        dist, nb = KDTree(previous[idx]).query(previous, k=min(k, len(idx)), distance_upper_bound=radius)
        keep = rigidity_votes(dist.reshape(len(previous), -1), nb.reshape(len(previous), -1).astype(np.int64), idx,
                              current, radius, params.rigidity_tolerance, params.rigidity_floor_m,
                              params.min_neighbours, params.min_agreement)
    return keep


@numba.njit(cache=True)
def rigidity_votes(dist, nb, idx, current, radius, tolerance, floor_m, min_neighbours, min_agreement):
    """(n,) bool: whether each pair's neighbours (`nb` into `idx`, at distances `dist` in the
    previous frame; pykdtree's answer within `radius`: inf and len(idx) beyond it) mostly keep
    their distance in `current`: at least min_neighbours of them other than itself, a share of
    at least min_agreement within max(tolerance * distance, floor_m) of it. The numpy expression
    it replaced, to the bit (tests), without its (n, k, 3) temporaries: a twist-limb frame's two
    passes over 4.2k flow pairs 10.6-11.6 -> 4.8-5.0 ms, the rest their neighbour searches."""
    n, k = dist.shape
    keep = np.zeros(n, np.bool_)
    for i in range(n):
        count = agreeing = 0
        for m in range(k):
            d, j = dist[i, m], idx[min(nb[i, m], len(idx) - 1)]
            if not (d < radius and j != i):         # inf beyond the radius: not a neighbour
                continue
            count += 1
            # ((x*x + y*y) + z*z): numpy's sum of the squares along the last axis, in its order
            x, y, z = current[i, 0] - current[j, 0], current[i, 1] - current[j, 1], current[i, 2] - current[j, 2]
            after = np.sqrt(x * x + y * y + z * z)
            if abs(after - d) <= max(tolerance * d, floor_m):
                agreeing += 1
        keep[i] = count >= min_neighbours and agreeing / max(count, 1) >= min_agreement
    return keep
