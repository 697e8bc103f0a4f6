"""Exact point-to-triangle-mesh queries: closest point, its triangle and barycentric coordinates.

Search points: the centroids of the triangles, or of a regular n x n subdivision of the
triangles larger than `sample_radius_m` (a coarse flat wall beside a fine tube), so that
every point of a triangle lies within r of one of its search points. Candidates are the
triangles of the k nearest search points (pykdtree). The answer is proven exact when the
k-th search point is farther than the best distance found plus r: no other triangle can
come closer. Points where that fails are asked again with 4x more candidates, up to all.

Closest point on one triangle a + s (b - a) + t (c - a): the plane projection if it falls
inside, else the nearest of the three clamped edge projections; everything follows from
d1 = (b - a).(p - a), d2 = (c - a).(p - a) and per-triangle constants.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree


def _triangle_constants(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> dict:
    ab, ac = b - a, c - a
    e, f, g = np.sum(ab * ab, -1), np.sum(ab * ac, -1), np.sum(ac * ac, -1)
    return {"a": a, "ab": ab, "ac": ac, "e": e, "f": f, "g": g, "det": e * g - f * f}


def _closest_st(d1, d2, e, f, g, det) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates (s, t) of the closest point, from the dot products; any matching shapes."""
    def div(num, den):
        return num / np.where(den > 0, den, 1.0)

    s_in, t_in = div(g * d1 - f * d2, det), div(e * d2 - f * d1, det)
    inside = (det > 1e-30 * (e * g + 1e-300)) & (s_in >= 0) & (t_in >= 0) & (s_in + t_in <= 1)
    u_ab = np.clip(div(d1, e), 0, 1)
    u_ac = np.clip(div(d2, g), 0, 1)
    u_bc = np.clip(div(d2 - d1 - f + e, g - 2 * f + e), 0, 1)
    s = np.stack([u_ab, np.zeros_like(u_ac), 1 - u_bc])
    t = np.stack([np.zeros_like(u_ab), u_ac, u_bc])
    # |w - s ab - t ac|^2 without the common |w|^2 term
    q = -2 * s * d1 - 2 * t * d2 + s * s * e + 2 * s * t * f + t * t * g
    best = np.argmin(q, axis=0)[None]
    s_edge, t_edge = np.take_along_axis(s, best, 0)[0], np.take_along_axis(t, best, 0)[0]
    return np.where(inside, s_in, s_edge), np.where(inside, t_in, t_edge)


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N, 3) of the point of triangle (a, b, c) closest to p; all (N, 3)."""
    k = _triangle_constants(a, b, c)
    w = p - a
    s, t = _closest_st(np.sum(k["ab"] * w, -1), np.sum(k["ac"] * w, -1), k["e"], k["f"], k["g"], k["det"])
    return np.stack([1 - s - t, s, t], -1)


def _subdivision_centroids(n: int) -> np.ndarray:
    """(s, t) of the centroids of the n*n congruent triangles of a regular subdivision."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    up = (i + j <= n - 1)
    down = (i + j <= n - 2)
    st = [np.stack([i[up] + 1 / 3, j[up] + 1 / 3], -1), np.stack([i[down] + 2 / 3, j[down] + 2 / 3], -1)]
    return np.vstack(st) / n


@dataclass(frozen=True)
class ClosestPoints:
    distance: np.ndarray      # (N,) metres
    face: np.ndarray          # (N,) triangle index
    bary: np.ndarray          # (N, 3) barycentric coordinates in that triangle
    point: np.ndarray         # (N, 3) closest point


class TriangleMesh:
    """A fixed triangle mesh answering exact closest-point queries."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, sample_radius_m: float = 0.004,
                 chunk: int = 131072):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        corners = self.vertices[self.faces]                           # (F, 3, 3)
        c = _triangle_constants(corners[:, 0], corners[:, 1], corners[:, 2])
        self.packed = np.concatenate([c["a"], c["ab"], c["ac"], np.stack([c["e"], c["f"], c["g"], c["det"]], -1)], 1)
        centroids = corners.mean(axis=1)
        radius = np.linalg.norm(corners - centroids[:, None], axis=-1).max(axis=1)
        levels = np.maximum(1, np.ceil(radius / sample_radius_m)).astype(np.int64)
        points, owner = [], []
        for n in np.unique(levels):
            sel = np.nonzero(levels == n)[0]
            st = _subdivision_centroids(int(n))
            points.append((corners[sel, :1] + st[None, :, :1] * c["ab"][sel, None] + st[None, :, 1:] * c["ac"][sel, None]
                           ).reshape(-1, 3))
            owner.append(np.repeat(sel, len(st)))
        self.search_points, self.search_face = np.vstack(points), np.concatenate(owner)
        # float32 tree: a fast search; its rounding (~1e-7 m) is covered by the 1e-6 margin
        self.radius = float(np.max(radius / levels)) + 1e-6
        self.tree = KDTree(self.search_points.astype(np.float32))
        self.chunk = chunk

    def _nearest_centroids(self, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Distances to the k nearest search points (ascending) and the triangles they belong to."""
        if k <= 512:
            dist, idx = self.tree.query(points.astype(np.float32), k=k)
            dist, idx = (dist[:, None], idx[:, None]) if k == 1 else (dist, idx)
            return dist.astype(np.float64), self.search_face[idx.astype(np.int64)]
        # Large k (far outliers): the tree's k-best lists get slow; select from all search points.
        c = self.search_points
        dist, idx = np.empty((len(points), k)), np.empty((len(points), k), np.int64)
        rows = max(1, 4_000_000 // len(c))
        for start in range(0, len(points), rows):
            p = points[start:start + rows]
            d2 = np.sum(p ** 2, 1)[:, None] - 2 * p @ c.T + np.sum(c ** 2, 1)[None]
            near = np.argpartition(d2, k - 1, axis=1)[:, :k] if k < len(c) else np.tile(np.arange(len(c)), (len(p), 1))
            part = np.take_along_axis(d2, near, 1)
            order = np.argsort(part, axis=1)
            dist[start:start + rows] = np.sqrt(np.maximum(np.take_along_axis(part, order, 1), 0))
            idx[start:start + rows] = np.take_along_axis(near, order, 1)
        return dist, self.search_face[idx]

    def _candidates(self, points: np.ndarray, k: int):
        dist, idx = self._nearest_centroids(points, k)
        g = self.packed[idx]                                          # one gather: (n, k, 13)
        a, ab, ac = g[..., 0:3], g[..., 3:6], g[..., 6:9]
        w = points[:, None, :] - a
        d1 = np.einsum("nkj,nkj->nk", ab, w)
        d2 = np.einsum("nkj,nkj->nk", ac, w)
        s, t = _closest_st(d1, d2, g[..., 9], g[..., 10], g[..., 11], g[..., 12])
        offset = w - s[..., None] * ab - t[..., None] * ac
        d = np.sqrt(np.einsum("nkj,nkj->nk", offset, offset))
        best = np.argmin(d, axis=1)[:, None]
        face = np.take_along_axis(idx, best, 1)[:, 0]
        s, t = np.take_along_axis(s, best, 1)[:, 0], np.take_along_axis(t, best, 1)[:, 0]
        dbest = np.take_along_axis(d, best, 1)[:, 0]
        exact = (dist[:, -1] >= dbest + self.radius) | (k >= len(self.search_points))
        rows = np.arange(len(points))
        point = points - offset[rows, best[:, 0]]
        return dbest, face, np.stack([1 - s - t, s, t], -1), point, exact

    def query(self, points: np.ndarray, k: int = 8) -> ClosestPoints:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n = len(points)
        distance, face = np.empty(n), np.empty(n, np.int64)
        bary, closest = np.empty((n, 3)), np.empty((n, 3))
        todo = np.arange(n)
        k = min(k, len(self.search_points))
        while len(todo):
            still = []
            step = max(1, self.chunk // k)
            for start in range(0, len(todo), step):
                sel = todo[start:start + step]
                d, f, b, c, exact = self._candidates(points[sel], k)
                distance[sel], face[sel], bary[sel], closest[sel] = d, f, b, c
                still.append(sel[~exact])
            todo = np.concatenate(still)
            k = min(4 * k, len(self.search_points))
        return ClosestPoints(distance, face, bary, closest)

    def interpolate(self, values: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Per-vertex `values` (V, C) at barycentric points of the given faces."""
        return np.einsum("ni,nic->nc", bary, np.asarray(values, dtype=np.float64)[self.faces[face]])
